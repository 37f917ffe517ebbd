"""Learning labels of the contextual pose-update network (PyTorch; NumPy accepted where noted).

Poses are CT-volume poses ``T = (R, t)``, ``(..., 4, 4)``, with ``X_cam = R (X_lps - c) + t``
(``docs/conventions.md``). For an image pair of one CT, *target* ``A`` (pose ``T_A``) and
*current* ``B`` (pose ``T_B``), the label is the Riemannian gradient at ``T_B`` of the squared
product-metric distance ``d^2(T, T_A)`` on SO(3) x R^3 with ``lambda = 1`` (rad and mm as they
are), in the body coordinates of ``T = product_exp(T_B, eps)``:

``g = -2 log_{T_B}(T_A) = -2 product_log(T_B, T_A)``, ``(..., 6)``:

* ``g[..., :3]`` = ``-2 so3_log(R_B^T R_A)``, **rad** (rotation vector about the patient's L, P, S),
* ``g[..., 3:]`` = ``-2 R_B^T (t_A - t_B)``, **mm** (along L, P, S).

Sign: ``g`` points *uphill* (away from ``T_A``); ``-g`` is the descent direction, so the
registration update is ``T <- product_exp(T, -step * g)`` (:func:`apply_update`). Because the
gradient of ``d^2`` is ``-2 log``, a step of ``0.5`` lands exactly on ``T_A``; the method's default
``step = 0.15`` moves 30 % of the way along the geodesic.

The network regresses ``y = normalize(g)`` (unit-free, :class:`LabelNormalizer`).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from sim.core.errors import InputError
from sim.projection.se3 import product_exp, product_log

__all__ = [
    "LearnLabelError",
    "DEFAULT_ROT_SCALE_RAD",
    "DEFAULT_TRANS_SCALE_MM",
    "DEFAULT_STEP",
    "geodesic_label",
    "apply_update",
    "label_scale",
    "LabelNormalizer",
    "sample_pairs",
]

#: Rotation scale of the normalised label, rad: ``2 * 40`` degrees. The original protocol
#: draws each rotation angle uniformly in +-40 deg, so two poses differ by up to 80 deg per
#: axis; ``|log|`` is of that order and the label ``-2 log`` maps to ``|y|`` of order 1-2.
DEFAULT_ROT_SCALE_RAD = math.radians(2.0 * 40.0)

#: Translation scale of the normalised label, mm: ``2 * 75`` mm (translations uniform in
#: +-75 mm per axis in the original protocol, so differences up to 150 mm per axis).
DEFAULT_TRANS_SCALE_MM = 2.0 * 75.0

#: Default update step of the registration, ``T <- product_exp(T, -DEFAULT_STEP * g)``.
DEFAULT_STEP = 0.15


class LearnLabelError(InputError):
    """An input to :mod:`learn.labels` cannot be used; the message names it and the problem."""


def _check_pose(T: Any, name: str) -> Any:
    if not (isinstance(T, (torch.Tensor, np.ndarray))):
        raise LearnLabelError(f"{name}: expected a torch tensor or numpy array, got {type(T).__name__}")
    if T.ndim < 2 or tuple(T.shape[-2:]) != (4, 4):
        raise LearnLabelError(f"{name}: expected shape (..., 4, 4), got {tuple(T.shape)}")
    return T


def geodesic_label(T_a: Any, T_b: Any) -> Any:
    """Label ``g = -2 product_log(T_b, T_a)``: ``(..., 4, 4), (..., 4, 4) -> (..., 6)``.

    ``T_a`` is the target pose, ``T_b`` the current pose (both CT-volume poses, translations in
    mm). ``g = (g_rot rad, g_trans mm)``, rotation first, in ``T_b``'s body (LPS) coordinates;
    it is the gradient of ``d^2(T, T_a)`` (product metric, ``lambda = 1``) at ``T = T_b``, so it
    points away from ``T_a`` (descend along ``-g``). Torch float32/float64 (or NumPy) in, same
    kind and promoted dtype out; leading dimensions broadcast.
    """
    _check_pose(T_a, "T_a")
    _check_pose(T_b, "T_b")
    return -2.0 * product_log(T_b, T_a)


def apply_update(T_b: Any, g: Any, step: float = DEFAULT_STEP) -> Any:
    """Registration update ``product_exp(T_b, -step * g)``: ``(..., 4, 4), (..., 6) -> (..., 4, 4)``.

    ``g`` is a (de-normalised) label ``(rad, mm)``; moving along ``-g`` decreases the distance to
    the target. With ``g = geodesic_label(T_a, T_b)`` and ``step = 0.5`` the result is exactly
    ``T_a`` (``-0.5 g = product_log(T_b, T_a)``). ``step`` is unit-free, ``> 0``.
    """
    _check_pose(T_b, "T_b")
    if not isinstance(g, (torch.Tensor, np.ndarray)) or g.ndim < 1 or g.shape[-1] != 6:
        shape = tuple(g.shape) if hasattr(g, "shape") else type(g).__name__
        raise LearnLabelError(f"g: expected shape (..., 6) (rad, mm), got {shape}")
    if not (isinstance(step, numbers.Real) and math.isfinite(step) and step > 0):
        raise LearnLabelError(f"step: expected a finite number > 0, got {step!r}")
    return product_exp(T_b, -float(step) * g)


def _check_scale(value: Any, name: str) -> float:
    if not (isinstance(value, numbers.Real) and math.isfinite(value) and value > 0):
        raise LearnLabelError(f"{name}: expected a finite number > 0, got {value!r}")
    return float(value)


def label_scale(
    rot_scale_rad: float = DEFAULT_ROT_SCALE_RAD,
    trans_scale_mm: float = DEFAULT_TRANS_SCALE_MM,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Per-component label scale ``(6,)``: 3 x ``rot_scale_rad`` (rad), 3 x ``trans_scale_mm`` (mm).

    Defaults :data:`DEFAULT_ROT_SCALE_RAD` (80 deg in rad) and :data:`DEFAULT_TRANS_SCALE_MM`
    (150 mm). ``y = g / label_scale()`` is the unit-free network target.
    """
    r = _check_scale(rot_scale_rad, "rot_scale_rad")
    s = _check_scale(trans_scale_mm, "trans_scale_mm")
    return torch.tensor([r, r, r, s, s, s], dtype=dtype, device=device)


