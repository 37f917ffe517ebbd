"""register's commands (``ctxreg register``, ``evaluate``, ``study``): their options (one dataclass each) and runs.

Each checks its options and output folder before any work; ``register`` is a thin layer over
:func:`register.api.register_xray`, ``evaluate`` builds its methods with
:mod:`register.engines.methods` and runs :func:`register.evaluation.evaluate.evaluate`, ``study``
runs :func:`register.evaluation.study.run_domain_study`. (``ctxreg demo``'s are
:mod:`register.evaluation.demo`'s.)
"""

from __future__ import annotations

import contextlib
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from register.api import (OUTPUT_FILES, REGISTER_RESTARTS, REGISTER_SCATTER_PHOTONS, RESTART_METHODS, SEARCH_METHODS,
                          SEARCH_MODES, RegistrationRequest, parse_init, register_xray)
from register.engines.cmaes import CMAESSettings
from register.engines.result import RegistrationError
from register.engines.methods import METHOD_NAMES, build_method, load_predictor, needs_model
from register.engines.pipeline import NETWORK_DEPTH_RANGE_MM
from register.engines.search import GlobalSearchSettings
from register.evaluation.evaluate import (LOCAL_ROT_DEG, LOCAL_TRANS_MM, START_MODES, EvaluationError,
                                          EvaluationSettings, MethodSpec, evaluate)
from register.xray.intensity import POLARITIES, SCALES, TONES
from register.serve import FolderWatch, ServeError, serve_frames, stdin_frames
from register.xray.field import TOOL_OPTIONS, TOOLS_DEFAULT
from register.xray.io import ORIENTATIONS
from sim.cli import CT_HELP
from sim.core.cliargs import IMAGE_SIDE_PX, Range, opt, refuse_unused, refuse_unused_label_map
from sim.core.outputs import Written, check_output_dir
from sim.core.progress import process_seconds
from sim.core.scale import dask_client, parse_scheduler
from sim.physics.options import (check_level_options, label_materials, level_field, physics_option,
                                 physics_settings)
from sim import load_ct
from sim.core.errors import CtxregError, USER_OS_ERRORS
from sim.ct.anatomy import anatomy_center
from sim.ct.io import load_ct_spec
from sim.physics.imaging import LogImageRenderer, PhysicsSettings
from sim.projection.drr import DRRRenderer, RenderSettings
from sim.projection.scene import load_scene

__all__ = ["EvaluateCommand", "RegisterCommand", "run_evaluate", "run_register", "REGISTER_RESTARTS",
           "REGISTER_SCATTER_PHOTONS"]

#: Outputs of ``ctxreg evaluate`` (trajectories.json for the contextual methods only).
EVALUATE_FILES = ("cases.csv", "summary.json", "table.md", "violins.png", "trajectories.json")


