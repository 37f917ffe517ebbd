"""Materials: HU to attenuation and to per-material densities, and the materials' cross sections.

Two volume quantities are derived from Hounsfield units (HU):

* linear attenuation ``mu = mu_water * (1 + HU / 1000)``, clipped at 0, in 1/mm, with an
  overridable ``mu_water`` (default :data:`MU_WATER_60KEV_PER_MM`, water at 60 keV, a usual
  effective energy of a 100-120 kVp beam): what the line-integral DRR renderer integrates;
* per-material partial densities (g/cm^3) from a :class:`MaterialDecomposition`: a
  piecewise-linear HU-to-density curve and a partition of unity of "hat" functions between
  neighbouring material anchors, so fractions change smoothly with HU and no contour appears
  where one material hands over to the next. Their line integrals (g/cm^2) are what the
  polychromatic physics (:mod:`sim.physics`) multiplies by mass attenuation coefficients.

The materials of the body (and implants) have mass attenuation coefficients from xraylib's NIST
data (:func:`mass_attenuation`): every coefficient comes from xraylib (``CS_Total_CP`` and its
parts for NIST compounds, the element functions for titanium), no hand-copied tables.

:data:`TISSUE_DECOMPOSITION` maps HU to seven materials with the smooth hat-function partition
of :class:`MaterialDecomposition` (no iso-HU contours) and a piecewise-linear HU-to-density
curve. The anchors are typical CT numbers: air -1000, lung -750, adipose -100, soft tissue 40,
cancellous bone 300, cortical bone 1400, titanium 3000 HU. The density knots follow the usual
stoichiometric calibrations (Schneider et al. 1996/2000): air 0.0012, lung 0.26, adipose 0.95,
soft tissue 1.04, cancellous bone 1.18, cortical bone 1.92, titanium 4.51 g/cm^3. CT numbers of
metal saturate (3071 HU for 12-bit scanners), so everything above ~3000 HU is titanium at its
nominal density. A :class:`LabelOverride` lets a label map override the HU-based materials
(an implant segmented as titanium).

Units: energies in keV, mass attenuation in cm^2/g, densities in g/cm^3, linear attenuation in
1/mm. numpy only (xraylib imported where cross sections are needed); no Dr.Jit.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from sim.core.errors import InputError


class MaterialError(InputError):
    """A material, label-material item or decomposition that cannot be used; the message names
    the value and what is allowed."""

#: Linear attenuation of liquid water at 60 keV in 1/mm: xraylib's NIST data, total with
#: coherent scattering, 0.2059 cm^2/g x 1.0 g/cm^3 (checked against xraylib in the tests).
MU_WATER_60KEV_PER_MM = 0.020587


def mu_from_hu(hu: np.ndarray, mu_water_per_mm: float = MU_WATER_60KEV_PER_MM) -> np.ndarray:
    """Linear attenuation (1/mm) from HU: ``mu_water * (1 + HU/1000)`` clipped at 0; same shape."""
    if not (np.isfinite(mu_water_per_mm) and mu_water_per_mm > 0):
        raise MaterialError(f"mu_water must be a positive number in 1/mm, got {mu_water_per_mm}")
    hu = np.asarray(hu, dtype=np.float32)
    return np.maximum(np.float32(mu_water_per_mm) * (1.0 + hu / 1000.0), 0.0).astype(np.float32)


@dataclass(frozen=True)
class MaterialDecomposition:
    """Materials as HU anchors plus an HU-to-density curve.

    Attributes:
        anchors: ``(name, HU)`` pairs in increasing HU. The fraction of material m is a hat
            function that is 1 at its anchor and falls linearly to 0 at the neighbouring anchors
            (constant 1 beyond the first and the last), so fractions sum to 1 for every HU.
        density_points: ``(HU, g/cm^3)`` knots of a piecewise-linear density curve, increasing
            HU; extrapolated with the end slopes, and never below 0.
    """

    anchors: tuple[tuple[str, float], ...] = (("air", -1000.0), ("soft_tissue", 40.0), ("bone", 1000.0))
    density_points: tuple[tuple[float, float], ...] = (
        (-1000.0, 0.0012),
        (0.0, 1.0),
        (1000.0, 1.6),
        (3000.0, 2.8),
    )

    def __post_init__(self) -> None:
        hus = [h for _, h in self.anchors]
        if len(hus) < 1 or any(b <= a for a, b in zip(hus, hus[1:])):
            raise MaterialError(f"material anchors must have strictly increasing HU, got {self.anchors}")
        knots = [h for h, _ in self.density_points]
        if len(knots) < 2 or any(b <= a for a, b in zip(knots, knots[1:])):
            raise MaterialError(f"density knots must have strictly increasing HU, got {self.density_points}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.anchors)

    def density(self, hu: np.ndarray) -> np.ndarray:
        """Mass density (g/cm^3) for HU; same shape."""
        hu = np.asarray(hu, dtype=np.float64)
        x = np.array([h for h, _ in self.density_points])
        y = np.array([r for _, r in self.density_points])
        rho = np.interp(hu, x, y)
        lo, hi = hu < x[0], hu > x[-1]
        rho = np.where(lo, y[0] + (hu - x[0]) * (y[1] - y[0]) / (x[1] - x[0]), rho)
        rho = np.where(hi, y[-1] + (hu - x[-1]) * (y[-1] - y[-2]) / (x[-1] - x[-2]), rho)
        return np.maximum(rho, 0.0)

    def fractions(self, hu: np.ndarray) -> np.ndarray:
        """``(M, *hu.shape)`` material fractions (sum 1) for HU."""
        hu = np.asarray(hu, dtype=np.float64)
        a = np.array([h for _, h in self.anchors])
        if len(a) == 1:
            return np.ones((1,) + hu.shape)
        lower, t = self._hat(hu)
        return self._spread(lower, 1.0 - t, t, hu.shape, np.float64)

    def _hat(self, hu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional anchor index of each voxel, clamped at both ends: its lower anchor
        ``(N,)`` and the weight ``t`` ``(N,)`` of the upper one (hat weights of the two)."""
        a = np.array([h for _, h in self.anchors])
        pos = np.interp(hu.ravel(), a, np.arange(len(a), dtype=np.float64))
        lower = np.clip(np.floor(pos), 0, len(a) - 2)
        return lower.astype(np.intp), pos - lower

    def _spread(self, lower, w_lower, w_upper, shape, dtype) -> np.ndarray:
        """``(M, *shape)``: ``w_lower`` in channel ``lower``, ``w_upper`` in ``lower + 1``, else 0
        (each voxel touches two channels: no (M, N) temporaries)."""
        out = np.zeros((len(self.anchors), w_lower.size), dtype=dtype)
        cols = np.arange(w_lower.size)
        out[lower, cols] = w_lower
        out[lower + 1, cols] = w_upper
        return out.reshape((len(self.anchors),) + tuple(shape))

    def partial_densities(self, hu: np.ndarray) -> np.ndarray:
        """``(M, *hu.shape)`` float32 partial densities (g/cm^3): fraction x density."""
        hu = np.asarray(hu, dtype=np.float64)
        if len(self.anchors) == 1:
            return self.density(hu)[None].astype(np.float32)
        lower, t = self._hat(hu)
        rho = self.density(hu).ravel()
        return self._spread(lower, (1.0 - t) * rho, t * rho, hu.shape, np.float32)


