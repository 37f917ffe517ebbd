"""``ctxreg render`` and ``ctxreg demo``: DRRs from the command line.

Heavy modules (Mitsuba, Dr.Jit, nibabel) are imported inside the commands, so ``--help`` is
instant. Outputs are written atomically; beside every image a JSON sidecar records the
geometry (see :func:`geometry_record`).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.core.cliargs import IMAGE_SIDE_PX, Range, opt
from sim.core.errors import InputError
from sim.physics.options import level_field, physics_option
from sim.ct.anatomy import find_center
from sim.projection.drr import QUANTITIES, RAY_MODELS, STEP_FRACTION, RenderSettings
from sim.core.atomic import atomic_path, write_json
from sim.core.cliargs import refuse_unused, refuse_unused_label_map
from sim.core.outputs import check_output_file
from sim.core.scale import dask_client, parse_scheduler
from sim.ct.io import load_ct_spec
from sim.physics.options import check_level_options, label_materials, physics_settings

_DEFAULTS = RenderSettings()  # the renderer's defaults are the command line's

CT_HELP = "CT: a NIfTI file, a DICOM series folder, or 'phantom' / 'phantom:SEED' (built-in pelvis)"


class CommandError(InputError):
    """A command-line input that cannot be used; printed as one line."""


@dataclass(frozen=True)
class RenderCommand:
    """Defaults of ``ctxreg render`` (each field is one option)."""

    ct: str = field(metadata=opt(CT_HELP, group="input", metavar="PATH|phantom"))
    label_map: str | None = field(default=None, metadata=opt(
        "label map on the CT's grid (NIfTI or DICOM folder); its centroid is the anatomy centre",
        group="input", metavar="PATH"))
    center: tuple[float, float, float] | None = field(default=None, metadata=opt(
        "anatomy centre c in LPS (default: label-map centroid, else bone centroid)", group="input",
        unit="mm", nargs=3, metavar=("X", "Y", "Z")))
    scene: str = field(default=_DEFAULTS.scene, metadata=opt(
        "C-arm scene: a name from scenes/ or a scene XML path", group="geometry"))
    size: tuple[int, int] = field(default=_DEFAULTS.size, metadata=opt(
        "rendered image rows and columns (the detector is resampled, its extent kept)",
        group="geometry", unit="pixels", nargs=2, metavar=("H", "W"), bounds=IMAGE_SIDE_PX))
    pose: tuple[float, float, float, float, float, float] = field(default=(0.0,) * 6, metadata=opt(
        "pose parameters: rotations phi theta psi about the patient's S, L, P axes, then "
        "translations tx ty tz in the camera frame; all zero is the AP view", group="pose",
        unit="deg deg deg mm mm mm", nargs=6, metavar=("PHI", "THETA", "PSI", "TX", "TY", "TZ")))
    pose_matrix: str | None = field(default=None, metadata=opt(
        "4x4 pose T from a .npy/.txt file or a render's .json sidecar (replaces --pose)",
        group="pose", metavar="FILE"))
    quantity: str = field(default=_DEFAULTS.quantity, metadata=opt(
        "what each pixel holds", group="physics", choices=QUANTITIES[:2]))
    mu_water: float = field(default=_DEFAULTS.mu_water_per_mm, metadata=opt(
        "attenuation of water; mu = mu_water (1 + HU/1000), clipped at 0", group="physics",
        unit="1/mm", metavar="MU"))
    ray_model: str = field(default=_DEFAULTS.ray_model, metadata=opt(
        "siddon: exact voxel traversal; trilinear: sampled trilinear interpolant",
        group="physics", choices=RAY_MODELS))
    step_fraction: float = field(default=_DEFAULTS.step_fraction, metadata=opt(
        "trilinear step as a fraction of the smallest voxel spacing (--ray-model trilinear, --physics line)",
        group="physics", metavar="F", bounds=STEP_FRACTION))
    physics: str = level_field(help=(
        "line: line integrals of mu (DRR); poly: tube spectrum, 7 materials with NIST cross "
        "sections, CsI detector, noise; full: poly + Monte Carlo scatter"))
    kvp: float = physics_option("kvp")
    filters: tuple[str, ...] = physics_option("filters")
    anode_angle_deg: float = physics_option("anode_angle_deg")
    mas: float = physics_option("mas")
    bins: int = physics_option("bins")
    detector_mm: float = physics_option("detector_mm")
    detector_mode: str = physics_option("detector_mode")
    noise: bool = physics_option("noise")
    blur_mm: float = physics_option("blur_mm")
    electronic_noise: float = physics_option("electronic_noise")
    seed: int = physics_option("seed")
    scatter_photons: int = physics_option("scatter_photons")
    scatter_voxel_mm: float = physics_option("scatter_voxel_mm")
    grid_ratio: float = physics_option("grid_ratio")
    label_material: tuple[str, ...] = physics_option("label_material")
    primary: bool = field(default=False, metadata=opt(
        "also write the noise-free primary signal as <out stem>_primary.npy, and with --physics "
        "full the expected scatter signal as <out stem>_scatter.npy (poly, full)", group="output"))
    out: str = field(default="out/drr.png", metadata=opt(
        ".npy: float32 (H, W) raw values; .png: display image (bone bright). A .json sidecar "
        "with the geometry is written beside it. With --physics poly or full the image is -log(I/I0) and the "
        "raw detector signal goes to <out stem>_raw.npy", group="output", metavar="FILE"))


def load_pose_matrix(path: str) -> np.ndarray:
    """A ``(4, 4)`` pose from .npy, text, or a render's JSON sidecar (key ``pose_4x4``)."""
    p = Path(path)
    if not p.is_file():
        raise CommandError(f"--pose-matrix {path}: file not found")
    try:
        if p.suffix == ".npy":
            m = np.load(p, allow_pickle=False)
        elif p.suffix == ".json":
            import json

            m = np.array(json.loads(p.read_text())["pose_4x4"], dtype=np.float64)
        else:
            m = np.loadtxt(p)
    except (ValueError, KeyError, OSError) as e:
        raise CommandError(f"--pose-matrix {path}: cannot read a 4x4 matrix ({e})") from None
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise CommandError(f"--pose-matrix {path}: expected a 4x4 matrix, got shape {m.shape}")
    return m


