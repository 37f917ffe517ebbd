"""Built-in digital adult pelvis phantom: a seeded generator of anatomically plausible pelvis CTs.

:func:`make_pelvis_phantom` returns a :class:`~sim.ct.volume.CTVolume` in Hounsfield units with a
label map. It is ctxreg's default CT (the demo renders it, tests use it) and a source of
"virtual patients": :meth:`PelvisShape.sample` draws every shape parameter within its adult
range from a seed, so ``make_pelvis_phantom(seed)`` is a different, reproducible patient per
seed (same seed, bit-identical arrays on the same machine).

Frame and grid
    The affine is axis-aligned LPS: voxel index ``i`` runs along +x (patient Left), ``j`` along
    +y (Posterior), ``k`` along +z (Superior), all with the same spacing. The grid centre is the
    LPS origin ``(0, 0, 0)``, and the anatomy is placed so that the centroid of the pelvic bones
    (labels 1 and 2) lies within a few mm of it. The mid-sagittal plane is ``x = 0``; for
    ``shape=PelvisShape.default()`` the bones are mirror-symmetric about it.

Labels (``CTVolume.labels``, uint8)
    ====  ==========================================================
    0     background: air, fat, muscle, organs, bowel gas, discs
    1     pelvic bones: both hip bones (ilium + ischium + pubis)
    2     sacrum with coccyx
    3     left femur (patient left, +x)
    4     right femur (patient right, -x)
    5     lumbar vertebrae (L5 and L4)
    ====  ==========================================================

    A voxel carries a bone label when its centre lies inside that bone's surface.

Hounsfield units
    air outside the body -1000 (exactly), bowel gas about -900, subcutaneous and pelvic fat
    about -100, generic soft tissue 40, muscles (psoas, iliacus, glutei, thigh) 55, urine in
    the bladder 10, intervertebral discs 90, cortical bone ``PelvisShape.cortical_hu``
    (1200-1800), cancellous bone ``PelvisShape.cancellous_hu`` (180-400), femoral medullary
    canal 0. Everything inside the body carries smooth seeded noise (about 11 HU standard
    deviation; cancellous bone has an extra trabecular texture of about 40 HU), and material
    boundaries are ramped over one voxel (partial-volume), so the volume is not piecewise
    constant and shows no staircase.

How it is built
    Every bone is an implicit surface (a signed distance, negative inside, mm) evaluated with
    NumPy on the voxel centres inside the bounding box of each primitive: capsules and tapered
    tubes along polylines (pubic and ischial rami forming the obturator rings, iliac crests,
    arcuate lines, femoral necks and shafts, vertebral processes), spheres and ellipsoids
    (femoral heads, trochanters, ischial tuberosities), hemispherical cups (acetabula) and thin
    curved plates given as dense point sets with a per-point half-thickness (iliac wings,
    quadrilateral plates, the sacrum), whose distance comes from a k-d tree. Primitives of one
    bone are joined with a smooth minimum (fillets of a few mm). The cortex is the shell
    ``-t < sdf <= 0`` (``t`` = ``cortical_thickness_mm``, 2.5 x that in the femoral shaft) and
    the inside is cancellous bone.

Anatomical proportions follow the usual adult references: hip joint centres from the
inter-ASIS distance (Bell et al. 1990: 36 % lateral, 19 % posterior, 30 % inferior of the
mid-ASIS point), true conjugate about 115 mm, sacral slope 40 degrees, neck-shaft angle
128 degrees, femoral anteversion 12 degrees, symphysis height about 42 mm.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Callable

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from sim.core.errors import InputError
from sim.core.seeds import TAG_PELVIS_SHAPE, TAG_PHANTOM_TEXTURE, tagged_rng
from sim.ct.volume import CTVolume
from sim.core.atomic import atomic_path

__all__ = [
    "LABEL_NAMES",
    "PelvisShape",
    "PhantomInputError",
    "make_pelvis_phantom",
    "pelvis_landmarks",
    "write_phantom_nifti",
]

#: Label value -> structure name (see the module docstring).
LABEL_NAMES: dict[int, str] = {
    0: "background",
    1: "pelvis",
    2: "sacrum",
    3: "femur_left",
    4: "femur_right",
    5: "lumbar_spine",
}

HU_AIR = -1000.0
HU_GAS = -900.0
HU_FAT = -100.0
HU_SOFT = 40.0
HU_MUSCLE = 55.0
HU_URINE = 10.0
HU_DISC = 90.0
HU_MARROW = 0.0

#: Largest grid (voxels) the generator accepts: about 1.2 GB per float32 working array.
MAX_VOXELS = 300_000_000


class PhantomInputError(InputError):
    """An input of the phantom generator is unusable; the message names it and the problem."""


# ---------------------------------------------------------------------------------------------
# Shape parameters
# ---------------------------------------------------------------------------------------------


def _param(unit: str, low: float, mean: float, high: float, doc: str):
    return field(default=mean, metadata={"unit": unit, "range": (low, high), "mean": mean, "doc": doc})


@dataclass(frozen=True)
class PelvisShape:
    """Shape (and bone density) parameters of one phantom patient.

    Every field has a unit and a plausible adult range (``PelvisShape.ranges()``); construction
    rejects values outside it with :class:`PhantomInputError`. All lengths are multiplied by
    ``scale`` when the phantom is built except the body's own semi-axes and fat thickness.
    The default (:meth:`default`) is a typical adult; :meth:`sample` draws a random one.
    """

    inter_asis_mm: float = _param("mm", 205.0, 240.0, 275.0,
                                  "distance between the left and right anterior superior iliac spines")
    iliac_flare_deg: float = _param("deg", 18.0, 26.0, 34.0,
                                    "coronal angle between the vertical and the line from the hip "
                                    "centre to the most lateral point of the iliac crest")
    wing_height_mm: float = _param("mm", 92.0, 110.0, 130.0,
                                   "height of the iliac crest's top above the hip joint centre")
    sacrum_width_mm: float = _param("mm", 96.0, 110.0, 124.0, "width across the sacral alae at S1")
    sacral_slope_deg: float = _param("deg", 28.0, 40.0, 52.0,
                                     "angle between the S1 upper endplate and the horizontal (axial) plane")
    sacrum_length_mm: float = _param("mm", 88.0, 105.0, 122.0,
                                     "length of the sacrum along its curved mid-line, S1 endplate to apex")
    acetabulum_radius_mm: float = _param("mm", 22.5, 26.0, 30.5, "radius of the acetabular socket")
    femoral_head_radius_mm: float = _param("mm", 20.0, 23.5, 28.0,
                                           "radius of the femoral head (1 to 5 mm less than the socket)")
    neck_shaft_angle_deg: float = _param("deg", 118.0, 128.0, 140.0,
                                         "angle between the femoral neck and shaft axes")
    femoral_neck_length_mm: float = _param("mm", 40.0, 50.0, 60.0,
                                           "head centre to the shaft axis along the neck axis")
    femoral_anteversion_deg: float = _param("deg", 0.0, 12.0, 25.0,
                                            "forward rotation of the femoral neck out of the coronal plane")
    symphysis_height_mm: float = _param("mm", 32.0, 42.0, 52.0, "height of the pubic symphysis")
    obturator_height_mm: float = _param("mm", 36.0, 46.0, 56.0,
                                        "height of the obturator foramen, superior pubic ramus to "
                                        "ischiopubic ramus (the hole in an AP view is 1-5 mm less: "
                                        "rounded corners)")
    cortical_thickness_mm: float = _param("mm", 1.0, 2.0, 3.0,
                                          "cortical shell thickness of the pelvis, sacrum and vertebrae "
                                          "(femoral head 0.6 x: subchondral; femoral shaft 2.5 x)")
    body_semi_axis_lr_mm: float = _param("mm", 160.0, 180.0, 198.0,
                                         "left-right semi-axis of the elliptic body outline at the hips "
                                         "(enlarged if needed to keep 25 mm of tissue outside the bones)")
    body_semi_axis_ap_mm: float = _param("mm", 105.0, 120.0, 140.0,
                                         "antero-posterior semi-axis of the elliptic body outline "
                                         "(enlarged likewise)")
    fat_thickness_mm: float = _param("mm", 8.0, 20.0, 45.0, "subcutaneous fat layer thickness")
    bowel_gas_pockets: int = _param("count", 0, 4, 10, "number of gas pockets in the lower abdomen")
    scale: float = _param("1", 0.9, 1.0, 1.1, "overall scale factor of the skeleton")
    cortical_hu: float = _param("HU", 1200.0, 1500.0, 1800.0, "Hounsfield units of cortical bone")
    cancellous_hu: float = _param("HU", 180.0, 280.0, 400.0,
                                  "Hounsfield units of cancellous bone (sacrum 0.8 x, femoral head 1.35 x)")

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            low, high = f.metadata["range"]
            unit = f.metadata["unit"]
            if f.name == "bowel_gas_pockets":
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                    raise PhantomInputError(f"PelvisShape.{f.name} must be an integer count, got {value!r}")
            elif isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise PhantomInputError(f"PelvisShape.{f.name} must be a number ({unit}), got {value!r}")
            if not (math.isfinite(float(value)) and low <= float(value) <= high):
                raise PhantomInputError(
                    f"PelvisShape.{f.name} = {value} {unit} is outside its plausible range [{low}, {high}] {unit}"
                )
            object.__setattr__(self, f.name, int(value) if f.name == "bowel_gas_pockets" else float(value))
        gap = self.acetabulum_radius_mm - self.femoral_head_radius_mm
        if not 1.0 <= gap <= 5.0:
            raise PhantomInputError(
                f"PelvisShape: acetabulum_radius_mm - femoral_head_radius_mm = {gap:.2f} mm; the joint "
                "space must be 1 to 5 mm"
            )

    @staticmethod
    def ranges() -> dict[str, tuple[float, float, float, str]]:
        """``{field: (low, mean, high, unit)}`` of every parameter."""
        return {
            f.name: (f.metadata["range"][0], f.metadata["mean"], f.metadata["range"][1], f.metadata["unit"])
            for f in fields(PelvisShape)
        }

    @classmethod
    def default(cls) -> PelvisShape:
        """A typical adult: every parameter at its mean value (no randomness)."""
        return cls(**{f.name: f.metadata["mean"] for f in fields(cls)})

    @classmethod
    def sample(cls, seed: int) -> PelvisShape:
        """A random adult, deterministic in ``seed`` (a non-negative integer).

        Each parameter is ``mean + z * (high - mean)`` for ``z > 0`` and ``mean + z * (mean - low)``
        otherwise, with ``z = 2 * Beta(3, 3) - 1`` in (-1, 1): bounded, most values near the mean.
        The acetabulum radius is the drawn head radius plus a joint space of 1.5 to 3.5 mm.
        """
        rng = tagged_rng(_check_seed(seed), TAG_PELVIS_SHAPE)
        z = 2.0 * rng.beta(3.0, 3.0, size=len(fields(cls))) - 1.0
        joint_space = rng.uniform(1.5, 3.5)
        values = {}
        for zi, f in zip(z, fields(cls)):
            low, high = f.metadata["range"]
            mean = f.metadata["mean"]
            v = mean + zi * ((high - mean) if zi > 0 else (mean - low))
            values[f.name] = int(round(v)) if f.name == "bowel_gas_pockets" else float(v)
        lo_ac, hi_ac = cls.__dataclass_fields__["acetabulum_radius_mm"].metadata["range"]
        values["acetabulum_radius_mm"] = float(np.clip(values["femoral_head_radius_mm"] + joint_space, lo_ac, hi_ac))
        return cls(**values)


def _shape_table() -> str:
    rows = [f"    {'parameter':<26} {'unit':<6} {'low':>7} {'mean':>7} {'high':>7}  meaning"]
    for f in fields(PelvisShape):
        low, high = f.metadata["range"]
        rows.append(f"    {f.name:<26} {f.metadata['unit']:<6} {low:>7g} {f.metadata['mean']:>7g} {high:>7g}"
                    f"  {f.metadata['doc']}")
    return "\n".join(rows)


PelvisShape.__doc__ = (
    (PelvisShape.__doc__ or "") + "\n    Parameters (plausible adult range):\n\n" + _shape_table() + "\n"
)


def _check_seed(seed: object) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or int(seed) < 0:
        raise PhantomInputError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


# ---------------------------------------------------------------------------------------------
# Implicit-surface primitives (signed distance in mm, negative inside)
# ---------------------------------------------------------------------------------------------

Vec = np.ndarray
SDF = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class _Prim:
    """An implicit shape: ``sdf(X, Y, Z)`` on broadcastable LPS mm coordinates, valid (negative)
    only inside the box ``lo``..``hi`` (mm), outside of which it is never evaluated."""

    lo: Vec
    hi: Vec
    sdf: SDF


def _v(*xyz: float) -> Vec:
    return np.asarray(xyz, dtype=np.float64)


def _unit(v: Vec) -> Vec:
    return np.asarray(v, dtype=np.float64) / np.linalg.norm(v)


def _capsule(a: Vec, b: Vec, ra: float, rb: float | None = None) -> _Prim:
    """Tube from ``a`` to ``b`` (mm) with radius ``ra`` at ``a`` linearly changing to ``rb``."""
    rb = ra if rb is None else rb
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    ba = b - a
    inv_l2 = 1.0 / max(float(ba @ ba), 1e-12)
    r = max(ra, rb)

    def sdf(X, Y, Z):
        px, py, pz = X - np.float32(a[0]), Y - np.float32(a[1]), Z - np.float32(a[2])
        t = np.clip((px * ba[0] + py * ba[1] + pz * ba[2]) * np.float32(inv_l2), 0.0, 1.0).astype(np.float32)
        dx, dy, dz = px - t * np.float32(ba[0]), py - t * np.float32(ba[1]), pz - t * np.float32(ba[2])
        return np.sqrt(dx * dx + dy * dy + dz * dz) - (np.float32(ra) + np.float32(rb - ra) * t)

    return _Prim(np.minimum(a, b) - r, np.maximum(a, b) + r, sdf)


def _tube(points: Vec, radii) -> list[_Prim]:
    """Capsules along a polyline ``(N, 3)`` with per-vertex radii ``(N,)`` (mm)."""
    points = np.asarray(points, np.float64)
    radii = np.broadcast_to(np.asarray(radii, np.float64), (len(points),))
    return [_capsule(points[i], points[i + 1], radii[i], radii[i + 1]) for i in range(len(points) - 1)]


def _sphere(c: Vec, r: float) -> _Prim:
    c = np.asarray(c, np.float64)

    def sdf(X, Y, Z):
        dx, dy, dz = X - np.float32(c[0]), Y - np.float32(c[1]), Z - np.float32(c[2])
        return np.sqrt(dx * dx + dy * dy + dz * dz) - np.float32(r)

    return _Prim(c - r, c + r, sdf)


def _local(X, Y, Z, c: Vec, R: Vec | None):
    """Coordinates relative to ``c`` in the frame whose axes are the columns of ``R``."""
    px, py, pz = X - np.float32(c[0]), Y - np.float32(c[1]), Z - np.float32(c[2])
    if R is None:
        return px, py, pz
    R = np.asarray(R, np.float32)
    return (px * R[0, 0] + py * R[1, 0] + pz * R[2, 0],
            px * R[0, 1] + py * R[1, 1] + pz * R[2, 1],
            px * R[0, 2] + py * R[1, 2] + pz * R[2, 2])


def _ellipsoid(c: Vec, radii: Vec, R: Vec | None = None) -> _Prim:
    """Ellipsoid with semi-axes ``radii`` (mm) along the columns of ``R`` (distance is exact on
    the surface and a close bound near it)."""
    c = np.asarray(c, np.float64)
    rad = np.asarray(radii, np.float32)
    ext = float(np.max(rad))

    def sdf(X, Y, Z):
        u, v, w = _local(X, Y, Z, c, R)
        k0 = np.sqrt((u / rad[0]) ** 2 + (v / rad[1]) ** 2 + (w / rad[2]) ** 2)
        k1 = np.sqrt((u / rad[0] ** 2) ** 2 + (v / rad[1] ** 2) ** 2 + (w / rad[2] ** 2) ** 2)
        return k0 * (k0 - 1.0) / np.maximum(k1, np.float32(1e-6))

    return _Prim(c - ext, c + ext, sdf)


def _rounded_box(c: Vec, half: Vec, R: Vec | None = None, rounding: float = 0.0) -> _Prim:
    """Box with half-extents ``half`` (mm, rounding included) along the columns of ``R``."""
    c = np.asarray(c, np.float64)
    b = np.asarray(half, np.float32) - np.float32(rounding)
    ext = float(np.linalg.norm(half))

    def sdf(X, Y, Z):
        u, v, w = _local(X, Y, Z, c, R)
        qx, qy, qz = np.abs(u) - b[0], np.abs(v) - b[1], np.abs(w) - b[2]
        out = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qy, 0) ** 2 + np.maximum(qz, 0) ** 2)
        return out + np.minimum(np.maximum(np.maximum(qx, qy), qz), 0) - np.float32(rounding)

    return _Prim(c - ext, c + ext, sdf)


def _elliptic_cylinder(c: Vec, R: Vec, rx: float, ry: float, half_height: float, rounding: float) -> _Prim:
    """Elliptic cylinder (vertebral body): semi-axes ``rx``, ``ry`` along ``R[:, 0]``, ``R[:, 1]``,
    axis ``R[:, 2]``, half-height ``half_height``, edges rounded by ``rounding`` (all mm)."""
    c = np.asarray(c, np.float64)
    ax, ay = np.float32(rx - rounding), np.float32(ry - rounding)
    hh = np.float32(half_height - rounding)
    ext = float(math.hypot(max(rx, ry), half_height))

    def sdf(X, Y, Z):
        u, v, w = _local(X, Y, Z, c, R)
        k0 = np.sqrt((u / ax) ** 2 + (v / ay) ** 2)
        k1 = np.sqrt((u / ax**2) ** 2 + (v / ay**2) ** 2)
        d2 = k0 * (k0 - 1.0) / np.maximum(k1, np.float32(1e-6))
        dz = np.abs(w) - hh
        out = np.sqrt(np.maximum(d2, 0) ** 2 + np.maximum(dz, 0) ** 2)
        return out + np.minimum(np.maximum(d2, dz), 0) - np.float32(rounding)

    return _Prim(c - ext, c + ext, sdf)


def _plate(points: Vec, half_thickness: Vec) -> _Prim:
    """Thin curved plate: the union of balls of radius ``half_thickness`` ``(N,)`` (mm) centred on
    a dense sampling ``(N, 3)`` of its mid-surface (nearest centre by k-d tree)."""
    points = np.asarray(points, np.float64)
    rad = np.asarray(half_thickness, np.float64)
    rmax = float(rad.max())
    tree = cKDTree(points, leafsize=32)
    rad_ext = np.append(rad, 0.0).astype(np.float32)

    def sdf(X, Y, Z):
        x, y, z = X.ravel(), Y.ravel(), Z.ravel()
        shape = (len(x), len(y), len(z))
        h = float(max(x[1] - x[0] if len(x) > 1 else 0, y[1] - y[0] if len(y) > 1 else 0,
                      z[1] - z[0] if len(z) > 1 else 0, 1e-3))
        # only voxels within rmax + 2 voxels of a mid-surface point need a k-d tree query
        ijk = np.rint((points - np.array([x[0], y[0], z[0]])) / h).astype(np.int64)
        ok = np.all((ijk >= 0) & (ijk < np.array(shape)), axis=1)
        seed_free = np.ones(shape, dtype=bool)
        seed_free[tuple(ijk[ok].T)] = False
        far = rmax + 2.0 * h
        if seed_free.all():
            return np.full(shape, far - rmax, dtype=np.float32)
        idx_vox = np.nonzero(distance_transform_edt(seed_free) <= far / h + 0.87)
        out = np.full(shape, far - rmax, dtype=np.float32)
        if len(idx_vox[0]):
            q = np.stack([x[idx_vox[0]], y[idx_vox[1]], z[idx_vox[2]]], axis=1).astype(np.float64)
            dist, idx = tree.query(q, distance_upper_bound=far, workers=-1)
            out[idx_vox] = np.where(np.isfinite(dist), dist - rad_ext[idx], far - rmax).astype(np.float32)
        return out

    return _Prim(points.min(axis=0) - rmax, points.max(axis=0) + rmax, sdf)


def _halfspace_cut(prim: _Prim, normal: Vec, point: Vec) -> _Prim:
    """``prim`` intersected with the half-space ``normal . (p - point) <= 0``."""
    n = _unit(normal).astype(np.float32)
    p0 = np.asarray(point, np.float64)

    def sdf(X, Y, Z):
        plane = (X - np.float32(p0[0])) * n[0] + (Y - np.float32(p0[1])) * n[1] + (Z - np.float32(p0[2])) * n[2]
        return np.maximum(prim.sdf(X, Y, Z), plane)

    return _Prim(prim.lo, prim.hi, sdf)


def _ruled_points(top: Vec, bottom: Vec, step_mm: float, bulge_mm: float = 0.0,
                  bulge_dir: Callable[[Vec], Vec] | None = None) -> tuple[Vec, Vec, Vec]:
    """Dense points of the ruled surface between two curves of equal length ``(M, 3)``.

    Returns ``(points (N, 3), u (N,), v (N,))`` with ``u`` along the curves and ``v`` from
    ``top`` (0) to ``bottom`` (1), both in [0, 1]; ``bulge_mm * sin(pi u) sin(pi v)`` is added
    along ``bulge_dir(points)`` (unit vectors ``(N, 3)``).
    """
    m = len(top)
    length = max(float(np.linalg.norm(np.diff(top, axis=0), axis=1).sum()),
                 float(np.linalg.norm(np.diff(bottom, axis=0), axis=1).sum()))
    nu = max(int(math.ceil(length / step_mm)), 2)
    height = float(np.linalg.norm(top - bottom, axis=1).max())
    nv = max(int(math.ceil(height / step_mm)), 2)
    s = np.linspace(0.0, m - 1.0, nu)
    top_u = np.stack([np.interp(s, np.arange(m), top[:, a]) for a in range(3)], axis=1)
    bot_u = np.stack([np.interp(s, np.arange(m), bottom[:, a]) for a in range(3)], axis=1)
    v = np.linspace(0.0, 1.0, nv)
    pts = (1.0 - v)[None, :, None] * top_u[:, None, :] + v[None, :, None] * bot_u[:, None, :]
    uu, vv = np.meshgrid(np.linspace(0.0, 1.0, nu), v, indexing="ij")
    pts = pts.reshape(-1, 3)
    uu, vv = uu.ravel(), vv.ravel()
    if bulge_mm and bulge_dir is not None:
        pts = pts + (bulge_mm * np.sin(np.pi * uu) * np.sin(np.pi * vv))[:, None] * bulge_dir(pts)
    return pts, uu, vv


def _spline(points: Vec, n: int) -> Vec:
    """``n`` points ``(n, 3)`` on the Catmull-Rom spline through ``points`` ``(M, 3)`` (ends included)."""
    p = np.asarray(points, np.float64)
    ext = np.vstack([2 * p[0] - p[1], p, 2 * p[-1] - p[-2]])
    s = np.linspace(0.0, len(p) - 1.0, n)
    i = np.minimum(np.floor(s).astype(int), len(p) - 2)
    t = (s - i)[:, None]
    p0, p1, p2, p3 = ext[i], ext[i + 1], ext[i + 2], ext[i + 3]
    return 0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3)


# ---------------------------------------------------------------------------------------------
# Voxel grid and bone accumulation
# ---------------------------------------------------------------------------------------------


class _Grid:
    """Voxel-centre coordinates (LPS mm) of an axis-aligned grid centred on the origin, and the
    running per-voxel bone state: signed distance ``D`` to the nearest bone, its label, its
    cortical thickness ``TC`` (mm) and interior HU ``HIN``."""

    def __init__(self, shape: tuple[int, int, int], spacing: float) -> None:
        self.shape = shape
        self.h = spacing
        self.axes = [((np.arange(n, dtype=np.float64) - (n - 1) / 2.0) * spacing).astype(np.float32) for n in shape]
        self.D = np.full(shape, 1e4, dtype=np.float32)
        self.L = np.zeros(shape, dtype=np.uint8)
        self.TC = np.zeros(shape, dtype=np.float32)
        self.HIN = np.zeros(shape, dtype=np.float32)

    def index_range(self, lo: Vec, hi: Vec, within: tuple[slice, ...] | None = None):
        """Slices of the voxels whose centres lie in the box ``lo``..``hi`` (mm), or None."""
        sl = []
        for a in range(3):
            start = (self.shape[a] - 1) / 2.0
            i0 = max(int(math.ceil(lo[a] / self.h + start)), 0)
            i1 = min(int(math.floor(hi[a] / self.h + start)) + 1, self.shape[a])
            if within is not None:
                i0, i1 = max(i0, within[a].start), min(i1, within[a].stop)
            if i1 <= i0:
                return None
            sl.append(slice(i0, i1))
        return tuple(sl)

    def coords(self, sl: tuple[slice, ...]):
        x, y, z = (self.axes[a][sl[a]] for a in range(3))
        return x[:, None, None], y[None, :, None], z[None, None, :]


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth minimum with blend width ``k`` (mm); the hard minimum for ``k <= 0``."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / np.float32(k), 0.0, 1.0)
    return b + (a - b) * h - np.float32(k) * h * (1.0 - h)


class _Bone:
    """One labelled bone: smooth union of primitives, minus subtractions, merged into the grid."""

    def __init__(self, label: int, blend_mm: float) -> None:
        self.label = label
        self.blend = blend_mm
        self.unions: list[_Prim] = []
        self.cuts: list[_Prim] = []

    def add(self, *prims: _Prim | list[_Prim]) -> None:
        for p in prims:
            self.unions.extend(p if isinstance(p, list) else [p])

    def cut(self, *prims: _Prim | list[_Prim]) -> None:
        for p in prims:
            self.cuts.extend(p if isinstance(p, list) else [p])

    def render(self, grid: _Grid, cortical_mm, interior_hu) -> None:
        """Merge into ``grid``; ``cortical_mm`` and ``interior_hu`` are numbers or functions of
        ``(X, Y, Z)`` giving per-voxel values."""
        lo = np.min([p.lo for p in self.unions], axis=0) - 2 * grid.h
        hi = np.max([p.hi for p in self.unions], axis=0) + 2 * grid.h
        box = grid.index_range(lo, hi)
        if box is None:
            return
        d = np.full(tuple(s.stop - s.start for s in box), 1e4, dtype=np.float32)
        for prim in self.unions:
            self._apply(grid, box, d, prim, lambda old, new: _smin(old, new, self.blend))
        for prim in self.cuts:
            self._apply(grid, box, d, prim, lambda old, new: np.maximum(old, -new))
        X, Y, Z = grid.coords(box)
        wins = d < grid.D[box]
        grid.D[box] = np.where(wins, d, grid.D[box])
        grid.L[box] = np.where(wins, np.uint8(self.label), grid.L[box])
        for target, value in ((grid.TC, cortical_mm), (grid.HIN, interior_hu)):
            val = value(X, Y, Z) if callable(value) else np.float32(value)
            target[box] = np.where(wins, val, target[box])

    @staticmethod
    def _apply(grid: _Grid, box, d, prim: _Prim, op) -> None:
        sub = grid.index_range(prim.lo - grid.h, prim.hi + grid.h, within=box)
        if sub is None:
            return
        local = tuple(slice(s.start - b.start, s.stop - b.start) for s, b in zip(sub, box))
        d[local] = op(d[local], prim.sdf(*grid.coords(sub)).astype(np.float32))


# ---------------------------------------------------------------------------------------------
# Anatomy (built in an "ASIS frame" - origin at the mid-point of the two ASIS, LPS axes, left
# side given, right side mirrored - then scaled and shifted into the grid's LPS frame)
# ---------------------------------------------------------------------------------------------

#: Pelvic-bone centroid minus the mean of the landmarks of :meth:`_Anatomy._landmark_mean`
#: (ASIS frame, mm), measured on the default shape; over sampled shapes the sum tracks the
#: centroid of labels 1 + 2 to within ~4 mm.
_CENTROID_OFFSET = _v(0.0, 16.1, -3.6)
#: Body outline centre (y, mm) in the ASIS frame.
_BODY_Y_ASIS = 66.0


@dataclass(frozen=True)
class _Anatomy:
    """Derived geometry of one shape: key points of the left side in the ASIS frame (mm)."""

    s: PelvisShape

    # frame helpers ---------------------------------------------------------------------
    @cached_property
    def centre(self) -> Vec:
        """Approximate pelvic-bone centroid in the ASIS frame (mm): it maps to the LPS origin."""
        return self._landmark_mean() + _CENTROID_OFFSET

    def _landmark_mean(self) -> Vec:
        pts = [self.hip, self.crest_top, self.asis, self.psis, self.tuberosity(), self.obturator_centre()]
        both = [q * m for q in pts for m in (_v(1, 1, 1), _v(-1, 1, 1))]
        ys, ztop, zbot = self.symphysis
        return np.mean(both + [self.s1, _v(0.0, ys, 0.5 * (ztop + zbot))], axis=0)

    def to_lps(self, p: Vec) -> Vec:
        return self.s.scale * (np.asarray(p, np.float64) - self.centre)

    def mm(self, r):
        return self.s.scale * np.asarray(r, np.float64)

    # pelvis --------------------------------------------------------------------------------
    @property
    def hip(self) -> Vec:
        iad = self.s.inter_asis_mm
        return _v(0.36 * iad, 0.19 * iad, -0.30 * iad)

    @property
    def z_crest(self) -> float:
        return float(self.hip[2] + self.s.wing_height_mm)

    @property
    def asis(self) -> Vec:
        return _v(self.s.inter_asis_mm / 2.0, 0.0, 0.0)

    @property
    def crest_lateral(self) -> Vec:
        h = self.hip
        x = h[0] + (self.z_crest - h[2]) * math.tan(math.radians(self.s.iliac_flare_deg))
        return _v(x, 0.19 * self.s.inter_asis_mm, self.z_crest - 10.0)

    @property
    def crest_top(self) -> Vec:
        return _v(self.crest_lateral[0] - 16.0, 0.33 * self.s.inter_asis_mm, self.z_crest)

    @property
    def psis(self) -> Vec:
        iad = self.s.inter_asis_mm
        return _v(0.18 * iad, 0.58 * iad, self.z_crest - 28.0)

    @property
    def symphysis(self) -> tuple[float, float, float]:
        """(y, z top, z bottom) of the pubic symphysis (mm)."""
        top = float(self.hip[2] - 14.0)
        return 0.025 * self.s.inter_asis_mm, top, top - self.s.symphysis_height_mm

    # sacrum --------------------------------------------------------------------------------
    @property
    def s1(self) -> Vec:
        """Centre of the S1 upper endplate."""
        return _v(0.0, 0.43 * self.s.inter_asis_mm, self.z_crest - 35.0)

    @property
    def slope(self) -> float:
        return math.radians(self.s.sacral_slope_deg)

    @property
    def endplate_normal(self) -> Vec:
        return _v(0.0, -math.sin(self.slope), math.cos(self.slope))

    def sacral_curve(self, s: np.ndarray) -> tuple[Vec, Vec]:
        """Mid-line point and anterior normal ``(N, 3)`` at arc length ``s`` (mm) below S1."""
        s = np.atleast_1d(np.asarray(s, np.float64))
        rc = self.s.sacrum_length_mm  # radius of curvature: about one sacral length
        th = self.slope - s / rc
        y = self.s1[1] + rc * (np.cos(th) - math.cos(self.slope))
        z = self.s1[2] + rc * (np.sin(th) - math.sin(self.slope))
        pts = np.stack([np.zeros_like(s), y, z], axis=1)
        normal = np.stack([np.zeros_like(s), -np.cos(th), -np.sin(th)], axis=1)
        return pts, normal

    def sacral_half_width(self, s: np.ndarray) -> np.ndarray:
        """Outer half-width (mm) of the sacrum at arc length ``s``."""
        t = np.clip(np.asarray(s, np.float64) / self.s.sacrum_length_mm, 0.0, 1.0)
        return self.s.sacrum_width_mm / 2.0 * (1.0 - 0.75 * t**1.3)

    def sacral_half_thickness(self, s: np.ndarray) -> np.ndarray:
        """Half-thickness (mm) of the sacrum on its mid-line at arc length ``s`` (the lateral
        edges are 45 % thinner)."""
        t = np.clip(np.asarray(s, np.float64) / self.s.sacrum_length_mm, 0.0, 1.0)
        return 20.0 - 14.0 * t

    def auricular_line(self, n: int = 8) -> tuple[Vec, Vec]:
        """Centre line (mm) and radii of the ilium's auricular part beside the left SI joint."""
        s = np.linspace(2.0, 0.5 * self.s.sacrum_length_mm, n)
        pts, normal = self.sacral_curve(s)
        r = 11.0 - 2.0 * np.linspace(0, 1, n)
        lat = self.sacral_half_width(s) + 2.5 + r
        pts = pts + lat[:, None] * _v(1, 0, 0) - normal * 3.0
        return pts, r

    # femur ---------------------------------------------------------------------------------
    def femur_axes(self) -> tuple[Vec, Vec, Vec]:
        """(neck unit vector shaft->head, shaft unit vector pointing distally, neck-shaft junction)."""
        beta = math.radians(8.0)  # anatomical shaft axis: 8 degrees from vertical, converging distally
        phi = math.radians(180.0 - self.s.neck_shaft_angle_deg) - beta  # neck from vertical, medial
        av = math.radians(self.s.femoral_anteversion_deg)
        neck = _v(-math.sin(phi) * math.cos(av), -math.sin(phi) * math.sin(av), math.cos(phi))
        shaft = _v(-math.sin(beta), 0.0, -math.cos(beta))
        junction = self.hip - self.s.femoral_neck_length_mm * neck
        return neck, shaft, junction

    def greater_trochanter(self) -> tuple[Vec, Vec]:
        neck, shaft, j = self.femur_axes()
        return j - 18.0 * shaft + _v(14.0, 7.0, 0.0), _v(12.0, 15.0, 21.0)

    # obturator ring ------------------------------------------------------------------------
    def obturator_ring(self) -> tuple[Vec, Vec]:
        """Closed ring (mm) of the superior pubic ramus, pubic body, ischiopubic ramus and
        ischial body around the left obturator foramen, with radii (mm)."""
        h = self.hip
        ys, ztop, zbot = self.symphysis
        ramus_top = h[2] - 10.0
        inner_top = ramus_top - 1.0 - 9.0
        bottom = inner_top - self.s.obturator_height_mm - 7.0
        pts = np.array([
            [h[0] - 26.0, h[1] - 24.0, ramus_top],          # iliopubic eminence
            [40.0, 0.6 * (h[1] - 24.0) + 0.4 * ys, ramus_top - 1.0],  # superior ramus
            [17.0, ys, ztop - 8.0],                          # pubic body (top)
            [15.0, ys + 3.0, zbot + 6.0],                    # pubic body (bottom)
            [28.0, ys + 20.0, bottom + 6.0],                 # ischiopubic ramus
            [46.0, h[1] + 12.0, bottom],
            [58.0, h[1] + 34.0, bottom + 2.0],               # ischial tuberosity
            [h[0] - 14.0, h[1] + 28.0, 0.5 * (bottom + h[2]) - 4.0],  # ischial body
            [h[0] - 8.0, h[1] + 16.0, h[2] - 22.0],          # below the acetabulum
            [h[0] - 26.0, h[1] - 24.0, ramus_top],           # closed
        ])
        radii = np.array([10.0, 9.0, 9.0, 9.0, 7.0, 7.5, 11.0, 13.0, 13.0, 10.0])
        return pts, radii

    def obturator_centre(self) -> Vec:
        pts, _ = self.obturator_ring()
        ys, ztop, zbot = self.symphysis
        inner_top = pts[0, 2] - 10.0
        x_med = 17.0 + 9.0
        x_lat = pts[7, 0] - 13.0
        return _v(0.5 * (x_med + x_lat), 0.5 * (ys + pts[7, 1]), inner_top - 0.5 * self.s.obturator_height_mm)

    def tuberosity(self) -> Vec:
        pts, _ = self.obturator_ring()
        return pts[6] + _v(3.0, 2.0, -5.0)

    # lumbar spine --------------------------------------------------------------------------
    def vertebrae(self) -> list[tuple[Vec, Vec, float]]:
        """(body centre, unit axis pointing up, body half-width) of L5 and L4 (mm)."""
        out = []
        base = self.s1
        axis = self.endplate_normal
        for half_width, lordosis_deg in ((26.0, 16.0), (25.0, 10.0)):
            ang = math.radians(lordosis_deg)
            # rotate the axis towards the vertical (about x) by the segment's lordosis
            c, sn = math.cos(ang), math.sin(ang)
            axis = _v(0.0, axis[1] * c + axis[2] * sn, -axis[1] * sn + axis[2] * c)
            centre = base + axis * (10.0 + 14.0)
            out.append((centre, _unit(axis), half_width))
            base = centre + axis * 14.0
        return out