#: name -> xraylib NIST compound name, or ("element", Z). ``water`` is not in the HU
#: decomposition; it serves phantoms and validation. Cancellous bone (spongiosa) is not in
#: the NIST list: it is a mass mixture of ICRP cortical bone and soft tissue (see
#: :data:`CANCELLOUS_CORTICAL_MASS_FRACTION`). The tool and equipment materials of
#: :mod:`sim.distractors`: ``stainless_steel`` is modelled as iron (Fe; a 316L-like Fe-Cr-Ni
#: 70/19/11 mix attenuates 0.7-1.1 % less at 40-100 keV), ``carbon`` stands for carbon-fibre
#: table tops (give their low effective density), ``pvc`` for cable insulation.
MATERIALS: dict[str, str | tuple[str, int]] = {
    "air": "Air, Dry (near sea level)",
    "lung": "Lung (ICRP)",
    "adipose": "Adipose Tissue (ICRP)",
    "soft_tissue": "Tissue, Soft (ICRP)",
    "cancellous_bone": "mixture",
    "cortical_bone": "Bone, Cortical (ICRP)",
    "titanium": ("element", 22),
    "water": "Water, Liquid",
    # surgical tools and equipment in the field (sim.distractors), not in the HU decomposition
    "stainless_steel": ("element", 26),
    "aluminium": ("element", 13),
    "copper": ("element", 29),
    "carbon": ("element", 6),
    "pvc": "Polyvinyl Chloride",
}

