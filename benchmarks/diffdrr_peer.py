"""DiffDRR 0.6.1 as a measured peer renderer, adapted to ctxreg's geometry and units.

ctxreg's camera (see ``sim/projection/geometry.py``): ``X_cam = E @ X_lps`` with ``E`` a ``(4, 4)`` rigid map
from LPS mm to camera mm; the camera's origin is the focal spot, +z runs along the principal ray
toward the detector, +x along detector columns (increasing column index ``j``), +y along rows
(increasing row index ``i``); the detector plane is ``z = SDD`` and pixel ``(i, j)`` has its centre
at ``x = (j - (W - 1) / 2) s``, ``y = (i - (H - 1) / 2) s``. Images are indexed ``[row, col]``.

What DiffDRR 0.6.1 does (read from its source, ``diffdrr/{data,drr,detector,renderers,pose}.py``)
and how this adaptor maps onto it:

* Volume and world frame. ``DRR`` takes voxel -> world from ``subject.volume.affine`` (stored as
  float32, applied and inverted as a general 4 x 4 matrix) and integrates
  ``subject.density.data`` (``(1, I, J, K)``, squeezed). ``diffdrr.data.read`` would (1) replace the
  CT by ``transform_hu_to_density``: HU <= -800 set to the smallest soft-tissue HU, HU > 350 times
  ``bone_attenuation_multiplier``, then min-max normalised to [0, 1] (not a linear map of mu, and not
  invertible: air is clamped); (2) with ``center_volume=True`` shift the world so the volume's box
  centre is the origin; (3) keep torchio's (nibabel RAS) world. This adaptor bypasses ``read``: it
  builds the ``torchio.Subject`` itself with ``density`` = mu in 1/mm, the LPS affine unchanged (no
  centring) and ``reorient`` = identity, so DiffDRR's world is LPS mm and it integrates exactly mu.
* Voxel placement. ``voxel_shift=0.5`` (default) puts voxel centres at integer indices, the voxel
  ``n`` spanning ``[n - 0.5, n + 0.5]``; this matches ctxreg's affine (index -> voxel centre).
* Camera. ``Detector`` puts the source at the origin and pixel ``(i, j)``'s target at
  ``(x, y, z) = (-(j - (W - 1) / 2) delx, -(i - (H - 1) / 2) dely, sdd)`` with the default
  ``reverse_x_axis=True`` (rows come from the outer, columns from the inner loop of
  ``cartesian_prod``; ``DRR`` reshapes to ``(B, 1, H, W)``, no transpose, no flip afterwards). That is
  ctxreg's camera turned 180 degrees about z: ``p_diffdrr = Rz(pi) p_ctxreg``. Its pose is camera ->
  world, applied after ``reorient`` (``world = pose @ reorient @ p``; ``read(orientation="AP")`` sets
  ``reorient`` = ``[[1,0,0],[0,0,-1],[0,1,0]]`` and ``convert(..., "euler_angles")`` builds
  ``[R | R t]``). With ``reorient`` = identity the adaptor's pose is therefore
  ``E^-1 @ diag(-1, -1, 1, 1)`` (a proper rotation, no reflection), passed directly as a
  ``RigidTransform``.
* Units. Siddon: ``img = |target - source| (mm) * sum_k diff(alpha)_k * mu(midpoint_k)`` with
  ``alpha`` the ray parameter from source (0) to detector pixel (1) and nearest-voxel lookup: the exact
  line integral of the piecewise-constant volume, in mm x (1/mm) = dimensionless. Trilinear:
  ``n_points`` samples evenly spaced in ``alpha`` between the smallest entry and largest exit over
  all rays (DiffDRR's exit plane is one voxel past the far face, a harmless overshoot into zero
  padding), trilinear lookup with zero padding, times ``|target - source| * step_alpha`` (rectangle
  rule), also dimensionless. No further scaling is needed; the tests check it against closed-form
  chords.

DiffDRR is an optional dependency: this module imports it only when a renderer is prepared.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim.physics.materials import MU_WATER_60KEV_PER_MM

__all__ = [
    "MU_WATER_PER_MM",
    "DiffDRRPeerInputError",
    "DiffDRRUnavailableError",
    "PreparedDiffDRR",
    "hu_to_mu",
    "diffdrr_pose_from_extrinsic",
    "prepare",
    "render",
    "render_diffdrr",
]

#: Linear attenuation coefficient of water in 1/mm used by default: ctxreg's (water at 60 keV).
MU_WATER_PER_MM = MU_WATER_60KEV_PER_MM

#: ``diag(-1, -1, 1, 1)``: DiffDRR's detector frame (``reverse_x_axis=True``) -> ctxreg's camera frame.
_RZ_PI = np.diag([-1.0, -1.0, 1.0, 1.0])

_RENDERERS = ("siddon", "trilinear")


class DiffDRRPeerInputError(ValueError):
    """An input to the DiffDRR adaptor cannot be used; the message names the input and the problem."""


class DiffDRRUnavailableError(ImportError):
    """DiffDRR (or torchio, which it needs) is not installed in this environment."""


@dataclass(frozen=True, eq=False)
class PreparedDiffDRR:
    """A DiffDRR ``DRR`` module set up for one volume and detector (float32, CPU).

    Attributes:
        drr: the ``diffdrr.drr.DRR`` module (density = mu in 1/mm, world = LPS mm).
        pose: ``(1, 4, 4)`` float32 torch tensor, DiffDRR camera -> LPS mm for the extrinsic given
            to :func:`prepare`.
        renderer: ``"siddon"`` or ``"trilinear"``.
        n_points: samples per ray for the trilinear renderer (``None``: DiffDRR's default, 500;
            always ``None`` for siddon).
        height: detector rows ``H``.
        width: detector columns ``W``.
        prepare_s: seconds spent in :func:`prepare`.
    """

    drr: Any
    pose: Any
    renderer: str
    n_points: int | None
    height: int
    width: int
    prepare_s: float


def _import_diffdrr() -> tuple[Any, Any, Any, Any]:
    try:
        import torch
        import torchio
        from diffdrr.drr import DRR
        from diffdrr.pose import RigidTransform
    except ImportError as exc:  # pragma: no cover - exercised only without the bench extra
        raise DiffDRRUnavailableError(
            f"DiffDRR 0.6.1 is not importable ({exc}); install the project's 'bench' extra"
        ) from exc
    return torch, torchio, DRR, RigidTransform


def _matrix(value: object, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (4, 4):
        raise DiffDRRPeerInputError(f"{name}: expected a (4, 4) matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or not np.allclose(arr[3], (0.0, 0.0, 0.0, 1.0)):
        raise DiffDRRPeerInputError(f"{name}: not a finite homogeneous transform:\n{arr}")
    return arr


def _positive(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise DiffDRRPeerInputError(f"{name}: expected a number, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise DiffDRRPeerInputError(f"{name}: must be finite and > 0, got {v}")
    return v


def _count(value: object, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise DiffDRRPeerInputError(f"{name}: expected an integer, got {value!r}")
    if int(value) < minimum:
        raise DiffDRRPeerInputError(f"{name}: must be >= {minimum}, got {value}")
    return int(value)


def hu_to_mu(hu: np.ndarray, mu_water_per_mm: float = MU_WATER_PER_MM) -> np.ndarray:
    """``(I, J, K)`` float32 mu in 1/mm: ``mu_water (1 + HU / 1000)`` clipped at 0, from HU."""
    mu_w = _positive(mu_water_per_mm, "mu_water_per_mm")
    hu = np.asarray(hu, dtype=np.float32)
    return np.maximum(np.float32(mu_w) * (np.float32(1.0) + hu / np.float32(1000.0)), np.float32(0.0))


def diffdrr_pose_from_extrinsic(extrinsic_lps_to_cam: np.ndarray) -> np.ndarray:
    """``(4, 4)`` float64 DiffDRR pose (its detector frame -> LPS mm) for a ctxreg extrinsic.

    ``extrinsic_lps_to_cam``: ``(4, 4)`` rigid map LPS mm -> ctxreg camera mm. The result is
    ``E^-1 @ diag(-1, -1, 1, 1)``, valid with ``reorient`` = identity and ``reverse_x_axis=True``.
    """
    E = _matrix(extrinsic_lps_to_cam, "extrinsic_lps_to_cam")
    R = E[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > 1e-6 or np.linalg.det(R) < 0:
        raise DiffDRRPeerInputError(
            f"extrinsic_lps_to_cam: rotation block is not a proper rotation (|R^T R - I| = {err:.3g})"
        )
    E_inv = np.eye(4)
    E_inv[:3, :3] = R.T
    E_inv[:3, 3] = -R.T @ E[:3, 3]
    return E_inv @ _RZ_PI


def _trilinear_n_points(drr: Any, pose: Any, step_mm: float, torch: Any, RigidTransform: Any) -> int:
    """Samples per ray so that DiffDRR's trilinear step is at most ``step_mm`` on every ray."""
    from diffdrr.renderers import _get_alpha_minmax  # same span as Trilinear.forward uses

    with torch.no_grad():
        source, target = drr.detector(RigidTransform(pose), None)
        ray_mm = (target - source).norm(dim=-1).max().item()
        src_v = drr.affine_inverse(source)
        tgt_v = drr.affine_inverse(target)
        dims = torch.tensor(drr.density.shape).to(drr.density)
        amin, amax = _get_alpha_minmax(src_v, tgt_v, dims, drr.renderer.voxel_shift, drr.renderer.eps)
        span_mm = (amax.max() - amin.min()).item() * ray_mm
    return max(2, int(math.ceil(span_mm / step_mm)) + 1)