@dataclass(frozen=True)
class EvaluateCommand:
    """Defaults of ``ctxreg evaluate``."""

    ct: str | None = field(default=None, metadata=opt(
        CT_HELP + " (the simulated protocol: required unless --deepfluoro)", group="input", metavar="PATH|phantom"))
    deepfluoro: str | None = field(default=None, metadata=opt(
        "the DeepFluoro full-resolution HDF5 file (ipcai_2020_full_res_data.h5): register its real frames against "
        "their ground truth instead of simulated cases (docs/deepfluoro.md)", group="input", metavar="FILE"))
    specimen: tuple[str, ...] = field(default=(), metadata=opt(
        "--deepfluoro: the specimens, by name (17-1882) or number 1-6 (default: all)", group="input", nargs="+",
        metavar="ID"))
    frames: int | None = field(default=None, metadata=opt(
        "--deepfluoro: at most N frames per specimen, the first ones (default: all)", group="input", metavar="N",
        bounds=Range(1)))
    detect_field: bool = field(default=True, metadata=opt(
        "--deepfluoro: find a collimated field in each frame after its 50 px border is cut (register's field "
        "detection on raw frames: docs/xray_input.md); --no-detect-field takes the whole frame within the border",
        group="input", negatable=True))
    resume: bool = field(default=False, metadata=opt(
        "--deepfluoro: continue an interrupted run from --out's progress.json (same file, options and model)",
        group="input"))
    label_map: str | None = field(default=None, metadata=opt(
        "label map on the CT's grid: its centroid is the anatomy centre", group="input", metavar="PATH"))
    center: tuple[float, float, float] | None = field(default=None, metadata=opt(
        "anatomy centre c in LPS", group="input", unit="mm", nargs=3, metavar=("X", "Y", "Z")))
    cases: int = field(default=20, metadata=opt("number of target poses", group="protocol", metavar="N",
                                                bounds=Range(1)))
    method: tuple[str, ...] | None = field(default=None, metadata=opt(
        "registration methods to compare (default: cmaes; with --deepfluoro contextual+cmaes, as ctxreg register)",
        group="protocol", nargs="+", choices=METHOD_NAMES))
    model: str | None = field(default=None, metadata=opt(
        "the contextual methods' network: a shipped model's name (ctxreg models), a model folder or a ctxreg train "
        "checkpoint "
        "(default: the shipped default model)", group="protocol", metavar="NAME|CKPT"))
    start: str = field(default="ap", metadata=opt(
        "start every case at AP, at --init (pose), near the truth (local: --local-rot / --local-trans) or at the "
        "truth itself (a check: the error must stay near 0)", group="protocol", choices=START_MODES))
    init: tuple[float, float, float, float, float, float] | None = field(default=None, metadata=opt(
        "the start pose of --start pose: PHI THETA PSI TX TY TZ", group="protocol", unit="deg deg deg mm mm mm",
        nargs=6, metavar=("PHI", "THETA", "PSI", "TX", "TY", "TZ")))
    local_rot: float = field(default=5.0, metadata=opt(
        "largest start offset in rotation for --start local", group="protocol", unit="deg", bounds=LOCAL_ROT_DEG))
    local_trans: float = field(default=10.0, metadata=opt(
        "largest start offset in translation for --start local", group="protocol", unit="mm",
        bounds=LOCAL_TRANS_MM))
    seed: int = field(default=0, metadata=opt("seed of the target poses and starts", group="protocol",
                                              bounds=Range(0)))
    size: tuple[int, int] = field(default=(128, 128), metadata=opt(
        "image rows and columns of targets and DRRs", group="protocol", unit="pixels", nargs=2,
        metavar=("H", "W"), bounds=IMAGE_SIDE_PX))
    scene: str = field(default="cios_fusion", metadata=opt("C-arm scene", group="protocol"))
    target_ray_model: str = field(default="siddon", metadata=opt(
        "ray model of the target images (the methods render with siddon): trilinear makes the "
        "targets differ from the DRRs", group="protocol", choices=("siddon", "trilinear")))
    target_physics: str = field(default="line", metadata=opt(
        "physics of the target images: line (DRRs like the methods') or poly (120 kVp spectrum, 7 "
        "materials, CsI detector, quantum noise: -log(I/I0)) or full (poly + Monte Carlo scatter, "
        "10^6 histories per target): a simulated domain gap", group="protocol", choices=("line", "poly", "full")))
    target_mas: float = field(default=2.5, metadata=opt(
        "exposure of poly and full targets (less mAs, more noise)", group="protocol", unit="mAs",
        bounds=Range(0, lo_open=True)))
    physics: str = level_field(group="protocol", help=(
        "physics of the methods' moving images: line (line-integral DRRs) or poly / full "
        "(noise-free -log(I/I0) at 120 kVp, full with 10^5 scatter histories per image)"))
    scheduler: str | None = field(default=None, metadata=opt(
        "register the cases on a Dask cluster: local:N (N worker processes here) or ADDRESS (tcp://host:8786, a "
        "scheduler file *.json); the same rows in the same order as a run here (docs/scale.md)", group="protocol",
        metavar="local:N|ADDRESS"))
    out: str = field(default="out/evaluate", metadata=opt(
        "folder for cases.csv, summary.json, table.md, violins.png", group="output", metavar="DIR"))


