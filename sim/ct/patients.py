"""Virtual patients: plausible new anatomies derived from one CT, reproducible from a seed.

A virtual patient is the CT warped by an anisotropic scaling and a smooth random deformation,
with perturbed tissue densities, scanner noise and optionally a truncated field of view. Every
choice is held in a :class:`VirtualPatientParams` (seed included), so a manifest entry
(:meth:`VirtualPatientParams.to_dict`) regenerates the volume bit for bit;
:class:`VirtualPatientRanges` draws such parameters from a ``numpy.random.Generator``.

Geometry (units mm; frame LPS, see ``docs/conventions.md``)
    The output keeps the input grid (shape and affine). Output voxel centre ``x`` (LPS mm)
    samples the input at the backward map::

        phi(x) = c + S^-1 (x + u(x) - c)

    with ``c`` the scaling centre (default :func:`sim.ct.anatomy.anatomy_center`), ``S =
    diag(scale)`` along LPS x, y, z and ``u`` the random displacement field (mm) on the output
    grid (:func:`displacement_field`). So the new anatomy is the input scaled by ``S`` about
    ``c`` and then deformed by approximately ``-u``. Scaling and deformation are one map and
    one trilinear resampling (``scipy.ndimage.map_coordinates``, order 1 for HU, order 0 =
    nearest for the label map); samples outside the input volume are -1000 HU (label 0).

Displacement field
    Each LPS component of ``u`` is white noise on a coarse grid (node spacing
    ``deformation_length_mm / 4``, at least one voxel) smoothed with a Gaussian of standard
    deviation ``deformation_length_mm / 2``, so its correlation falls as
    ``exp(-r^2 / L^2)``: to 1/e at ``r = L = deformation_length_mm`` (the correlation length).
    It is upsampled to the voxels by trilinear interpolation, made zero-mean (no net shift of
    the anatomy) and scaled so that the RMS length of the displacement vectors over the grid
    is ``deformation_mm``.

    Invertibility guard: on a trilinear field, each derivative ``du_i/dx_j`` inside a coarse
    cell is a convex combination of the cell's four edge differences along ``j``, so the
    per-cell maximum of those differences bounds the displacement gradient everywhere in the
    cell. When that bound's Frobenius norm exceeds :data:`MAX_DISPLACEMENT_GRADIENT` = 0.5
    anywhere, the whole field is scaled down until it does not. Then ``||grad u||_2 <= 0.5``
    everywhere, the singular values of ``I + grad u`` lie in [0.5, 1.5] and the Jacobian
    determinant of ``phi`` is at least ``0.125 / (sx sy sz) > 0``: the map never folds and
    no tissue is compressed or stretched locally by more than a factor of 2 along any
    direction. The realised RMS is then below ``deformation_mm``; this happens only for
    strong, short fields (RMS above about a tenth of the correlation length).

Hounsfield units (applied after resampling, in this order)
    1. A smooth, strictly increasing transfer curve ``f(HU)`` (:func:`perturb_hu`): soft
       tissue in the plateau :data:`SOFT_TISSUE_HU` = [-200, 100] HU (fat, water, muscle,
       organs) becomes ``offset + scale * HU``; bone above ``t =``
       :data:`sim.ct.anatomy.BONE_HU_THRESHOLD` (200 HU) + 100 HU becomes ``t + bone_scale (HU
       - t)``; air and lung below -300 HU are unchanged. Between them the changes fade with
       C1 smoothsteps over 100 HU ([-300, -200], [100, 200] and, for bone, [200, 300] HU),
       so no iso-HU contour appears. Within the parameter limits (:data:`PARAM_LIMITS`) the
       slope ``f'`` stays in [0.1, 1.9]: the curve is continuous and monotone, so the order
       of tissues is kept.
    2. Gaussian noise of standard deviation ``noise_hu`` (seeded), only where the output
       sampled the input (not in the -1000 HU fill). Values are not clipped (CTs hold air
       below -1000 HU too).
    3. Truncation: voxels farther than ``fov_radius_mm`` from the CT's axial centre line (the
       line through the grid centre along LPS z; distance in the x-y plane) and voxels
       within ``z_crop_mm = (inferior, superior)`` mm of the grid's lower or upper z face
       become exactly -1000 HU (label 0), like a limited reconstruction circle or a shorter
       scan.

Default ranges (:class:`VirtualPatientRanges`) and why
    * scale 0.92-1.08 per axis, independently: adult pelvic breadths and heights vary with a
      coefficient of variation of about 5-7 % (e.g. inter-ASIS distance 205-275 mm about
      240 mm), so +-8 % spans about +-1.5 SD; independent axes give wide/narrow and
      tall/short proportions.
    * deformation 0-6 mm RMS at correlation length 40-80 mm: shape differences left after
      scaling (iliac flare, sacral slope: a few degrees over 100 mm, i.e. several mm) are
      smooth over tens of millimetres. The typical RMS strain is a few percent. The largest
      local gradient is about 5 x RMS / L, so in the strong corner of the ranges (RMS above
      about L / 10, e.g. more than 4 mm at 40 mm) the guard caps it at 0.5; with 30 mm
      (RMS 6 mm: local gradients near 1, i.e. folding) it would cap most strong draws,
      hence 40 mm.
    * soft-tissue offset -20..20 HU and scale 0.95-1.05, bone scale 0.85-1.15: calibration
      differences between scanners and kVp, and bone mineral density variation between
      adults (about +-15 % between young and older adults).
    * noise 0-15 HU: the standard deviation of routine abdominal CT in soft tissue.
    * field-of-view truncation with probability 0.3 at radius 160-240 mm: large patients
      exceed the 320-500 mm reconstruction circle; z crop 0-30 mm at each end with
      probability 0.3: scans end at different levels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Mapping

import numpy as np
from scipy import ndimage

from sim.ct.anatomy import BONE_HU_THRESHOLD, anatomy_center
from sim.core.errors import InputError
from sim.core.seeds import KIND_VP_FIELD, KIND_VP_NOISE, rng_for
from sim.ct.volume import CTVolume

__all__ = [
    "AIR_HU",
    "AugmentConfigError",
    "BONE_RAMP_HU",
    "MAX_DISPLACEMENT_GRADIENT",
    "PARAM_LIMITS",
    "SOFT_TISSUE_HU",
    "SOFT_TISSUE_TAPER_HU",
    "VirtualPatientParams",
    "VirtualPatientRanges",
    "displacement_field",
    "make_virtual_patient",
    "perturb_hu",
]

#: HU written where the output leaves the input volume or is truncated.
AIR_HU = -1000.0

#: Largest Frobenius norm (mm/mm, dimensionless) allowed for the displacement gradient
#: ``grad u`` anywhere; see the module docstring (Jacobian determinant >= 0.125 / det S).
MAX_DISPLACEMENT_GRADIENT = 0.5

#: ``(low, high)`` HU of the soft-tissue plateau where ``offset + scale * HU`` applies fully.
SOFT_TISSUE_HU = (-200.0, 100.0)
#: Width (HU) of the smoothsteps that fade the soft-tissue change in and out of the plateau.
SOFT_TISSUE_TAPER_HU = 100.0
#: Width (HU) of the smoothstep above :data:`sim.ct.anatomy.BONE_HU_THRESHOLD` over which the bone
#: scaling fades in.
BONE_RAMP_HU = 100.0

#: Hard limits ``(low, high)`` of every parameter (for a single value, and for both ends of a
#: sampling range). Beyond them the result would not be a plausible patient, or the HU curve
#: could lose monotonicity: with |offset| <= 30 HU, |scale - 1| <= 0.08 and |bone_scale - 1|
#: <= 0.5 its slope stays >= 0.1 (1 - 0.015 x 54 - 0.08 in the lower taper, 1 - 0.5 x 1.69 in
#: the bone ramp).
PARAM_LIMITS: dict[str, tuple[float, float]] = {
    "scale": (0.5, 2.0),
    "deformation_mm": (0.0, 30.0),
    "deformation_length_mm": (10.0, 500.0),
    "soft_tissue_hu_offset": (-30.0, 30.0),
    "soft_tissue_hu_scale": (0.92, 1.08),
    "bone_hu_scale": (0.5, 1.5),
    "noise_hu": (0.0, 100.0),
    "fov_radius_mm": (50.0, 1000.0),
    "z_crop_mm": (0.0, 1000.0),
}

_SEED_MAX = 2**63 - 1
#: Coarse-grid node spacing and Gaussian smoothing, as fractions of the correlation length.
_NODE_FRACTION = 0.25
_SMOOTH_FRACTION = 0.5
_TRUNCATE_SD = 3.0
#: Output voxels per resampling slab (bounds the float64 coordinate memory to ~50 MB).
_SLAB_VOXELS = 1 << 21


class AugmentConfigError(InputError):
    """Unusable virtual-patient parameters, ranges or inputs; the message names the key."""


# --------------------------------------------------------------------------- validation
def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise AugmentConfigError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise AugmentConfigError(f"{name} must be finite, got {value!r}")
    return v


def _limited(name: str, key: str, value: Any, unit: str) -> float:
    v = _number(name, value)
    lo, hi = PARAM_LIMITS[key]
    if not lo <= v <= hi:
        raise AugmentConfigError(f"{name} = {v:g} {unit} is outside the allowed range [{lo:g}, {hi:g}] {unit}")
    return v


def _sequence(name: str, value: Any, n: int) -> tuple:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != n:
        raise AugmentConfigError(f"{name} must be a sequence of {n} numbers, got {value!r}")
    return tuple(value)


# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class VirtualPatientParams:
    """Everything that defines one virtual patient; see the module docstring for the model.

    Attributes:
        seed: non-negative integer; drives the displacement field and the HU noise
            (independent streams).
        scale: ``(sx, sy, sz)`` scale factors (dimensionless) along LPS x, y, z about the
            anatomy centre, each in [0.5, 2].
        deformation_mm: RMS length (mm) of the displacement vectors over the grid, >= 0.
        deformation_length_mm: correlation length L (mm) of the displacement field: its
            correlation is ``exp(-r^2 / L^2)``; 10 to 500 mm.
        soft_tissue_hu_offset: HU added to soft tissue (plateau -200..100 HU).
        soft_tissue_hu_scale: factor (about 0 HU) applied to soft tissue.
        bone_hu_scale: factor applied to ``HU - 200`` above 300 HU (faded in from 200 HU).
        noise_hu: standard deviation (HU) of the added Gaussian noise, >= 0.
        fov_radius_mm: radius (mm) of the axial field of view about the grid's axial centre
            line; outside becomes air. None: no truncation.
        z_crop_mm: ``(inferior, superior)`` mm set to air at the low-z and high-z ends of the
            grid; None: no crop.

    Values outside :data:`PARAM_LIMITS` raise :class:`AugmentConfigError`.
    """

    seed: int
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    deformation_mm: float = 0.0
    deformation_length_mm: float = 50.0
    soft_tissue_hu_offset: float = 0.0
    soft_tissue_hu_scale: float = 1.0
    bone_hu_scale: float = 1.0
    noise_hu: float = 0.0
    fov_radius_mm: float | None = None
    z_crop_mm: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        seed = self.seed
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) <= _SEED_MAX:
            raise AugmentConfigError(f"seed must be an integer in [0, 2**63 - 1], got {seed!r}")
        object.__setattr__(self, "seed", int(seed))
        scale = tuple(_limited(f"scale[{i}]", "scale", v, "")
                      for i, v in enumerate(_sequence("scale", self.scale, 3)))
        object.__setattr__(self, "scale", scale)
        for key, unit in (("deformation_mm", "mm"), ("deformation_length_mm", "mm"),
                          ("soft_tissue_hu_offset", "HU"), ("soft_tissue_hu_scale", ""),
                          ("bone_hu_scale", ""), ("noise_hu", "HU")):
            object.__setattr__(self, key, _limited(key, key, getattr(self, key), unit))
        if self.fov_radius_mm is not None:
            object.__setattr__(self, "fov_radius_mm",
                               _limited("fov_radius_mm", "fov_radius_mm", self.fov_radius_mm, "mm"))
        if self.z_crop_mm is not None:
            crop = tuple(_limited(f"z_crop_mm[{i}]", "z_crop_mm", v, "mm")
                         for i, v in enumerate(_sequence("z_crop_mm", self.z_crop_mm, 2)))
            object.__setattr__(self, "z_crop_mm", crop)

    @classmethod
    def identity(cls, seed: int = 0) -> VirtualPatientParams:
        """Parameters that return the CT unchanged (no resampling, no HU change, no noise)."""
        return cls(seed=seed)

    @property
    def geometry_is_identity(self) -> bool:
        """True when scaling and deformation leave every voxel in place (no resampling)."""
        return self.scale == (1.0, 1.0, 1.0) and self.deformation_mm == 0.0

    @property
    def hu_is_identity(self) -> bool:
        """True when the HU transfer curve is the identity."""
        return (self.soft_tissue_hu_offset == 0.0 and self.soft_tissue_hu_scale == 1.0
                and self.bone_hu_scale == 1.0)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (tuples as lists, None kept); :meth:`from_dict` inverts it exactly."""
        d = asdict(self)
        d["scale"] = list(self.scale)
        d["z_crop_mm"] = None if self.z_crop_mm is None else list(self.z_crop_mm)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> VirtualPatientParams:
        """Parameters from :meth:`to_dict` output; every key required, unknown keys rejected."""
        if not isinstance(d, Mapping):
            raise AugmentConfigError(f"virtual patient parameters must be a mapping, got {type(d).__name__}")
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(d) - set(names))
        if unknown:
            raise AugmentConfigError(f"unknown virtual patient parameter(s) {unknown}; allowed keys: {names}")
        missing = [n for n in names if n not in d]
        if missing:
            raise AugmentConfigError(f"virtual patient parameters miss key(s) {missing}")
        return cls(**{n: d[n] for n in names})


