"""Training the pose-update network on campaign pairs: config, loop, checkpoints, resume, logs.

``ctxreg train CONFIG.toml [--resume]`` reads a ``[train]`` table (:class:`TrainConfig`; every
key documented there with its default), trains on pairs of the campaign's ``train`` split, and
validates on its ``val`` split (``test`` if it has no ``val``). ``dataset`` is either a campaign
folder written by ``ctxreg simulate`` (pairs of its stored images, :mod:`learn.data`) or a
campaign ``.toml`` file, whose subjects are then rendered on the fly, near pairs included
(:mod:`learn.online`). With ``freeze_backbone`` and ``cache_features`` the backbone's maps of
every image are computed once (``<out>/features/features.h5``, :class:`learn.features.FeatureCache`)
and only the heads run per step, on the same pairs in the same order. The output folder holds
``checkpoint.pt`` (:mod:`learn.checkpoint`: model, architecture, image size (H, W) in pixels,
preprocessing, physics, config, optimiser, scheduler, iteration, random states; written atomically
every ``checkpoint_every`` iterations and at the end), ``log.csv`` (iteration, training loss,
validation loss, rotation and translation error of the predicted gradient, learning rate, training
seconds so far) and ``loss.png``.
A run killed at any point and restarted with ``--resume`` continues from its last checkpoint
and takes exactly the steps an uninterrupted run would have taken (tested); a resume with another
config is refused, naming the keys that changed. The first Ctrl-C (SIGINT) or SIGTERM (a cluster
scheduler's, ``kill``) stops after the current step with a checkpoint there (no validation), so
nothing since the last periodic checkpoint is lost; a second one interrupts at once.

Every key of the ``[train]`` table is type-checked (``batch_size = "2"``, ``batch_size = 2.5`` and
``iterations = true`` are refused, not taken as numbers); the message names the key.
"""

from __future__ import annotations

import contextlib
import csv
import math
import os
import signal
import threading
import time
import typing
from dataclasses import MISSING, asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch

from learn.distributed import DistributedRun, unwrap
from sim.core.atomic import folder_lock
from sim.core.errors import InputError
from learn.checkpoint import (Checkpoint, CheckpointError, capture_rng, load_checkpoint, load_weights, remove_stale_temps, restore_rng, save_checkpoint)
from learn.data import PairDataset
from learn.features import CACHE_FILE, FeatureCache, FeatureCacheError, feature_bytes_per_image
from learn.image_term import ImageTerm
from learn.labels import LabelNormalizer, geodesic_label
from learn.model import PoseInputError, PoseUpdateNet, PoseUpdateOutput, Weights, pose_update_net
from learn.online import FRAMINGS, NearPairs, OnlinePairs, OnlinePairsError, check_trainable, current_field_problem
from learn.preprocess import build
from sim.campaign import open_dataset
from sim.campaign.config import CampaignConfigError, load_campaign
from sim.core.atomic import read_toml, save_figure, write_csv
from sim.physics.display import TONES
from sim.randomize import DomainRandomization, RandomizeError
from learn.batched import BatchedPairs
from sim.core.progress import Progress


class TrainConfigError(InputError):
    """A training config key is wrong; the message names the key and the allowed values."""


#: How realistic targets are made (``[train] pairs``; :class:`TrainConfig`).
PAIRS = ("per-pair", "batched")

#: The arithmetic of a training step's forward pass (``[train] precision``; :class:`TrainConfig`):
#: ``auto`` is bf16 where the device computes it natively, else fp32 (:func:`step_precision`).
PRECISIONS = ("fp32", "bf16", "auto")

#: With ``precision = "bf16"``, a step whose gradient is not finite is skipped (as a loss scaler
#: skips it); more than this fraction of a run's steps (at least 100 counted) stops it.
MAX_SKIPPED_FRACTION = 0.01

#: Config keys a resumed run may change, each change logged: how the steps are computed
#: (``precision``; the device may change too), the rate schedule from the resumed step on, and
#: the run's length. The rest would make the checkpoint another run's.
#: The learning-rate schedules of ``train.lr_schedule``.
LR_SCHEDULES = ("step", "cosine")
#: What ``train.cosine_over`` may count (see :class:`TrainConfig`).
COSINE_OVER = ("auto", "iterations")

RESUME_MAY_CHANGE = ("precision", "lr", "lr_step", "lr_decay", "lr_schedule", "lr_warmup", "iterations")


