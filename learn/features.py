"""Per-image backbone features and their on-disk cache, for training the heads of a frozen backbone.

The backbone of :class:`learn.model.PoseUpdateNet` is Siamese: ``extract_features(target, current)``
runs the SAME ``DenseNet.features`` module on both images (as one batch of ``2 B``, see
:class:`learn.model.FeatureExtractor`) and concatenates each level's maps along channels, target
first. With the backbone frozen (eval-mode batch norm, no gradients) an image's maps therefore do
not depend on the image it is paired with, so they can be computed once per image
(:func:`image_features`) and every pair's input assembled from two stored images::

    torch.cat([f_target[i], f_current[i]], dim=1) == model.extract_features(target, current)[i]

:class:`FeatureCache` computes the maps of every image of a campaign folder's splits once and
stores them in ``<folder>/features.h5``; training then costs only the heads
(``TrainConfig.cache_features``, :mod:`learn.train`).

File ``features.h5`` (written atomically, :func:`sim.core.atomic.atomic_path`):

=====================  =============================  ==============================================
dataset                shape, dtype                   meaning
=====================  =============================  ==============================================
``index``              (n,) int64, increasing         campaign dataset index of each row
``level0``             (n, C_0, H/8, W/8) float16     ``denseblock2`` output of row's image
``level1``             (n, C_1, H/16, W/16) float16   ``denseblock3`` output
``level2``             (n, C_2, H/32, W/32) float16   ``norm5`` output
=====================  =============================  ==============================================

(float32 with ``dtype="float32"``). Attributes: ``format``, ``format_version``, ``key`` (SHA-256
of the key components), one ``key_<name>`` per component (:data:`KEY_COMPONENTS`: the backbone
kind and SHA-256 of its state dict's tensors, the campaign's ``config_hash`` and shard checksums,
the preprocessing record, the physics name, the storage dtype), ``splits`` (JSON list),
``image_size`` (H, W) in pixels.

Memory and disk per image (per pair of a training step twice this is read; float16, float32 in
parentheses; sum over the three levels of ``C_i * (H / s_i) * (W / s_i)`` values, channels
``C_i`` from :func:`learn.model._tap_channels`, strides ``s_i`` 8, 16, 32 pixels):

===============  ====================  ========================  =========================
backbone         channels C_0..C_2     128 x 128 px              64 x 64 px
===============  ====================  ========================  =========================
densenet161      768, 2112, 2208       734,208 B (1,468,416 B)   183,552 B (367,104 B)
densenet121      512, 1024, 1024       425,984 B (851,968 B)     106,496 B (212,992 B)
tiny             32, 32, 32            21,504 B (43,008 B)       5,376 B (10,752 B)
===============  ====================  ========================  =========================

So 10,000 images of 128 x 128 px with DenseNet-161 take about 7.3 GB as float16 (14.7 GB as
float32); :func:`feature_bytes_per_image` computes the number for other sizes. Rows are read
from the file on demand (one HDF5 chunk per image) unless ``in_memory=True``.

float16 keeps about 3 significant digits (relative rounding error <= 2^-11 ~ 4.9e-4, range
+-65504; the DenseNet maps after batch norm and ReLU are far inside it): heads trained on a
float16 cache follow the uncached run closely but not bit for bit; a float32 cache gives
bit-identical training (tested).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from learn.model import (
    MIN_INPUT_SIZE,
    NUM_LEVELS,
    Backbone,
    PoseInputError,
    PoseUpdateNet,
    _tap_channels,
)
from sim.core.errors import InputError
from sim.core.atomic import atomic_path

__all__ = [
    "CACHE_FILE",
    "FeatureCache",
    "FeatureCacheError",
    "KEY_COMPONENTS",
    "backbone_digest",
    "dataset_digest",
    "feature_bytes_per_image",
    "image_features",
]

#: The cache file's name inside the cache folder.
CACHE_FILE = "features.h5"
FORMAT = "ctxreg-features"
FORMAT_VERSION = 1
#: What a cache is valid for; each is stored as attribute ``key_<name>``.
KEY_COMPONENTS: tuple[str, ...] = ("backbone", "dataset", "preprocess", "physics", "dtype")
_DTYPES = {"float16": np.float16, "float32": np.float32}
_STRIDES = (8, 16, 32)  # pixels, of the three tapped maps (FeatureExtractor.tap_names)


class FeatureCacheError(InputError):
    """A feature cache cannot be built, opened or read; the message names the file and what differs."""


# --------------------------------------------------------------------------------------------
# Per-image features
# --------------------------------------------------------------------------------------------


def image_features(model: PoseUpdateNet, images: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The backbone's three tapped maps of single images: ``(N, 1, H, W) -> (N, C_i, h_i, w_i)``.

    ``C_i`` are ``model.backbone.channels`` (per image), ``h_i = H / 8, H / 16, H / 32`` (rounded
    as the DenseNet rounds). With the backbone in eval mode (a frozen backbone always is),
    ``torch.cat([image_features(model, t)[i], image_features(model, c)[i]], dim=1)`` equals
    ``model.extract_features(t, c)[i]``; in training mode batch norm uses the batch's statistics
    and the two differ. Gradients flow as usual (wrap the call in ``torch.no_grad()`` to cache).

    Raises:
        PoseInputError: ``images`` is not a finite floating-point ``(N, 1, H, W)`` tensor with
            ``N >= 1`` and ``H, W >= 32``.
    """
    if not isinstance(images, Tensor):
        raise PoseInputError(f"images must be a torch.Tensor, got {type(images).__name__}")
    if images.ndim != 4 or images.shape[1] != 1 or images.shape[0] < 1:
        raise PoseInputError(f"images must be (N >= 1, 1, H, W), got shape {tuple(images.shape)}")
    if not images.is_floating_point():
        raise PoseInputError(f"images must be floating point, got dtype {images.dtype}")
    if min(images.shape[-2:]) < MIN_INPUT_SIZE:
        raise PoseInputError(
            f"images must be at least {MIN_INPUT_SIZE} x {MIN_INPUT_SIZE} pixels, got {tuple(images.shape[-2:])}"
        )
    bad = int((~torch.isfinite(images)).sum())
    if bad:
        raise PoseInputError(f"images have {bad} NaN or infinite pixels")
    x = images
    taps = []
    for name, module in model.backbone.features.named_children():  # as FeatureExtractor.forward
        x = module(x)
        if name in model.backbone.tap_names:
            taps.append(x)
    return tuple(taps)  # type: ignore[return-value]


