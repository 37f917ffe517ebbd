"""Photon interaction data for Monte Carlo transport, all from xraylib.

Per material (:data:`sim.physics.materials.MATERIALS`) and energy:

* mass attenuation of the three processes, photoelectric, Compton (incoherent) and Rayleigh
  (coherent), ``(mu/rho)`` in cm^2/g (:func:`sim.physics.materials.mass_attenuation`);
* the angular distributions of the two scattering processes, per gram and steradian
  (:func:`differential_cross_section`):

  - Compton: Klein-Nishina times the incoherent scattering function,
    ``dsigma/dOmega = (dsigma_KN/dOmega)(E, theta) * sum_i w_i N_A / A_i * S_i(x)``;
  - Rayleigh: Thomson times the squared atomic form factor,
    ``dsigma/dOmega = (dsigma_T/dOmega)(theta) * sum_i w_i N_A / A_i * F_i(x)^2``;

  with ``x = sin(theta / 2) / lambda`` (1/Angstrom, xraylib's ``MomentTransf``), element mass
  fractions ``w_i`` of the NIST compound, and xraylib's ``DCS_KN``, ``DCS_Thoms``, ``SF_Compt``
  and ``FF_Rayl``. xraylib's tables start at ``x = 1e-3``; below it ``S`` is continued as ``x^2``
  (its small-``x`` limit) and ``F`` as constant (``F(0) = Z``).

:class:`InteractionTables` puts them on grids for the Dr.Jit transport
(:mod:`sim.physics.scatter`): coefficients on an energy grid (linear interpolation), and for each
scattering process a per-steradian angular pdf on a grid in theta plus its inverse cumulative
distribution (sampling theta from ``u`` in [0, 1)). Units: keV, radians, cm^2/g, 1/sr.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from sim.physics import PhysicsError
from sim.physics.materials import CANCELLOUS_CORTICAL_MASS_FRACTION, KINDS, MATERIALS, _check_name, mass_attenuation

SCATTER_KINDS = ("compton", "rayleigh")
_X_MIN = 1e-3  # smallest momentum transfer (1/Angstrom) in xraylib's S and F tables


def _composition(name: str) -> list[tuple[int, float]]:
    """``[(Z, mass fraction), ...]`` of a material (the cancellous mixture expanded)."""
    import xraylib as xr

    spec = MATERIALS[name]
    if spec == "mixture":
        w = CANCELLOUS_CORTICAL_MASS_FRACTION
        out: dict[int, float] = {}
        for part, frac in (("cortical_bone", w), ("soft_tissue", 1 - w)):
            for z, f in _composition(part):
                out[z] = out.get(z, 0.0) + frac * f
        return sorted(out.items())
    if isinstance(spec, tuple):
        return [(int(spec[1]), 1.0)]
    d = xr.GetCompoundDataNISTByName(spec)
    return list(zip((int(z) for z in d["Elements"]), (float(f) for f in d["massFractions"])))


def differential_cross_section(name: str, kind: str, energies_keV, theta_rad) -> np.ndarray:
    """``d(mu/rho)/dOmega`` in cm^2/g/sr of material ``name`` for ``kind`` ``"compton"`` or
    ``"rayleigh"``, on the grid ``energies_keV`` ``(E,)`` x ``theta_rad`` ``(T,)`` -> ``(E, T)``."""
    import xraylib as xr
    import xraylib_np as xrn

    _check_name(name)
    if kind not in SCATTER_KINDS:
        raise PhysicsError(f"scatter kind must be one of {SCATTER_KINDS}, got {kind!r}")
    e = np.atleast_1d(np.asarray(energies_keV, dtype=np.float64))
    th = np.atleast_1d(np.asarray(theta_rad, dtype=np.float64))
    if e.ndim != 1 or th.ndim != 1 or e.min() < 1.0 or e.max() > 1000.0:
        raise PhysicsError("energies (E,) in [1, 1000] keV and angles (T,) expected")
    if th.min() < 0 or th.max() > math.pi + 1e-12:
        raise PhysicsError("scattering angles must be in [0, pi] rad")
    x = np.sin(th / 2)[None, :] * e[:, None] / 12.39841984  # (E, T) 1/Angstrom
    xc = np.maximum(x, _X_MIN)
    comp = _composition(name)
    zs = np.array([z for z, _ in comp], dtype=np.int64)
    per_gram = np.array([f * xr.AVOGNUM / xr.AtomicWeight(int(z)) for z, f in comp])  # 1e24 atoms / g
    flat = np.unique(xc.ravel())
    pos = np.searchsorted(flat, xc)
    if kind == "compton":
        s = xrn.SF_Compt(zs, flat)  # (Z, Q)
        atoms = (per_gram[:, None] * s).sum(0)[pos] * np.where(x < _X_MIN, (x / _X_MIN) ** 2, 1.0)
        kn = np.stack([xrn.DCS_KN(np.array([ev]), th)[0] for ev in e])  # (E, T) barn-scale units of xraylib
        return kn * atoms
    f = xrn.FF_Rayl(zs, flat)  # (Z, Q)
    atoms = (per_gram[:, None] * f**2).sum(0)[pos]
    return xrn.DCS_Thoms(th)[None, :] * atoms


@dataclass(frozen=True)
class InteractionTables:
    """Gridded interaction data of ``materials`` for the transport.

    Attributes:
        materials: names, in the order of the volume's density channels.
        energies_keV: ``(E,)`` uniform grid of the coefficients.
        mu_mass: ``(3, M, E)`` cm^2/g of photoelectric, Compton, Rayleigh.
        angular_energies_keV: ``(A,)`` uniform grid of the angular tables.
        theta_rad: ``(T,)`` uniform grid in [0, pi].
        pdf_sr: ``(2, M, A, T)`` angular pdf per steradian (integrates to 1 over the sphere,
            with linear interpolation in theta) of Compton and Rayleigh.
        icdf_theta: ``(2, M, A, U)`` theta (rad) at ``U`` uniform cumulative probabilities
            from 0 to 1 of that pdf.
    """

    materials: tuple[str, ...]
    energies_keV: np.ndarray
    mu_mass: np.ndarray
    angular_energies_keV: np.ndarray
    theta_rad: np.ndarray
    pdf_sr: np.ndarray
    icdf_theta: np.ndarray

    @classmethod
    def build(cls, materials, e_max_keV: float, *, e_min_keV: float = 5.0, energy_step_keV: float = 0.5,
              angular_step_keV: float = 2.0, n_theta: int = 721, n_u: int = 2049) -> InteractionTables:
        """Tables from ``e_min_keV`` to at least ``e_max_keV``; ``n_theta`` angles (0.25 deg
        default), ``n_u`` inverse-CDF nodes. Tables are kept per arguments (a few seconds of
        xraylib calls each): every subject of a campaign shares one, read-only."""
        materials = tuple(materials)
        if not materials:
            raise PhysicsError("interaction tables need at least one material")
        if not (1.0 <= e_min_keV < e_max_keV <= 1000.0):
            raise PhysicsError(f"energy range [{e_min_keV}, {e_max_keV}] keV must lie in [1, 1000]")
        return _build_tables(cls, materials, float(e_max_keV), float(e_min_keV), float(energy_step_keV),
                             float(angular_step_keV), int(n_theta), int(n_u))

    @classmethod
    def _build(cls, materials, e_max_keV, e_min_keV, energy_step_keV, angular_step_keV, n_theta, n_u):
        n_e = int(math.ceil((e_max_keV - e_min_keV) / energy_step_keV)) + 1
        energies = e_min_keV + energy_step_keV * np.arange(n_e)
        mu = np.stack([np.stack([mass_attenuation(m, energies, k) for m in materials]) for k in KINDS[1:]])
        n_a = int(math.ceil((energies[-1] - e_min_keV) / angular_step_keV)) + 1
        e_ang = e_min_keV + angular_step_keV * np.arange(n_a)
        theta = np.linspace(0.0, math.pi, n_theta)
        pdf = np.empty((2, len(materials), n_a, n_theta))
        icdf = np.empty((2, len(materials), n_a, n_u))
        # fine sub-grid for integrating the piecewise-linear pdf times 2 pi sin(theta)
        sub = 8
        fine = np.linspace(0.0, math.pi, (n_theta - 1) * sub + 1)
        u = np.linspace(0.0, 1.0, n_u)
        for k, kind in enumerate(SCATTER_KINDS):
            for m, name in enumerate(materials):
                dcs = differential_cross_section(name, kind, e_ang, theta)  # (A, T)
                for a in range(n_a):
                    p_fine = np.interp(fine, theta, dcs[a]) * 2 * math.pi * np.sin(fine)
                    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (p_fine[1:] + p_fine[:-1]) * np.diff(fine))])
                    total = cdf[-1]
                    pdf[k, m, a] = dcs[a] / total
                    cdf = cdf / total
                    # invert: strictly increasing support for np.interp
                    keep = np.concatenate([[True], np.diff(cdf) > 0])
                    icdf[k, m, a] = np.interp(u, cdf[keep], fine[keep])
        out = cls(materials, energies, mu, e_ang, theta, pdf.astype(np.float32), icdf.astype(np.float32))
        for a in (out.energies_keV, out.mu_mass, out.angular_energies_keV, out.theta_rad, out.pdf_sr, out.icdf_theta):
            a.setflags(write=False)  # shared between callers (see build)
        return out


@functools.lru_cache(maxsize=8)
def _build_tables(cls, *args) -> InteractionTables:
    return cls._build(*args)
