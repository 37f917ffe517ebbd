"""Networks on each other's validation pairs: every checkpoint on every config's validation set.

    .venv/bin/python benchmarks/validate_checkpoints.py --configs A.toml [B.toml ...] \\
        --checkpoints X.pt [Y.pt ...] [--device cpu] [--json out.json]

A run's log holds its network on its own validation pairs; when a recipe changes the pairs (a new
scatter model, display shares), its curve cannot be compared with the old run's. This evaluates
each checkpoint's weights on each config's validation pairs (``learn.train.validate_checkpoint``:
the same pairs, groups and AP-start targets as training logs, a function of the config only) and
prints one table: mean rotation / translation error over all pairs, and the rotation error per
group (near, far, ideal, log, linear, collimated field, open) and from AP. The configs must share
the checkpoints' backbone. Minutes per cell on this CPU (1024 pairs, realistic targets).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository first: benchmarks/learn.py and register.py are not the packages

GROUPS = ("near", "far", "ideal", "log", "linear", "field", "open", "ap")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", nargs="+", required=True, help="training configs whose validation pairs to use")
    ap.add_argument("--checkpoints", nargs="+", required=True, help="ctxreg train checkpoints (weights)")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or auto (default cpu)")
    ap.add_argument("--json", default=None, help="also write the rows here")
    a = ap.parse_args(argv)
    for p in a.configs + a.checkpoints:
        if not Path(p).is_file():
            print(f"validate_checkpoints: {p} not found", file=sys.stderr)
            return 2

    from learn.train import TrainConfigError, load_train_config, validate_checkpoint
    from sim.core.atomic import write_json

    rows = []
    t0 = time.perf_counter()
    for c in a.configs:
        try:
            cfg = load_train_config(c)
        except TrainConfigError as e:
            print(f"validate_checkpoints: {e}", file=sys.stderr)
            return 2
        for k in a.checkpoints:
            try:
                row = validate_checkpoint(cfg, k, device=a.device)
            except TrainConfigError as e:
                print(f"validate_checkpoints: {e}", file=sys.stderr)
                return 2
            rows.append({"config": c, "checkpoint": k, **row})
            print(f"validate_checkpoints: {k} on {c} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    print(f"\n# {time.strftime('%Y-%m-%d %H:%M')}: mean error, deg / mm (all), deg (groups)\n")
    print("| validation pairs of | checkpoint | all | " + " | ".join(GROUPS) + " |")
    print("|---|---|---|" + "---|" * len(GROUPS))
    for r in rows:
        cells = [f"{r.get(f'val_rot_{g}_deg', float('nan')):.1f}" for g in GROUPS]
        print(f"| {r['config']} | {r['checkpoint']} | {r['val_rot_err_deg']:.1f} / {r['val_trans_err_mm']:.1f} | "
              + " | ".join(cells) + " |")
    if a.json:
        write_json(a.json, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