# --------------------------------------------------------------------------- ranges
_PAIR_KEYS = ("scale", "deformation_mm", "deformation_length_mm", "soft_tissue_hu_offset",
              "soft_tissue_hu_scale", "bone_hu_scale", "noise_hu", "fov_radius_mm", "z_crop_mm")
_PROBABILITY_KEYS = ("fov_probability", "z_crop_probability")


@dataclass(frozen=True)
class VirtualPatientRanges:
    """Sampling ranges of :class:`VirtualPatientParams` (uniform within each ``(low, high)``).

    Attributes (units as in :class:`VirtualPatientParams`; reasons in the module docstring):
        scale: ``(low, high)`` for each of sx, sy, sz, drawn independently.
        deformation_mm, deformation_length_mm: ``(low, high)`` mm.
        soft_tissue_hu_offset: ``(low, high)`` HU; soft_tissue_hu_scale, bone_hu_scale:
            ``(low, high)`` factors.
        noise_hu: ``(low, high)`` HU standard deviation.
        fov_probability: probability (0-1) that a patient gets a truncated field of view,
            with radius drawn from ``fov_radius_mm`` ``(low, high)`` mm.
        z_crop_probability: probability (0-1) of a z crop; each end's crop drawn from
            ``z_crop_mm`` ``(low, high)`` mm.

    Both ends of each range must lie in :data:`PARAM_LIMITS`, low <= high.
    """

    scale: tuple[float, float] = (0.92, 1.08)
    deformation_mm: tuple[float, float] = (0.0, 6.0)
    deformation_length_mm: tuple[float, float] = (40.0, 80.0)
    soft_tissue_hu_offset: tuple[float, float] = (-20.0, 20.0)
    soft_tissue_hu_scale: tuple[float, float] = (0.95, 1.05)
    bone_hu_scale: tuple[float, float] = (0.85, 1.15)
    noise_hu: tuple[float, float] = (0.0, 15.0)
    fov_probability: float = 0.3
    fov_radius_mm: tuple[float, float] = (160.0, 240.0)
    z_crop_probability: float = 0.3
    z_crop_mm: tuple[float, float] = (0.0, 30.0)

    def __post_init__(self) -> None:
        for key in _PAIR_KEYS:
            value = getattr(self, key)
            if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
                value = (value, value)  # a single number: a fixed value
            lo_hi = _sequence(key, value, 2)
            lo, hi = (_number(f"{key}[{i}]", v) for i, v in enumerate(lo_hi))
            allowed_lo, allowed_hi = PARAM_LIMITS[key]
            if not (allowed_lo <= lo <= hi <= allowed_hi):
                raise AugmentConfigError(
                    f"{key} = [{lo:g}, {hi:g}] must satisfy {allowed_lo:g} <= low <= high <= {allowed_hi:g}"
                )
            object.__setattr__(self, key, (lo, hi))
        for key in _PROBABILITY_KEYS:
            p = _number(key, getattr(self, key))
            if not 0.0 <= p <= 1.0:
                raise AugmentConfigError(f"{key} = {p:g} is outside the allowed range [0, 1]")
            object.__setattr__(self, key, p)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> VirtualPatientRanges:
        """Ranges from a mapping (e.g. a campaign's ``[virtual_patients]`` TOML table).

        Missing keys keep their defaults; a range is ``[low, high]`` or one number (fixed).
        Raises :class:`AugmentConfigError` naming an unknown key (and the allowed keys) or a
        value outside its allowed range.
        """
        if not isinstance(d, Mapping):
            raise AugmentConfigError(f"virtual patient ranges must be a mapping (table), got {type(d).__name__}")
        names = [f.name for f in fields(cls)]
        unknown = sorted(str(k) for k in set(d) - set(names))
        if unknown:
            raise AugmentConfigError(f"unknown virtual patient range key(s) {unknown}; allowed keys: {names}")
        return cls(**dict(d))

    def to_dict(self) -> dict[str, Any]:
        """JSON/TOML-ready dict (pairs as lists); :meth:`from_dict` inverts it."""
        return {f.name: (list(v) if isinstance(v := getattr(self, f.name), tuple) else v) for f in fields(self)}

    def sample(self, rng: np.random.Generator) -> VirtualPatientParams:
        """One :class:`VirtualPatientParams` drawn from ``rng`` (its seed too).

        The number and order of draws is fixed (optional parts are drawn even when unused), so
        the stream stays aligned whatever the probabilities.
        """
        if not isinstance(rng, np.random.Generator):
            raise AugmentConfigError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        seed = int(rng.integers(0, 2**32))
        scale = tuple(float(rng.uniform(*self.scale)) for _ in range(3))
        u = {key: float(rng.uniform(*getattr(self, key)))
             for key in ("deformation_mm", "deformation_length_mm", "soft_tissue_hu_offset",
                         "soft_tissue_hu_scale", "bone_hu_scale", "noise_hu")}
        fov_on = bool(rng.random() < self.fov_probability)
        radius = float(rng.uniform(*self.fov_radius_mm))
        crop_on = bool(rng.random() < self.z_crop_probability)
        crop = (float(rng.uniform(*self.z_crop_mm)), float(rng.uniform(*self.z_crop_mm)))
        return VirtualPatientParams(
            seed=seed, scale=scale, **u,
            fov_radius_mm=radius if fov_on else None,
            z_crop_mm=crop if crop_on else None,
        )


