"""Monte Carlo photon transport in Dr.Jit: scattered (and, for validation, primary) X-ray signal.

Photons are vectorised over Dr.Jit lanes. One *history* is a tube photon:

1. **Source**: its energy is drawn from the binned spectrum (:class:`sim.physics.spectrum.Spectrum`),
   its direction points from the focal spot to a uniform random point of the detector. The
   field is the detector, and the fluence is taken as uniform over it (the flat-field-corrected
   detector that the deterministic primary of :mod:`sim.physics.poly` also assumes). Each
   history carries ``w = photons per pixel x pixels / histories`` photons.
2. **Woodcock (delta) tracking** through the voxel grid of per-material densities with the
   energy-dependent local majorants ``mu_max(c, E) = max over the voxels of macro cell c of
   sum_m rho_m (mu/rho)_m(E)`` (exact, tabulated on the 0.5 keV grid of the coefficients: linear
   interpolation in E then bounds the interpolated mu too). Optical depths ``-ln(1-u)`` are spent
   cell by cell; where one runs out, a collision is real with probability ``mu(x, E) / mu_max``.
   Local majorants keep a metal implant (or bone) from slowing the tracking everywhere else.
   The loop is a symbolic ``dr.while_loop``.
3. **Real collision**: the material and process are drawn in proportion to
   ``rho_m (mu/rho)_{m,k}(E)``, ``k`` in photoelectric, Compton, Rayleigh (xraylib,
   :mod:`sim.physics.interactions`).

   * photoelectric: the photon is absorbed (its energy deposited; fluorescence neglected);
   * Compton: the angle is drawn from Klein-Nishina x incoherent scattering function (tabulated
     inverse CDF), the energy from Compton kinematics ``E' = E / (1 + E/mc^2 (1 - cos))``
     (no Doppler broadening), ``E - E'`` is deposited;
   * Rayleigh: the angle from Thomson x form factor squared, no energy change.

   Before the photon moves on, **forced detection** (next-event estimation) scores its
   expected direct contribution: a detector point ``y`` is drawn, with probability 1/2 each,
   uniformly over the detector area ``A`` or along the process's angular pdf (one-sample
   multiple importance sampling, balance heuristic), and
   ``w * p_k(Omega_y) G(y) / (1/(2A) + p_k(Omega_y) G(y) / 2) * T(x -> y, E_y) * eta(E_y) * g``
   with ``G = cos(alpha) / r^2`` is added to ``y``'s cell of a coarse detector grid, with ``p_k`` the process's angular pdf per
   steradian (:class:`sim.physics.interactions.InteractionTables`), ``E_y`` the energy after
   scattering toward ``y``, ``alpha`` the incidence angle, ``T`` the transmission estimated by
   **ratio tracking** (a second symbolic loop), ``eta`` the detector response and ``g`` the
   anti-scatter grid transmission. Photons below ``e_cut_keV`` are absorbed where they are.
4. A photon that leaves the volume without any collision is scored as **primary** at its
   detector point (only to validate against the deterministic primary; scattered photons
   leaving the volume are not scored: forced detection has already counted them, in expectation).

Stages run as a wavefront: all photons are tracked to their next collision (one kernel),
collisions are processed and the surviving photons compacted (``dr.compress``), shadow rays are
ratio-tracked (one kernel); this repeats up to ``max_scatter`` times (the same two loop kernels
are reused, never unrolled). Energy is tallied in float64: emitted = deposited + escaped +
truncated (photons stopped after ``max_scatter`` collisions, normally ~0).

The volume is block-averaged to ``voxel_mm`` (mass-conserving): scatter varies slowly and a
coarse grid is the usual choice for scatter estimation. Units: mm, keV, g/cm^3, cm^2/g.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.physics import PhysicsError
from sim.physics.settings import SETTINGS
from sim.core.seeds import TAG_SCATTER_CHUNKS, tagged
from sim.physics.interactions import InteractionTables, SCATTER_KINDS
from sim.physics.poly import Detector
from sim.projection.backend import ensure_variant

_ME_C2_KEV = 510.99895


@dataclass(frozen=True)
class ScatterSettings:
    """Monte Carlo settings.

    Attributes:
        photons: histories per image (int >= 1000; default 10^6); the setting ``scatter_photons``.
        voxel_mm: transport grid voxel (mm, in (0, 100]): the CT is block-averaged to about this
            size; the setting ``scatter_voxel_mm``.
        cell_px: detector pixels per side of a tally cell (int >= 1; default 8).
        smooth_mm: Gaussian sigma (mm at the detector) applied to the cell tallies before they
            are interpolated to pixels (0 = none; default None: :func:`auto_smooth_mm` of the
            histories per detector area, the sigma of least error against a many-history
            reference, :meth:`smoothing_mm`).
        max_scatter: collisions per history before it is stopped (tallied as truncated).
        macro_voxels: side (voxels) of the macro cells that hold the local majorants.
        e_cut_keV: photons below this energy are absorbed locally (keV).
        grid_ratio: anti-scatter grid ratio h/D (0 = no grid). Focused, lamellae along the
            detector columns; transmission ``grid_transmission * max(0, 1 - ratio |tan beta|)``
            with ``beta`` the angle to the focused direction across the lamellae.
        grid_transmission: primary transmission of the grid (0-1].
        batch: photons per wavefront launch.
    """

    photons: int = SETTINGS["scatter_photons"].default
    voxel_mm: float = SETTINGS["scatter_voxel_mm"].default
    cell_px: int = 8
    smooth_mm: float | None = None
    max_scatter: int = 40
    e_cut_keV: float = 5.0
    macro_voxels: int = 8
    grid_ratio: float = SETTINGS["grid_ratio"].default
    grid_transmission: float = 0.7
    batch: int = 1 << 20

    def __post_init__(self) -> None:
        # the ranges of the physics settings of the same meaning (sim.physics.settings)
        for setting, name in (("scatter_photons", "photons"), ("scatter_voxel_mm", "voxel_mm"),
                              ("grid_ratio", "grid_ratio")):
            SETTINGS[setting].check(getattr(self, name), f"scatter {name}")
        ints = {"cell_px": 1, "max_scatter": 1, "batch": 1024, "macro_voxels": 1}
        for name, lo in ints.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise PhysicsError(f"scatter {name} must be an integer >= {lo}, got {v!r}")
        for name, lo, hi in (("smooth_mm", -1e-9, 1000.0), ("e_cut_keV", 1.0, 50.0), ("grid_transmission", 0.0, 1.0)):
            v = getattr(self, name)
            if name == "smooth_mm" and v is None:
                continue
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo < v <= hi):
                raise PhysicsError(f"scatter {name} must be in ({max(lo, 0.0)}, {hi}], got {v!r}")

    def smoothing_mm(self, geometry, photons: int | None = None) -> float:
        """The Gaussian sigma (mm at the detector) of the cell tallies of a run of ``photons``
        histories (default :attr:`photons`) on ``geometry``'s detector: :attr:`smooth_mm`, or
        when that is None :func:`auto_smooth_mm` of the histories and the detector's area."""
        if self.smooth_mm is not None:
            return float(self.smooth_mm)
        g = geometry
        area_mm2 = g.height * g.width * g.pixel_spacing_mm ** 2
        return auto_smooth_mm(int(photons or self.photons), area_mm2)

    @classmethod
    def of(cls, physics) -> ScatterSettings:
        """The Monte Carlo settings of a :class:`sim.physics.settings.PhysicsSettings` (its
        ``scatter_photons``, ``scatter_voxel_mm`` and ``grid_ratio``; the rest default)."""
        return cls(photons=physics.scatter_photons, voxel_mm=physics.scatter_voxel_mm, grid_ratio=physics.grid_ratio)


