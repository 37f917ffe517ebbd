"""Training the pose-update network on campaign pairs: config, loop, checkpoints, resume, logs.

``ctxreg train CONFIG.toml [--resume]`` reads a ``[train]`` table (:class:`TrainConfig`; every
key documented there with its default), trains on pairs of the campaign's ``train`` split, and
validates on its ``val`` split (``test`` if it has no ``val``). The output folder holds
``checkpoint.pt`` (model, optimiser, scheduler, iteration, random states; written atomically
every ``checkpoint_every`` iterations and at the end), ``log.csv`` (iteration, training loss,
validation loss, rotation and translation error of the predicted gradient) and ``loss.png``.
A run killed at any point and restarted with ``--resume`` continues from its last checkpoint
and takes exactly the steps an uninterrupted run would have taken (tested).
"""

from __future__ import annotations

import csv
import math
import os
import tomllib
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch


class TrainConfigError(ValueError):
    """A training config key is wrong; the message names the key and the allowed values."""


@dataclass(frozen=True)
class TrainConfig:
    """The ``[train]`` table. Paths relative to the config file's folder.

    Attributes:
        dataset: campaign folder (written by ``ctxreg simulate``).
        out: output folder for checkpoints and logs.
        backbone: "tiny", "densenet121" or "densenet161" (:class:`learn.model.Backbone`).
        weights: "none" or "imagenet_local" (needs ``weights_path``).
        weights_path: local torchvision DenseNet checkpoint (no download is possible).
        freeze_backbone: train the heads only.
        physics: campaign physics name of the images (default: the campaign's first).
        preprocess: preprocessing step names applied to both images (:mod:`learn.preprocess`).
        batch_size: pairs per step; iterations: optimiser steps in all.
        lr: Adam learning rate; lr_decay / lr_step: multiply the rate by ``lr_decay`` every
            ``lr_step`` iterations (the original: 0.3 every 30000).
        pairs_per_epoch: pairs drawn per epoch (re-drawn each epoch from the seed).
        val_pairs: validation pairs (fixed); val_every / checkpoint_every: in iterations.
        seed: every random draw (weights init, pairs, batches).
    """

    dataset: str
    out: str = "runs/train"
    backbone: str = "tiny"
    weights: str = "none"
    weights_path: str | None = None
    freeze_backbone: bool = False
    physics: str | None = None
    preprocess: tuple[str, ...] = ("normalize",)
    batch_size: int = 16
    iterations: int = 1000
    lr: float = 1e-4
    lr_decay: float = 0.3
    lr_step: int = 30000
    pairs_per_epoch: int = 1024
    val_pairs: int = 128
    val_every: int = 100
    checkpoint_every: int = 100
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("batch_size", "iterations", "lr_step", "pairs_per_epoch", "val_pairs", "val_every",
                     "checkpoint_every"):
            if int(getattr(self, name)) < 1:
                raise TrainConfigError(f"train.{name} must be >= 1, got {getattr(self, name)}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise TrainConfigError(f"train.lr must be positive, got {self.lr}")
        if not 0 < self.lr_decay <= 1:
            raise TrainConfigError(f"train.lr_decay must be in (0, 1], got {self.lr_decay}")
        if self.weights not in ("none", "imagenet_local"):
            raise TrainConfigError(f"train.weights must be 'none' or 'imagenet_local', got {self.weights!r}")
        if self.weights == "imagenet_local" and not self.weights_path:
            raise TrainConfigError("train.weights = 'imagenet_local' needs train.weights_path")


def load_train_config(path: str | os.PathLike) -> TrainConfig:
    """Read and validate a training config file."""
    path = Path(path)
    if not path.is_file():
        raise TrainConfigError(f"training config {path} not found")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise TrainConfigError(f"{path}: not valid TOML ({e})") from None
    table = data.get("train")
    if not isinstance(table, dict) or set(data) - {"train"}:
        raise TrainConfigError(f"{path}: expected exactly one [train] table, got {sorted(data)}")
    names = {f.name for f in fields(TrainConfig)}
    unknown = sorted(set(table) - names)
    if unknown:
        raise TrainConfigError(f"{path}: unknown key(s) train.{', train.'.join(unknown)}; allowed: {sorted(names)}")
    if "dataset" not in table:
        raise TrainConfigError(f"{path}: train.dataset (the campaign folder) is required")
    for key in ("dataset", "out", "weights_path"):
        if table.get(key):
            table[key] = str((path.parent / table[key]).resolve())
    if "preprocess" in table:
        table["preprocess"] = tuple(table["preprocess"])
    try:
        return TrainConfig(**table)
    except TypeError as e:
        raise TrainConfigError(f"{path}: {e}") from None


def _rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state()}


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])


def _save_checkpoint(path: Path, payload: dict) -> None:
    from sim.atomic import atomic_path

    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def _errors(pred_norm: torch.Tensor, true_norm: torch.Tensor, normalizer) -> tuple[float, float]:
    """Mean rotation (deg) and translation (mm) error of predicted gradients."""
    p, t = normalizer.denormalize(pred_norm), normalizer.denormalize(true_norm)
    rot = torch.linalg.norm(p[:, :3] - t[:, :3], dim=1).mean().item() * 180.0 / math.pi
    trans = torch.linalg.norm(p[:, 3:] - t[:, 3:], dim=1).mean().item()
    return rot, trans