def prepare(
    hu: np.ndarray,
    affine_lps: np.ndarray,
    extrinsic_lps_to_cam: np.ndarray,
    sdd_mm: float,
    height: int,
    width: int,
    pixel_spacing_mm: float,
    renderer: str = "siddon",
    mu_water_per_mm: float = MU_WATER_PER_MM,
    n_points: int | None = None,
    step_mm: float | None = None,
) -> PreparedDiffDRR:
    """One-off set-up: HU -> mu, the torchio subject, the ``DRR`` module and the pose (float32, CPU).

    Args:
        hu: ``(I, J, K)`` HU; ``hu[i, j, k]`` is the voxel whose centre is ``affine_lps @ (i, j, k, 1)``.
        affine_lps: ``(4, 4)`` voxel index -> LPS mm of voxel centres (any non-singular affine).
        extrinsic_lps_to_cam: ``(4, 4)`` rigid map LPS mm -> ctxreg camera mm.
        sdd_mm: source-to-detector distance in mm.
        height, width: detector rows ``H`` and columns ``W`` (pixels).
        pixel_spacing_mm: square pixel pitch ``s`` in mm.
        renderer: ``"siddon"`` (exact, nearest voxel) or ``"trilinear"`` (sampled).
        mu_water_per_mm: mu of water in 1/mm for the HU -> mu map.
        n_points: trilinear samples per ray (``None``: DiffDRR's default, 500).
        step_mm: trilinear only, instead of ``n_points``: the largest sample step in mm along any
            ray; ``n_points`` is then derived from DiffDRR's own sampling span for this geometry.
    """
    t0 = time.perf_counter()
    if renderer not in _RENDERERS:
        raise DiffDRRPeerInputError(f"renderer: expected one of {_RENDERERS}, got {renderer!r}")
    vol = np.asarray(hu)
    if vol.ndim != 3 or min(vol.shape) < 2:
        # DiffDRR squeezes the density buffer, so a length-1 axis would silently change its rank.
        raise DiffDRRPeerInputError(f"hu: expected an (I, J, K) volume with every axis >= 2, got {vol.shape}")
    if not np.issubdtype(vol.dtype, np.number) or not np.all(np.isfinite(vol)):
        raise DiffDRRPeerInputError("hu: voxel values must be finite numbers")
    affine = _matrix(affine_lps, "affine_lps")
    if abs(np.linalg.det(affine[:3, :3])) < 1e-9:
        raise DiffDRRPeerInputError(f"affine_lps: singular (zero voxel spacing?):\n{affine}")
    pose_np = diffdrr_pose_from_extrinsic(extrinsic_lps_to_cam)
    sdd = _positive(sdd_mm, "sdd_mm")
    h = _count(height, "height", 1)
    w = _count(width, "width", 1)
    s = _positive(pixel_spacing_mm, "pixel_spacing_mm")
    if renderer == "siddon" and (n_points is not None or step_mm is not None):
        raise DiffDRRPeerInputError("n_points/step_mm: only the trilinear renderer samples; leave them None")
    if n_points is not None and step_mm is not None:
        raise DiffDRRPeerInputError("n_points/step_mm: give at most one of them")
    if n_points is not None:
        n_points = _count(n_points, "n_points", 2)
    step = None if step_mm is None else _positive(step_mm, "step_mm")
    mu = hu_to_mu(vol, mu_water_per_mm)

    torch, torchio, DRR, RigidTransform = _import_diffdrr()
    density = torch.from_numpy(np.ascontiguousarray(mu))[None]  # (1, I, J, K) float32
    volume = torchio.ScalarImage(tensor=density, affine=affine)
    subject = torchio.Subject(
        volume=volume,
        density=torchio.ScalarImage(tensor=density, affine=affine),
        mask=None,
        orientation=None,
        reorient=torch.eye(4, dtype=torch.float32),
        fiducials=None,
    )
    drr = DRR(subject, sdd=sdd, height=h, delx=s, width=w, dely=s, x0=0.0, y0=0.0, renderer=renderer)
    drr = drr.to(torch.float32).eval()
    pose = torch.as_tensor(pose_np, dtype=torch.float32)[None]
    if step is not None:
        n_points = _trilinear_n_points(drr, pose, step, torch, RigidTransform)
    return PreparedDiffDRR(
        drr=drr,
        pose=pose,
        renderer=renderer,
        n_points=n_points,
        height=h,
        width=w,
        prepare_s=time.perf_counter() - t0,
    )


