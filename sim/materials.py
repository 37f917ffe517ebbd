"""HU to attenuation and to per-material densities: what the DRR renderer integrates.

Two volume quantities are derived from Hounsfield units (HU):

* linear attenuation ``mu = mu_water * (1 + HU / 1000)``, clipped at 0, in 1/mm, with an
  overridable ``mu_water`` (default :data:`MU_WATER_60KEV_PER_MM`, water at 60 keV, a usual
  effective energy of a 100-120 kVp beam);
* per-material partial densities (g/cm^3) from a :class:`MaterialDecomposition`: a
  piecewise-linear HU-to-density curve and a partition of unity of "hat" functions between
  neighbouring material anchors, so fractions change smoothly with HU and no contour appears
  where one material hands over to the next. Their line integrals (g/cm^2) are what the
  polychromatic physics multiplies by mass attenuation coefficients.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Linear attenuation of liquid water at 60 keV in 1/mm: xraylib's NIST data, total with
#: coherent scattering, 0.2059 cm^2/g x 1.0 g/cm^3 (checked against xraylib in the tests).
MU_WATER_60KEV_PER_MM = 0.020587


def mu_from_hu(hu: np.ndarray, mu_water_per_mm: float = MU_WATER_60KEV_PER_MM) -> np.ndarray:
    """Linear attenuation (1/mm) from HU: ``mu_water * (1 + HU/1000)`` clipped at 0; same shape."""
    if not (np.isfinite(mu_water_per_mm) and mu_water_per_mm > 0):
        raise ValueError(f"mu_water must be a positive number in 1/mm, got {mu_water_per_mm}")
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
            raise ValueError(f"material anchors must have strictly increasing HU, got {self.anchors}")
        knots = [h for h, _ in self.density_points]
        if len(knots) < 2 or any(b <= a for a, b in zip(knots, knots[1:])):
            raise ValueError(f"density knots must have strictly increasing HU, got {self.density_points}")

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
