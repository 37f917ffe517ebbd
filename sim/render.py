"""One X-ray image of a CT at a pose, at any physics level: the line DRR or a realistic image.

:func:`render` (also ``from sim import render``: the module itself is callable and calls
:func:`render`) takes a CT or a CT name, a pose given as six parameters or a 4 x 4 matrix, and any
physics level; :func:`render_view` is the same with the renderer and the pose kept, for callers
that record the geometry (``ctxreg render``). Both refuse a pose at which the CT is not in the
view (:func:`sim.projection.drr.check_in_view`) instead of returning an empty image. Line images come from
the DRR renderer (:class:`sim.projection.drr.DRRRenderer`), poly / full ones from
:class:`sim.physics.imaging.XRayImager`.

The DRR renderer itself (:class:`~sim.projection.drr.DRRRenderer`, :class:`~sim.projection.drr.RenderSettings`,
:class:`~sim.projection.drr.RenderError`, :func:`~sim.projection.drr.check_in_view`, ...) lives in :mod:`sim.projection.drr`.
"""

from __future__ import annotations

import sys
import types
from dataclasses import dataclass, field

import numpy as np

from sim.projection.drr import DRRRenderer, RenderError, RenderSettings, check_in_view
from sim.projection.geometry import pose_from_params
from sim.physics.imaging import XRayImager
from sim.physics.settings import LEVELS, PhysicsSettings
from sim.projection.scene import DEFAULT_SCENE
from sim.ct.volume import CTVolume
from sim.core.cliargs import IMAGE_SIDE_PX


@dataclass
class View:
    """One rendered image and how it was made (:func:`render_view`).

    Attributes:
        image: ``(H, W)`` float32: the line integral (or ``intensity``) for line physics, else
            ``-log(I/I0)``.
        pose: ``(4, 4)`` the volume pose T.
        renderer: the :class:`sim.projection.drr.DRRRenderer` (its ``geometry``, ``center_lps``, ``settings``);
            for poly / full the one that rendered the material densities.
        images: every image of the level, ``(H, W)`` float32 each: ``{"image"}`` for line, the
            :class:`sim.physics.imaging.XRayImager` outputs (``raw``, ``log``, ``primary`` and
            ``scatter`` for full) otherwise.
        physics: the imager's record (:meth:`XRayImager.record`) for poly / full, else None.
    """

    image: np.ndarray
    pose: np.ndarray
    renderer: DRRRenderer
    images: dict = field(default_factory=dict)
    physics: dict | None = None


def _as_pose(pose, sod_mm: float) -> np.ndarray:
    p = np.asarray(pose, dtype=np.float64)
    if p.shape == (6,):
        if not np.all(np.isfinite(p)):
            raise RenderError(f"pose parameters must be finite, got {p.tolist()}")
        return pose_from_params(p, sod_mm)
    if p.shape == (4, 4):
        return DRRRenderer._check_poses(p)[0]
    raise RenderError(f"pose: give six parameters (phi theta psi deg, tx ty tz mm) or a 4 x 4 matrix, "
                      f"got shape {p.shape}")


def render_view(volume: CTVolume, pose, *, settings: RenderSettings | None = None, physics=None,
                center_lps=None, label_materials: dict[int, str] | None = None, what: str = "the pose") -> View:
    """Render ``volume`` at ``pose`` (``(6,)`` parameters in deg / mm, or ``(4, 4)``) with the line
    ``settings`` or, with ``physics`` (a :class:`sim.physics.imaging.PhysicsSettings` of level poly
    or full), as a realistic X-ray (``settings`` then gives scene, size and ray model; its
    ``step_fraction``, ``quantity`` and ``mu_water_per_mm`` are for line images and must keep their
    defaults). Refuses (:class:`RenderError`) a pose at which the CT is out of view, and a line
    image whose every ray crossed only air; ``what`` names the pose's inputs in the message."""
    settings = settings or RenderSettings()
    level = "line" if physics is None else physics.level
    if level == "line":
        renderer = DRRRenderer(volume, settings, center_lps=center_lps)
        T = _as_pose(pose, renderer.geometry.sod_mm)
        check_in_view(volume, renderer.geometry, T, renderer.center_lps, what=what)
        image = renderer.render(T)[0]
        empty = image.min() >= settings.i0 if settings.quantity == "intensity" else image.max() <= 0.0
        if settings.quantity != "density" and empty:
            raise RenderError(f"every ray of the view crosses only air (mu = 0): the CT's anatomy is not in "
                              f"the view at {what} (check the pose, the anatomy centre and the scene)")
        return View(image=image, pose=T, renderer=renderer, images={"image": image})
    line_only = [n for n, d in (("step_fraction", RenderSettings.step_fraction), ("quantity", RenderSettings.quantity),
                                ("mu_water_per_mm", RenderSettings.mu_water_per_mm))
                 if getattr(settings, n) != d]
    if line_only:
        raise RenderError(f"{', '.join(line_only)}: meaningful for line images only; this is physics {level}")
    imager = XRayImager(volume, physics, scene=settings.scene, size=settings.size, ray_model=settings.ray_model,
                        center_lps=center_lps, label_materials=label_materials)
    T = _as_pose(pose, imager.geometry.sod_mm)
    check_in_view(volume, imager.geometry, T, imager.renderer.center_lps, what=what)
    images = {k: v[0] for k, v in imager.render(T).items()}
    return View(image=images["log"], pose=T, renderer=imager.renderer, images=images, physics=imager.record())