def train(cfg: TrainConfig, *, resume: bool = False, log=print) -> dict:
    """Train; returns the last log row. See the module doc for the outputs."""
    from learn.data import PairDataset
    from learn.model import Weights, pose_update_net
    from learn.preprocess import build
    from sim.campaign import open_dataset

    out = Path(cfg.out)
    ckpt_path = out / "checkpoint.pt"
    if ckpt_path.exists() and not resume:
        raise TrainConfigError(f"{out} already holds a checkpoint: use --resume, or another train.out")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    data = open_dataset(cfg.dataset)
    transform = build(list(cfg.preprocess))
    train_set = PairDataset(data, "train", pairs=cfg.pairs_per_epoch, physics=cfg.physics,
                            transform=transform, seed=cfg.seed)
    val_split = "val" if len(data.indices("val")) >= 2 else "test"
    val_set = PairDataset(data, val_split, pairs=cfg.val_pairs, physics=cfg.physics, transform=transform,
                          seed=cfg.seed + 1)
    model = pose_update_net(backbone=cfg.backbone,
                            weights=Weights.IMAGENET_LOCAL if cfg.weights == "imagenet_local" else Weights.NONE,
                            weights_path=cfg.weights_path, freeze_backbone=cfg.freeze_backbone)
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=cfg.lr)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=cfg.lr_step, gamma=cfg.lr_decay)
    iteration = 0
    if resume and ckpt_path.exists():
        state = torch.load(ckpt_path, weights_only=False)
        if state["config"] != asdict(cfg):
            raise TrainConfigError(f"{ckpt_path} was written with another config; use another train.out")
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        iteration = state["iteration"]
        _set_rng_state(state["rng"])
        log(f"resumed at iteration {iteration}")
    log_path = out / "log.csv"
    rows = []
    if resume and log_path.exists():
        with open(log_path) as f:
            rows = [r for r in csv.DictReader(f) if int(r["iteration"]) <= iteration]
    per_epoch = math.ceil(cfg.pairs_per_epoch / cfg.batch_size)
    last = {}
    current_epoch, order = None, None
    model.train()
    while iteration < cfg.iterations:
        # batches are a function of (seed, iteration) alone, so a resumed run takes the same steps
        epoch, step_in_epoch = divmod(iteration, per_epoch)
        if epoch != current_epoch:
            train_set.set_epoch(epoch)
            order = torch.randperm(len(train_set), generator=torch.Generator().manual_seed(
                cfg.seed * 1_000_003 + epoch))
            current_epoch = epoch
        idx = order[step_in_epoch * cfg.batch_size:(step_in_epoch + 1) * cfg.batch_size]
        batch = [train_set[int(i)] for i in idx]
        target = torch.stack([b[0] for b in batch])
        current = torch.stack([b[1] for b in batch])
        label = torch.stack([b[2] for b in batch])
        output = model(target, current)
        loss = _loss(output, label)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        scheduler.step()
        iteration += 1
        last = {"iteration": iteration, "train_loss": float(loss.item()), "lr": scheduler.get_last_lr()[0]}
        if iteration % cfg.val_every == 0 or iteration == cfg.iterations:
            last.update(_validate(model, val_set, cfg.batch_size))
            model.train()
            rows.append({k: last.get(k, "") for k in ("iteration", "train_loss", "val_loss", "val_rot_err_deg",
                                                    "val_trans_err_mm", "lr")})
            _write_log(log_path, rows)
            log(f"iteration {iteration}/{cfg.iterations}: train {last['train_loss']:.4f}, "
                f"val {last['val_loss']:.4f}, rotation {last['val_rot_err_deg']:.2f} deg, "
                f"translation {last['val_trans_err_mm']:.1f} mm")
        if iteration % cfg.checkpoint_every == 0 or iteration == cfg.iterations:
            _save_checkpoint(ckpt_path, {"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                                         "scheduler": scheduler.state_dict(), "iteration": iteration,
                                         "rng": _rng_state(), "config": asdict(cfg)})
    _plot(rows, out / "loss.png")
    data.close()
    return last


def _loss(output, label):
    from learn.model import PoseUpdateNet

    return PoseUpdateNet.loss(output, label)


@torch.no_grad()
def _validate(model, val_set, batch_size: int) -> dict:
    model.eval()
    losses, preds, trues = [], [], []
    for start in range(0, len(val_set), batch_size):
        batch = [val_set[i] for i in range(start, min(start + batch_size, len(val_set)))]
        target = torch.stack([b[0] for b in batch])
        current = torch.stack([b[1] for b in batch])
        label = torch.stack([b[2] for b in batch])
        out = model(target, current)
        losses.append(float(_loss(out, label)) * len(batch))
        preds.append(out.g)
        trues.append(label)
    rot, trans = _errors(torch.cat(preds), torch.cat(trues), val_set.normalizer)
    return {"val_loss": sum(losses) / len(val_set), "val_rot_err_deg": rot, "val_trans_err_mm": trans}


def _write_log(path: Path, rows: list[dict]) -> None:
    from sim.atomic import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


def _plot(rows: list[dict], path: Path) -> None:
    if not rows:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim.atomic import save_figure

    it = [int(r["iteration"]) for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(it, [float(r["train_loss"]) for r in rows], label="train")
    ax.plot(it, [float(r["val_loss"]) for r in rows], label="validation")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.legend()
    save_figure(fig, path)