# --------------------------------------------------------------------------- HU curve
def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """C1 step from 0 at ``lo`` to 1 at ``hi`` (3u^2 - 2u^3), same dtype as ``x``."""
    u = np.clip((x - x.dtype.type(lo)) * x.dtype.type(1.0 / (hi - lo)), 0, 1)
    return u * u * (x.dtype.type(3.0) - x.dtype.type(2.0) * u)


def perturb_hu(hu: np.ndarray, params: VirtualPatientParams) -> np.ndarray:
    """The HU transfer curve ``f`` of the module docstring applied to ``hu`` (any shape).

    Returns a new array: float64 input stays float64, anything else becomes float32.
    Identity parameters return a plain copy.
    """
    arr = np.asarray(hu)
    h = np.array(arr, dtype=np.float64 if arr.dtype == np.float64 else np.float32, copy=True)
    _apply_hu_curve(h, params)
    return h


def _apply_hu_curve(h: np.ndarray, params: VirtualPatientParams) -> None:
    """:func:`perturb_hu` in place on a float32 or float64 array."""
    if params.hu_is_identity:
        return
    f = h.dtype.type
    o, s, bs = params.soft_tissue_hu_offset, params.soft_tissue_hu_scale, params.bone_hu_scale
    lo, hi = SOFT_TISSUE_HU
    w = SOFT_TISSUE_TAPER_HU
    delta = None
    if o != 0.0 or s != 1.0:
        weight = _smoothstep(h, lo - w, lo)
        weight *= f(1.0) - _smoothstep(h, hi, hi + w)
        delta = weight * (f(o) + f(s - 1.0) * h)
    if bs != 1.0:
        t = BONE_HU_THRESHOLD
        bone = _smoothstep(h, t, t + BONE_RAMP_HU)
        bone *= f(bs - 1.0) * (h - f(t))
        delta = bone if delta is None else delta + bone
    h += delta


