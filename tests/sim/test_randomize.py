"""Domain randomization (sim/randomize.py): every setting is drawn inside its declared range and
covers it, a draw is reproducible from (seed, index), overrides are checked against the
declaration (and the physics ranges), the post-render stages reuse the collimator and display
chain, and the docs table is the declaration's."""

from __future__ import annotations

import json
import math
import re
import tomllib

import numpy as np
import pytest

from sim.core.errors import InputError
from sim.physics.display import Collimator, DisplayChain
from sim.physics.settings import SETTINGS, PhysicsSettings
from sim.randomize import (DECLARATION, DomainRandomization, Draw, RandomizeError, apply_image, doc_table_rows,
                           image_rng, load_randomization)
from tests.conftest import REPO

N_DRAWS = 600
NUMERIC = ("uniform", "log-uniform")


@pytest.fixture(scope="module")
def draws() -> list[Draw]:
    dr = DomainRandomization()
    return [dr.draw(7, i) for i in range(N_DRAWS)]


def _rng(seed: int, *key: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(entropy=seed, spawn_key=key)))


# -- ranges and coverage ------------------------------------------------------------------------


@pytest.mark.parametrize("rec", DECLARATION, ids=lambda r: r.name)
def test_every_setting_is_drawn_inside_its_range_and_covers_it(rec, draws):
    values = [d[rec.name] for d in draws]
    if rec.dist in NUMERIC:
        v = np.array(values, float)
        assert v.min() >= rec.low and v.max() <= rec.high
        if rec.step is not None:  # every grid point low, low + step, ... appears, nothing else
            grid = np.round(rec.low + rec.step * np.arange(round((rec.high - rec.low) / rec.step) + 1), 9)
            assert sorted(set(v.tolist())) == grid.tolist()
        else:
            t = np.log(v) if rec.dist == "log-uniform" else v
            lo, hi = (math.log(rec.low), math.log(rec.high)) if rec.dist == "log-uniform" else (rec.low, rec.high)
            assert t.min() - lo < 0.02 * (hi - lo) and hi - t.max() < 0.02 * (hi - lo)
            # uniform in t: the mean is the middle (5 sigma of the mean of N uniforms)
            assert abs(t.mean() - (lo + hi) / 2) < 5 * (hi - lo) / math.sqrt(12 * N_DRAWS)
    elif rec.dist == "bernoulli":
        assert all(isinstance(x, bool) for x in values)
        if rec.p in (0.0, 1.0):  # a setting off (or on) by default: never drawn otherwise
            assert all(x == bool(rec.p) for x in values)
        else:
            assert abs(np.mean(values) - rec.p) < 5 * math.sqrt(rec.p * (1 - rec.p) / N_DRAWS)
    else:
        assert set(values) <= set(rec.choices)
        for c, q in zip(rec.choices, rec.probs):
            share = sum(x == c for x in values) / N_DRAWS
            if q == 0:  # a choice off by default (scatter "sks": opt-in): never drawn then
                assert share == 0, (c, share)
                continue
            assert share > 0 and abs(share - q) < 5 * math.sqrt(q * (1 - q) / N_DRAWS), (c, share, q)


def test_values_are_plain_python_and_the_record_lists_the_active_settings(draws):
    for d in draws[:50]:
        rec = d.to_dict()
        assert json.loads(json.dumps(rec)) == rec
        assert (rec["seed"], rec["index"]) == (7, d.index)
        shown = rec["values"]
        assert ("field_radius" in shown) == (d["field"] == "circle")
        assert ("field_rotation_deg" in shown) == (d["field"] == "rectangle")
        assert ("shutter" in shown) == (d["field"] != "none")
        assert ("grid_ratio" in shown) == d["grid"]
        assert ("scatter_spr" in shown) == (d["scatter"] == "kernel")
        assert ("scatter_scale" in shown) == (d["scatter"] == "monte-carlo")
        assert ("unsharp_amount" in shown) == d["unsharp"]
        assert "kvp" in shown and "bits" in shown
        assert all(type(v) in (float, int, bool, str) for v in d.values.values())
    assert len({d for d in draws}) == N_DRAWS  # hashable, all distinct


