"""Two-basis polychromatic X-rays: realistic images at (nearly) line-DRR cost, batched in torch.

The 9-channel renderer (:mod:`sim.physics.poly`) marches the CT once per pose and gathers one
density line integral per material of :data:`sim.physics.materials.TISSUE_DECOMPOSITION` plus the tool
materials: 9 values per ray step, about 10x a line DRR. Over the diagnostic energies every
body material's mass attenuation is, to within a few per cent, a linear combination of two
basis materials' (Alvarez and Macovski 1976): here **water** and **ICRP cortical bone**::

    (mu/rho)_m(E) ~ a_m (mu/rho)_water(E) + b_m (mu/rho)_bone(E)

(:func:`basis_coefficients`: least squares of the relative error over 15-150 keV, log-spaced).
A voxel of partial densities ``rho_m`` (g/cm^3) then holds two basis densities
``rho_w = sum_m a_m rho_m`` and ``rho_b = sum_m b_m rho_m`` (:func:`basis_densities`), one ray
march gathers their two line integrals ``L_w, L_b`` (g/cm^2), and the detector signal of any
spectrum and detector follows from the two numbers per pixel::

    I = sum_E w(E) exp(-(mu/rho)_w(E) L_w - s_b (mu/rho)_b(E) L_b - sum_t (mu/rho)_t(E) L_t)

with ``w(E)`` the photons per pixel times the detector response (:mod:`sim.physics.poly`), ``s_b``
a bone-attenuation factor (domain randomization's ``bone_scale``; 1 is the physics), ``L_t`` the
tool chords' density integrals. The approximation error against the 9-material model is
stated in ``docs/physics.md`` and tested (``tests/sim/test_two_basis.py``).

:class:`SpectralTable` holds every tube setting a domain randomization can draw (the grids of
kV, Al and Cu), binned as :func:`sim.physics.spectrum.filtered_tube_spectrum` bins them, with
the mass attenuations at each bin energy and the detector response: built once with spekpy and
xraylib, saved to a small ``.npz`` (no object pickles), and gathered per pair on any torch
device (:class:`TorchImager`): the expected signal and its quantum-noise variance
(compound Poisson, exact for the energy-integrating detector without Swank noise) in one pass.
"""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.physics import PhysicsError
from sim.core.atomic import atomic_path
from sim.physics.materials import TISSUE_DECOMPOSITION, mass_attenuation
from sim.physics.poly import Detector
from sim.physics.settings import SETTINGS
from sim.physics.spectrum import filtered_tube_spectrum

__all__ = ["BASES", "TOOL_CHANNELS", "basis_coefficients", "basis_matrix", "basis_densities", "BasisDecomposition",
           "SpectralTable", "TorchImager"]

#: The two basis materials (:data:`sim.physics.materials.MATERIALS` names), in channel order.
BASES: tuple[str, str] = ("water", "cortical_bone")
#: Tool materials with their own channel in a :class:`SpectralTable` (metal and equipment of
#: :mod:`sim.distractors`; a tool's chords are not part of the CT, so they need no basis fit).
TOOL_CHANNELS: tuple[str, ...] = ("titanium", "stainless_steel", "carbon", "copper", "pvc")
#: Energies (keV) of the basis fit: the span of the tube spectra (60-130 kV after 2 mm Al).
FIT_ENERGIES_KEV = np.geomspace(15.0, 150.0, 64)


def basis_coefficients(material: str, bases: tuple[str, str] = BASES) -> np.ndarray:
    """``(2,)`` coefficients ``(a, b)`` with ``(mu/rho)_material ~ a (mu/rho)_bases[0] + b
    (mu/rho)_bases[1]`` over :data:`FIT_ENERGIES_KEV`: least squares of the relative error
    (each energy's row divided by the material's own coefficient), dimensionless."""

    e = FIT_ENERGIES_KEV
    target = mass_attenuation(material, e)
    a = np.stack([mass_attenuation(b, e) for b in bases], axis=1) / target[:, None]
    coef, *_ = np.linalg.lstsq(a, np.ones_like(e), rcond=None)
    return coef


def basis_matrix(materials, bases: tuple[str, str] = BASES) -> np.ndarray:
    """``(M, 2)``: :func:`basis_coefficients` of each material name."""
    return np.stack([basis_coefficients(m, bases) for m in materials])


