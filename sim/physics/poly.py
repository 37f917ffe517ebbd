"""Polychromatic detector signal from per-material density line integrals; detector; noise.

Signal per pixel (energy-integrating detector)::

    I = mAs * A_px * (1000 / SDD)^2 * sum_E N(E) * eta(E) * exp(-sum_m (mu/rho)_m(E) L_m)

with ``N(E)`` the binned tube fluence (:class:`sim.physics.spectrum.Spectrum`, photons / mm^2 /
mAs at 1000 mm), ``A_px`` the pixel area (mm^2) and ``SDD`` the source-detector distance (mm),
the inverse-square law, ``(mu/rho)_m`` from xraylib (cm^2/g), and ``L_m`` the density line
integrals (g/cm^2) of the renderer's ``quantity="density"``. The rays are marched once per pose,
not once per energy. ``eta(E)`` is the detector response (:class:`Detector`):

* ``counting``: the probability that a photon interacts in the CsI layer, ``1 - exp(-mu t)``;
* ``integrating``: the mean energy it deposits (keV), approximated as
  ``E * (1 - exp(-mu t)) * (mu_pe + mu_C * f_C(E)) / mu``. Photoelectric absorption deposits
  all of E; Compton deposits the mean recoil fraction ``f_C`` (Klein-Nishina); Rayleigh deposits
  nothing. K-fluorescence escape and secondary re-absorption are neglected (a few % at
  35-60 keV).

The log image is ``-log(I / I0)`` with ``I0`` the flat field (no object).

Noise (:meth:`Polychromatic.noisy`), in this order:

1. Quantum noise: the photons that interact in the CsI are Poisson per energy bin and pixel;
   each adds its mean signal (1 count, or its mean deposited energy: compound Poisson for the
   integrating detector; the spread of deposits, Swank noise, is neglected).
2. Detector blur: a Gaussian of ``blur_mm`` at the detector. Light spreads in the CsI, which
   blurs the quanta.
3. Electronic noise: Gaussian, ``electronic_noise`` in signal units.

All of it is seeded (``numpy.random.Generator``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.physics.materials import mass_attenuation
from sim.physics import PhysicsError
from sim.physics.settings import SETTINGS
from sim.physics.spectrum import Spectrum

_ME_C2_KEV = 510.99895


def compton_mean_energy_fraction(energies_keV) -> np.ndarray:
    """Mean fraction of the photon energy given to the electron in Compton scattering
    (Klein-Nishina, free electrons): ``sigma_tr / sigma`` from the closed forms."""
    k = np.asarray(energies_keV, dtype=np.float64) / _ME_C2_KEV
    a = 1 + 2 * k
    sigma = (1 + k) / k**2 * (2 * (1 + k) / a - np.log(a) / k) + np.log(a) / (2 * k) - (1 + 3 * k) / a**2
    sigma_tr = (2 * (1 + k) ** 2 / (k**2 * a) - (1 + 3 * k) / a**2 - (1 + k) * (2 * k**2 - 2 * k - 1) / (k**2 * a**2)
                - 4 * k**2 / (3 * a**3) - ((1 + k) / k**3 - 1 / (2 * k) + 1 / (2 * k**3)) * np.log(a))
    return sigma_tr / sigma


@dataclass(frozen=True)
class Detector:
    """Flat-panel detector. ``thickness_mm`` of CsI:Tl (4.51 g/cm^3); ``mode`` integrating or
    counting; ``electronic_noise`` (signal units: keV for integrating, counts for counting);
    ``blur_mm`` Gaussian sigma at the detector (mm; 0 here, the setting's default is for images).
    Defaults and ranges: the settings ``detector_mm``, ``detector_mode``, ``electronic_noise``,
    ``blur_mm`` of :mod:`sim.physics.settings`."""

    thickness_mm: float = SETTINGS["detector_mm"].default
    mode: str = SETTINGS["detector_mode"].default
    electronic_noise: float = SETTINGS["electronic_noise"].default
    blur_mm: float = 0.0
    density_g_cm3: float = 4.51

    def __post_init__(self) -> None:
        # the ranges of the physics settings of the same meaning (sim.physics.settings)
        for setting, name in (("detector_mode", "mode"), ("detector_mm", "thickness_mm"),
                              ("electronic_noise", "electronic_noise"), ("blur_mm", "blur_mm")):
            SETTINGS[setting].check(getattr(self, name), f"detector {name}")
        v = self.density_g_cm3
        if not (math.isfinite(v) and v > 0):
            raise PhysicsError(f"detector density_g_cm3 must be a positive number, got {v}")

    def _cs(self, f, e: np.ndarray) -> np.ndarray:
        return np.array([f("CsI", float(v)) for v in e.ravel()]).reshape(e.shape)

    def response(self, energies_keV) -> np.ndarray:
        """Signal per incident photon: probability (counting) or deposited keV (integrating)."""
        import xraylib as xr

        e = np.asarray(energies_keV, dtype=np.float64)
        mu = self._cs(xr.CS_Total_CP, e)
        absorbed = 1.0 - np.exp(-mu * self.density_g_cm3 * self.thickness_mm / 10.0)
        if self.mode == "counting":
            return absorbed
        dep = (self._cs(xr.CS_Photo_CP, e) + self._cs(xr.CS_Compt_CP, e) * compton_mean_energy_fraction(e)) / mu
        return e * absorbed * dep


class Polychromatic:
    """Detector signal of density line integrals for one spectrum, detector and material list.

    Args:
        spectrum: :class:`Spectrum`.
        detector: :class:`Detector`.
        materials: names (:data:`sim.physics.materials.MATERIALS`) of the density channels, in
            the renderer's order (its :class:`sim.physics.materials.MaterialDecomposition` names).
    """

    def __init__(self, spectrum: Spectrum, detector: Detector | None = None, materials=("soft_tissue",)):
        self.spectrum = spectrum
        self.detector = detector or Detector()
        self.materials = tuple(materials)
        e = spectrum.energies_keV
        self.mass_att = np.stack([mass_attenuation(m, e) for m in self.materials])  # (M, E) cm^2/g
        self.response = self.detector.response(e)  # (E,)
        self.interaction = Detector(self.detector.thickness_mm, "counting",
                                    density_g_cm3=self.detector.density_g_cm3).response(e)  # (E,)

    def _check(self, L: np.ndarray) -> np.ndarray:
        L = np.asarray(L, dtype=np.float64)
        if L.ndim != 4 or L.shape[1] != len(self.materials):
            raise PhysicsError(f"density line integrals must be (B, M={len(self.materials)}, H, W) g/cm^2, "
                               f"got {L.shape}")
        if not np.all(np.isfinite(L)) or L.min() < 0:
            raise PhysicsError("density line integrals must be finite and >= 0")
        return L

    def photons_per_pixel(self, *, mas: float, sdd_mm: float, pixel_area_mm2: float) -> np.ndarray:
        """Incident photons per pixel and energy bin without an object, ``(E,)``."""
        for name, v in (("mas", mas), ("sdd_mm", sdd_mm), ("pixel_area_mm2", pixel_area_mm2)):
            if not (math.isfinite(v) and v > 0):
                raise PhysicsError(f"{name} must be a positive number, got {v}")
        return self.spectrum.fluence * mas * pixel_area_mm2 * (1000.0 / sdd_mm) ** 2

    def expected_counts(self, L, **exposure) -> np.ndarray:
        """Expected photons reaching the detector per energy bin, ``(B, E, H, W)``."""
        L = self._check(L)
        n0 = self.photons_per_pixel(**exposure)
        path = np.einsum("me,bmhw->behw", self.mass_att, L)  # sum_m (mu/rho)_m(E) L_m, dimensionless
        return n0[None, :, None, None] * np.exp(-path)

    #: Pixels per block of :meth:`expected` (a (block, E) float64 array stays in the cache).
    BLOCK_PIXELS = 1 << 15

    def expected(self, L, **exposure) -> np.ndarray:
        """Expected detector signal ``(B, H, W)`` (keV or counts); ``exposure``: mas, sdd_mm, pixel_area_mm2.

        The same sum as ``expected_counts(L) . response``, pixel block by pixel block as two
        contractions around an in-place ``exp``: 4x faster than the ``(B, E, H, W)`` array and
        equal to it within 1e-15 (relative). The contractions are ``np.einsum`` on purpose, not
        ``@``: BLAS's threads keep spinning after a product and slow the next Dr.Jit kernel on
        the same cores (a 128 x 128 image took 50 ms instead of 14 in a registration loop).
        """
        L = self._check(L)
        b, m, h, w = L.shape
        weights = self.photons_per_pixel(**exposure) * self.response  # (E,)
        neg_att = -self.mass_att  # (M, E)
        pixels = np.moveaxis(L, 1, -1).reshape(-1, m)  # (P, M)
        out = np.empty(len(pixels))
        for start in range(0, len(pixels), self.BLOCK_PIXELS):
            # (p, E): -sum_m (mu/rho)_m(E) L_m
            path = np.einsum("pm,me->pe", pixels[start:start + self.BLOCK_PIXELS], neg_att)
            np.exp(path, out=path)
            out[start:start + self.BLOCK_PIXELS] = np.einsum("pe,e->p", path, weights)
        return out.reshape(b, h, w)

    def flat_field(self, **exposure) -> float:
        """The signal without an object."""
        return float((self.photons_per_pixel(**exposure) * self.response).sum())

    def noisy(self, L, rng: np.random.Generator, *, pixel_spacing_mm: float, scatter=None, gain: float = 1.0,
              **exposure) -> np.ndarray:
        """One noisy realisation ``(B, H, W)`` (see the module doc for the order).

        ``scatter``: optional ``(signal, interacting photons)``, each ``(B, H, W)``, the expected
        scattered signal: its photons are Poisson too, each adding the mean signal of a scattered
        photon in that pixel. ``gain``: primary transmission of an anti-scatter grid (0-1]."""
        from scipy.ndimage import gaussian_filter

        # photons that interact in the detector are Poisson (a thinned Poisson process); each
        # then adds its mean signal (1 count, or its mean deposited keV: Swank noise neglected)
        p_int = self.interaction
        counts = rng.poisson(self.expected_counts(L, **exposure) * (gain * p_int)[None, :, None, None])
        per_photon = np.where(p_int > 0, self.response / np.where(p_int > 0, p_int, 1.0), 0.0)
        signal = np.einsum("behw,e->bhw", counts.astype(np.float64), per_photon)
        if scatter is not None:
            s_signal, s_counts = (np.asarray(a, dtype=np.float64) for a in scatter)
            mean_per = np.where(s_counts > 0, s_signal / np.where(s_counts > 0, s_counts, 1.0), 0.0)
            signal = signal + rng.poisson(np.maximum(s_counts, 0.0)) * mean_per
        if self.detector.blur_mm > 0:
            sigma = self.detector.blur_mm / pixel_spacing_mm
            signal = gaussian_filter(signal, sigma=(0, sigma, sigma), mode="nearest")
        if self.detector.electronic_noise > 0:
            signal = signal + rng.normal(0.0, self.detector.electronic_noise, signal.shape)
        return signal

    @staticmethod
    def log_image(signal: np.ndarray, flat: float) -> np.ndarray:
        """``-log(I / I0)``, with I clipped at a tiny positive value (photon starvation)."""
        return -np.log(np.maximum(np.asarray(signal, np.float64), 1e-12 * flat) / flat)