def run_evaluate(cmd: EvaluateCommand) -> list[Path]:
    """Check the options and the output folder, then run the protocol (:func:`register.evaluation.evaluate.evaluate`)."""
    methods = cmd.method or (("contextual+cmaes",) if cmd.deepfluoro else ("cmaes",))
    contextual = [m for m in methods if needs_model(m)]
    if len(set(methods)) < len(methods):
        raise EvaluationError(f"--method {' '.join(methods)}: a method is listed twice")
    refuse_unused(cmd, ("model",), applies=bool(contextual),
                  why="meaningful with the contextual methods only; this run compares " + " ".join(methods))
    refuse_unused(cmd, ("local_rot", "local_trans"), applies=cmd.start == "local",
                  why=f"meaningful with --start local only; this run is --start {cmd.start}")
    if (cmd.init is not None) != (cmd.start == "pose"):
        raise EvaluationError("--init gives the start of --start pose: give both or neither")
    scheduler = parse_scheduler(cmd.scheduler) if cmd.scheduler is not None else None
    if cmd.deepfluoro is not None:
        return _run_deepfluoro(cmd, methods, scheduler)
    refuse_unused(cmd, ("specimen", "frames", "resume", "detect_field"), applies=False,
                  why="meaningful with --deepfluoro only")
    if cmd.ct is None:
        raise EvaluationError("--ct: required (the CT of the simulated cases), unless --deepfluoro FILE is given")
    refuse_unused_label_map(cmd)
    if cmd.target_physics == "line" and cmd.target_mas != 2.5:
        raise EvaluationError("--target-mas only applies with --target-physics poly or full")
    settings = EvaluationSettings(cases=cmd.cases, seed=cmd.seed, size=tuple(cmd.size), start=cmd.start,
                                  local_rot_deg=cmd.local_rot, local_trans_mm=cmd.local_trans,
                                  init=None if cmd.init is None else tuple(cmd.init))
    out = check_output_dir(cmd.out, EVALUATE_FILES)
    predictor = load_predictor(cmd.model) if contextual else None
    with contextlib.ExitStack() as stack:  # a scheduler is reached (or refused) before any work
        client = None if scheduler is None else stack.enter_context(dask_client(scheduler))
        return _run_simulated(cmd, methods, settings, out, predictor, scheduler, client)


def _run_simulated(cmd: EvaluateCommand, methods: tuple[str, ...], settings: EvaluationSettings, out: Path, predictor,
                   scheduler, client) -> list[Path]:
    """The simulated protocol's run, here or on ``client``'s Dask workers."""

    volume = load_ct_spec(cmd.ct, label_map=cmd.label_map)
    center = np.asarray(cmd.center, float) if cmd.center is not None else anatomy_center(volume)
    if cmd.target_physics in ("poly", "full"):
        physics = PhysicsSettings(level=cmd.target_physics, mas=cmd.target_mas, seed=cmd.seed)
        target_renderer = LogImageRenderer(volume, physics,
                                           scene=cmd.scene, size=tuple(cmd.size), ray_model=cmd.target_ray_model,
                                           center_lps=center)
    else:
        target_renderer = DRRRenderer(volume, RenderSettings(scene=cmd.scene, size=tuple(cmd.size),
                                                             ray_model=cmd.target_ray_model), center_lps=center)
    moving = None if cmd.physics == "line" else PhysicsSettings(
        level=cmd.physics, noise=False, scatter_photons=REGISTER_SCATTER_PHOTONS)

    def note(text: str) -> None:
        print(f"ctxreg evaluate: note: {text}", file=sys.stderr)

    physics_record = {"target_physics": cmd.target_physics if cmd.target_physics == "line" else asdict(physics),
                      "moving_physics": "line" if moving is None else asdict(moving)}
    common = dict(center_lps=center, geometry=target_renderer.geometry, target_renderer=target_renderer,
                  record=physics_record)
    if client is None:
        built = {name: build_method(name, volume, center_lps=center, size=tuple(cmd.size), scene=cmd.scene,
                                    model=predictor if needs_model(name) else None, physics=moving, note=note)
                 for name in methods}
        result = evaluate(volume, built, settings, out, **common)
    else:
        spec = MethodSpec(ct=str(cmd.ct), label_map=cmd.label_map, center_lps=tuple(float(v) for v in center),
                          size=tuple(cmd.size), scene=cmd.scene, methods=tuple(methods), model=cmd.model,
                          physics=moving)
        print(f"ctxreg evaluate: registering on {scheduler.describe()}", file=sys.stderr, flush=True)
        result = evaluate(volume, {}, settings, out, client=client, spec=spec, **common)
    print(result["table"])
    return [out / name for name in ("cases.csv", "summary.json", "table.md", "violins.png")]