# -- reproducibility ----------------------------------------------------------------------------


def test_a_draw_is_the_literal_stream_of_seed_and_index_whatever_the_order():
    dr = DomainRandomization()
    for seed, index in ((0, 0), (3, 11), (2**40, 5)):
        u = _rng(seed, 50, index, 0).random(len(DECLARATION))
        d = dr.draw(seed, index)
        assert d.values == {r.name: r.value(float(x)) for r, x in zip(DECLARATION, u)}
        assert DomainRandomization().draw(seed, index) == d
    a = [dr.draw(1, i) for i in (5, 2, 9)]
    b = [dr.draw(1, i) for i in (9, 2, 5)][::-1]
    assert a == b
    assert dr.draw(1, 2) != dr.draw(1, 3) and dr.draw(1, 2) != dr.draw(2, 2)
    noise = image_rng(4, 6).random(8)
    assert np.array_equal(noise, _rng(4, 50, 6, 1).random(8))


def test_narrowing_one_range_changes_no_other_value():
    base = DomainRandomization()
    narrow = DomainRandomization.from_table({"kvp": [70, 80], "field": ["rectangle"]})
    for i in range(30):
        a, b = base.draw(3, i), narrow.draw(3, i)
        assert b["kvp"] in (70.0, 75.0, 80.0) and b["field"] == "rectangle"
        assert {k: v for k, v in a.values.items() if k not in ("kvp", "field")} == \
               {k: v for k, v in b.values.items() if k not in ("kvp", "field")}


@pytest.mark.parametrize("seed, index", [(-1, 0), (0, -1), (0, 1.5), (True, 0), (0, "3")])
def test_bad_seeds_and_indices_are_refused(seed, index):
    with pytest.raises(RandomizeError, match=r"^(seed|index) must be an integer >= 0"):
        DomainRandomization().draw(seed, index)


# -- overrides ----------------------------------------------------------------------------------


def test_overrides_set_the_distributions():
    dr = DomainRandomization.from_table({"kvp": 90, "mas": [1, 1], "grid": False, "log": True, "bits": {"8": 1},
                                         "cu_mm": {"0": 1, "0.3": 3}, "scatter": ["none", "kernel"],
                                         "gamma": [1.0, 1.0], "window_low": [2, 2]})
    ds = [dr.draw(0, i) for i in range(200)]
    assert {d["kvp"] for d in ds} == {90.0} and {d["mas"] for d in ds} == {1.0}
    assert not any(d["grid"] for d in ds) and all(d["log"] for d in ds)
    assert {d["bits"] for d in ds} == {8} and {d["scatter"] for d in ds} == {"none", "kernel"}
    assert {d["cu_mm"] for d in ds} == {0.0, 0.3}
    assert 0.6 < np.mean([d["cu_mm"] == 0.3 for d in ds]) < 0.9  # weights 1 : 3 normalised
    assert {d["gamma"] for d in ds} == {1.0} and {d["window_low"] for d in ds} == {2.0}
    assert DomainRandomization.from_table(dr.to_dict()) == dr
    assert DomainRandomization.from_table(DomainRandomization().to_dict()) == DomainRandomization()
    assert DomainRandomization.from_table(None) == DomainRandomization() == DomainRandomization.from_table({})