def geometry_record(renderer, pose: np.ndarray, quantity: str, *, center_how: str = "given") -> dict:
    """The JSON sidecar: everything needed to reproduce or project into the image; ``center_how``:
    how the anatomy centre was found (:meth:`sim.ct.anatomy.Center.to_dict`)."""
    g = renderer.geometry
    return {
        "ct": renderer.volume.source,
        "scene": renderer.scene_info.name,
        "quantity": quantity,
        "units": "line integral of mu (dimensionless)" if quantity == "line-integral" else "I/I0",
        "mu_water_per_mm": renderer.settings.mu_water_per_mm,
        "ray_model": renderer.settings.ray_model,
        "image_size_hw": [g.height, g.width],
        "pixel_spacing_mm": g.pixel_spacing_mm,
        "sdd_mm": g.sdd_mm,
        "sod_mm": g.sod_mm,
        "detector_size_mm_hw": list(g.detector_size_mm),
        "principal_point_uv": list(g.principal_point),
        "K": g.intrinsics().tolist(),
        "anatomy_center_lps_mm": renderer.center_lps.tolist(),
        "anatomy_center_how": center_how,
        "pose_4x4": np.asarray(pose).tolist(),
        "projection_3x4_lps_to_pixels": renderer.projection_matrix(pose).tolist(),
        "conventions": "docs/conventions.md: X_cam = R (X_lps - c) + t; pixel (u=column, v=row)",
    }