def feature_bytes_per_image(backbone: Backbone | str, size: tuple[int, int], dtype: str = "float16") -> int:
    """Bytes of one image's three cached maps: ``sum_i C_i * (H // s_i) * (W // s_i) * itemsize``.

    ``size`` (H, W) in pixels; exact when H and W are multiples of 32 (else a close estimate)."""
    if dtype not in _DTYPES:
        raise FeatureCacheError(f"dtype must be one of {sorted(_DTYPES)}, got {dtype!r}")
    channels = _tap_channels(Backbone(backbone))
    h, w = size
    values = sum(c * max(h // s, 1) * max(w // s, 1) for c, s in zip(channels, _STRIDES))
    return values * np.dtype(_DTYPES[dtype]).itemsize


# --------------------------------------------------------------------------------------------
# Cache keys
# --------------------------------------------------------------------------------------------


def backbone_digest(model: PoseUpdateNet) -> str:
    """SHA-256 (hex) over the backbone's state dict: every entry's name, dtype, shape and bytes,
    in name order (weights and batch-norm running statistics)."""
    h = hashlib.sha256()
    for name, t in sorted(model.backbone.state_dict().items()):
        t = t.detach().to("cpu").contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def dataset_digest(data) -> str:
    """SHA-256 (hex) over a campaign's ``config_hash`` and its shards' names and SHA-256 sums
    (from ``data.manifest``, :mod:`sim.campaign.dataset`): the images' identity."""
    manifest = data.manifest
    shards = sorted((name, info["sha256"]) for name, info in manifest["shards"].items())
    text = json.dumps({"config_hash": manifest["config_hash"], "shards": shards}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def _transform_record(transform) -> list:
    if transform is None:
        return []
    if hasattr(transform, "record"):
        return transform.record()
    if hasattr(transform, "to_dict"):
        return [transform.to_dict()]
    raise FeatureCacheError(
        f"transform must be a learn.preprocess step or Compose (it is recorded in the cache key), "
        f"got {type(transform).__name__}"
    )


def _check_deterministic(record: list) -> None:
    random = [step["name"] for step in record if step.get("name") == "random_convolution" and step.get("p", 0) > 0]
    if random:
        raise FeatureCacheError(
            "the preprocessing has the random step 'random_convolution' (a new draw per pair): "
            "its images cannot be cached; drop the step or train without a feature cache"
        )


# --------------------------------------------------------------------------------------------
# The cache
# --------------------------------------------------------------------------------------------


class FeatureCache:
    """Backbone maps of every image of some splits of a campaign folder, stored once on disk.

    Opening checks the stored key against ``(model, data, transform, physics, dtype)``: when it
    matches (and the stored splits include ``splits``) the file is used as it is, nothing is
    computed (``built`` is False). When there is no file it is computed and written (``built``
    is True). When the key differs it is recomputed with ``rebuild=True``, else
    :class:`FeatureCacheError` names the components that differ.

    Args:
        folder: the cache folder; the file is ``folder / "features.h5"``.
        data: an open campaign dataset (:func:`sim.campaign.open_dataset`).
        model: the network; its backbone must be frozen (:meth:`PoseUpdateNet.freeze_backbone`).
            The maps are computed on the backbone's device, in batches of ``batch_size`` images.
        transform: the preprocessing of the images (:func:`learn.preprocess.build`), applied per
            image ``(N, 1, H, W)`` before the backbone, as :class:`learn.data.PairDataset` applies
            it per pair; it must not be random (``random_convolution``).
        physics: the ``images/<physics>`` to use (default: the campaign's first).
        splits: which splits' images to store.
        dtype: ``"float16"`` (default, half the disk) or ``"float32"`` (bit-exact).
        rebuild: recompute a cache whose key differs instead of refusing it.
        in_memory: read the whole file into memory once (at the storage dtype) instead of reading
            rows on demand.
        log: progress messages (every 10 % of the images while computing).

    Raises:
        FeatureCacheError: unfrozen backbone, unknown physics or split, random preprocessing, a
            different key without ``rebuild``, an unreadable file.
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        data,
        model: PoseUpdateNet,
        transform=None,
        physics: str | None = None,
        *,
        splits: Sequence[str] = ("train",),
        dtype: str = "float16",
        rebuild: bool = False,
        batch_size: int = 32,
        in_memory: bool = False,
        log: Callable[[str], object] = print,
    ) -> None:
        if dtype not in _DTYPES:
            raise FeatureCacheError(f"dtype must be one of {sorted(_DTYPES)}, got {dtype!r}")
        if not isinstance(batch_size, int) or batch_size < 1:
            raise FeatureCacheError(f"batch_size must be a positive integer, got {batch_size!r}")
        if not model.backbone_frozen:
            raise FeatureCacheError("the backbone is not frozen (call model.freeze_backbone()): "
                                    "its features change while it trains and cannot be cached")
        physics = physics or data.physics[0]
        if physics not in data.physics:
            raise FeatureCacheError(f"physics {physics!r} is not in the campaign {data.folder} (it has {data.physics})")
        splits = sorted(set(splits))
        unknown = [s for s in splits if s not in data.splits]
        if unknown:
            raise FeatureCacheError(f"split(s) {unknown} not in the campaign {data.folder} "
                                    f"(it has {sorted(data.splits)})")
        record = _transform_record(transform)
        _check_deterministic(record)

        self.path = Path(folder) / CACHE_FILE
        self.dtype = dtype
        self.splits = splits
        self.components: dict[str, str] = {
            "backbone": f"{model.backbone_kind.value} sha256:{backbone_digest(model)}",
            "dataset": f"sha256:{dataset_digest(data)}",
            "preprocess": json.dumps(record, sort_keys=True),
            "physics": physics,
            "dtype": dtype,
        }
        self.key = hashlib.sha256(json.dumps(self.components, sort_keys=True).encode()).hexdigest()
        self.built = False
        self._file = None

        differs = self._differences() if self.path.exists() else None
        if differs is None or (differs and rebuild):
            if differs:
                log(f"feature cache {self.path}: rebuilding ({'; '.join(differs)})")
            self._build(data, model, transform, physics, batch_size, log)
            self.built = True
        elif differs:
            raise FeatureCacheError(
                f"feature cache {self.path} was built for other inputs: {'; '.join(differs)}. "
                "Delete the file (or the folder) to rebuild it, or pass rebuild=True"
            )
        self._open(in_memory)

    # -- opening and building ------------------------------------------------------------------

    def _differences(self) -> list[str]:
        """What differs between the stored key and this one (empty when it matches)."""
        import h5py

        try:
            with h5py.File(self.path, "r") as f:
                attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        except OSError as e:
            return [f"the file cannot be read ({e})"]
        if attrs.get("format") != FORMAT or attrs.get("format_version") != FORMAT_VERSION:
            return [f"format {attrs.get('format')!r} version {attrs.get('format_version')!r} "
                    f"(expected {FORMAT!r} version {FORMAT_VERSION})"]
        out = []
        for name in KEY_COMPONENTS:
            stored = str(attrs.get(f"key_{name}"))
            if stored != self.components[name]:
                out.append(f"{name}: stored {_short(stored)} vs now {_short(self.components[name])}")
        stored_splits = json.loads(attrs.get("splits", "[]"))
        missing = [s for s in self.splits if s not in stored_splits]
        if missing:
            out.append(f"splits: stored {stored_splits}, {missing} missing")
        return out

    def _build(self, data, model: PoseUpdateNet, transform, physics: str, batch_size: int, log) -> None:
        import h5py

        for stale in self.path.parent.glob(f".{CACHE_FILE}.*.tmp*"):  # left by a killed build
            stale.unlink(missing_ok=True)
        indices = np.unique(np.concatenate([np.asarray(data.indices(s), dtype=np.int64) for s in self.splits]))
        n = len(indices)
        device = next(model.backbone.parameters()).device
        store = _DTYPES[self.dtype]
        log(f"feature cache {self.path}: computing the {model.backbone_kind.value} features of {n} images "
            f"(splits {', '.join(self.splits)}, {self.dtype})")
        started = time.perf_counter()
        next_report = 0.1
        with atomic_path(self.path) as tmp, h5py.File(tmp, "w") as f:
            for name, value in self.components.items():
                f.attrs[f"key_{name}"] = value
            f.attrs["key"] = self.key
            f.attrs["format"] = FORMAT
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["splits"] = json.dumps(self.splits)
            f.create_dataset("index", data=indices)
            levels = None
            for start in range(0, n, batch_size):
                chunk = indices[start:start + batch_size]
                images = torch.from_numpy(np.stack([data[int(i)]["images"][physics] for i in chunk])
                                          .astype(np.float32))[:, None]  # (n, 1, H, W), as PairDataset
                if transform is not None:
                    images = transform(images)
                with torch.no_grad():
                    maps = image_features(model, images.to(device))
                if levels is None:
                    f.attrs["image_size"] = list(images.shape[-2:])
                    levels = [f.create_dataset(f"level{k}", shape=(n, *m.shape[1:]), dtype=store,
                                               chunks=(1, *m.shape[1:])) for k, m in enumerate(maps)]
                for ds, m in zip(levels, maps):
                    ds[start:start + len(chunk)] = m.to("cpu").numpy().astype(store)
                done = start + len(chunk)
                if done / n >= next_report or done == n:
                    log(f"feature cache: {done}/{n} images ({100 * done / n:.0f}%), "
                        f"{time.perf_counter() - started:.1f} s")
                    next_report = math.floor(done / n * 10 + 1) / 10
        size = self.path.stat().st_size
        log(f"feature cache {self.path}: {n} images, {size / 2**20:.1f} MiB, {time.perf_counter() - started:.1f} s")

    def _open(self, in_memory: bool) -> None:
        import h5py

        try:
            self._file = h5py.File(self.path, "r")
            self.index = np.asarray(self._file["index"], dtype=np.int64)
            self._levels = [self._file[f"level{k}"] for k in range(NUM_LEVELS)]
            self.image_size = tuple(int(v) for v in self._file.attrs["image_size"])  # (H, W) pixels
        except (OSError, KeyError) as e:
            self.close()
            raise FeatureCacheError(f"feature cache {self.path} cannot be read ({e}); delete it to rebuild") from None
        self._memory = [torch.from_numpy(ds[()]) for ds in self._levels] if in_memory else None

    # -- reading ---------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.index)

    @property
    def shapes(self) -> list[tuple[int, ...]]:
        """Per level ``(C_i, h_i, w_i)`` of one image."""
        return [tuple(ds.shape[1:]) for ds in self._levels]

    def rows(self, indices: Iterable[int] | np.ndarray | Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Campaign dataset indices ``(n,)`` (any order, repeats allowed) -> the three levels'
        maps ``(n, C_i, h_i, w_i)`` float32, row ``j`` the image ``indices[j]``'s.

        Raises:
            FeatureCacheError: an index is not in the cache (another split).
        """
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        pos = np.searchsorted(self.index, idx)
        ok = (pos < len(self.index)) & (self.index[np.minimum(pos, len(self.index) - 1)] == idx)
        if not ok.all():
            raise FeatureCacheError(f"feature cache {self.path} has no rows for dataset images "
                                    f"{idx[~ok][:5].tolist()} (it holds splits {self.splits})")
        unique, inverse = np.unique(pos, return_inverse=True)
        out = []
        for k in range(NUM_LEVELS):
            if self._memory is not None:
                block = self._memory[k][torch.from_numpy(unique)]
            else:
                block = torch.from_numpy(self._levels[k][unique])  # h5py: increasing rows
            out.append(block[torch.from_numpy(inverse)].to(torch.float32))
        return tuple(out)  # type: ignore[return-value]

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> FeatureCache:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _short(text: str, limit: int = 120) -> str:
    return repr(text if len(text) <= limit else text[:limit] + "...")