#: Cancellous bone = this mass fraction of ICRP cortical bone + the rest ICRP soft tissue
#: (a spongiosa of density ~1.18 g/cm^3 with ~20 % bone volume: 0.2 x 1.92 / 1.18 ~ 0.33).
CANCELLOUS_CORTICAL_MASS_FRACTION = 0.33

KINDS = ("total", "photo", "compton", "rayleigh")

TISSUE_DECOMPOSITION = MaterialDecomposition(
    anchors=(("air", -1000.0), ("lung", -750.0), ("adipose", -100.0), ("soft_tissue", 40.0),
             ("cancellous_bone", 300.0), ("cortical_bone", 1400.0), ("titanium", 3000.0)),
    density_points=((-1000.0, 0.0012), (-750.0, 0.26), (-100.0, 0.95), (40.0, 1.04), (300.0, 1.18),
                    (1400.0, 1.92), (2500.0, 2.6), (3000.0, 4.51), (4000.0, 4.51)),
)


def _check_name(name: str) -> str:
    if name not in MATERIALS:
        raise MaterialError(f"unknown material {name!r}; known: {', '.join(MATERIALS)}")
    return name


@lru_cache(maxsize=None)
def _mass_attenuation(name: str, energies: tuple[float, ...], kind: str) -> np.ndarray:
    import xraylib as xr

    spec = MATERIALS[name]
    if spec == "mixture":
        w = CANCELLOUS_CORTICAL_MASS_FRACTION
        return (w * _mass_attenuation("cortical_bone", energies, kind)
                + (1 - w) * _mass_attenuation("soft_tissue", energies, kind))
    if isinstance(spec, tuple):
        z = spec[1]
        f = {"total": xr.CS_Total, "photo": xr.CS_Photo, "compton": xr.CS_Compt, "rayleigh": xr.CS_Rayl}[kind]
        return np.array([f(z, e) for e in energies])
    f = {"total": xr.CS_Total_CP, "photo": xr.CS_Photo_CP, "compton": xr.CS_Compt_CP, "rayleigh": xr.CS_Rayl_CP}[kind]
    return np.array([f(spec, e) for e in energies])


def mass_attenuation(name: str, energies_keV, kind: str = "total") -> np.ndarray:
    """``(mu/rho)`` in cm^2/g of material ``name`` at ``energies_keV`` (any shape, 1-1000 keV).

    ``kind``: ``"total"`` (photoelectric + Compton + Rayleigh), or one of its parts
    ``"photo"``, ``"compton"``, ``"rayleigh"``.
    """
    _check_name(name)
    if kind not in KINDS:
        raise MaterialError(f"kind must be one of {KINDS}, got {kind!r}")
    e = np.asarray(energies_keV, dtype=np.float64)
    if not np.all(np.isfinite(e)) or e.size and (e.min() < 1.0 or e.max() > 1000.0):
        raise MaterialError(f"energies must be finite and in [1, 1000] keV, got {e.min()}..{e.max()}")
    flat = tuple(float(v) for v in e.ravel())
    return _mass_attenuation(name, flat, kind).reshape(e.shape)


def nominal_density(name: str) -> float:
    """Nominal density (g/cm^3) from xraylib's NIST data (the mixture: its knot in the HU curve)."""
    import xraylib as xr

    spec = MATERIALS[_check_name(name)]
    if spec == "mixture":
        return 1.18
    if isinstance(spec, tuple):
        return float(xr.ElementDensity(spec[1]))
    return float(xr.GetCompoundDataNISTByName(spec)["density"])