BAD = [
    ({"kv": [60, 100]}, r"unknown key\(s\) randomize\.kv; allowed: kvp, "),
    ({"kvp": [130, 70]}, r"randomize\.kvp: must be \[low, high\] with low <= high, got \[130, 70\]"),
    ({"kvp": [10, 100]}, r"randomize\.kvp: the range must lie in \[20, 150\] kV, got 10"),
    ({"kvp": [60, 151]}, r"randomize\.kvp: the range must lie in \[20, 150\] kV, got 151"),
    ({"kvp": "70"}, r"randomize\.kvp: must be \[low, high\] \(kV\) or one number, got '70'"),
    ({"kvp": [60, True]}, r"randomize\.kvp: must be \[low, high\]"),
    ({"kvp": [60, 80, 100]}, r"randomize\.kvp: must be \[low, high\]"),
    ({"kvp": [60, float("nan")]}, r"randomize\.kvp: must be \[low, high\]"),
    ({"mas": [0, 2]}, r"randomize\.mas: the range must lie in > 0 mAs, got 0"),
    ({"al_mm": [-1, 2]}, r"randomize\.al_mm: the range must lie in >= 0 mm, got -1"),
    ({"grid_ratio": [6, 60]}, r"randomize\.grid_ratio: the range must lie in \[0, 50\], got 60"),
    ({"blur_mm": [-0.1, 0.2]}, r"randomize\.blur_mm: the range must lie in >= 0 mm"),
    ({"grid": 1.5}, r"randomize\.grid: the probability of true must be a number in \[0, 1\], got 1\.5"),
    ({"grid": "yes"}, r"randomize\.grid: must be the probability of true"),
    ({"bits": [14]}, r"randomize\.bits: 14 is not a choice; allowed: 8, 10, 12, 16"),
    ({"bits": []}, r"randomize\.bits: must list at least one of 8, 10, 12, 16"),
    ({"bits": {"8": -1}}, r"randomize\.bits\.8: the weight must be a number >= 0, got -1"),
    ({"bits": {"8": 0}}, r"randomize\.bits: at least one weight must be > 0"),
    ({"bits": 12}, r"randomize\.bits: must be a list of choices or a table choice -> weight"),
    ({"field": ["circle", "circle"]}, r"randomize\.field: 'circle' is listed twice"),
    ({"field": ["oval"]}, r"randomize\.field: 'oval' is not a choice; allowed: none, circle, rectangle"),
    ({"cu_mm": {"0.15": 1}}, r"randomize\.cu_mm: '0\.15' is not a choice; allowed: 0, 0\.1, 0\.2"),
    ({"field_radius": [0, 0.5]}, r"randomize\.field_radius: the range must lie in \(0, 5\]"),
    ({"field_offset_x": [-0.6, 0]}, r"randomize\.field_offset_x: the range must lie in \[-0\.5, 0\.5\]"),
    ({"gamma": [0.5, 11]}, r"randomize\.gamma: the range must lie in \(0, 10\], got 11"),
    ({"window_low": [0, 96]}, r"randomize\.window_low's high end \(96 %\) must be below randomize\.window_high's"),
    ({"unsharp_sigma_px": [0, 2]}, r"randomize\.unsharp_sigma_px: the range must lie in \(0, 100\] px, got 0"),
    ({"electronic_noise_fraction": [1e-4, 2]}, r"randomize\.electronic_noise_fraction: the range must lie in "
                                               r"\(0, 1\]"),
]


@pytest.mark.parametrize("table, message", BAD, ids=[next(iter(t)) + "-" + str(i) for i, (t, _) in enumerate(BAD)])
def test_bad_overrides_are_refused_in_one_line(table, message):
    with pytest.raises(RandomizeError, match="^" + message) as e:
        DomainRandomization.from_table(table)
    assert isinstance(e.value, InputError) and "\n" not in str(e.value)


def test_a_table_that_is_not_a_mapping_and_a_wrong_settings_tuple_are_refused():
    with pytest.raises(RandomizeError, match=r"^randomize must be a table of setting = range, got list"):
        DomainRandomization.from_table([("kvp", 70)])
    with pytest.raises(RandomizeError, match=r"^DomainRandomization needs one setting per declared name"):
        DomainRandomization(DECLARATION[:-1])
    from dataclasses import replace

    steps = tuple(replace(r, step=1.0) if r.name == "kvp" else r for r in DECLARATION)
    with pytest.raises(RandomizeError, match=r"^randomize\.kvp: step is declared as 5\.0 and cannot change"):
        DomainRandomization(steps)


