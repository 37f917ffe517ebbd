"""The training loop: it learns, logs, and a resumed run takes exactly the uninterrupted steps."""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from tests.learn.conftest import log_rows, train_killed_after_first_checkpoint


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
    assert log_rows(tmp_path / "b") == log_rows(tmp_path / "a")
    # the training seconds go on from the interrupted run's instead of starting again
    elapsed = [float(r["elapsed_s"]) for r in log_rows(tmp_path / "b", times=True)]
    assert elapsed == sorted(elapsed) and elapsed[0] > 0


def test_the_cosine_schedule_warms_up_then_falls_to_zero_over_the_iterations(campaign, tmp_path):
    """lr_schedule = "cosine": step k (from 0) is taken at scheduled_rate(k / iterations), which is
    linear over the warm-up and the closed form (1 + cos(pi s)) / 2 after it."""
    import math

    import learn.train as tr

    cfg = config(campaign, tmp_path / "c", iterations=10, val_every=1, checkpoint_every=5, lr=1e-3,
                 lr_schedule="cosine", lr_warmup=0.2)
    tr.train(cfg, log=lambda *_: None)
    rates = [float(r["lr"]) for r in csv.DictReader(open(tmp_path / "c" / "log.csv"))]
    want = [0.0, 5e-4] + [1e-3 * 0.5 * (1 + math.cos(math.pi * (k / 10 - 0.2) / 0.8)) for k in range(2, 10)]
    assert rates == pytest.approx(want, rel=1e-6, abs=1e-12)
    assert rates[2] == pytest.approx(1e-3) and rates[-1] < 0.05 * 1e-3


def test_under_a_time_limit_the_cosine_runs_over_the_seconds(campaign, tmp_path, monkeypatch):
    """Under stop_after_s the cosine's progress is the training seconds against the limit: on a
    clock that ticks 1 s per reading the rate falls monotonically to near 0 when the time is up,
    and a resume given more seconds stretches it to the new end (a warm restart at that point)."""
    import types

    import learn.train as tr

    clock = {"t": 0.0}

    def tick():
        clock["t"] += 1.0
        return clock["t"]

    monkeypatch.setattr(tr, "time", types.SimpleNamespace(perf_counter=tick))
    cfg = config(campaign, tmp_path / "c", iterations=10_000, val_every=1, checkpoint_every=1000, lr=1e-3,
                 lr_schedule="cosine")
    tr.train(cfg, stop_after_s=40.0, log=lambda *_: None)
    rows = list(csv.DictReader(open(tmp_path / "c" / "log.csv")))
    rates = [float(r["lr"]) for r in rows]
    assert 5 < len(rates) < 40  # stopped by the time limit, long before 10000 iterations
    assert all(b <= a for a, b in zip(rates, rates[1:])) and rates[0] > 0.9e-3 and rates[-1] < 0.05e-3
    before = float(rows[-1]["elapsed_s"])
    tr.train(cfg, resume=True, stop_after_s=3 * before, log=lambda *_: None)  # 4x the seconds in all
    rates = [float(r["lr"]) for r in csv.DictReader(open(tmp_path / "c" / "log.csv"))][len(rows):]
    assert tr.scheduled_rate(cfg, 0.30) < rates[0] < tr.scheduled_rate(cfg, 0.20)  # progress 1/4: a warm restart
    assert rates[-1] < 0.05e-3


def test_cosine_over_iterations_keeps_one_schedule_under_a_time_limit(campaign, tmp_path):
    """cosine_over = "iterations": a run trained in time-limited calls (a GPU's) keeps the schedule of
    its iterations: the same rates, step for step, as the run without a limit."""
    import learn.train as tr

    kw = dict(iterations=8, val_every=1, checkpoint_every=4, lr=1e-3, lr_schedule="cosine", lr_warmup=0.25)
    tr.train(config(campaign, tmp_path / "a", **kw), log=lambda *_: None)
    tr.train(config(campaign, tmp_path / "b", cosine_over="iterations", **kw), stop_after_s=3600.0,
             log=lambda *_: None)
    rates = [[float(r["lr"]) for r in csv.DictReader(open(tmp_path / x / "log.csv"))] for x in "ab"]
    assert rates[0] == rates[1] and len(rates[0]) == 8
    with pytest.raises(tr.TrainConfigError, match="cosine_over must be one of 'auto', 'iterations'"):
        config(campaign, tmp_path, cosine_over="seconds")