#: The simulated protocol's options that a --deepfluoro run has no use for (the file gives the CT,
#: the frames and their physics).
_SIMULATED_ONLY = ("ct", "label_map", "center", "cases", "target_ray_model", "target_physics", "target_mas", "physics")


def _run_deepfluoro(cmd: EvaluateCommand, methods: tuple[str, ...], scheduler=None) -> list[Path]:
    """``ctxreg evaluate --deepfluoro FILE``: :func:`register.evaluation.deepfluoro.evaluate_deepfluoro`."""
    from register.evaluation.deepfluoro import DEEPFLUORO_FILES, DeepFluoroSettings, evaluate_deepfluoro  # off the CLI's start-up: building the parser imports every command's module

    refuse_unused(cmd, _SIMULATED_ONLY, applies=False,
                  why="the simulated protocol's; --deepfluoro takes the CT, the frames and the truth from the file")
    settings = DeepFluoroSettings(specimens=tuple(cmd.specimen), frames=cmd.frames, methods=tuple(methods),
                                  start=cmd.start, init=None if cmd.init is None else tuple(cmd.init),
                                  local_rot_deg=cmd.local_rot, local_trans_mm=cmd.local_trans, seed=cmd.seed,
                                  sod_mm=load_scene(cmd.scene).geometry.sod_mm, size=tuple(cmd.size), scene=cmd.scene,
                                  detect_field=cmd.detect_field)
    out = check_output_dir(cmd.out, DEEPFLUORO_FILES)
    with contextlib.ExitStack() as stack:  # a scheduler is reached (or refused) before any work
        client = None if scheduler is None else stack.enter_context(dask_client(scheduler))
        if client is not None:
            print(f"ctxreg evaluate: registering the frames on {scheduler.describe()}", file=sys.stderr, flush=True)
        result = evaluate_deepfluoro(cmd.deepfluoro, settings, out, model=cmd.model, resume=cmd.resume,
                                     log=lambda line: print(line, flush=True), client=client)
    print(result["table"])
    return [out / name for name in DEEPFLUORO_FILES]