def test_load_randomization_reads_the_randomize_table(tmp_path):
    p = tmp_path / "train.toml"
    p.write_text('[train]\ndataset = "x"\n\n[randomize]\nkvp = [80, 90]\ngrid = false\n')
    dr = load_randomization(p)
    assert dr.by_name["kvp"].low == 80 and dr.by_name["grid"].p == 0.0
    (tmp_path / "none.toml").write_text('[train]\ndataset = "x"\n')
    assert load_randomization(tmp_path / "none.toml") == DomainRandomization()
    (tmp_path / "bad.toml").write_text("[randomize]\nkvp = [200, 210]\n")
    with pytest.raises(RandomizeError, match=r"bad\.toml: randomize\.kvp: the range must lie in \[20, 150\] kV"):
        load_randomization(tmp_path / "bad.toml")
    (tmp_path / "broken.toml").write_text("[randomize\n")
    with pytest.raises(RandomizeError, match=r"broken\.toml: not valid TOML"):
        load_randomization(tmp_path / "broken.toml")
    with pytest.raises(RandomizeError, match=r"not found"):
        load_randomization(tmp_path / "missing.toml")


# -- nesting inside the physics declaration -----------------------------------------------------


def _physics_value(rec, v):
    return [(rec.name[:2].capitalize(), v)] if SETTINGS[rec.physics].kind == "filters" else v


@pytest.mark.parametrize("rec", [r for r in DECLARATION if r.physics], ids=lambda r: r.name)
def test_physics_ranges_lie_inside_the_physics_declaration(rec):
    s = SETTINGS[rec.physics]
    ends = (rec.low, rec.high) if rec.dist in NUMERIC else [c for c, q in zip(rec.choices, rec.probs) if q > 0]
    for v in ends:
        s.check(_physics_value(rec, v))  # raises PhysicsError when outside
    if s.kind in ("float", "int") and s.low is not None and rec.dist in NUMERIC:
        below = s.low - 1e-6 if not s.low_open else s.low
        with pytest.raises(RandomizeError, match=f"randomize.{rec.name}"):
            DomainRandomization.from_table({rec.name: [below, rec.high]})
    if s.kind in ("float", "int") and s.high is not None and rec.dist in NUMERIC:
        DomainRandomization.from_table({rec.name: [rec.low, s.high]})  # the physics end itself is allowed
        with pytest.raises(RandomizeError, match=f"randomize.{rec.name}"):
            DomainRandomization.from_table({rec.name: [rec.low, s.high + 1e-6]})


def test_physics_settings_take_the_drawn_values(draws):
    base = PhysicsSettings(level="poly", bins=12, anode_angle_deg=10.0, noise=False, electronic_noise=3.0)
    seen = set()
    for d in draws[:60]:
        p = d.physics_settings(base)
        assert p.level == ("full" if d["scatter"] == "monte-carlo" else "poly")
        assert (p.kvp, p.mas, p.blur_mm) == (d["kvp"], d["mas"], d["blur_mm"]) and p.noise
        assert p.filters == ((("Al", d["al_mm"]), ("Cu", d["cu_mm"])) if d["cu_mm"] > 0 else (("Al", d["al_mm"]),))
        assert p.grid_ratio == (d["grid_ratio"] if d["grid"] else 0.0)
        assert (p.bins, p.anode_angle_deg, p.electronic_noise, p.seed) == (12, 10.0, 3.0, 0)
        seen.add(p.level)
    assert seen == {"poly", "full"}
    with pytest.raises(RandomizeError, match=r"^domain randomization needs physics level poly or full"):
        draws[0].physics_settings(PhysicsSettings(level="line"))
    with pytest.raises(RandomizeError, match=r"^physics_settings needs a PhysicsSettings, got dict"):
        draws[0].physics_settings({})


# -- post-render stages -------------------------------------------------------------------------


