"""Running a campaign: work units, worker processes, resume, and shards of the work.

The work of a campaign is a list of units, one per shard file: subject (a CT or a virtual
patient), shard index and image range. Every random draw is keyed by the campaign seed and the
unit's indices (see :func:`sim.core.seeds.rng_for`), so a unit renders the same images whichever process
runs it, in whatever order, after whatever interruption.

* ``workers > 1``: units run in spawned worker processes (Dr.Jit is not fork-safe), grouped by
  subject so a worker loads each CT once. A worker that dies (killed, out of memory) stops the
  run with an error; finished shards are kept. Workers die with the run: on Linux the kernel
  kills them when the parent dies (``PR_SET_PDEATHSIG``), elsewhere they notice within a
  second; SIGTERM, Ctrl-C or an error in the parent stops them first.
* ``resume``: finished shards (checksum file matches) are kept, partial files removed, the rest
  rendered. The manifest is rewritten atomically after every shard.
* ``shard=(K, N)``: runs units ``K-1, K-1+N, ...`` only, for batch schedulers; each part writes
  ``manifest.partK-of-N.json``. Once all parts are in one folder, a run with ``resume`` and no
  ``shard`` finds every shard finished, renders nothing, and writes the full manifest.

Before anything is written the run checks the output path, that no other run writes into the
folder (a lock file; parts share it), and that every pose to render shows some of its CT (the
CT's box projected for every sampled pose: :func:`check_view`). A campaign whose poses or
``center`` put a CT out of view is refused naming the subject and the pose, not rendered as
blank images.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.core.atomic import remove_stale_temps, write_json
from sim.campaign import dataset as ds
from sim.core.errors import InputError
from sim.core.scale import WorkerLost, each_result
from sim.core.seeds import KIND_NOISE, KIND_POSES, KIND_VIRTUAL_PATIENT, rng_for  # the random streams
from sim.core.progress import Progress
from sim.campaign.poses import pose_histogram
from sim.core.outputs import check_output_dir
from sim.ct.volume import CTVolume
from sim.projection.drr import DRRRenderer, RenderSettings
from sim.projection.geometry import pose_from_params, project_points
from sim.projection.scene import load_scene
from sim.physics.imaging import LogImageRenderer

#: A pixel is bone in ``bone_mask`` where the ray crosses at least this much bone (mm).
BONE_MASK_MIN_PATH_MM = 1.0

#: Most worker processes (``--workers``); each loads a CT and Dr.Jit's kernels.
MAX_WORKERS = 256
#: The lock file in the output folder: a run of the whole campaign holds it exclusively, the
#: parts of a campaign (``--shard``) hold it shared.
LOCK_FILE = ".simulate.lock"
#: A projected CT box counts as in view when it reaches this close to the image (pixels).
VIEW_MARGIN_PX = 1.0
#: Poses checked at a time by :func:`visible_poses` (bounds its memory).
_VIEW_CHUNK = 1 << 16
#: The manifest is rewritten at most this often while shards finish (seconds), and at the end.
MANIFEST_EVERY_S = 2.0
#: Most poses drawn in the pose histogram (48 bytes each).
HISTOGRAM_POSES = 2_000_000


class CampaignError(InputError):
    """A campaign cannot run or resume; the message says why and what to do."""


@dataclass(frozen=True)
class Unit:
    """One shard's work: images ``start .. stop - 1`` of subject ``subject``."""

    subject: int
    shard: int
    start: int
    stop: int

    @property
    def name(self) -> str:
        return ds.shard_name(self.subject, self.shard)


def plan_units(cfg) -> list[Unit]:
    """All units of a campaign, in subject order."""
    units = []
    per = cfg.shard_size
    for subject in cfg.subjects():
        for k in range(math.ceil(cfg.images_per_ct / per)):
            units.append(Unit(subject.index, k, k * per, min((k + 1) * per, cfg.images_per_ct)))
    return units