@dataclass(frozen=True)
class LabelNormalizer:
    """Maps labels ``g (..., 6)`` (rad, mm) to unit-free targets ``y = g / scale`` and back.

    ``rot_scale_rad`` (rad) divides the three rotation components, ``trans_scale_mm`` (mm) the
    three translation components. ``denormalize(normalize(g)) == g`` to rounding (one
    division and one multiplication: at most about 1 ulp per component); exactly when the scales
    are powers of two.
    """

    rot_scale_rad: float = DEFAULT_ROT_SCALE_RAD
    trans_scale_mm: float = DEFAULT_TRANS_SCALE_MM

    def __post_init__(self) -> None:
        object.__setattr__(self, "rot_scale_rad", _check_scale(self.rot_scale_rad, "rot_scale_rad"))
        object.__setattr__(
            self, "trans_scale_mm", _check_scale(self.trans_scale_mm, "trans_scale_mm")
        )

    def _scale_like(self, x: torch.Tensor, name: str) -> torch.Tensor:
        if not isinstance(x, torch.Tensor) or x.ndim < 1 or x.shape[-1] != 6:
            shape = tuple(x.shape) if hasattr(x, "shape") else type(x).__name__
            raise LearnLabelError(f"{name}: expected a torch tensor of shape (..., 6), got {shape}")
        if not torch.is_floating_point(x):
            raise LearnLabelError(f"{name}: expected a floating tensor, got {x.dtype}")
        return label_scale(self.rot_scale_rad, self.trans_scale_mm, dtype=x.dtype, device=x.device)

    def normalize(self, g: torch.Tensor) -> torch.Tensor:
        """Label ``g (..., 6)`` (rad, mm) -> unit-free target ``y (..., 6)``."""
        return g / self._scale_like(g, "g")

    def denormalize(self, y: torch.Tensor) -> torch.Tensor:
        """Unit-free network output ``y (..., 6)`` -> label ``g (..., 6)`` (rad, mm)."""
        return y * self._scale_like(y, "y")

    def to_dict(self) -> dict[str, float]:
        """JSON-serialisable record of the scales."""
        return {"rot_scale_rad": self.rot_scale_rad, "trans_scale_mm": self.trans_scale_mm}


def sample_pairs(
    n_images: int,
    n_pairs: int,
    rng: np.random.Generator,
    *,
    groups: np.ndarray | None = None,
) -> np.ndarray:
    """Random (target, current) index pairs from the same subject: ``(n_pairs, 2)`` int64.

    ``groups`` ``(n_images,)`` holds a subject id per image (``None``: all one subject). The
    target ``i`` is uniform over all images; the current ``j`` is uniform over the other images
    of ``i``'s subject, so ``i != j`` unless that subject has a single image (then ``j = i``,
    a zero label). Deterministic for a given ``rng`` state.
    """
    if isinstance(n_images, bool) or not isinstance(n_images, numbers.Integral) or n_images < 1:
        raise LearnLabelError(f"n_images: expected an integer >= 1, got {n_images!r}")
    if isinstance(n_pairs, bool) or not isinstance(n_pairs, numbers.Integral) or n_pairs < 0:
        raise LearnLabelError(f"n_pairs: expected an integer >= 0, got {n_pairs!r}")
    if not isinstance(rng, np.random.Generator):
        raise LearnLabelError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
    if groups is None:
        groups_arr = np.zeros(n_images, dtype=np.int64)
    else:
        groups_arr = np.asarray(groups)
        if groups_arr.shape != (n_images,):
            raise LearnLabelError(
                f"groups: expected shape (n_images,) = ({n_images},), got {groups_arr.shape}"
            )
    # Members of each subject, in index order: order[start[u] : start[u] + size[u]].
    _, inverse, counts = np.unique(groups_arr, return_inverse=True, return_counts=True)
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    position = np.empty(n_images, dtype=np.int64)
    position[order] = np.arange(n_images) - starts[inverse[order]]

    i = rng.integers(0, n_images, size=int(n_pairs))
    u = inverse[i]
    size = counts[u]
    # Offset uniform in [1, size - 1] (0 for single-image subjects), then wrap within the subject.
    offset = np.where(size > 1, 1 + np.floor(rng.random(len(i)) * np.maximum(size - 1, 1)), 0)
    offset = np.minimum(offset.astype(np.int64), np.maximum(size - 1, 0))
    j = order[starts[u] + (position[i] + offset) % size]
    return np.stack([i, j], axis=1).astype(np.int64)
