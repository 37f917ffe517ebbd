"""The training loop: it learns, logs, and a resumed run takes exactly the uninterrupted steps."""

from __future__ import annotations

import csv
from dataclasses import replace

import pytest
import torch
from tests.learn.conftest import train_killed_after_first_checkpoint


def config(campaign, out, **kw):
    from learn.train import TrainConfig

    base = dict(dataset=str(campaign.folder), out=str(out), backbone="tiny", batch_size=4, iterations=12,
                lr=1e-3, pairs_per_epoch=16, val_pairs=8, val_every=6, checkpoint_every=6, seed=5)
    base.update(kw)
    return TrainConfig(**base)


def test_resume_after_an_interruption_gives_the_same_model(campaign, tmp_path, monkeypatch):
    import learn.train as tr
    from learn.checkpoint import load_checkpoint

    cfg_a = config(campaign, tmp_path / "a")
    tr.train(cfg_a, log=lambda *_: None)
    ref = load_checkpoint(tmp_path / "a" / "checkpoint.pt")

    cfg_b = config(campaign, tmp_path / "b")
    train_killed_after_first_checkpoint(cfg_b, monkeypatch)
    assert load_checkpoint(tmp_path / "b" / "checkpoint.pt").iteration == 6
    tr.train(cfg_b, resume=True, log=lambda *_: None)
    got = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert got.iteration == 12
    for key, value in ref.model_state.items():
        torch.testing.assert_close(got.model_state[key], value, rtol=0, atol=0, msg=key)
    rows = list(csv.DictReader(open(tmp_path / "b" / "log.csv")))
    ref_rows = list(csv.DictReader(open(tmp_path / "a" / "log.csv")))
    assert rows == ref_rows


def test_refusals_name_the_key(campaign, tmp_path):
    from learn.train import TrainConfigError, load_train_config, train

    with pytest.raises(TrainConfigError, match="lr"):
        config(campaign, tmp_path, lr=-1.0)
    with pytest.raises(TrainConfigError, match="weights_path"):
        config(campaign, tmp_path, weights="imagenet_local")
    bad = tmp_path / "bad.toml"
    bad.write_text('[train]\ndataset = "x"\nbatchsize = 3\n')
    with pytest.raises(TrainConfigError, match="batchsize"):
        load_train_config(bad)
    cfg = config(campaign, tmp_path / "c", iterations=2, val_every=1, checkpoint_every=1)
    train(cfg, log=lambda *_: None)
    with pytest.raises(TrainConfigError, match="--resume"):
        train(cfg, log=lambda *_: None)
    with pytest.raises(TrainConfigError, match=r"another config \(train.lr 0.001 -> 0.0005\)"):
        train(replace(cfg, lr=5e-4), resume=True, log=lambda *_: None)


def test_single_prediction_errors_have_the_zero_baseline_right(campaign, tmp_path):
    import numpy as np

    from learn.accuracy import single_prediction_errors
    from learn.labels import geodesic_label
    from learn.train import train
    from sim.campaign.poses import ORIGINAL_PROTOCOL
    from sim.ct_io import load_ct_spec
    from sim.geometry import pose_from_params

    cfg = config(campaign, tmp_path / "e", iterations=2, val_every=2, checkpoint_every=2)
    train(cfg, log=lambda *_: None)
    vol = load_ct_spec(campaign.subjects[0]["source"])
    res = single_prediction_errors(str(tmp_path / "e" / "checkpoint.pt"), vol, pairs=6, size=(32, 32), seed=2)
    assert set(res) == {"weighted_sum", "zero_baseline", "depth1", "depth2", "depth3"}
    # the baseline is the labels' own size, computed here independently from the same draws
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(2, spawn_key=(30,))))
    pa, pb = ORIGINAL_PROTOCOL.sample(rng, 6), ORIGINAL_PROTOCOL.sample(rng, 6)
    g = geodesic_label(torch.from_numpy(pose_from_params(pa, 700.0)), torch.from_numpy(pose_from_params(pb, 700.0)))
    expected = np.degrees(np.linalg.norm(g.numpy()[:, :3], axis=1)).mean()
    assert res["zero_baseline"]["rot_deg_mean"] == pytest.approx(expected, rel=1e-9)
    assert all(np.isfinite(v) for r in res.values() for v in r.values())


def test_accuracy_command_writes_its_table_and_the_baseline_is_the_label_size(campaign, tmp_path):
    import json

    import numpy as np

    from learn.commands import AccuracyCommand, run_accuracy
    from learn.accuracy import AccuracyError
    from learn.train import train

    cfg = config(campaign, tmp_path / "m", iterations=2, val_every=2, checkpoint_every=2)
    train(cfg, log=lambda *_: None)
    ckpt = str(tmp_path / "m" / "checkpoint.pt")
    files = run_accuracy(AccuracyCommand(model=ckpt, campaign=str(campaign.folder.parent / "c.toml"), split="test",
                                         pairs=8, out=str(tmp_path / "acc")))
    assert all(f.is_file() for f in files)
    res = json.loads((tmp_path / "acc" / "accuracy.json").read_text())["results"]
    assert set(res) == {"far", "ap", "near"}
    # near pairs are close by construction (default NearPairs: at most 20 deg), far ones are not
    assert res["near"]["zero_baseline"]["rot_deg_mean"] <= 2 * 20.0 + 1e-9
    assert res["far"]["zero_baseline"]["rot_deg_mean"] > res["near"]["zero_baseline"]["rot_deg_mean"]
    assert all(np.isfinite(v) for k in res.values() for r in k.values() for v in r.values())
    assert "| near | weighted sum |" in (tmp_path / "acc" / "accuracy.md").read_text()
    with pytest.raises(AccuracyError, match="exactly one of --ct and --campaign"):
        run_accuracy(AccuracyCommand(model=ckpt, out=str(tmp_path / "x")))


