"""Realistic randomized targets for training (learn.online.RealisticTargets) and their preparation
as registration prepares a user's X-ray (learn.online.prepare_like_registration)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from learn.online import (MAX_BATCH, OnlinePairs, OnlinePairsError, RealisticTargets, check_trainable,
                          prepare_like_registration)
from sim.randomize import DomainRandomization

ROOT = Path(__file__).resolve().parents[2]
TRAINABLE = DomainRandomization.from_table({"scatter": ["none", "kernel"]})


def _line_image(h=48, w=64):
    """A smooth line-integral image (mm^-1 x mm): a 'body' ellipse with a brighter 'bone' inside."""
    yy, xx = np.mgrid[0:h, 0:w]
    body = np.clip(1 - ((xx - 30) / 28.0) ** 2 - ((yy - 24) / 20.0) ** 2, 0, None) ** 0.5 * 4.0
    bone = np.exp(-(((xx - 36) / 5.0) ** 2 + ((yy - 20) / 8.0) ** 2)) * 1.5
    return body + bone


@pytest.mark.parametrize("log_display, bone_dark, raw", [(True, False, False), (True, True, False),
                                                          (False, False, False), (False, True, False),
                                                          (False, True, True), (False, False, True)])
def test_every_display_comes_back_bone_bright(log_display, bone_dark, raw):
    # a display of the line image L: log -> L, linear -> exp(-L) (bone dark), each inverted where the
    # polarity asks. Log displays and raw intensity (log-corrected) come back as an affine map of L;
    # a windowed linear display, as registration leaves it, comes back bone bright and monotone in L.
    from scipy.stats import spearmanr

    L = _line_image()
    shown = L if log_display else np.exp(-L)
    if log_display == bone_dark:
        shown = shown.max() + shown.min() - shown
    display = np.round(shown / shown.max() * 4095).astype(np.uint16)
    field = np.ones(L.shape, bool)
    target, current = prepare_like_registration(display, field, L, log_display=log_display, bone_dark=bone_dark,
                                                raw_intensity=raw)
    assert target.dtype == np.float32 and target.shape == L.shape
    assert 0.0 <= target.min() and target.max() <= 1.0
    np.testing.assert_array_equal(current, L.astype(np.float32))  # an open field leaves the current alone
    inside = L > 0.5  # the body: where the normalisation's clipping leaves the order intact
    assert spearmanr(target[inside], L[inside])[0] > 0.97  # bone bright: the same order as L
    if log_display or raw:
        assert np.corrcoef(target.ravel(), L.ravel())[0, 1] > 0.97


@pytest.mark.parametrize("log_display, bone_dark", [(True, True), (False, False), (False, True)])
def test_a_toned_target_is_affine_in_its_line_integrals(log_display, bone_dark):
    """With ``tone`` a display of any curve (here linear displays of ``exp(-L)`` and a gamma 2.6
    log display) comes back linear in L when the current image is the same view: correlation
    > 0.99 where untoned linear displays stay below 0.97. A raw image is log-corrected, never
    toned."""
    L = _line_image()
    shown = (L / L.max()) ** 2.6 if log_display else np.exp(-L)
    if log_display == bone_dark:
        shown = shown.max() + shown.min() - shown
    display = np.round(shown / shown.max() * 4095).astype(np.uint16)
    field = np.ones(L.shape, bool)
    kw = dict(log_display=log_display, bone_dark=bone_dark)
    toned, _ = prepare_like_registration(display, field, L, tone=True, **kw)
    plain, _ = prepare_like_registration(display, field, L, **kw)
    inside = L > 0.2
    assert np.corrcoef(toned[inside], L[inside])[0, 1] > 0.99
    assert np.corrcoef(plain[inside], L[inside])[0, 1] < 0.97
    if not log_display:
        raw, _ = prepare_like_registration(display, field, L, raw_intensity=True, tone=True, **kw)
        raw0, _ = prepare_like_registration(display, field, L, raw_intensity=True, **kw)
        np.testing.assert_array_equal(raw, raw0)


def test_a_collimated_pair_is_cropped_to_the_field_and_filled_neutrally():
    L = _line_image(64, 64)
    field = np.zeros((64, 64), bool)
    field[10:42, 20:52] = True  # the field's bounding box: 32 x 32 at (10, 20)
    display = np.where(field, np.round(L / L.max() * 4095), 0).astype(np.uint16)
    target, current = prepare_like_registration(display, field, L, log_display=True, bone_dark=False)
    # the crop fills the whole image: no filled pixel left, and the current shows the same window
    ref = L[10:42, 20:52]
    assert np.corrcoef(current[::2, ::2].ravel(), ref.ravel())[0, 1] > 0.99
    assert np.corrcoef(target[::2, ::2].ravel(), ref.ravel())[0, 1] > 0.97
    # a round field: outside pixels take the field's mean in both images
    yy, xx = np.mgrid[0:64, 0:64]
    disc = (yy - 32) ** 2 + (xx - 32) ** 2 < 20 ** 2
    t, c = prepare_like_registration(np.where(disc, display.max(), 0).astype(np.uint16) + disc, disc, L,
                                     log_display=True, bone_dark=False)
    corner = (slice(0, 2), slice(0, 2))
    assert np.allclose(c[corner], c[corner][0, 0]) and np.allclose(t[corner], t[corner][0, 0])


def test_an_empty_field_is_refused():
    with pytest.raises(OnlinePairsError, match="field holds no pixel"):
        prepare_like_registration(np.ones((8, 8), np.uint16), np.zeros((8, 8), bool), np.ones((8, 8)),
                                  log_display=True, bone_dark=False)


def test_monte_carlo_scatter_cannot_be_trained_per_pair():
    with pytest.raises(OnlinePairsError, match="randomize.scatter: online training cannot run a Monte Carlo"):
        check_trainable(DomainRandomization())  # the declaration allows monte-carlo
    check_trainable(TRAINABLE)
    with pytest.raises(OnlinePairsError, match="must be a DomainRandomization"):
        check_trainable({"scatter": ["none"]})


@pytest.fixture(scope="module")
def realistic_pairs():
    from sim.campaign.config import load_campaign

    cfg = load_campaign(ROOT / "campaigns" / "smoke.toml")
    return cfg, OnlinePairs(cfg, "train", seed=3, randomization=TRAINABLE, subjects_per_batch=1)


def test_realistic_batches_are_reproducible_ready_and_varied(realistic_pairs):
    cfg, pairs = realistic_pairs
    a1, b1, y1 = pairs.batch(5, 6)
    a2, b2, y2 = pairs.batch(5, 6)  # a batch is a function of (seed, k): the same images again
    for u, v in ((a1, a2), (b1, b2), (y1, y2)):
        np.testing.assert_array_equal(u.numpy(), v.numpy())
    assert a1.shape == b1.shape == (6, 1, *cfg.scene.size)
    assert float(a1.min()) >= 0.0 and float(a1.max()) <= 1.0  # normalised as registration does
    a3 = pairs.batch(6, 6)[0]
    assert not np.array_equal(a1.numpy(), a3.numpy())
    # every pair's draw is its own: pair i of batch k is index k * MAX_BATCH + i
    draws = [TRAINABLE.draw(3, 5 * MAX_BATCH + i) for i in range(6)]
    assert len({d["kvp"] for d in draws} | {d["field"] for d in draws}) > 2


def test_realistic_target_physics_tracks_the_draw(realistic_pairs):
    # the same density integrals at 60 and 130 kV: the harder beam passes more (a higher mean signal
    # over I0), and tools, where drawn, add attenuation (a darker raw signal somewhere)
    from sim.randomize import DomainRandomization as DR

    cfg, pairs = realistic_pairs
    L = pairs.density_renderer(0).render(np.eye(4)[None])[0]
    common = {"scatter": ["none"], "field": ["none"], "log": False, "polarity": ["bone-dark"], "window_low": 0,
              "window_high": 100, "gamma": 1.0, "unsharp": False, "bits": [16], "mas": 8.0, "tools": False}
    for kvp in (60, 130):
        rt = RealisticTargets(DR.from_table({**common, "kvp": kvp}), 0, pairs.realistic.geometry)
        display, field, draw = rt.image(L, 0)
        assert draw["kvp"] == kvp and field.all() and display.dtype == np.uint16
    # a linear display windowed over [0, 100] % shows I / I0 rescaled: compare transmissions via the raw model
    rt60 = RealisticTargets(DR.from_table({**common, "kvp": 60}), 0, pairs.realistic.geometry)
    rt130 = RealisticTargets(DR.from_table({**common, "kvp": 130}), 0, pairs.realistic.geometry)
    phys = [r.randomization.draw(0, 0).physics_settings(r.base) for r in (rt60, rt130)]
    dens = np.zeros((1, len(rt60.names), *L.shape[1:]))
    dens[0, :L.shape[0]] = L
    t = [float(np.median(r._model(p).expected(dens, mas=1.0, sdd_mm=1000.0, pixel_area_mm2=1.0)
                          / r._model(p).flat_field(mas=1.0, sdd_mm=1000.0, pixel_area_mm2=1.0)))
         for r, p in zip((rt60, rt130), phys)]
    assert t[1] > t[0]
    with_tools = RealisticTargets(DR.from_table({**common, "kvp": 90, "tools": True, "tools_pick": 0.0}), 0,
                                  pairs.realistic.geometry)
    chords, channels = with_tools.bank.for_draw(with_tools.randomization.draw(0, 0))
    assert chords.max() > 0 and {m for m, _ in channels} <= set(with_tools.names)


def test_train_config_checks_the_randomize_table(tmp_path):
    from learn.train import TrainConfig, TrainConfigError

    campaign = str(ROOT / "campaigns" / "smoke.toml")
    TrainConfig(dataset=campaign, randomize={"scatter": ["none", "kernel"]})
    with pytest.raises(TrainConfigError, match=r"train\.randomize\.scatter: online training cannot"):
        TrainConfig(dataset=campaign, randomize={})
    with pytest.raises(TrainConfigError, match=r"train\.randomize\.kvp"):
        TrainConfig(dataset=campaign, randomize={"scatter": ["none"], "kvp": [130, 70]})
    with pytest.raises(TrainConfigError, match="needs pairs rendered on the fly"):
        TrainConfig(dataset=str(tmp_path), randomize={"scatter": ["none"]})
    with pytest.raises(TrainConfigError, match="train.randomize must be a table"):
        TrainConfig(dataset=campaign, randomize=[1, 2])


def test_an_open_current_keeps_the_anatomy_around_the_field():
    L = _line_image(64, 64)
    yy, xx = np.mgrid[0:64, 0:64]
    disc = (yy - 32) ** 2 + (xx - 32) ** 2 < 20 ** 2  # bounding box 39 x 39: a crop of the whole disc
    display = np.where(disc, np.round(L / L.max() * 4095), 0).astype(np.uint16)
    t_m, c_m = prepare_like_registration(display, disc, L, log_display=True, bone_dark=False)
    t_o, c_o = prepare_like_registration(display, disc, L, log_display=True, bone_dark=False, mask_current=False)
    np.testing.assert_array_equal(t_m, t_o)  # the target is the same either way
    corner = (slice(0, 3), slice(0, 3))
    assert np.ptp(c_m[corner]) == 0 and np.ptp(c_o[corner]) > 0  # filled, against the anatomy kept
    # the open current is the crop of L itself (bilinear): the same as the masked one inside the field
    inside = t_m != t_m[0, 0]
    np.testing.assert_allclose(c_o[inside], c_m[inside])


def test_ideal_targets_are_collimated_as_drawn():
    # ideal = 1: every target is a line DRR; its pixels outside the drawn field are filled (one value),
    # inside they are the line DRR of the target pose (many values); open fields are left whole
    from sim.campaign.config import load_campaign

    cfg = load_campaign(ROOT / "campaigns" / "smoke.toml")
    table = {"scatter": ["none"], "ideal": True, "field": ["circle"], "field_radius": [0.3, 0.35]}
    pairs = OnlinePairs(cfg, "train", seed=4, randomization=DomainRandomization.from_table(table),
                        subjects_per_batch=1, current_field="open")
    target, current, _ = pairs.batch(0, 3)
    h, w = cfg.scene.size
    for i, (t, c) in enumerate(zip(target[:, 0].numpy(), current[:, 0].numpy())):
        # the filled pixels are exactly those outside the drawn circle, cropped to its bounding box
        # and resampled (nearest) as registration crops a frame: computed here from the draw alone
        draw = pairs.realistic.randomization.draw(4, i)
        disc = draw.collimator(h, w).mask(h, w)
        rows, cols = np.flatnonzero(disc.any(axis=1)), np.flatnonzero(disc.any(axis=0))
        # torch's "nearest": source index floor(i * n_in / n_out)
        r = np.floor(np.arange(h) * (rows[-1] + 1 - rows[0]) / h).astype(int) + rows[0]
        q = np.floor(np.arange(w) * (cols[-1] + 1 - cols[0]) / w).astype(int) + cols[0]
        outside = ~disc[np.ix_(r, q)]
        assert outside.any() and np.ptp(t[outside]) == 0 and len(np.unique(t[~outside])) > 50
        assert np.ptp(c[outside]) > 0  # the open current keeps its anatomy there
    masked = OnlinePairs(cfg, "train", seed=4, randomization=DomainRandomization.from_table(table),
                         subjects_per_batch=1)
    t2, c2, _ = masked.batch(0, 3)
    np.testing.assert_array_equal(t2.numpy(), target.numpy())
    assert all(np.ptp(c[:2, :2]) == 0 for c in c2[:, 0].numpy())
    with pytest.raises(OnlinePairsError, match="current_field must be one of masked, open"):
        OnlinePairs(cfg, "train", randomization=DomainRandomization.from_table(table), current_field="half")


def test_train_config_checks_the_current_field():
    from learn.train import TrainConfig, TrainConfigError

    campaign = str(ROOT / "campaigns" / "smoke.toml")
    assert TrainConfig(dataset=campaign, randomize={"scatter": ["none"]}, current_field="open").current_field == "open"
    with pytest.raises(TrainConfigError, match="train.current_field must be one of masked, open"):
        TrainConfig(dataset=campaign, randomize={"scatter": ["none"]}, current_field="closed")
    with pytest.raises(TrainConfigError, match="current_field = 'open' needs train.randomize"):
        TrainConfig(dataset=campaign, current_field="open")