@dataclass(frozen=True)
class RegisterCommand:
    """Defaults of ``ctxreg register``."""

    ct: str = field(metadata=opt(CT_HELP, group="input", metavar="PATH|phantom"))
    xray: str = field(metadata=opt(
        "X-ray: DICOM (geometry from its tags when present) or PNG/TIFF/JPEG", group="input", metavar="IMAGE"))
    label_map: str | None = field(default=None, metadata=opt(
        "label map on the CT's grid: its centroid is the anatomy centre", group="input", metavar="PATH"))
    center: tuple[float, float, float] | None = field(default=None, metadata=opt(
        "anatomy centre c in LPS", group="input", unit="mm", nargs=3, metavar=("X", "Y", "Z")))
    init: tuple[str, ...] = field(default=("ap",), metadata=opt(
        "start pose: 'ap' or six numbers PHI THETA PSI TX TY TZ", group="pose", nargs="+",
        unit="deg deg deg mm mm mm", metavar="ap|P"))
    method: str = field(default="contextual+cmaes", metadata=opt("registration method", group="pose", choices=METHOD_NAMES))
    model: str | None = field(default=None, metadata=opt(
        "the contextual methods' network: a shipped model's name (ctxreg models), a model folder or a ctxreg train "
        "checkpoint "
        "(default: the shipped default model)", group="pose", metavar="NAME|CKPT"))
    restarts: int = field(default=REGISTER_RESTARTS, metadata=opt(
        "CMA-ES restarts (new seed, twice the population) while the final gradient NCC is below "
        f"{CMAESSettings.restart_below}: a search lost far from the start tries again (--method cmaes only; "
        "contextual+cmaes runs a global search where the network's pose is lost)",
        group="pose", metavar="N", bounds=Range(0, 10)))
    search: str = field(default="auto", metadata=opt(
        "the global search of --method contextual+cmaes (a rotation / depth grid over the prior box around "
        "--init): auto first refines the network's pose as off does and keeps it where it scores at least "
        f"{GlobalSearchSettings.refined_above:g} and the verdict calls it "
        "clearly registered (every threshold 10 %% stricter), else runs the grid where the network's pose scores below "
        f"{GlobalSearchSettings.found_above:g} (gradient NCC), else refines the network's pose directly and runs it after all "
        f"where that refinement ends below {GlobalSearchSettings.refined_above:g}; off never builds it: the network's pose goes "
        "straight to the CMA-ES "
        f"refinement, whose box is +-{NETWORK_DEPTH_RANGE_MM:g} mm in depth, where the network is least sure "
        "(the network measured on its own; the polarity is still checked, by the registered pose or on a grid "
        "of its own, deciding the polarity only); "
        "always runs it whatever the network's pose scored. result.json's search_ran / search_status say what "
        "it did (--method contextual+cmaes only)", group="pose", choices=SEARCH_MODES))
    scene: str = field(default="cios_fusion", metadata=opt(
        "C-arm scene: the geometry where the image does not give it", group="geometry"))
    sdd: float | None = field(default=None, metadata=opt(
        "source-to-detector distance (overrides DICOM and scene)", group="geometry", unit="mm",
        bounds=Range(0, lo_open=True)))
    sod: float | None = field(default=None, metadata=opt(
        "source-to-isocentre distance (overrides DICOM and scene)", group="geometry", unit="mm",
        bounds=Range(0, lo_open=True)))
    pixel_spacing: float | None = field(default=None, metadata=opt(
        "detector pixel spacing (overrides DICOM and scene)", group="geometry", unit="mm",
        bounds=Range(0, lo_open=True)))
    size: tuple[int, int] = field(default=(128, 128), metadata=opt(
        "the image the optimiser works on: the X-ray, cropped to its field, scaled (aspect kept) to the "
        "largest size inside H x W with sides multiples of 4 (128 128: the longer side 128 px; a 2:1 "
        "X-ray becomes 128 x 64)", group="geometry", unit="pixels", nargs=2, metavar=("H", "W"),
        bounds=IMAGE_SIDE_PX))
    physics: str = level_field(help=(
        "physics of the moving images: line (line-integral DRRs), poly (noise-free -log(I/I0) with "
        "the tube spectrum, 7 materials, CsI detector: beam hardening like the X-ray's) or full "
        "(poly + Monte Carlo scatter, same seed at every pose)"))
    kvp: float = physics_option("kvp")
    filters: tuple[str, ...] = physics_option("filters")
    anode_angle_deg: float = physics_option("anode_angle_deg")
    bins: int = physics_option("bins")
    detector_mm: float = physics_option("detector_mm")
    detector_mode: str = physics_option("detector_mode")
    scatter_photons: int = physics_option("scatter_photons", default=REGISTER_SCATTER_PHOTONS)
    scatter_voxel_mm: float = physics_option("scatter_voxel_mm")
    grid_ratio: float = physics_option("grid_ratio")
    label_material: tuple[str, ...] = physics_option("label_material")
    preprocess: tuple[str, ...] = field(default=("field", "median", "intensity", "normalize", "crop"), metadata=opt(
        "preprocessing steps in order: field (collimated field, text and saturation -> valid-pixel mask), "
        "median, intensity (decides raw / log / display and bone bright / dark, then log and/or invert), "
        "log, invert, normalize (over the mask), crop (to the mask)", group="image", nargs="*"))
    intensity: str = field(default="auto", metadata=opt(
        "what the pixel values are: linear (raw detector intensity: takes the log), log, display "
        "(a vendor's LUT); auto decides from the DICOM tags, then the image", group="image",
        choices=("auto", *SCALES)))
    polarity: str = field(default="auto", metadata=opt(
        "bone in the image as displayed: bone-bright (radiograph) or bone-dark (fluoroscopy, raw); auto "
        "decides from the DICOM tags, the image's noise, DRRs of the CT around the start and the file's "
        "modality, then checks it against the CT (the image and its inverse scored over the global search's pose grid)", group="image",
        choices=("auto", *POLARITIES)))
    tone: str = field(default="ct", metadata=opt(
        "a display image's unknown look-up table (window, gamma, log or not): ct also makes a toned version, the "
        "field's pixels mapped by rank onto the line integrals of DRRs of the CT around the start, which the global "
        "search's grid ranks beside the image (and a network trained on toned targets sees); off makes none; raw "
        "and log images get none", group="image", choices=TONES))
    tools: str = field(default=TOOLS_DEFAULT, metadata=opt(
        "metal tools in the field (screws, K-wires, plates, retractors, cables): detect finds them with the "
        "shipped segmenter (models/tool_mask) and leaves them out of the similarities' pixels as clipped plateaus "
        "are (result.json: field.excluded.tools), but for pieces that attenuate less than half the field; off does "
        "not look for them (docs/xray_input.md)", group="image", choices=TOOL_OPTIONS))
    orient: str = field(default="none", metadata=opt(
        "how the stored X-ray is turned into the CT's view before anything else: mirrored (flip-left-right, "
        "flip-top-bottom), rotated counter-clockwise (rotate-90/180/270) or both (transpose, transverse); for "
        "vendors and viewers that store frames mirrored or rotated. Not guessed: a mirrored pelvis can score as "
        "well as the right view. The figures show the X-ray so turned", group="image", choices=tuple(ORIENTATIONS)))
    out: str = field(default="out/register", metadata=opt(
        "folder for result.json, overlay.png (DRR edges and the field outline over the X-ray at its full "
        "resolution), checkerboard.png, convergence.png (and trajectory.npz, trajectory.png, trajectory.gif for the "
        "contextual methods)", group="output", metavar="DIR"))
    ct_cache: str = field(default="auto", metadata=opt(
        "folder of loaded CTs (a CT is read once, then from one file with its anatomy centre; a changed CT misses): "
        "'auto' = $CTXREG_CT_CACHE or ~/.cache/ctxreg/ct, 'off' = read the CT's files every time",
        group="input", metavar="DIR|auto|off"))
    verbose: bool = field(default=False, metadata=opt(
        "print where the call's seconds went (start-up and imports, X-ray, model, CT, preparation, polarity check, "
        "registration stages, outputs) to stderr; result.json keeps them either way (timings_s, stage_seconds)",
        group="output"))