def test_init_from_starts_a_run_from_a_checkpoints_weights(campaign, tmp_path):
    """With ``init_from`` the first step starts at the given weights: one Adam step of lr 1e-12
    leaves them within 1e-9 (Adam's step is about lr per weight), while the same run without it
    starts elsewhere. A checkpoint of another architecture or a missing file is refused."""
    from learn.checkpoint import load_checkpoint
    from learn.train import TrainConfigError, train

    cfg_a = config(campaign, tmp_path / "a", iterations=2, val_every=2, checkpoint_every=2)
    train(cfg_a, log=lambda *_: None)
    a_path = tmp_path / "a" / "checkpoint.pt"
    a = load_checkpoint(a_path).model_state
    tiny_step = dict(iterations=1, val_every=1, checkpoint_every=1, lr=1e-12, seed=9)
    train(config(campaign, tmp_path / "b", init_from=str(a_path), **tiny_step), log=lambda *_: None)
    train(config(campaign, tmp_path / "c", **tiny_step), log=lambda *_: None)
    b = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    c = load_checkpoint(tmp_path / "c" / "checkpoint.pt").model_state
    weights = [k for k in a if "running_" not in k and "num_batches" not in k]  # BN statistics move anyway
    for k in weights:
        torch.testing.assert_close(b.model_state[k], a[k], rtol=0, atol=1e-9, msg=k)
    assert max(float((c[k] - a[k]).abs().max()) for k in weights) > 1e-3
    assert b.config["init_from"] == str(a_path)
    with pytest.raises(TrainConfigError, match="init_from: checkpoint .* not found"):
        train(config(campaign, tmp_path / "d", init_from=str(tmp_path / "none.pt"), **tiny_step))
    with pytest.raises(TrainConfigError, match="head_channels = 64, this run 32"):
        train(config(campaign, tmp_path / "e", init_from=str(a_path), head_channels=32, **tiny_step))


def test_shipped_training_configs_load_and_chain_up():
    """Every file in configs/ is a valid training config; the campaign entries it names exist;
    a fine-tuning config starts from the output of another shipped config or from a shipped
    model's weights (a typo in a path or
    an entry name would otherwise surface only an hour into a recipe)."""
    from pathlib import Path

    from learn.train import load_train_config
    from sim.campaign import load_campaign

    configs = sorted((Path(__file__).resolve().parents[2] / "configs").glob("*.toml"))
    assert len(configs) >= 4
    loaded = {path.name: load_train_config(path) for path in configs}
    outs = {str(Path(cfg.out) / "checkpoint.pt") for cfg in loaded.values()}
    for name, cfg in loaded.items():
        if cfg.dataset.endswith(".toml"):
            entries = {p.name for p in load_campaign(cfg.dataset).physics}
            for key in ("physics", "current_physics"):
                assert getattr(cfg, key) in entries | {None}, f"{name}: train.{key}"
        if cfg.init_from is not None:  # another config's output, or a shipped model's weights (in the repository)
            from learn.shipped import resolve_model, shipped_models

            models = {str(resolve_model(m)) for m in shipped_models()}
            assert cfg.init_from in outs | models, f"{name}: init_from is no shipped config's output or model"


def test_sigterm_or_ctrl_c_stops_with_a_checkpoint_at_that_step_and_resume_continues(campaign, tmp_path,
                                                                                    monkeypatch):
    """The first SIGTERM (a scheduler's) or SIGINT (Ctrl-C) stops the loop after the current step
    with a checkpoint there, not at the last periodic one (iteration 3 here, checkpoints every 6);
    the resumed run ends with the uninterrupted run's weights; the handlers are restored after."""
    import os
    import signal

    import learn.train as tr
    from learn.checkpoint import load_checkpoint

    tr.train(config(campaign, tmp_path / "a"), log=lambda *_: None)
    ref = load_checkpoint(tmp_path / "a" / "checkpoint.pt")
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    for sig in (signal.SIGTERM, signal.SIGINT):
        out = tmp_path / sig.name
        calls = []
        loss = tr._loss

        def signalling_loss(*a, **k):
            calls.append(1)
            if len(calls) == 3:
                os.kill(os.getpid(), sig)
            return loss(*a, **k)

        monkeypatch.setattr(tr, "_loss", signalling_loss)
        said = []
        tr.train(config(campaign, out), log=said.append)
        monkeypatch.setattr(tr, "_loss", loss)
        assert load_checkpoint(out / "checkpoint.pt").iteration == 3
        assert any(f"stopped by {sig.name} at iteration 3" in s for s in said), said
        assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
        tr.train(config(campaign, out), resume=True, log=lambda *_: None)
        got = load_checkpoint(out / "checkpoint.pt")
        assert got.iteration == 12
        for key, value in ref.model_state.items():
            torch.testing.assert_close(got.model_state[key], value, rtol=0, atol=0, msg=key)
