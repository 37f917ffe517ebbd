"""``ctxreg demo``: a realistic X-ray of a CT simulated at a known pose far from AP, registered from AP.

The main job of the README, for a newcomer to watch within minutes of installing:

1. **CT**: the pelvis CT of ``../shared/data`` beside the repository (the built-in phantom when it
   is absent, or ``--ct``);
2. **X-ray**: full physics (spectrum, CsI detector, Monte Carlo scatter, an anti-scatter grid,
   quantum noise) at :data:`DEMO_POSE`, a round collimator off centre, a fluoroscopy display
   chain (log, bone dark, gamma, edge enhancement, 12 bits), written as ``xray.dcm`` with its
   geometry tags: a frame as a C-arm delivers it;
3. **registration** from AP with ``contextual+cmaes`` and the shipped default model (or
   ``--model``), through :func:`register.api.register_xray`, exactly as ``ctxreg register
   --xray xray.dcm`` does; with ``--adapt M`` the clinical flow on a patient the network never
   saw (the validation pelvis by default): the frame registered with the base network (``--model``,
   default ``ctxreg adapt``'s base, :data:`learn.shipped.DEFAULT_ADAPT_BASE`), the network adapted
   from it to the CT for M minutes (:func:`learn.adapt.adapt`, ``ctxreg adapt``) and the frame
   registered again with it, both networks' errors shown;
4. **outputs** in ``--out``: ``overlay.png`` and ``checkerboard.png`` at the X-ray's full
   resolution, ``trajectory.gif`` (each iteration's DRR beside the X-ray, captioned with its error
   against the truth), ``trajectory.png``, ``convergence.png``, ``result.json`` (the
   registration) and ``demo.json`` (the truth, the errors and the time of each stage);
5. the error against the known truth (rotation, translation, mTRE) at the start, after the
   network and at the end, and the time of each stage, printed as tables.

Each stage prints a progress line when it starts and its time when it ends.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from register.api import OUTPUT_FILES, register_xray
from register.evaluation.errors import bone_points, pose_errors
from register.evaluation.frames import FrameSimulator
from sim.core.atomic import write_json
from sim.core.cliargs import IMAGE_SIDE_PX, OptionError, Range, opt
from sim.projection.geometry import pose_from_params
from sim.core.outputs import check_output_dir
from learn.shipped import DEFAULT_ADAPT_BASE, resolve_model
from sim.ct.anatomy import anatomy_center
from sim.ct.io import load_ct_spec
from sim.physics.display import Collimator, DisplayChain
from sim.physics.imaging import PhysicsSettings, XRayImager
from sim.projection.drr import check_in_view
from sim.projection.scene import SceneError, load_scene
from learn.adapt import adapt

__all__ = ["DemoCommand", "run_demo", "DEMO_POSE", "DEMO_FILES", "default_ct"]

#: The demo X-ray's pose (phi, theta, psi deg, tx, ty, tz mm; docs/conventions.md): an oblique
#: view 25 deg and 23 mm from AP that keeps the whole pelvis in the CT (and its screw) in view.
DEMO_POSE = (-22.0, 10.0, -6.0, -15.0, 12.0, 15.0)

#: What ``ctxreg demo`` writes besides the registration's own files.
DEMO_FILES = ("xray.dcm", "demo.json")

REPO = Path(__file__).resolve().parents[2]


def default_ct() -> str:
    """The pelvis CT of ``../shared/data`` beside the repository, or ``"phantom"`` without it."""
    path = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"
    return str(path) if path.is_file() else "phantom"


#: ``demo --adapt``'s CT without ``--ct``: another person's pelvis, never in a shipped model's training.
VALIDATION_CT = REPO.parent / "shared" / "data" / "ct" / "pelvis_chiconasa_2mm.nii.gz"
#: ... and without ``../shared/data``: a phantom pelvis of a seed no shipped model trained on.
UNSEEN_PHANTOM_SEED = 5


def _adapt_ct(cmd: "DemoCommand", out: Path) -> str:
    """The CT file that ``--adapt`` adapts to: ``--ct`` (a phantom spec written to ``out`` as NIfTI),
    else :data:`VALIDATION_CT`, else the phantom of :data:`UNSEEN_PHANTOM_SEED`."""
    spec = cmd.ct or (str(VALIDATION_CT) if VALIDATION_CT.is_file() else f"phantom:{UNSEEN_PHANTOM_SEED}")
    if not spec.startswith("phantom"):
        return spec

    seed = int(spec.split(":", 1)[1]) if ":" in spec else 0
    path = out / f"phantom{seed}.nii.gz"
    if not path.is_file():
        out.mkdir(parents=True, exist_ok=True)
        from sim.ct.phantom import write_phantom_nifti  # SciPy's spatial and linalg: only for the phantom, off start-up

        write_phantom_nifti(path, seed)
    return str(path)


@dataclass(frozen=True)
class DemoCommand:
    """Defaults of ``ctxreg demo``."""

    out: str = field(default="out/demo", metadata=opt(
        "folder for xray.dcm, overlay.png, checkerboard.png, trajectory.gif, convergence.png, result.json and "
        "demo.json", group="output", metavar="DIR"))
    ct: str | None = field(default=None, metadata=opt(
        "CT (NIfTI, DICOM folder or phantom[:SEED]); default: ../shared/data's pelvis CT beside the repository, "
        "else the built-in phantom", group="input", metavar="PATH|phantom"))
    model: str | None = field(default=None, metadata=opt(
        "the network: a shipped model's name (ctxreg models), a model folder or a ctxreg train checkpoint "
        f"(default: the shipped default model; with --adapt, the base adapted from, {DEFAULT_ADAPT_BASE})",
        group="input", metavar="NAME|CKPT"))
    pose: tuple[float, float, float, float, float, float] = field(default=DEMO_POSE, metadata=opt(
        "the X-ray's true pose PHI THETA PSI TX TY TZ: the anatomy centre between the source and the detector "
        "and on the detector", group="protocol", unit="deg deg deg mm mm mm", nargs=6,
        metavar="P"))
    seed: int = field(default=0, metadata=opt("noise and Monte Carlo seed of the X-ray", group="protocol",
                                              bounds=Range(0)))
    adapt: float | None = field(default=None, metadata=opt(
        "the clinical flow on a patient the network never saw: adapt the network to the CT for M minutes (ctxreg "
        "adapt, into OUT/adapted; a second run continues it) and register with the base and the adapted network; "
        "without --ct the CT is ../shared/data's validation pelvis (another person's), else a phantom pelvis",
        group="protocol", unit="min", metavar="M", bounds=Range(0.0, 120.0, lo_open=True)))
    size: tuple[int, int] = field(default=(256, 256), metadata=opt(
        "X-ray rows and columns, at least 32 and square like the detector (the registration works at 128 px on "
        "the longer side)", group="protocol",
        unit="pixels", nargs=2, metavar=("H", "W"), bounds=IMAGE_SIDE_PX))


#: The smallest side (px) of the demo's X-ray (``--size``): its field detection needs 16 px and its
#: round collimator a field of some pixels across; the registration then works at 128 px.
DEMO_MIN_SIDE_PX = 32


def demo_geometry(cmd: DemoCommand):
    """The demo X-ray's detector (the scene's at ``--size``); a size off the detector's aspect is
    refused naming ``--size``."""

    try:
        return load_scene().geometry_at(int(cmd.size[0]), int(cmd.size[1]))
    except SceneError as e:
        raise OptionError(f"--size {cmd.size[0]} {cmd.size[1]}: {e}") from None


def _network_line(rows: dict, search_status: str) -> str:
    """One sentence on what the network did: its own iteration's mTRE (mm) against the start's, and
    what the global search then did (``rows``: the error table's rows by pose; ``search_status``:
    :attr:`register.api.XRayRegistration.search_status`)."""
    start = rows["start (AP)"]["mtre_mm"]
    key = "after the network" if "after the network" in rows else "after the adapted network"
    if key not in rows:
        return f"the network: no trajectory recorded (start mTRE {start:.1f} mm); global search {search_status}"
    after = rows[key]["mtre_mm"]
    moved = "closer to" if after < start else "away from"
    base = (f" (the base network before adaptation: {rows['after the base network']['mtre_mm']:.1f} mm)"
            if "after the base network" in rows else "")
    return (f"the {'adapted ' if key != 'after the network' else ''}network: mTRE {start:.1f} mm (AP) -> {after:.1f} mm, "
            f"{moved} the truth{base}; global search {search_status}")


def check_demo_options(cmd: DemoCommand) -> None:
    """Refuse, naming the option, a ``--size`` the demo cannot register (below
    :data:`DEMO_MIN_SIDE_PX`, off the detector's aspect) and a ``--pose`` whose anatomy centre is
    not between the source and the detector or does not project onto the detector: before the CT
    is loaded and anything simulated. (Whether the CT itself is in view is checked once it is
    loaded, still before the simulation.)"""
    if min(cmd.size) < DEMO_MIN_SIDE_PX:
        raise OptionError(f"--size {cmd.size[0]} {cmd.size[1]}: the demo's X-ray needs at least {DEMO_MIN_SIDE_PX} px "
                          f"per side (its field detection and registration); the default is 256 256")
    g = demo_geometry(cmd)
    tx, ty, tz = (float(v) for v in cmd.pose[3:])
    shown = "--pose " + " ".join(f"{v:g}" for v in cmd.pose)
    depth = g.sod_mm + tz  # the anatomy centre's distance from the source along the principal ray
    if not 0.1 * g.sod_mm <= depth <= 0.9 * g.sdd_mm:
        raise OptionError(f"{shown}: TZ {tz:g} mm puts the anatomy centre {depth:g} mm from the source; it must lie "
                          f"between the source and the detector ({0.1 * g.sod_mm:g} to {0.9 * g.sdd_mm:g} mm, TZ "
                          f"{0.1 * g.sod_mm - g.sod_mm:g} to {0.9 * g.sdd_mm - g.sod_mm:g})")
    cx, cy = g.principal_point
    u = tx / depth * g.sdd_mm / g.pixel_spacing_mm + cx
    v = ty / depth * g.sdd_mm / g.pixel_spacing_mm + cy
    if not (-0.5 <= u <= g.width - 0.5 and -0.5 <= v <= g.height - 0.5):
        raise OptionError(f"{shown}: TX {tx:g} / TY {ty:g} mm move the anatomy centre off the detector (it would "
                          f"project at column {u:.0f}, row {v:.0f} of {g.width} x {g.height})")


class _Stages:
    """A progress line per stage and its time."""

    def __init__(self, n: int):
        self.n, self.k, self.times, self.t0 = n, 0, {}, time.perf_counter()

    def start(self, name: str, what: str) -> None:
        self.k += 1
        self.name, self.t = name, time.perf_counter()
        print(f"[{self.k}/{self.n}] {what} ...", file=sys.stderr, flush=True)

    def done(self, detail: str = "") -> None:
        dt = time.perf_counter() - self.t
        self.times[self.name] = dt
        print(f"[{self.k}/{self.n}] {self.name}: {dt:.1f} s{(' - ' + detail) if detail else ''}", file=sys.stderr,
              flush=True)


def run_demo(cmd: DemoCommand) -> list[Path]:
    """Simulate, register, write and report (module doc)."""

    out = check_output_dir(cmd.out, OUTPUT_FILES + DEMO_FILES)
    check_demo_options(cmd)  # --size and --pose, before the CT is loaded or anything simulated
    # a bad --model is refused before any work; with --adapt the network adapted from and first registered with
    base = cmd.model if cmd.model is not None or cmd.adapt is None else DEFAULT_ADAPT_BASE
    model = resolve_model(base)
    stages = _Stages(4 if cmd.adapt is None else 6)
    ct = _adapt_ct(cmd, out) if cmd.adapt is not None else cmd.ct or default_ct()
    stages.start("load CT", f"loading the CT {ct}")
    volume = load_ct_spec(ct)
    center = anatomy_center(volume)
    stages.done(f"{volume.shape} voxels")

    stages.start("simulate X-ray", f"simulating a realistic X-ray at {' '.join(f'{v:g}' for v in cmd.pose)} "
                                   "(full physics, scatter, grid, noise, round collimator, fluoroscopy display)")
    physics = PhysicsSettings(level="full", kvp=85.0, mas=1.0, grid_ratio=10.0, noise=True, seed=cmd.seed,
                              scatter_photons=200_000)
    g = demo_geometry(cmd)
    T_true = pose_from_params(np.asarray(cmd.pose, float), g.sod_mm)
    check_in_view(volume, g, T_true, center, what=f"--pose {' '.join(f'{v:g}' for v in cmd.pose)}")
    imager = XRayImager(volume, physics, size=tuple(cmd.size), center_lps=center)
    collimator = Collimator(shape="circle", radius=0.46, center=(0.53, 0.47), transmission=0.02)
    chain = DisplayChain(log=True, polarity="bone-dark", gamma=0.8, unsharp_sigma_px=4.0, unsharp_amount=0.6,
                         bits=12, shutter="black")
    out.mkdir(parents=True, exist_ok=True)
    dcm = FrameSimulator(imager, chain, collimator, geometry=g).simulate(out / "xray.dcm", T_true, cmd.seed)
    stages.done(f"{dcm}")

    stages.start("register", "registering it from AP (contextual+cmaes, shipped model), as ctxreg register does")
    outcome = register_xray(volume, dcm, method="contextual+cmaes", model=str(model), init="ap", center=center,
                            log=lambda line: print(f"    {line}", file=sys.stderr))
    stages.done(f"similarity {outcome.similarity:.3f}")
    base_outcome = None
    if cmd.adapt is not None:  # the clinical flow: adapt the network to this CT, then register again

        folder = out / "adapted"
        again = (folder / "adapt.json").is_file()
        stages.start("adapt", f"adapting the network to {Path(ct).name} for {cmd.adapt:g} min (ctxreg adapt --ct {ct} "
                              f"--out {folder}{' --resume' if again else ''})")
        adapt(ct, folder, minutes=cmd.adapt, base=base, resume=again,
              log=lambda line: print(f"    {line}", file=sys.stderr))
        stages.done(f"{folder}")
        stages.start("register adapted", "registering it again from AP with the adapted network (--model "
                                         f"{folder})")
        base_outcome, model = outcome, folder
        outcome = register_xray(volume, dcm, method="contextual+cmaes", model=str(folder), init="ap", center=center,
                                log=lambda line: print(f"    {line}", file=sys.stderr))
        stages.done(f"similarity {outcome.similarity:.3f}")

    stages.start("figures", "writing the overlay, checkerboard, trajectory GIF and convergence plot")
    points = bone_points(volume, 2000, 0)

    def err(T) -> dict:
        return pose_errors(T, T_true, points, center, g)

    traj = outcome.result.trajectory
    visited = [pose_from_params(p, g.sod_mm) for p in traj["params"]] if traj is not None else []
    frames = visited[:len(traj["drrs"])] + [outcome.pose] if traj is not None else []  # as the GIF's frames
    captions = [f"error: {e['rot_err_deg']:.1f} deg, {e['trans_err_mm']:.0f} mm, mTRE {e['mtre_mm']:.0f} mm"
                for e in map(err, frames)]
    outcome.write(out, trajectory_errors=captions)
    rows = {"start (AP)": err(pose_from_params(np.zeros(6), g.sod_mm))}
    if base_outcome is not None:
        base_traj = base_outcome.result.trajectory
        if base_traj is not None and len(base_traj["params"]):
            rows["after the base network"] = err(pose_from_params(base_traj["params"][-1], g.sod_mm))
        rows["final with the base network"] = err(base_outcome.pose)
    if visited:
        rows["after the network" if base_outcome is None else "after the adapted network"] = err(visited[-1])
    rows["final (contextual+CMA-ES)"] = err(outcome.pose)
    stages.done()

    table = ["| pose | rotation error (deg) | translation error (mm) | mTRE (mm) |", "|---|---|---|---|"]
    table += [f"| {k} | {e['rot_err_deg']:.2f} | {e['trans_err_mm']:.1f} | {e['mtre_mm']:.1f} |"
              for k, e in rows.items()]
    times = ["| stage | seconds |", "|---|---|"] + [f"| {k} | {v:.1f} |" for k, v in stages.times.items()]
    times.append(f"| total | {sum(stages.times.values()):.1f} |")
    final = rows["final (contextual+CMA-ES)"]
    verdict = "registered" if final["mtre_mm"] < 10.0 else "NOT registered"
    network = _network_line(rows, outcome.search_status)
    write_json(out / "demo.json", {
        "ct": volume.source, "true_params": list(map(float, cmd.pose)), "estimated_params": outcome.result.params.tolist(),
        "errors": rows, "stage_seconds": stages.times, "model": str(model),
        "success_mtre_mm": 10.0, "registered": final["mtre_mm"] < 10.0, "search": outcome.search_status,
        "verdict": outcome.verdict.label, "verdict_reasons": list(outcome.verdict.reasons),
        "network": network,
        "xray": {"physics": "full", "kvp": physics.kvp, "mas": physics.mas, "grid_ratio": physics.grid_ratio,
                 "collimator": "circle r 0.46", "display": "log, bone dark, gamma 0.8, unsharp, 12 bits"}})
    print("\n".join(["", *times, "", f"outputs in {out}: xray.dcm, overlay.png, checkerboard.png, trajectory.gif, "
                     "convergence.png, result.json, demo.json", "",
                     network, f"the registration's own {outcome.verdict.line().replace('verdict: ', 'verdict, without the truth: ')}",
                     f"ctxreg demo: {verdict} (mTRE {final['mtre_mm']:.1f} mm; success < 10 mm)", "", *table]))
    return []  # the outputs are listed above: the error table stays the last thing printed
