"""Batched realistic pairs (learn.batched.BatchedPairs) against the per-pair path they replace,
their reproducibility, and a resumed batched training run."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch

from learn.online import OnlinePairs, OnlinePairsError
from sim.physics import PhysicsError
from sim.randomize import DomainRandomization

ROOT = Path(__file__).resolve().parents[2]
#: one tube setting (one spectral table row: quick to build), everything else as declared
TABLE = {"scatter": ["none", "kernel"], "kvp": 80, "al_mm": 2.5, "cu_mm": {"0.1": 1.0}, "ideal": 0.3}


@pytest.fixture(scope="module")
def campaign():
    from sim.campaign.config import load_campaign

    return load_campaign(ROOT / "campaigns" / "smoke.toml")


@pytest.fixture(scope="module")
def both(campaign, tmp_path_factory):
    from learn.batched import BatchedPairs

    r = DomainRandomization.from_table(TABLE)
    per_pair = OnlinePairs(campaign, "train", seed=3, randomization=r)
    batched = BatchedPairs(campaign, "train", seed=3, randomization=r, tables=tmp_path_factory.mktemp("tables"))
    return r, per_pair, batched


def test_batched_pairs_are_the_per_pair_pairs(both):
    """The same draws (poses, subjects, randomization) through both paths, 24 pairs: labels equal,
    current images equal (the same Siddon renders, 1e-5), ideal targets equal (1e-4 of the [0, 1]
    range); realistic targets differ by the two-basis model against the 9 materials and by their
    noise draws, which a display's unsharp mask and window magnify: each pair's mean absolute
    difference below 0.08 of the range and correlation above 0.9, their median below 0.03
    (measured on these 17 realistic pairs: 0.002-0.057, median 0.015; correlations 0.93-1.00, the
    lowest with unsharp masking inside a collimated field)."""
    r, per_pair, batched = both
    n, k = 24, 2
    a1, b1, y1 = per_pair.batch(k, n)
    a2, b2, y2 = batched.batch(k, n)
    torch.testing.assert_close(y2, y1, rtol=0, atol=1e-6)
    np.testing.assert_allclose(b2.numpy(), b1.numpy(), atol=1e-5)
    draws = [r.draw(3, k * (1 << 16) + i) for i in range(n)]
    ideal = [i for i, d in enumerate(draws) if d["ideal"]]
    real = [i for i, d in enumerate(draws) if not d["ideal"]]
    assert ideal and real
    np.testing.assert_allclose(a2.numpy()[ideal], a1.numpy()[ideal], atol=1e-4)
    mad = []
    for i in real:
        x, y = a1.numpy()[i].ravel(), a2.numpy()[i].ravel()
        mad.append(np.abs(x - y).mean())
        assert mad[-1] < 0.08, (i, draws[i].to_dict())
        assert np.corrcoef(x, y)[0, 1] > 0.9, (i, draws[i].to_dict())
    assert np.median(mad) < 0.03


def test_batched_pairs_with_fitted_scatter_are_the_per_pair_pairs(campaign, tmp_path):
    """Scatter ``sks`` (the fitted kernel model at the pair's kV, grid and air gap, with its
    quantum noise) through both paths, 16 pairs: the mean absolute bounds of the test above (the
    scatter is the same model in both; the bases and the noise draws differ), correlations above
    0.7, median above 0.9 (measured 0.77-1.00: scatter lowers the contrast, so the paths' different
    noise weighs more), and the scatter acts in both: the per-pair targets are nearer the batched
    ones with scatter than those without it."""
    from learn.batched import BatchedPairs

    # the texture (its own noise draw in each path) nearly off: it is tested batched against numpy
    # with the same draws in tests/sim/test_physics_chain.py
    table = {**TABLE, "scatter": ["sks"], "ideal": 0.0, "mas": [4.0, 8.0], "sks_texture": [0.001, 0.002]}
    r = DomainRandomization.from_table(table)
    per_pair = OnlinePairs(campaign, "train", seed=4, randomization=r)
    batched = BatchedPairs(campaign, "train", seed=4, randomization=r, tables=tmp_path)
    n, k = 16, 1
    a1, _, _ = per_pair.batch(k, n)
    a2, _, _ = batched.batch(k, n)
    mad = [np.abs(a1.numpy()[i] - a2.numpy()[i]).mean() for i in range(n)]
    assert max(mad) < 0.08 and np.median(mad) < 0.03, mad
    corr = [np.corrcoef(a1.numpy()[i].ravel(), a2.numpy()[i].ravel())[0, 1] for i in range(n)]
    assert min(corr) > 0.7 and np.median(corr) > 0.9, corr  # measured: 0.77-1.00 (lowered contrast: noise weighs more)
    plain = BatchedPairs(campaign, "train", seed=4, randomization=DomainRandomization.from_table(
        {**table, "scatter": ["none"]}), tables=tmp_path)
    a3, _, _ = plain.batch(k, n)
    # the per-pair targets are nearer the batched ones with the same scatter than without it
    assert np.abs(a1.numpy() - a2.numpy()).mean() < 0.7 * np.abs(a1.numpy() - a3.numpy()).mean()
    assert np.abs(a3.numpy() - a2.numpy()).mean() > 0.01


def test_a_batch_is_reproducible_and_its_groups_follow_the_draws(both):
    r, _, batched = both
    a1, b1, y1 = batched.batch(5, 6)
    a2, b2, y2 = batched.batch(5, 6)
    for u, v in ((a1, a2), (b1, b2), (y1, y2)):
        torch.testing.assert_close(u, v, rtol=0, atol=0)
    assert not torch.equal(batched.batch(6, 6)[0], a1)
    g = batched.groups(5, 6)
    draws = [r.draw(3, 5 * (1 << 16) + i) for i in range(6)]
    np.testing.assert_array_equal(g["ideal"], [d["ideal"] for d in draws])
    np.testing.assert_array_equal(g["field"], [d["field"] != "none" for d in draws])
    np.testing.assert_array_equal(g["near"], ~g["far"])
    assert not (g["log"] & g["linear"]).any() and ((g["log"] | g["linear"]) == ~g["ideal"]).all()


def test_pairs_at_chosen_poses_are_the_batch_pairs_of_those_poses(both):
    """``pairs(subject, t_a, t_b, index)`` with batch k's own draws gives batch k exactly, pair by
    pair (a pair's draw and noise follow its number, not its neighbours); bad shapes are refused."""
    _, _, batched = both
    k, n = 4, 6
    subject, t_a, t_b = batched.draw(k, n)
    index = k * (1 << 16) + np.arange(n)
    ref = batched.batch(k, n)
    pick = [4, 1]  # two of the pairs, in another order
    got = batched.pairs(subject[pick], t_a[pick], t_b[pick], index[pick])
    for u, v in zip(got, ref):
        torch.testing.assert_close(u, v[pick], rtol=0, atol=0)
    with pytest.raises(OnlinePairsError, match=r"t_a and t_b \(n, 4, 4\) for 2 pair numbers"):
        batched.pairs(subject[:2], t_a[:2, :3], t_b[:2], index[:2])
    with pytest.raises(OnlinePairsError, match="subject indices must lie in"):
        batched.pairs(np.full(2, len(batched.subjects)), t_a[:2], t_b[:2], index[:2])


def test_displayed_pairs_of_a_batch_displays_are_the_batch(both, monkeypatch):
    """``displayed_pairs`` given the displayed targets and fields a batch rendered (captured on the
    way) gives that batch back: the same current renders, preparation and labels; a display of
    another size is refused."""
    _, _, batched = both
    k, n = 6, 5
    subject, t_a, t_b = batched.draw(k, n)
    seen = {}
    real = type(batched)._prepared

    def capture(self, display, field, current, log_display, bone_dark, *rest):
        seen.update(display=display.clone(), field=field.clone(), log=log_display.clone(), dark=bone_dark.clone())
        return real(self, display, field, current, log_display, bone_dark, *rest)

    monkeypatch.setattr(type(batched), "_prepared", capture)
    ref = batched.batch(k, n)
    monkeypatch.setattr(type(batched), "_prepared", real)
    got = batched.displayed_pairs(seen["display"], seen["field"], subject, t_a, t_b, log_display=seen["log"],
                                  bone_dark=seen["dark"])
    for u, v in zip(got, ref):
        torch.testing.assert_close(u, v, rtol=0, atol=0)
    with pytest.raises(OnlinePairsError, match="the campaign's image size"):
        batched.displayed_pairs(seen["display"][:, :-1], seen["field"][:, :-1], subject, t_a, t_b,
                                log_display=True, bone_dark=False)


def test_a_missed_field_shows_the_whole_detector(campaign, tmp_path, monkeypatch):
    """``field_missed`` (a field registration read as none): the same draws otherwise (the setting
    is appended to the stream), the same displayed images, but each collimated realistic target is
    prepared over the whole detector (its shadow or shutter shown), while open fields and ideal
    targets keep theirs; per-pair and batched paths agree within the first test's bounds where a shutter
    covers the outside."""
    from learn.batched import BatchedPairs

    k, n = 3, 16
    runs = {}
    real = BatchedPairs._prepared
    for p_missed in (0.0, 1.0):
        r = DomainRandomization.from_table({**TABLE, "field_missed": p_missed})
        batched = BatchedPairs(campaign, "train", seed=5, randomization=r, tables=tmp_path)
        seen = {}

        def capture(self, display, field, *rest, seen=seen):
            seen.update(display=display.clone(), field=field.clone())
            return real(self, display, field, *rest)

        monkeypatch.setattr(BatchedPairs, "_prepared", capture)
        out = batched.batch(k, n)
        monkeypatch.setattr(BatchedPairs, "_prepared", real)
        runs[p_missed] = (r, batched, seen, out)
    r1, batched1, seen1, out1 = runs[1.0]
    _, _, seen0, out0 = runs[0.0]
    draws = [r1.draw(5, k * (1 << 16) + i) for i in range(n)]
    missed = [i for i, d in enumerate(draws) if d["field"] != "none" and not d["ideal"]]
    kept = [i for i in range(n) if i not in missed]
    assert missed and kept
    torch.testing.assert_close(seen1["display"], seen0["display"], rtol=0, atol=0)
    assert bool(seen1["field"][missed].all())
    assert not bool(seen0["field"][missed].all(dim=(1, 2)).any())  # each had a field to miss
    torch.testing.assert_close(seen1["field"][kept], seen0["field"][kept], rtol=0, atol=0)
    torch.testing.assert_close(out1[0][kept], out0[0][kept], rtol=0, atol=0)
    torch.testing.assert_close(out1[2], out0[2], rtol=0, atol=0)
    assert all(float((out1[0][i] - out0[0][i]).abs().mean()) > 1e-3 for i in missed)
    # the per-pair path agrees where the outside is a shutter (black or white). Where it is the
    # processed shadow (shutter none), the normalisation over the whole detector shows the display's
    # window as the device set it, and that window collapses where more of the field than 100 -
    # window_high % is photon-starved (the signal at the log's 1e-12 floor after electronic noise):
    # one pair of these 16 (3 mAs, window_high 99.6 %) has 0.52 % such pixels in the 9-material
    # per-pair path and under 0.4 % in the two-basis batched one, and differs by 0.40 (mean absolute)
    per_pair = OnlinePairs(campaign, "train", seed=5, randomization=r1)
    a1, _, _ = per_pair.batch(k, n)
    shuttered = [i for i in missed if draws[i]["shutter"] != "none"]
    assert len(shuttered) >= 3
    mad = [float(np.abs(a1.numpy()[i] - out1[0].numpy()[i]).mean()) for i in shuttered]
    assert max(mad) < 0.08 and np.median(mad) < 0.03, mad


def test_the_ap_pairs_are_the_batch_targets_with_the_current_image_at_ap(both, campaign):
    """``ap_batch(k, n)``: batch k's targets unchanged, every current image the AP start's (pose
    parameters zero, as ``register.api.parse_init("ap")``), labels from that start."""
    from learn.labels import geodesic_label
    from register.api import parse_init
    from sim.projection.geometry import pose_from_params
    from sim.projection.scene import load_scene

    _, _, batched = both
    k, n = 3, 5
    target, _, _ = batched.batch(k, n)
    ap_target, ap_current, ap_label = batched.ap_batch(k, n)
    torch.testing.assert_close(ap_target, target, rtol=0, atol=0)
    subject, t_a, _ = batched.draw(k, n)
    start = pose_from_params(np.repeat(parse_init("ap")[None], n, 0), load_scene(campaign.scene.name).geometry.sod_mm)
    _, current, label = batched.pairs(subject, t_a, start, k * (1 << 16) + np.arange(n))
    torch.testing.assert_close(ap_current, current, rtol=0, atol=0)
    torch.testing.assert_close(ap_label, batched.normalizer.normalize(
        geodesic_label(torch.from_numpy(t_a), torch.from_numpy(start))).float(), rtol=0, atol=0)


def test_the_noise_of_a_pair_does_not_depend_on_its_batch():
    from sim.core.seeds import pair_normals

    a = pair_normals(4, [7, 9, 11], 1, (5, 6))
    b = pair_normals(4, [11], 1, (5, 6))
    torch.testing.assert_close(a[2], b[0], rtol=0, atol=0)
    assert not torch.equal(pair_normals(4, [11], 2, (5, 6))[0], b[0])


def test_batched_pairs_refuse_what_they_cannot_make(campaign, tmp_path):
    from learn.batched import BatchedPairs

    with pytest.raises(OnlinePairsError, match="need a randomization"):
        BatchedPairs(campaign, "train", randomization=None)
    with pytest.raises(OnlinePairsError, match="cannot run a Monte Carlo transport per pair"):
        BatchedPairs(campaign, "train", randomization=DomainRandomization())
    bad = tmp_path / "tables"
    bad.mkdir()
    (bad / "pair_tables.npz").write_bytes(b"damaged")
    pairs = BatchedPairs(campaign, "train", seed=3, randomization=DomainRandomization.from_table(TABLE), tables=bad)
    with pytest.raises(PhysicsError, match="pair_tables.npz cannot be read .*remove it to rebuild"):
        pairs.batch(0, 2)


def test_a_resumed_batched_training_takes_the_same_steps(campaign, tmp_path, monkeypatch):
    """Batched pairs, 8 steps straight against 4 steps, a kill right after the checkpoint, and a
    resume: the same steps. The weights agree to float32 rounding (1e-5 + 1e-4 relative; run alone
    they are equal to the bit, but in the whole suite a run differed in the last bits once: the
    batched stages' matrix products go through BLAS, whose summation order can follow the buffers'
    memory alignment). A different pair in any step would move a weight by about the learning rate
    (1e-3), which this tolerance does not hide; the log's iterations and losses agree too."""
    import learn.train as tr
    from learn.checkpoint import load_checkpoint
    from tests.learn.conftest import train_killed_after_first_checkpoint

    def cfg(out):
        return tr.TrainConfig(dataset=str(ROOT / "campaigns" / "smoke.toml"), out=str(out), backbone="tiny",
                              batch_size=3, iterations=8, lr=1e-3, val_pairs=4, val_every=4, checkpoint_every=4,
                              seed=5, loss="relative", pairs="batched", randomize=dict(TABLE))

    tr.train(cfg(tmp_path / "a"), log=lambda *_: None, device="cpu")
    ref = load_checkpoint(tmp_path / "a" / "checkpoint.pt")
    train_killed_after_first_checkpoint(cfg(tmp_path / "b"), monkeypatch)
    assert load_checkpoint(tmp_path / "b" / "checkpoint.pt").iteration == 4
    tr.train(cfg(tmp_path / "b"), resume=True, log=lambda *_: None, device="cpu")
    got = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert got.iteration == 8
    for key, value in ref.model_state.items():
        if value.is_floating_point():
            diff = float((got.model_state[key] - value).abs().max()) if value.numel() else 0.0
            assert torch.allclose(got.model_state[key], value, rtol=1e-4, atol=1e-5), (key, diff)
        else:
            assert torch.equal(got.model_state[key], value), key
    rows = list(csv.DictReader(open(tmp_path / "b" / "log.csv")))
    ref_rows = list(csv.DictReader(open(tmp_path / "a" / "log.csv")))
    assert [r["iteration"] for r in rows] == [r["iteration"] for r in ref_rows] == ["4", "8"]
    for r, q in zip(rows, ref_rows):
        for k in q:
            if k not in ("iteration", "elapsed_s") and q[k]:
                assert float(r[k]) == pytest.approx(float(q[k]), rel=1e-3, abs=1e-4, nan_ok=True), k
    assert "val_rot_near_deg" in rows[0] and "val_rot_field_deg" in rows[0]  # the curve by group
    assert all(float(r["val_rot_ap_deg"]) > 0 and float(r["val_trans_ap_mm"]) > 0 for r in rows)  # and from AP


def test_batched_config_refusals_name_the_key(tmp_path):
    from learn.train import TrainConfig, TrainConfigError, resolve_device

    base = dict(dataset=str(ROOT / "campaigns" / "smoke.toml"), out=str(tmp_path))
    with pytest.raises(TrainConfigError, match="train.pairs must be one of per-pair, batched"):
        TrainConfig(**base, pairs="fast", randomize=dict(TABLE))
    with pytest.raises(TrainConfigError, match="train.pairs = 'batched' needs train.randomize"):
        TrainConfig(**base, pairs="batched")
    with pytest.raises(TrainConfigError, match="cannot tone"):
        TrainConfig(**base, pairs="batched", randomize=dict(TABLE), tone="ct")
    with pytest.raises(TrainConfigError, match="device must be one of auto, cpu, cuda"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(TrainConfigError, match="torch sees no CUDA GPU"):
            resolve_device("cuda")


def test_the_cached_tables_serve_a_new_run_unchanged(both, campaign):
    """A second run reads the spectral table and tool bank its first one cached (what a GPU machine
    without spekpy, xraylib and Mitsuba does) and makes the same pairs."""
    from learn.batched import BatchedPairs

    r, _, batched = both
    batched.cache_tables()
    names = sorted(p.name for p in Path(batched.tables).iterdir())
    assert names == ["pair_tables.npz", "tool_bank_seed3_64x64.npz"]
    again = BatchedPairs(campaign, "train", seed=3, randomization=r, tables=batched.tables)
    for u, v in zip(again.batch(7, 4), batched.batch(7, 4)):
        torch.testing.assert_close(u, v, rtol=0, atol=0)
    with pytest.raises(OnlinePairsError, match="needs a tables folder"):
        BatchedPairs(campaign, "train", seed=3, randomization=r).cache_tables()


def test_a_new_run_folder_reads_the_build_cache_instead_of_building(campaign, tmp_path, monkeypatch):
    """A run in a new folder takes the spectral table and tool bank that an earlier run of the same
    settings built (sim.core.build_cache: 18 s and 13 s for the default randomization on 2 cores),
    bit for bit, and keeps its own copy; another seed's tool bank is built."""
    import learn.batched as lb
    from sim.physics.two_basis import SpectralTable

    monkeypatch.setenv("CTXREG_BUILD_CACHE", str(tmp_path / "cache"))
    r = DomainRandomization.from_table(TABLE)
    lines = []
    first = lb.BatchedPairs(campaign, "train", seed=3, randomization=r, tables=tmp_path / "a", log=lines.append)
    first.cache_tables()
    assert [line.split(" (")[0] for line in lines] == ["building the pairs' spectral table", "tracing the tool bank"]

    def never(*a, **k):
        raise AssertionError("built again")
    monkeypatch.setattr(SpectralTable, "for_randomization", classmethod(never))
    monkeypatch.setattr(lb, "tool_arrangements", never)
    again = lb.BatchedPairs(campaign, "train", seed=3, randomization=r, tables=tmp_path / "b", log=lines.append)
    again.cache_tables()
    assert len(lines) == 2  # read, not built: nothing to say
    for name in ("pair_tables.npz", "tool_bank_seed3_64x64.npz"):  # the arrays, not the bytes (zip times)
        with np.load(tmp_path / "a" / name) as a, np.load(tmp_path / "b" / name) as b:
            assert sorted(a.files) == sorted(b.files)
            for k in a.files:
                np.testing.assert_array_equal(b[k], a[k])
    with pytest.raises(AssertionError, match="built again"):
        lb.BatchedPairs(campaign, "train", seed=4, randomization=r, tables=tmp_path / "c").cache_tables()


def test_validate_checkpoint_gives_the_logged_validation(tmp_path):
    """learn.train.validate_checkpoint of a run's final checkpoint on the run's own config is the
    log's last validation row (the same pairs, groups and AP targets); a checkpoint of another
    backbone is refused, naming it."""
    import learn.train as tr

    cfg = tr.TrainConfig(dataset=str(ROOT / "campaigns" / "smoke.toml"), out=str(tmp_path / "a"), backbone="tiny",
                         batch_size=3, iterations=4, lr=1e-3, val_pairs=4, val_every=4, checkpoint_every=4, seed=5,
                         loss="relative", pairs="batched", randomize={**TABLE, "scatter": ["none", "sks"]})
    tr.train(cfg, log=lambda *_: None, device="cpu")
    last = list(csv.DictReader(open(tmp_path / "a" / "log.csv")))[-1]
    got = tr.validate_checkpoint(cfg, tmp_path / "a" / "checkpoint.pt")
    assert set(got) == {k for k in last if k.startswith("val_")}
    for k, v in got.items():
        assert v == pytest.approx(float(last[k]), rel=1e-4, abs=1e-5, nan_ok=True), k
    other = tr.TrainConfig(**{**cfg.__dict__, "backbone": "small"})
    with pytest.raises(tr.TrainConfigError, match="backbone"):
        tr.validate_checkpoint(other, tmp_path / "a" / "checkpoint.pt")


def test_the_image_term_adds_its_weighted_value_to_the_loss(tmp_path):
    """A batched run with ``image_weight``: the logged training loss of the first step is the
    geodesic loss of the same batch plus the weight times the logged image term (in [0, 2]), the
    term recomputed from the initial network equals the logged one, and the steps differ from a
    run without it. Refusals name the key."""
    import learn.train as tr
    from learn.checkpoint import load_checkpoint
    from learn.model import pose_update_net

    def cfg(out, weight):
        return tr.TrainConfig(dataset=str(ROOT / "campaigns" / "smoke.toml"), out=str(out), backbone="tiny",
                              batch_size=4, iterations=1, lr=1e-3, val_pairs=4, val_every=1, checkpoint_every=1,
                              seed=5, loss="relative", pairs="batched", randomize=dict(TABLE),
                              image_weight=weight, image_pairs=3, image_size=16)

    tr.train(cfg(tmp_path / "a", 0.5), log=lambda *_: None, device="cpu")
    tr.train(cfg(tmp_path / "b", 0.0), log=lambda *_: None, device="cpu")
    row_a = list(csv.DictReader(open(tmp_path / "a" / "log.csv")))[0]
    row_b = list(csv.DictReader(open(tmp_path / "b" / "log.csv")))[0]
    image = float(row_a["train_image"])
    assert 0 < image <= 2
    assert "train_image" not in row_b
    # the same seed: the same initial network and batch, so the geodesic part is run b's loss
    assert float(row_a["train_loss"]) == pytest.approx(float(row_b["train_loss"]) + 0.5 * image, rel=1e-5)
    torch.manual_seed(5)
    model = pose_update_net(backbone="tiny")
    source = tr._OnlineSource(cfg(tmp_path / "c", 0.5))
    target, current, _ = source.train_batch(0)
    model.train()
    with torch.no_grad():
        y = model(target, current).g[:3]
    assert float(source.image_term(0, y)) == pytest.approx(image, rel=1e-4)
    a = load_checkpoint(tmp_path / "a" / "checkpoint.pt").model_state
    b = load_checkpoint(tmp_path / "b" / "checkpoint.pt").model_state
    assert not all(torch.equal(a[k], b[k]) for k in a if a[k].is_floating_point())

    base = dict(dataset=str(ROOT / "campaigns" / "smoke.toml"), out=str(tmp_path))
    with pytest.raises(tr.TrainConfigError, match="train.image_weight needs batched pairs"):
        tr.TrainConfig(**base, image_weight=0.5)
    with pytest.raises(tr.TrainConfigError, match="train.image_pairs must be in"):
        tr.TrainConfig(**base, pairs="batched", randomize=dict(TABLE), batch_size=4, image_weight=0.5, image_pairs=5)
    with pytest.raises(tr.TrainConfigError, match="train.image_weight must be a finite number"):
        tr.TrainConfig(**base, image_weight=float("nan"))


def test_the_no_motion_level_is_the_mean_size_of_the_validation_labels(tmp_path):
    """learn.train.validate_no_motion: a zero update's error on each pair is the pair's label
    itself, so the logged no-motion errors are the mean rotation (deg) and translation (mm) norms
    of the validation labels, per group and from AP."""
    import math

    import learn.train as tr
    from learn.labels import LabelNormalizer

    cfg = tr.TrainConfig(dataset=str(ROOT / "campaigns" / "smoke.toml"), out=str(tmp_path / "a"), backbone="tiny",
                         batch_size=3, iterations=4, val_pairs=5, seed=5, pairs="batched", randomize=dict(TABLE))
    row = tr.validate_no_motion(cfg)
    source = tr._OnlineSource(cfg)

    def sizes(batches):
        label = LabelNormalizer().denormalize(torch.cat([b[-1] for b in batches]))
        return torch.linalg.norm(label[:, :3], dim=1) * 180 / math.pi, torch.linalg.norm(label[:, 3:], dim=1)

    rot, trans = sizes(list(source.val_batches()))
    assert row["val_rot_err_deg"] == pytest.approx(float(rot.mean()), rel=1e-5)
    assert row["val_trans_err_mm"] == pytest.approx(float(trans.mean()), rel=1e-5)
    assert row["val_trans_err_mm"] > 1.0  # pairs that move: the check is not 0 == 0
    for name, mask in source.val_groups().items():
        m = torch.from_numpy(mask)
        if m.any():
            assert row[f"val_rot_{name}_deg"] == pytest.approx(float(rot[m].mean()), rel=1e-5), name
    rot_ap, trans_ap = sizes(list(source.val_ap_batches()))
    assert row["val_rot_ap_deg"] == pytest.approx(float(rot_ap.mean()), rel=1e-5)
    assert row["val_trans_ap_mm"] == pytest.approx(float(trans_ap.mean()), rel=1e-5)