def parse_shard(text: str | None) -> tuple[int, int] | None:
    """``"K/N"`` (1 <= K <= N) to ``(K, N)``; None stays None."""
    if text is None:
        return None
    try:
        k, n = (int(v) for v in str(text).split("/"))
    except ValueError:
        raise CampaignError(f"--shard {text!r}: expected K/N with whole numbers, e.g. 2/8") from None
    if not 1 <= k <= n:
        raise CampaignError(f"--shard {text!r}: need 1 <= K <= N")
    return k, n


def subject_poses(cfg, subject_index: int) -> np.ndarray:
    """``(images_per_ct, 6)`` pose parameters of a subject (deg, mm), independent of sharding."""
    return cfg.poses.sample(rng_for(cfg.seed, KIND_POSES, subject_index), cfg.images_per_ct)


# ----------------------------------------------------------------------------- checks before work
def visible_poses(box_rel_mm: np.ndarray, params: np.ndarray, geometry) -> np.ndarray:
    """Which poses show some of a box: ``(n,)`` bool.

    Args:
        box_rel_mm: ``(m, 3)`` points in LPS mm relative to the anatomy centre (``X - c``)
            whose convex hull holds the CT (its 8 corners minus the centre).
        params: ``(n, 6)`` pose parameters (deg, mm), :func:`sim.projection.geometry.pose_from_params`.
        geometry: the :class:`sim.projection.geometry.CArmGeometry` of the rendered images.

    A pose shows nothing when every point lies at or behind the source plane, or when the
    bounding rectangle of the projected points misses the image (by more than
    :data:`VIEW_MARGIN_PX`). Conservative: a box that straddles the source plane counts as
    visible, so a pose reported as showing nothing renders an all-zero image.
    """

    K = geometry.intrinsics()
    lo_u, hi_u = -0.5 - VIEW_MARGIN_PX, geometry.width - 0.5 + VIEW_MARGIN_PX
    lo_v, hi_v = -0.5 - VIEW_MARGIN_PX, geometry.height - 0.5 + VIEW_MARGIN_PX
    pts = np.asarray(box_rel_mm, dtype=np.float64)
    out = np.empty(len(params), dtype=bool)
    for a in range(0, len(params), _VIEW_CHUNK):
        T = pose_from_params(np.asarray(params[a:a + _VIEW_CHUNK], dtype=np.float64), geometry.sod_mm)
        cam = pts @ np.swapaxes(T[:, :3, :3], -1, -2) + T[:, None, :3, 3]  # (b, m, 3) camera mm
        z = cam[..., 2]
        front = z > 0
        pix = cam @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(front, pix[..., 0] / np.where(front, z, 1.0), np.nan)
            v = np.where(front, pix[..., 1] / np.where(front, z, 1.0), np.nan)
        overlap = ((np.nanmax(u, 1, initial=-np.inf) >= lo_u) & (np.nanmin(u, 1, initial=np.inf) <= hi_u)
                   & (np.nanmax(v, 1, initial=-np.inf) >= lo_v) & (np.nanmin(v, 1, initial=np.inf) <= hi_v))
        straddles = front.any(1) & ~front.all(1)
        out[a:a + _VIEW_CHUNK] = front.any(1) & (straddles | overlap)
    return out


def ct_box_from_header(path: str) -> np.ndarray | None:
    """``(8, 3)`` LPS mm corners of a CT's box read without loading the voxels: the built-in
    phantom's grid, or a NIfTI header. None for a DICOM folder or an unreadable file (the
    worker checks the loaded CT instead)."""
    corners = np.array([[a, b, d] for a in (0, 1) for b in (0, 1) for d in (0, 1)], dtype=np.float64)
    if path.startswith("phantom"):
        import inspect

        from sim.ct.phantom import make_pelvis_phantom  # loads SciPy: imported where first needed (start-up)

        sig = inspect.signature(make_pelvis_phantom).parameters
        spacing = float(sig["spacing_mm"].default)
        n = np.array([round(s / spacing) for s in sig["size_mm"].default], dtype=np.float64)
        return (corners - 0.5) * n * spacing  # the grid centre is the LPS origin
    if not path.lower().endswith((".nii", ".nii.gz")):
        return None
    try:
        import zlib

        import nibabel as nib
        from nibabel.filebasedimages import ImageFileError

        from sim.ct.io import RAS_TO_LPS  # with nibabel, only where a NIfTI header is read

        img = nib.load(path)
        shape = np.array(img.shape[:3], dtype=np.float64)
        affine = RAS_TO_LPS @ np.asarray(img.affine, dtype=np.float64)
    except (OSError, EOFError, ValueError, zlib.error, ImageFileError):  # the worker loads it and says why
        return None
    if len(img.shape) < 3 or not np.all(np.isfinite(affine)):
        return None
    ijk = corners * shape - 0.5
    return ijk @ affine[:3, :3].T + affine[:3, 3]