#: The smoothing of least error at 10^6 histories over a 298 x 298 mm detector (mm at the
#: detector; ``benchmarks/scatter_denoise.py``: the pelvis at 65 kV without a grid and at 125 kV
#: with a ratio-10 grid, 8 px cells of 18.6 mm) and the histories per area it was measured at.
SMOOTH_MM_REFERENCE = 24.0
_HISTORIES_PER_MM2_REFERENCE = 1e6 / 298.0 ** 2
#: How the least-error sigma falls with the histories per area: measured 32 / 24 / 18 mm at
#: 0.25 / 1 / 4 million (a factor 0.75 per 4x, exponent 0.21), as kernel smoothing's
#: bias-variance balance in two dimensions predicts (1/6 for a smooth signal).
SMOOTH_EXPONENT = 0.2


def auto_smooth_mm(histories: int, detector_area_mm2: float) -> float:
    """The Gaussian sigma (mm at the detector, rounded to 0.1 mm) that smooths a Monte Carlo
    scatter estimate of ``histories`` over a detector of ``detector_area_mm2`` (mm^2) to its least
    error: :data:`SMOOTH_MM_REFERENCE` scaled by the histories per area to the power
    ``-SMOOTH_EXPONENT``.

    The estimate's noise is not physics: the scatter of a real exposure (10^9 photons and more) is
    smooth at this scale, and its quantum noise is drawn per pixel with the primary's. Measured
    on the pelvis at 10^6 histories over 298 x 298 mm (``benchmarks/scatter_denoise.py``, docs/physics.md):
    relative error 11.6 % at the former 6 mm, 4.4 % at 24 mm.

    >>> auto_smooth_mm(1_000_000, 298.0 ** 2)
    24.0
    >>> auto_smooth_mm(4_000_000, 298.0 ** 2)
    18.2
    """
    if not (histories >= 1 and detector_area_mm2 > 0 and math.isfinite(detector_area_mm2)):
        raise PhysicsError(f"auto_smooth_mm needs histories >= 1 and a positive detector area, got "
                           f"{histories!r} and {detector_area_mm2!r} mm^2")
    density = histories / detector_area_mm2
    return round(SMOOTH_MM_REFERENCE * (density / _HISTORIES_PER_MM2_REFERENCE) ** -SMOOTH_EXPONENT, 1)