def test_trained_backbone_stages_take_their_share_of_every_schedule(campaign, tmp_path):
    """train_backbone_from: Adam's second group holds exactly the trained stages' weights, at
    backbone_lr_scale times the heads' rate on the cosine (step by step) and on a step schedule
    resumed with another rate; the stages before it end as they began."""
    import learn.train as tr
    from learn.checkpoint import load_checkpoint
    from learn.model import pose_update_net

    cfg = config(campaign, tmp_path / "c", iterations=6, val_every=3, checkpoint_every=3, lr=1e-3,
                 lr_schedule="cosine", lr_warmup=0.2, freeze_backbone=True, train_backbone_from="denseblock4",
                 backbone_lr_scale=0.25)
    tr.train(replace(cfg, iterations=3), log=lambda *_: None)
    ckpt = load_checkpoint(tmp_path / "c" / "checkpoint.pt")
    heads, stages = ckpt.optimizer["param_groups"]
    assert stages["lr_scale"] == 0.25 and stages["lr"] == pytest.approx(0.25 * heads["lr"]) and heads["lr"] > 0
    model = pose_update_net(backbone="tiny", head_channels=cfg.head_channels, freeze_backbone=True)
    model.train_backbone_from("denseblock4")
    assert len(stages["params"]) == sum(p.requires_grad for p in model.backbone.parameters())
    # a step schedule from here on, at another rate: both groups follow it, each at its share
    tr.train(replace(cfg, lr_schedule="step", lr=2e-4, lr_step=1000, lr_decay=0.5), resume=True, log=lambda *_: None)
    heads, stages = load_checkpoint(tmp_path / "c" / "checkpoint.pt").optimizer["param_groups"]
    assert heads["lr"] == pytest.approx(2e-4) and stages["lr"] == pytest.approx(5e-5)
    # the stages before denseblock4 never moved: a heads-only run from the same seed has them too
    tr.train(replace(cfg, out=str(tmp_path / "h"), train_backbone_from=None), log=lambda *_: None)
    a = load_checkpoint(tmp_path / "c" / "checkpoint.pt").model_state
    b = load_checkpoint(tmp_path / "h" / "checkpoint.pt").model_state
    before = [k for k in a if k.startswith("backbone.") and ".denseblock4." not in k and ".norm5." not in k]
    assert before and all(torch.equal(a[k], b[k]) for k in before)
    assert not torch.equal(a["backbone.features.norm5.weight"], b["backbone.features.norm5.weight"])


def test_a_backbone_trained_whole_takes_the_full_rate_with_the_heads(campaign, tmp_path):
    """Without train_backbone_from every trained weight, backbone and heads, is in one Adam group
    at lr (backbone_lr_scale is for a frozen backbone's stages only): a fine-tuning such as ctxreg
    adapt's moves its whole network at the rate it was given."""
    from learn.checkpoint import load_checkpoint
    from learn.model import pose_update_net
    from learn.train import train

    for frozen in (False, True):
        out = tmp_path / f"frozen_{frozen}"
        train(config(campaign, out, iterations=2, val_every=2, checkpoint_every=2, lr=1e-3, freeze_backbone=frozen),
              log=lambda *_: None)
        (group,) = load_checkpoint(out / "checkpoint.pt").optimizer["param_groups"]
        model = pose_update_net(backbone="tiny", head_channels=64, freeze_backbone=frozen)
        assert group["lr"] == pytest.approx(1e-3) and group["lr_scale"] == 1.0
        assert len(group["params"]) == sum(p.requires_grad for p in model.parameters())


def test_train_backbone_from_is_refused_where_it_cannot_apply(campaign, tmp_path):
    from learn.train import TrainConfigError, train

    with pytest.raises(TrainConfigError, match="train_backbone_from needs train.freeze_backbone = true"):
        config(campaign, tmp_path, train_backbone_from="denseblock4")
    with pytest.raises(TrainConfigError, match="backbone_lr_scale must be in"):
        config(campaign, tmp_path, backbone_lr_scale=0.0)
    with pytest.raises(TrainConfigError, match="cannot be used with train.train_backbone_from"):
        config(campaign, tmp_path, freeze_backbone=True, train_backbone_from="denseblock4", cache_features=True)
    with pytest.raises(TrainConfigError, match="train.train_backbone_from: the tiny backbone has no stage 'block11'"):
        train(config(campaign, tmp_path / "x", freeze_backbone=True, train_backbone_from="block11"),
              log=lambda *_: None)


