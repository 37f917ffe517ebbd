"""C-arm geometry: detector, intrinsics, volume pose parameters and projection (NumPy float64).

Conventions (full text with a worked example in ``docs/conventions.md``):

* Patient frame: LPS mm (+x patient left, +y posterior, +z superior).
* Camera frame: origin at the focal spot (X-ray source), +z along the principal ray toward the
  detector, +x along detector columns (increasing column index ``j``), +y along detector rows
  (increasing row index ``i``); the detector plane is ``z = SDD``. Pixel ``(i, j)`` has its centre
  at ``x = (j - cx) s``, ``y = (i - cy) s``; 2-D pixel coordinates are written ``(u, v)`` =
  ``(column, row)``.
* Volume pose ``T = (R, t)`` acts on anatomy-centred coordinates:
  ``X_cam = R (X_lps - c) + t``, ``c`` the anatomy centre in LPS mm.
* Pose parameters ``(phi, theta, psi, tx, ty, tz)`` in degrees and mm:
  ``R = R_AP Rz(phi) Rx(theta) Ry(psi)``, ``t = (tx, ty, SOD + tz)``; zero parameters = AP view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.projection import se3
from sim.core.errors import InputError

__all__ = [
    "GeometryError",
    "CArmGeometry",
    "R_AP",
    "pose_from_params",
    "params_from_pose",
    "extrinsic_lps_to_camera",
    "projection_matrix",
    "project_points",
    "backproject_pixel",
]

#: Rotation of the AP view, LPS -> camera: patient left -> +x (image right), posterior -> +z
#: (toward the detector; the source is anterior), superior -> -y (image up), i.e. inferior ->
#: +y (image down). It is ``Rx(+90 deg)``. Read-only ``(3, 3)`` float64.
R_AP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=np.float64)
R_AP.setflags(write=False)

#: Below this ``|cos(theta)|`` :func:`params_from_pose` treats the pose as gimbal-locked.
_GIMBAL_COS = 1e-8


class GeometryError(InputError):
    """A geometry, pose or point input cannot be used; the message names the input and the problem."""


def _finite_number(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise GeometryError(f"{name}: expected a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise GeometryError(f"{name}: must be finite, got {value}")
    return value


@dataclass(frozen=True)
class CArmGeometry:
    """A C-arm with a fixed source and a flat detector perpendicular to the principal ray.

    Attributes:
        sdd_mm: source-to-detector distance in mm (the detector plane is ``z = sdd_mm``).
        sod_mm: source-to-isocentre distance in mm, ``0 < sod_mm < sdd_mm``.
        height: detector rows ``H`` (pixels).
        width: detector columns ``W`` (pixels).
        pixel_spacing_mm: square pixel pitch ``s`` in mm.
        cx: principal point column in pixels (``None`` -> ``(W - 1) / 2``, the detector centre).
        cy: principal point row in pixels (``None`` -> ``(H - 1) / 2``).
    """

    sdd_mm: float
    sod_mm: float
    height: int
    width: int
    pixel_spacing_mm: float
    cx: float | None = None
    cy: float | None = None

    def __post_init__(self) -> None:
        sdd = _finite_number(self.sdd_mm, "sdd_mm")
        sod = _finite_number(self.sod_mm, "sod_mm")
        spacing = _finite_number(self.pixel_spacing_mm, "pixel_spacing_mm")
        if sdd <= 0:
            raise GeometryError(f"sdd_mm: must be > 0, got {sdd}")
        if not 0 < sod < sdd:
            raise GeometryError(
                f"sod_mm: must satisfy 0 < sod_mm < sdd_mm (isocentre between source and "
                f"detector), got sod_mm={sod}, sdd_mm={sdd}"
            )
        if spacing <= 0:
            raise GeometryError(f"pixel_spacing_mm: must be > 0, got {spacing}")
        for name in ("height", "width"):
            n = getattr(self, name)
            if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
                raise GeometryError(f"{name}: must be a positive integer (pixels), got {n!r}")
            object.__setattr__(self, name, int(n))
        for name in ("cx", "cy"):
            c = getattr(self, name)
            if c is not None:
                object.__setattr__(self, name, _finite_number(c, name))
        object.__setattr__(self, "sdd_mm", sdd)
        object.__setattr__(self, "sod_mm", sod)
        object.__setattr__(self, "pixel_spacing_mm", spacing)

    @property
    def principal_point(self) -> tuple[float, float]:
        """``(cx, cy)`` in pixels (column, row), defaults resolved."""
        cx = (self.width - 1) / 2.0 if self.cx is None else self.cx
        cy = (self.height - 1) / 2.0 if self.cy is None else self.cy
        return float(cx), float(cy)

    @property
    def focal_length_px(self) -> float:
        """``SDD / s``: the focal length in pixels."""
        return self.sdd_mm / self.pixel_spacing_mm

    def intrinsics(self) -> np.ndarray:
        """``(3, 3)`` float64 ``K = [[SDD/s, 0, cx], [0, SDD/s, cy], [0, 0, 1]]`` (camera mm -> px)."""
        f = self.focal_length_px
        cx, cy = self.principal_point
        return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=np.float64)

    @property
    def detector_size_mm(self) -> tuple[float, float]:
        """``(height_mm, width_mm)`` = ``(H s, W s)``: the physical detector extent."""
        return self.height * self.pixel_spacing_mm, self.width * self.pixel_spacing_mm

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view in degrees: angle between the rays to the left and right detector edges."""
        s = self.pixel_spacing_mm
        cx, _ = self.principal_point
        left = (-0.5 - cx) * s
        right = (self.width - 0.5 - cx) * s
        return math.degrees(math.atan2(right, self.sdd_mm) - math.atan2(left, self.sdd_mm))

    def resized(self, height: int, width: int) -> CArmGeometry:
        """The same physical detector sampled with ``height x width`` pixels.

        The pixel spacing becomes ``s * old / new`` (the same factor on both axes, so
        ``height / self.height`` must equal ``width / self.width``), and the principal point keeps
        its physical position: ``c_new + 0.5 = (c_old + 0.5) * new / old`` (pixel ``k`` covers
        ``[k - 0.5, k + 0.5]``, so ``c + 0.5`` is the distance from the detector edge in pixels).
        """
        for name, n in (("height", height), ("width", width)):
            if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
                raise GeometryError(f"{name}: must be a positive integer (pixels), got {n!r}")
        fy = height / self.height
        fx = width / self.width
        if abs(fy - fx) > 1e-9 * max(fx, fy):
            raise GeometryError(
                f"resized: {self.height} x {self.width} -> {height} x {width} changes the aspect "
                f"ratio (row factor {fy:g}, column factor {fx:g}); square pixels need equal factors"
            )
        cx = None if self.cx is None else (self.cx + 0.5) * fx - 0.5
        cy = None if self.cy is None else (self.cy + 0.5) * fy - 0.5
        return CArmGeometry(
            sdd_mm=self.sdd_mm,
            sod_mm=self.sod_mm,
            height=int(height),
            width=int(width),
            pixel_spacing_mm=self.pixel_spacing_mm * self.width / width,
            cx=cx,
            cy=cy,
        )

    def pixel_centers_camera(self) -> np.ndarray:
        """``(H, W, 3)`` float64 pixel centres in camera mm: ``((j - cx) s, (i - cy) s, SDD)``."""
        s = self.pixel_spacing_mm
        cx, cy = self.principal_point
        x = (np.arange(self.width, dtype=np.float64) - cx) * s
        y = (np.arange(self.height, dtype=np.float64) - cy) * s
        out = np.empty((self.height, self.width, 3), dtype=np.float64)
        out[..., 0] = x[None, :]
        out[..., 1] = y[:, None]
        out[..., 2] = self.sdd_mm
        return out