def _frame_from_axis(axis: Vec) -> Vec:
    """Rotation whose columns are (x, posterior-ish, axis) for a unit axis in the sagittal plane."""
    z = _unit(axis)
    x = _v(1.0, 0.0, 0.0)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _hip_bone(an: _Anatomy, side: int) -> _Bone:
    """Left (side=+1) or right (-1) hip bone, in LPS."""
    s = an.s
    sgn = _v(side, 1.0, 1.0)

    def P(p):  # ASIS-frame left-side point -> LPS point of this side
        return an.to_lps(np.asarray(p, np.float64) * sgn)

    R = an.mm
    bone = _Bone(1, blend_mm=float(R(3.0)))
    h = an.hip
    rac = s.acetabulum_radius_mm

    # iliac wing: ruled thin plate from the crest down to the supra-acetabular/sciatic root
    aur_pts, aur_r = an.auricular_line()
    piis = aur_pts[-1] + _v(4.0, 8.0, 0.0)
    crest = np.array([an.asis, an.crest_lateral, an.crest_top,
                      _v(0.5 * (an.crest_top[0] + an.psis[0]) + 10.0, 0.47 * s.inter_asis_mm, an.z_crest - 8.0),
                      an.psis])
    root = np.array([
        _v(s.inter_asis_mm / 2.0 - 14.0, 8.0, -0.15 * s.inter_asis_mm),  # AIIS
        _v(h[0] + 4.0, h[1] - 2.0, h[2] + rac + 10.0),                    # above the acetabulum
        _v(h[0] - 16.0, h[1] + 40.0, h[2] + rac + 6.0),                   # top of the sciatic notch
        piis,
    ])
    top = _spline(crest, 40)
    bottom = _spline(root, 40)

    def outward(p):
        d = p - _v(0.0, _BODY_Y_ASIS, 0.0)
        d[:, 2] = 0.0
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    pts, u, v = _ruled_points(top, bottom, 0.9, bulge_mm=9.0, bulge_dir=outward)
    half_t = 1.6 + 2.2 * v**3 + 1.2 * (u < 0.06) + 1.5 * (u > 0.9)
    bone.add(_plate(P(pts), R(half_t)))
    crest_r = np.interp(np.linspace(0, 1, 24), [0, 0.25, 0.5, 0.75, 1], [5.0, 6.5, 5.5, 6.5, 7.5])
    bone.add(_tube(P(_spline(crest, 24)), R(crest_r)))
    # iliac pillar (thick ridge from the acetabular roof to the iliac tubercle)
    pillar = np.array([h + _v(0.0, -4.0, rac + 2.0), an.crest_lateral + _v(-6.0, 0.0, -12.0)])
    bone.add(_tube(P(pillar), R([9.0, 5.5])))
    # sciatic buttress: posterior acetabulum -> notch -> auricular part
    buttress = np.array([h + _v(-10.0, 20.0, 12.0), root[2] + _v(-6.0, 4.0, -4.0), piis + _v(-4.0, -4.0, 0.0)])
    bone.add(_tube(P(buttress), R([12.0, 11.0, 10.0])))
    # auricular part beside the SI joint, and its link up to the PSIS
    bone.add(_tube(P(aur_pts), R(aur_r)))
    bone.add(_tube(P(np.array([aur_pts[0] + _v(0, 0, 4.0), an.psis + _v(4.0, -6.0, -4.0)])), R([9.0, 7.0])))
    bone.add(_tube(P(np.array([aur_pts[-1], an.psis + _v(2.0, -2.0, -6.0)])), R([9.0, 7.0])))
    # posterior and anterior columns of the acetabulum
    bone.add(_tube(P(np.array([h + _v(-10.0, 26.0, 16.0), h + _v(-14.0, 36.0, -8.0), h + _v(-16.0, 36.0, -40.0)])),
                   R([13.0, 15.0, 13.0])))
    bone.add(_tube(P(np.array([h + _v(-6.0, -20.0, 14.0), h + _v(-16.0, -24.0, -4.0)])), R([9.0, 9.0])))
    # supra-acetabular block
    bone.add(_ellipsoid(P(h + _v(2.0, -2.0, rac + 2.0)), R([16.0, 19.0, 12.0])))
    # arcuate line + quadrilateral plate (lateral wall of the true pelvis)
    ring, ring_r = an.obturator_ring()
    s_top = 6.0
    a1 = an.sacral_curve(np.array([s_top]))[0][0] + _v(an.sacral_half_width(s_top) + 3.0, -10.0, 0.0)
    arc = np.array([a1, _v(h[0] - 20.0, 0.5 * (a1[1] + h[1]) + 4.0, h[2] + 40.0),
                    _v(h[0] - 25.0, h[1] - 4.0, h[2] + 8.0), ring[0]])
    wall_bottom = np.array([_v(h[0] - 38.0, h[1] + 46.0, h[2] - 26.0), _v(h[0] - 37.0, h[1] + 14.0, h[2] - 24.0),
                            _v(h[0] - 34.0, h[1] - 4.0, h[2] - 20.0), ring[0] + _v(-6.0, 6.0, -8.0)])
    wpts, _, _ = _ruled_points(_spline(arc, 24), _spline(wall_bottom, 24), 0.9)
    bone.add(_plate(P(wpts), np.full(len(wpts), float(R(1.8)))))
    bone.add(_tube(P(_spline(arc, 16)), R(3.5)))
    # acetabulum: hemispherical cup opening laterally, inferiorly and anteriorly
    incl, av = math.radians(48.0), math.radians(18.0)
    opening = _v(side * math.sin(incl) * math.cos(av), -math.sin(incl) * math.sin(av), -math.cos(incl))
    bone.add(_halfspace_cut(_sphere(P(h), R(rac + 7.0)), opening, P(h)))
    # obturator ring, pubic body, ischial tuberosity and spine
    bone.add(_tube(P(ring), R(ring_r)))
    ys, ztop, zbot = an.symphysis
    bone.add(_rounded_box(P(_v(13.5, ys, 0.5 * (ztop + zbot))), R([11.0, 10.0, 0.5 * s.symphysis_height_mm]),
                          rounding=float(R(6.0))))
    bone.add(_ellipsoid(P(an.tuberosity()), R([13.0, 17.0, 19.0])))
    spine_base = _v(h[0] - 28.0, h[1] + 42.0, h[2] - 24.0)
    spine_tip = _v(0.2 * s.inter_asis_mm, h[1] + 52.0, h[2] - 32.0)
    bone.add(_capsule(P(spine_base), P(spine_tip), float(R(6.0)), float(R(3.0))))
    bone.cut(_sphere(P(h), R(rac)))
    return bone


