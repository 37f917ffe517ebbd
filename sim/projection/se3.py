"""SE(3) utilities shared by all ctxreg packages: batched, for NumPy arrays and torch tensors.

Every function accepts NumPy arrays (float32 or float64; integer input is promoted to float64)
or torch tensors (float32 or float64, any device) and returns the same kind and dtype. Torch is
imported only when a torch tensor is passed, so NumPy-only code never pays for it. All functions
broadcast over any leading dimensions ``...``.

Units and conventions (see ``docs/conventions.md``):

* Rotations in **radians** inside this module (public geometry interfaces use degrees; convert
  there), translations in **mm**.
* A transform ``T`` is a ``(..., 4, 4)`` homogeneous matrix ``[[R, t], [0, 0, 0, 1]]`` acting on
  column vectors: ``y = R x + t``.
* A twist ``xi`` is ``(..., 6)`` = ``(omega, v)``: **rotation first**, ``omega`` in rad (axis times
  angle), ``v`` in mm. ``se3_exp`` is the true SE(3) exponential (``t = V(omega) v``), whereas
  ``product_exp`` / ``product_log`` use the product manifold SO(3) x R^3 (``t`` moves straight).
* The product metric on SO(3) x R^3 with scale ``lambda`` (mm per rad) has squared distance
  ``d^2 = lambda^2 theta^2 + |t_a - t_b|^2``, ``theta`` the geodesic rotation angle in rad.

Errors: wrong trailing shapes raise :class:`SE3ShapeError`, NaN or infinite values raise
:class:`SE3NonFiniteError`; both are :class:`SE3InputError`, a ``ValueError``. (The finiteness
check reads one boolean back from the device for torch tensors.)
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np

from sim.core.errors import InputError

__all__ = [
    "DEFAULT_MM_PER_RAD",
    "SE3InputError",
    "SE3ShapeError",
    "SE3NonFiniteError",
    "so3_hat",
    "so3_vee",
    "so3_exp",
    "so3_log",
    "rotation_angle",
    "se3_exp",
    "se3_log",
    "se3_inverse",
    "se3_compose",
    "make_transform",
    "split",
    "product_log",
    "product_exp",
    "geodesic_distance",
    "rotation_error_deg",
    "translation_error_mm",
]

#: Default scale ``lambda`` of the product metric, in mm per rad: a rotation by ``theta`` rad
#: moves a point at 100 mm from the rotation centre (the order of an anatomy's half size, e.g. a
#: pelvis or a few vertebrae) by about ``100 * theta`` mm, so 1 degree counts about 1.75 mm.
DEFAULT_MM_PER_RAD = 100.0

#: Below this angle (rad) the closed forms switch to Taylor series (0/0 at zero, and torch
#: gradients must stay finite). The series used are accurate to far below float64 precision
#: there, and the closed forms lose at most about one ulp of absolute accuracy above it.
_SMALL_ANGLE = 1e-2

Array = Any  # numpy.ndarray or torch.Tensor


class SE3InputError(InputError):
    """An input to :mod:`sim.projection.se3` cannot be used; the message names the input and the problem."""


class SE3ShapeError(SE3InputError):
    """An input has the wrong trailing shape; the message names the expected shape."""


class SE3NonFiniteError(SE3InputError):
    """An input contains NaN or infinite values."""


# --------------------------------------------------------------------------------------------
# Array-namespace helpers: one implementation for numpy and torch.
# --------------------------------------------------------------------------------------------


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _xp(x: Array):
    """The array namespace of ``x``: ``torch`` for torch tensors, ``numpy`` otherwise."""
    if _is_torch(x):
        import torch

        return torch
    return np


def _stack(xs: list, axis: int) -> Array:
    return _xp(xs[0]).stack(xs, axis)


def _cat(xs: list, axis: int) -> Array:
    return _xp(xs[0]).concatenate(xs, axis)


def _eye3(like: Array) -> Array:
    if _is_torch(like):
        import torch

        return torch.eye(3, dtype=like.dtype, device=like.device)
    return np.eye(3, dtype=like.dtype)


def _const(values: list, like: Array) -> Array:
    if _is_torch(like):
        import torch

        return torch.tensor(values, dtype=like.dtype, device=like.device)
    return np.asarray(values, dtype=like.dtype)


def _mT(x: Array) -> Array:
    """Transpose of the last two axes."""
    return x.swapaxes(-1, -2)


def _safe_sqrt(sq: Array) -> Array:
    """``sqrt(sq)`` for ``sq >= 0`` whose torch gradient is 0 (not NaN/inf) where ``sq == 0``."""
    xp = _xp(sq)
    pos = sq > 0
    return xp.where(pos, xp.sqrt(xp.where(pos, sq, 1.0)), 0.0)


def _check(x: Any, name: str, trailing: tuple[int, ...]) -> Array:
    """Convert ``x`` to a float array/tensor and check its trailing shape and finiteness."""
    if _is_torch(x):
        import torch

        if not torch.is_floating_point(x):
            x = x.to(torch.get_default_dtype())
        elif x.dtype not in (torch.float32, torch.float64):
            x = x.to(torch.float32)  # half precision is too coarse for these formulas
        finite = bool(torch.isfinite(x).all())
    else:
        x = np.asarray(x)
        if x.dtype not in (np.float32, np.float64):
            if not (np.issubdtype(x.dtype, np.integer) or np.issubdtype(x.dtype, np.floating)):
                raise SE3InputError(f"{name}: expected a real numeric array, got dtype {x.dtype}")
            x = x.astype(np.float64)
        finite = bool(np.all(np.isfinite(x)))
    shape = tuple(x.shape)
    k = len(trailing)
    if len(shape) < k or shape[len(shape) - k :] != trailing:
        expected = "(..., " + ", ".join(str(n) for n in trailing) + ")"
        raise SE3ShapeError(f"{name}: expected shape {expected}, got {shape}")
    if not finite:
        raise SE3NonFiniteError(f"{name}: contains NaN or infinite values")
    return x


def _common(*xs: Array) -> tuple[Array, ...]:
    """Bring checked inputs to one kind (all numpy or all torch) and one float dtype."""
    kinds = {_is_torch(x) for x in xs}
    if len(kinds) > 1:
        raise SE3InputError("inputs mix numpy arrays and torch tensors; pass one kind only")
    if kinds == {True}:
        import torch

        dtype = xs[0].dtype
        for x in xs[1:]:
            dtype = torch.promote_types(dtype, x.dtype)
        return tuple(x.to(dtype) for x in xs)
    dtype = np.result_type(*xs)
    return tuple(x.astype(dtype, copy=False) for x in xs)


# --------------------------------------------------------------------------------------------
# SO(3)
# --------------------------------------------------------------------------------------------


def _hat(w: Array) -> Array:
    z = w[..., 0] * 0.0
    x, y, zz = w[..., 0], w[..., 1], w[..., 2]
    return _stack(
        [_stack([z, -zz, y], -1), _stack([zz, z, -x], -1), _stack([-y, x, z], -1)], -2
    )


def _vee(W: Array) -> Array:
    return 0.5 * _stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], -1
    )


def so3_hat(w: Array) -> Array:
    """Skew-symmetric matrix of a rotation vector: ``(..., 3) -> (..., 3, 3)``, ``hat(w) x = w x x``."""
    return _hat(_check(w, "w", (3,)))


def so3_vee(W: Array) -> Array:
    """Inverse of :func:`so3_hat`: ``(..., 3, 3) -> (..., 3)``.

    Uses the skew-symmetric part ``(W - W^T) / 2``, so it is exact for skew matrices and the
    least-squares answer otherwise.
    """
    return _vee(_check(W, "W", (3, 3)))


def _so3_exp_coeffs(theta_sq: Array) -> tuple[Array, Array, Array]:
    """``theta``, ``A = sin(theta)/theta`` and ``B = (1 - cos(theta))/theta^2`` from ``theta^2``."""
    xp = _xp(theta_sq)
    small = theta_sq < _SMALL_ANGLE**2
    theta = xp.sqrt(xp.where(small, 1.0, theta_sq))
    half = 0.5 * theta
    a_big = xp.sin(theta) / theta
    sinc_half = xp.sin(half) / half
    b_big = 0.5 * sinc_half * sinc_half  # (1 - cos t)/t^2 = 2 sin^2(t/2)/t^2, no cancellation
    t2 = theta_sq
    a = xp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, a_big)
    b = xp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, b_big)
    return xp.where(small, 0.0, theta), a, b


def _so3_exp(w: Array) -> Array:
    theta_sq = (w * w).sum(-1)
    _, a, b = _so3_exp_coeffs(theta_sq)
    W = _hat(w)
    return _eye3(w) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def so3_exp(w: Array) -> Array:
    """Rotation matrix of a rotation vector (Rodrigues): ``(..., 3)`` rad -> ``(..., 3, 3)``.

    ``R = I + sin(t)/t W + (1 - cos t)/t^2 W^2`` with ``W = hat(w)``, ``t = |w|``; Taylor series
    below ``t = 1e-2`` rad, so ``w = 0`` is exact and torch gradients are finite there.
    """
    return _so3_exp(_check(w, "w", (3,)))


def _so3_log(R: Array) -> Array:
    """Rotation vector via a quaternion (Shepperd's method): stable at 0 and at pi."""
    xp = _xp(R)
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = r00 + r11 + r22

    def pivot(arg: Array) -> Array:
        # 2 q_k = sqrt(1 + ...); clamped so that branches not selected stay finite (gradients).
        return xp.sqrt(xp.clip(arg, 1e-12, None))

    # Each candidate is 2 (q_w, q_x, q_y, q_z), from the pivot component 2 q_k = sqrt(arg)
    # (the common factor 2 cancels below).
    pw = pivot(1.0 + tr)
    qw = _stack([pw * pw, r21 - r12, r02 - r20, r10 - r01], -1) / pw[..., None]
    px = pivot(1.0 + r00 - r11 - r22)
    qx = _stack([r21 - r12, px * px, r01 + r10, r02 + r20], -1) / px[..., None]
    py = pivot(1.0 - r00 + r11 - r22)
    qy = _stack([r02 - r20, r01 + r10, py * py, r12 + r21], -1) / py[..., None]
    pz = pivot(1.0 - r00 - r11 + r22)
    qz = _stack([r10 - r01, r02 + r20, r12 + r21, pz * pz], -1) / pz[..., None]
    idx = _stack([tr, r00, r11, r22], -1).argmax(-1)[..., None]
    q = xp.where(idx == 0, qw, xp.where(idx == 1, qx, xp.where(idx == 2, qy, qz)))
    # q = 2 * (cos(t/2), sin(t/2) n): choose the hemisphere with q_w >= 0 so that t <= pi.
    q = xp.where(q[..., :1] < 0, -q, q)
    qr, qv = q[..., 0], q[..., 1:]
    s_sq = (qv * qv).sum(-1)
    # omega = factor * q_v with factor = 2 atan2(s, q_w) / s (t = 2 atan2(s, q_w), s = |q_v|);
    # near t = 0 the series of atan(x)/x in x = s/q_w = tan(t/2) (q_w > 0 there).
    small = s_sq < _SMALL_ANGLE**2 * (qr * qr)
    qr_safe = xp.where(small, qr, 1.0)
    x_sq = s_sq / (qr_safe * qr_safe)
    s = xp.sqrt(xp.where(small, 1.0, s_sq))
    f_big = 2.0 * xp.arctan2(s, qr) / s
    f_small = (2.0 / qr_safe) * (1.0 - x_sq / 3.0 + x_sq * x_sq / 5.0 - x_sq * x_sq * x_sq / 7.0)
    factor = xp.where(small, f_small, f_big)
    return factor[..., None] * qv


def so3_log(R: Array) -> Array:
    """Rotation vector of a rotation matrix: ``(..., 3, 3) -> (..., 3)`` rad, angle in ``[0, pi]``.

    Goes through the unit quaternion (Shepperd's branch selection), ``t = 2 atan2(|q_v|, q_w)``,
    so it is accurate near 0 and near pi; at exactly pi either of the two equivalent vectors
    ``+-pi n`` is returned. ``R`` is assumed orthonormal (not checked).
    """
    return _so3_log(_check(R, "R", (3, 3)))


def _rotation_angle(Ra: Array, Rb: Array) -> Array:
    xp = _xp(Ra)
    M = _mT(Ra) @ Rb
    v = 2.0 * _vee(M)  # = 2 sin(t) n
    tr = M[..., 0, 0] + M[..., 1, 1] + M[..., 2, 2]  # = 1 + 2 cos(t)
    return xp.arctan2(_safe_sqrt((v * v).sum(-1)), tr - 1.0)


def rotation_angle(R_a: Array, R_b: Array) -> Array:
    """Geodesic angle between rotations, ``(..., 3, 3), (..., 3, 3) -> (...)`` rad in ``[0, pi]``.

    ``t = atan2(|vee(M - M^T)|, trace(M) - 1)`` with ``M = R_a^T R_b`` (both arguments equal
    ``2 sin t`` and ``2 cos t``), which has no arccos loss of accuracy near 0 or pi.
    """
    Ra, Rb = _common(_check(R_a, "R_a", (3, 3)), _check(R_b, "R_b", (3, 3)))
    return _rotation_angle(Ra, Rb)


# --------------------------------------------------------------------------------------------
# SE(3)
# --------------------------------------------------------------------------------------------


def _make_transform(R: Array, t: Array) -> Array:
    xp = _xp(R)
    lead = tuple(np.broadcast_shapes(tuple(R.shape[:-2]), tuple(t.shape[:-1])))
    R = xp.broadcast_to(R, lead + (3, 3))
    t = xp.broadcast_to(t, lead + (3,))
    top = _cat([R, t[..., None]], -1)
    bottom = xp.broadcast_to(_const([[0.0, 0.0, 0.0, 1.0]], R), lead + (1, 4))
    return _cat([top, bottom], -2)


def make_transform(R: Array, t: Array) -> Array:
    """``(..., 3, 3)`` rotation and ``(..., 3)`` mm translation -> ``(..., 4, 4)`` transform."""
    R, t = _common(_check(R, "R", (3, 3)), _check(t, "t", (3,)))
    return _make_transform(R, t)


def split(T: Array) -> tuple[Array, Array]:
    """``(..., 4, 4)`` transform -> ``(R (..., 3, 3), t (..., 3) mm)``."""
    T = _check(T, "T", (4, 4))
    return T[..., :3, :3], T[..., :3, 3]


def se3_exp(xi: Array) -> Array:
    """SE(3) exponential of a twist: ``(..., 6)`` = ``(omega rad, v mm)`` -> ``(..., 4, 4)``.

    ``R = so3_exp(omega)``, ``t = V v`` with the left Jacobian
    ``V = I + (1 - cos t)/t^2 W + (t - sin t)/t^3 W^2`` (``W = hat(omega)``, ``t = |omega|``),
    i.e. exactly ``expm([[W, v], [0, 0]])``.
    """
    xi = _check(xi, "xi", (6,))
    xp = _xp(xi)
    w, v = xi[..., :3], xi[..., 3:]
    theta_sq = (w * w).sum(-1)
    theta, a, b = _so3_exp_coeffs(theta_sq)
    small = theta_sq < _SMALL_ANGLE**2
    th = xp.where(small, 1.0, theta)
    c_big = (th - xp.sin(th)) / (th * th * th)
    t2 = theta_sq
    c = xp.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, c_big)
    W = _hat(w)
    WW = W @ W
    eye = _eye3(xi)
    R = eye + a[..., None, None] * W + b[..., None, None] * WW
    V = eye + b[..., None, None] * W + c[..., None, None] * WW
    t = (V @ v[..., None])[..., 0]
    return _make_transform(R, t)