def _register_keywords(cmd: RegisterCommand, command: str = "register") -> dict:
    """Check the options of a ``register`` (or ``serve``) command and return
    :func:`register.api.register_xray`'s keywords from them (all but the CT, the X-ray, the model and
    the label map)."""
    parse_init(cmd.init)
    refuse_unused_label_map(cmd)
    refuse_unused(cmd, ("restarts",), applies=cmd.method in RESTART_METHODS,
                  why=f"meaningful with --method {' or '.join(RESTART_METHODS)} only; this run is --method {cmd.method}")
    refuse_unused(cmd, ("search",), applies=cmd.method in SEARCH_METHODS,
                  why=f"meaningful with --method {' or '.join(SEARCH_METHODS)} only (the other methods have no global "
                      f"search); this run is --method {cmd.method}")
    steps = [str(n).strip().lower() for n in cmd.preprocess]
    refuse_unused(cmd, ("intensity", "polarity", "tone"), applies="intensity" in steps,
                  why="meaningful with the 'intensity' step of --preprocess only; this run's steps are "
                      + (" ".join(steps) or "none"))
    check_level_options(cmd)
    return dict(method=cmd.method, init=cmd.init, center=cmd.center, scene=cmd.scene, sdd_mm=cmd.sdd,
                sod_mm=cmd.sod, pixel_spacing_mm=cmd.pixel_spacing, size=tuple(cmd.size),
                physics=physics_settings(cmd, noise=False), label_materials=label_materials(cmd), preprocess=steps,
                intensity=cmd.intensity, polarity=cmd.polarity, tone=cmd.tone, tools=cmd.tools, orient=cmd.orient,
                restarts=cmd.restarts if cmd.method in RESTART_METHODS else None,
                search=cmd.search if cmd.method in SEARCH_METHODS else "auto",
                ct_cache={"auto": True, "off": False}.get(cmd.ct_cache, cmd.ct_cache),
                note=lambda text: print(f"ctxreg {command}: note: {text}", file=sys.stderr))


