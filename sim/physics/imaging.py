"""Realistic X-ray images of a CT: density line integrals once per pose, then spectrum, detector, noise.

:class:`XRayImager` wraps a :class:`sim.projection.drr.DRRRenderer` with ``quantity="density"`` over
:data:`sim.physics.materials.TISSUE_DECOMPOSITION`, and a :class:`sim.physics.poly.Polychromatic`
model. Physics levels (:data:`sim.physics.settings.LEVELS`):

* ``line``: line integrals of mu at one effective energy (the plain DRR of :mod:`sim.projection.drr`);
* ``poly``: spectral polychromatic attenuation, energy-integrating CsI detector, and optionally
  quantum and electronic noise with detector blur;
* ``full``: ``poly`` plus Monte Carlo scatter (:mod:`sim.physics.scatter`), added to the
  primary signal before noise, and an optional anti-scatter grid.

The settings (:class:`PhysicsSettings`, :data:`LEVELS`) are declared in :mod:`sim.physics.settings`.

Outputs per pose (:meth:`XRayImager.render`): ``raw`` detector signal (keV per pixel, or counts),
``log`` = ``-log(I / I0)`` (the usual log-corrected image: comparable to a line integral of mu),
``primary`` (the expected primary signal without noise) and, for ``full``, ``scatter`` (the
expected scattered signal, smoothed Monte Carlo estimate). With a grid, the flat field ``I0`` is
taken with the grid in place (as a flat-field calibration would), so the log image of the
primary does not change.
"""

from __future__ import annotations

import numpy as np

from sim.physics import PhysicsError
from sim.physics.settings import PhysicsSettings  # noqa: F401  (declared in settings; imported from here too)
from sim.core.seeds import image_noise_rng, pose_seed
from sim.physics.materials import LabelOverride, TISSUE_DECOMPOSITION
from sim.physics.poly import Detector, Polychromatic
from sim.physics.scatter import upsample_cells
from sim.physics.spectrum import tube_spectrum
from sim.projection.drr import DRRRenderer, RenderSettings
from sim.projection.geometry import extrinsic_lps_to_camera
from sim.physics.scatter import MonteCarloScatter, ScatterSettings