def _describe_pose(p: np.ndarray) -> str:
    return (f"phi {p[0]:.4g}, theta {p[1]:.4g}, psi {p[2]:.4g} deg, tx {p[3]:.4g}, ty {p[4]:.4g}, "
            f"tz {p[5]:.4g} mm")


def _refuse_view(cfg, subject, params: np.ndarray, visible: np.ndarray, box: np.ndarray,
                 center: np.ndarray | None) -> None:
    bad = np.flatnonzero(~visible)
    if not len(bad):
        return
    k = int(bad[0])
    entry = cfg.cts[subject.ct_index]
    where = (f"the anatomy centre cts[{subject.ct_index}].center = {[float(c) for c in center]} mm"
             if entry.center is not None else "the anatomy centre (derived from the CT)")
    raise CampaignError(
        f"{cfg.source}: cts[{subject.ct_index}] ({entry.path}), subject {subject.name}: pose {k} "
        f"({_describe_pose(params[k])}) shows nothing of the CT ({len(bad)} of the subject's {len(params)} "
        f"poses show nothing): the CT's box (LPS mm {np.round(box.min(0), 1).tolist()} to "
        f"{np.round(box.max(0), 1).tolist()}) lies outside the field of view or behind the source. "
        f"Check [poses] (tx, ty, tz are offsets of {where} from the isocentre) and cts[{subject.ct_index}].center")


def check_view(cfg, subject_indices) -> None:
    """Refuse before rendering when a pose of these subjects shows nothing of its CT.

    Reads each CT's box from its header (:func:`ct_box_from_header`; DICOM folders are left to
    the worker, which checks the loaded CT before rendering it). Without an explicit ``center``
    the centre may lie anywhere in the CT's box, so the box of all ``X - c`` is used: a
    campaign refused here renders blank images whatever the derived centre is.

    Raises:
        CampaignError: naming the campaign file, the ``[[cts]]`` entry, the subject and the pose.
    """

    geometry = load_scene(cfg.scene.name).geometry_at(*cfg.scene.size)
    subjects = cfg.subjects()
    boxes: dict[int, np.ndarray | None] = {}
    for index in sorted(set(subject_indices)):
        subject = subjects[index]
        ci = subject.ct_index
        if ci not in boxes:
            boxes[ci] = ct_box_from_header(cfg.cts[ci].path)
        box = boxes[ci]
        if box is None:
            continue
        center = cfg.cts[ci].center
        rel = (box - np.asarray(center, float) if center is not None
               else (box[:, None, :] - box[None, :, :]).reshape(-1, 3))  # virtual patients share the grid
        params = subject_poses(cfg, index)
        _refuse_view(cfg, subject, params, visible_poses(rel, params, geometry), box, center)


def check_out_path(out: Path) -> None:
    """Refuse an output path that cannot be a campaign folder, before any work (one line each):
    an existing file, a folder under a file, a folder that cannot be written
    (:func:`sim.core.outputs.check_output_dir`), a file where the ``shards`` folder goes."""

    check_output_dir(out, (ds.MANIFEST, "pose_histogram.png"), flag="--out")
    shards = out / ds.SHARD_DIR
    if shards.exists() and not shards.is_dir():
        raise CampaignError(f"--out {out}: {shards} is a file where the folder of shard files goes")


