"""Pairs rendered on the fly: right subjects, right labels, near offsets as asked, reproducible."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from tests.learn.conftest import log_rows, train_killed_after_first_checkpoint


@pytest.fixture(scope="module")
def campaign_file(campaign):
    return campaign.folder.parent / "c.toml"


@pytest.fixture(scope="module")
def cfg(campaign_file):
    from sim.campaign import load_campaign

    return load_campaign(campaign_file)


def test_batches_are_reproducible_and_labelled_by_their_poses(cfg):
    from learn.labels import LabelNormalizer, geodesic_label
    from learn.online import NearPairs, OnlinePairs

    pairs = OnlinePairs(cfg, "train", near=NearPairs(0.5), seed=3)
    t1, c1, y1 = pairs.batch(7, 6)
    t2, c2, y2 = pairs.batch(7, 6)
    assert t1.shape == c1.shape == (6, 1, 32, 32) and y1.shape == (6, 6) and y1.dtype == torch.float32
    assert torch.equal(t1, t2) and torch.equal(c1, c2) and torch.equal(y1, y2)
    assert not torch.equal(pairs.batch(8, 6)[0], t1)
    subject, T_a, T_b = pairs.draw(7, 6)
    expect = LabelNormalizer().normalize(geodesic_label(torch.from_numpy(T_a), torch.from_numpy(T_b)))
    torch.testing.assert_close(y1, expect.float())
    # the images are the subject's DRRs at those poses
    renderer = pairs.context(0).renderers["line"]
    np.testing.assert_allclose(t1[:, 0].numpy(), renderer.render(T_a), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(c1[:, 0].numpy(), renderer.render(T_b), rtol=1e-6, atol=1e-6)


def test_near_offsets_follow_their_log_uniform_ranges(cfg):
    from learn.labels import geodesic_label
    from learn.online import NearPairs, OnlinePairs

    near = NearPairs(1.0, (1.0, 10.0), (2.0, 20.0))
    pairs = OnlinePairs(cfg, "train", near=near, seed=1)
    _, T_a, T_b = pairs.draw(0, 400)
    g = geodesic_label(torch.from_numpy(T_a), torch.from_numpy(T_b)).numpy()
    rot = np.degrees(np.linalg.norm(g[:, :3], axis=1)) / 2  # |log| = |g| / 2
    trans = np.linalg.norm(g[:, 3:], axis=1) / 2
    assert rot.min() >= 1.0 - 1e-9 and rot.max() <= 10.0 + 1e-9
    assert trans.min() >= 2.0 - 1e-9 and trans.max() <= 20.0 + 1e-9
    # log-uniform: the log of the angle is uniform, so its median is the geometric mean (+-4 sigma of 400 draws)
    assert abs(np.median(np.log(rot)) - math.log(math.sqrt(10.0))) < 4 * (math.log(10) / math.sqrt(12 * 400)) * 1.6
    far = OnlinePairs(cfg, "train", near=NearPairs(0.0), seed=1)
    _, T_a, T_b = far.draw(0, 400)
    g = geodesic_label(torch.from_numpy(T_a), torch.from_numpy(T_b)).numpy()
    assert np.median(np.degrees(np.linalg.norm(g[:, :3], axis=1)) / 2) > 20.0  # independent poses are far apart


def test_only_the_splits_subjects_are_used(cfg):
    from learn.online import OnlinePairs, OnlinePairsError

    train = OnlinePairs(cfg, "train", seed=0)
    test = OnlinePairs(cfg, "test", seed=0)
    assert [s.split for s in train.subjects] == ["train"] and [s.split for s in test.subjects] == ["test"]
    with pytest.raises(OnlinePairsError, match="no subject in split 'val'"):
        OnlinePairs(cfg, "val")


def test_bad_near_settings_are_refused():
    from learn.online import NearPairs, OnlinePairsError

    with pytest.raises(OnlinePairsError, match="fraction"):
        NearPairs(1.5)
    with pytest.raises(OnlinePairsError, match="rot_deg"):
        NearPairs(0.5, (5.0, 1.0))
    with pytest.raises(OnlinePairsError, match="trans_mm"):
        NearPairs(0.5, (1.0, 5.0), (0.0, 3.0))


def test_online_training_resumes_exactly_and_records_the_image_size_and_physics(campaign_file, tmp_path,
                                                                               monkeypatch):
    import learn.train as tr

    def cfg_for(out):
        return tr.TrainConfig(dataset=str(campaign_file), out=str(out), backbone="tiny", batch_size=4, iterations=6,
                              lr=1e-3, val_pairs=6, val_every=3, checkpoint_every=3, seed=2, loss="relative",
                              near_fraction=0.5)

    from learn.checkpoint import load_checkpoint

    tr.train(cfg_for(tmp_path / "a"), log=lambda *_: None)
    ref = load_checkpoint(tmp_path / "a" / "checkpoint.pt")
    assert ref.image_size == (32, 32)
    from sim.campaign import load_campaign

    assert ref.physics == load_campaign(campaign_file).physics[0].to_dict()  # what the images were
    train_killed_after_first_checkpoint(cfg_for(tmp_path / "b"), monkeypatch)
    tr.train(cfg_for(tmp_path / "b"), resume=True, log=lambda *_: None)
    got = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    for key, value in ref.model_state.items():
        torch.testing.assert_close(got.model_state[key], value, rtol=0, atol=0, msg=key)
    assert log_rows(tmp_path / "b") == log_rows(tmp_path / "a")


def test_online_settings_are_checked(campaign, campaign_file, tmp_path):
    from learn.train import TrainConfig, TrainConfigError

    with pytest.raises(TrainConfigError, match="near_fraction needs pairs rendered on the fly"):
        TrainConfig(dataset=str(campaign.folder), near_fraction=0.3)
    with pytest.raises(TrainConfigError, match="near"):
        TrainConfig(dataset=str(campaign_file), near_rot_deg=(3.0, 1.0))
    with pytest.raises(TrainConfigError, match="loss"):
        TrainConfig(dataset=str(campaign_file), loss="l1")


def test_relative_loss_weighs_each_pair_by_its_label_length():
    from learn.model import PoseUpdateNet, PoseUpdateOutput

    label = torch.tensor([[0.01, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0]])
    err = torch.tensor([[0.01, 0, 0, 0, 0, 0], [0.01, 0, 0, 0, 0, 0]])  # the same absolute error on both pairs
    out = PoseUpdateOutput(g=label + err, g_levels=(label + err)[:, None].repeat(1, 3, 1),
                           weights=torch.full((2, 3), 1 / 3))
    eps = 0.05
    got = PoseUpdateNet.loss(out, label, relative_eps=eps)
    w = 1 / (label[:, 0] ** 2 + eps**2)
    expect = 2 * (err[:, 0] ** 2 * w).sum() / 12  # (levels mean + sum mean), each over B x 6 entries
    torch.testing.assert_close(got, expect)
    assert PoseUpdateNet.loss(out, label) == pytest.approx(2 * 2 * 1e-4 / 12)
    with pytest.raises(ValueError, match="relative_eps"):
        PoseUpdateNet.loss(out, label, relative_eps=-1.0)


def test_poly_pairs_draw_fresh_reproducible_noise_per_batch(tmp_path):
    """Online pairs of a poly campaign: each batch's noise comes from its own seed, a function of
    (seed, batch, subject), so a batch is the same when drawn again and two batches have
    uncorrelated noise (residuals: image minus the noise-free image at the same poses)."""
    from dataclasses import replace

    from learn.online import NearPairs, OnlinePairs
    from sim.campaign import load_campaign
    from sim.physics.imaging import XRayImager

    (tmp_path / "p.toml").write_text('''
[campaign]
name = "p"
images_per_ct = 2
[scene]
size = [32, 32]
[[physics]]
name = "poly"
level = "poly"
mas = 0.001
[[cts]]
path = "phantom:0"
split = "train"
''')
    cfg = load_campaign(tmp_path / "p.toml")
    pairs = OnlinePairs(cfg, "train", near=NearPairs(0.0), seed=2)
    renderer = pairs.context(0).renderers["poly"]
    seeds = []
    real_render = renderer.render

    def recording_render(poses, seed=None):
        seeds.append(seed)
        return real_render(poses, seed=seed)

    renderer.render = recording_render
    t0 = pairs.batch(0, 8)[0]
    assert torch.equal(t0, pairs.batch(0, 8)[0])
    pairs.batch(1, 8)
    assert seeds[0] is not None and seeds[0] == seeds[1] != seeds[2]
    imager = renderer.imager
    noiseless = XRayImager(imager.renderer.volume, replace(imager.physics, noise=False), size=(32, 32),
                           center_lps=pairs.context(0).center)
    residuals = []
    for k in (0, 1):
        _, T_a, _ = pairs.draw(k, 8)
        target = pairs.batch(k, 8)[0][:, 0].numpy()
        residuals.append((target - noiseless.render(T_a)["log"]).ravel())
    assert np.std(residuals[0]) > 0.02  # there is noise (0.001 mAs)
    assert abs(np.corrcoef(residuals[0], residuals[1])[0, 1]) < 0.2


TWO_PHYSICS = '''
[campaign]
name = "two"
images_per_ct = 2
[scene]
size = [32, 32]
[[physics]]
name = "full"
level = "full"
mas = 0.01
scatter_photons = 2000
[[physics]]
name = "poly_clean"
level = "poly"
noise = false
[[cts]]
path = "phantom:0"
split = "train"
[[cts]]
path = "phantom:1"
split = "train"
[[cts]]
path = "phantom:2"
split = "train"
'''


def test_targets_and_currents_can_have_their_own_physics(tmp_path):
    """train.physics / current_physics: the targets are the noisy, scattered ``full`` images and
    the currents exactly the noise-free ``poly`` images of their poses (what a registration's
    moving images are); with one entry for both, the targets would be noise-free too."""
    from learn.online import NearPairs, OnlinePairs, OnlinePairsError
    from sim.campaign import load_campaign

    (tmp_path / "two.toml").write_text(TWO_PHYSICS)
    cfg = load_campaign(tmp_path / "two.toml")
    pairs = OnlinePairs(cfg, "train", near=NearPairs(0.5), seed=1, physics="full", current_physics="poly_clean")
    subject, T_a, T_b = pairs.draw(0, 6)
    target, current, _ = pairs.batch(0, 6)
    for i in range(6):
        clean = pairs.context(int(subject[i])).renderers["poly_clean"]
        np.testing.assert_array_equal(current[i, 0].numpy(), clean.render(T_b[i:i + 1])[0])
        residual = target[i, 0].numpy() - clean.render(T_a[i:i + 1])[0]
        assert np.std(residual) > 0.02  # quantum noise at 0.01 mAs, and scatter
    assert torch.equal(target, pairs.batch(0, 6)[0])  # reproducible
    both_clean = OnlinePairs(cfg, "train", near=NearPairs(0.5), seed=1, physics="poly_clean")
    assert torch.equal(both_clean.batch(0, 6)[1], current)
    with pytest.raises(OnlinePairsError, match="'poly' is not a physics entry"):
        OnlinePairs(cfg, "train", current_physics="poly")


def test_subjects_per_batch_limits_each_batch_to_that_many_subjects(tmp_path):
    from learn.online import OnlinePairs, OnlinePairsError
    from sim.campaign import load_campaign

    (tmp_path / "two.toml").write_text(TWO_PHYSICS)
    cfg = load_campaign(tmp_path / "two.toml")
    pairs = OnlinePairs(cfg, "train", seed=0, physics="poly_clean", subjects_per_batch=2)
    seen = set()
    for k in range(12):
        subject = pairs.draw(k, 32)[0]
        assert len(set(subject.tolist())) == 2
        seen |= set(subject.tolist())
    assert seen == {0, 1, 2}  # the chosen subjects change from batch to batch
    # without the option, a 32-pair batch draws from all three subjects
    assert len(set(OnlinePairs(cfg, "train", seed=0).draw(0, 32)[0].tolist())) == 3
    for bad in (0, 4, 1.5, True):
        with pytest.raises(OnlinePairsError, match="subjects_per_batch"):
            OnlinePairs(cfg, "train", subjects_per_batch=bad)


def test_train_config_checks_the_physics_entries(campaign, tmp_path):
    import learn.train as tr

    (tmp_path / "two.toml").write_text(TWO_PHYSICS)
    with pytest.raises(tr.TrainConfigError, match="current_physics needs pairs rendered on the fly"):
        tr.TrainConfig(dataset=str(campaign.folder), current_physics="poly_clean")
    with pytest.raises(tr.TrainConfigError, match="subjects_per_batch needs pairs rendered on the fly"):
        tr.TrainConfig(dataset=str(campaign.folder), subjects_per_batch=2)
    cfg = tr.TrainConfig(dataset=str(tmp_path / "two.toml"), out=str(tmp_path / "o"), current_physics="clean")
    with pytest.raises(tr.TrainConfigError, match=r"train.current_physics = 'clean' is not a \[\[physics\]\] entry"):
        tr.train(cfg, log=lambda *_: None)


def test_a_checkpoint_records_the_current_images_physics(tmp_path):
    """The checkpoint of a run with full targets and poly currents records both entries, and the
    registration's physics note compares the moving images with the *current* images' entry."""
    import learn.train as tr
    from learn.checkpoint import load_checkpoint
    from learn.predict import NetworkPredictor
    from sim.physics.imaging import PhysicsSettings

    (tmp_path / "two.toml").write_text(TWO_PHYSICS)
    cfg = tr.TrainConfig(dataset=str(tmp_path / "two.toml"), out=str(tmp_path / "o"), backbone="tiny",
                         batch_size=2, iterations=1, val_pairs=2, val_every=1, checkpoint_every=1,
                         physics="full", current_physics="poly_clean", subjects_per_batch=1)
    (tmp_path / "two.toml").write_text(TWO_PHYSICS.replace('split = "train"\n[[cts]]\npath = "phantom:2"\nsplit = "train"',
                                                           'split = "train"\n[[cts]]\npath = "phantom:2"\nsplit = "val"'))
    tr.train(cfg, log=lambda *_: None)
    state = load_checkpoint(tmp_path / "o" / "checkpoint.pt")
    assert state.physics["name"] == "full" and state.current_physics["name"] == "poly_clean"
    p = NetworkPredictor(str(tmp_path / "o" / "checkpoint.pt"))
    assert p.physics_mismatch(PhysicsSettings(level="poly")) is None
    assert "poly at 120 kVp current images" in p.physics_mismatch(PhysicsSettings(level="full"))
    assert "poly" in p.physics_mismatch(None)
    # ctxreg accuracy on the same pairs as a registration sees them: full targets, poly currents
    from learn.commands import AccuracyCommand, run_accuracy
    from learn.accuracy import AccuracyError

    def accuracy(out, **kw):
        run_accuracy(AccuracyCommand(model=str(tmp_path / "o" / "checkpoint.pt"), campaign=str(tmp_path / "two.toml"),
                                     kind=("ap",), pairs=3, out=str(tmp_path / out), **kw))
        return json.loads((tmp_path / out / "accuracy.json").read_text())

    mixed = accuracy("acc_mixed", entry="full", current_entry="poly_clean")
    same = accuracy("acc_full", entry="full")
    assert (mixed["physics"], mixed["current_physics"], mixed["note"]) == ("full", "poly_clean", None)
    assert same["current_physics"] == "full" and "poly at 120 kVp current images" in same["note"]
    assert same["note"].endswith("pick a matching --current-entry")  # accuracy's option, not register's
    # the same poses (the baselines agree), but other current images (the predictions do not)
    assert mixed["results"]["ap"]["zero_baseline"] == same["results"]["ap"]["zero_baseline"]
    assert mixed["results"]["ap"]["weighted_sum"] != same["results"]["ap"]["weighted_sum"]
    with pytest.raises(AccuracyError, match="'clean' is not a \\[\\[physics\\]\\] entry"):
        accuracy("x", current_entry="clean")
    with pytest.raises(AccuracyError, match="with --ct both images are line DRRs"):
        run_accuracy(AccuracyCommand(model=str(tmp_path / "o" / "checkpoint.pt"), ct="phantom:0", entry="full",
                                     out=str(tmp_path / "y")))