def _femur(an: _Anatomy, side: int) -> tuple[_Bone, Callable, Callable]:
    """Left (side=+1) or right (-1) proximal femur, with its cortical-thickness (mm) and
    interior-HU functions of ``(X, Y, Z)``."""
    s = an.s
    sgn = _v(side, 1.0, 1.0)

    def P(p):
        return an.to_lps(np.asarray(p, np.float64) * sgn)

    R = an.mm
    neck, shaft, j = an.femur_axes()
    h = an.hip
    rh = s.femoral_head_radius_mm
    bone = _Bone(3 if side > 0 else 4, blend_mm=float(R(4.0)))
    bone.add(_sphere(P(h), R(rh)))
    bone.add(_capsule(P(h), P(j), float(R(0.66 * rh)), float(R(0.78 * rh))))
    bone.add(_capsule(P(j - 8.0 * shaft), P(j + 60.0 * shaft), float(R(18.0)), float(R(14.0))))
    bone.add(_capsule(P(j + 60.0 * shaft), P(j + 500.0 * shaft), float(R(14.0)), float(R(12.5))))
    gt_c, gt_r = an.greater_trochanter()
    bone.add(_ellipsoid(P(gt_c), R(gt_r)))
    lt = j + 50.0 * shaft + _v(-14.0, 9.0, 0.0)
    bone.add(_ellipsoid(P(lt), R([8.0, 8.0, 11.0])))
    bone.add(_capsule(P(gt_c + _v(-4.0, 8.0, -6.0)), P(lt + _v(4.0, 2.0, 4.0)), float(R(7.0)), float(R(6.0))))
    # the shaft (from 40 mm below the junction) has a thicker cortex and a fatty medullary canal
    z0 = float(P(j + 40.0 * shaft)[2])
    ramp = float(R(50.0))
    tc0 = float(R(s.cortical_thickness_mm))
    hin0 = s.cancellous_hu

    # the head has a thin subchondral cortex (0.6 x) over dense trabecular bone (1.35 x)
    hc = P(h).astype(np.float32)
    rh_in = np.float32(R(rh + 1.5))

    def shaft_fraction(Z):
        return np.clip((np.float32(z0) - Z) / np.float32(ramp), 0.0, 1.0)

    def in_head(X, Y, Z):
        return ((X - hc[0]) ** 2 + (Y - hc[1]) ** 2 + (Z - hc[2]) ** 2 < rh_in * rh_in).astype(np.float32)

    def cortical(X, Y, Z):
        return np.float32(tc0) * (1.0 + 1.5 * shaft_fraction(Z) - 0.4 * in_head(X, Y, Z))

    def interior(X, Y, Z):
        f = shaft_fraction(Z)
        return np.float32(hin0) * (1.0 - f + 0.35 * in_head(X, Y, Z)) + np.float32(HU_MARROW) * f

    return bone, cortical, interior


