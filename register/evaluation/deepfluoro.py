"""Registering the DeepFluoro data set's real frames and scoring them as the field does.

Every chosen frame is registered as ``ctxreg register`` registers a file (:func:`register.api.register_xray`,
its defaults: method, network, global search, size), from a start of the protocol's
(:data:`START_MODES`), and scored against the file's ground truth on the specimen's 3-D landmarks:

* **mTRE** (mm): the mean 3-D distance between the landmarks placed by the estimated and by the true
  pose (xvr's ``mTRE``, the field's main number);
* **mPD** (mm): the mean distance between their projections by the two poses, at the detector plane
  (pixels x 0.194 mm; xvr's ``mPE``);
* **mRPE** (mm): the mean distance at the detector between the landmarks projected by the estimated
  pose and the file's annotated 2-D landmarks (those on the detector), which includes the
  annotation's own error (about 1 px, the reprojection check);
* rotation error (deg, geodesic) and translation error of the anatomy centre (mm).

Each error is measured at the start too ("initial"); a frame counts as registered below 10 mm mTRE
(xvr's and ProST's failure threshold) and as sub-millimetre below 1 mm. Per specimen and over all
frames: the mean and median, the shares under 10 mm and 1 mm, initial and final, and the seconds
per frame. Before the first registration the command prints the file's own geometry check (the 3-D
landmarks projected with the file's intrinsics and ground-truth poses against the 2-D landmarks).

Outputs (``out``): ``cases.csv`` (a row per frame and method), ``summary.json``, ``table.md`` and
``worst/``: overlays (the registered DRR's edges in red over the frame) of the worst frames.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from register.api import register_xray
from register.datasets.deepfluoro import DeepFluoroError, DeepFluoroFile, DeepFluoroProjection, DeepFluoroSpecimen
from register.engines.methods import METHOD_NAMES, load_predictor, needs_model
from register.evaluation.errors import pose_errors
from register.evaluation.evaluate import START_MODES, start_params, verdict_rates
from register.plots import overlay_png
from register.xray.prepare import fit_to_size
from register.xray.preprocess import DEFAULT_STEPS
from sim.core.atomic import atomic_path, jsonable, sha256_file, write_csv, write_json
from sim.core.outputs import check_output_dir
from sim.projection.geometry import params_from_pose, pose_from_params, project_points, projection_matrix
from sim.core.progress import Progress
from sim.core.scale import each_result
from sim.core.seeds import KIND_EVALUATE_CASES, rng_for
from sim.projection.drr import DRRRenderer, RenderSettings

__all__ = ["DeepFluoroSettings", "evaluate_deepfluoro", "frame_errors", "START_MODES", "DEEPFLUORO_FILES"]


#: The thresholds the shares are reported at (mm of mTRE).
SUCCESS_MM = (10.0, 1.0)

DEEPFLUORO_FILES = ("cases.csv", "summary.json", "table.md")
#: The rows so far, written after every frame: what ``resume`` continues from.
PROGRESS = "progress.json"

_ERRORS = ("mtre_mm", "mpd_mm", "mrpe_mm", "rot_err_deg", "trans_err_mm")


@dataclass(frozen=True)
class DeepFluoroSettings:
    """The protocol. Units: degrees, mm.

    Attributes:
        specimens: names or numbers 1-6 (empty: every specimen of the file).
        frames: at most this many frames per specimen, the first ones (None: all).
        methods: registration methods (:data:`register.engines.methods.METHOD_NAMES`).
        start: one of :data:`START_MODES`; init: ``(6,)`` the start of ``start="pose"``.
        local_rot_deg, local_trans_mm: the largest offsets of ``start="local"``; seed: their stream.
        sod_mm: the isocentre distance of the start and of the pose parameters (the Cios Fusion's 700).
        size: the optimiser's image box ``(H, W)`` (``register_xray``'s ``size``).
        scene: the C-arm scene of the values the file does not give.
        worst: overlays of this many worst frames (by final mTRE).
        border_px: the collimator's border cut from every side of a frame, in pixels of the
            1536-px detector (DiffPose's 50; scaled to a file's own detector size).
        detect_field: run ``register``'s field detection on the frame left after the border (raw
            frames: :func:`register.xray.field.detect_field` with ``raw=True``, by the collimator's
            edge); False: the whole frame within the border is the field.
    """

    specimens: tuple[str, ...] = ()
    frames: int | None = None
    methods: tuple[str, ...] = ("contextual+cmaes",)
    start: str = "ap"
    init: tuple[float, ...] | None = None
    local_rot_deg: float = 5.0
    local_trans_mm: float = 10.0
    seed: int = 0
    sod_mm: float = 700.0
    size: tuple[int, int] = (128, 128)
    scene: str = "cios_fusion"
    worst: int = 3
    border_px: float = 50.0
    detect_field: bool = True

    def __post_init__(self) -> None:
        if self.start not in START_MODES:
            raise DeepFluoroError(f"start must be one of {', '.join(START_MODES)}, got {self.start!r}")
        if (self.init is not None) != (self.start == "pose"):
            raise DeepFluoroError("--init gives the start of --start pose, and only of it")
        if self.init is not None and (len(self.init) != 6 or not all(math.isfinite(v) for v in self.init)):
            raise DeepFluoroError(f"--init: six finite numbers (deg, mm), got {self.init}")
        if self.frames is not None and self.frames < 1:
            raise DeepFluoroError(f"--frames must be >= 1, got {self.frames}")
        bad = [m for m in self.methods if m not in METHOD_NAMES]
        if bad or not self.methods or len(set(self.methods)) < len(self.methods):
            raise DeepFluoroError(f"methods: distinct names of {', '.join(METHOD_NAMES)}, got {list(self.methods)}")
        if not (math.isfinite(self.sod_mm) and self.sod_mm > 0):
            raise DeepFluoroError(f"sod_mm must be positive, got {self.sod_mm}")
        if not (math.isfinite(self.border_px) and 0 <= self.border_px < 512):
            raise DeepFluoroError(f"border_px must be in [0, 512) px of the 1536-px detector, got {self.border_px}")
        if self.worst < 0:
            raise DeepFluoroError(f"worst must be >= 0, got {self.worst}")


def frame_errors(T_est: np.ndarray, T_true: np.ndarray, frame: DeepFluoroProjection, specimen: DeepFluoroSpecimen,
                 geometry) -> dict[str, float]:
    """The errors of the ctxreg pose ``T_est`` ``(4, 4)`` against ``T_true`` on ``specimen``'s
    landmarks (module docstring); ``geometry`` is the frame's full-resolution ctxreg geometry."""
    names, X = specimen.landmark_array()
    c = specimen.center_lps
    err = pose_errors(T_est, T_true, X, c, geometry)
    annotated = [n for n in names if n in frame.landmarks_px]
    uv = frame.to_ctxreg_px(np.array([frame.landmarks_px[n] for n in annotated]).reshape(-1, 2))
    on = frame.visible(uv)  # (the flip keeps the detector's extent)
    Xa = np.array([specimen.landmarks_lps[n] for n in annotated]).reshape(-1, 3)[on]
    if len(Xa):
        est = project_points(projection_matrix(geometry, T_est, c), Xa)
        rpe = np.linalg.norm(est - uv[on], axis=1)
        rpe = rpe[np.isfinite(rpe)]
        err["mrpe_mm"] = float(rpe.mean() * geometry.pixel_spacing_mm) if rpe.size else math.nan
    else:
        err["mrpe_mm"] = math.nan
    return err