def display_image(values: np.ndarray, quantity: str) -> np.ndarray:
    """``(H, W)`` uint8 radiograph-like display: high attenuation bright, 0.5/99.5 % window."""
    v = values if quantity == "line-integral" else -np.log(np.maximum(values, 1e-30))
    lo, hi = np.percentile(v, (0.5, 99.5))
    scaled = np.clip((v - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return (scaled * 255.0 + 0.5).astype(np.uint8)


def write_image(path: str | Path, values: np.ndarray, record: dict, quantity: str) -> None:
    """Write ``values`` (H, W) as .npy or .png and the JSON sidecar, each atomically."""
    from PIL import Image

    path = Path(path)
    if path.suffix == ".npy":
        with atomic_path(path) as tmp:
            np.save(tmp, values.astype(np.float32), allow_pickle=False)
    elif path.suffix == ".png":
        with atomic_path(path) as tmp:
            Image.fromarray(display_image(values, quantity)).save(tmp, format="PNG")
    else:
        raise CommandError(f"--out {path}: the file must end in .npy or .png")
    write_json(path.with_suffix(".json"), record)


def run_render(cmd: RenderCommand) -> Path | list[Path]:
    """Check every option and the output names, then load the CT, render (:func:`sim.render.render_view`:
    refuses a pose at which the CT is out of view) and write the image and its sidecar."""
    from sim.render import render_view  # off the CLI's start-up: building the parser imports every command's module

    out = Path(cmd.out)
    if out.suffix not in (".npy", ".png"):
        raise CommandError(f"--out {cmd.out}: the file must end in .npy or .png")
    _check_physics_options(cmd)
    if cmd.pose_matrix is not None and any(cmd.pose):
        raise CommandError("give either --pose or --pose-matrix, not both")
    extra = [] if cmd.physics == "line" else ["raw", *(("primary", "scatter") if cmd.primary else ())]
    check_output_file(out, beside=[out.with_suffix(".json"), *(out.with_name(f"{out.stem}_{n}.npy") for n in extra)])
    pose = load_pose_matrix(cmd.pose_matrix) if cmd.pose_matrix is not None else np.array(cmd.pose, np.float64)

    volume = load_ct_spec(cmd.ct, label_map=cmd.label_map)
    line = cmd.physics == "line"
    settings = RenderSettings(scene=cmd.scene, size=tuple(cmd.size), ray_model=cmd.ray_model,
                              **(dict(step_fraction=cmd.step_fraction, quantity=cmd.quantity,
                                      mu_water_per_mm=cmd.mu_water) if line else {}))
    found = find_center(volume, center=cmd.center)
    view = render_view(volume, pose, settings=settings, physics=None if line else physics_settings(cmd),
                       center_lps=found.lps_mm, label_materials=None if line else label_materials(cmd),
                       what="--pose / --pose-matrix with this --center")
    how = found.to_dict()["anatomy_center_how"]
    if line:
        write_image(out, view.image, geometry_record(view.renderer, view.pose, cmd.quantity, center_how=how),
                    cmd.quantity)
        return out
    return _write_physics(cmd, view, out, how)


#: Options of ``render`` itself that only mean something at some physics levels (the shared
#: physics options know their levels: :mod:`sim.physics.options`).
_LEVEL_BOUND = {"quantity": ("line",), "mu_water": ("line",), "step_fraction": ("line",),
                "primary": ("poly", "full")}


def _check_physics_options(cmd: RenderCommand) -> None:
    """Refuse options that this run would ignore (another physics level's, or the trilinear step
    with the Siddon ray model) instead of ignoring them silently."""

    check_level_options(cmd, extra=_LEVEL_BOUND)
    refuse_unused_label_map(cmd)
    refuse_unused(cmd, ("step_fraction",), applies=cmd.ray_model == "trilinear",
                  why=f"meaningful with --ray-model trilinear only; this run is --ray-model {cmd.ray_model}")


def _write_physics(cmd: RenderCommand, view, out: Path, center_how: str) -> list[Path]:
    record = {**geometry_record(view.renderer, view.pose, "line-integral", center_how=center_how),
              "quantity": "-log(I/I0)",
              "units": "-log(I / I0), dimensionless", "physics": view.physics}
    write_image(out, view.image, record, "line-integral")
    written = [out]
    names = ("raw", "primary", "scatter") if cmd.primary else ("raw",)
    for name in (n for n in names if n in view.images):
        path = out.with_name(f"{out.stem}_{name}.npy")
        with atomic_path(path) as tmp:
            np.save(tmp, view.images[name], allow_pickle=False)
        written.append(path)
    return written


@dataclass(frozen=True)
class SimulateCommand:
    """Defaults of ``ctxreg simulate``."""

    campaign: str = field(metadata=opt("campaign file (TOML; see docs/campaigns.md)", group="input",
                                       positional=True, metavar="CAMPAIGN.toml"))
    out: str | None = field(default=None, metadata=opt(
        "output folder (default: out/<campaign name>)", group="output", metavar="DIR"))
    workers: int = field(default=1, metadata=opt(
        "worker processes (each renders whole shards; they end with the run)", group="run", metavar="N",
        bounds=Range(1, 256)))  # sim.campaign.runner.MAX_WORKERS
    resume: bool = field(default=False, metadata=opt(
        "continue an interrupted run in --out: keep finished shards, render the rest (and any corrupt "
        "or truncated shard again)", group="run"))
    shard: str | None = field(default=None, metadata=opt(
        "run only part K of N of the work (for batch schedulers; with --resume when other parts share "
        "--out); merge with a later --resume", group="run", metavar="K/N"))
    scheduler: str | None = field(default=None, metadata=opt(
        "render the shards on a Dask cluster: local:N starts N worker processes here, ADDRESS (tcp://host:8786) "
        "or a scheduler file (*.json) joins a running scheduler, e.g. dask-jobqueue's on SLURM/PBS; the workers "
        "must see --out and the CTs (docs/scale.md)", group="run", metavar="local:N|ADDRESS"))


def run_simulate(cmd: SimulateCommand) -> list[Path]:
    from sim.campaign.config import load_campaign  # off the CLI's start-up: building the parser imports every command's module
    from sim.campaign.runner import CampaignError, parse_shard, run_campaign  # off the CLI's start-up: building the parser imports every command's module

    scheduler = parse_scheduler(cmd.scheduler) if cmd.scheduler is not None else None
    if scheduler is not None and cmd.workers != 1:
        raise CampaignError("--workers and --scheduler: choose one (the scheduler's workers render the shards)")
    cfg = load_campaign(cmd.campaign)
    out = Path(cmd.out) if cmd.out is not None else Path("out") / cfg.name
    shard = parse_shard(cmd.shard)
    if scheduler is None:
        manifest = run_campaign(cfg, out, workers=cmd.workers, resume=cmd.resume, shard=shard)
    else:
        with dask_client(scheduler) as client:
            print(f"{cfg.name}: rendering on {scheduler.describe()}", file=sys.stderr, flush=True)
            manifest = run_campaign(cfg, out, resume=cmd.resume, shard=shard, client=client)
    counts = manifest["counts"]
    state = "complete" if manifest["complete"] else "incomplete"
    print(f"{cfg.name}: {counts['images']}/{counts['expected']} images in {counts['shards']} shards, {state}")
    return [out / "manifest.json"] if cmd.shard is None else [out]
