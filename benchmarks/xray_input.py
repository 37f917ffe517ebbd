"""Realistic C-arm frames of the pelvis CT registered through ``ctxreg register``: collimated vs open.

Prints a Markdown table (success mTRE < 10 mm, errors, seconds per registration) per frame kind
and start, and writes every row to ``--out``/rows.json. See register/evaluation/xray_study.py for the frames
(full physics at 4 tube/grid/exposure settings, round collimator, fluoroscopy display chain,
12-bit RF DICOM) and docs/results.md for the numbers.

    .venv/bin/python benchmarks/xray_input.py --cases 20 --out runs/xray_input
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from register.evaluation.xray_study import format_xray_study, run_xray_study, summarize_xray_study  # noqa: E402
from timing import add_frame_arguments, input_problem  # noqa: E402  (benchmarks/timing.py)
from sim.core.atomic import write_json  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_frame_arguments(ap, cases=20)
    ap.add_argument("--size", type=int, default=256, help="detector pixels per side (px)")
    ap.add_argument("--scatter-photons", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="runs/xray_input")
    a = ap.parse_args()
    problem = input_problem("xray_input", a.ct, a.cases)
    if problem:
        print(problem, file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    rows = run_xray_study(a.ct, a.out, cases=a.cases, size=a.size, seed=a.seed, scatter_photons=a.scatter_photons,
                     progress=lambda s: print(s, file=sys.stderr, flush=True))
    summary = summarize_xray_study(rows)
    write_json(Path(a.out) / "rows.json", {"rows": rows, "summary": summary})
    print(format_xray_study(summary))
    print(f"\n{a.cases} cases in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