def _sacral_plate(an: _Anatomy) -> _Prim:
    """The sacrum as a thick curved plate, in closed form.

    Its mid-surface is the sagittal arc of :meth:`_Anatomy.sacral_curve` (centre ``O``, radius
    one sacral length) swept along x, with the lateral parts shifted 8 mm anteriorly at the
    alae. A point's arc length ``s`` comes from its polar angle about ``O``, its depth from its
    radius; the cross-section at ``s`` is a plate of half-width ``sacral_half_width(s)`` and
    half-thickness ``sacral_half_thickness(s)`` (35 % thinner at the lateral edges, which are
    rounded). ``s = 0`` is the S1 endplate plane; the alae's top slopes 14 mm down laterally.
    """
    s = an.s
    length = s.sacrum_length_mm
    rc = length
    oy = an.s1[1] - rc * math.cos(an.slope)
    oz = an.s1[2] - rc * math.sin(an.slope)
    w0_half = s.sacrum_width_mm / 2.0
    scale, cen = np.float32(s.scale), an.centre.astype(np.float32)
    w_top = float(an.sacral_half_width(0.0) - 0.55 * an.sacral_half_thickness(0.0))

    def sdf(X, Y, Z):
        xa = X / scale + cen[0]
        dy = Y / scale + cen[1] - np.float32(oy)
        dz = Z / scale + cen[2] - np.float32(oz)
        rho = np.sqrt(dy * dy + dz * dz)
        arc = (np.float32(an.slope) - np.arctan2(dz, np.maximum(dy, np.float32(1e-3)))) * np.float32(rc)
        t = np.clip(arc / np.float32(length), 0.0, 1.0)
        ht = np.float32(20.0) - np.float32(14.0) * t
        w_out = np.float32(w0_half) * (1.0 - np.float32(0.75) * t ** np.float32(1.3))
        w = np.maximum(w_out - np.float32(0.55) * ht, 1.0)
        ax = np.abs(xa)
        rel = np.minimum(ax / w, 1.0)
        q = (np.float32(rc) - rho) - np.float32(8.0) * (xa / np.float32(w0_half)) ** 2
        d_cross = np.sqrt(np.maximum(ax - w, 0.0) ** 2 + q * q) - ht * (1.0 - np.float32(0.45) * rel * rel)
        ala = np.clip((ax / np.float32(w_top) - np.float32(0.34)) / np.float32(0.66), 0.0, 1.0)
        top = np.float32(14.0) * ala ** np.float32(1.5)
        d_s = np.maximum(top - arc, arc - np.float32(length))
        out = np.sqrt(np.maximum(d_cross, 0.0) ** 2 + np.maximum(d_s, 0.0) ** 2)
        out = out + np.minimum(np.maximum(d_cross, d_s), 0.0)
        return np.where(dy > 0.0, out * scale, np.float32(1e4))

    ss = np.linspace(0.0, length, 12)
    mid, _ = an.sacral_curve(ss)
    ext = w0_half + 16.0
    lo = an.to_lps(mid.min(axis=0) - _v(ext, 20.0, 20.0))
    hi = an.to_lps(mid.max(axis=0) + _v(ext, 20.0, 20.0))
    return _Prim(lo, hi, sdf)


