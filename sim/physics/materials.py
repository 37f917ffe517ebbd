"""Materials of the body (and implants) with mass attenuation coefficients from xraylib's NIST data.

Every coefficient comes from xraylib (``CS_Total_CP`` and its parts for NIST compounds, the
element functions for titanium): no hand-copied tables. Units: energies in keV, mass
attenuation in cm^2/g, densities in g/cm^3, linear attenuation in 1/mm.

:data:`TISSUE_DECOMPOSITION` maps HU to seven materials with the smooth hat-function partition
of :class:`sim.materials.MaterialDecomposition` (no iso-HU contours) and a piecewise-linear
HU-to-density curve. The anchors are typical CT numbers: air -1000, lung -750, adipose -100,
soft tissue 40, cancellous bone 300, cortical bone 1400, titanium 3000 HU. The density knots
follow the usual stoichiometric calibrations (Schneider et al. 1996/2000): air 0.0012,
lung 0.26, adipose 0.95, soft tissue 1.04, cancellous bone 1.18, cortical bone 1.92,
titanium 4.51 g/cm^3. CT numbers of metal saturate (3071 HU for 12-bit scanners), so everything
above ~3000 HU is titanium at its nominal density.
"""

from __future__ import annotations

import re
from functools import lru_cache

import numpy as np

from sim.materials import MaterialDecomposition
from sim.physics import PhysicsError

#: name -> xraylib NIST compound name, or ("element", Z). ``water`` is not in the HU
#: decomposition; it serves phantoms and validation. Cancellous bone (spongiosa) is not in
#: the NIST list: it is a mass mixture of ICRP cortical bone and soft tissue (see
#: :data:`CANCELLOUS_CORTICAL_MASS_FRACTION`).
MATERIALS: dict[str, str | tuple[str, int]] = {
    "air": "Air, Dry (near sea level)",
    "lung": "Lung (ICRP)",
    "adipose": "Adipose Tissue (ICRP)",
    "soft_tissue": "Tissue, Soft (ICRP)",
    "cancellous_bone": "mixture",
    "cortical_bone": "Bone, Cortical (ICRP)",
    "titanium": ("element", 22),
    "water": "Water, Liquid",
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
        raise PhysicsError(f"unknown material {name!r}; known: {', '.join(MATERIALS)}")
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
        raise PhysicsError(f"kind must be one of {KINDS}, got {kind!r}")
    e = np.asarray(energies_keV, dtype=np.float64)
    if not np.all(np.isfinite(e)) or e.size and (e.min() < 1.0 or e.max() > 1000.0):
        raise PhysicsError(f"energies must be finite and in [1, 1000] keV, got {e.min()}..{e.max()}")
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
    HU-based fractions. Used like :class:`sim.materials.MaterialDecomposition` by the renderer
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
            raise PhysicsError(f"label map must hold integers, got {self.labels.dtype}")
        if not label_materials:
            raise PhysicsError("label_materials is empty: give {label: material}")
        for lab, name in label_materials.items():
            if name not in self.base.names:
                raise PhysicsError(f"label {lab}: material {name!r} is not one of {', '.join(self.base.names)}")
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
            raise PhysicsError(f"label map shape {self.labels.shape} differs from the CT's {hu.shape}")
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
            raise PhysicsError(f"label material {item!r}: expected LABEL:MATERIAL with an integer label > 0, "
                               "e.g. 3:titanium")
        if name not in TISSUE_DECOMPOSITION.names:
            raise PhysicsError(f"label material {item!r}: material {name!r} is not one of "
                               f"{', '.join(TISSUE_DECOMPOSITION.names)}")
        if int(lab) in out:
            raise PhysicsError(f"label material {item!r}: label {int(lab)} is given twice")
        out[int(lab)] = name
    return out
