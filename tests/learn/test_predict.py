"""The one network predictor (learn.predict): a checkpoint drives it, one pair or a batch give the
same numbers, other image sizes are resampled, bad checkpoints are refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import torch


def _train(campaign, out, **kw):
    from learn.train import TrainConfig, train

    base = dict(dataset=str(campaign.folder), out=str(out), backbone="tiny", batch_size=4, lr=1e-3,
                pairs_per_epoch=16, val_pairs=8, seed=5, iterations=3, val_every=3, checkpoint_every=3)
    base.update(kw)
    train(TrainConfig(**base), log=lambda *_: None)
    return out / "checkpoint.pt"


@pytest.fixture(scope="module")
def trained(campaign, tmp_path_factory):
    """A checkpoint of a 3-step run on the shared 32 x 32 campaign."""
    return _train(campaign, tmp_path_factory.mktemp("predict") / "p")


def test_a_trained_checkpoint_drives_the_contextual_predictor(campaign, trained):
    from learn.predict import NetworkPredictor

    predictor = NetworkPredictor(str(trained))
    # the checkpoint records the campaign's physics entry of the training images
    assert predictor.physics == campaign.manifest["config"]["physics"][0] and predictor.physics["level"] == "line"
    assert predictor.physics_mismatch(None) is None
    a, b = campaign[0]["images"]["line"], campaign[1]["images"]["line"]
    g = predictor(a, b)
    assert g.shape == (6,) and g.dtype == np.float64 and np.all(np.isfinite(g))
    assert not np.allclose(g, predictor(b, a))  # it knows which image is the target


def test_registration_uses_the_one_predictor():
    """The methods load the network through learn.predict (one predictor, no second home)."""
    import register.engines.contextual
    import register.engines.methods

    assert not hasattr(register.engines.contextual, "NetworkPredictor")
    assert "NetworkPredictor" in register.engines.methods.load_predictor.__code__.co_names


def test_predictor_resamples_other_image_sizes_to_the_training_size(campaign, trained):
    from learn.predict import NetworkPredictor

    predictor = NetworkPredictor(str(trained))
    assert predictor.size == (32, 32)
    a, b = campaign[0]["images"]["line"], campaign[1]["images"]["line"]
    big_a, big_b = (np.kron(x, np.ones((2, 2))) for x in (a, b))  # 64 x 64, each pixel repeated 2 x 2
    np.testing.assert_allclose(predictor(big_a, big_b), predictor(a, b), rtol=1e-5, atol=1e-6)
    # the batched path resamples too (ctxreg accuracy's; its own batching once did not)
    many = predictor.predict(np.stack([big_a, big_b]), np.stack([big_b, big_a]))
    np.testing.assert_allclose(many.g[0], predictor(a, b), rtol=1e-5, atol=1e-6)


def test_a_batch_gives_each_pairs_single_prediction(campaign, trained, monkeypatch):
    """Batches of 32 (and a last, shorter one) give the numbers of one pair at a time, and the
    weighted sum is the depths' estimates weighted by the model's softmax weights."""
    from learn.predict import NetworkPredictor

    predictor = NetworkPredictor(str(trained))
    monkeypatch.setattr(predictor, "batch_size", 4)  # 6 pairs: a batch of 4, then one of 2
    images = np.stack([campaign[i]["images"]["line"] for i in range(len(campaign))])
    fixed, drr = images[[0, 1, 2, 3, 4, 5]], images[[1, 2, 3, 4, 5, 0]]
    out = predictor.predict(fixed, drr)
    assert out.g.shape == (6, 6) and out.g_levels.shape == (6, 3, 6)
    for i in range(6):
        np.testing.assert_allclose(out.g[i], predictor(fixed[i], drr[i]), rtol=1e-5, atol=1e-7)
    # the weighted sum lies in the depths' hull: the (convex) softmax weights reproduce it
    with torch.no_grad():
        x = predictor.transform(torch.from_numpy(np.concatenate([fixed, drr]).astype(np.float32))[:, None])
        w = predictor.model(x[:6], x[6:]).weights.double().numpy()
    np.testing.assert_allclose(out.g, np.einsum("nk,nkj->nj", w, out.g_levels), rtol=1e-5, atol=1e-7)
    assert predictor.predict(fixed[:0], drr[:0]).g.shape == (0, 6)


def test_the_targets_maps_are_kept_while_the_target_does_not_change(campaign, trained, monkeypatch):
    """The iteration's calls (one X-ray, a new DRR each time) run the backbone on the DRR only, and
    give the model's own numbers; a changed target (even one pixel, in place) is mapped again."""
    from learn.predict import NetworkPredictor

    predictor = NetworkPredictor(str(trained))
    images = [np.array(campaign[i]["images"]["line"], np.float64) for i in range(4)]
    target = images[0].copy()

    def model_g(f, d):  # the model on the pair as one stack, as in training
        with torch.no_grad():
            x = predictor.transform(torch.from_numpy(np.stack([f, d]).astype(np.float32))[:, None])
            return predictor.normalizer.denormalize(predictor.model(x[:1], x[1:]).g.double()).numpy()[0]

    expected = [model_g(target, d) for d in images[1:]]
    changed = target.copy()
    changed[5, 7] += 0.5
    expected_changed = model_g(changed, images[1])
    seen = []
    taps = predictor.model.backbone.taps
    monkeypatch.setattr(predictor.model.backbone, "taps", lambda x: (seen.append(len(x)), taps(x))[1])
    for d, e in zip(images[1:], expected):
        np.testing.assert_allclose(predictor(target, d), e, rtol=1e-5, atol=1e-6)
    assert seen == [1, 1, 1, 1]  # the target once, then each DRR
    target[5, 7] += 0.5  # the same array, changed in place
    np.testing.assert_allclose(predictor(target, images[1]), expected_changed, rtol=1e-5, atol=1e-6)
    assert seen == [1, 1, 1, 1, 1, 1]  # the changed target mapped again