def _sacrum(an: _Anatomy) -> _Bone:
    s = an.s
    R = an.mm
    bone = _Bone(2, blend_mm=float(R(3.0)))
    length = s.sacrum_length_mm
    bone.add(_sacral_plate(an))
    # coccyx
    cs = np.linspace(length + 4.0, length + 34.0, 4)
    cp, _ = an.sacral_curve(cs)
    bone.add(_tube(an.to_lps(cp), R([6.0, 5.0, 4.0, 3.0])))
    # sacral canal, behind the fused vertebral bodies
    cs = np.linspace(-10.0, 0.8 * length, 6)
    cp, cn = an.sacral_curve(cs)
    back = an.sacral_half_thickness(cs) - 9.0
    bone.cut(_tube(an.to_lps(cp - back[:, None] * cn), R(np.linspace(6.0, 2.5, 6))))
    # four pairs of anterior sacral foramina
    for frac, lat, r in ((0.17, 0.44, 4.5), (0.37, 0.42, 4.0), (0.56, 0.40, 3.5), (0.73, 0.38, 3.0)):
        sk = frac * length
        c, n = an.sacral_curve(np.array([sk]))
        for side in (1.0, -1.0):
            l = side * lat * float(an.sacral_half_width(sk))
            cc = c[0] + _v(l, 0.0, 0.0) + 8.0 * (l / (s.sacrum_width_mm / 2.0)) ** 2 * n[0]
            # the anterior half only: the foramina are canals, not straight holes
            bone.cut(_capsule(an.to_lps(cc - 2.0 * n[0]), an.to_lps(cc + 25.0 * n[0]), float(R(r))))
    return bone


