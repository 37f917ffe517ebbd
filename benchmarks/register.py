"""Registration benchmark: time per CMA-ES registration and DRRs per second inside the optimiser.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/register.py [--cases 5] [--physics line poly]

On ``../shared/data/ct/pelvis_abdomen_3mm.nii.gz`` (the built-in phantom when absent), for
target poses of the evaluation protocol (seed 0) started at AP and near the truth, it prints
the median wall time per registration, the DRRs rendered, the DRRs per second the optimiser
achieves (render + similarity + CMA-ES bookkeeping), and the time per stage, for each physics
level of the moving images given (targets rendered with the same physics, without noise). A
second table times one population (24 moving images) at each pyramid size for line, poly and
full physics (ratio against line); a third, 24 line DRRs rendered as a batch against 24
single renders: the reason the optimiser renders whole generations per kernel launch.
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
    ap.add_argument("--physics", nargs="+", choices=("line", "poly", "full"), default=["line", "poly"],
                    help="physics of the moving images to register with (default: line poly; full takes "
                         "minutes per registration)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import numpy as np

    from register.engines.cmaes import CMAESRegistration, CMAESSettings
    from register.evaluation.evaluate import EvaluationSettings, sample_cases
    from sim.ct.anatomy import anatomy_center
    from sim.ct.io import load_ct_spec
    from register.commands import REGISTER_SCATTER_PHOTONS
    from sim.projection.geometry import pose_from_params
    from sim.physics.imaging import PhysicsSettings

    spec = str(PELVIS) if PELVIS.is_file() else "phantom:0"
    vol = load_ct_spec(spec)
    c = anatomy_center(vol)
    s = CMAESSettings()
    physics = {lv: PhysicsSettings(level=lv, noise=False, scatter_photons=REGISTER_SCATTER_PHOTONS)
               for lv in ("line", "poly", "full")}
    engines = {}

    def engine_for(level):
        if level not in engines:
            engines[level] = CMAESRegistration(vol, s, center_lps=c, physics=physics[level])
        return engines[level]

    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, CT {Path(spec).name}, levels {s.levels} of {s.size}, "
          f"popsize {s.popsize}, metrics {s.metrics}, polish {s.polish}; full: {REGISTER_SCATTER_PHOTONS} "
          "histories per image")
    print("| moving physics | start | median s / registration | median images | images/s in the optimiser | "
          "median s per stage |")
    print("|---|---|---|---|---|---|")
    for level in args.physics:
        engine = engine_for(level)
        target_r = engine.by_factor[1]  # the same physics, noise-free, at the finest size
        for start in ("ap", "local"):
            targets, starts = sample_cases(EvaluationSettings(cases=args.cases, start=start))
            times, renders, stages = [], [], {}
            for t, s0 in zip(targets, starts):
                image = target_r.render(pose_from_params(t, target_r.geometry.sod_mm))[0]
                t0 = time.perf_counter()
                res = engine.register(image, s0)
                times.append(time.perf_counter() - t0)
                renders.append(res.renders)
                for k, v in res.stage_seconds.items():
                    stages.setdefault(k, []).append(v)
            stage_text = ", ".join(f"{k} {statistics.median(v):.1f}" for k, v in stages.items())
            print(f"| {level} | {start} | {statistics.median(times):.1f} | {statistics.median(renders):.0f} | "
                  f"{sum(renders) / sum(times):.0f} | {stage_text} |")
    # one population per pyramid size and physics level
    params = sample_cases(EvaluationSettings(cases=s.popsize))[0]
    print()
    print(f"| moving physics | {s.popsize} images at | ms per population | ms per image | ratio to line |")
    print("|---|---|---|---|---|")
    for factor in sorted(engine_for("line").by_factor, reverse=True):
        base = None
        for level in ("line", "poly", "full"):
            e = engine_for(level)
            e.render(params, factor)  # warm-up: kernel compilation
            t = statistics.median([_timed(lambda: e.render(params, factor)) for _ in range(5 if level != "full" else 3)])
            base = base or t
            h, w = s.size[0] // factor, s.size[1] // factor
            print(f"| {level} | {h}x{w} | {t * 1e3:.1f} | {t * 1e3 / len(params):.2f} | {t / base:.1f}x |")
    # batch against single renders at the coarse level
    engine = engine_for("line")
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
