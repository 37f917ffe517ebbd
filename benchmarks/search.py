"""The global search (register/search.py) on realistic frames, against the CMA-ES restarts it replaced.

Frames: the first ``--cases`` poses of a study ``xray`` target (``--study``, default
``studies/domain_gap.toml`` and its ``fluoro-65kV``: full physics, round iris, fluoroscopy display chain, 12-bit DICOM; the
study's own frames, cached in ``--out``), registered from AP through ``register_xray`` as
``ctxreg register`` does, with three methods:

* ``cmaes + restarts`` (the peer): multi-resolution CMA-ES from AP with up to 3 IPOP restarts
  while the gradient NCC is below 0.6, what contextual+cmaes fell back to before the search;
* ``search + cmaes``: contextual+cmaes with a null network (its gradient is 0, so its pose is the
  start): the global search and the refinement alone;
* ``contextual+cmaes``: the same with the shipped default network.

Prints one table: success (mTRE < 10 mm, the issue's bar; and with rotation < 1 deg too), median
and slowest seconds per registration (the whole ``register_xray``: reading, field, polarity,
registration) and the ratio to the peer, median seconds of the grid; and a second with the grid's split (rendering
the padded DRRs of every grid pose against the FFT NCC of every shift), medians over the frames.

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
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def null_network(fixed, drr):
    """A predictor with no opinion: gradient 0, so the contextual iteration stops at its start."""
    return np.zeros(6)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ct", default=str(ROOT.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"),
                    help="the CT (NIfTI; default ../shared/data/ct/pelvis_abdomen_3mm.nii.gz)")
    ap.add_argument("--cases", type=int, default=10, help="frames: the protocol's first N poses (default 10)")
    ap.add_argument("--study", nargs="+", default=[str(ROOT / "studies" / "domain_gap.toml")],
                    help="the study file(s) whose xray targets give the frames (default studies/domain_gap.toml; "
                         "studies/heldout*.toml: conditions the search was not tuned on)")
    ap.add_argument("--target", default="fluoro-65kV",
                    help="an xray target of --study (default fluoro-65kV), or 'all': every xray target of every "
                         "--study, one summary row each")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_search"),
                    help="frame cache folder (default runs/bench_search; frames in OUT/TARGET)")
    ap.add_argument("--methods", nargs="+", choices=("peer", "null", "network"), default=("peer", "null", "network"),
                    help="which rows to run (default all three; the peer's seconds give the ratio column)")
    a = ap.parse_args()
    if not Path(a.ct).exists():
        print(f"search: CT {a.ct} not found (see ../shared/data/README.md)", file=sys.stderr)
        return 2
    if a.cases < 1:
        print(f"search: --cases must be >= 1, got {a.cases}", file=sys.stderr)
        return 2

    from register.study import load_study
    from sim import load_ct
    from sim.anatomy import anatomy_center

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
        print("| target | refused | method | mTRE < 10 mm | and rotation < 1 deg | median s / registration |")
        print("|---|---|---|---|---|---|")
        for name, (rows, refused) in summary:
            for method, r in rows.items():
                v = np.array(r, float)
                print(f"| {name} | {refused} | {method} | {v[:, 3].mean():.0%} | {v[:, 0].mean():.0%} | "
                      f"{np.median(v[:, 1]):.1f} |")
    return 0


def _measure(a, study, target, volume, center):
    """One target's frames through every method: prints its table (and the grid's split) and returns
    ``(rows, refused)``: per method ``[(success, seconds, grid seconds, mTRE < 10 mm)]`` per frame."""
    from register.api import register_xray
    from register.evaluate import EvaluationSettings, bone_points, pose_errors, sample_cases
    from register.study import XRayFrames, frame_refusals
    from sim.geometry import pose_from_params

    frames = XRayFrames(study, target, volume, center)
    sod = frames.imager.geometry.sod_mm
    poses, _ = sample_cases(EvaluationSettings(cases=a.cases, seed=study.seed, size=study.size, start="ap"))
    points = bone_points(volume, 2000, 0)
    folder = Path(a.out) / target.name
    folder.mkdir(parents=True, exist_ok=True)
    methods = {name: kw for key, name, kw in (
        ("peer", "cmaes + restarts (peer)", dict(method="cmaes", restarts=3)),
        ("null", "search + cmaes (null network)", dict(method="contextual+cmaes", model=null_network)),
        ("network", "contextual+cmaes (default network)", dict(method="contextual+cmaes"))) if key in a.methods}
    rows = {name: [] for name in methods}
    split = []
    refused = 0  # frames whose content registration refuses (counted as failures)
    t_all = time.perf_counter()
    for i, params in enumerate(poses):
        T_true = pose_from_params(params, sod)
        path = folder / f"case_{i:03d}.dcm"
        if not path.exists():
            frames.write(path, T_true, i)
        refused_frame = False
        for name, kw in methods.items():
            t0 = time.perf_counter()
            try:
                res = register_xray(volume, path, center=center, **kw)
            except frame_refusals() as exc:  # the frame's content refused: a failed case, as in the study
                rows[name].append((False, time.perf_counter() - t0, np.nan, False))
                refused_frame = True
                print(f"search: frame {i} {name}: refused ({exc})", file=sys.stderr, flush=True)
                continue
            seconds = time.perf_counter() - t0
            e = pose_errors(res.pose, T_true, points, center, np.eye(3, 4), np.eye(3, 4), 1.0)
            ok = e["mtre_mm"] < 10 and e["rot_err_deg"] < 1
            rows[name].append((ok, seconds, res.result.stage_seconds.get("search_grid", np.nan), e["mtre_mm"] < 10))
            record = res.result.search
            if name.startswith("search") and record["grid_poses"]:  # the grid's two parts on this frame
                split.append((record["grid_poses"], record["grid_render_s"], record["grid_ncc_s"]))
            print(f"search: frame {i} {name}: mTRE {e['mtre_mm']:.1f} mm, rotation {e['rot_err_deg']:.2f} deg, "
                  f"similarity {res.similarity:.2f}, {seconds:.1f} s", file=sys.stderr, flush=True)
        refused += refused_frame
        done = i + 1
        rate = done / (time.perf_counter() - t_all)
        print(f"search: {done}/{a.cases} frames, {rate:.3f} frames/s, ETA {(a.cases - done) / rate:.0f} s",
              file=sys.stderr, flush=True)

    peer_rows = rows.get("cmaes + restarts (peer)")
    peer = np.median([r[1] for r in peer_rows]) if peer_rows else float("nan")
    print(f"\n{target.name}: {a.cases} frames from AP through register_xray ({refused} refused by their content, "
          f"counted as failures; {time.strftime('%Y-%m-%d %H:%M')}, 2-core CPU)\n")
    print("| method | mTRE < 10 mm | and rotation < 1 deg | median s / registration | slowest s | ratio to the peer "
          "| median s of the grid |")
    print("|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        v = np.array(r, float)
        grid_s = np.nanmedian(v[:, 2]) if np.isfinite(v[:, 2]).any() else float("nan")
        print(f"| {name} | {v[:, 3].mean():.0%} | {v[:, 0].mean():.0%} | {np.median(v[:, 1]):.1f} | "
              f"{v[:, 1].max():.1f} | " + ("-" if not np.isfinite(peer) else f"{np.median(v[:, 1]) / peer:.2f}x") + " | "
              + ("-" if not np.isfinite(grid_s) else f"{grid_s:.2f}") + " |")
    if not split:
        return rows, refused
    s = np.array([(x[1], x[2]) for x in split])
    n = split[0][0]
    from register.search import GlobalSearchSettings

    k = GlobalSearchSettings().rescore
    print(f"\n| grid ({n} poses at 1/4 resolution) and rescoring ({k} at 1/2), padded detectors | median ms | "
          f"ms per grid pose |")
    print("|---|---|---|")
    for label, col in (("render (line DRRs, one batch)", 0), ("FFT masked NCC, every shift, x and y", 1)):
        print(f"| {label} | {1e3 * np.median(s[:, col]):.0f} | {1e3 * np.median(s[:, col]) / n:.2f} |")
    return rows, refused

if __name__ == "__main__":
    raise SystemExit(main())