def _starts(settings: DeepFluoroSettings, truths: np.ndarray) -> np.ndarray:
    """``(N, 6)`` start parameters for the ``(N, 6)`` true parameters (:func:`register.evaluation.evaluate.start_params`)."""
    return start_params(settings.start, truths, rng_for(settings.seed, KIND_EVALUATE_CASES), init=settings.init,
                        local_rot_deg=settings.local_rot_deg, local_trans_mm=settings.local_trans_mm)


def _stats(values) -> dict[str, float]:
    v = np.array([x for x in values if math.isfinite(x)], np.float64)
    if not v.size:
        return {"mean": math.nan, "median": math.nan, "min": math.nan, "max": math.nan}
    return {"mean": float(v.mean()), "median": float(np.median(v)), "min": float(v.min()), "max": float(v.max())}


def summarize(rows: list[dict]) -> dict:
    """Per method, per specimen and ``"all"``: frames, each error's statistics (initial and final),
    the shares of mTRE under :data:`SUCCESS_MM` (initial and final) and the seconds per frame."""
    out: dict = {}
    for method in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == method]
        groups = {s: [r for r in sel if r["specimen"] == s] for s in dict.fromkeys(r["specimen"] for r in sel)}
        groups["all"] = sel
        out[method] = {}
        for name, rs in groups.items():
            g = {"frames": len(rs), "time_s": _stats(r["time_s"] for r in rs)}
            for col in _ERRORS:
                g[col] = _stats(r[col] for r in rs)
                g[f"initial_{col}"] = _stats(r[f"initial_{col}"] for r in rs)
            g.update(verdict_rates(rs, 10.0))
            for mm in SUCCESS_MM:
                g[f"under_{mm:g}mm"] = float(np.mean([r["mtre_mm"] < mm for r in rs]))
                g[f"initial_under_{mm:g}mm"] = float(np.mean([r["initial_mtre_mm"] < mm for r in rs]))
            out[method][name] = g
    return out