def mu_linear(name: str, energies_keV, density_g_cm3: float | None = None) -> np.ndarray:
    """Linear attenuation (1/mm) at ``density_g_cm3`` (default the nominal density)."""
    rho = nominal_density(name) if density_g_cm3 is None else float(density_g_cm3)
    return mass_attenuation(name, energies_keV) * rho / 10.0


#: Materials whose density a label override takes from xraylib's nominal value, not from the
#: HU curve: metal saturates CT numbers, so its HU says nothing about its density.
NOMINAL_DENSITY_MATERIALS = ("titanium",)


class LabelOverride:
    """A decomposition in which a label map overrides the HU-based materials.

    In voxels whose label is a key of ``label_materials`` the whole partial density goes to that
    material: density from the HU curve of ``base``, or the nominal density for
    :data:`NOMINAL_DENSITY_MATERIALS` (an implant segmented by the user). Other voxels keep the
    HU-based fractions. Used like :class:`MaterialDecomposition` by the renderer
    (``names``, ``partial_densities(hu)``) for the CT whose ``labels`` ``(I, J, K)`` it holds.

    Args:
        labels: integer label map ``(I, J, K)`` on the CT's grid.
        label_materials: ``{label: material name}``; names must be in ``base.names``.
        base: the HU decomposition (default :data:`TISSUE_DECOMPOSITION`).
    """

    def __init__(self, labels: np.ndarray, label_materials: dict[int, str], base: MaterialDecomposition | None = None):
        self.base = base or TISSUE_DECOMPOSITION
        self.labels = np.asarray(labels)
        if not np.issubdtype(self.labels.dtype, np.integer):
            raise MaterialError(f"label map must hold integers, got {self.labels.dtype}")
        if not label_materials:
            raise MaterialError("label_materials is empty: give {label: material}")
        for lab, name in label_materials.items():
            if name not in self.base.names:
                raise MaterialError(f"label {lab}: material {name!r} is not one of {', '.join(self.base.names)}")
        self.label_materials = {int(k): str(v) for k, v in label_materials.items()}

    @property
    def names(self) -> tuple[str, ...]:
        return self.base.names

    def density(self, hu: np.ndarray) -> np.ndarray:
        return self.base.density(hu)

    def partial_densities(self, hu: np.ndarray) -> np.ndarray:
        """``(M, I, J, K)`` float32 g/cm^3 with the overrides applied."""
        hu = np.asarray(hu)
        if hu.shape != self.labels.shape:
            raise MaterialError(f"label map shape {self.labels.shape} differs from the CT's {hu.shape}")
        out = self.base.partial_densities(hu)
        for lab, name in self.label_materials.items():
            mask = self.labels == lab
            if not mask.any():
                continue
            m = self.base.names.index(name)
            rho = (np.full(int(mask.sum()), nominal_density(name)) if name in NOMINAL_DENSITY_MATERIALS
                   else self.base.density(hu[mask]))
            out[:, mask] = 0.0
            out[m, mask] = rho
        return out


def parse_label_materials(items) -> dict[int, str]:
    """``["3:titanium", "7:cortical_bone"]`` -> ``{3: "titanium", 7: "cortical_bone"}``.

    Each item is ``LABEL:MATERIAL`` with an integer label > 0 (0 is the background of a label map)
    and a material of :data:`TISSUE_DECOMPOSITION`; a label may appear once.
    """
    out: dict[int, str] = {}
    for item in items:
        lab, sep, name = str(item).partition(":")
        name = name.strip()
        if not sep or not re.fullmatch(r"\s*\d+\s*", lab) or int(lab) == 0:
            raise MaterialError(f"label material {item!r}: expected LABEL:MATERIAL with an integer label > 0, "
                               "e.g. 3:titanium")
        if name not in TISSUE_DECOMPOSITION.names:
            raise MaterialError(f"label material {item!r}: material {name!r} is not one of "
                               f"{', '.join(TISSUE_DECOMPOSITION.names)}")
        if int(lab) in out:
            raise MaterialError(f"label material {item!r}: label {int(lab)} is given twice")
        out[int(lab)] = name
    return out
