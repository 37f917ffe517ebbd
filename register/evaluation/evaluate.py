"""The evaluation protocol: sampled target poses, registration from a start, errors against truth.

For a CT, ``cases`` target poses are drawn (seeded) from a pose distribution (default: the
original protocol, rotations +-40/+-20/+-20 deg and translations +-75 mm), their DRRs rendered
as the "X-rays", and every method started at AP (``start="ap"``) or near the truth
(``start="local"``: a random offset of at most ``local_rot_deg`` / ``local_trans_mm``).
Errors per case:

* rotation error: geodesic angle of ``R_est^T R_true`` (degrees);
* translation error: ``|t_est - t_true|``, the anatomy centre's displacement (mm);
* mTRE: mean 3-D distance between bone points (voxel centres of the bone mask, at most
  ``max_points``) placed by the two poses (mm);
* mPD: mean distance between their projections on the detector (mm at the detector plane);
* success: mTRE < ``success_mtre_mm`` and rotation error < ``success_rot_deg``.

Methods are plug-ins (:class:`register.engines.methods.RegistrationMethod`, built by
:func:`register.engines.methods.build_method`): anything with ``name`` and
``register(fixed (H, W), init_params (6,)) -> RegistrationResult``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from register.engines.methods import RegistrationMethod, build_method, load_predictor, needs_model
from register.evaluation.errors import bone_points, pose_errors
from register.verdict import judge_result
from sim.core.atomic import atomic_path, save_figure, write_csv, write_json
from sim.campaign.poses import ORIGINAL_PROTOCOL
from sim.core.cliargs import Range
from sim.ct.io import load_ct_spec
from sim.core.errors import InputError
from sim.projection.geometry import pose_from_params
from sim.core.progress import Progress
from sim.core.scale import each_result
from sim.core.seeds import KIND_EVALUATE_CASES, rng_for

#: ``ap``: ctxreg's AP pose; ``pose``: ``init``; ``local``: the truth moved by a seeded random offset;
#: ``truth``: the truth itself (a check: a method must stay there).
START_MODES = ("ap", "pose", "local", "truth")
#: The largest start offsets of ``start="local"`` a protocol may ask for: rotation (deg) and
#: translation (mm). Beyond them "local" means nothing (the original capture range is 40 deg, 75 mm).
LOCAL_ROT_DEG = Range(0.0, 90.0, lo_open=True)
LOCAL_TRANS_MM = Range(0.0, 500.0, lo_open=True)
ERROR_COLUMNS = ("rot_err_deg", "trans_err_mm", "mtre_mm", "mpd_mm")


class EvaluationError(InputError):
    """Bad evaluation settings; the message names the setting."""


@dataclass(frozen=True)
class EvaluationSettings:
    """Units: degrees, mm. ``local_rot_deg`` in :data:`LOCAL_ROT_DEG`, ``local_trans_mm`` in
    :data:`LOCAL_TRANS_MM`."""

    cases: int = 20
    seed: int = 0
    size: tuple[int, int] = (128, 128)
    start: str = "ap"
    local_rot_deg: float = 5.0
    local_trans_mm: float = 10.0
    success_mtre_mm: float = 10.0
    success_rot_deg: float = 1.0
    max_points: int = 5000
    init: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.cases < 1:
            raise EvaluationError(f"cases must be >= 1, got {self.cases}")
        if self.start not in START_MODES:
            raise EvaluationError(f"start must be one of {START_MODES}, got {self.start!r}")
        if (self.init is not None) != (self.start == "pose"):
            raise EvaluationError("init gives the start of start='pose', and only of it")
        if self.init is not None and (len(self.init) != 6 or not np.all(np.isfinite(self.init))):
            raise EvaluationError(f"init: six finite numbers (deg, mm), got {self.init}")
        for name, bounds in (("local_rot_deg", LOCAL_ROT_DEG), ("local_trans_mm", LOCAL_TRANS_MM)):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) in bounds):
                raise EvaluationError(f"{name} must be {bounds}, got {getattr(self, name)}")
        for name in ("success_mtre_mm", "success_rot_deg"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise EvaluationError(f"{name} must be positive, got {getattr(self, name)}")
        if self.seed < 0:
            raise EvaluationError(f"seed must be >= 0, got {self.seed}")


def start_params(start: str, targets: np.ndarray, rng: np.random.Generator, *, init=None, local_rot_deg: float = 5.0,
                 local_trans_mm: float = 10.0) -> np.ndarray:
    """``(N, 6)`` start parameters (deg, mm) for the ``(N, 6)`` true ``targets`` (:data:`START_MODES`):
    ``ap`` zeros, ``pose`` ``init`` ``(6,)`` for every case, ``truth`` the targets, ``local`` the targets
    moved by offsets drawn from ``rng``, rotation and translation apart, each in a uniform direction
    with a uniform norm: at most ``local_rot_deg / sqrt(3)`` for the three angles (deg) and
    ``local_trans_mm`` for the three translations (mm)."""
    targets = np.asarray(targets, np.float64).reshape(-1, 6)
    if start == "ap":
        return np.zeros_like(targets)
    if start == "pose":
        return np.tile(np.asarray(init, np.float64), (len(targets), 1))
    if start == "truth":
        return targets.copy()

    def ball(radius):
        v = rng.normal(size=(len(targets), 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        return v * rng.uniform(0, radius, size=(len(targets), 1))

    return targets + np.concatenate([ball(local_rot_deg / np.sqrt(3)), ball(local_trans_mm)], axis=1)


def sample_cases(settings: EvaluationSettings, distribution=None) -> tuple[np.ndarray, np.ndarray]:
    """``(targets (N, 6), starts (N, 6))`` pose parameters (deg, mm), seeded."""
    dist = distribution or ORIGINAL_PROTOCOL

    rng = rng_for(settings.seed, KIND_EVALUATE_CASES)
    targets = dist.sample(rng, settings.cases)
    return targets, start_params(settings.start, targets, rng, init=settings.init, local_rot_deg=settings.local_rot_deg,
                                 local_trans_mm=settings.local_trans_mm)


def verdict_rates(rows: list[dict], within_mm: float) -> dict:
    """How the verdicts (``rows[i]["verdict"]``; rows without one are left out) match the truth
    (``mtre_mm``): ``accepted`` the share of the registrations within ``within_mm`` called
    ``registered``, ``false_accepts`` the number further off called ``registered`` (the one count
    that must be 0), with the counts of each (``within``, ``off``) and of each verdict."""
    judged = [r for r in rows if r.get("verdict")]
    within = [r for r in judged if r["mtre_mm"] < within_mm]
    off = [r for r in judged if not r["mtre_mm"] < within_mm]
    return {"within": len(within), "off": len(off),
            "accepted": float(np.mean([r["verdict"] == "registered" for r in within])) if within else float("nan"),
            "false_accepts": sum(r["verdict"] == "registered" for r in off),
            "verdicts": {label: sum(r["verdict"] == label for r in judged) for label in ("registered", "doubtful",
                                                                                       "failed")}}


def summarize(rows: list[dict], settings: EvaluationSettings) -> dict:
    """Per method: mean, std, median, min, max of each error, success rates, time."""
    out = {}
    for method in sorted({r["method"] for r in rows}):
        sel = [r for r in rows if r["method"] == method]
        stats = {}
        for col in ERROR_COLUMNS + ("time_s",):
            v = np.array([r[col] for r in sel], float)
            stats[col] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
                          "median": float(np.median(v)), "min": float(v.min()), "max": float(v.max())}
        stats["success_mtre"] = float(np.mean([r["mtre_mm"] < settings.success_mtre_mm for r in sel]))
        stats["success_rot"] = float(np.mean([r["rot_err_deg"] < settings.success_rot_deg for r in sel]))
        stats["success"] = float(np.mean([r["success"] for r in sel]))
        stats.update(verdict_rates(sel, settings.success_mtre_mm))
        stats["cases"] = len(sel)
        stats["refused"] = sum(1 for r in sel if r.get("refused"))  # frames the registration refused (study)
        out[method] = stats
    return out


def format_table(summary: dict, settings: EvaluationSettings) -> str:
    """The summary in the form of the original Table 3.1 (Markdown)."""
    lines = ["| method | error | mean | std | median | min | max |", "|---|---|---|---|---|---|---|"]
    names = {"rot_err_deg": "rotation (deg)", "trans_err_mm": "translation (mm)", "mtre_mm": "mTRE (mm)",
             "mpd_mm": "mPD (mm)", "time_s": "time (s)"}
    for method, stats in summary.items():
        for col, label in names.items():
            s = stats[col]
            lines.append(f"| {method} | {label} | {s['mean']:.2f} | {s['std']:.2f} | {s['median']:.2f} | "
                         f"{s['min']:.2f} | {s['max']:.2f} |")
        lines.append(f"| {method} | success: mTRE < {settings.success_mtre_mm:g} mm | "
                     f"{100 * stats['success_mtre']:.0f} % | | | | |")
        lines.append(f"| {method} | success: rotation < {settings.success_rot_deg:g} deg | "
                     f"{100 * stats['success_rot']:.0f} % | | | | |")
        if "verdicts" in stats and sum(stats["verdicts"].values()):
            v = stats["verdicts"]
            lines.append(f"| {method} | verdict: registered / doubtful / failed | {v['registered']} / {v['doubtful']} / "
                         f"{v['failed']} | | | | |")
            acc = "-" if not stats["within"] else f"{100 * stats['accepted']:.0f} % of {stats['within']}"
            lines.append(f"| {method} | verdict: registered within {settings.success_mtre_mm:g} mm (mTRE) | {acc} | | | | |")
            lines.append(f"| {method} | verdict: registered further off (false accepts) | "
                         f"{stats['false_accepts']} of {stats['off']} | | | | |")
    return "\n".join(lines)


def violin_plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = sorted({r["method"] for r in rows})
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
    for ax, col, label in zip(axes, ("rot_err_deg", "trans_err_mm", "mtre_mm"),
                              ("rotation error (deg)", "translation error (mm)", "mTRE (mm)")):
        data = [np.array([r[col] for r in rows if r["method"] == m]) for m in methods]
        ax.violinplot(data, showmedians=True)
        ax.set_xticks(range(1, len(methods) + 1), methods)
        ax.set_yscale("symlog", linthresh=1.0)
        ax.set_title(label)
    save_figure(fig, path)


@dataclass(frozen=True)
class MethodSpec:
    """What a Dask worker needs to build an evaluation's methods itself (built methods hold Dr.Jit
    scenes, which do not pickle): the CT (:func:`sim.ct.io.load_ct_spec`'s spec and label map), its
    anatomy centre ``(3,)`` LPS mm, the image size ``(H, W)`` px, the scene, the method names, the
    network (a checkpoint path or shipped model name; None: the default) and the moving images'
    physics (None: line DRRs)."""

    ct: str
    label_map: str | None
    center_lps: tuple[float, float, float]
    size: tuple[int, int]
    scene: str
    methods: tuple[str, ...]
    model: str | None = None
    physics: object = None


_WORKER_BUILT: dict = {}  # MethodSpec -> (volume, methods, bone points): one per worker process


def _worker_methods(spec: MethodSpec, settings: EvaluationSettings):
    """The volume, built methods and bone points of ``spec`` in this process (built once)."""
    key = (spec, settings.max_points, settings.seed)
    if key not in _WORKER_BUILT:
        _WORKER_BUILT.clear()
        volume = load_ct_spec(spec.ct, label_map=spec.label_map)
        predictor = load_predictor(spec.model) if any(needs_model(m) for m in spec.methods) else None
        methods = {name: build_method(name, volume, center_lps=np.asarray(spec.center_lps), size=spec.size,
                                      scene=spec.scene, model=predictor if needs_model(name) else None,
                                      physics=spec.physics) for name in spec.methods}
        _WORKER_BUILT[key] = (volume, methods, bone_points(volume, settings.max_points, settings.seed))
    return _WORKER_BUILT[key]


def verdict_renderer(volume, center_lps, geometry):
    """The line DRR renderer of the verdict's evidence (:func:`register.verdict.judge_result`) on
    images of ``geometry``."""
    from sim.projection.drr import DRRRenderer, RenderSettings  # Dr.Jit loads with the first renderer, not at import

    return DRRRenderer(volume, RenderSettings(size=(geometry.height, geometry.width)), center_lps=center_lps,
                       geometry=geometry)


def _case_rows(i: int, target, start, image, methods: dict, settings: EvaluationSettings, points, center_lps,
               geometry, judge_with) -> tuple[list[dict], list[dict]]:
    """One case registered by every method: its rows (with the verdict on each, ``judge_with``: the
    line DRR renderer of :func:`verdict_renderer`) and the contextual methods' trajectories."""
    rows, trajectories = [], []
    T_true = pose_from_params(target, geometry.sod_mm)
    for name, method in methods.items():
        t0 = time.perf_counter()
        result = method.register(image, start)
        elapsed = time.perf_counter() - t0
        err = pose_errors(result.pose, T_true, points, center_lps, geometry)
        verdict = judge_result(result, image, render=judge_with.render, sod_mm=geometry.sod_mm)
        rows.append({"case": i, "method": name, "start": settings.start, **err, "verdict": verdict.label,
                     "success": err["mtre_mm"] < settings.success_mtre_mm and err["rot_err_deg"] < settings.success_rot_deg,
                     "time_s": elapsed, "renders": result.renders, "similarity": result.similarity,
                     **{f"true_{k}": float(v) for k, v in zip("phi theta psi tx ty tz".split(), target)},
                     **{f"est_{k}": float(v) for k, v in zip("phi theta psi tx ty tz".split(), result.params)}})
        if result.trajectory is not None:
            trajectories.append({"case": i, "method": name, "true_params": np.asarray(target).tolist(),
                                 "params_deg_mm": np.asarray(result.trajectory["params"]).tolist(),
                                 "g_rad_mm": np.asarray(result.trajectory["g"]).tolist()})
    return rows, trajectories


def _dask_case(spec: MethodSpec, i: int, target, start, image, settings: EvaluationSettings, geometry):
    """:func:`_case_rows` on a Dask worker, its methods built there (:func:`_worker_methods`)."""
    volume, methods, points = _worker_methods(spec, settings)
    center = np.asarray(spec.center_lps)
    return _case_rows(i, target, start, image, methods, settings, points, center, geometry,
                      verdict_renderer(volume, center, geometry))


def evaluate(volume, methods: dict[str, RegistrationMethod], settings: EvaluationSettings, out: Path,
             *, center_lps, geometry, target_renderer, log=print, record: dict | None = None, client=None,
             spec: MethodSpec | None = None) -> dict:
    """Run the protocol; writes ``cases.csv``, ``summary.json``, ``table.md``, ``violins.png`` and,
    for the contextual methods, ``trajectories.json`` (every case's poses per iteration), all
    after the last case (a run that fails leaves nothing). ``record`` (e.g. the targets' and the
    methods' physics) is stored in ``summary.json``.

    ``client``: a :class:`distributed.Client` (:func:`sim.core.scale.dask_client`): the cases are
    registered on its workers, each building the methods of ``spec`` once (``methods`` may then be
    empty); the targets are rendered here, so the images (and their noise) are the sequential run's,
    and the rows come back in the sequential order (only ``time_s`` differs)."""
    out = Path(out)
    targets, starts = sample_cases(settings)
    target_images = target_renderer.render(pose_from_params(targets, geometry.sod_mm))
    names = list(spec.methods) if client is not None else list(methods)
    per_case: dict[int, tuple[list[dict], list[dict]]] = {}
    bar = Progress(settings.cases * len(names), 0, f"evaluate {out.name}", "registrations", rate_unit="reg/s")

    def done(i: int, result) -> None:
        per_case[i] = result
        for row in result[0]:
            log(f"case {i + 1}/{settings.cases} {row['method']}: rotation {row['rot_err_deg']:.2f} deg, "
                f"translation {row['trans_err_mm']:.1f} mm, mTRE {row['mtre_mm']:.1f} mm, {row['time_s']:.1f} s")
        bar.update(len(result[0]))

    if client is None:
        points = bone_points(volume, settings.max_points, settings.seed)
        judge_with = verdict_renderer(volume, center_lps, geometry)
        for i, (target, start, image) in enumerate(zip(targets, starts, target_images)):
            done(i, _case_rows(i, target, start, image, methods, settings, points, center_lps, geometry, judge_with))
    else:
        if spec is None:
            raise EvaluationError("evaluate on a Dask client needs the methods' spec (MethodSpec)")
        each_result(client, {i: (_dask_case, spec, i, targets[i], starts[i], target_images[i], settings, geometry)
                             for i in range(len(targets))}, done)
    rows = [r for i in sorted(per_case) for r in per_case[i][0]]
    trajectories = [t for i in sorted(per_case) for t in per_case[i][1]]
    summary = summarize(rows, settings)
    write_csv(out / "cases.csv", rows)
    write_json(out / "summary.json", {"settings": asdict(settings), **(record or {}), "summary": summary})
    table = format_table(summary, settings)
    with atomic_path(out / "table.md") as tmp:
        tmp.write_text(table + "\n")
    violin_plot(rows, out / "violins.png")
    if trajectories:
        write_json(out / "trajectories.json", {"units": "params in deg and mm (phi theta psi tx ty tz), g in rad "
                                                         "and mm", "trajectories": trajectories})
    return {"rows": rows, "summary": summary, "table": table}