def config_changes(old: dict, new: dict, limit: int = 6) -> str:
    """The keys that differ between two ``CampaignConfig.to_dict()`` tables (``source`` left out),
    as ``"campaign.images_per_ct: 6 -> 5; poses.tz.high: 75.0 -> 80.0"``."""
    changes: list[str] = []

    def walk(a, b, key: str) -> None:
        if isinstance(a, dict) and isinstance(b, dict):
            for k in sorted(set(a) | set(b), key=str):
                if key == "" and k == "source":
                    continue
                sub = f"{key}.{k}" if key else str(k)
                if k not in a:
                    changes.append(f"{sub}: (absent) -> {b[k]!r}")
                elif k not in b:
                    changes.append(f"{sub}: {a[k]!r} -> (absent)")
                else:
                    walk(a[k], b[k], sub)
        elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
            for i, (x, y) in enumerate(zip(a, b)):
                walk(x, y, f"{key}[{i}]")
        elif a != b:
            changes.append(f"{key}: {a!r} -> {b!r}")

    walk(old, new, "")
    if not changes:
        return "no key differs (the config hash recipe changed?)"
    more = f"; and {len(changes) - limit} more" if len(changes) > limit else ""
    return "; ".join(changes[:limit]) + more


class _RunLock:
    """``flock`` on :data:`LOCK_FILE`: exclusive for a whole run, shared for a part."""

    def __init__(self, out: Path, shared: bool):
        self.path, self.shared, self.fd = out / LOCK_FILE, shared, None

    def __enter__(self):
        import fcntl

        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if self.shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise CampaignError(
                f"{self.path.parent}: another `ctxreg simulate` is writing into this folder (the whole "
                "campaign, or parts of it while this is a whole run); wait for it to end or stop it, "
                "then run again with --resume") from None
        except OSError:  # a file system without locks (some network mounts): go on unlocked
            pass
        self.fd = fd
        return self

    def __exit__(self, *exc):
        if self.fd is not None:
            os.close(self.fd)  # releases the lock
            self.fd = None


# ----------------------------------------------------------------------------- worker side
def subject_volume(cfg, subject):
    """A campaign subject's CT (a virtual patient's deformed copy where it is one), its anatomy
    centre (LPS mm) and its virtual-patient parameters (None for a CT itself), without renderers:
    ``(CTVolume, (3,) centre, VirtualPatientParams | None)``."""
    from sim.ct.anatomy import anatomy_center  # loads SciPy: imported where first needed (start-up)
    from sim.ct.io import load_ct_spec  # loads SciPy: imported where first needed (start-up)

    entry = cfg.cts[subject.ct_index]
    volume = load_ct_spec(entry.path, label_map=entry.label_map)
    center = np.asarray(entry.center, float) if entry.center is not None else anatomy_center(volume)
    params = None
    if subject.vp_index is not None:
        from sim.ct.patients import VirtualPatientRanges, make_virtual_patient  # loads SciPy: imported where first needed (start-up)

        ranges = VirtualPatientRanges.from_dict(dict(cfg.virtual_patients))
        params = ranges.sample(rng_for(cfg.seed, KIND_VIRTUAL_PATIENT, subject.ct_index, subject.vp_index))
        volume = make_virtual_patient(volume, params, center_lps=center)
    return volume, center, params


