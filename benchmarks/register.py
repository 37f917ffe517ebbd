"""Registration benchmark: time per CMA-ES registration and DRRs per second inside the optimiser.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/register.py [--cases 5]

On ``../shared/data/ct/pelvis_abdomen_3mm.nii.gz`` (the built-in phantom when absent), for
target poses of the evaluation protocol (seed 0) started at AP and near the truth, it prints
the median wall time per registration, the DRRs rendered, the DRRs per second the optimiser
achieves (render + similarity + CMA-ES bookkeeping), and the time per stage. A second table
times one population (24 DRRs) rendered as a batch against 24 single renders: the reason the
optimiser renders whole generations per kernel launch.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PELVIS = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=5, help="registrations per start mode (default: 5)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import numpy as np

    from register.cmaes import CMAESRegistration, CMAESSettings
    from register.evaluate import EvaluationSettings, sample_cases
    from sim.anatomy import anatomy_center
    from sim.ct_io import load_ct_spec
    from sim.render import DRRRenderer, RenderSettings

    spec = str(PELVIS) if PELVIS.is_file() else "phantom:0"
    vol = load_ct_spec(spec)
    c = anatomy_center(vol)
    s = CMAESSettings()
    engine = CMAESRegistration(vol, s, center_lps=c)
    target_r = DRRRenderer(vol, RenderSettings(size=s.size), center_lps=c)
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, CT {Path(spec).name}, levels {s.levels} of {s.size}, "
          f"popsize {s.popsize}, metrics {s.metrics}, polish {s.polish}")
    print("| start | median s / registration | median DRRs | DRRs/s in the optimiser | median s per stage |")
    print("|---|---|---|---|---|")
    for start in ("ap", "local"):
        targets, starts = sample_cases(EvaluationSettings(cases=args.cases, start=start))
        times, renders, stages = [], [], {}
        for t, s0 in zip(targets, starts):
            image = target_r.render_params(t)[0]
            t0 = time.perf_counter()
            res = engine.register(image, s0)
            times.append(time.perf_counter() - t0)
            renders.append(res.renders)
            for k, v in res.stage_seconds.items():
                stages.setdefault(k, []).append(v)
        stage_text = ", ".join(f"{k} {statistics.median(v):.1f}" for k, v in stages.items())
        print(f"| {start} | {statistics.median(times):.1f} | {statistics.median(renders):.0f} | "
              f"{sum(renders) / sum(times):.0f} | {stage_text} |")
    # batch against single renders at the coarse level
    params = sample_cases(EvaluationSettings(cases=s.popsize))[0]
    factor = s.levels[0]
    engine.render(params, factor)
    tb = statistics.median([_timed(lambda: engine.render(params, factor)) for _ in range(9)])
    ts = statistics.median([_timed(lambda: [engine.render(p, factor) for p in params]) for _ in range(3)])
    h, w = s.size[0] // factor, s.size[1] // factor
    print()
    print("| population of 24 DRRs | ms | ratio |")
    print("|---|---|---|")
    print(f"| one batch, {h}x{w} | {tb * 1e3:.1f} | 1 |")
    print(f"| 24 single renders, {h}x{w} | {ts * 1e3:.1f} | {ts / tb:.1f}x |")
    return 0


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


if __name__ == "__main__":
    sys.exit(main())