def format_table(summary: dict) -> str:
    """The summary as a Markdown table: a row per method and specimen."""
    lines = ["| method | specimen | frames | mTRE initial -> final, median (mm) | mean (mm) | < 10 mm initial -> final "
             "| < 1 mm | mPD median (mm) | mRPE median (mm) | rotation median (deg) | s / frame | registered within "
             "10 mm | registered further off |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for method, groups in summary.items():
        for name, g in groups.items():
            accepted = "-" if not g.get("within") else f"{100 * g['accepted']:.0f} %"
            lines.append(
                f"| {method} | {name} | {g['frames']} | {g['initial_mtre_mm']['median']:.1f} -> "
                f"{g['mtre_mm']['median']:.2f} | {g['mtre_mm']['mean']:.2f} | {100 * g['initial_under_10mm']:.0f} % -> "
                f"{100 * g['under_10mm']:.0f} % | {100 * g['under_1mm']:.0f} % | {g['mpd_mm']['median']:.2f} | "
                f"{g['mrpe_mm']['median']:.2f} | {g['rot_err_deg']['median']:.2f} | {g['time_s']['median']:.1f} | "
                f"{accepted} | {g.get('false_accepts', 0)} of {g.get('off', 0)} |")
    return "\n".join(lines)


def _overlay(path: Path, frame: DeepFluoroProjection, specimen: DeepFluoroSpecimen, T: np.ndarray, geometry,
             side: int = 384) -> None:
    """The frame (as a log image, at most ``side`` px) with the line DRR's edges at ``T`` in red."""

    raw = frame.ctxreg_pixels().astype(np.float64)
    log_image = -np.log(np.clip(raw, max(float(raw.max()) * 1e-6, 1e-12), None))
    image, _, g = fit_to_size(log_image, None, geometry, min(side, max(geometry.height, geometry.width)))
    drr = DRRRenderer(specimen.volume, RenderSettings(size=(g.height, g.width)), center_lps=specimen.center_lps,
                      geometry=g).render(T)[0]
    overlay_png(image, drr, path)


def _progress_record(path, settings: DeepFluoroSettings, model) -> dict:
    """What a resumed run must share with the run it continues: the file (by its path and its
    content's SHA-256: a file changed in place, even at the same size, is another run), the
    settings, the model."""
    p = Path(path)
    return {"file": str(p.resolve()), "file_sha256": sha256_file(p) if p.is_file() else None,
            "settings": json.loads(json.dumps(asdict(settings))),
            "model": None if model is None else (str(model) if not callable(model) else type(model).__name__)}


def _resumed_rows(out: Path, record: dict) -> list[dict]:
    """The rows of ``out/PROGRESS`` when its record matches ``record``; else :class:`DeepFluoroError`."""
    f = out / PROGRESS
    if not f.exists():
        raise DeepFluoroError(f"--resume: {f} not found: nothing to resume (run without --resume)")
    try:
        saved = json.loads(f.read_text())
        rows = saved["rows"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DeepFluoroError(f"--resume: {f} cannot be read ({exc}); run without --resume to start again") from None
    problem = _rows_problem(rows)
    if problem or not isinstance(saved.get("settings"), dict):
        raise DeepFluoroError(f"--resume: {f} is damaged ({problem or 'its settings are not a table'}); run without "
                              "--resume to start again")
    differ = [k for k in record if k != "settings" and saved.get(k) != record[k]]
    differ += [f"settings.{k}" for k, v in record["settings"].items() if saved.get("settings", {}).get(k) != v]
    if differ:
        raise DeepFluoroError(f"--resume: {f} was written by another run (differs in {', '.join(differ)}); run "
                              f"without --resume, or with the same file, options and model")
    return rows


#: What every row of ``progress.json`` holds (and its type), as :func:`_register_frame` writes it.
_ROW_TYPES = {"specimen": str, "frame": int, "method": str, "mtre_mm": float, "initial_mtre_mm": float,
              "time_s": float, "pose": list}


def _rows_problem(rows) -> str | None:
    """What is wrong with the rows of a ``progress.json`` (None: nothing)."""
    if not isinstance(rows, list):
        return f"its rows are {type(rows).__name__}, not a list"
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            return f"row {i} is {type(row).__name__}, not a table"
        for key, kind in _ROW_TYPES.items():
            value = row.get(key)
            ok = (isinstance(value, (int, float)) and not isinstance(value, bool) if kind is float
                  else isinstance(value, kind) and not isinstance(value, bool))
            if not ok:
                return f"row {i} has no {key} of type {kind.__name__} (got {value!r})"
    return None


_SPECIMENS: dict = {}  # (file, specimen) -> DeepFluoroSpecimen with its CT: one per process


def _specimen(f: DeepFluoroFile, sid: str) -> DeepFluoroSpecimen:
    """Specimen ``sid`` of ``f`` with its CT, read once per process (one specimen's CT kept at a time)."""
    key = (str(f.path.resolve()), sid)
    if key not in _SPECIMENS:
        _SPECIMENS.clear()
        _SPECIMENS[key] = f.specimen(sid)
    return _SPECIMENS[key]


def _register_frame(f: DeepFluoroFile, sid: str, index: int, start, methods: tuple[str, ...],
                    settings: DeepFluoroSettings, predictor, border: int, steps: list[str]) -> list[dict]:
    """Frame ``index`` of specimen ``sid`` registered from ``start`` ``(6,)`` by each of ``methods``:
    its rows (errors at the start and the end, seconds, the pose)."""
    spec = _specimen(f, sid)
    fr = spec.projection(index)
    T_true, geometry = fr.truth(spec.center_lps, sod_mm=settings.sod_mm)
    initial = frame_errors(pose_from_params(start, settings.sod_mm), T_true, fr, spec, geometry)
    out = []
    for method in methods:
        t0 = time.perf_counter()
        reg = register_xray(spec.volume, fr.xray(sod_mm=settings.sod_mm, border_px=border), method=method,
                            model=predictor if needs_model(method) else None, init=start, center=spec.center_lps,
                            scene=settings.scene, size=settings.size, intensity="linear", polarity="bone-dark",
                            preprocess=steps)
        seconds = time.perf_counter() - t0
        err = frame_errors(reg.pose, T_true, fr, spec, geometry)
        out.append({"specimen": spec.id, "frame": fr.index, "method": method, "start": settings.start,
                    "rot_180_for_up": fr.rot_180_for_up, **err, **{f"initial_{k}": v for k, v in initial.items()},
                    "time_s": seconds, "renders": reg.result.renders, "similarity": reg.similarity,
                    "search": reg.search_status, "verdict": reg.verdict.label,
                    **{f"true_{k}": float(v) for k, v in zip(("phi", "theta", "psi", "tx", "ty", "tz"),
                                                             params_from_pose(T_true, settings.sod_mm))},
                    **{f"est_{k}": float(v) for k, v in reg.params.items()}, "pose": np.asarray(reg.pose).tolist()})
    return out


_WORKER_STATE: dict = {}  # the open file and the network of a Dask worker


def _dask_frame(path: str, sid: str, index: int, start, methods, settings: DeepFluoroSettings, model, border: int,
                steps: list[str]) -> list[dict]:
    """:func:`_register_frame` on a Dask worker: the file opened and the network loaded once per process."""
    if _WORKER_STATE.get("path") != path:
        if "file" in _WORKER_STATE:
            _WORKER_STATE["file"].close()
        _WORKER_STATE.update(path=path, file=DeepFluoroFile(path))
    if "predictor" not in _WORKER_STATE or not (_WORKER_STATE["model"] is model or _WORKER_STATE["model"] == model):
        _WORKER_STATE.update(model=model, predictor=None)
    if _WORKER_STATE["predictor"] is None and any(needs_model(m) for m in methods):
        _WORKER_STATE["predictor"] = load_predictor(model)
    return _register_frame(_WORKER_STATE["file"], sid, index, start, methods, settings, _WORKER_STATE["predictor"],
                           border, steps)


def evaluate_deepfluoro(path, settings: DeepFluoroSettings, out, *, model=None, resume: bool = False,
                        log: Callable[[str], None] = print, client=None) -> dict:
    """Register the chosen frames of the DeepFluoro file ``path`` and write the scores into ``out``
    (module docstring). ``model``: the contextual methods' network (a name, a checkpoint or a loaded
    predictor; None: the shipped default). After every frame the rows so far are kept in
    ``out/progress.json``; ``resume=True`` continues a run from there (same file, settings and model).
    ``client``: a :class:`distributed.Client` (:func:`sim.core.scale.dask_client`) whose workers register
    the frames (each opens the file, which they must see, and loads the network once; ``model`` then a
    name or a path); the rows are kept in the plan's order. Returns ``{"rows", "summary", "table",
    "reprojection"}``."""
    out = check_output_dir(out, DEEPFLUORO_FILES + (PROGRESS,))
    record = _progress_record(path, settings, model)
    rows = _resumed_rows(out, record) if resume else []
    done = {(r["specimen"], int(r["frame"]), r["method"]) for r in rows}
    with DeepFluoroFile(path) as f:
        # a specimen named twice (by number and by name) is registered once
        chosen = list(dict.fromkeys(f.resolve(s) for s in settings.specimens)) or list(f.specimens)
        p = f.params
        cx, cy = p.principal_point
        if abs(cx - (p.cols - 1) / 2) > 0.5 or abs(cy - (p.rows - 1) / 2) > 0.5:
            raise DeepFluoroError(f"{path}: the principal point ({cx:g}, {cy:g}) px is off the detector's centre "
                                  f"({(p.cols - 1) / 2:g}, {(p.rows - 1) / 2:g}); ctxreg register takes the centre")
        border = int(round(settings.border_px * p.cols / 1536.0))
        steps = [step for step in DEFAULT_STEPS if settings.detect_field or step != "field"]
        log(f"{path}: {len(f.specimens)} specimens ({', '.join(f.specimens)}); detector {p.rows} x {p.cols} px at "
            f"{p.spacing_mm:g} mm, SDD {p.sdd_mm:.1f} mm; {border} px of collimator border cut from each side, field "
            f"detection {'on' if settings.detect_field else 'off'}")
        # the file's own geometry, before any registration: landmarks reprojected with the truth
        plan, reprojection = [], {}
        for sid in chosen:
            light = f.specimen(sid, ct=False)
            names = light.projection_names[: settings.frames] if settings.frames else light.projection_names
            checks = [light.projection(int(n), pixels=False).reprojection_px(light.landmarks_lps) for n in names]
            counted = [c for c in checks if c["count"]]
            reprojection[sid] = {
                "frames": len(names), "landmarks": int(sum(c["count"] for c in checks)),
                "stored_mean_px": float(np.mean([c["stored_mean_px"] for c in counted])) if counted else math.nan,
                "stored_max_px": float(max(c["stored_max_px"] for c in counted)) if counted else math.nan,
                "ctxreg_mean_px": float(np.mean([c["ctxreg_mean_px"] for c in counted])) if counted else math.nan}
            r = reprojection[sid]
            log(f"geometry check, specimen {sid}: 3-D landmarks projected with the file's intrinsics and ground-truth "
                f"poses land {r['stored_mean_px']:.3f} px (max {r['stored_max_px']:.3f} px) from its 2-D landmarks "
                f"({r['landmarks']} on {len(names)} frames); through ctxreg's pose and geometry "
                f"{r['ctxreg_mean_px']:.3f} px")
            plan.append((sid, [int(n) for n in names]))
        predictor = load_predictor(model) if any(needs_model(m) for m in settings.methods) else None
        total = sum(len(idx) for _, idx in plan) * len(settings.methods)
        if done:
            log(f"resuming: {len(done)} of {total} registrations done ({out / PROGRESS})")
        bar = Progress(total, len(done), f"deepfluoro {out.name}", "frames", rate_unit="frames/min", rate_scale=60.0)
        jobs = []  # (specimen, frame, start, methods left), in the plan's order
        for sid, indices in plan:
            if all((sid, i, m) in done for i in indices for m in settings.methods):
                continue
            light = f.specimen(sid, ct=False)
            centre = _specimen(f, sid).center_lps if settings.start in ("local", "truth") else None
            truths = np.array([params_from_pose(light.projection(i, pixels=False).truth(centre, sod_mm=settings.sod_mm)[0],
                                                settings.sod_mm) for i in indices]) if centre is not None \
                else np.zeros((len(indices), 6))
            for i, start in zip(indices, _starts(settings, truths)):
                left = tuple(m for m in settings.methods if (sid, i, m) not in done)
                if left:
                    jobs.append((sid, i, start, left))

        def finished(new_rows: list[dict]) -> None:
            rows.extend(new_rows)
            for row in new_rows:
                log(f"{row['specimen']} frame {row['frame']:03d} {row['method']}: mTRE {row['initial_mtre_mm']:.1f} -> "
                    f"{row['mtre_mm']:.2f} mm, rotation {row['rot_err_deg']:.2f} deg, mRPE {row['mrpe_mm']:.2f} mm, "
                    f"{row['time_s']:.1f} s")
            bar.update(len(new_rows))
            write_json(out / PROGRESS, jsonable({**record, "rows": rows}))

        if client is None:
            for sid, i, start, left in jobs:
                finished(_register_frame(f, sid, i, start, left, settings, predictor, border, steps))
        else:
            each_result(client, {n: (_dask_frame, str(Path(path).resolve()), sid, i, start, left, settings, model,
                                     border, steps) for n, (sid, i, start, left) in enumerate(jobs)},
                        lambda _n, new_rows: finished(new_rows))
        order = {key: n for n, key in enumerate((sid, i) for sid, indices in plan for i in indices)}
        methods = {m: k for k, m in enumerate(settings.methods)}
        rows.sort(key=lambda r: (order[(r["specimen"], int(r["frame"]))], methods[r["method"]]))
        records = [(r["mtre_mm"], r["specimen"], int(r["frame"]), np.array(r["pose"]), r["method"]) for r in rows]
        worst = sorted(records, key=lambda r: -r[0] if math.isfinite(r[0]) else -math.inf)[: settings.worst]
        if worst:
            (out / "worst").mkdir(parents=True, exist_ok=True)
        for sid in dict.fromkeys(w[1] for w in worst):
            spec = f.specimen(sid)
            for _, _, index, T, method in (w for w in worst if w[1] == sid):
                fr = spec.projection(index)
                T_true, geometry = fr.truth(spec.center_lps, sod_mm=settings.sod_mm)
                stem = f"{sid}_{index:03d}_{method.replace('+', '-')}"
                _overlay(out / "worst" / f"{stem}_estimate.png", fr, spec, T, geometry)
                _overlay(out / "worst" / f"{stem}_truth.png", fr, spec, T_true, geometry)
    summary = summarize(rows)
    table = format_table(summary)
    write_csv(out / "cases.csv", [{k: v for k, v in r.items() if k != "pose"} for r in rows])
    write_json(out / "summary.json", jsonable({"file": str(path), "settings": asdict(settings),
                                               "success_mm": list(SUCCESS_MM), "reprojection_px": reprojection,
                                               "summary": summary}))
    with atomic_path(out / "table.md") as tmp:
        tmp.write_text(table + "\n")
    return {"rows": rows, "summary": summary, "table": table, "reprojection": reprojection}