def run_register(cmd: RegisterCommand) -> Written:
    """Check the options and the output folder, register (:func:`register.api.register_xray`: it
    checks the method, model, start, CT, X-ray and geometry before the work) and write the outputs.
    The verdict (:mod:`register.verdict`) is the last line printed and sets the exit status: 0
    registered, 3 doubtful or failed (every output written either way)."""
    keywords = _register_keywords(cmd)
    out = check_output_dir(cmd.out, OUTPUT_FILES)
    startup = process_seconds()  # the interpreter's start-up and the imports, before any work
    outcome = register_xray(cmd.ct, cmd.xray, model=cmd.model, label_map=cmd.label_map, log=print, **keywords)
    if startup is not None:
        outcome.timings = {"startup": startup, **outcome.timings}
    written = outcome.write(out)
    print(outcome.summary())
    verdict = outcome.verdict
    if cmd.verbose:
        total = process_seconds()
        lines = [f"  {k}: {v:.2f} s" for k, v in outcome.timings.items()]
        lines += [f"    {k}: {v:.2f} s" for k, v in outcome.result.stage_seconds.items()]
        print("ctxreg register: where the seconds went (wall; the indented ones split register):\n" + "\n".join(lines)
              + (f"\n  total since the process started: {total:.2f} s" if total is not None else ""), file=sys.stderr)
    return Written(written, last_line=verdict.line(), exit_status=verdict.exit_status)


@dataclass(frozen=True)
class ServeCommand(RegisterCommand):
    """Defaults of ``ctxreg serve``: ``ctxreg register``'s options, for a case's frames in one process."""

    xray: str = field(default="-", metadata=opt(
        "where the frames come from: '-' reads X-ray paths from stdin, one per line, until its end; a folder is "
        "watched for new X-ray files (DICOM, PNG, TIFF, JPEG, .npy; each taken once its size and time hold, in name "
        "order; a refused one again when it changes; one already registered into --out, by path and content, not "
        "again, so a restart continues) until --frames, SIGTERM or Ctrl-C (the first finishes the frame in hand, "
        "a second abandons it)", group="input", metavar="-|DIR"))
    out: str = field(default="out/serve", metadata=opt(
        "folder that gets one folder per frame (its file name's stem; _2, _3, ... where taken) with register's "
        "outputs and frame.json (the X-ray's path and SHA-256), each written whole or not at all", group="output", metavar="DIR"))
    frames: int = field(default=0, metadata=opt(
        "stop after this many frames (0: at the end of stdin, or never for a folder)", group="input", metavar="N",
        bounds=Range(0, 1_000_000)))