class SubjectContext:
    """A subject's volume, anatomy centre and renderers, built once per worker and subject."""

    def __init__(self, cfg, subject):
        from sim.ct.anatomy import bone_mask  # loads SciPy: imported where first needed (start-up)

        entry = cfg.cts[subject.ct_index]
        volume, center, self.vp_params = subject_volume(cfg, subject)
        self.subject = subject
        self.center = center
        self.volume = volume  # the subject's CT (a virtual patient's deformed copy): for further renderers
        self.source = volume.source
        self.renderers = {}
        for p in cfg.physics:
            if p.level in ("poly", "full"):
                self.renderers[p.name] = LogImageRenderer(volume, p.settings(), scene=cfg.scene.name,
                                                          size=tuple(cfg.scene.size), ray_model=p.ray_model,
                                                          center_lps=center,
                                                          label_materials=dict(entry.label_materials) or None)
                continue
            settings = RenderSettings(scene=cfg.scene.name, size=tuple(cfg.scene.size),
                                      ray_model=p.ray_model, step_fraction=p.step_fraction,
                                      mu_water_per_mm=p.mu_water_per_mm)
            self.renderers[p.name] = DRRRenderer(volume, settings, center_lps=center)
        self.bone = None
        if cfg.outputs.bone_mask:
            mask = bone_mask(volume)
            bone_ct = CTVolume(np.where(mask, 0.0, -1000.0).astype(np.float32), volume.affine,
                               source=f"{volume.source}#bone")
            first = cfg.physics[0]
            self.bone = DRRRenderer(bone_ct, RenderSettings(scene=cfg.scene.name, size=tuple(cfg.scene.size),
                                                            mu_water_per_mm=first.mu_water_per_mm),
                                    center_lps=center)
        self.poses = subject_poses(cfg, subject.index)
        any_renderer = next(iter(self.renderers.values()))
        box = volume.corners_lps()
        _refuse_view(cfg, subject, self.poses, visible_poses(box - center, self.poses, any_renderer.geometry),
                     box, center)

    def metadata(self) -> dict:
        return {
            "index": self.subject.index, "name": self.subject.name, "split": self.subject.split,
            "ct_index": self.subject.ct_index, "vp_index": self.subject.vp_index,
            "source": self.source, "anatomy_center_lps_mm": self.center.tolist(),
            "virtual_patient": None if self.vp_params is None else self.vp_params.to_dict(),
        }


_worker_cfg = None
_worker_ctx: SubjectContext | None = None

#: ``prctl`` option: the signal a process gets when its parent dies (Linux).
_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent_pid: int) -> None:
    """Make this worker die with the process that started it.

    Linux: ``prctl(PR_SET_PDEATHSIG, SIGKILL)``. Everywhere: exit at once if the parent is
    already gone, and a daemon thread that exits within a second once it is.
    """
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != parent_pid:  # died before the prctl
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="ctxreg-parent-watch", daemon=True).start()


def _init_worker(cfg, parent_pid: int | None = None) -> None:
    global _worker_cfg, _worker_ctx
    if parent_pid is not None:
        _die_with_parent(parent_pid)
    _worker_cfg, _worker_ctx = cfg, None


def render_unit(cfg, unit: Unit, out: Path) -> dict:
    """Render one unit and write its shard; returns the manifest entry and subject metadata."""
    global _worker_ctx

    key = (cfg.config_hash(), unit.subject)
    if _worker_ctx is None or _worker_ctx.key != key:
        _worker_ctx = SubjectContext(cfg, cfg.subjects()[unit.subject])
        _worker_ctx.key = key
    ctx = _worker_ctx
    params = ctx.poses[unit.start:unit.stop]
    any_renderer = next(iter(ctx.renderers.values()))
    poses = pose_from_params(params, any_renderer.geometry.sod_mm)
    arrays: dict[str, np.ndarray] = {}
    for k, (name, renderer) in enumerate(ctx.renderers.items()):
        if cfg.physics[k].level in ("poly", "full"):
            rng = rng_for(cfg.seed, KIND_NOISE, unit.subject, unit.shard, k)
            arrays[f"images/{name}"] = renderer.render(poses, seed=int(rng.integers(2**63)))
        else:
            arrays[f"images/{name}"] = renderer.render(poses)
    for k, p in enumerate(cfg.physics):
        if p.level == "line" and not np.any(arrays[f"images/{p.name}"]):
            raise CampaignError(
                f"{cfg.source}: cts[{ctx.subject.ct_index}] ({cfg.cts[ctx.subject.ct_index].path}), subject "
                f"{ctx.subject.name}: all {len(params)} images of shard {unit.name} (poses {unit.start} to "
                f"{unit.stop - 1}, e.g. {_describe_pose(params[0])}) are zero: the rays miss everything "
                f"but air; check [poses] and cts[{ctx.subject.ct_index}].center")
    proj = any_renderer.projection_matrix(poses)
    arrays.update(pose=poses, params=params, projection=proj,
                  image_index=np.arange(unit.start, unit.stop, dtype=np.int64))
    if cfg.outputs.projected_center:
        arrays["projected_center"] = project_points(proj, ctx.center[None])[:, 0, :]
    if ctx.bone is not None:
        path_mm = ctx.bone.render(poses) / cfg.physics[0].mu_water_per_mm
        arrays["bone_mask"] = (path_mm >= BONE_MASK_MIN_PATH_MM).astype(np.uint8)
    attrs = dict(subject=unit.subject, shard=unit.shard, start=unit.start, stop=unit.stop,
                 config_hash=cfg.config_hash(), split=ctx.subject.split, name=ctx.subject.name,
                 seed=cfg.seed, pose_spawn_key=f"{KIND_POSES},{unit.subject}")
    name, digest, size = ds.write_shard(out, unit.subject, unit.shard, arrays, attrs)
    return {"shard": name, "entry": {"subject": unit.subject, "start": unit.start, "stop": unit.stop,
                                     "sha256": digest, "bytes": size},
            "subject": ctx.metadata()}