def se3_log(T: Array) -> Array:
    """SE(3) logarithm: ``(..., 4, 4) -> (..., 6)`` = ``(omega rad, v mm)``, inverse of :func:`se3_exp`.

    ``omega = so3_log(R)`` (angle in ``[0, pi]``), ``v = V^{-1} t`` with
    ``V^{-1} = I - W/2 + (1 - (t/2) cot(t/2))/t^2 W^2``, finite up to and including ``t = pi``.
    """
    T = _check(T, "T", (4, 4))
    xp = _xp(T)
    R, t = T[..., :3, :3], T[..., :3, 3]
    w = _so3_log(R)
    theta_sq = (w * w).sum(-1)
    small = theta_sq < _SMALL_ANGLE**2
    th = xp.sqrt(xp.where(small, 1.0, theta_sq))
    half = 0.5 * th
    d_big = (1.0 - half * xp.cos(half) / xp.sin(half)) / (th * th)
    t2 = theta_sq
    d = xp.where(small, 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0, d_big)
    W = _hat(w)
    V_inv = _eye3(T) - 0.5 * W + d[..., None, None] * (W @ W)
    v = (V_inv @ t[..., None])[..., 0]
    return _cat([w, v], -1)


def _inverse(T: Array) -> Array:
    R, t = T[..., :3, :3], T[..., :3, 3]
    Rt = _mT(R)
    return _make_transform(Rt, -(Rt @ t[..., None])[..., 0])