class BasisDecomposition:
    """A CT's voxels as two basis densities (g/cm^3), usable wherever a
    :class:`sim.physics.materials.MaterialDecomposition` is (``names``, ``partial_densities(hu)``): the
    Dr.Jit renderer's ``quantity="density"`` then gathers the two basis line integrals.

    Args:
        decomposition: the HU decomposition whose materials are projected on the bases (default
            :data:`sim.physics.materials.TISSUE_DECOMPOSITION`).
        matrix: its ``(M, 2)`` :func:`basis_matrix` when already computed (default: computed).
    """

    def __init__(self, decomposition=None, *, matrix=None):
        self.decomposition = decomposition or TISSUE_DECOMPOSITION
        # (M, 2); a stored one (SpectralTable.basis) spares xraylib where it is not installed
        self.matrix = basis_matrix(self.decomposition.names) if matrix is None else np.asarray(matrix, np.float64)
        if self.matrix.shape != (len(self.decomposition.names), 2):
            raise PhysicsError(f"basis matrix must be (M={len(self.decomposition.names)}, 2), got {self.matrix.shape}")

    names = BASES

    def partial_densities(self, hu: np.ndarray) -> np.ndarray:
        """``(2, *hu.shape)`` float32 basis densities (g/cm^3; the bone one may be slightly
        negative in fat, where the fit's water coefficient exceeds 1)."""
        rho = self.decomposition.partial_densities(hu)  # (M, ...)
        return np.tensordot(self.matrix.T.astype(np.float32), rho, axes=1).astype(np.float32)


def basis_densities(hu: np.ndarray, decomposition=None) -> np.ndarray:
    """``(2, *hu.shape)`` float32 water and bone basis densities (g/cm^3) of HU values."""
    return BasisDecomposition(decomposition).partial_densities(hu)


def _discrete_values(setting) -> list[float]:
    """The values a :class:`sim.randomize.Randomized` can take, for a discrete one."""
    if setting.dist == "choice":
        return sorted({float(c) for c, q in zip(setting.choices, setting.probs) if q > 0})
    if setting.step is not None:
        n = int(math.floor((setting.high - setting.low) / setting.step + 1e-9)) + 1
        return sorted({min(round(setting.low + i * setting.step, 9), setting.high) for i in range(n)})
    if setting.low == setting.high:
        return [float(setting.low)]
    raise PhysicsError(f"randomize.{setting.name} must be discrete (a 'step', a choice or one value) for a "
                       f"spectral table, got a continuous [{setting.low:g}, {setting.high:g}]")