def _worker_unit(unit: Unit, out: str) -> dict:
    return render_unit(_worker_cfg, unit, Path(out))


# ----------------------------------------------------------------------------- parent side


def _base_manifest(cfg) -> dict:
    return {
        "format": ds.FORMAT,
        "format_version": ds.FORMAT_VERSION,
        "config_hash": cfg.config_hash(),
        "config": cfg.to_dict(),
        "package_versions": ds.package_versions(),
        "subjects": [{"index": s.index, "name": s.name, "split": s.split, "ct_index": s.ct_index,
                      "vp_index": s.vp_index} for s in cfg.subjects()],
        "shards": {},
        "complete": False,
    }


def run_campaign(cfg, out: str | os.PathLike, *, workers: int = 1, resume: bool = False,
                 shard: tuple[int, int] | None = None, progress: bool = True, client=None) -> dict:
    """Run (or resume) a campaign into ``out``; returns the manifest written.

    ``client``: a :class:`distributed.Client` (:func:`sim.core.scale.dask_client`) whose workers render
    the shards instead of ``workers`` local processes: the same units (:func:`render_unit`), seeds
    and bytes; a unit lost with its worker is retried by Dask.

    Everything that can be checked is checked before anything is written: the output path,
    the folder's earlier runs (same campaign, ``resume``), a concurrent run (:data:`LOCK_FILE`)
    and the view of every pose to render (:func:`check_view`). SIGTERM stops the run (and its
    workers) with a :class:`CampaignError`; finished shards are kept for ``resume``.

    Raises:
        CampaignError: ``out`` is a file or cannot be made; it holds another campaign (naming the
            keys that changed) or files without ``resume``; another run writes into it; a pose
            shows nothing of its CT; a worker died; SIGTERM.
    """
    out = Path(out)
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= MAX_WORKERS:
        raise CampaignError(f"--workers must be an integer in [1, {MAX_WORKERS}], got {workers}")
    if client is not None and workers != 1:
        raise CampaignError("--workers and --scheduler: choose one (the scheduler's workers render the shards)")
    check_out_path(out)
    manifest_path = out / ds.MANIFEST
    if out.exists() and any(out.iterdir()) and not resume:
        raise CampaignError(f"{out} is not empty: use --resume to continue a run there, or another --out")
    for existing in sorted(out.glob("manifest*.json")) if out.is_dir() else []:
        old = ds.read_manifest(out, existing.name)
        if old["config_hash"] != cfg.config_hash():
            raise CampaignError(f"{existing} belongs to a different campaign (config hash "
                                f"{old['config_hash'][:12]} != {cfg.config_hash()[:12]}); changed since that "
                                f"run: {config_changes(old.get('config', {}), cfg.to_dict())}; use another "
                                "--out, or undo the change to continue")
    all_units = plan_units(cfg)
    units = all_units if shard is None else all_units[shard[0] - 1::shard[1]]
    mine = None if shard is None else {u.name for u in units}
    finished = {k: v for k, v in ds.finished_shards(out).items() if mine is None or k in mine}
    check_view(cfg, {u.subject for u in units if u.name not in finished})
    out.mkdir(parents=True, exist_ok=True)
    with _RunLock(out, shared=shard is not None), _stop_on_sigterm(out):
        return _run_locked(cfg, out, manifest_path, all_units, units, workers, shard, progress, client)


