"""Running a campaign: work units, worker processes, resume, and shards of the work.

The work of a campaign is a list of units, one per shard file: subject (a CT or a virtual
patient), shard index and image range. Every random draw is keyed by the campaign seed and the
unit's indices (see :func:`rng_for`), so a unit renders the same images whichever process
runs it, in whatever order, after whatever interruption.

* ``workers > 1``: units run in spawned worker processes (Dr.Jit is not fork-safe), grouped by
  subject so a worker loads each CT once. A worker that dies (killed, out of memory) stops the
  run with an error; finished shards are kept.
* ``resume``: finished shards (checksum file matches) are kept, partial files removed, the rest
  rendered. The manifest is rewritten atomically after every shard.
* ``shard=(K, N)``: runs units ``K-1, K-1+N, ...`` only, for batch schedulers; each part writes
  ``manifest.partK-of-N.json``. Once all parts are in one folder, a run with ``resume`` and no
  ``shard`` finds every shard finished, renders nothing, and writes the full manifest.
"""

from __future__ import annotations

from sim.errors import InputError

import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.atomic import write_json
from sim.campaign import dataset as ds

#: Spawn keys of the random streams (with the subject / CT / image indices after them).
KIND_POSES, KIND_VIRTUAL_PATIENT = 0, 1
#: Spawn key of a shard's noise stream (poly physics): ``(KIND_NOISE, subject, shard)``.
KIND_NOISE = 4

#: A pixel is bone in ``bone_mask`` where the ray crosses at least this much bone (mm).
BONE_MASK_MIN_PATH_MM = 1.0


class CampaignError(InputError):
    """A campaign cannot run or resume; the message says why and what to do."""


def rng_for(seed: int, *key: int) -> np.random.Generator:
    """The random stream for one purpose: ``SeedSequence(seed, spawn_key=key)``."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(entropy=seed, spawn_key=key)))


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


# ----------------------------------------------------------------------------- worker side
class SubjectContext:
    """A subject's volume, anatomy centre and renderers, built once per worker and subject."""

    def __init__(self, cfg, subject):
        from sim.anatomy import anatomy_center, bone_mask
        from sim.ct_io import load_ct_spec
        from sim.render import DRRRenderer, RenderSettings
        from sim.volume import CTVolume

        entry = cfg.cts[subject.ct_index]
        volume = load_ct_spec(entry.path, label_map=entry.label_map)
        center = np.asarray(entry.center, float) if entry.center is not None else anatomy_center(volume)
        self.vp_params = None
        if subject.vp_index is not None:
            from sim.augment import VirtualPatientRanges, make_virtual_patient

            ranges = VirtualPatientRanges.from_dict(dict(cfg.virtual_patients))
            self.vp_params = ranges.sample(rng_for(cfg.seed, KIND_VIRTUAL_PATIENT, subject.ct_index,
                                                   subject.vp_index))
            volume = make_virtual_patient(volume, self.vp_params, center_lps=center)
        self.subject = subject
        self.center = center
        self.source = volume.source
        self.renderers = {}
        for p in cfg.physics:
            if p.level in ("poly", "full"):
                from sim.physics.imaging import LogImageRenderer

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

    def metadata(self) -> dict:
        return {
            "index": self.subject.index, "name": self.subject.name, "split": self.subject.split,
            "ct_index": self.subject.ct_index, "vp_index": self.subject.vp_index,
            "source": self.source, "anatomy_center_lps_mm": self.center.tolist(),
            "virtual_patient": None if self.vp_params is None else self.vp_params.to_dict(),
        }


_worker_cfg = None
_worker_ctx: SubjectContext | None = None


def _init_worker(cfg) -> None:
    global _worker_cfg, _worker_ctx
    _worker_cfg, _worker_ctx = cfg, None