def se3_inverse(T: Array) -> Array:
    """Inverse of a rigid transform, ``(..., 4, 4) -> (..., 4, 4)``: ``[R^T, -R^T t]``."""
    return _inverse(_check(T, "T", (4, 4)))


def se3_compose(A: Array, B: Array) -> Array:
    """``A @ B`` for ``(..., 4, 4)`` transforms (apply ``B`` first, then ``A``); broadcasts."""
    A, B = _common(_check(A, "A", (4, 4)), _check(B, "B", (4, 4)))
    return A @ B


# --------------------------------------------------------------------------------------------
# Product metric SO(3) x R^3
# --------------------------------------------------------------------------------------------


def product_log(T_b: Array, T_a: Array) -> Array:
    """Log of ``T_a`` at ``T_b`` on SO(3) x R^3: ``(..., 4, 4), (..., 4, 4) -> (..., 6)``.

    Returns ``(w, v)`` = ``(so3_log(R_b^T R_a)`` rad, ``R_b^T (t_a - t_b)`` mm): the tangent
    vector at ``T_b``, in ``T_b``'s body coordinates, of the product-metric geodesic from
    ``T_b`` to ``T_a``. Rotation and translation are independent (unlike :func:`se3_log`).
    ``|w|`` is the rotation angle and ``|v| = |t_a - t_b|``.

    Learning label: with ``lambda = 1`` (rad and mm as they are) the gradient of
    ``d^2(T_b, T_a)`` with respect to ``g`` in ``T_b -> product_exp(T_b, g)`` at ``g = 0`` is
    ``-2 product_log(T_b, T_a)``; for a general ``lambda`` the rotation part is multiplied by
    ``lambda^2``.
    """
    Tb, Ta = _common(_check(T_b, "T_b", (4, 4)), _check(T_a, "T_a", (4, 4)))
    Rb_t = _mT(Tb[..., :3, :3])
    w = _so3_log(Rb_t @ Ta[..., :3, :3])
    v = (Rb_t @ (Ta[..., :3, 3] - Tb[..., :3, 3])[..., None])[..., 0]
    return _cat([w, v], -1)