def _lumbar(an: _Anatomy) -> tuple[_Bone, list[_Prim]]:
    """L5 and L4 (label 5) and the L5-S1 and L4-L5 discs (soft tissue primitives)."""
    R = an.mm
    bone = _Bone(5, blend_mm=float(R(3.0)))
    discs = []
    prev_top = an.s1
    for idx, (c, axis, hw) in enumerate(an.vertebrae()):
        F = _frame_from_axis(axis)
        post = F[:, 1]
        lat = F[:, 0]
        ry = 19.0
        bone.add(_elliptic_cylinder(an.to_lps(c), F, float(R(hw)), float(R(ry)), float(R(13.5)), float(R(2.5))))
        disc_c = 0.5 * (prev_top + (c - 13.5 * axis))
        discs.append(_elliptic_cylinder(an.to_lps(disc_c), F, float(R(hw - 1.0)), float(R(ry - 1.0)),
                                        float(R(7.0)), float(R(2.0))))
        prev_top = c + 13.5 * axis
        for sd in (1.0, -1.0):
            ped0 = c + post * (ry - 4.0) + sd * lat * 13.0 + axis * 4.0
            ped1 = ped0 + post * 16.0 + sd * lat * 2.0
            bone.add(_capsule(an.to_lps(ped0), an.to_lps(ped1), float(R(5.0))))
            # lamina to the midline, transverse and articular processes
            lam = c + post * (ry + 27.0) + axis * 0.0
            bone.add(_capsule(an.to_lps(ped1), an.to_lps(lam), float(R(4.5))))
            tip = ped1 + sd * lat * (28.0 if idx == 0 else 24.0) + axis * (6.0 if idx == 0 else 2.0) - post * 2.0
            bone.add(_capsule(an.to_lps(ped1 + sd * lat * 2.0), an.to_lps(tip), float(R(6.5 if idx == 0 else 5.0)),
                              float(R(5.0 if idx == 0 else 3.5))))
            facet = ped1 + sd * lat * 3.0
            bone.add(_capsule(an.to_lps(facet + axis * 10.0), an.to_lps(facet - axis * 12.0),
                              float(R(5.0))))
        sp0 = c + post * (ry + 27.0)
        sp1 = sp0 + post * 26.0 - axis * 8.0
        bone.add(_capsule(an.to_lps(sp0), an.to_lps(sp1), float(R(5.0)), float(R(4.0))))
        bone.add(_capsule(an.to_lps(sp0 - axis * 7.0), an.to_lps(sp1 - axis * 6.0), float(R(4.0)), float(R(3.5))))
    return bone, discs


# ---------------------------------------------------------------------------------------------
# Soft tissue
# ---------------------------------------------------------------------------------------------