def render_unit(cfg, unit: Unit, out: Path) -> dict:
    """Render one unit and write its shard; returns the manifest entry and subject metadata."""
    global _worker_ctx
    from sim.geometry import pose_from_params, project_points

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
class Progress:
    """Images done, rate and ETA on stderr: in place on a terminal, else a line every 5 s."""

    def __init__(self, total: int, done: int, label: str):
        self.total, self.done, self.label = total, done, label
        self.start_done, self.t0, self.last = done, time.monotonic(), 0.0
        self.tty = sys.stderr.isatty()
        self.show(force=True)

    def update(self, n: int) -> None:
        self.done += n
        self.show(force=self.done >= self.total)

    def show(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self.last < (0.2 if self.tty else 5.0):
            return
        self.last = now
        rate = (self.done - self.start_done) / max(now - self.t0, 1e-9)
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        pct = 100.0 * self.done / max(self.total, 1)
        eta_text = "--" if not math.isfinite(eta) else time.strftime("%H:%M:%S", time.gmtime(eta))
        line = (f"{self.label}: {self.done}/{self.total} images ({pct:5.1f} %), "
                f"{rate:6.1f} img/s, ETA {eta_text}")
        print(("\r" + line) if self.tty else line, end="" if self.tty else "\n", file=sys.stderr,
              flush=True)
        if self.tty and self.done >= self.total:
            print(file=sys.stderr)


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
                 shard: tuple[int, int] | None = None, progress: bool = True) -> dict:
    """Run (or resume) a campaign into ``out``; returns the manifest written.

    Raises:
        CampaignError: ``out`` holds another campaign or files without ``resume``; a worker died.
    """
    out = Path(out)
    if workers < 1:
        raise CampaignError(f"--workers must be >= 1, got {workers}")
    manifest_path = out / ds.MANIFEST
    if out.exists() and any(out.iterdir()) and not resume:
        raise CampaignError(f"{out} is not empty: use --resume to continue a run there, or another --out")
    for existing in sorted(out.glob("manifest*.json")) if out.is_dir() else []:
        old = ds.read_manifest(out, existing.name)
        if old["config_hash"] != cfg.config_hash():
            raise CampaignError(f"{existing} belongs to a different campaign (config hash "
                                f"{old['config_hash'][:12]} != {cfg.config_hash()[:12]}): the campaign "
                                "file changed since that run; use another --out")
    out.mkdir(parents=True, exist_ok=True)
    manifest = _base_manifest(cfg)
    if manifest_path.is_file():  # keep what earlier runs learnt about subjects
        old_subjects = {s["index"]: s for s in ds.read_manifest(out)["subjects"]}
        manifest["subjects"] = [old_subjects.get(s["index"], s) for s in manifest["subjects"]]
    all_units = plan_units(cfg)
    units = all_units if shard is None else all_units[shard[0] - 1::shard[1]]
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

    def record(result: dict) -> None:
        manifest["shards"][result["shard"]] = result["entry"]
        manifest["subjects"][result["subject"]["index"]] = result["subject"]
        _finish(manifest, all_units)
        write_json(target, manifest)

    _finish(manifest, all_units)
    write_json(target, manifest)
    total = sum(u.stop - u.start for u in units)
    bar = Progress(total, total - sum(u.stop - u.start for u in todo), cfg.name) if progress else None
    if workers == 1 or len(todo) <= 1:
        for unit in todo:
            record(render_unit(cfg, unit, out))
            if bar:
                bar.update(unit.stop - unit.start)
    else:
        import multiprocessing as mp

        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                                 initializer=_init_worker, initargs=(cfg,)) as pool:
            futures = {pool.submit(_worker_unit, u, str(out)): u for u in todo}
            try:
                for fut in as_completed(futures):
                    record(fut.result())
                    if bar:
                        bar.update(futures[fut].stop - futures[fut].start)
            except BrokenProcessPool:
                raise CampaignError("a worker process died (killed or out of memory); finished shards "
                                    f"are kept in {out}: rerun with --resume") from None
    if shard is None and manifest["complete"]:
        _pose_histogram(cfg, out)
    return manifest


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
    from sim.campaign.poses import pose_histogram

    params = np.concatenate([subject_poses(cfg, s.index) for s in cfg.subjects()])
    pose_histogram(params, cfg.poses, out / "pose_histogram.png")