def _raw(h=40, w=48, i0=1000.0):
    r, c = np.mgrid[:h, :w]
    L = 0.2 + 1.5 * np.exp(-((r - h / 2) ** 2 + (c - w / 2) ** 2) / (2 * 6.0**2)) + 0.01 * c
    return i0 * np.exp(-L), i0


def test_collimator_and_display_chain_are_the_drawn_ones(draws):
    kinds = set()
    for d in draws[:80]:
        col = d.collimator(40, 48)
        kinds.add(d["field"])
        if d["field"] == "none":
            assert col is None
            continue
        center = (0.5 + d["field_offset_x"], 0.5 + d["field_offset_y"])
        if d["field"] == "circle" and d["field_blades"]:
            kinds.add("iris-blades")
            assert col == Collimator("iris-blades", center=center, radius=d["field_radius"],
                                     half_size=(5.0, d["field_blade_half"]), rotation_deg=d["field_blade_rotation_deg"],
                                     transmission=d["field_transmission"])
        elif d["field"] == "circle":
            assert col == Collimator("circle", center=center, radius=d["field_radius"],
                                     transmission=d["field_transmission"])
        else:
            assert col == Collimator("rectangle", center=center, half_size=(d["field_half_width"],
                                                                             d["field_half_height"]),
                                     rotation_deg=d["field_rotation_deg"], transmission=d["field_transmission"])
        chain = d.display_chain()
        assert chain == DisplayChain(log=d["log"], polarity=d["polarity"], window=(d["window_low"], d["window_high"]),
                                     gamma=d["gamma"], unsharp_sigma_px=d["unsharp_sigma_px"] if d["unsharp"] else 0.0,
                                     unsharp_amount=d["unsharp_amount"] if d["unsharp"] else 0.0, bits=d["bits"],
                                     shutter=d["shutter"])
    assert kinds == {"none", "circle", "rectangle", "iris-blades"}
    tiny = DomainRandomization.from_table({"field": ["circle"], "field_radius": [1e-4, 1e-4],
                                           "field_offset_x": 0, "field_offset_y": 0}).draw(0, 0)
    with pytest.raises(RandomizeError, match=r"^draw 0: the circle field holds no pixel of a 8 x 8 image"):
        tiny.collimator(8, 8)


def test_apply_image_gives_the_drawn_field_and_bit_depth(draws):
    raw, i0 = _raw()
    for d in draws[:40]:
        if d["scatter"] == "monte-carlo":
            continue
        img, mask = apply_image(raw, i0, d, image_rng(7, d.index))
        col = d.collimator(*raw.shape)
        assert img.dtype == np.uint16 and img.shape == raw.shape and mask.dtype == bool
        assert np.array_equal(mask, np.ones(raw.shape, bool) if col is None else col.mask(*raw.shape))
        top = (1 << d["bits"]) - 1
        assert img.max() == top and img[mask].min() == 0  # the window spans the full range in the field
        if col is not None and d["shutter"] != "none":
            assert np.all(img[~mask] == (0 if d["shutter"] == "black" else top))
    for bits in (8, 10, 12, 16):
        d = DomainRandomization.from_table({"bits": [bits], "scatter": ["none"]}).draw(1, 3)
        img, _ = apply_image(raw, i0, d, image_rng(1, 3))
        assert img.max() == (1 << bits) - 1


def test_apply_image_is_collimation_then_noise_then_the_display_chain():
    """Without scatter: the collimator's signal plus electronic noise from the same stream, through the
    drawn display chain; polarity: with log and bone-dark, the dense centre is dark."""
    raw, i0 = _raw()
    dr = DomainRandomization.from_table({"scatter": ["none"], "field": ["circle"], "log": True,
                                         "polarity": ["bone-dark"], "shutter": ["black"]})
    d = dr.draw(2, 4)
    img, mask = apply_image(raw, i0, d, image_rng(2, 4))
    col = d.collimator(*raw.shape)
    noise = image_rng(2, 4).normal(0.0, d["electronic_noise_fraction"] * i0, raw.shape)
    expect = d.display_chain().apply(col.apply(raw) + noise, i0, col.mask(*raw.shape))
    assert np.array_equal(img, expect)
    assert img[20, 24] < np.median(img[mask])  # bone-dark: the attenuating blob is dark