def test_bad_checkpoints_are_named_in_one_line(tmp_path):
    from learn.checkpoint import CheckpointError
    from learn.predict import NetworkPredictor

    with pytest.raises(CheckpointError, match="not found") as info:
        NetworkPredictor(str(tmp_path / "none.pt"))
    assert str(tmp_path / "none.pt") in str(info.value)
    bad = tmp_path / "bad.pt"
    torch.save({"something": 1}, bad)
    with pytest.raises(CheckpointError, match="is not a ctxreg checkpoint") as info:
        NetworkPredictor(str(bad))
    assert "\n" not in str(info.value)


def test_a_checkpoint_written_before_the_format_still_predicts(tmp_path):
    """A file of the earlier form (model, config, image size; no format key) loads as version 0
    and predicts exactly what a version-1 file of the same weights does."""
    from learn.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
    from learn.model import pose_update_net
    from learn.predict import NetworkPredictor

    torch.manual_seed(0)
    state = pose_update_net(backbone="tiny", head_channels=16).state_dict()
    torch.save({"model": state, "image_size": [32, 32], "config": {"backbone": "tiny", "head_channels": 16,
                                                                   "preprocess": ["normalize"]}}, tmp_path / "old.pt")
    save_checkpoint(tmp_path / "new.pt", Checkpoint(model_state=state, backbone="tiny", head_channels=16,
                                                    preprocess=("normalize",), config={}, image_size=(32, 32)))
    assert load_checkpoint(tmp_path / "old.pt").format_version == 0
    old, new = NetworkPredictor(str(tmp_path / "old.pt")), NetworkPredictor(str(tmp_path / "new.pt"))
    rng = np.random.default_rng(1)
    a, b = rng.random((2, 32, 32))
    assert np.array_equal(old(a, b), new(a, b))
