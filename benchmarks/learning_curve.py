"""How many pairs a training run would need to reach a validation error, from its learning curve.

    .venv/bin/python benchmarks/learning_curve.py resume/batched_small_gpu/log.csv [more log.csv ...]
        [--batch-size 256] [--from-pairs 5e5] [--target-deg 9.7] [--rates 200 1500]

Each ``ctxreg train`` run logs its validation error every ``val_every`` iterations (``log.csv``:
``iteration``, ``lr``, ``val_rot_err_deg`` and one column per pair group, ``val_rot_far_deg`` ...).
For each run and group this fits a power law ``error = a N^-b`` in the pairs seen ``N`` to the
validation checks from ``--from-pairs`` on that share the first learning rate (a learning-rate
step bends the curve: the checks after it are reported, not fitted). The fit is Theil-Sen's in
log-log (scipy.stats.theilslopes: the median of the pairwise slopes), so that single spikes of the
curve (a check 3-7 deg above its neighbours at lr 1e-3) do not tilt it. It prints the exponent
``b`` with its 95 % interval, the fitted error at the last fitted check, the pairs ``N*`` at which
the fitted law reaches ``--target-deg`` (default 9.7 deg: the line-DRR network's validation error,
with which it registers line DRRs alone to 1.5 deg / 11.7 mm) with the interval the exponent's
interval gives, and the hours beyond the last check that would take at each of ``--rates`` pairs per second. A power law
fitted over one decade and extrapolated over more is a rough guide, not a prediction: the point is
the order of magnitude.
"""
from __future__ import annotations

import argparse
import csv
import math
import statistics
import sys
from pathlib import Path


def _rows(path: Path) -> list[dict]:
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        raise SystemExit(f"learning_curve: {path} cannot be read ({e.strerror})") from None
    need = {"iteration", "lr", "val_rot_err_deg"}
    if not rows or not need <= set(rows[0]):
        raise SystemExit(f"learning_curve: {path} is not a ctxreg train log.csv (needs columns {sorted(need)})")
    return [r for r in rows if r.get("val_rot_err_deg")]


def fit(pairs: list[float], errors: list[float], target: float) -> dict:
    """Theil-Sen power law through ``(pairs, errors)`` (both > 0) -> ``{b, b_low, b_high, fitted,
    n_star, n_star_low, n_star_high}``: ``error = a N^-b`` (b with its 95 % interval), the fitted
    error at the last point, and the pairs where the law (and its interval's ends) reaches ``target``
    (inf where the curve does not fall)."""
    from scipy.stats import theilslopes

    x = [math.log(p) for p in pairs]
    y = [math.log(e) for e in errors]
    slope, intercept, low, high = theilslopes(y, x, alpha=0.95)

    def reach(s: float) -> float:
        if s >= 0:
            return math.inf
        # the line with slope s through (median x, median y), Theil-Sen's own pivot
        xm, ym = statistics.median(x), statistics.median(y)
        return math.exp(xm + (math.log(target) - ym) / s)

    return {"b": -slope, "b_low": -high, "b_high": -low, "fitted": math.exp(intercept + slope * x[-1]),
            "n_star": reach(slope), "n_star_low": reach(low), "n_star_high": reach(high)}


def _pairs(n: float) -> str:
    if math.isinf(n):
        return "never"
    return f"{n / 1e9:.1f} G" if n >= 1e9 else f"{n / 1e6:.1f} M"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="+", type=Path, help="ctxreg train log.csv files")
    ap.add_argument("--batch-size", type=int, default=256, help="pairs per iteration (default 256)")
    ap.add_argument("--from-pairs", type=float, default=5e5, help="fit the checks from this many pairs on (default 5e5)")
    ap.add_argument("--target-deg", type=float, default=9.7, help="the validation rotation error to reach (deg; default 9.7)")
    ap.add_argument("--rates", type=float, nargs="+", default=[200.0, 1500.0],
                    help="pairs per second to convert pairs into hours (default: this CPU's 200, an H200's 1500)")
    ap.add_argument("--groups", nargs="+", default=["all", "far", "near", "log", "linear"],
                    help="validation groups (all = val_rot_err_deg; others val_rot_<group>_deg)")
    a = ap.parse_args(argv)
    if a.batch_size < 1 or a.target_deg <= 0 or a.from_pairs < 0 or min(a.rates) <= 0:
        print("learning_curve: --batch-size, --target-deg and --rates must be > 0, --from-pairs >= 0", file=sys.stderr)
        return 2
    head = ("| run | group | checks fitted | exponent b (95 %) | fitted error now | pairs to "
            f"{a.target_deg:g} deg (range) | " + " | ".join(f"hours more at {r:g} pairs/s" for r in a.rates)
            + " | checks after the lr step |")
    logs = [(path, _rows(path)) for path in a.logs]  # every file read (or refused) before the table
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for path, rows in logs:
        lr0 = next((r["lr"] for r in rows if int(r["iteration"]) * a.batch_size >= a.from_pairs), None)
        for group in a.groups:
            col = "val_rot_err_deg" if group == "all" else f"val_rot_{group}_deg"
            if col not in rows[0]:
                print(f"| {path} | {group} | (no column {col}) |")
                continue
            pts = [(int(r["iteration"]) * a.batch_size, float(r[col]), r["lr"]) for r in rows if r.get(col)]
            fitted = [(n, e) for n, e, lr in pts if n >= a.from_pairs and lr == lr0 and n > 0 and e > 0]
            after = [(n, e) for n, e, lr in pts if n >= a.from_pairs and lr != lr0]
            if len(fitted) < 3:
                print(f"| {path} | {group} | {len(fitted)}: too few to fit |")
                continue
            f = fit([n for n, _ in fitted], [e for _, e in fitted], a.target_deg)
            later = ", ".join(f"{e:.1f} at {_pairs(n)}" for n, e in after) or "none"
            if f["fitted"] <= a.target_deg:
                print(f"| {path} | {group} | {len(fitted)} ({_pairs(fitted[0][0])}-{_pairs(fitted[-1][0])}) | "
                      f"{f['b']:.2f} ({f['b_low']:.2f}-{f['b_high']:.2f}) | {f['fitted']:.1f} deg | reached | "
                      + " | ".join("0" for _ in a.rates) + f" | {later} |")
                continue
            lo, hi = sorted((f["n_star_low"], f["n_star_high"]))
            hours = " | ".join("never" if math.isinf(f["n_star"]) else f"{max(f['n_star'] - fitted[-1][0], 0) / r / 3600:.0f}"
                               for r in a.rates)
            print(f"| {path} | {group} | {len(fitted)} ({_pairs(fitted[0][0])}-{_pairs(fitted[-1][0])}) | "
                  f"{f['b']:.2f} ({f['b_low']:.2f}-{f['b_high']:.2f}) | {f['fitted']:.1f} deg | "
                  f"{_pairs(f['n_star'])} ({_pairs(lo)}-{_pairs(hi)}) | {hours} | {later} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