def _ellipse_sdf(X, Y, ax, ay):
    k0 = np.sqrt((X / ax) ** 2 + (Y / ay) ** 2)
    k1 = np.sqrt((X / ax**2) ** 2 + (Y / ay**2) ** 2)
    return k0 * (k0 - 1.0) / np.maximum(k1, np.float32(1e-6))


def _body_sdf(an: _Anatomy, grid: _Grid, ax: float, ay: float) -> np.ndarray:
    """In-slice signed distance (mm) to the skin ``(I, J, K)``: an elliptic trunk that narrows
    slightly above the iliac crests and morphs, over 30 mm about the gluteal fold (30 mm below
    the ischial tuberosities), into two thighs that follow the femoral shafts. Distances are
    measured within each axial slice, so the fat layer is a skin layer, never a horizontal slab."""
    X, Y, Z = grid.coords(tuple(slice(0, n) for n in grid.shape))
    yc = float(an.to_lps(_v(0.0, _BODY_Y_ASIS, 0.0))[1])
    z_crest = float(an.to_lps(_v(0.0, 0.0, an.z_crest))[2])
    waist = 1.0 - 0.07 * np.clip((Z - np.float32(z_crest)) / 60.0, 0.0, 1.0)
    trunk = _ellipse_sdf(X, Y - np.float32(yc), np.float32(ax) * waist, np.float32(ay)).astype(np.float32)
    z_fold = float(an.to_lps(an.tuberosity() + _v(0.0, 0.0, -30.0))[2])
    below = grid.axes[2] < z_fold + 15.0
    if np.any(below):
        kk = np.nonzero(below)[0]
        Zb = Z[:, :, kk]
        neck, shaft, j = an.femur_axes()
        thighs = None
        for side in (1.0, -1.0):
            jl = an.to_lps(j * _v(side, 1, 1))
            sh = shaft * _v(side, 1, 1)
            xs = jl[0] + (Zb - jl[2]) * np.float32(sh[0] / sh[2])
            x0 = jl[0] + (z_fold - jl[2]) * float(sh[0] / sh[2])
            cx = xs - np.float32(x0) + np.float32(side * 0.47 * ax)
            taper = 1.0 - 0.1 * np.clip((np.float32(z_fold) - Zb) / 100.0, 0.0, 2.0)
            thigh = _ellipse_sdf(X - cx, Y - np.float32(yc + 0.03 * ay),
                                 np.float32(0.5 * ax) * taper, np.float32(0.8 * ay) * taper).astype(np.float32)
            thighs = thigh if thighs is None else np.minimum(thighs, thigh)
        w = np.clip((np.float32(z_fold + 15.0) - Zb) / np.float32(30.0), 0.0, 1.0)
        w = w * w * (3.0 - 2.0 * w)
        trunk[:, :, kk] = trunk[:, :, kk] * (1.0 - w) + thighs * w
    return trunk


def _ramp(sdf: np.ndarray, h: float) -> np.ndarray:
    """Inside fraction of a voxel of size ``h`` (mm) at signed distance ``sdf``: 1 inside, 0
    outside, linear over one voxel."""
    return np.clip(0.5 - sdf / np.float32(h), 0.0, 1.0)


def _paint(grid: _Grid, soft: np.ndarray, mask: np.ndarray, prim: _Prim, hu: float) -> None:
    """Blend ``hu`` into ``soft`` inside ``prim``, weighted by ``mask`` (the deep body region)."""
    box = grid.index_range(prim.lo - grid.h, prim.hi + grid.h)
    if box is None:
        return
    f = _ramp(prim.sdf(*grid.coords(box)), grid.h) * mask[box]
    soft[box] += f * (np.float32(hu) - soft[box])


def _soft_tissue(an: _Anatomy, grid: _Grid, rng: np.random.Generator,
                 disc_prims: list[_Prim]) -> tuple[np.ndarray, np.ndarray]:
    """HU of everything but bone ``(I, J, K)`` and the body fraction ``(I, J, K)``."""
    s = an.s
    R = an.mm
    h = grid.h
    # the body encloses the skeleton with at least 25 mm of tissue
    gt_c, gt_r = an.greater_trochanter()
    ax = max(s.body_semi_axis_lr_mm, float(R(max(gt_c[0] + gt_r[0], an.crest_lateral[0] + 8.0))) + 25.0)
    yc = _BODY_Y_ASIS
    ay = max(s.body_semi_axis_ap_mm, float(R(max(yc - (-5.0), an.psis[1] + 8.0 - yc))) + 25.0)
    body = _body_sdf(an, grid, ax, ay)
    inside = _ramp(body, h)
    deep = _ramp(body + np.float32(s.fat_thickness_mm), h)
    soft = np.float32(HU_AIR) + inside * np.float32(HU_FAT - HU_AIR) + deep * np.float32(HU_SOFT - HU_FAT)

    hip = an.hip
    neck, shaft, j = an.femur_axes()
    ys, ztop, zbot = an.symphysis
    P = an.to_lps
    # pelvic fat around the bladder and rectum
    _paint(grid, soft, deep, _ellipsoid(P(_v(0.0, 70.0, zbot + 25.0)), R([52.0, 48.0, 40.0])), HU_FAT + 15.0)
    for side in (1.0, -1.0):
        sg = _v(side, 1.0, 1.0)
        # psoas: along the lumbar spine, over the pelvic brim, to the lesser trochanter
        psoas = np.array([[32.0, 92.0, an.z_crest + 110.0], [40.0, 88.0, an.z_crest + 20.0],
                          [56.0, 66.0, an.z_crest - 50.0], [hip[0] - 18.0, 22.0, hip[2] - 8.0],
                          j + 50.0 * shaft + _v(-12.0, 4.0, 0.0)]) * sg
        for prim in _tube(P(psoas), R([16.0, 20.0, 19.0, 15.0, 12.0])):
            _paint(grid, soft, deep, prim, HU_MUSCLE)
        # iliacus (in the iliac fossa), gluteus medius/minimus (outside the wing), gluteus maximus
        iliacus = _v(88.0, 50.0, an.z_crest - 40.0) * sg
        _paint(grid, soft, deep, _ellipsoid(P(iliacus), R([22.0, 36.0, 34.0])), HU_MUSCLE)
        _paint(grid, soft, deep, _ellipsoid(P(_v(an.crest_lateral[0] + 6.0, 80.0, an.z_crest - 45.0) * sg),
                                            R([24.0, 48.0, 45.0])), HU_MUSCLE)
        _paint(grid, soft, deep, _ellipsoid(P(_v(82.0, 150.0, hip[2] - 20.0) * sg), R([52.0, 28.0, 80.0])), HU_MUSCLE)
        # thigh muscles around the femoral shaft
        top = j + 40.0 * shaft
        _paint(grid, soft, deep, _capsule(P(top * sg), P((j + 500.0 * shaft) * sg), float(R(58.0))), HU_MUSCLE)
    # bladder (urine) behind the symphysis, rectum along the sacrum
    _paint(grid, soft, deep, _ellipsoid(P(_v(0.0, 42.0, zbot + 32.0)), R([34.0, 27.0, 28.0])), HU_URINE)
    rect, _ = an.sacral_curve(np.array([0.45, 0.75, 1.0]) * s.sacrum_length_mm)
    rect = rect + _v(0.0, -30.0, 0.0)
    for prim in _tube(P(np.vstack([rect, [[0.0, rect[-1, 1] - 22.0, zbot - 10.0]]])), R([14.0, 15.0, 14.0, 12.0])):
        _paint(grid, soft, deep, prim, 30.0)
    if rng.uniform() < 0.6:
        _paint(grid, soft, deep, _ellipsoid(P(rect[1] + _v(0.0, 2.0, 0.0)), R([8.0, 6.0, 12.0])), HU_GAS)
    # lower-abdominal bowel: a few fat lobules and the gas pockets
    for _ in range(6):
        c = _v(rng.uniform(-80, 80), rng.uniform(-10, 60), rng.uniform(-20, an.z_crest + 60))
        _paint(grid, soft, deep, _ellipsoid(P(c), R(rng.uniform(8.0, 18.0, 3))), HU_FAT + 10.0)
    for _ in range(s.bowel_gas_pockets):
        c = _v(rng.uniform(-85, 85), rng.uniform(-15, 55), rng.uniform(-30, an.z_crest + 70))
        _paint(grid, soft, deep, _ellipsoid(P(c), R(rng.uniform(6.0, 22.0, 3))), HU_GAS)
    for prim in disc_prims:
        _paint(grid, soft, deep, prim, HU_DISC)
    return soft, inside


def _smooth_noise(rng: np.random.Generator, grid: _Grid, lattice_mm: float) -> np.ndarray:
    """Unit-variance smooth noise ``(I, J, K)``: iid normal values on a lattice of spacing
    ``lattice_mm`` interpolated with cubic B-splines (weights normalised to unit L2 norm)."""
    mats = []
    for ax in grid.axes:
        nodes = np.arange(math.floor(ax[0] / lattice_mm) - 2, math.ceil(ax[-1] / lattice_mm) + 3) * lattice_mm
        t = np.abs(ax[:, None].astype(np.float64) - nodes[None, :]) / lattice_mm
        w = np.where(t < 1.0, 2.0 / 3.0 - t**2 + 0.5 * t**3, np.where(t < 2.0, (2.0 - t) ** 3 / 6.0, 0.0))
        mats.append((w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32))
    c = rng.standard_normal((mats[0].shape[1], mats[1].shape[1], mats[2].shape[1])).astype(np.float32)
    c = np.tensordot(mats[0], c, axes=(1, 0))
    c = np.tensordot(c, mats[1], axes=(1, 1)).transpose(0, 2, 1)
    return np.ascontiguousarray(np.tensordot(c, mats[2], axes=(2, 1)))


# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------


def pelvis_landmarks(shape: PelvisShape | None = None) -> dict[str, np.ndarray]:
    """Anatomical landmarks ``{name: (3,) LPS mm}`` of the phantom built from ``shape`` (default:
    :meth:`PelvisShape.default`), in the frame of :func:`make_pelvis_phantom`'s affine (they do
    not depend on the grid's spacing or size).

    Names: ``hip_centre_{left,right}`` (femoral head = acetabulum centres), ``asis_*``,
    ``psis_*``, ``iliac_crest_top_*``, ``obturator_centre_*``, ``ischial_tuberosity_*``,
    ``greater_trochanter_top_*``, ``pubic_symphysis`` (centre), ``sacral_promontory``,
    ``s1_endplate_centre``.
    """
    if shape is None:
        shape = PelvisShape.default()
    if not isinstance(shape, PelvisShape):
        raise PhantomInputError(f"shape must be a PelvisShape, got {type(shape).__name__}")
    an = _Anatomy(shape)
    ys, ztop, zbot = an.symphysis
    gt_c, gt_r = an.greater_trochanter()
    out = {
        "pubic_symphysis": an.to_lps(_v(0.0, ys, 0.5 * (ztop + zbot))),
        "sacral_promontory": an.to_lps(an.s1 + float(an.sacral_half_thickness(0.0))
                                       * _v(0.0, -math.cos(an.slope), -math.sin(an.slope))),
        "s1_endplate_centre": an.to_lps(an.s1),
    }
    for side, name in ((1.0, "left"), (-1.0, "right")):
        m = _v(side, 1.0, 1.0)
        out[f"hip_centre_{name}"] = an.to_lps(an.hip * m)
        out[f"asis_{name}"] = an.to_lps(an.asis * m)
        out[f"psis_{name}"] = an.to_lps(an.psis * m)
        out[f"iliac_crest_top_{name}"] = an.to_lps(an.crest_top * m)
        out[f"obturator_centre_{name}"] = an.to_lps(an.obturator_centre() * m)
        out[f"ischial_tuberosity_{name}"] = an.to_lps((an.tuberosity() + _v(0, 0, -19.0)) * m)
        out[f"greater_trochanter_top_{name}"] = an.to_lps((gt_c + _v(0, 0, gt_r[2])) * m)
    return out


def _check_grid(spacing_mm: object, size_mm: object) -> tuple[float, tuple[int, int, int]]:
    if isinstance(spacing_mm, bool) or not isinstance(spacing_mm, (int, float, np.integer, np.floating)):
        raise PhantomInputError(f"spacing_mm must be a number (mm), got {spacing_mm!r}")
    spacing = float(spacing_mm)
    if not (math.isfinite(spacing) and 0.2 <= spacing <= 20.0):
        raise PhantomInputError(f"spacing_mm must be between 0.2 and 20 mm, got {spacing_mm!r}")
    try:
        size = np.asarray(size_mm, dtype=np.float64)
    except (TypeError, ValueError):
        raise PhantomInputError(f"size_mm must be three lengths (mm), got {size_mm!r}") from None
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size < 2 * spacing):
        raise PhantomInputError(f"size_mm must be three finite lengths of at least 2 voxels (mm), got {size_mm!r}")
    shape = tuple(max(int(round(v / spacing)), 2) for v in size)
    n = shape[0] * shape[1] * shape[2]
    if n > MAX_VOXELS:
        raise PhantomInputError(
            f"size_mm={tuple(size)} at spacing_mm={spacing} gives {n} voxels, more than the {MAX_VOXELS} allowed"
        )
    return spacing, shape  # type: ignore[return-value]


def make_pelvis_phantom(
    seed: int | None = 0,
    *,
    shape: PelvisShape | None = None,
    spacing_mm: float = 2.0,
    size_mm: tuple[float, float, float] = (400.0, 300.0, 300.0),
) -> CTVolume:
    """A seeded adult pelvis CT.

    Args:
        seed: non-negative integer: the patient's shape is ``PelvisShape.sample(seed)`` (unless
            ``shape`` is given) and the seed drives all texture (noise, bowel gas). ``None``:
            the mean shape :meth:`PelvisShape.default` with texture stream 0.
        shape: explicit shape parameters (then ``seed`` only drives the texture).
        spacing_mm: isotropic voxel spacing (mm), 0.2 to 20.
        size_mm: extent of the grid along x (left-right), y (antero-posterior), z
            (cranio-caudal) in mm; each axis gets ``round(size / spacing)`` voxels.

    Returns:
        :class:`CTVolume` with ``hu`` ``(I, J, K)`` float32, an axis-aligned LPS ``affine``
        whose grid centre is the LPS origin, ``source="phantom:{seed}"`` and ``labels``
        ``(I, J, K)`` uint8 (0 background, 1 pelvis, 2 sacrum, 3 left femur, 4 right femur,
        5 lumbar spine).

    Raises:
        PhantomInputError: a bad seed, shape, spacing or size.
    """
    if seed is not None:
        seed = _check_seed(seed)
    if shape is None:
        shape = PelvisShape.default() if seed is None else PelvisShape.sample(seed)
    elif not isinstance(shape, PelvisShape):
        raise PhantomInputError(f"shape must be a PelvisShape or None, got {type(shape).__name__}")
    spacing, grid_shape = _check_grid(spacing_mm, size_mm)

    an = _Anatomy(shape)
    grid = _Grid(grid_shape, spacing)
    rng = tagged_rng(0 if seed is None else seed, TAG_PHANTOM_TEXTURE)

    tc = float(an.mm(shape.cortical_thickness_mm))
    for side in (1, -1):
        _hip_bone(an, side).render(grid, tc, shape.cancellous_hu)
    _sacrum(an).render(grid, tc, 0.8 * shape.cancellous_hu)  # the sacrum is less dense
    lumbar, discs = _lumbar(an)
    lumbar.render(grid, tc, shape.cancellous_hu)
    for side in (1, -1):
        bone, cortical, interior = _femur(an, side)
        bone.render(grid, cortical, interior)

    soft, inside = _soft_tissue(an, grid, rng, discs)
    h = np.float32(spacing)
    bone_frac = _ramp(grid.D, h)
    inner_frac = _ramp(grid.D + grid.TC, h)
    hu = soft * (1.0 - bone_frac) + np.float32(shape.cortical_hu) * (bone_frac - inner_frac) + grid.HIN * inner_frac
    noise = _smooth_noise(rng, grid, 12.0) * np.float32(9.0)
    fine = _smooth_noise(rng, grid, 4.0)
    noise += fine * (np.float32(7.0) + np.float32(35.0) * inner_frac * (grid.HIN > 100.0))
    hu += noise * inside
    np.maximum(hu, np.float32(HU_AIR), out=hu)
    labels = np.where(grid.D <= 0.0, grid.L, np.uint8(0)).astype(np.uint8)

    affine = np.eye(4)
    affine[:3, :3] *= spacing
    affine[:3, 3] = [-(n - 1) / 2.0 * spacing for n in grid_shape]
    return CTVolume(hu=hu.astype(np.float32, copy=False), affine=affine, source=f"phantom:{seed}", labels=labels)


def write_phantom_nifti(path: str | os.PathLike, seed: int | None = 0, *,
                        labels_path: str | os.PathLike | None = None, **kwargs) -> CTVolume:
    """Build :func:`make_pelvis_phantom` ``(seed, **kwargs)`` and write it as NIfTI (``.nii`` or
    ``.nii.gz``, float32 HU, RAS affine ``diag(-1, -1, 1, 1) @ LPS affine``), atomically
    (temporary file beside the target, then ``os.replace``). ``labels_path`` optionally writes
    the label map (uint8) the same way. Returns the volume."""
    import nibabel as nib

    for name, p in (("path", path), ("labels_path", labels_path)):
        if p is None:
            continue
        text = os.fspath(p)
        if not (text.endswith(".nii") or text.endswith(".nii.gz")):
            raise PhantomInputError(f"{name} must end in .nii or .nii.gz, got {text!r}")
    volume = make_pelvis_phantom(seed, **kwargs)
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ volume.affine
    outputs = [(path, volume.hu.astype(np.float32))]
    if labels_path is not None:
        outputs.append((labels_path, volume.labels.astype(np.uint8)))
    for target, data in outputs:
        img = nib.Nifti1Image(data, ras)
        img.header.set_xyzt_units("mm")
        img.header["descrip"] = volume.source.encode()[:79]
        img.set_qform(ras, code=1)
        img.set_sform(ras, code=1)
        with atomic_path(target) as tmp:
            nib.save(img, tmp)
    return volume