def test_refusals_name_the_key(campaign, tmp_path):
    from learn.train import TrainConfigError, load_train_config, train

    with pytest.raises(TrainConfigError, match="lr"):
        config(campaign, tmp_path, lr=-1.0)
    with pytest.raises(TrainConfigError, match="lr_schedule must be one of 'step', 'cosine'"):
        config(campaign, tmp_path, lr_schedule="linear")
    with pytest.raises(TrainConfigError, match=r"lr_warmup must be in \[0, 0.5\]"):
        config(campaign, tmp_path, lr_warmup=0.8)
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
    with pytest.raises(TrainConfigError, match=r"another config \(train.seed 5 -> 6\)"):
        train(replace(cfg, seed=6), resume=True, log=lambda *_: None)
    with pytest.raises(TrainConfigError, match="train.precision must be one of fp32, bf16, auto"):
        config(campaign, tmp_path, precision="fp16")


def test_auto_precision_is_bf16_only_where_the_device_computes_it_natively(campaign, tmp_path, monkeypatch):
    """precision "auto" resolves to bf16 where the device has native bf16 and fp32 elsewhere; the
    log names the choice; an explicit "bf16" on a device without it trains with a warning (bf16
    emulated on an AVX2-only CPU took 4.9x fp32's step, docs/benchmarks.md)."""
    import torch

    import learn.train as tr

    cpu = torch.device("cpu")
    monkeypatch.setattr(tr, "native_bf16", lambda device: False)
    assert tr.step_precision("auto", cpu) == "fp32"
    assert tr.step_precision("bf16", cpu) == "bf16" and tr.step_precision("fp32", cpu) == "fp32"
    with pytest.raises(tr.TrainConfigError, match="train.precision must be one of"):
        tr.step_precision("fp16", cpu)
    lines = []
    tr.train(config(campaign, tmp_path / "a", precision="auto", iterations=2), log=lines.append)
    assert "precision auto: fp32 on cpu (native bf16: no)" in lines
    lines = []
    tr.train(config(campaign, tmp_path / "b", precision="bf16", iterations=2), log=lines.append)
    assert any(line.startswith("warning: train.precision = 'bf16' on a cpu without native bf16") for line in lines)
    monkeypatch.setattr(tr, "native_bf16", lambda device: True)
    assert tr.step_precision("auto", cpu) == "bf16"
    lines = []
    tr.train(config(campaign, tmp_path / "c", precision="auto", iterations=2), log=lines.append)
    assert "precision auto: bf16 on cpu (native bf16: yes)" in lines
    assert not any(line.startswith("warning") for line in lines)


def test_a_run_resumes_in_bf16_and_its_steps_follow_the_fp32_run(campaign, tmp_path, monkeypatch):
    """train.precision is how the steps are computed: a run resumes with the other one (logged),
    and its weights stay within the bound two Adam runs from one state can reach.

    The bound is Adam's, whatever the gradients (so neither load nor thread count can break it):
    by Cauchy-Schwarz over the moments' weights, step t moves a weight by at most
    ``lr * (1 - b1) / sqrt(1 - b2) * sqrt(sum_{k<t} (b1^2 / b2)^k) * sqrt(1 - b2^t) / (1 - b1^t)``
    (1.02 lr at t = 7, 1.06 lr at t = 12 with torch's b1 = 0.9, b2 = 0.999). The two runs share
    the state at step 6 and take steps 7-12 on gradients that differ (bfloat16 keeps 8 bits of
    mantissa), so their weights differ by at most twice the sum: 12.5e-3 for lr 1e-3. A fixed
    6e-3 (half of it) failed once under load. A resume that lost the weights moves them by far
    more (a trained weight against a new initialisation), and a bf16 run that did not run in
    bf16 would not differ at all."""
    import learn.train as tr
    from learn.checkpoint import load_checkpoint

    cfg_a = config(campaign, tmp_path / "a")
    tr.train(cfg_a, log=lambda *_: None)
    ref = load_checkpoint(tmp_path / "a" / "checkpoint.pt")
    cfg_b = config(campaign, tmp_path / "b")
    train_killed_after_first_checkpoint(cfg_b, monkeypatch)
    lines = []
    tr.train(replace(cfg_b, precision="bf16"), resume=True, log=lines.append)
    assert "train.precision 'fp32' -> 'bf16' from here on" in lines
    got = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert got.iteration == 12 and got.config["precision"] == "bf16"
    weights = [k for k in ref.model_state if "running_" not in k and ref.model_state[k].is_floating_point()]
    moved = max(float((ref.model_state[k] - got.model_state[k]).abs().max()) for k in weights)
    b1, b2, lr = 0.9, 0.999, 1e-3

    def step_bound(t):
        return lr * (1 - b1) / (1 - b2) ** 0.5 * sum((b1 * b1 / b2) ** k for k in range(t)) ** 0.5 \
            * (1 - b2 ** t) ** 0.5 / (1 - b1 ** t)

    bound = 2 * sum(step_bound(t) for t in range(7, 13))
    assert bound == pytest.approx(12.5e-3, abs=0.1e-3)
    assert 0 < moved < bound