def render(prepared: PreparedDiffDRR, extrinsic_lps_to_cam: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` float32 line integral of mu (dimensionless), ctxreg's ``[row, col]`` convention.

    ``extrinsic_lps_to_cam``: optional ``(4, 4)`` LPS mm -> camera mm replacing the one given to
    :func:`prepare` for this call only.
    """
    if not isinstance(prepared, PreparedDiffDRR):
        raise DiffDRRPeerInputError(f"prepared: expected a PreparedDiffDRR, got {type(prepared).__name__}")
    torch, _, _, RigidTransform = _import_diffdrr()
    pose = prepared.pose
    if extrinsic_lps_to_cam is not None:
        pose = torch.as_tensor(diffdrr_pose_from_extrinsic(extrinsic_lps_to_cam), dtype=torch.float32)[None]
    kwargs = {} if prepared.n_points is None else {"n_points": prepared.n_points}
    with torch.no_grad():
        img = prepared.drr(RigidTransform(pose), **kwargs)  # (1, 1, H, W)
    return img[0, 0].detach().cpu().numpy().astype(np.float32, copy=False)


def render_diffdrr(*args, **kwargs) -> np.ndarray:
    """``(H, W)`` float32 DiffDRR line integral of ``mu = mu_water (1 + HU/1000)``, clipped at 0.

    Takes :func:`prepare`'s arguments and renders once; the image is in ctxreg's camera and
    ``[row, col]`` convention and is dimensionless (mu in 1/mm times path length in mm).
    """
    return render(prepare(*args, **kwargs))
