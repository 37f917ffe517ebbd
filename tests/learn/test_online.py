"""Pairs rendered on the fly: right subjects, right labels, near offsets as asked, reproducible."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch
from tests.learn.conftest import train_killed_after_first_checkpoint


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

    tr.train(cfg_for(tmp_path / "a"), log=lambda *_: None)
    ref = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    assert ref["image_size"] == [32, 32]
    from sim.campaign import load_campaign

    assert ref["physics"] == load_campaign(campaign_file).physics[0].to_dict()  # what the images were
    train_killed_after_first_checkpoint(cfg_for(tmp_path / "b"), monkeypatch)
    tr.train(cfg_for(tmp_path / "b"), resume=True, log=lambda *_: None)
    got = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    for key, value in ref["model"].items():
        torch.testing.assert_close(got["model"][key], value, rtol=0, atol=0, msg=key)
    assert list(csv.DictReader(open(tmp_path / "b" / "log.csv"))) == \
        list(csv.DictReader(open(tmp_path / "a" / "log.csv")))


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
