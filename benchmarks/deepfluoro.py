"""``ctxreg evaluate --deepfluoro`` on DeepFluoro-layout files made from the pelvis CT (issue 32).

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/deepfluoro.py [--frames 8] [--binning 4] [--starts ap local]

The real DeepFluoro file is not available here. This script writes one file per condition
(:mod:`register.datasets.deepfluoro_synthetic`: the DeepFluoro layout and geometry, SDD 1020 mm, a
298 mm detector of 1536 / binning px, raw intensities, the C-arm world frame through the
ground-truth poses) with frames at poses of the original protocol (rotations +-40 / 20 / 20 deg,
translations +-75 mm, seeded), then runs the evaluation on each from every start, and prints a
table: per condition and start, mTRE initial -> final (median), the shares under 10 mm and 1 mm,
and the seconds per frame. Conditions differ in tube voltage, exposure, scatter and collimator,
none of them tuned to. Files and outputs go to ``runs/bench_deepfluoro/`` (frames cached by
condition). It numbers the pipeline on frames whose CT is the evaluation CT itself, the case of
a network trained on the specimen's own CT.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
CT = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"


def conditions():
    from sim.physics.display import Collimator
    from sim.physics.settings import PhysicsSettings

    return {
        "poly-90kV-border": dict(physics=PhysicsSettings(level="poly", kvp=90.0, mas=2.0, noise=True),
                                 collimator=Collimator(shape="rectangle", half_size=(0.467, 0.467))),
        "poly-70kV-iris-lowdose": dict(physics=PhysicsSettings(level="poly", kvp=70.0, mas=0.5, noise=True),
                                       collimator=Collimator(shape="circle", radius=0.46)),
        "full-120kV-scatter": dict(physics=PhysicsSettings(level="full", kvp=120.0, mas=2.0, noise=True,
                                                           scatter_photons=200_000),
                                   collimator=Collimator(shape="iris-blades", radius=0.5, half_size=(0.42, 0.5))),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=8, help="frames per condition")
    ap.add_argument("--binning", type=int, default=4, help="detector binning (1536 / binning px)")
    ap.add_argument("--starts", nargs="+", default=["ap", "local"], choices=["ap", "local", "truth"])
    ap.add_argument("--conditions", nargs="+", default=None, help="a subset of the conditions")
    ap.add_argument("--no-detect-field", dest="detect_field", action="store_false",
                    help="the whole frame within the border as the field (default: register's field detection)")
    ap.add_argument("--methods", nargs="+", default=["contextual+cmaes"],
                    choices=["contextual+cmaes", "contextual", "cmaes"], help="the methods (contextual: the network alone)")
    ap.add_argument("--out", default=str(REPO / "runs" / "bench_deepfluoro"))
    args = ap.parse_args(argv)

    from register.datasets.deepfluoro_synthetic import SyntheticSettings, synthesize_deepfluoro
    from register.evaluation.deepfluoro import DeepFluoroSettings, evaluate_deepfluoro
    from sim import load_ct
    from sim.campaign.poses import ORIGINAL_PROTOCOL

    if not CT.exists():
        print(f"the pelvis CT {CT} is missing (see ../shared/data/README.md)", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ct = load_ct(CT)
    params = ORIGINAL_PROTOCOL.sample(np.random.default_rng(2032), args.frames)
    rows = []
    chosen = {k: v for k, v in conditions().items() if args.conditions is None or k in args.conditions}
    for name, cond in chosen.items():
        path = out / f"{name}_b{args.binning}_n{args.frames}.h5"
        if not path.exists():
            t0 = time.perf_counter()
            synthesize_deepfluoro(path, ct, params, settings=SyntheticSettings(binning=args.binning, rot_180_every=3,
                                                                               **cond))
            print(f"{name}: {args.frames} frames written in {time.perf_counter() - t0:.0f} s", flush=True)
        for start in args.starts:
            tag = f"{name}_{start}" + ("" if args.detect_field else "_nofield") + (
                "" if args.methods == ["contextual+cmaes"] else "_" + "_".join(m.replace("+", "-") for m in args.methods))
            res = evaluate_deepfluoro(path, DeepFluoroSettings(start=start, worst=2, detect_field=args.detect_field,
                                                               methods=tuple(args.methods)),
                                      out / tag, log=lambda line: None)
            for method in args.methods:
                g = res["summary"][method]["all"]
                label = f"{name} {method}" + ("" if args.detect_field else " (no field detection)")
                rows.append((label, start, g))
                print(f"{label} from {start}: mTRE {g['initial_mtre_mm']['median']:.1f} -> {g['mtre_mm']['median']:.2f} "
                      f"mm, < 10 mm {100 * g['under_10mm']:.0f} %, < 1 mm {100 * g['under_1mm']:.0f} %", flush=True)
    print("\n| condition | start | frames | mTRE initial -> final, median (mm) | mean (mm) | < 10 mm initial -> final "
          "| < 1 mm | rotation median (deg) | s / frame, median |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, start, g in rows:
        print(f"| {name} | {start} | {g['frames']} | {g['initial_mtre_mm']['median']:.1f} -> {g['mtre_mm']['median']:.2f} "
              f"| {g['mtre_mm']['mean']:.2f} | {100 * g['initial_under_10mm']:.0f} % -> {100 * g['under_10mm']:.0f} % | "
              f"{100 * g['under_1mm']:.0f} % | {g['rot_err_deg']['median']:.2f} | {g['time_s']['median']:.1f} |")
    (out / "table.json").write_text(json.dumps({f"{n}/{s}": g for n, s, g in rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