def test_a_run_resumes_with_another_rate_schedule_from_the_resumed_step(campaign, tmp_path, monkeypatch):
    """train.lr / lr_step / lr_decay (and iterations) may change on resume: the rate from the
    resumed step on is the new schedule's at that step, the logged rates say so, and the optimiser's
    moments are the checkpoint's (the first step after the resume equals a step of the old run
    scaled by the rates' ratio: Adam's update is linear in the rate)."""
    import learn.train as tr
    from learn.checkpoint import load_checkpoint

    cfg_a = config(campaign, tmp_path / "a", iterations=7)
    tr.train(cfg_a, log=lambda *_: None)  # the old schedule, uninterrupted to step 7
    cfg_b = config(campaign, tmp_path / "b")
    train_killed_after_first_checkpoint(cfg_b, monkeypatch)
    at6 = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    lines = []
    tr.train(replace(cfg_b, lr_step=4, lr_decay=0.5, iterations=7), resume=True, log=lines.append)
    assert "train.lr_step 30000 -> 4 from here on" in lines and "learning rate 0.0005 at iteration 6" in lines
    rows = list(csv.DictReader(open(tmp_path / "b" / "log.csv")))
    rates = {int(r["iteration"]): float(r["lr"]) for r in rows}
    assert rates[7] == pytest.approx(1e-3 * 0.5)  # 1e-3 * 0.5^(7 // 4)
    assert rates[6] == pytest.approx(1e-3)  # logged before the resume: the old schedule's
    ref = load_checkpoint(tmp_path / "a" / "checkpoint.pt")
    got = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert got.iteration == 7 and got.config["lr_step"] == 4
    weights = [k for k in ref.model_state if "running_" not in k and ref.model_state[k].is_floating_point()]
    for k in weights:
        step_old = ref.model_state[k] - at6.model_state[k]
        step_new = got.model_state[k] - at6.model_state[k]
        # float32 weights of size <= 1 differ from the difference of two of them by a few 1e-8;
        # a step of the old rate (or of moments started afresh) would miss by ~1e-4
        torch.testing.assert_close(step_new, 0.5 * step_old, rtol=0, atol=1e-6, msg=k)
    assert max(float((ref.model_state[k] - at6.model_state[k]).abs().max()) for k in weights) > 1e-4


def test_a_bf16_step_has_the_fp32_gradient_direction():
    """Under bfloat16 autocast (train.precision = "bf16") the gradient is float32's to within a
    small part of what another batch changes: at random weights on random images, cosine
    similarity 0.968 against float32's on the same batch (8-bit mantissas through a deep
    network), while two batches' float32 gradients are far apart. (With trained weights of the
    small backbone on 128 realistic pairs: 0.994-0.997 against 0.03 for two batches,
    docs/training.md.) A wrong cast or a loss taken in bfloat16 would fall below 0.9."""
    from learn.model import pose_update_net
    from learn.train import TrainConfig, _loss

    torch.manual_seed(0)
    model = pose_update_net(backbone="tiny")
    batches = [(torch.randn(8, 1, 64, 64), torch.randn(8, 1, 64, 64), torch.randn(8, 6) * 0.3) for _ in range(2)]
    cfg = TrainConfig(dataset="x.toml", loss="relative", relative_eps=0.1)

    def gradient(batch, bf16):
        a, b, y = batch
        model.zero_grad()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = model(a, b)
        assert out.g.dtype == torch.float32  # the heads run in float32
        _loss(type(out)(*(t.float() for t in out)), y, cfg).backward()
        return torch.cat([p.grad.flatten() for p in model.parameters()])

    cos = torch.nn.functional.cosine_similarity
    ref, bf16, other = gradient(batches[0], False), gradient(batches[0], True), gradient(batches[1], False)
    assert cos(ref, bf16, dim=0) > 0.9
    assert (ref - bf16).norm() < 0.5 * (ref - other).norm()