class XRayImager:
    """Realistic images of one CT at many poses (see the module doc).

    Args:
        volume: :class:`sim.ct.volume.CTVolume`.
        physics: :class:`PhysicsSettings`.
        scene, size, ray_model: as :class:`sim.projection.drr.RenderSettings`.
        center_lps, geometry: as :class:`sim.projection.drr.DRRRenderer`.
        label_materials: ``{label: material}``: the CT's label map overrides the HU-based
            materials there (:class:`sim.physics.materials.LabelOverride`), e.g. an implant
            segmented as titanium.
        fixed_scatter_seed: draw every pose's Monte Carlo from the same seed (common random
            numbers), so that the image of a pose does not depend on its place in a batch and an
            optimiser comparing poses sees a deterministic objective. Off (the default), each pose
            of a batch has its own stream, as independent images of a dataset should.
    """

    def __init__(self, volume, physics: PhysicsSettings | None = None, *, scene: str = "cios_fusion",
                 size=None, ray_model: str = "siddon", center_lps=None, geometry=None,
                 label_materials: dict[int, str] | None = None, fixed_scatter_seed: bool = False):

        self.physics = physics or PhysicsSettings()
        self.label_materials = dict(label_materials or {})
        self.fixed_scatter_seed = bool(fixed_scatter_seed)
        p = self.physics
        materials = TISSUE_DECOMPOSITION
        if label_materials:
            if volume.labels is None:
                raise PhysicsError("label_materials needs a CT with a label map (load it with label_map=...)")
            materials = LabelOverride(volume.labels, label_materials)
        self.renderer = DRRRenderer(volume, RenderSettings(scene=scene, size=size, ray_model=ray_model,
                                                           quantity="density"),
                                    center_lps=center_lps, geometry=geometry, materials=materials)
        self.geometry = self.renderer.geometry
        self.spectrum = tube_spectrum(p.kvp, anode_angle_deg=p.anode_angle_deg, filters=p.filters, bins=p.bins)
        self.detector = Detector(p.detector_mm, p.detector_mode, p.electronic_noise, p.blur_mm)
        self.model = Polychromatic(self.spectrum, self.detector, TISSUE_DECOMPOSITION.names)
        g = self.geometry
        self.exposure = dict(mas=p.mas, sdd_mm=g.sdd_mm, pixel_area_mm2=g.pixel_spacing_mm**2)
        self.scatter = None
        self.gain = 1.0
        if p.level == "full":
            self.scatter = MonteCarloScatter(materials.partial_densities(volume.hu), volume.affine,
                                             TISSUE_DECOMPOSITION.names, self.spectrum, self.detector,
                                             ScatterSettings.of(p))
            self.gain = self.scatter.settings.grid_transmission if p.grid_ratio > 0 else 1.0
        self.flat = self.model.flat_field(**self.exposure) * self.gain

    def _scatter_images(self, poses: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Expected scattered signal and interacting scattered photons, each ``(B, H, W)``."""

        g = self.geometry
        mc = self.scatter
        ppp = float(self.model.photons_per_pixel(**self.exposure).sum())
        cam_to_lps = np.linalg.inv(extrinsic_lps_to_camera(poses, self.renderer.center_lps))
        sig = np.empty((len(poses), g.height, g.width))
        cnt = np.empty_like(sig)
        sigma = mc.settings.smoothing_mm(g) / (g.pixel_spacing_mm * mc.settings.cell_px)
        seeds = [pose_seed(seed, 0 if self.fixed_scatter_seed else b) for b in range(len(poses))]
        # all poses in shared launches; pose b's result is that of mc.run with seeds[b]
        for b, out in enumerate(mc.run_batch(cam_to_lps, g, photons_per_pixel=ppp, seeds=seeds)):
            sig[b] = upsample_cells(out["scatter"], g.height, g.width, out["cell_px"], sigma)
            cnt[b] = upsample_cells(out["scatter_counts"], g.height, g.width, out["cell_px"], sigma)
        return sig, cnt

    def render(self, poses: np.ndarray, *, seed: int | None = None) -> dict[str, np.ndarray]:
        """``poses`` ``(B, 4, 4)`` or ``(4, 4)`` -> ``{"raw", "log", "primary"}`` (and ``"scatter"``
        for ``full``) each ``(B, H, W)`` float32. Noise and Monte Carlo are drawn from ``seed``
        (default the settings' seed)."""
        seed = self.physics.seed if seed is None else int(seed)
        poses = self.renderer._check_poses(poses)
        L = self.renderer.render(poses)  # (B, M, H, W) g/cm^2
        primary = self.model.expected(L, **self.exposure) * self.gain
        scatter = self._scatter_images(poses, seed) if self.scatter is not None else None
        raw = primary if scatter is None else primary + scatter[0]
        if self.physics.noise:
            rng = image_noise_rng(seed)
            raw = self.model.noisy(L, rng, pixel_spacing_mm=self.geometry.pixel_spacing_mm, scatter=scatter,
                                   gain=self.gain, **self.exposure)
        log = self.model.log_image(raw, self.flat)
        out = {"raw": raw.astype(np.float32), "log": log.astype(np.float32), "primary": primary.astype(np.float32)}
        if scatter is not None:
            out["scatter"] = scatter[0].astype(np.float32)
        return out

    def record(self) -> dict:
        """The physics settings and derived values for a sidecar."""
        from dataclasses import asdict

        return {**asdict(self.physics), "spectrum_mean_energy_keV": self.spectrum.mean_energy_keV,
                "flat_field_signal": self.flat, "materials": list(self.model.materials),
                "label_materials": {str(k): v for k, v in self.label_materials.items()},
                "signal_units": "keV per pixel" if self.detector.mode == "integrating" else "counts per pixel"}


class LogImageRenderer:
    """An :class:`XRayImager` seen as a DRR renderer: ``render(poses, seed=None)`` returns the
    ``-log(I/I0)`` images ``(B, H, W)``; ``geometry``, ``center_lps`` and ``projection_matrix``
    as :class:`sim.projection.drr.DRRRenderer`. Used for realistic targets and campaign images."""

    def __init__(self, volume, physics: PhysicsSettings | None = None, **kwargs):
        self.imager = XRayImager(volume, physics, **kwargs)
        self.geometry = self.imager.geometry
        self.center_lps = self.imager.renderer.center_lps

    def projection_matrix(self, poses):
        return self.imager.renderer.projection_matrix(poses)

    def render(self, poses, seed: int | None = None) -> np.ndarray:
        return self.imager.render(poses, seed=seed)["log"]


def moving_renderer(volume, physics: PhysicsSettings | None = None, *, scene: str = "cios_fusion", size=None,
                    ray_model: str = "siddon", center_lps=None, geometry=None,
                    label_materials: dict[int, str] | None = None, coarsen: bool = False):
    """The renderer of a registration's moving images ("DRRs") at a physics level.

    ``line`` (or ``physics=None``): a :class:`sim.projection.drr.DRRRenderer` of line integrals of mu.
    ``poly`` / ``full``: a :class:`LogImageRenderer` of ``-log(I/I0)`` with the settings'
    spectrum and detector, without noise (a moving image is an expected image: noise would
    only make the similarity noisy), and for ``full`` with the same Monte Carlo seed for every
    pose (``fixed_scatter_seed``), so the objective is deterministic. ``label_materials``
    needs ``poly`` or ``full``. Both renderers have ``render(poses (B, 4, 4) or (4, 4)) ->
    (B, H, W)``, ``geometry``, ``center_lps`` and ``projection_matrix``. ``coarsen``: line DRRs
    from a CT averaged to the image's resolution (:attr:`sim.projection.drr.RenderSettings.coarsen`); the
    physics levels always render the CT's own voxels.
    """
    from dataclasses import replace

    if physics is None or physics.level == "line":
        if label_materials:
            raise PhysicsError("label materials need physics poly or full (line DRRs use mu from HU)")
        return DRRRenderer(volume, RenderSettings(scene=scene, size=size, ray_model=ray_model, coarsen=coarsen),
                           center_lps=center_lps, geometry=geometry)
    return LogImageRenderer(volume, replace(physics, noise=False), scene=scene, size=size, ray_model=ray_model,
                            center_lps=center_lps, geometry=geometry, label_materials=label_materials,
                            fixed_scatter_seed=True)