def block_average(densities: np.ndarray, spacing_mm, voxel_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mass-conserving block average of ``(M, I, J, K)`` densities to about ``voxel_mm``.

    Returns ``(coarse (M, I', J', K'), factors (3,), coarse spacing (3,) mm)``; a partial last
    block is padded with vacuum (its density averaged over the whole block), which keeps the mass.
    """
    spacing = np.asarray(spacing_mm, dtype=np.float64)
    f = np.maximum(1, np.round(voxel_mm / spacing)).astype(int)
    m, *shape = densities.shape
    out_shape = [int(math.ceil(n / k)) for n, k in zip(shape, f)]
    pad = [(0, 0)] + [(0, o * k - n) for o, k, n in zip(out_shape, f, shape)]
    d = np.pad(np.asarray(densities, np.float32), pad)
    d = d.reshape(m, out_shape[0], f[0], out_shape[1], f[1], out_shape[2], f[2]).mean(axis=(2, 4, 6))
    return d.astype(np.float32), f, spacing * f


class MonteCarloScatter:
    """Transport through one CT (block-averaged once), for any number of source/detector poses.

    Args:
        densities: ``(M, I, J, K)`` g/cm^3 partial densities of ``materials`` on the CT grid.
        affine: ``(4, 4)`` CT voxel index -> LPS mm (orthogonal axes).
        materials: names of the M channels.
        spectrum: :class:`sim.physics.spectrum.Spectrum`.
        detector: :class:`sim.physics.poly.Detector` (its normal-incidence response).
        settings: :class:`ScatterSettings`.
    """

    def __init__(self, densities: np.ndarray, affine: np.ndarray, materials, spectrum, detector,
                 settings: ScatterSettings | None = None):

        ensure_variant()
        import drjit as dr
        import mitsuba as mi

        self.settings = s = settings or ScatterSettings()
        densities = np.asarray(densities)
        materials = tuple(materials)
        if densities.ndim != 4 or densities.shape[0] != len(materials):
            raise PhysicsError(f"densities must be (M={len(materials)}, I, J, K) g/cm^3, got {densities.shape}")
        if not np.all(np.isfinite(densities)) or densities.min() < 0:
            raise PhysicsError("densities must be finite and >= 0")
        affine = np.asarray(affine, dtype=np.float64)
        spacing = np.linalg.norm(affine[:3, :3], axis=0)
        rot = affine[:3, :3] / spacing
        if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-3:
            raise PhysicsError("Monte Carlo transport needs a CT with orthogonal voxel axes (no shear or gantry tilt)")
        coarse, self.factors, self.voxel_size = block_average(densities, spacing, s.voxel_mm)
        present = [m for m in range(len(materials)) if coarse[m].max() > 0]
        if not present:
            raise PhysicsError("the volume is empty (all densities are zero)")
        self.materials = tuple(materials[m] for m in present)
        coarse = coarse[present]
        self.shape = coarse.shape[1:]
        # LPS -> transport frame q = (fine index + 0.5) * fine spacing: the grid spans [0, n * voxel)
        self._q_from_lps = np.diag(np.append(spacing, 1.0)) @ np.linalg.inv(affine)
        self._q_from_lps[:3, 3] += 0.5 * spacing
        self.spectrum = spectrum
        self.detector = detector
        e_max = float(spectrum.edges_keV[-1]) + 1.0
        self.tables = t = InteractionTables.build(self.materials, e_max, e_min_keV=min(s.e_cut_keV, 5.0))
        e = t.energies_keV
        mu_tot = t.mu_mass.sum(0)  # (M, E) cm^2/g
        # local majorants (1/mm): per macro cell of `macro_voxels`^3 voxels and energy node, the
        # exact maximum over its voxels of sum_m rho_m (mu/rho)_m(E)
        mv = s.macro_voxels
        self.macro_shape = tuple(-(-n // mv) for n in self.shape)
        self.macro_mm = np.asarray(self.voxel_size) * mv
        pad = [(0, 0)] + [(0, c * mv - n) for c, n in zip(self.macro_shape, self.shape)]
        padded = np.pad(coarse, pad).reshape(len(present), -1)
        mc = self.macro_shape
        major = np.empty((int(np.prod(mc)), len(e)), np.float64)
        for start in range(0, len(e), 8):
            mu_v = mu_tot[:, start:start + 8].T.astype(np.float32) @ padded  # (8, voxels) cm^-1
            blocks = mu_v.reshape(-1, mc[0], mv, mc[1], mv, mc[2], mv).max(axis=(2, 4, 6))
            major[:, start:start + 8] = blocks.reshape(blocks.shape[0], -1).T
        # / 10: 1/cm -> 1/mm; a relative margin covers float32 rounding of mu in the kernel
        self.majorant_per_mm = (major / 10.0 * (1.0 + 1e-4) + 1e-12).astype(np.float32)  # (cells, E)
        self.response_keV = detector.response(e)
        self.interaction_prob = Detector(detector.thickness_mm, "counting",
                                         density_g_cm3=detector.density_g_cm3).response(e)
        # spectrum sampling table
        p = spectrum.fluence / spectrum.fluence.sum()
        self._cdf = np.cumsum(p)
        self._cdf[-1] = 1.0
        F = mi.Float
        self._vol = F(np.ascontiguousarray(np.moveaxis(coarse, 0, -1)).ravel())
        self._mu = F((t.mu_mass / 10.0).astype(np.float32).ravel())  # (3, M, E) cm^2/g -> mm^-1 per g/cm^3
        self._major = F(self.majorant_per_mm.ravel())
        self._resp = F(self.response_keV.astype(np.float32))
        self._pint = F(self.interaction_prob.astype(np.float32))
        self._pdf = F(t.pdf_sr.ravel())
        self._icdf = F(t.icdf_theta.ravel())
        self._spec_e = F(spectrum.energies_keV.astype(np.float32))
        self._spec_cdf = F(self._cdf.astype(np.float32))
        self._dr, self._mi = dr, mi

    # ----------------------------------------------------------- helpers
    def _lerp_table(self, table, offset, e):
        """Linear interpolation on the energy grid of ``table[offset + i]``."""
        dr, mi = self._dr, self._mi
        t = self.tables
        x = (e - float(t.energies_keV[0])) / float(t.energies_keV[1] - t.energies_keV[0])
        x = dr.clip(x, 0.0, float(len(t.energies_keV) - 1) - 1e-3)
        i = mi.UInt32(dr.floor(x))
        a = x - mi.Float(i)
        lo = dr.gather(mi.Float, table, offset + i)
        hi = dr.gather(mi.Float, table, offset + i + 1)
        return dr.fma(a, hi - lo, lo)

    def _mu_kind(self, kind: int, m: int, e):
        """(mu/rho) / 10 of process ``kind`` (0 photo, 1 Compton, 2 Rayleigh), material ``m``."""
        n_e = len(self.tables.energies_keV)
        return self._lerp_table(self._mu, (kind * len(self.materials) + m) * n_e, e)

    def _density(self, p, active):
        """Per-material densities at points ``p`` (transport frame, mm) and whether inside."""
        dr, mi = self._dr, self._mi
        vs = self.voxel_size
        ni, nj, nk = self.shape
        inside = (p.x >= 0) & (p.y >= 0) & (p.z >= 0) & (p.x < float(ni * vs[0])) \
            & (p.y < float(nj * vs[1])) & (p.z < float(nk * vs[2]))
        i = dr.clip(mi.Int32(dr.floor(p.x / float(vs[0]))), 0, ni - 1)
        j = dr.clip(mi.Int32(dr.floor(p.y / float(vs[1]))), 0, nj - 1)
        k = dr.clip(mi.Int32(dr.floor(p.z / float(vs[2]))), 0, nk - 1)
        m_count = len(self.materials)
        base = mi.UInt32(((i * nj + j) * nk + k) * m_count)
        rho = [dr.gather(mi.Float, self._vol, base + m, active & inside) for m in range(m_count)]
        return rho, inside

    def _track(self, p, d, mu_m, e_node, rng, active, *, ratio: bool, t_max=None):
        """Delta tracking (``ratio=False``: to the next real collision; returns p, collided, rng)
        or ratio tracking (``ratio=True``: transmission to leaving the volume or ``t_max`` mm;
        returns T, rng) with the local majorants of the macro grid. Each iteration either
        crosses into the next macro cell (spending optical depth ``mu_cell * distance``) or
        reaches the sampled optical depth inside the cell and tests a collision there. One
        symbolic loop; ``mu_m`` (per-material 1/mm per g/cm^3) and ``e_node`` (energy grid
        index, fraction) are loop invariants."""
        dr, mi = self._dr, self._mi
        m_count = len(self.materials)
        n_e = len(self.tables.energies_keV)
        mc = self.macro_shape
        msize = [float(v) for v in self.macro_mm]
        e_i, e_a = e_node
        flag = mi.Bool(False)  # collided (delta tracking)
        trans = mi.Float(1.0)
        travelled = mi.Float(0.0)
        tau = mi.Float(0.0)  # remaining optical depth to the next tentative collision; 0 = draw
        limit = t_max if t_max is not None else mi.Float(dr.inf)
        inv_d = dr.rcp(dr.select(dr.abs(d) < 1e-12, dr.copysign(1e-12, d), d))
        up = mi.Vector3f(dr.select(inv_d.x > 0, 1.0, 0.0), dr.select(inv_d.y > 0, 1.0, 0.0),
                         dr.select(inv_d.z > 0, 1.0, 0.0))
        # the macro cell is carried as integers (a 3-D DDA): crossing a face always changes it,
        # however small the direction component along that axis
        cell = mi.Vector3i(dr.clip(mi.Int32(dr.floor(p.x / msize[0])), 0, mc[0] - 1),
                           dr.clip(mi.Int32(dr.floor(p.y / msize[1])), 0, mc[1] - 1),
                           dr.clip(mi.Int32(dr.floor(p.z / msize[2])), 0, mc[2] - 1))

        def cond(active, p, cell, flag, trans, travelled, tau, rng):
            return active

        def body(active, p, cell, flag, trans, travelled, tau, rng):
            draw = active & (tau <= 0.0)
            tau = dr.select(draw, -dr.log(1.0 - rng.next_float32(active)), tau)
            row = mi.UInt32(((cell.x * mc[1] + cell.y) * mc[2] + cell.z) * n_e) + e_i
            lo = dr.gather(mi.Float, self._major, row, active)
            hi = dr.gather(mi.Float, self._major, row + 1, active)
            maj = dr.fma(e_a, hi - lo, lo)
            # distance to the macro cell's exit face, and which axis it is on
            tx = dr.maximum(((mi.Float(cell.x) + up.x) * msize[0] - p.x) * inv_d.x, 0.0)
            ty = dr.maximum(((mi.Float(cell.y) + up.y) * msize[1] - p.y) * inv_d.y, 0.0)
            tz = dr.maximum(((mi.Float(cell.z) + up.z) * msize[2] - p.z) * inv_d.z, 0.0)
            ax = (tx <= ty) & (tx <= tz)
            ay = ~ax & (ty <= tz)
            az = ~ax & ~ay
            t_exit = dr.minimum(dr.minimum(tx, ty), tz)
            stop = mi.Bool(False)
            if ratio:
                left = dr.maximum(limit - travelled, 0.0)
                stop = left <= t_exit
                t_exit = dr.minimum(t_exit, left)
            cross = active & (maj * t_exit < tau)
            step = dr.select(cross, t_exit, tau / maj)
            tau = dr.select(cross, tau - maj * t_exit, 0.0)
            travelled = dr.select(active, travelled + step, travelled)
            p = dr.select(active, p + d * step, p)
            move = cross & ~stop
            cell = mi.Vector3i(cell.x + dr.select(move & ax, dr.select(inv_d.x > 0, 1, -1), 0),
                               cell.y + dr.select(move & ay, dr.select(inv_d.y > 0, 1, -1), 0),
                               cell.z + dr.select(move & az, dr.select(inv_d.z > 0, 1, -1), 0))
            in_grid = (cell.x >= 0) & (cell.y >= 0) & (cell.z >= 0) & (cell.x < mc[0]) & (cell.y < mc[1]) \
                & (cell.z < mc[2])
            test = active & ~cross
            rho, inside = self._density(p, test)
            mu = mi.Float(0.0)
            for m in range(m_count):
                mu = dr.fma(rho[m], mu_m[m], mu)
            test &= inside
            if ratio:
                trans = dr.select(test, trans * dr.maximum(1.0 - mu / maj, 0.0), trans)
                # Russian roulette below 5 % transmission: survive with probability 1/2 at
                # twice the transmission (unbiased), so deep shadow rays end early
                low = test & (trans < 0.05)
                killed = low & (rng.next_float32(low) >= 0.5)
                trans = dr.select(low, dr.select(killed, 0.0, 2.0 * trans), trans)
                active = active & in_grid & ~(cross & stop) & (inside | cross) & ~killed
            else:
                u = rng.next_float32(test)
                real = test & (u * maj < mu)
                flag = flag | real
                active = active & in_grid & (inside | cross) & ~real
            return active, p, cell, flag, trans, travelled, tau, rng

        active, p, cell, flag, trans, travelled, tau, rng = dr.while_loop(
            state=(mi.Bool(active), p, cell, flag, trans, travelled, tau, rng), cond=cond, body=body,
            label="ctxreg_ratio_tracking" if ratio else "ctxreg_delta_tracking")
        return (trans, rng) if ratio else (p, flag, rng)

    def _invariants(self, e):
        """Per-lane total (mu/rho)/10 (1/mm per g/cm^3) of each material, and the energy grid
        node (index, fraction) of ``e`` for the majorant table."""
        dr, mi = self._dr, self._mi
        mu_m = [self._mu_kind(0, m, e) + self._mu_kind(1, m, e) + self._mu_kind(2, m, e)
                for m in range(len(self.materials))]
        t = self.tables
        x = dr.clip((e - float(t.energies_keV[0])) / float(t.energies_keV[1] - t.energies_keV[0]),
                    0.0, float(len(t.energies_keV) - 1) - 1e-3)
        i = mi.UInt32(dr.floor(x))
        return mu_m, (i, x - mi.Float(i))

    # ---------------------------------------------------------------- run
    def run(self, camera_to_lps: np.ndarray, geometry, *, photons_per_pixel: float, seed: int = 0,
            photons: int | None = None) -> dict:
        """Transport ``photons`` histories for one pose.

        Args:
            camera_to_lps: ``(4, 4)`` camera frame (source at the origin, detector plane
                ``z = sdd``; :mod:`sim.projection.geometry`) -> LPS mm.
            geometry: :class:`sim.projection.geometry.CArmGeometry` of the detector.
            photons_per_pixel: incident photons per pixel without an object (all energies).
            seed: random seed; photons: histories (default the settings').

        Returns:
            ``scatter``, ``scatter_counts``, ``primary`` ``(Hc, Wc)`` float64 per-pixel means over
            each cell of ``cell_px`` pixels (signal units, interacting photons, signal units), and
            ``energy_keV``: ``{"emitted", "deposited", "escaped", "truncated"}`` photon energy
            totals (keV, per history weight 1), ``histories``, ``cell_px``.
        """
        cam = np.asarray(camera_to_lps, dtype=np.float64)
        if cam.shape != (4, 4):
            raise PhysicsError(f"camera_to_lps must be (4, 4), got {cam.shape}")
        return self.run_batch(cam[None], geometry, photons_per_pixel=photons_per_pixel, seeds=[seed],
                              photons=photons)[0]

    def run_batch(self, cameras_to_lps: np.ndarray, geometry, *, photons_per_pixel: float, seeds,
                  photons: int | None = None) -> list[dict]:
        """Transport ``photons`` histories for each of ``B`` poses in shared wavefront launches.

        The photons of several poses travel in the same kernels (each lane carries its pose
        index), so a batch of small images pays the per-launch cost once, not once per pose.
        Pose ``b``'s histories draw from ``seeds[b]`` only, in the same streams as
        :meth:`run` with that seed: its result does not depend on the other poses of the batch
        (equal up to float64 summation order).

        Args:
            cameras_to_lps: ``(B, 4, 4)`` camera frames -> LPS mm (as :meth:`run`).
            geometry: :class:`sim.projection.geometry.CArmGeometry`, the same detector for every pose.
            photons_per_pixel: incident photons per pixel without an object (all energies).
            seeds: ``(B,)`` integer seeds, one per pose.
            photons: histories per pose (default the settings').

        Returns:
            ``B`` dicts as :meth:`run` returns.
        """
        dr, mi = self._dr, self._mi
        s = self.settings
        cams = np.asarray(cameras_to_lps, dtype=np.float64)
        if cams.ndim != 3 or cams.shape[1:] != (4, 4) or len(cams) == 0:
            raise PhysicsError(f"cameras_to_lps must be (B, 4, 4) with B >= 1, got {cams.shape}")
        if not np.all(np.isfinite(cams)):
            raise PhysicsError("cameras_to_lps must be finite")
        seeds = [int(x) for x in np.atleast_1d(np.asarray(seeds))]
        n_pose = len(cams)
        if len(seeds) != n_pose:
            raise PhysicsError(f"need one seed per pose: {n_pose} poses, {len(seeds)} seeds")
        n_total = int(photons or s.photons)
        if n_total < 1:
            raise PhysicsError(f"photons must be >= 1, got {photons}")
        h, w = geometry.height, geometry.width
        cp = s.cell_px
        hc, wc = -(-h // cp), -(-w // cp)
        cells = hc * wc
        sp = float(geometry.pixel_spacing_mm)
        cx = (w - 1) / 2 if geometry.cx is None else geometry.cx
        cy = (h - 1) / 2 if geometry.cy is None else geometry.cy
        # camera -> transport frame, per pose: source, detector corner, detector axes and normal
        q = self._q_from_lps[None] @ cams  # (B, 4, 4)
        src = q[:, :3, 3]
        corner = np.einsum("bij,j->bi", q[:, :3, :3], np.array([(-0.5 - cx) * sp, (-0.5 - cy) * sp,
                                                                  geometry.sdd_mm])) + src
        frames_np = {"src": src, "corner": corner, "eu": q[:, :3, 0], "ev": q[:, :3, 1], "nrm": q[:, :3, 2]}
        frames = {k: mi.Vector3f(*(mi.Float(v[:, i].astype(np.float32)) for i in range(3)))
                  for k, v in frames_np.items()}
        area = float(h * w * sp * sp)
        weight = float(photons_per_pixel) * h * w / n_total  # photons per history
        box = np.array(self.shape) * self.voxel_size

        def V3(*xyz):
            return mi.Vector3f(*(float(c) for c in xyz))

        # one pose: its frame as literals, which the kernels fold in (per-lane gathers of 15
        # floats cost a one-pose run about a quarter of its throughput)
        single = None if n_pose > 1 else tuple(np.asarray(frames_np[k][0], np.float32)
                                               for k in ("src", "corner", "eu", "ev", "nrm"))

        def frame(pose):
            """Per-lane source, corner, eu, ev, normal of the lanes' poses."""
            if single is not None:
                # new literals each time: Dr.Jit 1.5 widens a literal 0.0 in place when it is
                # multiplied by an array, so a frame component that is exactly zero would keep
                # the width of the first wavefront and clash with the compacted ones
                return tuple(V3(*v) for v in single)
            return tuple(dr.gather(mi.Vector3f, frames[k], pose) for k in ("src", "corner", "eu", "ev", "nrm"))

        # tallies are reduced in NumPy (float64, fixed order): atomic scatter-adds from parallel
        # threads would make the images differ in the last bits from run to run
        tallies = {name: np.zeros(n_pose * cells) for name in ("scatter", "scatter_counts", "primary")}

        def tally(name, pose, cell, value, mask):
            keep = np.array(mask, dtype=bool)
            if keep.any():
                index = np.array(cell, dtype=np.int64)[keep]
                if pose is not None:
                    index += np.array(pose, dtype=np.int64)[keep] * cells
                tallies[name] += np.bincount(index, weights=np.array(value, dtype=np.float64)[keep],
                                             minlength=n_pose * cells)
        energy = {k: np.zeros(n_pose) for k in ("emitted", "deposited", "escaped", "truncated")}

        def tally_energy(name, pose, x):
            if dr.width(x):
                lanes = np.zeros(dr.width(x), np.int64) if pose is None else np.array(pose, dtype=np.int64)
                energy[name] += np.bincount(lanes, weights=np.array(x, dtype=np.float64), minlength=n_pose)
        m_count = len(self.materials)
        grid_r, grid_tp = float(s.grid_ratio), float(s.grid_transmission if s.grid_ratio > 0 else 1.0)

        def grid(dn, y, fr):
            if grid_r <= 0:
                return mi.Float(1.0)
            src_v, _, eu_v, _, nrm_v = fr
            f = dr.normalize(y - src_v)
            tan_b = dr.dot(dn, eu_v) / dr.dot(dn, nrm_v) - dr.dot(f, eu_v) / dr.dot(f, nrm_v)
            return grid_tp * dr.maximum(1.0 - grid_r * dr.abs(tan_b), 0.0)

        def detector_point(rng, active, fr):
            _, corner_v, eu_v, ev_v, _ = fr
            px = rng.next_float32(active) * float(w)
            py = rng.next_float32(active) * float(h)
            y = corner_v + eu_v * (px * sp) + ev_v * (py * sp)
            cell = mi.UInt32(dr.minimum(mi.UInt32(py) // cp, hc - 1) * wc + dr.minimum(mi.UInt32(px) // cp, wc - 1))
            return y, cell

        # units of work: (pose, chunk of at most s.batch histories); chunk j of pose b draws from
        # SeedSequence([seed_b, TAG_SCATTER_CHUNKS]).spawn(...)[j], lanes numbered within the chunk
        chunk_sizes = [min(s.batch, n_total - start) for start in range(0, n_total, s.batch)]
        units = []
        for b, sd in enumerate(seeds):
            children = tagged(sd, TAG_SCATTER_CHUNKS).spawn(len(chunk_sizes))
            units += [(b, int(c.generate_state(1, np.uint64)[0]), n) for c, n in zip(children, chunk_sizes)]
        launches, current, filled = [], [], 0
        for u in units:  # pack units into launches of at most s.batch lanes
            if current and filled + u[2] > s.batch:
                launches.append(current)
                current, filled = [], 0
            current.append(u)
            filled += u[2]
        launches.append(current)

        for launch in launches:
            counts = np.array([n for _, _, n in launch])
            n = int(counts.sum())
            # the lanes' pose indices (None for a one-pose run: nothing to carry)
            pose = None if single is not None else mi.UInt32(np.repeat([b for b, _, _ in launch], counts)
                                                            .astype(np.uint32))
            # each unit's lanes i get the PCG32 streams (state + i, 2 i)
            if len(launch) == 1:  # the constructor adds arange(n) to both arguments
                rng = mi.PCG32(size=n, initstate=mi.UInt64(launch[0][1]), initseq=dr.arange(mi.UInt64, n))
            else:  # seed() takes them as given
                state = mi.UInt64(np.repeat(np.array([st for _, st, _ in launch], dtype=np.uint64), counts))
                lane = np.arange(n, dtype=np.uint64) - np.repeat(np.cumsum(counts) - counts, counts).astype(np.uint64)
                rng = mi.PCG32(size=n)
                local = mi.UInt64(lane)
                rng.seed(initstate=state + local, initseq=local + local)
            # source energies: the bin of u in the spectrum's CDF
            u = rng.next_float32()
            cdf = self._spec_cdf
            nb = len(self._cdf)
            b = dr.binary_search(0, nb - 1, lambda i: dr.gather(mi.Float, cdf, i) < u)
            e = dr.gather(mi.Float, self._spec_e, b)
            fr = frame(pose)
            y0, cell0 = detector_point(rng, mi.Bool(True), fr)
            src_v = fr[0]
            d = dr.normalize(y0 - src_v)
            # enter the box
            inv = dr.rcp(dr.select(dr.abs(d) < 1e-12, 1e-12, d))
            t0 = (V3(0.0) - src_v) * inv
            t1 = (V3(*box) - src_v) * inv
            t_near = dr.maximum(dr.max(dr.minimum(t0, t1)), 0.0)
            t_far = dr.min(dr.maximum(t0, t1))
            hits = t_near < t_far
            p = src_v + d * (t_near + 1e-4)
            tally_energy("emitted", pose, e)
            # photons that miss the volume are primary at once
            miss = ~hits
            resp = self._lerp_table(self._resp, 0, e)
            tally("primary", pose, cell0, weight * grid_tp * resp, miss)
            tally_energy("escaped", pose, dr.select(miss, e, 0.0))
            idx = dr.compress(hits)
            p, d, e, cell0, pose = _compact(idx, dr, p, d, e, cell0, pose)
            rng = _gather_rng(rng, idx, mi, dr)
            n_scat = dr.zeros(mi.UInt32, dr.width(idx))
            for _ in range(s.max_scatter + 1):
                if dr.width(e) == 0:
                    break
                mu_m, node = self._invariants(e)
                p, collided, rng = self._track(p, d, mu_m, node, rng, mi.Bool(True), ratio=False)
                dr.eval(p, collided, rng)
                escaped = ~collided
                first = escaped & (n_scat == 0)
                resp = self._lerp_table(self._resp, 0, e)
                tally("primary", pose, cell0, weight * grid_tp * resp, first)
                tally_energy("escaped", pose, dr.select(escaped, e, 0.0))
                idx = dr.compress(collided)
                p, d, e, cell0, n_scat, pose = _compact(idx, dr, p, d, e, cell0, n_scat, pose)
                rng = _gather_rng(rng, idx, mi, dr)
                if dr.width(e) == 0:
                    break
                fr = frame(pose)
                _, corner_v, eu_v, ev_v, nrm_v = fr
                # choose material and process
                # Loop outputs are evaluated once here: a symbolic loop used by two later kernels
                # would otherwise run twice.
                rho, _ = self._density(p, mi.Bool(True))
                parts = [(k, m, rho[m] * self._mu_kind(k, m, e)) for k in range(3) for m in range(m_count)]
                total = mi.Float(0.0)
                for _, _, v in parts:
                    total += v
                target = rng.next_float32() * total
                kind = mi.UInt32(2)
                mat = mi.UInt32(m_count - 1)
                acc = mi.Float(0.0)
                chosen = mi.Bool(False)
                for k, m, v in parts:
                    acc += v
                    pick = ~chosen & (target < acc)
                    kind = dr.select(pick, k, kind)
                    mat = dr.select(pick, m, mat)
                    chosen |= pick
                photo = kind == 0
                scat = ~photo
                compton = kind == 1
                sk = dr.select(compton, mi.UInt32(0), mi.UInt32(1))  # index into the angular tables
                # --- forced detection: one-sample multiple importance sampling of the detector
                # point, uniform over the detector or along the process's angular pdf (balance
                # heuristic). The uniform strategy alone gives "fireflies" where the Rayleigh
                # forward peak meets the detector; the mixture keeps every score bounded.
                y1, cell1 = detector_point(rng, scat, fr)
                th2 = self._sample_theta(sk, mat, e, rng.next_float32(scat), rng.next_float32(scat))
                d2 = _rotate(d, dr.cos(th2), dr.sin(th2), 2.0 * math.pi * rng.next_float32(scat), mi, dr)
                den = dr.dot(d2, nrm_v)
                t2 = dr.dot(corner_v - p, nrm_v) / dr.select(dr.abs(den) > 1e-9, den, 1e-9)
                y2 = p + d2 * t2
                px2 = dr.dot(y2 - corner_v, eu_v) / sp
                py2 = dr.dot(y2 - corner_v, ev_v) / sp
                on2 = (den > 1e-9) & (t2 > 0) & (px2 >= 0) & (py2 >= 0) & (px2 < float(w)) & (py2 < float(h))
                cell2 = mi.UInt32(dr.minimum(mi.UInt32(dr.maximum(py2, 0.0)) // cp, hc - 1) * wc
                                  + dr.minimum(mi.UInt32(dr.maximum(px2, 0.0)) // cp, wc - 1))
                by_pdf = rng.next_float32(scat) < 0.5
                y = dr.select(by_pdf, y2, y1)
                cell = dr.select(by_pdf, cell2, cell1)
                v = y - p
                r = dr.norm(v)
                dn = v / r
                cos_n = dr.clip(dr.dot(d, dn), -1.0, 1.0)
                e_n = dr.select(compton, e / (1.0 + e / _ME_C2_KEV * (1.0 - cos_n)), e)
                pdf = self._angular_pdf(sk, mat, e, dr.acos(cos_n))
                cos_a = dr.abs(dr.dot(dn, nrm_v))
                geo = cos_a / (r * r)
                mix = 0.5 / area + 0.5 * pdf * geo  # the two strategies' densities per mm^2
                value = weight * pdf * geo / mix * grid(dn, y, fr)
                nee = scat & (~by_pdf | on2)
                mu_n, node_n = self._invariants(e_n)
                dr.eval(dn, e_n, value, cell, kind, mat, scat, nee)
                trans, rng = self._track(p, dn, mu_n, node_n, rng, nee, ratio=True, t_max=r)
                dr.eval(trans, rng)
                value = dr.select(nee, value * trans, 0.0)
                tally("scatter", pose, cell, value * self._lerp_table(self._resp, 0, e_n), scat)
                tally("scatter_counts", pose, cell, value * self._lerp_table(self._pint, 0, e_n), scat)
                # --- the real interaction
                theta = self._sample_theta(sk, mat, e, rng.next_float32(), rng.next_float32())
                phi = 2.0 * math.pi * rng.next_float32()
                cos_t = dr.cos(theta)
                e_new = dr.select(compton, e / (1.0 + e / _ME_C2_KEV * (1.0 - cos_t)), e)
                e_new = dr.select(photo, 0.0, e_new)
                d = _rotate(d, cos_t, dr.sin(theta), phi, mi, dr)
                n_scat += 1
                low = scat & (e_new < float(s.e_cut_keV))
                tally_energy("deposited", pose, e - dr.select(low, 0.0, e_new))
                e = dr.select(low, 0.0, e_new)
                alive = scat & ~low
                last = n_scat > s.max_scatter
                tally_energy("truncated", pose, dr.select(alive & last, e, 0.0))
                dr.eval(p, d, e, n_scat, alive, last)
                idx = dr.compress(alive & ~last)
                p, d, e, cell0, n_scat, pose = _compact(idx, dr, p, d, e, cell0, n_scat, pose)
                rng = _gather_rng(rng, idx, mi, dr)
            tally_energy("truncated", pose, e)
        px_per_cell = _pixels_per_cell(h, w, cp)
        results = []
        for b in range(n_pose):
            out = {name: arr[b * cells:(b + 1) * cells].reshape(hc, wc) / px_per_cell for name, arr in tallies.items()}
            out["energy_keV"] = {k: float(v[b]) for k, v in energy.items()}
            out["histories"] = n_total
            out["cell_px"] = cp
            results.append(out)
        return results

    def _angular_pdf(self, sk, mat, e, theta):
        """Per-steradian pdf of scatter table ``sk`` of material ``mat`` at ``e``, ``theta`` (bilinear)."""
        dr, mi = self._dr, self._mi
        t = self.tables
        n_a, n_t = len(t.angular_energies_keV), len(t.theta_rad)
        xa = dr.clip((e - float(t.angular_energies_keV[0])) / float(t.angular_energies_keV[1] - t.angular_energies_keV[0]),
                     0.0, n_a - 1 - 1e-3)
        ia = mi.UInt32(dr.floor(xa))
        fa = xa - mi.Float(ia)
        xt = dr.clip(theta / float(t.theta_rad[1]), 0.0, n_t - 1 - 1e-3)
        it = mi.UInt32(dr.floor(xt))
        ft = xt - mi.Float(it)
        base = ((sk * len(self.materials) + mat) * n_a + ia) * n_t + it
        g = lambda off: dr.gather(mi.Float, self._pdf, base + off)  # noqa: E731
        lo = dr.lerp(g(0), g(1), ft)
        hi = dr.lerp(g(n_t), g(n_t + 1), ft)
        return dr.lerp(lo, hi, fa)

    def _sample_theta(self, sk, mat, e, u_energy, u):
        """Scattering angle (rad) of table ``sk`` of material ``mat`` at ``e``: the angular grid
        energy is chosen stochastically between its neighbours (so the sampled density is the
        same linear interpolation in energy as :meth:`_angular_pdf`), then the inverse CDF."""
        dr, mi = self._dr, self._mi
        t = self.tables
        n_a, n_u = len(t.angular_energies_keV), t.icdf_theta.shape[-1]
        xa = dr.clip((e - float(t.angular_energies_keV[0])) / float(t.angular_energies_keV[1] - t.angular_energies_keV[0]),
                     0.0, n_a - 1 - 1e-3)
        ia = mi.UInt32(dr.floor(xa))
        ia = dr.select(u_energy < xa - mi.Float(ia), ia + 1, ia)
        xu = u * float(n_u - 1)
        iu = dr.minimum(mi.UInt32(dr.floor(xu)), n_u - 2)
        fu = xu - mi.Float(iu)
        base = ((sk * len(self.materials) + mat) * n_a + ia) * n_u + iu
        return dr.lerp(dr.gather(mi.Float, self._icdf, base), dr.gather(mi.Float, self._icdf, base + 1), fu)

    def sample_angles(self, kind: str, material: str, energy_keV: float, n: int, seed: int = 0) -> np.ndarray:
        """``(n,)`` scattering angles (rad) drawn by the transport's own sampler (for tests)."""

        dr, mi = self._dr, self._mi
        if kind not in SCATTER_KINDS or material not in self.materials:
            raise PhysicsError(f"kind must be one of {SCATTER_KINDS} and material one of {self.materials}")
        rng = mi.PCG32(size=n, initstate=mi.UInt64(seed + 1), initseq=dr.arange(mi.UInt64, n))
        e = dr.full(mi.Float, float(energy_keV), n)
        sk = dr.full(mi.UInt32, SCATTER_KINDS.index(kind), n)
        mat = dr.full(mi.UInt32, self.materials.index(material), n)
        return np.array(self._sample_theta(sk, mat, e, rng.next_float32(), rng.next_float32()), dtype=np.float64)

    def angular_pdf(self, kind: str, material: str, energy_keV: float, theta_rad: np.ndarray) -> np.ndarray:
        """The transport's per-steradian pdf at ``theta_rad`` ``(N,)`` (for tests)."""

        mi = self._mi
        th = np.asarray(theta_rad, dtype=np.float32)
        n = len(th)
        sk = self._dr.full(mi.UInt32, SCATTER_KINDS.index(kind), n)
        mat = self._dr.full(mi.UInt32, self.materials.index(material), n)
        return np.array(self._angular_pdf(sk, mat, self._dr.full(mi.Float, float(energy_keV), n), mi.Float(th)),
                        dtype=np.float64)


def _pixels_per_cell(h: int, w: int, cp: int) -> np.ndarray:
    rows = np.minimum(cp, h - cp * np.arange(-(-h // cp)))
    cols = np.minimum(cp, w - cp * np.arange(-(-w // cp)))
    return rows[:, None] * cols[None, :].astype(np.float64)


def _compact(idx, dr, *values):
    """The lanes ``idx`` of each value (``None`` stays ``None``)."""
    return tuple(None if v is None else dr.gather(type(v), v, idx) for v in values)


def _gather_rng(rng, idx, mi, dr):
    out = mi.PCG32()
    out.state = dr.gather(type(rng.state), rng.state, idx)
    out.inc = dr.gather(type(rng.inc), rng.inc, idx)
    return out


def _rotate(d, cos_t, sin_t, phi, mi, dr):
    """Direction at polar angle theta (cos, sin) and azimuth phi about unit vector ``d``."""
    sign = dr.select(d.z >= 0, 1.0, -1.0)
    a = -1.0 / (sign + d.z)
    b = d.x * d.y * a
    t1 = mi.Vector3f(1.0 + sign * d.x * d.x * a, sign * b, -sign * d.x)
    t2 = mi.Vector3f(b, sign + d.y * d.y * a, -d.y)
    out = d * cos_t + (t1 * dr.cos(phi) + t2 * dr.sin(phi)) * sin_t
    return dr.normalize(out)


def upsample_cells(cells: np.ndarray, h: int, w: int, cell_px: int, sigma_cells: float) -> np.ndarray:
    """Smooth ``(Hc, Wc)`` cell means with a Gaussian of ``sigma_cells`` and interpolate them
    (bilinear, cell centres) to ``(h, w)`` pixels."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    c = np.asarray(cells, dtype=np.float64)
    if sigma_cells > 0:
        c = gaussian_filter(c, sigma_cells, mode="nearest")
    rows = (np.arange(h) + 0.5) / cell_px - 0.5
    cols = (np.arange(w) + 0.5) / cell_px - 0.5
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    return map_coordinates(c, [rr, cc], order=1, mode="nearest")