def product_exp(T: Array, g: Array) -> Array:
    """Inverse of :func:`product_log`: ``(..., 4, 4), (..., 6) -> (..., 4, 4)``.

    ``g = (w rad, v mm)`` in ``T``'s body coordinates gives ``(R so3_exp(w), t + R v)``, so
    ``product_exp(T_b, product_log(T_b, T_a)) == T_a``.
    """
    T, g = _common(_check(T, "T", (4, 4)), _check(g, "g", (6,)))
    R, t = T[..., :3, :3], T[..., :3, 3]
    R_new = R @ _so3_exp(g[..., :3])
    t_new = t + (R @ g[..., 3:, None])[..., 0]
    return _make_transform(R_new, t_new)


def geodesic_distance(
    T_a: Array, T_b: Array, *, mm_per_rad: float = DEFAULT_MM_PER_RAD, squared: bool = False
) -> Array:
    """Product-metric distance in mm, ``(..., 4, 4), (..., 4, 4) -> (...)``.

    ``d = sqrt(lambda^2 theta^2 + |t_a - t_b|^2)`` with ``theta = rotation_angle(R_a, R_b)`` rad
    and ``lambda = mm_per_rad`` (mm per rad; default :data:`DEFAULT_MM_PER_RAD`). Symmetric, zero
    iff the transforms are equal. ``squared=True`` returns ``d^2`` (mm^2), smooth everywhere.
    """
    if not (
        isinstance(mm_per_rad, numbers.Real) and math.isfinite(mm_per_rad) and mm_per_rad >= 0
    ):
        raise SE3InputError(f"mm_per_rad: expected a finite number >= 0, got {mm_per_rad!r}")
    Ta, Tb = _common(_check(T_a, "T_a", (4, 4)), _check(T_b, "T_b", (4, 4)))
    theta = _rotation_angle(Ta[..., :3, :3], Tb[..., :3, :3])
    dt = Ta[..., :3, 3] - Tb[..., :3, 3]
    d_sq = (mm_per_rad * theta) ** 2 + (dt * dt).sum(-1)
    return d_sq if squared else _safe_sqrt(d_sq)


def rotation_error_deg(T_a: Array, T_b: Array) -> Array:
    """Geodesic rotation angle between two transforms, ``(..., 4, 4) x 2 -> (...)`` degrees."""
    Ta, Tb = _common(_check(T_a, "T_a", (4, 4)), _check(T_b, "T_b", (4, 4)))
    return _rotation_angle(Ta[..., :3, :3], Tb[..., :3, :3]) * (180.0 / math.pi)


def translation_error_mm(T_a: Array, T_b: Array) -> Array:
    """Euclidean distance of the translations, ``(..., 4, 4) x 2 -> (...)`` mm."""
    Ta, Tb = _common(_check(T_a, "T_a", (4, 4)), _check(T_b, "T_b", (4, 4)))
    dt = Ta[..., :3, 3] - Tb[..., :3, 3]
    return _safe_sqrt((dt * dt).sum(-1))
