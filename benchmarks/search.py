"""The global search (register/engines/search.py) on realistic frames, against the CMA-ES restarts it replaced.

Frames: the first ``--cases`` poses of a study ``xray`` target (``--study``, default
``studies/domain_gap.toml`` and its ``fluoro-65kV``: full physics, round iris, fluoroscopy display chain, 12-bit DICOM; the
study's own frames, cached in ``--out``), registered from AP through ``register_xray`` as
``ctxreg register`` does, with the methods of ``--methods`` (default ``peer null network``):

* ``peer``, ``cmaes + restarts``: multi-resolution CMA-ES from AP with up to 3 IPOP restarts
  while the gradient NCC is below 0.6, what contextual+cmaes fell back to before the search;
* ``null``, ``search + cmaes``: contextual+cmaes with a null network (its gradient is 0, so its pose
  is the start): the global search and the refinement alone;
* ``contextual``, ``contextual alone``: the shipped default network's iteration, nothing after it
  (``method="contextual"``);
* ``off``, ``contextual+cmaes, no grid``: the network's pose straight to the CMA-ES refinement
  (``search="off"``: the network measured on its own, the global search never built);
* ``network``, ``contextual+cmaes``: the default pipeline with the shipped default network; its
  "grid skipped" column is the share of frames whose network pose scored well enough to skip the
  grid.

Prints one table: success (mTRE < 10 mm, the issue's bar; and with rotation < 1 deg too), mean
rotation and translation errors and the translation's part along the beam (depth, what one view
reads from the magnification alone; over the frames registered, refused ones left out), median and
slowest seconds per registration (the whole ``register_xray``: reading, field, polarity,
registration) and the ratio to the peer, median seconds of the grid, the share of frames whose grid
was skipped (methods with the search in ``auto``); and a second with the grid's split (rendering
the padded DRRs of every grid pose against the FFT NCC of every shift), medians over the frames.
The network measured on its own, per condition::

    .venv/bin/python benchmarks/search.py --methods contextual off network --cases 20 --target all \
        --study studies/domain_gap.toml studies/heldout.toml

With ``--target all`` every ``xray`` target of every ``--study`` is measured in turn and a last
table sums them up, one row per target and method: the whole robustness table in one command,

    .venv/bin/python benchmarks/search.py --cases 10
    .venv/bin/python benchmarks/search.py --methods network --cases 20 --target all \
        --study studies/domain_gap.toml studies/heldout.toml studies/heldout2.toml studies/heldout3.toml \
        studies/heldout4.toml        # 15 conditions, about 45 min on 2 cores
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from timing import add_frame_arguments, input_problem  # noqa: E402  (benchmarks/timing.py)

from register.xray.field import TOOL_OPTIONS, TOOLS_DEFAULT  # noqa: E402


def null_network(fixed, drr):
    """A predictor with no opinion: gradient 0, so the contextual iteration stops at its start."""
    return np.zeros(6)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_frame_arguments(ap, cases=10)
    ap.add_argument("--only", type=int, nargs="+", default=None, metavar="CASE",
                    help="register only these frames of the first --cases (0-based; default all): to register again "
                         "the frames a change of the pipeline touches")
    ap.add_argument("--study", nargs="+", default=[str(ROOT / "studies" / "domain_gap.toml")],
                    help="the study file(s) whose xray targets give the frames (default studies/domain_gap.toml; "
                         "studies/heldout*.toml: conditions the search was not tuned on)")
    ap.add_argument("--target", default="fluoro-65kV",
                    help="an xray target of --study (default fluoro-65kV), or 'all': every xray target of every "
                         "--study, one summary row each")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_search"),
                    help="frame cache folder (default runs/bench_search; frames in OUT/TARGET)")
    ap.add_argument("--methods", nargs="+", choices=tuple(METHODS), default=("peer", "null", "network"),
                    help="which rows to run, in this order: peer (cmaes + restarts), null (search + cmaes, null "
                         "network), contextual (the network alone), off (contextual+cmaes without the grid, "
                         "search='off'), network (contextual+cmaes, the default pipeline); default peer null network "
                         "(the peer's seconds give the ratio column)")
    ap.add_argument("--model", default=None,
                    help="the network of the contextual, off and network rows: a shipped model's name (ctxreg models) "
                         "or a ctxreg train checkpoint (default: the shipped default)")
    ap.add_argument("--scatter-smooth-mm", type=float, default=None,
                    help="the frames' Monte Carlo scatter smoothing sigma (mm at the detector; default the "
                         "simulator's own, sim.physics.scatter.auto_smooth_mm): frames of another smoothing, e.g. "
                         "6 for those made before 2026-11-27 (give them their own --out)")
    ap.add_argument("--refine-polish", choices=("pattern", "powell"), default=None,
                    help="the refinement's polish (register.engines.pipeline.REFINE_SETTINGS.polish_method; default "
                         "the pipeline's own): to measure one against the other on the same frames")
    ap.add_argument("--tools", choices=TOOL_OPTIONS, default=TOOLS_DEFAULT,
                    help="every row's --tools (register_xray's tools: detect leaves the metal tools the shipped "
                         f"segmenter finds out of the mask; default {TOOLS_DEFAULT}, the pipeline's default)")
    ap.add_argument("--rows", default=None,
                    help="append every registration as a JSON line to this file: the condition, CT, model, method, "
                         "case, its errors (mTRE, rotation, translation) and register's whole result (result.json's "
                         "content): the data a verdict on registrations is calibrated on")
    a = ap.parse_args()
    if a.refine_polish is not None:  # the pipeline's refinement is built from this module constant
        import register.engines.methods as methods

        methods.REFINE_SETTINGS = replace(methods.REFINE_SETTINGS, polish_method=a.refine_polish)
    problem = input_problem("search", a.ct, a.cases)
    if not problem and a.only is not None and not all(0 <= c < a.cases for c in a.only):
        problem = f"search: --only: frames are 0 to {a.cases - 1} (--cases {a.cases}), got {a.only}"
    if not problem and a.scatter_smooth_mm is not None and not (0 <= a.scatter_smooth_mm <= 1000):
        problem = f"search: --scatter-smooth-mm must be a sigma in [0, 1000] mm, got {a.scatter_smooth_mm}"
    if problem:
        print(problem, file=sys.stderr)
        return 2

    from register.evaluation.study import load_study
    from sim import load_ct
    from sim.ct.anatomy import anatomy_center

    chosen = []  # (study, target) pairs to measure
    for path in a.study:
        if not Path(path).exists():
            print(f"search: study file {path} not found", file=sys.stderr)
            return 2
        study = load_study(path)
        chosen += [(study, t) for t in study.targets if t.kind == "xray" and a.target in ("all", t.name)]
    if not chosen:
        names = sorted({t.name for p in a.study for t in load_study(p).targets if t.kind == "xray"})
        print(f"search: --target must be 'all' or one of {names}", file=sys.stderr)
        return 2
    names = [t.name for _, t in chosen]
    if len(set(names)) != len(names):  # the frame cache is OUT/TARGET
        print(f"search: target names must be unique across the studies, got {sorted(names)}", file=sys.stderr)
        return 2
    volume = load_ct(a.ct)
    center = anatomy_center(volume)
    summary = []
    for k, (study, target) in enumerate(chosen):
        print(f"search: target {k + 1}/{len(chosen)}: {target.name}", file=sys.stderr, flush=True)
        summary.append((target.name, _measure(a, study, target, volume, center)))
    if len(summary) > 1:
        print(f"\nevery target: {a.cases} frames each from AP through register_xray (refused frames count as "
              f"failures; {time.strftime('%Y-%m-%d %H:%M')}, 2-core CPU)\n")
        print("| target | refused | method | mTRE < 10 mm | and rotation < 1 deg | mean rotation error deg | "
              "mean translation error mm | of it in depth mm | median s / registration | grid skipped |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for name, (rows, refused) in summary:
            for method, r in rows.items():
                c = _columns(r)
                print(f"| {name} | {refused} | {method} | {c['hit']} | {c['ok']} | {c['rot']} | {c['trans']} | "
                      f"{c['depth']} | {c['median_s']} | {c['skipped']} |")
    return 0


def _append_row(path: str, row: dict) -> None:
    """One JSON line appended to ``path`` (a whole line per write: a killed run loses at most its last)."""
    import json

    def plain(v):  # NumPy arrays and scalars as JSON, anything else by its repr
        return v.tolist() if hasattr(v, "tolist") else repr(v)

    line = json.dumps(row, default=plain) + "\n"
    with open(path, "a") as f:
        f.write(line)


#: ``--methods`` key: (row name, register_xray's keywords); the model is the shipped default where
#: none is given
METHODS = {
    "peer": ("cmaes + restarts (peer)", dict(method="cmaes", restarts=3)),
    "null": ("search + cmaes (null network)", dict(method="contextual+cmaes", model=null_network)),
    "contextual": ("contextual alone (default network)", dict(method="contextual")),
    "off": ("contextual+cmaes, no grid (search off, default network)", dict(method="contextual+cmaes", search="off")),
    "network": ("contextual+cmaes (default network)", dict(method="contextual+cmaes")),
    "always": ("contextual+cmaes, grid always (default network)", dict(method="contextual+cmaes", search="always")),
}


#: The ``--methods`` keys that run the network (``--model`` replaces it).
NETWORK_METHODS = ("contextual", "off", "network", "always")


def _pct(values) -> str:
    return "-" if not len(values) else f"{np.mean(values):.0%}"


def _columns(frames: list[dict]) -> dict[str, str]:
    """One method's table cells from its frames' rows (:func:`_measure`)."""
    done = [f for f in frames if not f["refused"]]
    rot = np.array([f["rot"] for f in done], float)
    trans = np.array([f["trans"] for f in done], float)
    depth = np.array([f["depth"] for f in done], float)
    grid = np.array([f["grid_s"] for f in done], float)
    searched = [f["skipped"] for f in done if f["skipped"] is not None]
    modes = {f["search_mode"] for f in done}
    seconds = [f["s"] for f in frames]
    return {"hit": _pct([f["hit"] for f in frames]), "ok": _pct([f["ok"] for f in frames]),
            "rot": "-" if not len(rot) else f"{rot.mean():.2f}",
            "trans": "-" if not len(trans) else f"{trans.mean():.1f}",
            "depth": "-" if not len(depth) else f"{depth.mean():.1f}",
            "median_s": f"{np.median(seconds):.1f}", "slowest_s": f"{np.max(seconds):.1f}",
            "median_grid_s": f"{np.nanmedian(grid):.2f}" if np.isfinite(grid).any() else "-",
            "skipped": _pct(searched) if searched else ("off" if modes == {"off"} else "-")}


def _measure(a, study, target, volume, center):
    """One target's frames through every method: prints its table (and the grid's split) and returns
    ``(rows, refused)``: per method one dict per frame: ``hit`` (mTRE < 10 mm), ``ok`` (and rotation
    < 1 deg), ``rot`` / ``trans`` / ``depth`` (deg, mm, mm; NaN when refused), ``s`` (seconds), ``grid_s`` (the grid's
    seconds, NaN where it did not run), ``skipped`` (whether the grid was skipped; None for a method
    without the search in auto or always), ``search_mode``, ``refused``."""
    from register.api import SEARCH_METHODS, register_xray
    from register.evaluation.errors import bone_points, pose_errors
    from register.evaluation.evaluate import EvaluationSettings, sample_cases
    from register.evaluation.study import frame_refusals, frame_seed, study_frames
    from sim.projection.geometry import pose_from_params

    frames = study_frames(study, target, volume, center)
    if a.scatter_smooth_mm is not None and frames.imager.scatter is not None:  # the frames' fingerprint has it
        mc = frames.imager.scatter
        mc.settings = replace(mc.settings, smooth_mm=a.scatter_smooth_mm)
    sod = frames.imager.geometry.sod_mm
    poses, _ = sample_cases(EvaluationSettings(cases=a.cases, seed=study.seed, size=study.size, start="ap"))
    points = bone_points(volume, 2000, 0)
    folder = Path(a.out) / target.name
    folder.mkdir(parents=True, exist_ok=True)
    methods = {name: (key, kw) for key, (name, kw) in METHODS.items() if key in a.methods}
    if a.model is not None:  # the network rows with another model, named in the row
        methods = {(name.replace("default network", Path(a.model).parent.name if a.model.endswith(".pt") else a.model)
                    if key in NETWORK_METHODS else name): (key, {**kw, "model": a.model} if key in NETWORK_METHODS else kw)
                   for name, (key, kw) in methods.items()}
    if a.tools != "off":  # named in the row and the table
        methods = {f"{name}, tools {a.tools}": v for name, v in methods.items()}
    rows = {name: [] for name in methods}
    split = []
    refused = 0  # frames whose content registration refuses (counted as failures)
    t_all = time.perf_counter()
    done, total = 0, a.cases if a.only is None else len(set(a.only))
    for i, params in enumerate(poses):
        if a.only is not None and i not in a.only:
            continue
        T_true = pose_from_params(params, sod)
        path = folder / f"case_{i:03d}.dcm"
        frames.cached(path, T_true, frame_seed(study, i))
        refused_frame = False
        for name, (key, kw) in methods.items():
            t0 = time.perf_counter()
            try:
                res = register_xray(volume, path, center=center, tools=a.tools, **kw)
            except frame_refusals() as exc:  # the frame's content refused: a failed case, as in the study
                rows[name].append({"hit": False, "ok": False, "rot": np.nan, "trans": np.nan, "depth": np.nan,
                                   "s": time.perf_counter() - t0, "grid_s": np.nan, "skipped": None,
                                   "search_mode": kw.get("search", "auto") if kw["method"] in SEARCH_METHODS else None,
                                   "refused": True})
                refused_frame = True
                print(f"search: frame {i} {name}: refused ({exc})", file=sys.stderr, flush=True)
                continue
            seconds = time.perf_counter() - t0
            e = pose_errors(res.pose, T_true, points, center, np.eye(3, 4), np.eye(3, 4), 1.0)
            searched = res.search_mode in ("auto", "always")
            rows[name].append({"hit": e["mtre_mm"] < 10, "ok": e["mtre_mm"] < 10 and e["rot_err_deg"] < 1,
                               "rot": e["rot_err_deg"], "trans": e["trans_err_mm"], "depth": e["depth_err_mm"],
                               "s": seconds,
                               "grid_s": res.result.stage_seconds.get("search_grid", np.nan),
                               "skipped": (not res.search_ran) if searched else None, "search_mode": res.search_mode,
                               "refused": False})
            if a.rows is not None:
                _append_row(a.rows, {"target": target.name, "study": study.source, "ct": a.ct, "model": a.model,
                                     "method": name, "tools": a.tools, "case": i, "true_params": params,
                                     "mtre_mm": e["mtre_mm"],
                                     "rot_err_deg": e["rot_err_deg"], "trans_err_mm": e["trans_err_mm"],
                                     "depth_err_mm": e["depth_err_mm"],
                                     "seconds": seconds, "result": res.to_dict()})
            record = res.result.search
            if key == "null" and record["grid_poses"]:  # the grid's two parts on this frame
                split.append((record["grid_poses"], record["grid_render_s"], record["grid_ncc_s"]))
            print(f"search: frame {i} {name}: mTRE {e['mtre_mm']:.1f} mm, rotation {e['rot_err_deg']:.2f} deg, "
                  f"similarity {res.similarity:.2f}, search {res.search_status}, {seconds:.1f} s", file=sys.stderr,
                  flush=True)
        refused += refused_frame
        done += 1
        rate = done / (time.perf_counter() - t_all)
        print(f"search: {done}/{total} frames, {rate:.3f} frames/s, ETA {(total - done) / rate:.0f} s",
              file=sys.stderr, flush=True)

    peer_rows = rows.get("cmaes + restarts (peer)")
    peer = np.median([r["s"] for r in peer_rows]) if peer_rows else float("nan")
    print(f"\n{target.name}: {a.cases} frames from AP through register_xray ({refused} refused by their content, "
          f"counted as failures, left out of the mean errors; {time.strftime('%Y-%m-%d %H:%M')}, 2-core CPU)\n")
    print("| method | mTRE < 10 mm | and rotation < 1 deg | mean rotation error deg | mean translation error mm "
          "| of it in depth mm | median s / registration | slowest s | ratio to the peer | median s of the grid "
          "| grid skipped |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        c = _columns(r)
        ratio = "-" if not np.isfinite(peer) else f"{np.median([f['s'] for f in r]) / peer:.2f}x"
        print(f"| {name} | {c['hit']} | {c['ok']} | {c['rot']} | {c['trans']} | {c['depth']} | {c['median_s']} | "
              f"{c['slowest_s']} | {ratio} | {c['median_grid_s']} | {c['skipped']} |")
    if not split:
        return rows, refused
    s = np.array([(x[1], x[2]) for x in split])
    n = split[0][0]
    from register.engines.search import GlobalSearchSettings

    k = GlobalSearchSettings().rescore
    print(f"\n| grid ({n} poses at 1/4 resolution) and rescoring ({k} at 1/2), padded detectors | median ms | "
          f"ms per grid pose |")
    print("|---|---|---|")
    for label, col in (("render (line DRRs, one batch)", 0), ("FFT masked NCC, every shift, x and y", 1)):
        print(f"| {label} | {1e3 * np.median(s[:, col]):.0f} | {1e3 * np.median(s[:, col]) / n:.2f} |")
    return rows, refused

if __name__ == "__main__":
    raise SystemExit(main())