def render(ct, pose=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0), *, size: tuple[int, int] = (256, 256), physics="line",
           scene: str = DEFAULT_SCENE, center=None, ray_model: str = "siddon", step_fraction: float = 0.5,
           label_materials: dict[int, str] | None = None) -> np.ndarray:
    """One X-ray image of a CT: ``(H, W)`` float32, ``H, W = size``.

    Args:
        ct: a :class:`sim.ct.volume.CTVolume` (:func:`sim.load_ct`), or what :func:`sim.load_ct`
            takes: a NIfTI file, a DICOM series folder, ``"phantom"`` / ``"phantom:SEED"``.
        pose: six parameters ``(phi, theta, psi, tx, ty, tz)`` in degrees and mm (all zero: the
            AP view; ``docs/conventions.md``) or a ``(4, 4)`` pose T.
        size: ``(rows, cols)`` of the image, each in [8, 4096]; the detector keeps its extent
            (the scene's aspect).
        physics: what a pixel holds.

            * ``"line"``: the line integral of mu = mu_water (1 + HU / 1000) along the pixel's
              ray (dimensionless; a DRR; about 0-10 for a body), exact for ``ray_model="siddon"``;
            * ``"poly"``: ``-log(I / I0)`` of a realistic X-ray (dimensionless): a 120 kVp tube
              spectrum, seven materials with NIST cross sections, a CsI detector, quantum and
              electronic noise (:class:`sim.physics.imaging.PhysicsSettings` defaults, seed 0);
            * ``"full"``: ``poly`` plus Monte Carlo scatter (slower: seconds to minutes);
            * a :class:`~sim.physics.imaging.PhysicsSettings` for other kVp, exposure, noise, seed.
        scene: the C-arm (a name from ``scenes/`` or a scene XML): source-detector distances, detector.
        center: ``(3,)`` anatomy centre c in LPS mm that the pose turns about; None = the bone
            centroid (or the label map's).
        ray_model: ``"siddon"`` (exact voxel traversal) or ``"trilinear"`` (smoother on coarse CTs).
        step_fraction: the trilinear step as a fraction of the smallest voxel spacing
            (:data:`sim.projection.drr.STEP_FRACTION`; line physics only).
        label_materials: ``{label: material}`` for poly / full (a CT loaded with a label map).

    Raises :class:`sim.core.errors.InputError` subclasses, each naming the problem: a CT that cannot be
    read, a size or setting out of range, a pose at which the CT is not in the view.

    Example::

        >>> from sim import load_ct, render
        >>> drr = render(load_ct("phantom"), pose=[20, -10, 0, 0, 0, 0], size=(64, 64))  # doctest: +SKIP
        >>> drr.shape, drr.dtype                                                           # doctest: +SKIP
        ((64, 64), dtype('float32'))
    """

    volume = ct if isinstance(ct, CTVolume) else _load(ct)
    try:
        rows, cols = (int(v) for v in size)
    except (TypeError, ValueError):
        raise RenderError(f"size must be (rows, cols) in pixels, got {size!r}") from None
    if rows not in IMAGE_SIDE_PX or cols not in IMAGE_SIDE_PX:
        raise RenderError(f"size {rows} x {cols}: each side must be {IMAGE_SIDE_PX} pixels")
    settings = RenderSettings(scene=scene, size=(rows, cols), ray_model=ray_model, step_fraction=step_fraction)
    return render_view(volume, pose, settings=settings, physics=_physics(physics), center_lps=center,
                       label_materials=label_materials).image


def _load(spec) -> CTVolume:
    from sim.ct.io import load_ct_spec  # loads SciPy: imported where first needed (start-up)

    return load_ct_spec(spec)


def _physics(physics):
    """None for line, else a PhysicsSettings (a level name -> its defaults)."""
    if isinstance(physics, PhysicsSettings):
        return None if physics.level == "line" else physics
    if physics not in LEVELS:
        raise RenderError(f"physics must be one of {LEVELS} or a PhysicsSettings, got {physics!r}")
    return None if physics == "line" else PhysicsSettings(level=physics)


class _CallableModule(types.ModuleType):
    """``from sim import render`` gives this module (a package's submodule wins over a function of
    the same name), so calling the module calls :func:`render`."""

    def __call__(self, *args, **kwargs) -> np.ndarray:
        return render(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