# --------------------------------------------------------------------------------------------
# Pose parameters
# --------------------------------------------------------------------------------------------


def _as_float_array(x: object, name: str, trailing: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{name}: expected a numeric array ({exc})") from None
    k = len(trailing)
    if a.ndim < k or a.shape[a.ndim - k :] != trailing:
        expected = "(..., " + ", ".join(str(n) for n in trailing) + ")"
        raise GeometryError(f"{name}: expected shape {expected}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise GeometryError(f"{name}: contains NaN or infinite values")
    return a


def _check_sod(sod_mm: object) -> float:
    sod = _finite_number(sod_mm, "sod_mm")
    if sod <= 0:
        raise GeometryError(f"sod_mm: must be > 0, got {sod}")
    return sod


def _rz(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _rx(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _ry(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def pose_from_params(params: np.ndarray, sod_mm: float) -> np.ndarray:
    """Volume pose from parameters: ``(..., 6)`` -> ``(..., 4, 4)`` float64.

    ``params = (phi, theta, psi, tx, ty, tz)``: angles in degrees about the patient's S, L and P
    axes (LPS z, x, y; right-handed, counter-clockwise seen from the positive axis), offsets in
    camera mm. ``R = R_AP @ Rz(phi) @ Rx(theta) @ Ry(psi)`` and ``t = (tx, ty, sod_mm + tz)``.
    In the anatomy frame the rotations apply ``psi`` first, then ``theta``, then ``phi``, all about
    the fixed LPS axes. Zero parameters give the AP view ``(R_AP, (0, 0, SOD))``.
    """
    p = _as_float_array(params, "params", (6,))
    sod = _check_sod(sod_mm)
    ang = np.deg2rad(p[..., :3])
    R = R_AP @ _rz(ang[..., 0]) @ _rx(ang[..., 1]) @ _ry(ang[..., 2])
    t = p[..., 3:].copy()
    t[..., 2] += sod
    return se3.make_transform(R, t)


def params_from_pose(T: np.ndarray, sod_mm: float) -> np.ndarray:
    """Inverse of :func:`pose_from_params`: ``(..., 4, 4)`` -> ``(..., 6)`` (degrees, mm).

    With ``M = R_AP^T R = Rz(phi) Rx(theta) Ry(psi)``: ``theta = atan2(M[2,1], hypot(M[0,1],
    M[1,1]))`` in ``[-90, 90]``, ``phi = atan2(-M[0,1], M[1,1])`` and ``psi = atan2(-M[2,0],
    M[2,2])`` in ``(-180, 180]``. At gimbal lock (``|cos theta| < 1e-8``, theta = +-90) only
    ``phi +- psi`` is determined: ``psi = 0`` is returned and ``phi = atan2(M[1,0], M[0,0])``.
    ``(tx, ty, tz) = t - (0, 0, sod_mm)``. ``R`` must be a rotation (checked to 1e-6).
    """
    T = _as_float_array(T, "T", (4, 4))
    sod = _check_sod(sod_mm)
    R = T[..., :3, :3]
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(initial=0.0)
    if err > 1e-6 or np.any(np.linalg.det(R) < 0):
        raise GeometryError(f"T: rotation block is not a proper rotation (|R^T R - I| = {err:.3g})")
    M = R_AP.T @ R
    cos_theta = np.hypot(M[..., 0, 1], M[..., 1, 1])
    theta = np.arctan2(M[..., 2, 1], cos_theta)
    locked = cos_theta < _GIMBAL_COS
    phi = np.where(locked, np.arctan2(M[..., 1, 0], M[..., 0, 0]), np.arctan2(-M[..., 0, 1], M[..., 1, 1]))
    psi = np.where(locked, 0.0, np.arctan2(-M[..., 2, 0], M[..., 2, 2]))
    t = T[..., :3, 3].copy()
    t[..., 2] -= sod
    return np.concatenate([np.rad2deg(np.stack([phi, theta, psi], -1)), t], -1)


# --------------------------------------------------------------------------------------------
# Projection
# --------------------------------------------------------------------------------------------


def extrinsic_lps_to_camera(T: np.ndarray, center_lps: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` map from LPS mm to camera mm: ``[R | t - R c]`` for pose ``T`` and centre ``c``.

    ``T``: ``(..., 4, 4)`` volume pose; ``center_lps``: ``(3,)`` or ``(..., 3)`` anatomy centre ``c``
    in LPS mm.
    """
    T = _as_float_array(T, "T", (4, 4))
    c = _as_float_array(center_lps, "center_lps", (3,))
    R, t = T[..., :3, :3], T[..., :3, 3]
    return se3.make_transform(R, t - (R @ c[..., None])[..., 0])


def projection_matrix(geometry: CArmGeometry, T: np.ndarray, center_lps: np.ndarray) -> np.ndarray:
    """``(..., 3, 4)`` projection ``P = K [R | t - R c]``: homogeneous LPS mm -> homogeneous pixel ``(u, v, 1)``."""
    if not isinstance(geometry, CArmGeometry):
        raise GeometryError(f"geometry: expected a CArmGeometry, got {type(geometry).__name__}")
    E = extrinsic_lps_to_camera(T, center_lps)
    return geometry.intrinsics() @ E[..., :3, :]


def project_points(P: np.ndarray, X_lps: np.ndarray) -> np.ndarray:
    """Project LPS points to pixels ``(u, v)`` = ``(column, row)``.

    ``P``: ``(3, 4)`` or ``(B, 3, 4)``; ``X_lps``: ``(N, 3)`` mm. Returns ``(N, 2)`` or
    ``(B, N, 2)`` float64. Points at or behind the source plane (camera ``z <= 0``) have no
    image and get NaN.
    """
    P = _as_float_array(P, "P", (3, 4))
    if P.ndim not in (2, 3):
        raise GeometryError(f"P: expected shape (3, 4) or (B, 3, 4), got {P.shape}")
    X = _as_float_array(X_lps, "X_lps", (3,))
    if X.ndim != 2:
        raise GeometryError(f"X_lps: expected shape (N, 3), got {X.shape}")
    p = X @ np.swapaxes(P[..., :, :3], -1, -2) + P[..., None, :, 3]  # (..., N, 3)
    w = p[..., 2:3]
    ok = w > 0
    uv = p[..., :2] / np.where(ok, w, 1.0)
    return np.where(ok, uv, np.nan)


def backproject_pixel(geometry: CArmGeometry, u: float | np.ndarray, v: float | np.ndarray) -> np.ndarray:
    """Unit ray direction in the camera frame through pixel ``(u, v)`` (column, row; may be fractional).

    ``u``, ``v``: scalars or broadcastable arrays of shape ``(...)``; returns ``(..., 3)`` float64,
    ``normalize(((u - cx) s, (v - cy) s, SDD))``.
    """
    if not isinstance(geometry, CArmGeometry):
        raise GeometryError(f"geometry: expected a CArmGeometry, got {type(geometry).__name__}")
    uu = _as_float_array(u, "u", ())
    vv = _as_float_array(v, "v", ())
    uu, vv = np.broadcast_arrays(uu, vv)
    s = geometry.pixel_spacing_mm
    cx, cy = geometry.principal_point
    d = np.stack([(uu - cx) * s, (vv - cy) * s, np.full(uu.shape, geometry.sdd_mm)], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