# --------------------------------------------------------------------------- deformation
def _check_grid(shape: Any, affine: Any) -> tuple[tuple[int, int, int], np.ndarray]:
    try:
        shp = tuple(int(n) for n in shape)
    except (TypeError, ValueError):
        raise AugmentConfigError(f"shape must be 3 positive integers, got {shape!r}") from None
    if len(shp) != 3 or min(shp) < 2:
        raise AugmentConfigError(f"shape must be 3 integers >= 2, got {shape!r}")
    a = np.asarray(affine, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)) or abs(np.linalg.det(a[:3, :3])) < 1e-9:
        raise AugmentConfigError(f"affine must be a finite, non-singular (4, 4) matrix, got {affine!r}")
    return shp, a


def _upsample_axis(coarse: np.ndarray, axis: int, n: int, step: float) -> np.ndarray:
    """Linear interpolation along ``axis`` from nodes at voxel ``m * step`` to voxels ``0..n-1``."""
    pos = np.arange(n, dtype=np.float64) / step
    i0 = np.minimum(np.floor(pos).astype(np.intp), coarse.shape[axis] - 2)
    w = (pos - i0).astype(coarse.dtype)
    shape = [1] * coarse.ndim
    shape[axis] = n
    w = w.reshape(shape)
    a = np.take(coarse, i0, axis=axis)
    b = np.take(coarse, i0 + 1, axis=axis)
    return a + w * (b - a)


