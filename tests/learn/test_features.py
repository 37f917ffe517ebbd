"""Per-image backbone features and their cache: equal to the Siamese extractor's, reused, keyed,
and heads trained on them take exactly the steps of the uncached frozen-backbone run."""

from __future__ import annotations

import os
from dataclasses import asdict

import pytest
import torch
from tests.learn.conftest import log_rows, train_killed_after_first_checkpoint


def config(campaign, out, **kw):
    from learn.train import TrainConfig

    base = dict(dataset=str(campaign.folder), out=str(out), backbone="tiny", freeze_backbone=True, batch_size=4,
                iterations=6, lr=1e-3, pairs_per_epoch=16, val_pairs=8, val_every=3, checkpoint_every=3, seed=5,
                head_channels=8)
    base.update(kw)
    return TrainConfig(**base)


def frozen_tiny(seed: int = 0):
    from learn.model import pose_update_net

    torch.manual_seed(seed)
    return pose_update_net(backbone="tiny", freeze_backbone=True, head_channels=8)


def quiet(*_):
    pass


def test_per_image_features_concatenated_are_the_siamese_features():
    from learn.features import feature_bytes_per_image, image_features
    from learn.model import PoseInputError

    model = frozen_tiny()
    g = torch.Generator().manual_seed(1)
    target, current = torch.randn(3, 1, 64, 64, generator=g), torch.randn(3, 1, 64, 64, generator=g)
    with torch.no_grad():
        pair = model.extract_features(target, current)
        ft, fc = image_features(model, target), image_features(model, current)
    assert len(ft) == 3
    for level, (p, t, c) in enumerate(zip(pair, ft, fc)):
        assert t.shape == (3, model.backbone.channels[level], 64 // 2 ** (level + 3), 64 // 2 ** (level + 3))
        torch.testing.assert_close(torch.cat([t, c], dim=1), p, rtol=1e-6, atol=1e-7)
    stored = sum(t[0].numel() for t in ft) * 2  # float16
    assert feature_bytes_per_image("tiny", (64, 64)) == stored == 5376
    with pytest.raises(PoseInputError, match="N >= 1, 1, H, W"):
        image_features(model, torch.zeros(2, 3, 64, 64))
    with pytest.raises(PoseInputError, match="at least 32"):
        image_features(model, torch.zeros(2, 1, 16, 64))


def test_the_cache_is_reused_and_refuses_other_weights_or_preprocessing(campaign, tmp_path, monkeypatch):
    import learn.features as lf
    from learn.preprocess import build

    model, transform = frozen_tiny(), build(["normalize"])
    messages = []
    with lf.FeatureCache(tmp_path, campaign, model, transform, splits=("train", "test"), log=messages.append) as c:
        assert c.built and len(c) == len(campaign)
        assert any("100%" in m for m in messages)
        path = tmp_path / lf.CACHE_FILE
        mtime = os.stat(path).st_mtime_ns
        idx = [5, 0, 5, 7]
        rows = c.rows(idx)
        # rows equal the per-image features of the preprocessed images, to float16 rounding
        images = torch.stack([torch.from_numpy(campaign[i]["images"]["line"]) for i in idx])[:, None]
        with torch.no_grad():
            direct = lf.image_features(model, transform(images))
        for r, d in zip(rows, direct):
            assert r.dtype == torch.float32 and r.shape == d.shape
            torch.testing.assert_close(r, d, rtol=1e-3, atol=1e-3)
        with pytest.raises(lf.FeatureCacheError, match="no rows"):
            c.rows([len(campaign) + 3])

    def fail(*_):
        raise AssertionError("the cache was recomputed")

    monkeypatch.setattr(lf, "image_features", fail)
    with lf.FeatureCache(tmp_path, campaign, model, transform, splits=("train",), in_memory=True, log=quiet) as again:
        assert not again.built and os.stat(path).st_mtime_ns == mtime
        for a, b in zip(again.rows(idx), rows):
            assert torch.equal(a, b)

    other = frozen_tiny()
    with torch.no_grad():
        other.backbone.features.conv0.weight[0, 0, 0, 0] += 1e-3
    with pytest.raises(lf.FeatureCacheError, match=r"built for other inputs: backbone: stored 'tiny sha256:"):
        lf.FeatureCache(tmp_path, campaign, other, transform, log=quiet)
    with pytest.raises(lf.FeatureCacheError, match=r"preprocess: stored .*minmax.* vs now .*zscore"):
        lf.FeatureCache(tmp_path, campaign, model, build([{"name": "normalize", "mode": "zscore"}]), log=quiet)
    with pytest.raises(lf.FeatureCacheError, match="dtype"):
        lf.FeatureCache(tmp_path, campaign, model, transform, dtype="float32", log=quiet)
    with pytest.raises(lf.FeatureCacheError, match="random_convolution"):
        lf.FeatureCache(tmp_path, campaign, model, build(["random_convolution"]), log=quiet)
    unfrozen = frozen_tiny()
    unfrozen.backbone_frozen = False
    with pytest.raises(lf.FeatureCacheError, match="not frozen"):
        lf.FeatureCache(tmp_path, campaign, unfrozen, transform, log=quiet)
    monkeypatch.undo()
    with lf.FeatureCache(tmp_path, campaign, other, transform, rebuild=True, log=quiet) as rebuilt:
        assert rebuilt.built and not torch.equal(rebuilt.rows([0])[0], rows[1][:1])


def _weights(path):
    from learn.checkpoint import load_checkpoint

    return load_checkpoint(path / "checkpoint.pt").model_state


def _rows(path):
    return log_rows(path)


def test_cached_training_takes_the_uncached_steps_and_resumes_exactly(campaign, tmp_path, monkeypatch):
    import learn.train as tr

    tr.train(config(campaign, tmp_path / "plain"), log=quiet)
    ref = _weights(tmp_path / "plain")

    # float32 cache: bit for bit the same weights and log
    monkeypatch.setattr(tr._CachedSource, "DTYPE", "float32")
    tr.train(config(campaign, tmp_path / "f32", cache_features=True), log=quiet)
    assert (tmp_path / "f32" / "features" / "features.h5").is_file()
    got = _weights(tmp_path / "f32")
    for key, value in ref.items():
        torch.testing.assert_close(got[key], value, rtol=0, atol=0, msg=key)
    assert _rows(tmp_path / "f32") == _rows(tmp_path / "plain")

    # killed after the first checkpoint and resumed: the same again, the cache reused
    cfg = config(campaign, tmp_path / "resumed", cache_features=True)
    train_killed_after_first_checkpoint(cfg, monkeypatch)
    messages = []
    tr.train(cfg, resume=True, log=messages.append)
    assert any("reused" in m for m in messages)
    got = _weights(tmp_path / "resumed")
    for key, value in ref.items():
        torch.testing.assert_close(got[key], value, rtol=0, atol=0, msg=key)
    assert _rows(tmp_path / "resumed") == _rows(tmp_path / "plain")

    # float16 cache (the default): close to the uncached run, not bit for bit. Adam moves a weight
    # by about lr per step whatever the gradient's size, so a weight whose tiny gradient changes
    # sign with the rounding can differ by up to ~lr * iterations; the losses stay close.
    monkeypatch.setattr(tr._CachedSource, "DTYPE", "float16")
    cfg = config(campaign, tmp_path / "f16", cache_features=True)
    tr.train(cfg, log=quiet)
    got = _weights(tmp_path / "f16")
    for key, value in ref.items():
        torch.testing.assert_close(got[key], value, rtol=0, atol=2 * cfg.lr * cfg.iterations, msg=key)
    assert not all(torch.equal(got[k], v) for k, v in ref.items())
    for a, b in zip(_rows(tmp_path / "f16"), _rows(tmp_path / "plain"), strict=True):
        for key in ("train_loss", "val_loss"):
            assert float(a[key]) == pytest.approx(float(b[key]), rel=1e-3)


def test_cache_features_refusals_name_the_keys(campaign, tmp_path):
    from learn.train import TrainConfigError, _config_changes, load_train_config

    with pytest.raises(TrainConfigError, match="train.cache_features needs train.freeze_backbone"):
        config(campaign, tmp_path, cache_features=True, freeze_backbone=False)
    with pytest.raises(TrainConfigError, match="train.cache_features needs a campaign folder as train.dataset"):
        config(campaign, tmp_path, dataset=str(tmp_path / "c.toml"), cache_features=True)
    with pytest.raises(TrainConfigError, match="random_convolution.*train.preprocess"):
        config(campaign, tmp_path, cache_features=True, preprocess=("normalize", "random_convolution"))
    toml = tmp_path / "t.toml"
    toml.write_text(f'[train]\ndataset = "{campaign.folder}"\nfreeze_backbone = true\ncache_features = true\n')
    assert load_train_config(toml).cache_features
    # checkpoints written before the key existed still resume when it keeps its default
    cfg = config(campaign, tmp_path)
    old = {k: v for k, v in asdict(cfg).items() if k != "cache_features"}
    assert _config_changes(old, cfg) == []
    assert _config_changes(old, config(campaign, tmp_path, cache_features=True)) == [
        "train.cache_features (not recorded: False) -> True"]
    assert _config_changes({**old, "lr": 1.0}, cfg) == [f"train.lr 1.0 -> {cfg.lr!r}"]