def test_scatter_stages():
    raw, i0 = _raw()
    kernel = DomainRandomization.from_table({"scatter": ["kernel"], "field": ["none"], "log": False,
                                             "scatter_spr": [1.0, 1.0], "electronic_noise_fraction": 1e-9,
                                             "window_low": 0, "window_high": 100, "gamma": 1, "unsharp": False,
                                             "bits": [16], "polarity": ["bone-bright"]})
    import torch
    from scipy.ndimage import gaussian_filter

    from sim.physics.chain import gaussian_reflect

    def _kernel_scatter(x, sigma):  # the chain's Gaussian with mirrored edges, of one image
        return gaussian_reflect(torch.from_numpy(np.asarray(x, np.float64))[None], float(sigma))[0].numpy()

    d = kernel.draw(0, 0)
    img, _ = apply_image(raw, i0, d, image_rng(0, 0))  # raw + spr G(raw), then noise, then the chain
    noise = image_rng(0, 0).normal(0.0, 1e-9 * i0, raw.shape)
    sigma_px = d["scatter_sigma"] * min(raw.shape)
    assert np.array_equal(img, d.display_chain().apply(raw + _kernel_scatter(raw, sigma_px) + noise, i0))
    assert np.allclose(_kernel_scatter(np.full((32, 32), 500.0), 6.0), 500.0)  # G(c) = c
    x = np.random.default_rng(0).random((64, 80)) + np.linspace(0.0, 3.0, 80)[None, :]
    x[30, 41], x[5, 3] = 10.0, 20.0  # spikes in the middle and near an edge (mirrored as scipy's "reflect")
    for sigma in (3.0, 20.0, 200.0):
        truth = gaussian_filter(x, sigma, mode="reflect", truncate=12.0)
        assert np.abs(_kernel_scatter(x, sigma) - truth).max() < 1e-9 * truth.mean()
    mc = DomainRandomization.from_table({"scatter": ["monte-carlo"], "scatter_scale": [2.0, 2.0],
                                         "field": ["none"]}).draw(0, 1)
    with pytest.raises(RandomizeError, match=r"^apply_image: the draw's scatter is monte-carlo: pass the render's"):
        apply_image(raw, i0, mc, image_rng(0, 1))
    sc = np.full(raw.shape, 5.0)
    got, _ = apply_image(raw, i0, mc, image_rng(0, 1), scatter=sc)
    assert np.array_equal(got, apply_image(raw + sc, i0, replace_scatter_scale(mc, 1.0), image_rng(0, 1),
                                           scatter=sc)[0])
    with pytest.raises(RandomizeError, match=r"^apply_image: a scatter image was given but the draw's scatter is "
                                             r"'kernel'"):
        apply_image(raw, i0, kernel.draw(0, 0), image_rng(0, 0), scatter=sc)


def replace_scatter_scale(d: Draw, scale: float) -> Draw:
    return Draw(d.seed, d.index, tuple((k, scale if k == "scatter_scale" else v) for k, v in d.items))


@pytest.mark.parametrize("args, message", [
    ((np.ones((2, 4, 4)), 1.0), r"apply_image needs a real \(H, W\) raw signal, got shape \(2, 4, 4\)"),
    ((np.full((4, 4), np.nan), 1.0), r"apply_image: the raw signal must be finite"),
    ((np.ones((4, 4)), 0.0), r"apply_image: i0 \(the flat-field signal\) must be a finite number > 0, got 0\.0"),
    ((np.ones((4, 4)), float("inf")), r"apply_image: i0"),
])
def test_apply_image_refuses_bad_inputs_in_one_line(args, message, draws):
    with pytest.raises(RandomizeError, match="^" + message):
        apply_image(*args, draws[0], image_rng(0, 0))
    with pytest.raises(RandomizeError, match=r"^apply_image needs a Draw"):
        apply_image(np.ones((4, 4)), 1.0, draws[0].to_dict(), image_rng(0, 0))
    with pytest.raises(RandomizeError, match=r"^apply_image needs a numpy Generator"):
        apply_image(np.ones((4, 4)), 1.0, draws[0], 0)