def run_serve(cmd: ServeCommand) -> list[Path]:
    """Register a case's frames in one process (:mod:`register.serve`): the CT, its anatomy centre
    and the network loaded once, Dr.Jit's kernels compiled once, each frame as it arrives (stdin or
    a watched folder). One JSON line per frame on stdout (``xray``, ``out``, ``params`` deg/mm,
    ``similarity``, ``seconds``, ``search_status``; or ``error`` where the frame was refused: the
    next frame goes on). Refused (exit 2) when no frame was registered."""

    keywords = _register_keywords(cmd, "serve")
    source = None if cmd.xray == "-" else Path(cmd.xray)
    if source is not None and not source.is_dir():
        raise ServeError(f"--xray {cmd.xray}: not a folder to watch (or '-' for paths on stdin)")
    root = Path(cmd.out)
    if root.exists() and not root.is_dir():
        raise ServeError(f"--out {cmd.out}: a file, not a folder")
    volume = load_ct(cmd.ct, label_map=cmd.label_map, cache=keywords.pop("ct_cache"),
                     log=lambda line: print(f"ctxreg serve: {line}", file=sys.stderr))
    if keywords["center"] is None:
        keywords["center"] = anatomy_center(volume)
    model = load_predictor(cmd.model) if needs_model(cmd.method) else None
    print(f"ctxreg serve: {volume.source} and the {cmd.method} method ready; frames from "
          f"{'stdin' if source is None else source}", file=sys.stderr, flush=True)
    watch = None if source is None else FolderWatch(source)
    note = keywords.pop("note")
    request = RegistrationRequest(model=model, **keywords)  # the options checked once, for every frame
    summary = serve_frames(lambda path: request.run(volume, path, note=note),
                           stdin_frames() if watch is None else watch, root, watch=watch, limit=cmd.frames,
                           errors=(CtxregError, *USER_OS_ERRORS), verbose=cmd.verbose)
    if summary.registered + summary.skipped == 0:
        raise ServeError(f"no frame was registered ({summary.refused} refused"
                         + (f"; stopped by {summary.stopped_by}" if summary.stopped_by else "") + ")")
    return [root]


@dataclass(frozen=True)
class StudyCommand:
    """Defaults of ``ctxreg study``."""

    study: str = field(metadata=opt(
        "study file: [study] (evaluation CT, cases, start, methods), [[variant]] (name, [variant.train]) and "
        "[[target]] (name, kind drr|xray, physics, collimator, display); see register/evaluation/study.py",
        group="input", metavar="STUDY.toml", positional=True))
    out: str = field(default="out/study", metadata=opt(
        "folder for variants/, results/, table.md, results.json, study.png, commands.sh; a run continues a "
        "study already there", group="output", metavar="DIR"))
    only: tuple[str, ...] | None = field(default=None, metadata=opt(
        "train and evaluate only these variants (by name), e.g. one per process in parallel; the table keeps "
        "the other variants' finished results", group="protocol", nargs="+", metavar="VARIANT"))
    targets: tuple[str, ...] | None = field(default=None, metadata=opt(
        "evaluate only these target domains (by name), e.g. one per process in parallel; the table keeps the "
        "others' finished results", group="protocol", nargs="+", metavar="TARGET"))
    scheduler: str | None = field(default=None, metadata=opt(
        "register each evaluation's cases on a Dask cluster: local:N or ADDRESS (tcp://host:8786, a scheduler "
        "file *.json); the variants still train here (docs/scale.md)", group="protocol", metavar="local:N|ADDRESS"))


def run_study(cmd: StudyCommand) -> list[Path]:
    """Train every variant and evaluate it on every target domain (resumable: register/evaluation/study.py)."""
    from register.evaluation.study import STUDY_FILES, load_study, run_domain_study  # on use: its CT readers

    scheduler = parse_scheduler(cmd.scheduler) if cmd.scheduler is not None else None
    study = load_study(cmd.study)
    with contextlib.ExitStack() as stack:  # a scheduler is reached (or refused) before any work
        client = None if scheduler is None else stack.enter_context(dask_client(scheduler))
        if client is not None:
            print(f"ctxreg study: evaluating on {scheduler.describe()}", file=sys.stderr, flush=True)
        run_domain_study(study, cmd.out, only=cmd.only, targets=cmd.targets, client=client)
    return [Path(cmd.out) / name for name in STUDY_FILES]