@dataclass(frozen=True)
class SpectralTable:
    """Binned spectra, mass attenuations and detector response for every tube setting of a grid.

    Attributes (``C`` combinations of kV, Al and Cu; ``E`` energy bins; ``K`` channels =
    :data:`BASES` then :data:`TOOL_CHANNELS`):
        settings: ``(C, 3)`` float64 kV, Al mm, Cu mm.
        energies_keV: ``(C, E)`` bin energies (fluence-weighted means, as
            :func:`sim.physics.spectrum.filtered_tube_spectrum`).
        fluence: ``(C, E)`` photons / mm^2 / mAs at 1000 mm per bin.
        mass_att: ``(C, K, E)`` cm^2/g of each channel at each bin energy.
        response: ``(C, E)`` mean signal per incident photon (keV for the integrating detector).
        interaction: ``(C, E)`` probability that a photon interacts in the CsI.
        detector: ``(thickness_mm, mode)`` of the detector.
        basis: ``(M, 2)`` :func:`basis_matrix` of :data:`sim.physics.materials.TISSUE_DECOMPOSITION`'s
            materials (kept with the table: computing it needs xraylib).
    """

    settings: np.ndarray
    energies_keV: np.ndarray
    fluence: np.ndarray
    mass_att: np.ndarray
    response: np.ndarray
    interaction: np.ndarray
    detector: tuple[float, str]
    anode_angle_deg: float
    bins: int
    basis: np.ndarray

    channels = BASES + TOOL_CHANNELS

    @classmethod
    def build(cls, kvps, al_mm, cu_mm, *, bins: int | None = None, anode_angle_deg: float | None = None,
              detector=None) -> "SpectralTable":
        """Every combination of the given kV, Al mm and Cu mm (spekpy once per kV)."""

        bins = SETTINGS["bins"].default if bins is None else int(bins)
        angle = SETTINGS["anode_angle_deg"].default if anode_angle_deg is None else float(anode_angle_deg)
        det = detector or Detector()
        counting = Detector(det.thickness_mm, "counting", density_g_cm3=det.density_g_cm3)
        rows, energies, fluence, att, resp, inter = [], [], [], [], [], []
        for kv in kvps:
            for al in al_mm:
                for cu in cu_mm:
                    filters = (("Al", float(al)),) + ((("Cu", float(cu)),) if cu > 0 else ())
                    s = filtered_tube_spectrum(float(kv), anode_angle_deg=angle, filters=filters, bins=bins)
                    rows.append((float(kv), float(al), float(cu)))
                    energies.append(s.energies_keV)
                    fluence.append(s.fluence)
                    att.append(np.stack([mass_attenuation(m, s.energies_keV) for m in cls.channels]))
                    resp.append(det.response(s.energies_keV))
                    inter.append(counting.response(s.energies_keV))

        return cls(np.asarray(rows), np.asarray(energies), np.asarray(fluence), np.asarray(att), np.asarray(resp),
                   np.asarray(inter), (float(det.thickness_mm), str(det.mode)), angle, bins,
                   basis_matrix(TISSUE_DECOMPOSITION.names))

    @staticmethod
    def grid_for(randomization) -> dict[str, list[float]]:
        """``{"kvp": [...], "al_mm": [...], "cu_mm": [...]}``: every kV, Al mm and Cu mm a
        :class:`sim.randomize.DomainRandomization` can draw (all that its table depends on)."""
        s = randomization.by_name
        return {name: _discrete_values(s[name]) for name in ("kvp", "al_mm", "cu_mm")}

    @classmethod
    def for_randomization(cls, randomization, **kw) -> "SpectralTable":
        """The table of every (kV, Al, Cu) a :class:`sim.randomize.DomainRandomization` can draw."""
        grid = cls.grid_for(randomization)
        return cls.build(grid["kvp"], grid["al_mm"], grid["cu_mm"], **kw)

    def index(self, kvp, al_mm, cu_mm) -> np.ndarray:
        """``(B,)`` row of each ``(kvp, al_mm, cu_mm)``; refused when one is not in the table."""
        want = np.stack([np.asarray(kvp, float).ravel(), np.asarray(al_mm, float).ravel(),
                         np.asarray(cu_mm, float).ravel()], axis=1)
        d = np.abs(want[:, None, :] - self.settings[None, :, :]).max(axis=2)
        i = d.argmin(axis=1)
        bad = d[np.arange(len(i)), i] > 1e-6
        if bad.any():
            kv, al, cu = want[np.flatnonzero(bad)[0]]
            raise PhysicsError(f"tube setting {kv:g} kV, {al:g} mm Al, {cu:g} mm Cu is not in the spectral table "
                               f"(built for {len(self.settings)} settings): rebuild it for this randomization")
        return i

    # -- file ------------------------------------------------------------------------------------
    _ARRAYS = ("settings", "energies_keV", "fluence", "mass_att", "response", "interaction", "basis")

    def save(self, path: str | Path) -> Path:
        """Write an ``.npz`` (plain arrays, no pickles) atomically."""

        path = Path(path)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **{k: getattr(self, k) for k in self._ARRAYS},
                         detector_mm=np.float64(self.detector[0]), detector_mode=np.str_(self.detector[1]),
                         anode_angle_deg=np.float64(self.anode_angle_deg), bins=np.int64(self.bins),
                         channels=np.array(self.channels))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "SpectralTable":
        """Read :meth:`save`'s file; a damaged or foreign file is refused in one line."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                if tuple(str(c) for c in z["channels"]) != cls.channels:
                    raise PhysicsError(f"spectral table {path}: channels {list(z['channels'])} are not "
                                       f"{list(cls.channels)}: remove it to rebuild")
                arrays = {k: np.asarray(z[k]) for k in cls._ARRAYS}
                extra = dict(detector=(float(z["detector_mm"]), str(z["detector_mode"])),
                             anode_angle_deg=float(z["anode_angle_deg"]), bins=int(z["bins"]))
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as e:  # truncated: BadZipFile
            raise PhysicsError(f"spectral table {path} cannot be read ({e}): remove it to rebuild") from None
        c, e = arrays["fluence"].shape
        if (arrays["mass_att"].shape != (c, len(cls.channels), e) or arrays["settings"].shape != (c, 3)
                or arrays["basis"].ndim != 2 or arrays["basis"].shape[1] != 2):
            raise PhysicsError(f"spectral table {path}: inconsistent array shapes: remove it to rebuild")
        return cls(**arrays, **extra)


class TorchImager:
    """The expected detector signal and its quantum-noise variance, batched over pairs in torch.

    Args:
        table: the :class:`SpectralTable`.
        device: torch device of every tensor it returns.

    ``signal(L, combo, mas, bone_scale, *, pixel_area_mm2, sdd_mm)``: ``L`` ``(B, K, H, W)``
    density line integrals in g/cm^2 (channels :attr:`SpectralTable.channels`; fewer channels
    than ``K`` means the remaining ones are zero), ``combo`` ``(B,)`` table rows, ``mas`` ``(B,)``
    mAs, ``bone_scale`` ``(B,)`` factor on the bone basis -> ``(mean (B, H, W), variance
    (B, H, W), flat (B,))`` in signal units (keV): the expected signal, the variance of the
    compound-Poisson signal (the interacting photons of each bin Poisson, each adding its mean
    signal), and the signal without an object (``I0``).

    Example::

        >>> table = SpectralTable.build([80.0], [2.5], [0.0])               # doctest: +SKIP
        >>> imager = TorchImager(table, "cpu")                              # doctest: +SKIP
        >>> L = torch.zeros(1, 2, 4, 4); L[:, 0] = 20.0                     # 20 cm of water
        >>> mean, var, flat = imager.signal(L, torch.tensor([0]), torch.tensor([2.5]),
        ...                                 torch.ones(1), pixel_area_mm2=1.0, sdd_mm=1000.0)
    """

    #: Pairs per batched product on a CPU (:meth:`signal`).
    CPU_CHUNK = 16

    def __init__(self, table: SpectralTable, device="cpu"):
        import torch

        self.table = table
        self.device = torch.device(device)
        f64 = dict(dtype=torch.float64, device=self.device)
        self.fluence = torch.as_tensor(table.fluence, **f64)  # (C, E)
        self.mass_att = torch.as_tensor(table.mass_att, **f64)  # (C, K, E)
        self.response = torch.as_tensor(table.response, **f64)
        self.interaction = torch.as_tensor(table.interaction, **f64)
        per = np.where(table.interaction > 0, table.response / np.where(table.interaction > 0, table.interaction, 1), 0)
        self.per_photon = torch.as_tensor(per, **f64)  # mean signal of an interacting photon (C, E)

    def signal(self, L, combo, mas, bone_scale, *, pixel_area_mm2: float, sdd_mm: float):
        import torch

        if L.ndim != 4 or not 1 <= L.shape[1] <= self.mass_att.shape[1]:
            raise PhysicsError(f"density line integrals must be (B, K <= {self.mass_att.shape[1]}, H, W) g/cm^2, "
                               f"got {tuple(L.shape)}")
        b, k, h, w = L.shape
        combo = torch.as_tensor(combo, device=self.device, dtype=torch.long)
        att = self.mass_att[combo, :k].clone()  # (B, k, E)
        att[:, 1] = att[:, 1] * torch.as_tensor(bone_scale, **_like(att))[:, None]
        scale = torch.as_tensor(mas, **_like(att)) * pixel_area_mm2 * (1000.0 / sdd_mm) ** 2
        n0 = self.fluence[combo] * scale[:, None]  # (B, E) photons per pixel
        dtype = L.dtype
        weight = n0 * self.response[combo]  # (B, E) keV per pixel without an object
        counts = n0 * self.interaction[combo]
        per = self.per_photon[combo]
        exponent = att.neg().to(dtype).transpose(1, 2)  # (B, E, k)
        paths = L.reshape(b, k, h * w).to(dtype)
        sums = torch.stack([weight, counts * per * per], 1).to(dtype)  # (B, 2, E)
        # (B, E, P) exponents, then transmissions in place, then their two weighted sums over the
        # energies: batched matrix products (torch's einsum over these shapes is 10x slower on a
        # CPU), on a CPU a few pairs at a time so that the (chunk, E, P) transmissions stay in cache
        # (half the time of one call for a batch of 180 pairs of 64 x 64 px)
        chunk = b if self.device.type != "cpu" else self.CPU_CHUNK
        moments = torch.empty(b, 2, h * w, dtype=dtype, device=self.device)
        for s in range(0, b, chunk):
            t = torch.bmm(exponent[s:s + chunk], paths[s:s + chunk]).exp_()
            torch.bmm(sums[s:s + chunk], t, out=moments[s:s + chunk])
        mean, var = moments[:, 0], moments[:, 1]
        flat = weight.sum(dim=1).to(dtype)
        return mean.reshape(b, h, w), var.reshape(b, h, w), flat


def _like(t):
    return {"dtype": t.dtype, "device": t.device}