def _run_locked(cfg, out: Path, manifest_path: Path, all_units: list[Unit], units: list[Unit], workers: int,
                shard: tuple[int, int] | None, progress: bool, client=None) -> dict:
    manifest = _base_manifest(cfg)
    if manifest_path.is_file():  # keep what earlier runs learnt about subjects
        old_subjects = {s["index"]: s for s in ds.read_manifest(out)["subjects"]}
        manifest["subjects"] = [old_subjects.get(s["index"], s) for s in manifest["subjects"]]
    ds.remove_partial_files(out, only=None if shard is None else {u.name for u in units})
    done = ds.finished_shards(out)
    by_name = {u.name: u for u in all_units}
    for name, digest in done.items():
        if name in by_name:
            u = by_name[name]
            manifest["shards"][name] = {"subject": u.subject, "start": u.start, "stop": u.stop,
                                        "sha256": digest, "bytes": (out / ds.SHARD_DIR / name).stat().st_size}
    todo = [u for u in units if u.name not in done]
    target = out / (ds.MANIFEST if shard is None else f"manifest.part{shard[0]}-of-{shard[1]}.json")

    last_write, pending = 0.0, 0  # when the manifest was last written; shards recorded since

    def write_manifest() -> None:
        nonlocal last_write, pending
        _finish(manifest, all_units)
        write_json(target, manifest)
        last_write, pending = time.monotonic(), 0

    def record(result: dict) -> None:
        nonlocal pending
        manifest["shards"][result["shard"]] = result["entry"]
        manifest["subjects"][result["subject"]["index"]] = result["subject"]
        pending += 1
        # rewriting a manifest of n shards after each of n shards is quadratic: at most every
        # MANIFEST_EVERY_S seconds (resume rebuilds it from the shard files anyway), and at the end
        if time.monotonic() - last_write >= MANIFEST_EVERY_S:
            write_manifest()

    write_manifest()
    try:
        if client is not None:
            _render_on_dask(cfg, out, todo, units, client, record, progress)
        else:
            _render_all(cfg, out, todo, units, workers, record, progress)
    finally:
        if pending:
            write_manifest()
    if shard is None and manifest["complete"]:
        _pose_histogram(cfg, out)
    return manifest


def _render_all(cfg, out: Path, todo: list[Unit], units: list[Unit], workers: int, record, progress: bool) -> None:
    """Render the units ``todo`` (of ``units``, this run's share), calling ``record`` with each result."""
    total = sum(u.stop - u.start for u in units)
    bar = Progress(total, total - sum(u.stop - u.start for u in todo), cfg.name, "images",
                   rate_unit="img/s") if progress else None
    if workers == 1 or len(todo) <= 1:
        for unit in todo:
            record(render_unit(cfg, unit, out))
            if bar:
                bar.update(unit.stop - unit.start)
    else:
        import multiprocessing as mp

        pool = ProcessPoolExecutor(max_workers=min(workers, len(todo)), mp_context=mp.get_context("spawn"),
                                   initializer=_init_worker, initargs=(cfg, os.getpid()))
        try:
            futures = {pool.submit(_worker_unit, u, str(out)): u for u in todo}
            for fut in as_completed(futures):
                record(fut.result())
                if bar:
                    bar.update(futures[fut].stop - futures[fut].start)
        except BrokenProcessPool:
            _stop_pool(pool)
            raise CampaignError("a worker process died (killed or out of memory); finished shards "
                                f"are kept in {out}: rerun with --resume") from None
        except BaseException:  # an error, SIGTERM or Ctrl-C: no worker may go on writing
            _stop_pool(pool)
            raise
        pool.shutdown(wait=True)