@dataclass(frozen=True)
class TrainConfig:
    """The ``[train]`` table. Paths relative to the config file's folder.

    Attributes:
        dataset: campaign folder (written by ``ctxreg simulate``), or a campaign ``.toml`` file to
            render pairs on the fly (:class:`learn.online.OnlinePairs`).
        out: output folder for checkpoints and logs.
        backbone: "tiny", "small", "small-gn", "medium", "densenet121", "densenet161" or
            "efficientnet-lite0" (:class:`learn.model.Backbone`).
        weights: "none" or "imagenet_local" (needs ``weights_path``, except for
            "efficientnet-lite0", whose ImageNet weights the set-up installs).
        weights_path: local torchvision DenseNet checkpoint (no download is possible).
        freeze_backbone: train the heads only.
        train_backbone_from: with ``freeze_backbone``, the backbone's stage (a child of
            ``backbone.features``, e.g. ``"block11"`` of ``efficientnet-lite0``: the stride-32
            stages) from which on its weights train too, the stages before it staying frozen.
            The trained stages' batch norm keeps its running statistics (eval mode, as the rest
            of a frozen backbone): a fine-tuning of the pretrained filters, not of their
            normalisation, so batches of a few dozen pairs do not add noise there. Default
            None: the heads only.
        backbone_lr_scale: the trained backbone stages' learning rate as a share of ``lr``
            (default 0.1: pretrained filters move more slowly than the new heads), on every
            schedule.
        physics: campaign physics name of the images (default: the campaign's first); with
            ``current_physics``, of the target images only.
        current_physics: campaign physics name of the *current* images of each pair (online
            only; default: the same as the targets). Registration compares a realistic X-ray
            with noise-free moving images, so a network can be trained the same way: e.g. targets
            with scatter and noise (``full``), currents noise-free ``poly``, and registration
            then run with ``--physics poly``.
        subjects_per_batch: online only: each batch's pairs come from this many distinct
            subjects (default: a subject per pair). Makes ``full`` batches cheaper
            (:class:`learn.online.OnlinePairs`).
        preprocess: preprocessing step names applied to both images (:mod:`learn.preprocess`).
        batch_size: pairs per step; iterations: optimiser steps in all.
        lr: Adam learning rate; lr_decay / lr_step: multiply the rate by ``lr_decay`` every
            ``lr_step`` iterations (the original: 0.3 every 30000). A run may resume with another
            schedule (and another ``iterations``, :data:`RESUME_MAY_CHANGE`): from the resumed
            step on, the rate is the new schedule's at that step, ``lr * lr_decay^(k // lr_step)``
            (a plateau's rate drop without losing the optimiser's moments).
        lr_schedule: ``"step"`` (default: the step decay above) or ``"cosine"``: a linear warm-up
            from 0 over the first ``lr_warmup`` of the run, then a half cosine from ``lr`` to 0 at
            its end (xvr's schedule). The run's progress is ``iteration / iterations``; under a
            time limit (:func:`train`'s ``stop_after_s``) it is the training seconds against the
            limit (counted across resumes: a resume given more seconds stretches the cosine to the
            new end, a warm restart at the rate of that point), so that the rate reaches 0 when the
            time is up however fast the machine is. ``lr_step`` / ``lr_decay`` are then unused.
        lr_warmup: the warm-up's share of the run, in [0, 0.5] (default 0; cosine only).
        cosine_over: what the cosine's progress counts: ``"auto"`` (default: seconds under a time
            limit, else iterations, as above) or ``"iterations"`` (always ``iteration /
            iterations``: a run trained in several time-limited calls, e.g. a GPU's, keeps one
            schedule over its ``iterations``).
        pairs_per_epoch: pairs drawn per epoch (re-drawn each epoch from the seed).
        val_pairs: validation pairs (fixed); val_every / checkpoint_every: in iterations.
        near_fraction: share of near pairs (online only; default 0.5 there).
        near_rot_deg / near_trans_mm: ``[low, high]`` log-uniform ranges (deg, mm) of the near
            offsets (online only; :class:`learn.online.NearPairs`).
        loss: "mse" (:meth:`learn.model.PoseUpdateNet.loss`) or "relative" (each pair's squared
            error divided by ``|y|^2 + relative_eps^2``, ``y`` the normalised label, so that near
            pairs weigh as much as far ones).
        relative_eps: the floor of the relative loss, in normalised label units (0.05 = 4 deg or 7.5 mm).
        head_channels: channels of each depth's head.
        cache_features: compute the frozen backbone's maps of every train and validation image
            once, store them in ``<out>/features/features.h5`` (float16,
            :class:`learn.features.FeatureCache`; reused by later and resumed runs while the
            backbone weights, campaign, preprocessing and physics are the same) and train the
            heads on them: same pairs and batches as without, only the heads' cost per step.
            Needs ``freeze_backbone = true``, a campaign folder as ``dataset`` (not a ``.toml``
            file: online pairs are new images every batch) and no ``random_convolution`` step.
        seed: every random draw (weights init, pairs, batches).
        randomize: online only: draw every pair's target as a realistic X-ray with domain
            randomization (:class:`learn.online.RealisticTargets`) and prepare it as registration
            prepares a user's X-ray; the table holds overrides of :mod:`sim.randomize`'s declared
            ranges (``[train.randomize]``; an empty table: the declared ranges). Its ``scatter``
            must leave out ``monte-carlo``. The currents stay the ``current_physics`` entry's.
        init_from: a ``ctxreg train`` checkpoint whose model weights start this run instead of a
            random initialisation (fine-tuning, e.g. a network trained on line DRRs continued on
            ``poly`` images); its backbone and head channels must be this config's. The
            optimiser and schedule start afresh.
        tone: with ``randomize``: ``"ct"`` maps every target's values by rank onto the pair's
            current line integrals inside the target's field, as registration makes the toned
            version of a display image on the CT's DRRs (``ctxreg register --tone``,
            :func:`sim.physics.display.apply_tone`); ``"off"`` (default, what the networks before it
            were trained with) keeps the display's values. Recorded in the checkpoint's config;
            registration shows a ``"ct"`` network the X-ray's toned version.
        pairs: with ``randomize``: ``"per-pair"`` (default: :class:`learn.online.RealisticTargets`,
            the 9-material render and numpy post-processing pair by pair) or ``"batched"``
            (:class:`learn.batched.BatchedPairs`: the two-basis model and every image stage batched
            in torch, on the training device: the way to train on a GPU). ``tone = "ct"`` is
            per-pair only. The batched pairs' spectral table and tool bank are kept in
            ``<out>/tables`` (built once with spekpy, xraylib and Mitsuba; a GPU machine without
            them reads them there), and in the machine's build cache for the next run of the
            same settings (:mod:`sim.core.build_cache`).
        framing: with ``pairs = "batched"``: ``"field"`` (default) or ``"detector"``
            (:data:`learn.online.FRAMINGS`): the pair cropped to the target's field, or the whole
            detector with the field masked; registration frames the X-ray the same way for the
            network (the checkpoint records it: :func:`register.xray.network_view.network_view`).
        precision: ``"fp32"`` (default), ``"bf16"`` or ``"auto"`` (:data:`PRECISIONS`): with
            bf16 the training step's forward pass runs under ``torch.autocast`` with bfloat16
            (the backbone's convolutions in bfloat16; its heads, the weights, optimiser, loss and
            validation in float32). A step whose gradient is not finite is skipped and counted in
            the log (:data:`MAX_SKIPPED_FRACTION`). A step of the small backbone at batch 256 on a
            CPU with AVX-512 BF16 takes a third of float32's, but 4.9x float32's on one without
            (an AMD EPYC with AVX2 only, 2026-11-27: bf16 is emulated there; docs/benchmarks.md);
            bfloat16 is the tensor cores' format on a GPU. ``auto``: bf16 where the device
            computes it natively, fp32 elsewhere (:func:`step_precision`; the log names the
            choice); ``bf16`` on a CPU without it trains, with a warning. A run may resume with
            another precision (:data:`RESUME_MAY_CHANGE`).
        image_weight: the weight of an image-space term added to the loss (0, the default: none;
            xvr's choice): ``1 - NCC`` of the line DRRs at the network's predicted target pose and
            at the true one (:class:`learn.image_term.ImageTerm`), on the first ``image_pairs``
            pairs of each batch, rendered ``image_size x image_size`` px by the trilinear march
            (differentiable in the pose; on a CPU it costs about what the pairs' rendering does).
            Needs batched pairs of a campaign file; one process (not under torchrun). The log's
            ``train_image`` column is the term's value.
        image_pairs: pairs per batch in the image term (default 16).
        image_size: the image term's DRR side, px (default 32).
    """

    dataset: str
    out: str = "runs/train"
    backbone: str = "tiny"
    weights: str = "none"
    weights_path: str | None = None
    freeze_backbone: bool = False
    train_backbone_from: str | None = None
    backbone_lr_scale: float = 0.1
    physics: str | None = None
    current_physics: str | None = None
    subjects_per_batch: int | None = None
    preprocess: tuple[str, ...] = ("normalize",)
    batch_size: int = 16
    iterations: int = 1000
    lr: float = 1e-4
    lr_decay: float = 0.3
    lr_step: int = 30000
    lr_schedule: str = "step"
    lr_warmup: float = 0.0
    cosine_over: str = "auto"
    pairs_per_epoch: int = 1024
    val_pairs: int = 128
    val_every: int = 100
    checkpoint_every: int = 100
    near_fraction: float | None = None
    near_rot_deg: tuple[float, float] = (0.5, 20.0)
    near_trans_mm: tuple[float, float] = (1.0, 40.0)
    loss: str = "mse"
    relative_eps: float = 0.05
    head_channels: int = 64
    cache_features: bool = False
    seed: int = 0
    init_from: str | None = None
    randomize: dict | None = None
    current_field: str = "masked"
    tone: str = "off"
    pairs: str = "per-pair"
    framing: str = "field"
    precision: str = "fp32"
    image_weight: float = 0.0
    image_pairs: int = 16
    image_size: int = 32

    @property
    def online(self) -> bool:
        """True when ``dataset`` is a campaign file (pairs rendered on the fly)."""
        return str(self.dataset).endswith(".toml")

    def near(self):
        """The :class:`learn.online.NearPairs` of an online run."""

        try:
            return NearPairs(0.5 if self.near_fraction is None else self.near_fraction,
                             tuple(self.near_rot_deg), tuple(self.near_trans_mm))
        except OnlinePairsError as e:
            raise TrainConfigError(f"train.near_*: {e}") from None

    def randomization(self):
        """The :class:`sim.randomize.DomainRandomization` of ``randomize`` (None without it)."""
        if self.randomize is None:
            return None

        try:
            randomization = DomainRandomization.from_table(self.randomize, "train.randomize")
            check_trainable(randomization)
        except (RandomizeError, OnlinePairsError) as e:
            raise TrainConfigError(str(e).replace("randomize.scatter", "train.randomize.scatter", 1)
                                   if "train.randomize" not in str(e) else str(e)) from None
        return randomization

    def __post_init__(self) -> None:
        for f in fields(self):
            problem = _type_problem(f.name, getattr(self, f.name))
            if problem:
                raise TrainConfigError(problem)
        for name in ("batch_size", "iterations", "lr_step", "pairs_per_epoch", "val_pairs", "val_every",
                     "checkpoint_every"):
            if int(getattr(self, name)) < 1:
                raise TrainConfigError(f"train.{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.seed < 2**32:
            raise TrainConfigError(f"train.seed must be in [0, 2^32), got {self.seed}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise TrainConfigError(f"train.lr must be positive, got {self.lr}")
        if not 0 < self.lr_decay <= 1:
            raise TrainConfigError(f"train.lr_decay must be in (0, 1], got {self.lr_decay}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise TrainConfigError(f"train.lr_schedule must be one of {', '.join(map(repr, LR_SCHEDULES))}, "
                                   f"got {self.lr_schedule!r}")
        if self.cosine_over not in COSINE_OVER:
            raise TrainConfigError(f"train.cosine_over must be one of {', '.join(map(repr, COSINE_OVER))}, "
                                   f"got {self.cosine_over!r}")
        if not 0 <= self.lr_warmup <= 0.5:
            raise TrainConfigError(f"train.lr_warmup must be in [0, 0.5] (a share of the run), got {self.lr_warmup}")
        if self.weights not in ("none", "imagenet_local"):
            raise TrainConfigError(f"train.weights must be 'none' or 'imagenet_local', got {self.weights!r}")
        if self.weights == "imagenet_local" and not self.weights_path and self.backbone != "efficientnet-lite0":
            raise TrainConfigError("train.weights = 'imagenet_local' needs train.weights_path (only "
                                   "efficientnet-lite0's come with the set-up)")
        if self.loss not in ("mse", "relative"):
            raise TrainConfigError(f"train.loss must be 'mse' or 'relative', got {self.loss!r}")
        if not (math.isfinite(self.image_weight) and self.image_weight >= 0):
            raise TrainConfigError(f"train.image_weight must be a finite number >= 0, got {self.image_weight}")
        if self.image_weight > 0:
            if self.pairs != "batched" or not self.online:
                raise TrainConfigError("train.image_weight needs batched pairs of a campaign file (train.pairs = "
                                       "'batched', train.dataset a .toml): the term renders the pairs' subjects")
            if not 1 <= int(self.image_pairs) <= int(self.batch_size):
                raise TrainConfigError(f"train.image_pairs must be in [1, batch_size = {self.batch_size}], "
                                       f"got {self.image_pairs}")
            if not 8 <= int(self.image_size) <= 256:
                raise TrainConfigError(f"train.image_size must be in [8, 256] px, got {self.image_size}")
        if not (self.relative_eps > 0 and math.isfinite(self.relative_eps)):
            raise TrainConfigError(f"train.relative_eps must be positive, got {self.relative_eps}")
        if int(self.head_channels) < 1:
            raise TrainConfigError(f"train.head_channels must be >= 1, got {self.head_channels}")
        if self.train_backbone_from is not None:
            if not isinstance(self.train_backbone_from, str) or not self.train_backbone_from:
                raise TrainConfigError(f"train.train_backbone_from must be a stage name such as 'block11', "
                                       f"got {self.train_backbone_from!r}")
            if not self.freeze_backbone:
                raise TrainConfigError("train.train_backbone_from needs train.freeze_backbone = true (it trains the "
                                       "stages from there on of a backbone otherwise frozen)")
            if self.cache_features:
                raise TrainConfigError("train.cache_features cannot be used with train.train_backbone_from (the "
                                       "trained stages' maps change every step)")
        if not (isinstance(self.backbone_lr_scale, (int, float)) and math.isfinite(self.backbone_lr_scale)
                and 0 < self.backbone_lr_scale <= 1):
            raise TrainConfigError(f"train.backbone_lr_scale must be in (0, 1], got {self.backbone_lr_scale!r}")
        if self.cache_features:
            if not self.freeze_backbone:
                raise TrainConfigError("train.cache_features needs train.freeze_backbone = true (the features of a "
                                       "trained backbone change every step)")
            if self.online:
                raise TrainConfigError("train.cache_features needs a campaign folder as train.dataset, not a "
                                       "campaign .toml file (online pairs are new images every batch)")
            steps = [p if isinstance(p, str) else dict(p).get("name") for p in self.preprocess]
            if "random_convolution" in steps:
                raise TrainConfigError("train.cache_features cannot be used with the random step "
                                       "'random_convolution' in train.preprocess (a new draw per pair)")

        if current_field_problem(self.current_field):
            raise TrainConfigError(f"train.current_field {current_field_problem(self.current_field)}")

        if self.tone not in TONES:
            raise TrainConfigError(f"train.tone must be one of {', '.join(TONES)}, got {self.tone!r}")
        if self.tone != "off" and self.randomize is None:
            raise TrainConfigError("train.tone = 'ct' needs train.randomize (it tones the realistic targets)")
        if self.current_field != "masked" and self.randomize is None:
            raise TrainConfigError("train.current_field = 'open' needs train.randomize (a collimated field is drawn "
                                   "with the realistic targets)")
        if self.pairs not in PAIRS:
            raise TrainConfigError(f"train.pairs must be one of {', '.join(PAIRS)}, got {self.pairs!r}")
        if self.pairs == "batched" and self.randomize is None:
            raise TrainConfigError("train.pairs = 'batched' needs train.randomize (it batches the realistic targets)")

        if self.framing not in FRAMINGS:
            raise TrainConfigError(f"train.framing must be one of {', '.join(FRAMINGS)}, got {self.framing!r}")
        if self.precision not in PRECISIONS:
            raise TrainConfigError(f"train.precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        if self.framing != "field" and self.pairs != "batched":
            raise TrainConfigError("train.framing = 'detector' needs train.pairs = 'batched'")
        if self.pairs == "batched" and self.tone != "off":
            raise TrainConfigError("train.pairs = 'batched' cannot tone the targets (train.tone = 'ct' is per-pair only)")
        if self.randomize is not None:
            if not self.online:
                raise TrainConfigError("train.randomize needs pairs rendered on the fly: set train.dataset to a "
                                       "campaign .toml file")
            self.randomization()
        if self.online:
            self.near()
        elif self.near_fraction is not None:
            raise TrainConfigError("train.near_fraction needs pairs rendered on the fly: set train.dataset to a "
                                   "campaign .toml file (a campaign folder has fixed images)")
        if not self.online and self.subjects_per_batch is not None:
            raise TrainConfigError("train.subjects_per_batch needs pairs rendered on the fly: set train.dataset to "
                                   "a campaign .toml file")
        if not self.online and self.current_physics is not None:
            raise TrainConfigError("train.current_physics needs pairs rendered on the fly: set train.dataset to a "
                                   "campaign .toml file (a campaign folder's pairs share one physics entry)")


def _describe(value) -> str:
    """A TOML value as a message shows it: its written form and its kind."""
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    if isinstance(value, str):
        return f"the string {value!r}"
    if isinstance(value, int):
        return f"the integer {value}"
    if isinstance(value, float):
        return f"the number {value!r}"
    if isinstance(value, (list, tuple)):
        return f"the list {list(value)!r}"
    if isinstance(value, dict):
        return "a table"
    return f"a {type(value).__name__} ({value!r})"


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    """A finite int or float (not a bool: TOML's true is not 1)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _type_problem(key: str, value) -> str | None:
    """A message if ``value`` is not of the type :class:`TrainConfig` declares for ``key``
    (bool is not a number, a string is not a number, 2.5 is not an integer); None if it is.
    None is accepted where the default is None."""
    hint = _FIELD_TYPES[key]
    optional = type(None) in typing.get_args(hint)
    if value is None:
        return None if optional else f"train.{key} is required"
    base = next((a for a in typing.get_args(hint) if a is not type(None)), hint) if optional else hint
    origin = typing.get_origin(base)
    if key == "preprocess":
        ok = isinstance(value, (list, tuple)) and all(
            isinstance(v, str) or isinstance(v, dict) and isinstance(v.get("name"), str) for v in value)
        want = 'a list of step names or tables with a name (e.g. ["normalize"])'
    elif base is dict:  # a sub-table, checked by its own reader
        ok, want = isinstance(value, dict), "a table"
    elif origin is tuple:  # (low, high) number pairs
        ok = isinstance(value, (list, tuple)) and len(value) == 2 and all(map(_is_number, value))
        want = "a list of two finite numbers [low, high]"
    elif base is bool:
        ok, want = isinstance(value, bool), "true or false"
    elif base is int:
        ok, want = _is_int(value), "an integer"
    elif base is float:
        ok, want = _is_number(value), "a finite number"
    elif base is str:
        ok, want = isinstance(value, str), "a string"
    else:  # a new field type: teach this function about it
        raise TypeError(f"TrainConfig.{key}: no type check for {hint}")
    return None if ok else f"train.{key} must be {want}, got {_describe(value)}"


_FIELD_TYPES = typing.get_type_hints(TrainConfig)


def load_train_config(path: str | os.PathLike) -> TrainConfig:
    """Read and validate a training config file."""

    path = Path(path)
    data = read_toml(path, TrainConfigError, "training config")
    table = data.get("train")
    if not isinstance(table, dict) or set(data) - {"train"}:
        raise TrainConfigError(f"{path}: expected exactly one [train] table, got {sorted(data)}")
    names = {f.name for f in fields(TrainConfig)}
    unknown = sorted(set(table) - names)
    if unknown:
        raise TrainConfigError(f"{path}: unknown key(s) train.{', train.'.join(unknown)}; allowed: {sorted(names)}")
    if "dataset" not in table:
        raise TrainConfigError(f"{path}: train.dataset (the campaign folder) is required")
    for key, value in table.items():  # before the paths are resolved: dataset = 5 is not a path
        problem = _type_problem(key, value)
        if problem:
            raise TrainConfigError(f"{path}: {problem}")
    for key in ("dataset", "out", "weights_path", "init_from"):
        if table.get(key):
            table[key] = str((path.parent / table[key]).resolve())
    for key in ("preprocess", "near_rot_deg", "near_trans_mm"):
        if key in table:
            table[key] = tuple(table[key])
    try:
        return TrainConfig(**table)
    except TypeError as e:
        raise TrainConfigError(f"{path}: {e}") from None


def _plain(value):
    """Lists for tuples, recursively (a config read back compares equal to the one written)."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _config_changes(stored: dict, cfg: TrainConfig, *, ignore=("precision",)) -> list[str]:
    """The keys in which a checkpoint's config differs from ``cfg``, as ``"train.KEY OLD -> NEW"``;
    keys added since it was written (absent from ``stored``) count as equal when ``cfg`` has
    their default; the keys of ``ignore`` are not compared (default ``precision``: how the steps
    are computed, not which; ``--resume`` passes :data:`RESUME_MAY_CHANGE`, whereas a study asks
    whether a checkpoint is its variant's training and so compares the schedule too)."""
    now = asdict(cfg)
    defaults = {f.name: f.default for f in fields(TrainConfig)}
    changes = []
    for key in sorted(set(stored) | set(now)):
        if key in ignore:
            continue
        if key not in now:
            changes.append(f"train.{key} {stored[key]!r} -> (no longer a key)")
        elif key not in stored:
            if defaults[key] is MISSING or _plain(now[key]) != _plain(defaults[key]):
                changes.append(f"train.{key} (not recorded: {defaults[key]!r}) -> {now[key]!r}")
        elif _plain(stored[key]) != _plain(now[key]):
            changes.append(f"train.{key} {stored[key]!r} -> {now[key]!r}")
    return changes


def _save_checkpoint(path: Path, checkpoint) -> None:
    """Write the :class:`learn.checkpoint.Checkpoint` (a function of its own: the tests interrupt here)."""

    save_checkpoint(path, checkpoint)


def _resume_checkpoint(path: Path, cfg: TrainConfig):
    """The checkpoint at ``path`` to resume ``cfg`` from; refused if unreadable
    (:class:`learn.checkpoint.CheckpointError`), without training state, or of another config."""

    state = load_checkpoint(path)
    changes = _config_changes(state.config, cfg, ignore=RESUME_MAY_CHANGE)
    if changes:
        raise TrainConfigError(f"{path} was written with another config ({'; '.join(changes)}): resume with the "
                               f"same config, or use another train.out")
    missing = [k for k in ("iteration", "optimizer", "scheduler", "rng") if getattr(state, k) is None]
    if missing:
        raise CheckpointError(f"checkpoint {path} holds no training state ({', '.join(missing)} missing): it cannot "
                              f"be resumed; use it as train.init_from in a new train.out")
    return state


def _init_checkpoint(cfg: TrainConfig):
    """``cfg.init_from`` read and checked against ``cfg``'s architecture (see :class:`TrainConfig`)."""
    return _architecture_checkpoint(cfg, cfg.init_from, "train.init_from")


def _architecture_checkpoint(cfg: TrainConfig, path, where: str):
    """The checkpoint at ``path``, its backbone and head checked against ``cfg``'s; a refusal
    (:class:`TrainConfigError`) starts with ``where``."""

    path = Path(path)
    try:
        state = load_checkpoint(path)
    except CheckpointError as e:
        raise TrainConfigError(f"{where}: {e}") from None
    for key in ("backbone", "head_channels"):
        if getattr(state, key) != getattr(cfg, key):
            raise TrainConfigError(f"{where}: {path} has {key} = {getattr(state, key)!r}, this run "
                                   f"{getattr(cfg, key)!r}")
    return state


def _init_weights(model, init) -> None:
    """Load the :func:`_init_checkpoint`'s weights into ``model``."""

    try:
        load_weights(model, init.model_state, source=f"checkpoint {init.path}")
    except CheckpointError as e:
        raise TrainConfigError(f"train.init_from: {e}") from None


def _errors(pred_norm: torch.Tensor, true_norm: torch.Tensor, normalizer) -> tuple[float, float]:
    """Mean rotation (deg) and translation (mm) error of predicted gradients."""
    p, t = normalizer.denormalize(pred_norm), normalizer.denormalize(true_norm)
    rot = torch.linalg.norm(p[:, :3] - t[:, :3], dim=1).mean().item() * 180.0 / math.pi
    trans = torch.linalg.norm(p[:, 3:] - t[:, 3:], dim=1).mean().item()
    return rot, trans


#: Where ``ctxreg train`` runs (``--device``): ``auto`` is CUDA when torch sees a GPU, else the CPU.
DEVICES = ("auto", "cpu", "cuda")


def resolve_device(device: str = "auto") -> torch.device:
    """The torch device of a ``--device`` value (:data:`DEVICES`); ``cuda`` without a GPU is refused."""
    if device not in DEVICES:
        raise TrainConfigError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise TrainConfigError("device 'cuda': torch sees no CUDA GPU on this machine (use --device cpu or auto)")
    return torch.device(device)


def native_bf16(device: torch.device) -> bool:
    """Whether ``device`` computes bfloat16 convolutions natively: a CUDA GPU that supports it, a
    CPU whose oneDNN has bf16 kernels (AVX-512 BF16 or AMX); elsewhere bf16 is emulated."""
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # a torch build without oneDNN: no native bf16
        return False


def step_precision(precision: str, device: torch.device) -> str:
    """The arithmetic a training step uses on ``device``: ``"fp32"`` or ``"bf16"``; ``precision``
    ``"auto"`` is bf16 where :func:`native_bf16`, else fp32."""
    if precision not in PRECISIONS:
        raise TrainConfigError(f"train.precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if precision == "auto":
        return "bf16" if native_bf16(device) else "fp32"
    return precision


class _StopOnSignal:
    """While training: the first SIGINT (Ctrl-C) or SIGTERM (a cluster's scheduler, ``kill``) asks the
    loop to stop after the current step with a checkpoint there (no validation), so ``--resume``
    continues without losing the steps since the last checkpoint; a second one interrupts at once.
    Installed from the main thread only (elsewhere Python delivers no signals to handlers)."""

    SIGNALS = ("SIGINT", "SIGTERM")

    def __init__(self):
        self._event = threading.Event()
        self._previous = {}
        self.name = ""

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for name in self.SIGNALS:
                sig = getattr(signal, name)
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        if self._event.is_set():  # the second one: stop now
            raise KeyboardInterrupt
        self.name = signal.Signals(signum).name
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        return False


def _on(device, tensors):
    return [t.to(device, non_blocking=True) if isinstance(t, torch.Tensor) else t for t in tensors]


def train(cfg: TrainConfig, *, resume: bool = False, log=print, device: str = "auto",
          stop_after_s: float | None = None) -> dict:
    """Train; returns the last log row. See the module doc for the outputs. ``device``: where the
    network trains and batched pairs are made (:func:`resolve_device`); a checkpoint written on
    one device resumes on another. ``stop_after_s``: stop at the first iteration after this many
    seconds of training (s, > 0), with a checkpoint there, so that ``--resume`` continues the same
    steps (a lent machine's time, a session's end)."""
    if stop_after_s is not None and not (isinstance(stop_after_s, (int, float)) and stop_after_s > 0
                                         and math.isfinite(stop_after_s)):
        raise TrainConfigError(f"stop_after_s must be a positive number of seconds, got {stop_after_s!r}")
    run = DistributedRun.from_env()  # torchrun's processes (learn/distributed.py); one process: world 1
    run.check_batch(cfg.batch_size)
    if run.active and cfg.cache_features:
        raise TrainConfigError("train.cache_features: not with torchrun (the cached heads' forward would bypass DDP's "
                               "gradient averaging); train in one process or without the cache")
    if run.active and cfg.image_weight > 0:
        raise TrainConfigError("train.image_weight: not with torchrun (the term is taken on the first pairs of the "
                               "whole batch); train in one process")
    device = run.start(resolve_device(device))
    if not run.main:
        log = _silent

    out = Path(cfg.out)
    ckpt_path = out / "checkpoint.pt"
    if ckpt_path.exists() and not resume:
        raise TrainConfigError(f"{out} already holds a checkpoint: use --resume, or another train.out")
    out.mkdir(parents=True, exist_ok=True)
    # one run per folder at a time (rank 0 holds it under torchrun); a second is refused at once
    with folder_lock(out, "ctxreg train") if run.main else contextlib.nullcontext():
        for path in (ckpt_path, out / "log.csv", out / "loss.png") if run.main else ():  # a killed write's temporaries
            remove_stale_temps(path)
        # the checkpoints are read first: a bad one is refused before any rendering or caching
        resumed = _resume_checkpoint(ckpt_path, cfg) if resume and ckpt_path.exists() else None
        init = _init_checkpoint(cfg) if cfg.init_from and resumed is None else None
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        source = _OnlineSource(cfg, device, log=log) if cfg.online else None if cfg.cache_features else _CampaignSource(cfg)
        model = pose_update_net(backbone=cfg.backbone,
                                weights=Weights.IMAGENET_LOCAL if cfg.weights == "imagenet_local" else Weights.NONE,
                                weights_path=cfg.weights_path, freeze_backbone=cfg.freeze_backbone,
                                head_channels=cfg.head_channels)
        if init is not None:
            _init_weights(model, init)
            log(f"weights from {cfg.init_from}")
        model.to(device)
        if device.type != "cpu":
            log(f"training on {device} ({torch.cuda.get_device_name(device) if device.type == 'cuda' else device})")
        if source is None:  # the cache needs the (frozen) backbone; neither draws random numbers
            source = _CachedSource(cfg, model, rebuild=resumed is None, log=log)
        if cfg.train_backbone_from is not None:
            try:
                model.train_backbone_from(cfg.train_backbone_from)
            except PoseInputError as e:
                raise TrainConfigError(f"train.train_backbone_from: {e}") from None
        optimizer = torch.optim.Adam(_param_groups(model, cfg), lr=cfg.lr)
        scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=cfg.lr_step, gamma=cfg.lr_decay)
        iteration = 0
        if resumed is not None:
            load_weights(model, resumed.model_state, source=f"checkpoint {ckpt_path}")
            try:
                optimizer.load_state_dict(resumed.optimizer)
                scheduler.load_state_dict(resumed.scheduler)
            except (ValueError, KeyError) as e:  # torch's refusal of another optimiser's state
                raise CheckpointError(f"checkpoint {ckpt_path}: its optimiser state does not fit this run ({e})") from None
            iteration = resumed.iteration
            restore_rng(resumed.rng, source=f"checkpoint {ckpt_path}")
            log(f"resumed at iteration {iteration}")
            changed = set()
            for key in RESUME_MAY_CHANGE:
                was = resumed.config.get(key, next(f.default for f in fields(TrainConfig) if f.name == key))
                if _plain(was) != _plain(getattr(cfg, key)):
                    changed.add(key)
                    log(f"train.{key} {was!r} -> {getattr(cfg, key)!r} from here on")
            if changed & {"lr", "lr_step", "lr_decay", "lr_schedule"} and cfg.lr_schedule == "step":
                _follow_schedule(optimizer, scheduler, cfg, iteration)
                log(f"learning rate {optimizer.param_groups[0]['lr']:.3g} at iteration {iteration}")
        precision = step_precision(cfg.precision, device)
        if cfg.precision == "auto":
            log(f"precision auto: {precision} on {device.type} (native bf16: {'yes' if precision == 'bf16' else 'no'})")
        elif precision == "bf16" and not native_bf16(device):
            log(f"warning: train.precision = 'bf16' on a {device.type} without native bf16 (emulated: a step can "
                "take several times fp32's); precision = 'auto' chooses fp32 here")
        log_path = out / "log.csv"
        rows = []
        if resume and log_path.exists():
            with open(log_path) as f:
                rows = [r for r in csv.DictReader(f) if int(r["iteration"]) <= iteration]
        model = run.wrap(model, device)  # DDP under torchrun (after the weights are in place)
        model.train()
        started = time.perf_counter()

        bar = Progress(cfg.iterations, iteration, f"train {out.name}", "iterations", rate_unit="pairs/s",
                       rate_scale=cfg.batch_size, time_limit_s=stop_after_s) if run.main else None
        with _StopOnSignal() as signalled:
            last = _loop(cfg, source, model, optimizer, scheduler, device, iteration, rows, log_path, ckpt_path, bar,
                         started, stop_after_s, signalled, log, precision, run, _elapsed_before(rows))
        if run.main:
            try:
                _plot(rows, out / "loss.png")
            except ImportError as e:  # a bare GPU machine: the log.csv holds the curve
                log(f"loss.png not written: {e}")
        source.close()
        run.finish()
        return last


def _silent(*_args, **_kwargs) -> None:
    """The log of a rank other than 0 under torchrun."""


def _param_groups(model, cfg: TrainConfig) -> list[dict]:
    """Adam's parameter groups: every trained parameter at ``lr``, except the stages of a frozen
    backbone trained again (``train_backbone_from``), at ``lr * backbone_lr_scale``; each group
    records its ``lr_scale``, which every schedule multiplies its rate by. A backbone trained
    whole (not frozen) trains at ``lr`` with the heads: one group."""
    if cfg.train_backbone_from is None:
        return [{"params": [p for p in model.parameters() if p.requires_grad], "lr": cfg.lr, "lr_scale": 1.0}]
    backbone = {id(p) for p in model.backbone.parameters()}
    rest = [p for p in model.parameters() if p.requires_grad and id(p) not in backbone]
    stages = [p for p in model.backbone.parameters() if p.requires_grad]
    return [{"params": rest, "lr": cfg.lr, "lr_scale": 1.0},
            {"params": stages, "lr": cfg.lr * cfg.backbone_lr_scale, "lr_scale": cfg.backbone_lr_scale}]


def _follow_schedule(optimizer, scheduler, cfg: TrainConfig, iteration: int) -> None:
    """After a resume: the step schedule of ``cfg`` (``lr``, ``lr_step``, ``lr_decay``) in place of
    the checkpoint's, its rate at ``iteration`` set on every parameter group (only where the
    schedule changed: the restored state is otherwise bit for bit the checkpoint's)."""
    scheduler.step_size, scheduler.gamma = cfg.lr_step, cfg.lr_decay
    scales = [group.get("lr_scale", 1.0) for group in optimizer.param_groups]
    scheduler.base_lrs = [cfg.lr * k for k in scales]
    rate = cfg.lr * cfg.lr_decay ** (iteration // cfg.lr_step)
    for group, k in zip(optimizer.param_groups, scales):
        group["initial_lr"], group["lr"] = cfg.lr * k, rate * k
    scheduler._last_lr = [rate * k for k in scales]


def scheduled_rate(cfg: TrainConfig, progress: float) -> float:
    """The rate of ``train.lr_schedule = "cosine"`` at ``progress`` (the run's share done, clipped
    to [0, 1]): linear from 0 over the first ``lr_warmup``, then ``lr * (1 + cos(pi * s)) / 2``
    with ``s`` the share of the rest done.

    >>> cfg = TrainConfig(dataset="c.toml", lr=1e-3, lr_schedule="cosine", lr_warmup=0.1)
    >>> [round(scheduled_rate(cfg, p), 6) for p in (0.05, 0.1, 0.55, 1.0)]
    [0.0005, 0.001, 0.0005, 0.0]
    """
    progress = min(max(float(progress), 0.0), 1.0)
    if cfg.lr_warmup > 0 and progress < cfg.lr_warmup:
        return cfg.lr * progress / cfg.lr_warmup
    rest = (progress - cfg.lr_warmup) / (1.0 - cfg.lr_warmup)
    return cfg.lr * 0.5 * (1.0 + math.cos(math.pi * rest))


def _elapsed_before(rows: list[dict]) -> float:
    """Training seconds of the log's rows before a resume (its last ``elapsed_s``; 0 for logs
    written before the column)."""
    try:
        return float(rows[-1].get("elapsed_s") or 0.0) if rows else 0.0
    except ValueError:
        return 0.0


def _loop(cfg, source, model, optimizer, scheduler, device, iteration, rows, log_path, ckpt_path, bar, started,
          stop_after_s, signalled, log, precision: str, run: DistributedRun = DistributedRun(),
          elapsed_before: float = 0.0) -> dict:
    """The training iterations from ``iteration`` to the end, a time limit or a signal, in
    ``precision`` (``fp32`` or ``bf16``, :func:`step_precision`); returns the last log row. Under
    torchrun (``run``) each rank trains on its share of the batch; rank 0 validates, logs and
    writes the checkpoints. The log's ``elapsed_s`` is the run's training seconds (validations
    included, from ``elapsed_before`` on a resume)."""

    last = {}
    start_iteration = iteration
    bf16, skipped = precision == "bf16", 0
    params = [p for group in optimizer.param_groups for p in group["params"]]
    while iteration < cfg.iterations:
        # batches are a function of (seed, iteration) alone, so a resumed run takes the same steps
        *inputs, label = _on(device, run.share(source.train_batch(iteration)))
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            output = source.forward(model, inputs)
        loss = _loss(type(output)(*(t.float() for t in output)), label, cfg)  # the loss in float32
        image = None
        if cfg.image_weight > 0:
            image = source.image_term(iteration, output.g[:cfg.image_pairs].float())
            loss = loss + cfg.image_weight * image
        optimizer.zero_grad()
        loss.backward()
        if cfg.lr_schedule == "cosine":  # the share of the run done: of its seconds under a time limit
            done = ((elapsed_before + time.perf_counter() - started) / (elapsed_before + stop_after_s)
                    if stop_after_s is not None and cfg.cosine_over == "auto" else iteration / cfg.iterations)
            for group in optimizer.param_groups:
                group["lr"] = scheduled_rate(cfg, done) * group.get("lr_scale", 1.0)
        step_rate = optimizer.param_groups[0]["lr"]
        if bf16 and not all(bool(torch.isfinite(p.grad).all()) for p in params if p.grad is not None):
            skipped += 1  # a bfloat16 product overflowed: no step, as a loss scaler does
            if skipped > MAX_SKIPPED_FRACTION * max(iteration + 1 - start_iteration, 100):
                raise TrainConfigError(f"train.precision = 'bf16': {skipped} of the {iteration + 1 - start_iteration} "
                                       f"steps since iteration {start_iteration} had a non-finite gradient; train "
                                       "with precision = 'fp32'")
        else:
            optimizer.step()
        scheduler.step()
        iteration += 1
        if bar is not None:
            bar.update(1)
        last = {"iteration": iteration, "train_loss": float(loss.item()), "lr": step_rate}
        if image is not None:
            last["train_image"] = float(image.item())
        interrupted = run.any(signalled.is_set())  # every rank stops at the same iteration
        stopping = interrupted or run.any(stop_after_s is not None and time.perf_counter() - started >= stop_after_s)
        if not run.main:
            if stopping:
                break
            continue
        if (iteration % cfg.val_every == 0 or iteration == cfg.iterations or stopping) and not interrupted:
            last.update(_validate(unwrap(model), source, cfg, device))
            model.train()
            rate = (iteration - start_iteration) * cfg.batch_size / (time.perf_counter() - started)
            last["elapsed_s"] = round(elapsed_before + time.perf_counter() - started, 2)
            rows.append({k: last.get(k, "") for k in ("iteration", "train_loss", "val_loss", "val_rot_err_deg",
                                                    "val_trans_err_mm", "lr", "elapsed_s")}
                        | ({"train_image": last["train_image"]} if "train_image" in last else {})
                        | {k: v for k, v in last.items() if k.startswith(("val_rot_", "val_trans_"))
                           and k not in ("val_rot_err_deg", "val_trans_err_mm")})
            _write_log(log_path, rows)
            log(f"iteration {iteration}/{cfg.iterations}: train {last['train_loss']:.4f}, "
                f"val {last['val_loss']:.4f}, rotation {last['val_rot_err_deg']:.2f} deg, "
                f"translation {last['val_trans_err_mm']:.1f} mm"
                + (f" (from AP: {last['val_rot_ap_deg']:.2f} deg, {last['val_trans_ap_mm']:.1f} mm)"
                   if "val_rot_ap_deg" in last else "") + f" ({rate:.0f} pairs/s"
                + (f"; {skipped} bf16 steps skipped for a non-finite gradient" if skipped else "") + ")")
        if iteration % cfg.checkpoint_every == 0 or iteration == cfg.iterations or stopping:
            _save_checkpoint(ckpt_path, Checkpoint(
                model_state=unwrap(model).state_dict(), backbone=cfg.backbone, head_channels=cfg.head_channels,
                preprocess=tuple(cfg.preprocess), config=asdict(cfg), image_size=tuple(source.size),
                physics=source.physics, current_physics=getattr(source, "current_physics", source.physics),
                iteration=iteration, optimizer=optimizer.state_dict(), scheduler=scheduler.state_dict(),
                rng=capture_rng()))
        if stopping:
            why = f"by {signalled.name}" if interrupted else f"after {time.perf_counter() - started:.0f} s"
            log(f"stopped {why} at iteration {iteration}, checkpoint written (--resume continues)")
            break
    return last


class _CampaignSource:
    """Pairs of a campaign folder's stored images (:class:`learn.data.PairDataset`), epoch by epoch."""

    def __init__(self, cfg: TrainConfig):
        self.cfg = cfg
        self.data = open_dataset(cfg.dataset)
        transform = build(list(cfg.preprocess))
        self.train_set = PairDataset(self.data, "train", pairs=cfg.pairs_per_epoch, physics=cfg.physics,
                                     transform=transform, seed=cfg.seed)
        val_split = "val" if len(self.data.indices("val")) >= 2 else "test"
        self.val_set = PairDataset(self.data, val_split, pairs=cfg.val_pairs, physics=cfg.physics,
                                   transform=transform, seed=cfg.seed + 1)
        self.per_epoch = math.ceil(cfg.pairs_per_epoch / cfg.batch_size)
        self.epoch, self.order = None, None
        self.size = tuple(self.train_set[0][0].shape[-2:])  # (H, W) pixels
        #: the campaign's physics entry of the images (dict, as in the manifest)
        self.physics = next(p for p in self.data.manifest["config"]["physics"] if p["name"] == self.train_set.physics)

    @staticmethod
    def _stack(batch):
        return tuple(torch.stack([b[i] for b in batch]) for i in range(3))

    @staticmethod
    def forward(model, inputs):
        """``(target, current)`` ``(B, 1, H, W)`` each -> the model's output."""
        return model(*inputs)

    def _train_pairs(self, iteration: int) -> torch.Tensor:
        """This iteration's pair numbers ``(B,)`` into ``train_set`` (set to the iteration's epoch)."""
        cfg = self.cfg
        epoch, step = divmod(iteration, self.per_epoch)
        if epoch != self.epoch:
            self.train_set.set_epoch(epoch)
            self.order = torch.randperm(len(self.train_set), generator=torch.Generator().manual_seed(
                cfg.seed * 1_000_003 + epoch))
            self.epoch = epoch
        return self.order[step * cfg.batch_size:(step + 1) * cfg.batch_size]

    def train_batch(self, iteration: int):
        return self._stack([self.train_set[int(i)] for i in self._train_pairs(iteration)])

    def val_batches(self):
        n, size = len(self.val_set), self.cfg.batch_size
        for start in range(0, n, size):
            yield self._stack([self.val_set[i] for i in range(start, min(start + size, n))])

    def close(self):
        self.data.close()


class _CachedSource(_CampaignSource):
    """The pairs and batches of :class:`_CampaignSource`, as cached backbone maps
    (:class:`learn.features.FeatureCache` in ``<out>/features``): batches are
    ``(level0, level1, level2, label)``, level ``i`` ``(B, 2 C_i, h_i, w_i)`` float32 (target's
    channels first, as ``extract_features``), label ``(B, 6)``."""

    #: Cache files up to this size (bytes) are read into memory once; larger ones row by row.
    IN_MEMORY_MAX_BYTES = 2 * 2**30
    #: Storage dtype of the cache ("float32" trains bit-identically to the uncached run; tests).
    DTYPE = "float16"

    def __init__(self, cfg: TrainConfig, model, *, rebuild: bool, log=print):
        super().__init__(cfg)
        splits = sorted({self.train_set.split, self.val_set.split})
        n = sum(len(self.data.indices(s)) for s in splits)
        in_memory = n * feature_bytes_per_image(cfg.backbone, self.size, self.DTYPE) <= self.IN_MEMORY_MAX_BYTES
        folder = Path(cfg.out) / "features"
        try:
            self.cache = FeatureCache(folder, self.data, model, self.train_set.transform, self.train_set.physics,
                                      splits=splits, dtype=self.DTYPE, rebuild=rebuild, in_memory=in_memory,
                                      log=log)
        except FeatureCacheError as e:
            raise TrainConfigError(f"train.cache_features: {e}") from None
        if not self.cache.built:
            log(f"feature cache {folder / CACHE_FILE}: reused ({len(self.cache)} images)")
        self.poses = torch.from_numpy(np.asarray(self.data.arrays("pose"), dtype=np.float64))  # (N, 4, 4)

    @staticmethod
    def forward(model, inputs):
        """The three levels' maps -> the heads' output."""
        return model.heads_forward(inputs)

    def _batch(self, dataset, pairs: np.ndarray):
        """``pairs`` (B, 2) dataset indices (target, current) -> ``(*maps, label)``, labels as
        :class:`learn.data.PairDataset` computes them."""

        b = len(pairs)
        maps = self.cache.rows(np.concatenate([pairs[:, 0], pairs[:, 1]]))
        labels = torch.stack([dataset.normalizer.normalize(geodesic_label(self.poses[a], self.poses[c]))
                              .to(torch.float32) for a, c in pairs.tolist()])
        return (*(torch.cat((m[:b], m[b:]), dim=1) for m in maps), labels)

    def train_batch(self, iteration: int):
        k = self._train_pairs(iteration).numpy()
        return self._batch(self.train_set, self.train_set.pairs[k])

    def val_batches(self):
        n, size = len(self.val_set), self.cfg.batch_size
        for start in range(0, n, size):
            yield self._batch(self.val_set, self.val_set.pairs[start:min(start + size, n)])

    def close(self):
        self.cache.close()
        super().close()


class _OnlineSource:
    """Pairs rendered on the fly from a campaign file (:class:`learn.online.OnlinePairs`)."""

    def __init__(self, cfg: TrainConfig, device=None, log=None):
        self.cfg = cfg
        try:
            campaign = load_campaign(cfg.dataset)
        except CampaignConfigError as e:
            raise TrainConfigError(f"train.dataset: {e}") from None
        entries = {p.name: p for p in campaign.physics}
        for key in ("physics", "current_physics"):
            name = getattr(cfg, key)
            if name is not None and name not in entries:
                raise TrainConfigError(f"train.{key} = {name!r} is not a [[physics]] entry of {cfg.dataset} "
                                       f"(it has {sorted(entries)})")
        target = entries[cfg.physics] if cfg.physics is not None else campaign.physics[0]
        current = entries[cfg.current_physics] if cfg.current_physics is not None else target
        transform = build(list(cfg.preprocess))
        splits = {s.split for s in campaign.subjects()}
        val_split = "val" if "val" in splits else "test"
        try:
            kw = {"near": cfg.near(), "transform": transform, "physics": target.name, "current_physics": current.name,
                  "randomization": cfg.randomization(), "current_field": cfg.current_field,
                  "tone": cfg.tone}
            if cfg.pairs == "batched":
                del kw["physics"], kw["current_physics"], kw["tone"]
                kw.update(device=device or "cpu", tables=Path(cfg.out) / "tables", framing=cfg.framing, log=log)
                self.train = BatchedPairs(campaign, "train", seed=cfg.seed, subjects_per_batch=cfg.subjects_per_batch,
                                          **kw)
                self.val = BatchedPairs(campaign, val_split, seed=cfg.seed + 1, **kw)
            else:
                self.train = OnlinePairs(campaign, "train", seed=cfg.seed, subjects_per_batch=cfg.subjects_per_batch,
                                         **kw)
                self.val = OnlinePairs(campaign, val_split, seed=cfg.seed + 1, **kw)  # all subjects, every batch
        except OnlinePairsError as e:
            raise TrainConfigError(f"train.dataset {cfg.dataset}: {e}") from None
        self._val = self._val_ap = None
        self._image_term = None
        self.size = tuple(campaign.scene.size)  # (H, W) pixels
        self.physics = target.to_dict()  # the physics entries of the target and current images
        if cfg.randomize is not None:  # each target draws its own: the record is the randomization
            self.physics = {"name": "randomized", "level": "randomized",
                            "randomize": cfg.randomization().to_dict()}
        self.current_physics = current.to_dict()

    forward = staticmethod(_CampaignSource.forward)

    def train_batch(self, iteration: int):
        return self.train.batch(iteration, self.cfg.batch_size)

    def image_term(self, iteration: int, y: torch.Tensor) -> torch.Tensor:
        """The image-space term (``train.image_weight``) of the first ``len(y)`` pairs of batch
        ``iteration``, given the network's normalised outputs ``y`` ``(K, 6)`` for them."""
        if self._image_term is None:
            self._image_term = ImageTerm(self.train.image_volumes(self.cfg.image_size), self.train.normalizer)
        subject, t_a, t_b = self.train.draw(iteration, self.cfg.batch_size)
        k = len(y)
        return self._image_term(subject[:k], t_a[:k], t_b[:k], y)

    def val_batches(self):
        if self._val is None:  # fixed validation pairs, rendered once
            n, size = self.cfg.val_pairs, self.cfg.batch_size
            self._val = [self.val.batch(k, min(size, n - start)) for k, start in enumerate(range(0, n, size))]
        return iter(self._val)

    def val_ap_batches(self):
        """The validation pairs' targets with the current image at the AP start
        (:meth:`learn.batched.BatchedPairs.ap_batch`), rendered once; None for per-pair sources."""
        if not hasattr(self.val, "ap_batch"):
            return None
        if self._val_ap is None:
            n, size = self.cfg.val_pairs, self.cfg.batch_size
            self._val_ap = [self.val.ap_batch(k, min(size, n - start)) for k, start in enumerate(range(0, n, size))]
        return iter(self._val_ap)

    def val_groups(self) -> dict[str, np.ndarray] | None:
        """Each pair group's ``(val_pairs,)`` bool mask over the validation pairs in order (batched
        pairs: :meth:`learn.batched.BatchedPairs.groups`), or None."""
        if not hasattr(self.val, "groups"):
            return None
        n, size = self.cfg.val_pairs, self.cfg.batch_size
        parts = [self.val.groups(k, min(size, n - start)) for k, start in enumerate(range(0, n, size))]
        return {g: np.concatenate([p[g] for p in parts]) for g in parts[0]}

    def close(self):
        pass


def _loss(output, label, cfg: TrainConfig):
    return PoseUpdateNet.loss(output, label, relative_eps=cfg.relative_eps if cfg.loss == "relative" else None)


@torch.no_grad()
def validate_checkpoint(cfg: TrainConfig, checkpoint: str | os.PathLike, *, device: str = "cpu", log=None) -> dict:
    """A checkpoint's weights on ``cfg``'s validation pairs, as training logs them: the row of
    ``log.csv`` (``val_loss``, ``val_rot_err_deg``, ``val_trans_err_mm``, the groups' and the AP
    start's columns) without the training columns. ``cfg`` must draw its pairs online (its
    validation pairs are a function of its config: the same for any checkpoint); the checkpoint's
    backbone and head must be ``cfg``'s. Compares networks on one set of pairs (e.g. two
    randomizations' runs on each other's validation pairs: ``benchmarks/validate_checkpoints.py``).
    ``log``: called with a line where the pairs' tables are built (default: silence)."""

    if not cfg.online:
        raise TrainConfigError("validate_checkpoint: the config must draw its pairs online (train.pairs)")
    path = Path(checkpoint)
    state = _architecture_checkpoint(cfg, path, "validate_checkpoint")
    dev = resolve_device(device)
    model = pose_update_net(backbone=cfg.backbone, weights=Weights.NONE, head_channels=cfg.head_channels)
    load_weights(model, state.model_state, source=f"checkpoint {path}")
    model.to(dev)
    source = _OnlineSource(cfg, dev, log=log)
    try:
        with torch.no_grad():
            return _validate(model, source, cfg, dev)
    finally:
        source.close()


class _NoMotion(torch.nn.Module):
    """A network that predicts no motion (a zero update) for every pair."""

    def forward(self, target: torch.Tensor, current: torch.Tensor) -> PoseUpdateOutput:
        b = target.shape[0]
        return PoseUpdateOutput(g=target.new_zeros(b, 6), g_levels=target.new_zeros(b, 3, 6),
                                weights=target.new_full((b, 3), 1 / 3))


@torch.no_grad()
def validate_no_motion(cfg: TrainConfig, *, device: str = "cpu") -> dict:
    """The level a run must leave: the errors of predicting no motion on ``cfg``'s validation
    pairs, as training logs its rows (``val_rot_err_deg``, ``val_trans_err_mm``, the groups' and
    the AP start's columns; ``val_loss`` of a zero output). ``cfg`` must draw its pairs online."""

    if not cfg.online:
        raise TrainConfigError("validate_no_motion: the config must draw its pairs online (train.pairs)")
    dev = resolve_device(device)
    source = _OnlineSource(cfg, dev)
    try:
        return _validate(_NoMotion(), source, cfg, dev)
    finally:
        source.close()


@torch.no_grad()
def _validate(model, source, cfg: TrainConfig, device=None) -> dict:
    """Validation errors by group; no autograd graph (it kept every validation batch's)."""

    model.eval()

    def predictions(batches):
        losses, preds, trues = [], [], []
        for *inputs, label in batches:
            *inputs, label = _on(device or torch.device("cpu"), (*inputs, label))
            out = source.forward(model, inputs)
            losses.append(float(_loss(out, label, cfg)) * len(label))
            preds.append(out.g)
            trues.append(label)
        return sum(losses) / sum(len(t) for t in trues), torch.cat(preds).cpu(), torch.cat(trues).cpu()

    loss, pred, true = predictions(source.val_batches())
    rot, trans = _errors(pred, true, LabelNormalizer())
    row = {"val_loss": loss, "val_rot_err_deg": rot, "val_trans_err_mm": trans}
    groups = source.val_groups() if hasattr(source, "val_groups") else None
    for name, mask in (groups or {}).items():  # the learning curve by pair kind, field and display
        m = torch.from_numpy(np.asarray(mask, bool))
        rot, trans = _errors(pred[m], true[m], LabelNormalizer()) if m.any() else (float("nan"), float("nan"))
        row[f"val_rot_{name}_deg"], row[f"val_trans_{name}_mm"] = rot, trans
    ap = source.val_ap_batches() if hasattr(source, "val_ap_batches") else None
    if ap is not None:  # the same targets from the AP start: registration's first pairs (not in "all")
        _, pred, true = predictions(ap)
        row["val_rot_ap_deg"], row["val_trans_ap_mm"] = _errors(pred, true, LabelNormalizer())
    return row


def _write_log(path: Path, rows: list[dict]) -> None:
    """The log rows as CSV; columns: every key of any row (a group column appears once batched
    pairs log it; earlier rows leave it empty)."""

    keys = list(dict.fromkeys(k for r in rows for k in r))
    write_csv(path, [{k: r.get(k, "") for k in keys} for r in rows])


def _plot(rows: list[dict], path: Path) -> None:
    if not rows:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    it = [int(r["iteration"]) for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(it, [float(r["train_loss"]) for r in rows], label="train")
    ax.plot(it, [float(r["val_loss"]) for r in rows], label="validation")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.legend()
    save_figure(fig, path)