# -- declaration and docs -----------------------------------------------------------------------


def test_the_declaration_is_consistent():
    names = [r.name for r in DECLARATION]
    assert len(set(names)) == len(names)
    for r in DECLARATION:
        if r.when is not None:
            assert names.index(r.when[0]) < names.index(r.name)
            assert set(r.when[1]) <= set(next(x for x in DECLARATION if x.name == r.when[0]).choices or (True, False))
        if r.dist == "choice":
            assert len(r.probs) == len(r.choices) and math.isclose(sum(r.probs), 1.0)
    required = {"kvp", "al_mm", "cu_mm", "mas", "grid", "grid_ratio", "blur_mm", "electronic_noise_fraction",
                "scatter", "field", "field_radius", "field_half_width", "field_half_height", "field_offset_x",
                "field_offset_y", "field_rotation_deg", "field_transmission", "shutter", "log", "polarity",
                "window_low", "window_high", "gamma", "unsharp_sigma_px", "unsharp_amount", "bits"}
    assert required <= set(names)
    kvp = next(r for r in DECLARATION if r.name == "kvp")
    assert 55 <= kvp.low <= 65 and 125 <= kvp.high <= 135
    assert set(next(r for r in DECLARATION if r.name == "bits").choices) == {8, 10, 12, 16}


def test_the_docs_table_is_the_declaration():
    text = (REPO / "docs" / "domain_randomization.md").read_text()
    rows = doc_table_rows()
    for row in rows:
        assert row in text, row
    documented = re.findall(r"^\| `(\w+)` \|", text, flags=re.M)
    assert documented == [r.name for s in ("physics", "signal", "collimator", "display")
                          for r in DECLARATION if r.stage == s]
    example = re.search(r"```toml\n(.*?)```", text, flags=re.S).group(1)
    dr = DomainRandomization.from_table(tomllib.loads(example)["randomize"])
    assert dr.by_name["kvp"].low == 70 and dr.by_name["bits"].probs == (0.25, 0.0, 0.75, 0.0)


def test_the_tool_bank_is_reproducible_and_picks_by_the_draw():
    from sim.projection.geometry import CArmGeometry
    from sim.randomize import TOOL_BANK_SIZE, ToolBank

    geom = CArmGeometry(sdd_mm=1020.0, sod_mm=700.0, height=24, width=24, pixel_spacing_mm=12.0)
    bank, again = ToolBank(4, geom), ToolBank(4, geom)
    r = DomainRandomization.from_table({"tools": True})
    for index in range(3):
        d = r.draw(4, index)
        c1, ch1 = bank.for_draw(d)
        c2, ch2 = again.for_draw(d)
        np.testing.assert_array_equal(c1, c2)
        assert ch1 == ch2 and c1.shape == (len(ch1), 24, 24) and c1.max() > 0
    assert bank.for_draw(DomainRandomization.from_table({"tools": False}).draw(4, 0)) is None
    # pick 0 is arrangement 0 as traced; the flips and transposes keep its values
    c0, _ = bank.for_draw(DomainRandomization.from_table({"tools": True, "tools_pick": 0.0}).draw(4, 0))
    np.testing.assert_array_equal(c0, bank.arrangement(0)[0])
    c7, _ = bank.for_draw(DomainRandomization.from_table({"tools": True, "tools_pick": 7.5 / (8 * TOOL_BANK_SIZE)})
                          .draw(4, 0))
    np.testing.assert_array_equal(c7, bank.arrangement(0)[0][:, ::-1, ::-1].transpose(0, 2, 1))
    with pytest.raises(RandomizeError, match="arrangement must be <"):
        bank.arrangement(TOOL_BANK_SIZE)