def test_a_bf16_step_with_a_non_finite_gradient_is_skipped_and_too_many_stop_the_run(campaign, tmp_path,
                                                                                     monkeypatch):
    """An overflowed bfloat16 step (a NaN gradient) takes no optimiser step and is counted in the
    log; the weights stay finite. More than MAX_SKIPPED_FRACTION of the steps (1 % of at least 100,
    so a second one here) stops the run with a line naming the remedy."""
    import learn.train as tr
    from learn.checkpoint import load_checkpoint

    real_loss, calls = tr._loss, []

    def loss_poisoned_on(poisoned):
        def loss(*args, **kw):
            calls.append(None)
            value = real_loss(*args, **kw)
            return value * float("nan") if len(calls) in poisoned else value
        return loss

    monkeypatch.setattr(tr, "_loss", loss_poisoned_on({3}))
    lines = []
    tr.train(config(campaign, tmp_path / "a", precision="bf16"), log=lines.append)
    got = load_checkpoint(tmp_path / "a" / "checkpoint.pt")
    assert got.iteration == 12
    assert all(torch.isfinite(v).all() for v in got.model_state.values() if v.is_floating_point())
    steps = {int(s["step"]) for s in got.optimizer["state"].values()}
    assert steps == {11}, "the poisoned iteration must take no Adam step"
    assert any("1 bf16 steps skipped for a non-finite gradient" in line for line in lines)

    calls.clear()
    monkeypatch.setattr(tr, "_loss", loss_poisoned_on({2, 5}))
    with pytest.raises(tr.TrainConfigError, match="2 of the 5 steps .* non-finite gradient; train with precision = 'fp32'"):
        tr.train(config(campaign, tmp_path / "b", precision="bf16"), log=lambda *_: None)


def test_a_second_run_into_one_folder_is_refused_at_once(campaign, tmp_path):
    """Two trainings (or adaptations) writing one checkpoint would corrupt it: while a run holds
    its folder, a second is refused in one line naming the holder, before any work."""
    from learn.train import train
    from sim.core.atomic import FolderBusyError, folder_lock

    cfg = config(campaign, tmp_path / "busy", iterations=1)
    with folder_lock(tmp_path / "busy", "ctxreg train"):
        with pytest.raises(FolderBusyError, match=r"ctxreg train \(PID \d+ on .*\) is working in this folder"):
            train(cfg, log=lambda *_: None)
    assert not (tmp_path / "busy" / "checkpoint.pt").exists()


ROOT = Path(__file__).resolve().parents[2]
CONFIGS = sorted((ROOT / "configs").rglob("*.toml"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: str(p.relative_to(ROOT / "configs")))
def test_every_committed_config_loads_and_names_a_campaign_or_a_run(path):
    """A committed config is what its comment's command runs: every key known and of its type
    (load_train_config refuses others), its dataset a committed campaign file or a run's output,
    its starting weights a committed model, a resume state or a run's checkpoint."""
    from learn.train import load_train_config

    cfg = load_train_config(path)
    root = ROOT
    dataset = Path(cfg.dataset)
    if dataset.suffix == ".toml":
        assert dataset.is_file(), f"{path.name}: train.dataset {dataset} is not a committed campaign file"
        assert dataset.parent == root / "campaigns"
    else:
        assert dataset.is_relative_to(root / "runs"), f"{path.name}: train.dataset {dataset} is neither a campaign nor a run"
    if cfg.init_from:
        init = Path(cfg.init_from)
        assert init.parts[len(root.parts)] in ("models", "resume", "runs"), f"{path.name}: init_from {init}"
        if init.parts[len(root.parts)] == "models":
            assert init.is_file(), f"{path.name}: init_from {init} is not a committed model"