_DASK_UNIT_LOCK = threading.Lock()


def _dask_unit(cfg, unit: Unit, out: str) -> dict:
    """:func:`render_unit` on a Dask worker: one unit at a time per process (its subject context is
    the process's), whatever the worker's thread count."""
    with _DASK_UNIT_LOCK:
        return render_unit(cfg, unit, Path(out))


def _render_on_dask(cfg, out: Path, todo: list[Unit], units: list[Unit], client, record, progress: bool) -> None:
    """:func:`_render_all` on a Dask cluster: every unit ``todo`` submitted as one task, results
    recorded as they arrive. A task whose worker died is retried by the scheduler; one that kept
    losing its worker (:class:`distributed.KilledWorker`) or raised stops the run, finished shards
    kept for ``--resume``. Temporary files of workers that died are removed at the end."""
    total = sum(u.stop - u.start for u in units)
    bar = Progress(total, total - sum(u.stop - u.start for u in todo), cfg.name, "images",
                   rate_unit="img/s") if progress else None

    def finished(unit: Unit, result: dict) -> None:
        record(result)
        if bar:
            bar.update(unit.stop - unit.start)

    try:
        each_result(client, {u: (_dask_unit, cfg, u, str(out)) for u in todo}, finished)
    except WorkerLost as exc:
        raise CampaignError(f"shard {exc.key.name}: {exc}; finished shards are kept in {out}: rerun with "
                            "--resume") from None
    remove_stale_temps(out / ds.SHARD_DIR)


def _stop_pool(pool: ProcessPoolExecutor, timeout_s: float = 5.0) -> None:
    """Cancel the queued units and end the worker processes now (SIGTERM, then SIGKILL)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:
        with contextlib.suppress(OSError, ValueError):
            p.terminate()
    deadline = time.monotonic() + timeout_s
    for p in procs:
        with contextlib.suppress(OSError, ValueError):
            p.join(max(deadline - time.monotonic(), 0.0))
            if p.is_alive():
                p.kill()
                p.join(1.0)
    pool.shutdown(wait=False, cancel_futures=True)


@contextlib.contextmanager
def _stop_on_sigterm(out: Path):
    """While the run lasts, SIGTERM raises a :class:`CampaignError` in the main thread (so the
    workers are stopped and temporary files removed) instead of killing the process. Left
    alone when not in the main thread or when the program has its own SIGTERM handler."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def handler(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM kills at once
        raise CampaignError(f"stopped by SIGTERM; finished shards are kept in {out}: rerun with --resume")

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _finish(manifest: dict, all_units: list[Unit]) -> None:
    n_done = sum(v["stop"] - v["start"] for v in manifest["shards"].values())
    expected = sum(u.stop - u.start for u in all_units)
    manifest["counts"] = {"images": n_done, "expected": expected, "shards": len(manifest["shards"]),
                          "shards_expected": len(all_units)}
    per_split: dict[str, int] = {}
    subjects = {s["index"]: s for s in manifest["subjects"]}
    for v in manifest["shards"].values():
        split = subjects[v["subject"]]["split"]
        per_split[split] = per_split.get(split, 0) + v["stop"] - v["start"]
    manifest["counts"]["images_per_split"] = dict(sorted(per_split.items()))
    manifest["complete"] = n_done == expected and len(manifest["shards"]) == len(all_units)


def _pose_histogram(cfg, out: Path) -> None:
    """The histogram of every sampled pose, or of the first poses of every subject when the
    campaign has more than :data:`HISTOGRAM_POSES` (a subject's first ``m`` poses do not depend
    on how many it has)."""

    subjects = cfg.subjects()
    m = min(cfg.images_per_ct, max(1, HISTOGRAM_POSES // len(subjects)))
    params = np.concatenate([cfg.poses.sample(rng_for(cfg.seed, KIND_POSES, s.index), m) for s in subjects])
    pose_histogram(params, cfg.poses, out / "pose_histogram.png")