def _coarse_field(shape: tuple[int, int, int], spacing: np.ndarray, params: VirtualPatientParams
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(3, N0, N1, N2)`` float64 smoothed noise (arbitrary scale) and ``(3,)`` node steps (voxels)."""
    L = params.deformation_length_mm
    step = np.maximum(1.0, _NODE_FRACTION * L / spacing)  # voxels between nodes
    nodes = np.ceil((np.array(shape) - 1) / step).astype(int) + 1
    sigma = _SMOOTH_FRACTION * L / (step * spacing)  # nodes
    pad = np.ceil(_TRUNCATE_SD * sigma).astype(int)
    rng = rng_for(params.seed, KIND_VP_FIELD)
    noise = rng.standard_normal((3, *(nodes + 2 * pad)))
    crop = tuple(slice(p, p + n) for p, n in zip(pad, nodes))
    field = np.stack([
        ndimage.gaussian_filter(c, sigma, mode="constant", truncate=_TRUNCATE_SD)[crop] for c in noise
    ])
    return field, step


def _gradient_bound(coarse: np.ndarray, step: np.ndarray, affine: np.ndarray) -> float:
    """Upper bound on ``||grad u||_F`` (LPS, mm/mm) of the trilinear interpolant of ``coarse``.

    ``coarse`` is ``(3, N0, N1, N2)`` mm. Per cell, ``|du_i/d index_a|`` is at most the largest
    of the four edge differences along ``a`` divided by the node step; the index-to-LPS
    derivative factor is bounded by ``||diag(spacing) A^-1||_2`` (1 for orthogonal axes).
    """
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    kappa = float(np.linalg.norm(np.diag(spacing) @ np.linalg.inv(affine[:3, :3]), ord=2))
    sq = None
    for a in range(3):
        d = np.abs(np.diff(coarse, axis=a + 1)) / (step[a] * spacing[a])
        for b in range(3):
            if b != a:
                lo = [slice(None)] * 4
                hi = [slice(None)] * 4
                lo[b + 1], hi[b + 1] = slice(0, -1), slice(1, None)
                d = np.maximum(d[tuple(lo)], d[tuple(hi)])
        term = np.sum(d * d, axis=0)
        sq = term if sq is None else sq + term
    return float(np.sqrt(np.max(sq))) * kappa


def _displacement(shape: tuple[int, int, int], affine: np.ndarray, params: VirtualPatientParams
                  ) -> tuple[np.ndarray | None, float]:
    """``(3, I, J, K)`` float32 LPS mm field (None when ``deformation_mm`` is 0) and the guard factor."""
    if params.deformation_mm == 0.0:
        return None, 1.0
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    coarse, step = _coarse_field(shape, spacing, params)
    # expand the cheap axes first; the last expansion makes the full-size array
    fine = coarse.astype(np.float32)
    for axis in range(3):
        fine = _upsample_axis(fine, axis + 1, shape[axis], float(step[axis]))
    mean = fine.mean(axis=(1, 2, 3), dtype=np.float64)
    fine -= mean.astype(np.float32)[:, None, None, None]
    rms = math.sqrt(float(np.einsum("cijk,cijk->", fine, fine, dtype=np.float64)) / fine[0].size)
    if rms == 0.0:
        return None, 1.0
    k = params.deformation_mm / rms
    bound = _gradient_bound(coarse, step, affine) * k
    guard = min(1.0, MAX_DISPLACEMENT_GRADIENT / bound) if bound > 0 else 1.0
    fine *= np.float32(k * guard)
    return fine, guard


def displacement_field(shape: tuple[int, int, int], affine: np.ndarray,
                       params: VirtualPatientParams) -> np.ndarray:
    """The displacement field ``u`` (LPS mm) that :func:`make_virtual_patient` uses.

    Args:
        shape: ``(I, J, K)`` grid shape.
        affine: ``(4, 4)`` voxel index to LPS mm.
        params: uses ``seed``, ``deformation_mm``, ``deformation_length_mm``.

    Returns:
        ``(3, I, J, K)`` float32: ``u[:, i, j, k]`` is the displacement (mm, LPS x, y, z) at
        that voxel's centre; the backward map is ``phi(x) = c + S^-1 (x + u(x) - c)``. All
        zeros when ``deformation_mm`` is 0.
    """
    shp, a = _check_grid(shape, affine)
    if not isinstance(params, VirtualPatientParams):
        raise AugmentConfigError(f"params must be VirtualPatientParams, got {type(params).__name__}")
    u, _ = _displacement(shp, a, params)
    return np.zeros((3, *shp), np.float32) if u is None else u


# --------------------------------------------------------------------------- the patient
def _axis_lines(affine: np.ndarray, shape: tuple[int, int, int], row: int) -> list[np.ndarray]:
    """Broadcastable per-axis terms whose sum is LPS coordinate ``row`` of every voxel centre."""
    terms = []
    for axis in range(3):
        shp = [1, 1, 1]
        shp[axis] = shape[axis]
        terms.append((affine[row, axis] * np.arange(shape[axis], dtype=np.float64)).reshape(shp))
    terms[0] = terms[0] + affine[row, 3]
    return terms


def _truncation_mask(ct: CTVolume, params: VirtualPatientParams) -> np.ndarray | None:
    """``(I, J, K)`` bool: voxels set to air by the field of view and the z crop (None: none)."""
    shape, a = ct.shape, ct.affine
    mask = None
    if params.fov_radius_mm is not None:
        centre = ct.center_of_box_lps()
        x = sum(_axis_lines(a, shape, 0)) - centre[0]
        y = sum(_axis_lines(a, shape, 1)) - centre[1]
        mask = x * x + y * y > params.fov_radius_mm ** 2
    if params.z_crop_mm is not None:
        z = sum(_axis_lines(a, shape, 2))
        faces = ct.corners_lps()[:, 2]
        crop = (z < faces.min() + params.z_crop_mm[0]) | (z > faces.max() - params.z_crop_mm[1])
        crop = np.broadcast_to(crop, shape)
        mask = crop if mask is None else mask | crop
    return None if mask is None else np.broadcast_to(mask, shape)


def make_virtual_patient(ct: CTVolume, params: VirtualPatientParams, *,
                         center_lps: np.ndarray | None = None) -> CTVolume:
    """A virtual patient derived from ``ct`` (see the module docstring for the model).

    Args:
        ct: the source CT; its ``labels`` (if any) follow the anatomy (nearest neighbour).
        params: :class:`VirtualPatientParams`.
        center_lps: ``(3,)`` LPS mm centre of the scaling; None = ``anatomy_center(ct)``
            (computed only when a scale factor differs from 1).

    Returns:
        :class:`CTVolume` on the same grid (shape, affine) with float32 ``hu``, ``source =
        f"{ct.source}#vp(seed={seed})"`` and the resampled label map. Identity parameters give
        ``hu`` (and labels) equal to the input's.

    Raises:
        AugmentConfigError: ``ct``, ``params`` or ``center_lps`` is unusable.
    """
    if not isinstance(ct, CTVolume):
        raise AugmentConfigError(f"ct must be a CTVolume, got {type(ct).__name__}")
    if not isinstance(params, VirtualPatientParams):
        raise AugmentConfigError(f"params must be VirtualPatientParams, got {type(params).__name__}")
    c = None
    if center_lps is not None:
        c = np.asarray(center_lps, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise AugmentConfigError(f"center_lps must be 3 finite LPS mm values, got {center_lps!r}")
    shape, affine = ct.shape, ct.affine
    labels = None if ct.labels is None else np.asarray(ct.labels)

    if params.geometry_is_identity:
        hu = ct.hu.copy()
        in_input = None  # every voxel is the input's own
        labels = None if labels is None else labels.copy()
    else:
        if c is None:
            # the centre matters only for scaling; skip the bone labelling without it
            c = anatomy_center(ct) if params.scale != (1.0, 1.0, 1.0) else np.zeros(3)
        u, _ = _displacement(shape, affine, params)
        a3, t = affine[:3, :3], affine[:3, 3]
        a_inv = np.linalg.inv(a3)
        s_inv = np.diag(1.0 / np.asarray(params.scale))
        m = a_inv @ s_inv @ a3  # index -> index (linear part)
        n = a_inv @ s_inv  # displacement mm -> index
        b = a_inv @ ((np.eye(3) - s_inv) @ (c - t))
        hu = np.empty(shape, np.float32)
        out_labels = None if labels is None else np.empty(shape, labels.dtype)
        in_input = np.empty(shape, bool)
        rows = max(1, _SLAB_VOXELS // (shape[1] * shape[2]))
        jk = [np.arange(shape[1], dtype=np.float64)[:, None], np.arange(shape[2], dtype=np.float64)[None, :]]
        for i0 in range(0, shape[0], rows):
            i1 = min(shape[0], i0 + rows)
            ii = np.arange(i0, i1, dtype=np.float64)[:, None, None]
            q = np.empty((3, i1 - i0, shape[1], shape[2]), np.float64)
            for r in range(3):
                q[r] = m[r, 0] * ii + (m[r, 1] * jk[0] + m[r, 2] * jk[1] + b[r])
                if u is not None:
                    q[r] += n[r, 0] * u[0, i0:i1] + n[r, 1] * u[1, i0:i1] + n[r, 2] * u[2, i0:i1]
            ndimage.map_coordinates(ct.hu, q, output=hu[i0:i1], order=1, mode="constant", cval=AIR_HU)
            if labels is not None:
                ndimage.map_coordinates(labels, q, output=out_labels[i0:i1], order=0, mode="constant", cval=0)
            inside = np.ones(q.shape[1:], bool)
            for r in range(3):
                inside &= (q[r] >= 0.0) & (q[r] <= shape[r] - 1)
            in_input[i0:i1] = inside
        labels = out_labels

    _apply_hu_curve(hu, params)
    if params.noise_hu > 0.0:
        rng = rng_for(params.seed, KIND_VP_NOISE)
        noise = rng.standard_normal(shape, dtype=np.float32)
        noise *= np.float32(params.noise_hu)
        if in_input is not None:
            noise[~in_input] = 0.0
        hu += noise
    cut = _truncation_mask(ct, params)
    if cut is not None:
        hu[cut] = AIR_HU
        if labels is not None:
            labels[cut] = 0
    return CTVolume(hu=hu, affine=affine.copy(), source=f"{ct.source}#vp(seed={params.seed})", labels=labels)
