"""Registering an X-ray to a CT from Python: what ``ctxreg register`` does, as one call.

Example (README "Python API")::

    from sim import load_ct
    from register import register_xray

    ct = load_ct("pelvis.nii.gz")
    result = register_xray(ct, "xray.dcm", method="cmaes")
    print(result.params)              # {"phi": ..., "theta": ..., ..., "tz": ...} deg and mm
    result.pose                       # (4, 4) T: X_cam = R (X_lps - c) + t
    result.write("out/reg")           # result.json, overlay.png, checkerboard.png, convergence.png

:func:`register_xray` checks every input before the work starts (the method and its model,
the start pose, the preprocessing steps, the size; then the X-ray, its geometry, the memory the
size asks for, the CT, and that the CT is in the view at the start pose), prepares the X-ray
(:func:`register.xray.prepare.prepare_xray`: geometry with its sources, field mask, intensity, size),
checks the polarity against the CT (:func:`register.xray.prepare.confirm_polarity`), builds the
method (:func:`register.engines.methods.build_method`) and registers. ``ctxreg register``
(:func:`register.commands.run_register`) is this call plus :meth:`XRayRegistration.write`.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy import ndimage

from learn.adapt import adapted_ct_warning
from register.engines.methods import build_method, check_method, load_predictor, needs_model
from register.engines.cmaes import CMAESRegistration
from register.engines.metrics import downsample, gradient_ncc
from register.engines.pipeline import REFINE_SETTINGS, rescue as rescue_pose, scored_as_refined
from register.engines.result import RegistrationError, RegistrationResult
from register.engines.search import GlobalSearch, GlobalSearchSettings, describe_search
from register.verdict import Verdict, clearly_registered, judge_result
from register.plots import checkerboard_png, convergence_plot, overlay_png, trajectory_figure, trajectory_gif
from register.xray.geometry import resolve_geometry
from register.xray.io import XRayImage, check_orientation, load_xray
from register.xray.network_view import network_view
from register.xray.field import TOOL_OPTIONS, TOOLS_DEFAULT
from register.xray.prepare import (_fit_plan, confirm_polarity, confirm_polarity_by_pose, fit_box,
                                   polarity_needs_check, prepare_xray)
from register.xray.preprocess import DEFAULT_STEPS, Pipeline, PreprocessError
from sim.core.atomic import atomic_path, write_json
from sim.campaign.poses import PARAM_NAMES
from sim.core.cliargs import check_memory
from sim.ct.io import is_phantom_spec
from sim.ct.volume import CTInputError
from sim.core.outputs import check_output_dir
from sim.core.progress import StageClock
from sim import load_ct
from sim.ct.anatomy import find_center
from sim.physics.imaging import PhysicsSettings
from sim.physics.settings import LEVELS
from sim.projection.drr import DRRRenderer, RenderSettings, check_in_view
from sim.projection.geometry import pose_from_params, projection_matrix

__all__ = ["register_xray", "RegistrationRequest", "XRayRegistration", "parse_init", "REGISTER_RESTARTS", "REGISTER_SCATTER_PHOTONS",
           "OUTPUT_FILES", "SEARCH_MODES", "SEARCH_METHODS"]

#: Monte Carlo histories per moving image with physics full: a registration renders thousands
#: of images, and the smoothed scatter of 10^5 histories differs from that of 10^6 by a few %.
REGISTER_SCATTER_PHOTONS = 100_000

#: CMA-ES restarts of a registration (IPOP, see :class:`register.engines.cmaes.CMAESSettings`): a user's
#: X-ray is registered once, so spending up to 4x the time on a lost search is worth it.
REGISTER_RESTARTS = 3

#: The methods that take ``restarts``: CMA-ES's own. contextual+cmaes runs the global search
#: (:mod:`register.engines.search`, default settings) where the network's pose is lost instead.
RESTART_METHODS = ("cmaes",)

#: The methods with the global search (:mod:`register.engines.search`), the ones ``search`` (``--search``) applies to.
SEARCH_METHODS = ("contextual+cmaes",)

#: ``search`` (``--search``) of contextual+cmaes: ``"auto"`` runs the global search's grid where the
#: network's pose scores below :attr:`register.engines.search.GlobalSearchSettings.found_above` or ends below
#: :attr:`~register.engines.search.GlobalSearchSettings.refined_above` after its refinement (the default),
#: ``"off"`` never builds the search (the network's pose goes straight to the CMA-ES refinement: the
#: network measured on its own), ``"always"`` runs the grid whatever the network's pose scored.
SEARCH_MODES = ("auto", "off", "always")

#: The smallest side (px) of the optimiser's image box (``size``, ``--size``): the registration's
#: coarsest level works at 1/4 (CMA-ES's first level, the global search's grid and the polarity
#: check) and needs 8 px per side there and a field left after erosion (at 16 x 16 and 24 x 24 the
#: masked gradient similarity has no pixel left: "mask: empty after erosion").
REGISTER_MIN_SIDE_PX = 32
#: The longest side (px) of an X-ray prepared as it is; a larger frame is binned by the smallest
#: whole factor that brings it to this or below (its pitch scaled; :meth:`XRayImage.binned`), so
#: that a 6000 x 6000 px frame costs what a 2000 x 2000 one does. The registration itself works at
#: ``size`` (128 px by default) whatever the frame's.
MAX_XRAY_SIDE_PX = 2048

#: The field pixels the coarsest level (1/4) must keep after erosion by one pixel, the global
#: search's own minimum (:meth:`register.engines.search.GlobalSearch._field`).
MIN_COARSE_FIELD_PX = 16

#: Bytes per pixel of the global search's grid of padded DRRs at its peak (float32 DRRs, their
#: float32 Sobel, a float64 copy): the largest allocation a registration makes (the polarity check
#: and the search score on it). ~2000 grid poses: 4096 x 4096 on a 64 x 64 X-ray asked for 27 GiB.
GRID_BYTES_PER_PX = 16

#: The files :meth:`XRayRegistration.write` writes (the trajectory files for the contextual methods only).
OUTPUT_FILES = ("result.json", "overlay.png", "checkerboard.png", "convergence.png", "trajectory.npz", "trajectory.png",
                "trajectory.gif")


def parse_init(init) -> np.ndarray:
    """The start pose ``(6,)`` (deg, mm) from ``"ap"`` (zeros), six numbers, or their strings
    (``--init``). Raises :class:`register.engines.result.RegistrationError`."""
    values = [init] if isinstance(init, str) else list(np.ravel(np.asarray(init, dtype=object)))
    if len(values) == 1 and str(values[0]) == "ap":
        return np.zeros(6)
    try:
        x = np.array([float(v) for v in values])
    except (TypeError, ValueError):
        x = np.zeros(0)
    if x.shape != (6,) or not np.all(np.isfinite(x)):
        raise RegistrationError(f"--init {' '.join(map(str, values))}: give 'ap' or six finite numbers")
    return x


@dataclass
class XRayRegistration:
    """The outcome of :func:`register_xray`.

    Attributes:
        method: the registration method's name.
        params: ``{"phi", "theta", "psi"}`` in degrees and ``{"tx", "ty", "tz"}`` in mm: the pose
            parameters (``docs/conventions.md``).
        pose: ``(4, 4)`` the pose T (``X_cam = R (X_lps - c) + t``, c = ``center_lps``).
        similarity: the final gradient NCC at the optimiser's size (1 = identical edges).
        result: the method's :class:`register.engines.result.RegistrationResult` (projection, renders,
            stage times, history, trajectory).
        prepared: the :class:`register.xray.prepare.PreparedXRay` (geometry and its sources, field,
            intensity decision and its check, images at full and at the optimiser's size).
        volume: the CT; center_lps: ``(3,)`` its anatomy centre (LPS mm).
        init_params: ``(6,)`` the start pose (deg, mm).
        physics: the :class:`sim.physics.imaging.PhysicsSettings` of the moving images.
        label_materials: ``{label: material}`` overrides of the CT's label map, or None.
        search_mode: the ``search`` option (:data:`SEARCH_MODES`) of a method with the global
            search, None for the others.
        search_ran: whether the global search's grid ran (False where it was skipped, off, or not
            part of the method); ``result.search`` keeps the search's record where it was built,
            :attr:`search_status` says it in words.
        timings: wall seconds by stage of the whole call, disjoint, in the order they finished:
            ``model`` (the network's load), ``xray``, ``ct`` (its load and anatomy centre),
            ``prepare`` (field, intensity, the optimiser's image), ``search_setup`` (the global
            search, where built), ``engine_setup``, ``register`` (split further in
            ``result.stage_seconds``), ``polarity`` (the check against the CT: before ``register``
            where it ran on the search's grid, whose render it then holds), and ``write`` once
            :meth:`write` ran; a CLI call adds ``startup`` first (the process's start-up and
            imports, before the call); ``verdict`` (its evidence's DRR and checks).
        verdict: whether to trust the pose (:class:`register.verdict.Verdict`: ``registered``,
            ``doubtful`` or ``failed`` with its reasons and evidence); in ``result.json`` as
            ``verdict``, ``verdict_reasons`` and ``verdict_evidence``.
    """

    method: str
    result: Any
    prepared: Any
    volume: Any
    center_lps: np.ndarray
    init_params: np.ndarray
    physics: Any
    label_materials: dict | None = None
    notes: list[str] = field(default_factory=list)
    search_mode: str | None = None
    search_ran: bool = False
    timings: dict[str, float] = field(default_factory=dict)
    center_how: str = ""
    verdict: Verdict | None = None

    @property
    def search_status(self) -> str:
        """What the global search did: ``"ran"``, ``"skipped (the network's pose, refined, judged
        registered)"`` (the verdict kept it before the search), ``"skipped (network pose scored S >=
        T)"``, ``"off"`` (``search="off"``) or ``"none (method M has no global search)"``."""
        record = self.result.search
        if self.search_mode is None:
            return f"none (method {self.method} has no global search)"
        if self.search_mode == "off" or record is None:
            return "off"
        if self.search_ran:
            return "ran" + (" (--search always)" if record.get("always_grid") else "")
        if record.get("trusted"):
            return "skipped (the network's pose, refined, judged registered)"
        score = record.get("given_score", record.get("given_similarity"))
        return f"skipped (network pose scored {score:.2f} >= {record['found_above']:g})"

    @property
    def params(self) -> dict[str, float]:
        return dict(zip(PARAM_NAMES, map(float, self.result.params)))

    @property
    def pose(self) -> np.ndarray:
        return self.result.pose

    @property
    def similarity(self) -> float:
        return float(self.result.similarity)

    @property
    def xray_input(self) -> dict:
        """The prepared X-ray's summary (``result.json``'s ``xray_input``): where each geometry value
        came from, the field, the intensity decision and its check against the CT, the sizes."""
        return self.prepared.summary()

    @property
    def geometry(self):
        """:class:`sim.projection.geometry.CArmGeometry` of the optimiser's image (the pose's projection)."""
        return self.prepared.geometry

    def summary(self) -> str:
        """Similarity, renders and the pose (deg, mm) in one line; for a method with the global
        search a line before it, ``search: ran|skipped (...)|off`` (:attr:`search_status`), and
        where the grid ran a second one saying what it did
        (:func:`register.engines.search.describe_search`)."""
        r = self.result
        line = (f"similarity {r.similarity:.4f} after {r.renders} renders; pose: "
                + " ".join(f"{v:.2f}" for v in r.params))
        head = [] if self.search_mode is None else [f"search: {self.search_status}"]
        if r.search is not None and r.search["grid_poses"]:  # a skipped grid: the status line says it all
            head.append(describe_search(r.search))
        return "\n".join([*head, line])

    def _title(self) -> str:
        """The figures' title: the verdict and its reasons, the similarity and the pose."""
        p = self.result.params
        pose = f"pose {p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f} deg; {p[3]:.1f}, {p[4]:.1f}, {p[5]:.1f} mm"
        head = self.verdict.line() if self.verdict is not None else f"similarity {self.similarity:.3f}"
        return f"{head}. {pose}"

    def to_dict(self) -> dict:
        """``result.json``: the pose, its projection, the similarity, the method, the inputs (CT,
        X-ray, start, anatomy centre), the prepared X-ray's summary and preprocessing record, the
        moving physics and the optimiser's geometry; the global search: ``search_mode`` (None for a
        method without it), ``search_ran``, ``search_status`` (:attr:`search_status`) and, where it
        was built, its record ``search``."""
        g = self.geometry
        return {
            **self.result.to_dict(), "method": self.method, "search_mode": self.search_mode,
            "search_ran": bool(self.search_ran), "search_status": self.search_status,
            **(self.verdict.to_dict() if self.verdict is not None else {}),
            "timings_s": {k: round(v, 4) for k, v in self.timings.items()}, "ct": self.volume.source,
            "xray": self.prepared.xray.source, "init_params": self.init_params.tolist(),
            "anatomy_center_lps_mm": self.center_lps.tolist(), "anatomy_center_how": self.center_how,
            "xray_input": self.xray_input,
            "preprocessing": self.prepared.record,
            "moving_physics": {**asdict(self.physics),
                               "label_materials": {str(k): v for k, v in (self.label_materials or {}).items()}},
            "geometry": {"sdd_mm": g.sdd_mm, "sod_mm": g.sod_mm, "height": g.height, "width": g.width,
                         "pixel_spacing_mm": g.pixel_spacing_mm, "principal_point_uv": list(g.principal_point),
                         "K": g.intrinsics().tolist()},
        }

    def write(self, out: str | Path, *, trajectory_errors: list[str] | None = None) -> list[Path]:
        """Write into the folder ``out`` (checked first: :func:`sim.core.outputs.check_output_dir`):
        ``trajectory.npz``, ``trajectory.png`` and ``trajectory.gif`` (contextual methods: the
        iteration's DRRs beside the X-ray, then for contextual+cmaes the refined pose's;
        ``trajectory_errors``, one caption per frame, e.g. the error against a known truth),
        ``overlay.png`` (DRR edges
        and the field outline over the X-ray at its full resolution), ``checkerboard.png``,
        ``convergence.png`` and ``result.json`` (:meth:`to_dict`), each atomically. Returns the paths.
        Its seconds (up to ``result.json``) go to ``timings["write"]``."""

        t0 = time.perf_counter()
        out = check_output_dir(out, OUTPUT_FILES)
        result, prepared = self.result, self.prepared
        image = prepared.image
        written = []
        if result.trajectory is not None:
            with atomic_path(out / "trajectory.npz") as tmp:
                with open(tmp, "wb") as f:
                    np.savez_compressed(f, params_deg_mm=result.trajectory["params"], g_rad_mm=result.trajectory["g"],
                                        drrs=result.trajectory["drrs"].astype(np.float32),
                                        xray=image.astype(np.float32))
            trajectory_figure(image, result.trajectory["drrs"], result.trajectory["params"], out / "trajectory.png")
            drrs = list(result.trajectory["drrs"])
            params = list(result.trajectory["params"][:len(drrs)])
            labels = [f"iteration {i}" for i in range(len(drrs))]
            if self.method == "contextual+cmaes":  # the refined pose as the last frame
                g = self.geometry
                drrs.append(DRRRenderer(self.volume, RenderSettings(size=(g.height, g.width)), center_lps=self.center_lps,
                                        geometry=g).render(result.pose)[0])
                params.append(result.params)
                rescued = ((result.search or {}).get("rescue") or {}).get("kept") == "rescued"
                labels.append("final (local similarity)" if rescued else "final (CMA-ES)")
            trajectory_gif(image, np.array(drrs), np.array(params), out / "trajectory.gif", errors=trajectory_errors,
                           title=f"verdict: {self.verdict.label}" if self.verdict is not None else None,
                           labels=labels)
            written = [out / "trajectory.npz", out / "trajectory.png", out / "trajectory.gif"]
        # figures at the X-ray's own resolution: a line DRR with the X-ray's full geometry (its
        # edges are those of any physics level)
        full = prepared.full_geometry
        full_drr = DRRRenderer(self.volume, RenderSettings(size=(full.height, full.width)), center_lps=self.center_lps,
                               geometry=full).render(result.pose)[0]
        overlay_png(prepared.xray.pixels, full_drr, out / "overlay.png", mask=prepared.full_mask, title=self._title())
        checkerboard_png(prepared.full_image, full_drr, out / "checkerboard.png", mask=prepared.full_mask)
        convergence_plot(result.history, out / "convergence.png", title=self._title(),
                         search_status=self.search_status if self.search_mode is not None else None)
        self.timings["write"] = time.perf_counter() - t0
        write_json(out / "result.json", self.to_dict())
        return [out / "result.json", out / "overlay.png", out / "checkerboard.png", out / "convergence.png", *written]


def _moving_physics(physics):
    """The :class:`PhysicsSettings` of the moving images: a level name gets the defaults of a
    registration (noise-free, :data:`REGISTER_SCATTER_PHOTONS`)."""

    if isinstance(physics, PhysicsSettings):
        return physics
    if physics not in LEVELS:
        raise RegistrationError(f"physics must be one of {LEVELS} or a PhysicsSettings, got {physics!r}")
    return PhysicsSettings(level=physics, noise=False, scatter_photons=REGISTER_SCATTER_PHOTONS)


@dataclass(frozen=True)
class RegistrationRequest:
    """What a user asks of a registration: every option of :func:`register_xray` (and of
    ``ctxreg register``), checked as it is made, before any file is read. One request registers
    any number of X-rays (``ctxreg serve`` makes one per case).

    Attributes: ``method``, ``model``, ``init``, ``center``, ``label_map``, ``scene``, ``sdd_mm``,
    ``sod_mm``, ``pixel_spacing_mm``, ``size``, ``physics``, ``label_materials``, ``preprocess``,
    ``intensity``, ``polarity``, ``tone``, ``tools``, ``orient``, ``restarts``, ``search``, ``ct_cache``:
    as :func:`register_xray`'s arguments. Derived: ``start`` ``(6,)`` the start pose (deg, mm),
    ``steps`` the preprocessing step names, ``box`` ``(H, W)`` the optimiser's image box (px),
    ``moving`` the moving images' :class:`sim.physics.imaging.PhysicsSettings`, ``cmaes_restarts``.

    :meth:`run` takes an X-ray through the stages, in order, each timed under its name
    (:attr:`XRayRegistration.timings`): ``xray`` (:func:`_read_xray`), the checks that need the
    X-ray but no CT load (:func:`_check_before_loading`), ``model`` (:func:`_load_network`), ``ct``
    (:func:`_load_anatomy`), ``prepare`` (:func:`_prepare`), ``search_setup`` and
    ``engine_setup`` (:func:`_build_engine`), ``register`` and ``polarity``
    (:class:`_PolarityCheckedRun`), ``verdict`` (:func:`_verdict`).

    Example::

        >>> request = RegistrationRequest(method="cmaes", restarts=0, size=(64, 64))
        >>> request.box, request.start.tolist()
        ((64, 64), [0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        >>> RegistrationRequest(search="sometimes")
        Traceback (most recent call last):
        ...
        register.engines.result.RegistrationError: --search sometimes: choose one of auto, off, always
    """

    method: str = "contextual+cmaes"
    model: Any = None
    init: Any = "ap"
    center: Any = None
    label_map: Any = None
    scene: str = "cios_fusion"
    sdd_mm: float | None = None
    sod_mm: float | None = None
    pixel_spacing_mm: float | None = None
    size: Any = (128, 128)
    physics: Any = "line"
    label_materials: dict[int, str] | None = None
    preprocess: Any = None
    intensity: str = "auto"
    polarity: str = "auto"
    tone: str = "ct"
    tools: str = TOOLS_DEFAULT
    orient: str = "none"
    restarts: int | None = None
    search: str = "auto"
    ct_cache: Any = False
    start: np.ndarray = field(init=False, repr=False)
    steps: tuple[str, ...] = field(init=False, repr=False)
    box: tuple[int, int] = field(init=False, repr=False)
    moving: PhysicsSettings = field(init=False, repr=False)
    cmaes_restarts: int = field(init=False, repr=False)

    def __post_init__(self) -> None:
        derived = object.__setattr__
        derived(self, "start", parse_init(self.init))
        check_method(self.method, self.model)
        check_orientation(self.orient)
        if self.restarts is not None and self.method not in RESTART_METHODS:
            raise RegistrationError(f"--restarts: meaningful with --method {' or '.join(RESTART_METHODS)} only; this "
                                    f"run is --method {self.method}")
        if self.search not in SEARCH_MODES:
            raise RegistrationError(f"--search {self.search}: choose one of {', '.join(SEARCH_MODES)}")
        if self.search != "auto" and self.method not in SEARCH_METHODS:
            raise RegistrationError(f"--search {self.search}: meaningful with --method {' or '.join(SEARCH_METHODS)} "
                                    f"only (the other methods have no global search); this run is --method "
                                    f"{self.method}")
        derived(self, "cmaes_restarts", REGISTER_RESTARTS if self.restarts is None else self.restarts)
        steps = tuple(str(n).strip().lower() for n in (DEFAULT_STEPS if self.preprocess is None else self.preprocess))
        Pipeline.from_names(list(steps), {"intensity": {"scale": self.intensity, "polarity": self.polarity,
                                                        "tone": self.tone}})  # the choices, checked
        if "intensity" not in steps and (self.intensity, self.polarity, self.tone) != ("auto", "auto", "ct"):
            raise RegistrationError("--intensity / --polarity / --tone: meaningful with the 'intensity' preprocessing "
                                    f"step only; this run's steps are {' '.join(steps) or 'none'}")
        if self.tools not in TOOL_OPTIONS:
            raise RegistrationError(f"--tools {self.tools}: choose one of {', '.join(TOOL_OPTIONS)}")
        derived(self, "steps", steps)
        box = fit_box(self.size)
        if min(box) < REGISTER_MIN_SIDE_PX:
            raise RegistrationError(f"--size {box[0]} {box[1]}: the registration needs at least {REGISTER_MIN_SIDE_PX} "
                                    f"px per side (its coarsest level works at 1/4 and must keep a field there); give "
                                    f"e.g. --size 128 128")
        derived(self, "box", box)
        derived(self, "moving", _moving_physics(self.physics))

    @property
    def searches(self) -> bool:
        """Whether the method's global search is built (contextual+cmaes, ``search`` not ``"off"``)."""
        return self.method in SEARCH_METHODS and self.search != "off"

    def run(self, ct, xray, *, log: Callable[[str], None] | None = None,
            note: Callable[[str], None] | None = None) -> XRayRegistration:
        """Register ``xray`` to ``ct`` (as :func:`register_xray` takes them) through the stages
        (class doc); ``log`` and ``note`` as there."""
        log = log or (lambda line: None)
        notes: list[str] = []

        def remark(text: str) -> None:
            notes.append(text)
            if note is not None:
                note(text)

        clock = StageClock()
        # the X-ray and its geometry (a quick read: its refusals come first, before the network and
        # its torch load), the memory the size asks for; a CT that is not there; then the network
        # and the CT, the view at the start
        with clock("xray"):
            xr, pixel_spacing_mm = _read_xray(self, xray, log)
        full_geometry = _check_before_loading(self, xr, ct, pixel_spacing_mm)
        with clock("model"):
            predictor = _load_network(self, ct, log)
        with clock("ct"):
            volume, found = _load_anatomy(self, ct, log)
        log(f"anatomy centre {found.describe()}")
        c = found.lps_mm
        check_in_view(volume, full_geometry, pose_from_params(self.start, full_geometry.sod_mm), c,
                      what="the start pose (--init, with the anatomy centre --center)")
        with clock("prepare"):
            prepared = _prepare(self, xr, volume, c, pixel_spacing_mm)
        engine, grid = _build_engine(self, prepared, volume, c, predictor, clock, remark, log)
        run = _PolarityCheckedRun(self, volume, c, predictor, engine, grid, clock)
        result, prepared = run.register(prepared)
        line = _polarity_line(prepared)
        if line is not None:
            log(line)
        ran = result.search is not None and bool(result.search.get("grid_poses"))
        with clock("verdict"):
            verdict = run.judged(result, prepared) or _verdict(self, volume, c, prepared, result)
        return XRayRegistration(method=self.method, result=result, prepared=prepared, volume=volume, center_lps=c,
                                init_params=self.start, physics=self.moving, label_materials=self.label_materials,
                                notes=notes, search_mode=self.search if self.method in SEARCH_METHODS else None,
                                search_ran=ran, timings=clock.seconds,
                                center_how=found.to_dict()["anatomy_center_how"], verdict=verdict)


    def judge(self, ct, xray, params, *, similarity: float, search: dict | None = None, network_params=None,
              log: Callable[[str], None] | None = None) -> Verdict:
        """The verdict on a pose of ``xray`` already found (by a registration with this request, or
        elsewhere), without registering again: :meth:`finish` without the rescue. ``benchmarks/verdict.py
        --rejudge`` judges recorded registrations again so when the evidence changes."""
        return self.finish(ct, xray, params, similarity=similarity, search=search, network_params=network_params,
                           log=log, rescue=False)[1]

    def finish(self, ct, xray, params, *, similarity: float, search: dict | None = None, network_params=None,
               log: Callable[[str], None] | None = None, rescue: bool = True) -> tuple[RegistrationResult, Verdict]:
        """The steps after the pipeline's winner, on a pose of ``xray`` already found: the X-ray read
        and prepared as :meth:`run` does, its polarity checked by that pose (or, where the pose does
        not confirm it, on the grid around the start, as a registration whose pose does not), then
        (``rescue``, contextual+cmaes with its search) the search again by local similarity where
        the pose's is low (:func:`register.engines.pipeline.rescue`), then the verdict's evidence at
        the pose (:func:`_verdict`). A registration's winner, so finished, ends where :meth:`run`
        ends (the pipeline's steps are deterministic); ``benchmarks/verdict.py --rejudge`` finishes
        recorded registrations so when a step after the winner changes. Returns the result (the
        given pose, or the rescue's) and its verdict.

        Args:
            ct, xray: as :meth:`run` takes them.
            params: ``(6,)`` the pose (deg, mm).
            similarity: its final similarity as the registration scored it.
            search: the global search's record (``result.json``'s ``search``; None: no search).
            network_params: ``(6,)`` where the network's iteration ended (None: no network).
        """
        log = log or (lambda line: None)
        p = np.asarray(params, float).reshape(-1)
        if p.shape != (6,) or not np.all(np.isfinite(p)):
            raise RegistrationError(f"finish: the pose must be six finite numbers (deg, mm), got {params!r}")
        if not np.isfinite(similarity):
            raise RegistrationError(f"finish: the similarity must be finite, got {similarity!r}")
        xr, pixel_spacing_mm = _read_xray(self, xray, log)
        _check_before_loading(self, xr, ct, pixel_spacing_mm)
        volume, found = _load_anatomy(self, ct, log)
        c = found.lps_mm
        prepared = _prepare(self, xr, volume, c, pixel_spacing_mm)
        g = prepared.geometry
        pose = pose_from_params(p, g.sod_mm)
        if polarity_needs_check(prepared):
            checked = confirm_polarity_by_pose(prepared, _plain_score(volume, c, prepared, pose), p)
            prepared = checked if checked is not None else confirm_polarity(
                prepared, volume, c, self.start, physics=self.moving, label_materials=self.label_materials)
        trajectory = None if network_params is None else {"params": np.asarray(network_params, float).reshape(1, 6)}
        result = RegistrationResult(params=p, pose=pose, projection=projection_matrix(g, pose, c),
                                    similarity=float(similarity), renders=0, stage_seconds={}, search=search,
                                    trajectory=trajectory)
        if rescue and self.searches:
            refinement = CMAESRegistration(volume, replace(REFINE_SETTINGS, size=(g.height, g.width)), scene=self.scene,
                                           geometry=g, center_lps=c, physics=self.moving,
                                           label_materials=self.label_materials)
            result = rescue_pose(_global_search(self, volume, g, c), refinement, prepared.image, self.start, result,
                                 mask=prepared.mask, toned=prepared.toned)
            result.projection = projection_matrix(g, result.pose, c)
        return result, _verdict(self, volume, c, prepared, result)


def register_xray(ct, xray, *, log: Callable[[str], None] | None = None, note: Callable[[str], None] | None = None,
                  **options) -> XRayRegistration:
    """Register the X-ray ``xray`` to the CT ``ct``: its pose, as ``ctxreg register`` finds it.

    Args:
        ct: a :class:`sim.ct.volume.CTVolume` (:func:`sim.load_ct`) or what :func:`sim.load_ct` takes
            (a NIfTI file, a DICOM series folder, ``"phantom"``).
        xray: a file (DICOM: geometry from its tags where present; PNG / TIFF / JPEG / ``.npy``) or
            a :class:`register.xray.io.XRayImage`.
        ct_cache: read a CT file through the CT cache (:mod:`sim.ct.cache`; ``cache`` of
            :func:`sim.load_ct`): False (default), True (the default folder) or a folder.
        method: ``"cmaes"``, ``"contextual"`` or ``"contextual+cmaes"`` (:mod:`register.engines.methods`).
        model: the ``ctxreg train`` checkpoint (path or loaded predictor) of the contextual methods.
        init: the start pose: ``"ap"`` or six numbers (phi theta psi deg, tx ty tz mm).
        center: ``(3,)`` anatomy centre c in LPS mm; None = :func:`sim.ct.anatomy.find_center`'s (the
            label map's centroid, else that of the pelvis's bone pieces); result.json says which
            (``anatomy_center_how``).
        label_map: a label map for ``ct`` given as a path (with ``label_materials``: implants).
        scene: the C-arm for the geometry values the image does not give.
        sdd_mm, sod_mm, pixel_spacing_mm: explicit geometry (override the DICOM tags and the scene).
        size: ``(H, W)``: the optimiser's image is the X-ray (cropped to its field) scaled, aspect
            kept, to the largest size that fits inside ``H x W`` with sides multiples of 4 (the
            default 128 x 128: the longer side 128 px). Each side in [32, 4096]
            (:data:`REGISTER_MIN_SIDE_PX`); the largest allocation it implies is checked against
            the memory available (:func:`check_registration_memory`) before any work.
        physics: the moving images: ``"line"`` DRRs, ``"poly"`` / ``"full"`` (noise-free
            ``-log(I/I0)``), or a :class:`sim.physics.imaging.PhysicsSettings`.
        preprocess: the preprocessing step names (default
            :data:`register.xray.preprocess.DEFAULT_STEPS`); intensity / polarity: ``"auto"`` or the
            override of the intensity step (only with ``"intensity"`` among the steps); tone:
            ``"ct"`` maps a display image's values onto the CT's line integrals in its field,
            ``"off"`` keeps them (:class:`register.xray.preprocess.Intensity`).
        tools: ``"detect"`` (default, :data:`register.xray.field.TOOLS_DEFAULT`) leaves the metal
            tools the shipped segmenter finds in the field out of the similarities' mask
            (:class:`learn.tool_mask.ToolMask`; where ``"field"`` is the first preprocessing step:
            tools are looked for inside the detected field, and result.json's
            ``field.excluded.tools`` counts them); ``"off"`` does not look for them
            (docs/xray_input.md, "Metal tools").
        orient: how the stored X-ray is turned into the CT's view first (a name of
            :data:`register.xray.io.ORIENTATIONS`: ``"none"``, ``"flip-left-right"``, ...); the
            figures show the X-ray so turned.
        restarts: CMA-ES restarts for ``method="cmaes"`` (default :data:`REGISTER_RESTARTS`);
            ``"contextual+cmaes"`` runs the global search instead (:mod:`register.engines.search`: a grid over
            the prior box around ``init`` where the network's pose is lost).
        search: ``"contextual+cmaes"``'s global search (:data:`SEARCH_MODES`): ``"auto"`` (the
            default) runs its grid where the network's pose scores below
            :attr:`register.engines.search.GlobalSearchSettings.found_above`; ``"off"`` never builds it
            (the network's pose goes straight to the CMA-ES refinement; the polarity check still
            scores the image and its inverse on a grid of poses around ``init``, as for the other
            methods, and decides the polarity only);
            ``"always"`` runs the grid whatever the network's pose scored. Another value than
            ``"auto"`` with another method is refused. The result's ``search_ran`` says whether the
            grid ran.
        log: called with each line a user should check (geometry sources, field, intensity);
            note: with remarks (a network trained on other physics). Both default to silence.

    The options (every argument but ``ct``, ``xray``, ``log`` and ``note``) make a
    :class:`RegistrationRequest`; this is ``RegistrationRequest(**options).run(ct, xray, log=log, note=note)``.

    Returns an :class:`XRayRegistration`; :meth:`XRayRegistration.write` writes the figures and
    ``result.json``. Raises :class:`sim.core.errors.InputError` subclasses naming the bad input, before
    the work where the input allows it (everything but the image's contents).
    """
    return RegistrationRequest(**options).run(ct, xray, log=log, note=note)


# -- the stages of RegistrationRequest.run, in order ---------------------------------------------


def _read_xray(request: RegistrationRequest, xray, log) -> tuple[XRayImage, float | None]:
    """The X-ray read and turned into the CT's view; a frame over :data:`MAX_XRAY_SIDE_PX` binned
    at once. Returns it and the pixel pitch option (mm), scaled where binned (``--pixel-spacing``
    is the file's pixels')."""
    xr = (xray if isinstance(xray, XRayImage) else load_xray(xray)).reoriented(request.orient)
    pixel_spacing_mm = request.pixel_spacing_mm
    if max(xr.shape) > MAX_XRAY_SIDE_PX:  # a huge frame: binned at once, not prepared at full size
        factor = math.ceil(max(xr.shape) / MAX_XRAY_SIDE_PX)
        was = xr.shape
        xr = xr.binned(factor)
        if pixel_spacing_mm is not None:
            pixel_spacing_mm = float(pixel_spacing_mm) * factor
        log(f"{xr.source}: {was[0]} x {was[1]} px binned {factor} x {factor} to {xr.shape[0]} x {xr.shape[1]} px "
            f"(frames over {MAX_XRAY_SIDE_PX} px per side are binned before the preparation)")
    return xr, pixel_spacing_mm


def _check_before_loading(request: RegistrationRequest, xr: XRayImage, ct, pixel_spacing_mm):
    """What the X-ray decides before the network and the CT load: raw detector data needs a step
    that turns it; its geometry (:func:`register.xray.geometry.resolve_geometry`, returned: the
    full :class:`sim.projection.geometry.CArmGeometry`); the memory the size asks for; a CT path
    that is not there."""
    if not xr.attenuation_bright and not {"intensity", "log", "invert"} & set(request.steps):
        raise RegistrationError(f"{xr.source}: raw detector data (bone dark): add 'intensity' or 'log' to --preprocess")
    full_geometry, _ = resolve_geometry(xr, request.scene, sdd_mm=request.sdd_mm, sod_mm=request.sod_mm,
                                        pixel_spacing_mm=pixel_spacing_mm)
    check_registration_memory(request.box, (xr.pixels.shape[0], xr.pixels.shape[1]), full_geometry)
    if isinstance(ct, (str, os.PathLike)) and not is_phantom_spec(str(ct)) and not Path(ct).exists():
        raise CTInputError(f"{ct}: file or folder not found")  # before the network's load
    return full_geometry


def _load_network(request: RegistrationRequest, ct, log):
    """The method's network (None for CMA-ES alone), and a warning where it was adapted to another
    patient's CT."""
    predictor = load_predictor(request.model) if needs_model(request.method) else None
    if predictor is not None and isinstance(request.model, (str, os.PathLike)) and isinstance(ct, (str, os.PathLike)):
        warning = adapted_ct_warning(request.model, ct)
        if warning is not None:
            log(warning)
    return predictor


def _load_anatomy(request: RegistrationRequest, ct, log):
    """The CT (read, or as given) and its anatomy centre (:func:`sim.ct.anatomy.find_center`)."""
    volume = load_ct(ct, label_map=request.label_map, cache=request.ct_cache, log=log)
    return volume, find_center(volume, center=request.center)


def _prepare(request: RegistrationRequest, xr: XRayImage, volume, center_lps, pixel_spacing_mm):
    """The X-ray made ready (:func:`register.xray.prepare.prepare_xray`), its field checked at the
    registration's coarsest level."""
    prepared = prepare_xray(xr, volume=volume, center_lps=center_lps, init_params=request.start, scene=request.scene,
                            steps=list(request.steps), scale=request.intensity, polarity=request.polarity,
                            tone=request.tone, size=request.box, sdd_mm=request.sdd_mm, sod_mm=request.sod_mm,
                            pixel_spacing_mm=pixel_spacing_mm, tools=request.tools)
    _check_coarse_field(prepared, request.box, need=MIN_COARSE_FIELD_PX if request.searches else 1)
    return prepared


def _build_engine(request: RegistrationRequest, prepared, volume, center_lps, predictor, clock, remark, log):
    """The global search (where the method has one and it is not off) and the method's engine
    (:func:`register.engines.methods.build_method`); the input lines logged between them."""
    geometry = prepared.geometry
    grid = None  # contextual+cmaes's global search, built once: the polarity check scores on its grid
    if request.searches:
        with clock("search_setup"):
            grid = _global_search(request, volume, geometry, center_lps)
    log(prepared.sources.line())
    for line in _input_lines(prepared):
        log(line)
    with clock("engine_setup"):
        engine = build_method(request.method, volume, center_lps=center_lps, size=(geometry.height, geometry.width),
                              geometry=geometry, scene=request.scene, model=predictor, physics=request.moving,
                              label_materials=request.label_materials,
                              restarts=request.cmaes_restarts if request.method == "cmaes" else 0,
                              keep_drrs=True, note=remark, search=grid)
    return engine, grid


def _global_search(request: RegistrationRequest, volume, geometry, center_lps) -> GlobalSearch:
    """contextual+cmaes's global search for ``geometry``'s detector (``--search always``: its grid
    run whatever the network's pose scores)."""
    return GlobalSearch(volume, GlobalSearchSettings(always_grid=request.search == "always"),
                        size=(geometry.height, geometry.width), scene=request.scene, geometry=geometry,
                        center_lps=center_lps, physics=request.moving, label_materials=request.label_materials)


class _PolarityCheckedRun:
    """The registration with the decided polarity checked against the CT (unless an option or a
    decisive tag set it):

    - where the global search is about to run its grid, on that grid (its DRRs then serve the
      search; the search stops where the image is to be inverted, and starts again on the inverse);
    - else after the registration: a registered pose that matches the X-ray as decided confirms it
      (no grid at all), or a grid of its own around the start decides, and where it inverts the
      image the registration runs again on the inverse.

    With the global search in ``auto``, the pipeline asks the verdict whether the network's pose,
    refined, can be kept without the grid (:meth:`_trust`,
    :meth:`register.engines.pipeline.ContextualPipeline.trusted`); :meth:`judged` hands that verdict
    on where that pose is the result, so it is not gathered twice.

    :meth:`register` returns the result and the X-ray as finally prepared."""

    def __init__(self, request: RegistrationRequest, volume, center_lps, predictor, engine, grid, clock) -> None:
        self.request, self.volume, self.center_lps = request, volume, center_lps
        self.predictor, self.engine, self.grid, self.clock = predictor, engine, grid, clock
        self.prepared = None
        self._judged: tuple | None = None  # (result, image, verdict) of the last pose _trust judged

    def _once(self, **hook):
        """One registration of the X-ray as prepared now (``before_grid``: the search's hook)."""
        prepared = self.prepared
        view = network_view(self.predictor, prepared) if self.predictor is not None else None  # the network's input
        if self.grid is not None and self.request.search == "auto":
            hook["trust"] = self._trust
        return self.engine.register(prepared.image, self.request.start, mask=prepared.mask, toned=prepared.toned,
                                    network_view=view, **hook)

    def _trust(self, result) -> bool:
        """The pipeline's ``trust``: whether the verdict (:func:`_verdict`) on the network's pose,
        refined, of the X-ray as prepared now is clearly ``registered``
        (:func:`register.verdict.clearly_registered`: with every threshold 10 % stricter, as no
        alternative was examined)."""
        verdict = _verdict(self.request, self.volume, self.center_lps, self.prepared, result)
        self._judged = (result, self.prepared.image, verdict)
        return clearly_registered(verdict)

    def judged(self, result, prepared) -> Verdict | None:
        """The verdict :meth:`_trust` gathered where ``result`` is the pose it judged, of the same
        image (the polarity check left it as it was); None otherwise."""
        if self._judged is None:
            return None
        pose, image, verdict = self._judged
        return verdict if pose is result and image is prepared.image else None

    def _check(self):
        """The check against the CT on a grid of poses around the start (the search's, where built)."""
        r = self.request
        return confirm_polarity(self.prepared, self.volume, self.center_lps, r.start, physics=r.moving,
                                label_materials=r.label_materials, search=self.grid)

    def _grid_check(self) -> bool:
        """GlobalSearch.register's ``before_grid``: check on the grid; True stops it (to be inverted)."""
        with self.clock("polarity"):
            self.prepared = self._check()
        return bool(self.prepared.step("polarity_check")["inverted"])

    def register(self, prepared):
        self.prepared = prepared
        pending = polarity_needs_check(prepared)
        with self.clock("register"):
            result = self._once(**({"before_grid": self._grid_check} if pending and self.grid is not None else {}))
            if result is None:  # the grid's check inverted the image: the registration of the inverse
                result = self._once()
        if pending and self.prepared.step("polarity_check") is None:
            with self.clock("polarity"):
                score = _plain_score(self.volume, self.center_lps, self.prepared, result.pose)
                checked = confirm_polarity_by_pose(self.prepared, score, result.params)
                if checked is None:
                    checked = self._check()
            self.prepared = checked
            if self.prepared.step("polarity_check")["inverted"]:
                with self.clock("register"):
                    result = self._once()
        return result, self.prepared


def _verdict(request: RegistrationRequest, volume, center_lps, prepared, result) -> Verdict:
    """The verdict (:func:`register.verdict.judge_result`) on a registration's ``result``: three line
    DRRs (its pose and the depth probe's), the depth profile by the refinement's CMA-ES (the
    request's moving images, scored as the refinement scored this X-ray) and the rival by a
    line-DRR CMA-ES, at the optimiser's size."""
    g = prepared.geometry
    size = (g.height, g.width)
    renderer = DRRRenderer(volume, RenderSettings(size=size), center_lps=center_lps, geometry=g)
    settings = replace(REFINE_SETTINGS, size=size)
    refine = scored_as_refined(CMAESRegistration(volume, settings, geometry=g, center_lps=center_lps,
                                                 physics=request.moving, label_materials=request.label_materials),
                               prepared.toned)
    line = refine if request.moving.level == "line" else CMAESRegistration(volume, settings, geometry=g,
                                                                           center_lps=center_lps)
    fld = prepared.step("field")
    fraction = fld["valid_fraction"] if fld is not None and "valid_fraction" in fld else None
    return judge_result(result, prepared.image, render=renderer.render, sod_mm=g.sod_mm, mask=prepared.mask,
                        toned=prepared.toned, field_fraction=fraction, refine=refine, rival_search=line,
                        search_off=request.method in SEARCH_METHODS and request.search == "off")


def grid_bytes(box, shape, geometry) -> float:
    """The bytes of the largest allocation of a registration into ``box`` ``(H, W)`` of an X-ray of
    ``shape`` ``(h, w)`` px and full ``geometry`` (:class:`sim.projection.geometry.CArmGeometry`): the global
    search's grid of padded DRRs at 1/4 resolution (every grid pose at once, padded by the largest
    in-plane shift), :data:`GRID_BYTES_PER_PX` each. The polarity check scores on it even for
    ``method="cmaes"``. The field's crop is not known yet: the X-ray is taken whole."""
    s = GlobalSearchSettings()
    _, _, _, g = _fit_plan(tuple(shape), geometry, tuple(box))
    h, w = g.height // s.factor, g.width // s.factor
    spacing = g.pixel_spacing_mm * s.factor
    pad = int(np.ceil(s.range_mm * g.sdd_mm / max(g.sod_mm - s.range_mm, 1e-6) / spacing))
    return float(len(s.grid_offsets())) * (h + 2 * pad) * (w + 2 * pad) * GRID_BYTES_PER_PX


def check_registration_memory(box, shape, geometry, *, available: int | None = None) -> None:
    """Refuse (one line naming ``--size``) a registration whose largest allocation
    (:func:`grid_bytes`) exceeds the memory available now, before it is made."""
    check_memory(grid_bytes(box, shape, geometry), f"--size {box[0]} {box[1]}",
                 f"registering this {shape[0]} x {shape[1]} px X-ray at {box[0]} x {box[1]} px (the global search's "
                 "grid of DRRs, which the polarity check uses too)",
                 advice="give a smaller --size (the default 128 128 is the tested one)", available=available)


def _check_coarse_field(prepared, box, need: int) -> None:
    """Refuse, naming ``--size``, an X-ray whose field fitted into ``box`` leaves fewer than ``need``
    pixels at the registration's coarsest level (1/4, eroded by one pixel, as the global search and
    the masked gradient similarity see it): the registration would fail deep inside with "mask:
    empty after erosion" or "too few to search"."""
    mask = prepared.mask
    h, w = prepared.image.shape
    m = np.ones((h // 4, w // 4), bool) if mask is None else downsample(np.asarray(mask, np.float64), 4) > 0.999
    left = int(ndimage.binary_erosion(m, np.ones((3, 3)), border_value=0).sum())
    if left < need:
        raise PreprocessError(f"--size {box[0]} {box[1]}: the X-ray's field, fitted into it ({h} x {w} px), leaves "
                              f"{left} pixels at the registration's coarsest level (1/4), fewer than {need}: give a "
                              f"larger --size")


def _plain_score(volume, center_lps, prepared, pose) -> float:
    """The gradient NCC of the prepared X-ray (as decided, over its field) with the line DRR at
    ``pose`` ``(4, 4)``, at the optimiser's size: the score that confirms a polarity
    (:func:`register.xray.prepare.confirm_polarity_by_pose`)."""

    g = prepared.geometry
    drr = DRRRenderer(volume, RenderSettings(size=(g.height, g.width)), center_lps=center_lps, geometry=g).render(pose)
    return float(gradient_ncc(prepared.image, drr, mask=prepared.mask)[0])


def _input_lines(prepared) -> list[str]:
    """One line each for the orientation, the field, the intensity decision and the polarity check
    (what a user should check first)."""
    lines = []
    if prepared.xray.meta.get("orientation"):
        lines.append(f"orientation: {prepared.xray.meta['orientation']} (--orient), as the CT's view")
    fld = prepared.step("field")
    if fld is not None:
        kind = fld.get("kind")
        outside = f", {fld.get('outside')} outside" if fld.get("outside") else ""
        view = fld.get("view", "display")
        seen = ("" if view == "display" else
                f", found in the image's {view} view only (its anatomy lies in few grey levels, as on a linear or "
                f"narrow-window display: check the result)")
        lines.append(f"field: {kind}{outside}{seen}; {100 * fld.get('valid_fraction', 0):.0f} % of the pixels valid")
    dec = prepared.step("intensity")
    if dec is not None:
        steps = " + ".join(dec["steps"]) or "nothing"
        tone = f"; tone: {dec['tone']}" if dec.get("tone") else ""
        lines.append(f"intensity: {dec['scale']} ({dec['scale_source']}), {dec['polarity']} "
                     f"({dec['polarity_source']}): {steps}{tone}")
    polarity = _polarity_line(prepared)
    return lines if polarity is None else [*lines, polarity]


def _polarity_line(prepared) -> str | None:
    """The polarity check's line (None before or without the check)."""
    check = prepared.step("polarity_check")
    if check is None:
        return None
    if "reason" in check:
        return f"polarity check against the CT: not run ({check['reason']}): {check['polarity']}"
    if check.get("by") == "pose":
        return (f"polarity check against the CT: confirmed by the registered pose (similarity "
                f"{check['similarity_as_decided']:.3f} >= {check['threshold']:.2f} as decided): {check['polarity']}")
    verdict = {"inverted": "inverted the image", "confirmed": "confirmed",
               "inconclusive": "inconclusive, the decision stands"}[check["verdict"]]
    return (f"polarity check against the CT: {verdict} (similarity {check['similarity_as_decided']:.3f} "
            f"as decided, {check['similarity_inverted']:.3f} inverted): {check['polarity']}")
