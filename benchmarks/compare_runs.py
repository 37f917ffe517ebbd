"""Training runs side by side at equal pairs: their validation curves as a table and a figure.

    .venv/bin/python benchmarks/compare_runs.py NAME=runs/a/log.csv NAME=runs/b/log.csv ...
        [--batch-size 64] [--groups all far near ap] [--plot docs/images/curves.png]

Each ``ctxreg train`` run logs its validation every ``val_every`` iterations (``log.csv``). Runs
of one comparison share their validation pairs (the same campaign, seed and ``val_pairs``), so
their errors at the same number of pairs seen compare the options and nothing else. The table
gives, at every check the runs share, the rotation / translation error (deg / mm, means of single
predictions) of each group (``all``; ``far``, ``near``, ``log``, ``linear``, ``field``, ``open``
pairs; ``ap``: the same targets from registration's AP start), then each run's training seconds
and pairs per second (``elapsed_s``; validations included). ``--plot`` draws rotation and
translation error against pairs for the first two groups; ``--baseline GROUP=ROT/TRANS`` draws a
group's error of predicting no motion (deg / mm) as a dashed line, the level a run must leave;
``--no-motion CONFIG`` computes that level for every group on the validation pairs of a run's
config (:func:`learn.train.validate_no_motion`: the pairs rendered once, on the CPU) and prints it.
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository first: benchmarks/learn.py and register.py are not the packages


def _read(spec: str) -> tuple[str, list[dict]]:
    name, sep, path = spec.partition("=")
    if not sep or not name or not path:
        raise SystemExit(f"compare_runs: give each run as NAME=PATH/log.csv, got {spec!r}")
    try:
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("val_rot_err_deg")]
    except OSError as e:
        raise SystemExit(f"compare_runs: {path} cannot be read ({e.strerror})") from None
    if not rows or "iteration" not in rows[0]:
        raise SystemExit(f"compare_runs: {path} holds no validation rows of a ctxreg train log.csv")
    return name, rows


def _columns(group: str) -> tuple[str, str]:
    if group == "all":
        return "val_rot_err_deg", "val_trans_err_mm"
    return f"val_rot_{group}_deg", f"val_trans_{group}_mm"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="NAME=PATH/log.csv, one per run")
    ap.add_argument("--batch-size", type=int, default=64, help="pairs per iteration of every run (default 64)")
    ap.add_argument("--groups", nargs="+", default=["all", "far", "near", "ap"], help="validation groups")
    ap.add_argument("--plot", type=Path, help="write the curves of the first two groups to this PNG")
    ap.add_argument("--baseline", nargs="+", default=[], metavar="GROUP=ROT/TRANS",
                    help="a group's error of predicting no motion (deg / mm), drawn dashed on the plot")
    ap.add_argument("--no-motion", metavar="CONFIG",
                    help="compute the no-motion level of every group on this run config's validation pairs")
    a = ap.parse_args(argv)
    if a.batch_size < 1:
        print("compare_runs: --batch-size must be >= 1", file=sys.stderr)
        return 2
    baseline = {}
    for spec in a.baseline:
        group, _, values = spec.partition("=")
        try:
            baseline[group] = tuple(float(v) for v in values.split("/"))
        except ValueError:
            baseline[group] = ()
        if len(baseline[group]) != 2:
            print(f"compare_runs: --baseline {spec}: give GROUP=ROT/TRANS, e.g. all=44.8/110.2", file=sys.stderr)
            return 2
    runs = [_read(spec) for spec in a.runs]
    if a.no_motion:
        from learn.train import TrainConfigError, load_train_config, validate_no_motion  # only here: the tables need no torch

        try:
            row = validate_no_motion(load_train_config(a.no_motion))
        except (TrainConfigError, OSError) as e:
            raise SystemExit(f"compare_runs: --no-motion {a.no_motion}: {e}") from None
        levels = {g: (row[_columns(g)[0]], row[_columns(g)[1]]) for g in a.groups if _columns(g)[0] in row}
        print("predicting no motion: " + ", ".join(f"{g} {r:.1f} / {t:.1f}" for g, (r, t) in levels.items()))
        print()
        baseline = {**levels, **baseline}
    shared = sorted(set.intersection(*({int(r["iteration"]) for r in rows} for _, rows in runs)))
    by_iter = [{int(r["iteration"]): r for r in rows} for _, rows in runs]
    head = "| pairs | " + " | ".join(f"{name} {g}" for g in a.groups for name, _ in runs) + " |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for it in shared:
        cells = []
        for g in a.groups:
            rot, trans = _columns(g)
            for rows in by_iter:
                r = rows[it]
                cells.append(f"{float(r[rot]):.1f} / {float(r[trans]):.1f}" if r.get(rot) else "-")
        print(f"| {it * a.batch_size / 1e3:.0f} k | " + " | ".join(cells) + " |")
    print()
    print("| run | pairs | training s | pairs/s |")
    print("|---|---|---|---|")
    for name, rows in runs:
        last = rows[-1]
        pairs = int(last["iteration"]) * a.batch_size
        secs = float(last.get("elapsed_s") or "nan")
        print(f"| {name} | {pairs / 1e3:.0f} k | {secs:.0f} | {pairs / secs:.0f} |")
    if a.plot is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from sim.core.atomic import save_figure

        groups = a.groups[:2]
        fig, axes = plt.subplots(len(groups), 2, figsize=(10, 3.6 * len(groups)), squeeze=False)
        for i, g in enumerate(groups):
            for j, (col, unit) in enumerate(zip(_columns(g), ("rotation error (deg)", "translation error (mm)"))):
                ax = axes[i][j]
                for name, rows in runs:
                    pts = [(int(r["iteration"]) * a.batch_size / 1e3, float(r[col])) for r in rows if r.get(col)]
                    ax.plot(*zip(*pts), marker="o", ms=3, label=name)
                if g in baseline:
                    ax.axhline(baseline[g][j], color="grey", ls="--", lw=1, label="no motion predicted")
                ax.set_xlabel("pairs seen (thousands)")
                ax.set_ylabel(unit)
                ax.set_title(f"validation, {g} pairs" if g != "ap" else "validation, from AP")
                ax.grid(alpha=0.3)
        # one legend below the panels: inside, it hid the falling curves
        handles, labels = axes[0][0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 3), frameon=False)
        save_figure(fig, a.plot, dpi=110, rect=(0, 0.06 if len(labels) <= 3 else 0.1, 1, 1))
        print(f"\nwrote {a.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
