"""Campaign throughput: today's local runner against Dask workers (issue 33).

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/scale.py [--images 256] [--size 128] [--repeats 2]

Runs one campaign (the pelvis CT ``../shared/data/ct/pelvis_abdomen_3mm.nii.gz`` and one virtual
patient of it, line physics, shards of 16 images) as whole ``ctxreg simulate`` processes, in each
mode: ``--workers 1`` and ``--workers 2`` (the local process pool) and ``--scheduler local:1`` and
``--scheduler local:2`` (a Dask LocalCluster started by the command), and prints for each the
median wall seconds of ``--repeats`` runs and images per second, and its ratio to ``--workers 1``.
The wall seconds include each process's start, the CT's load in every worker and the cluster's
start: the cost a user pays. The datasets are checked to be identical (shard checksums).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PELVIS = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"

TEMPLATE = """
[campaign]
name = "scale"
seed = 0
images_per_ct = {n}
shard_size = 16
[scene]
size = [{size}, {size}]
[[physics]]
name = "line"
level = "line"
[split]
train = 1.0
val = 0.0
test = 0.0
[[cts]]
path = "{ct}"
virtual_patients = 1
"""

MODES = {"workers 1": ["--workers", "1"], "workers 2": ["--workers", "2"],
         "dask local:1": ["--scheduler", "local:1"], "dask local:2": ["--scheduler", "local:2"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=256, help="images per subject (two subjects)")
    ap.add_argument("--size", type=int, default=128, help="detector side (px)")
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    if not PELVIS.exists():
        print(f"the pelvis CT {PELVIS} is missing (see ../shared/data/README.md)", file=sys.stderr)
        return 2
    total = 2 * args.images
    rows, sums = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        camp = Path(tmp) / "scale.toml"
        camp.write_text(TEMPLATE.format(n=args.images, size=args.size, ct=PELVIS))
        for mode, flags in MODES.items():
            times = []
            for r in range(args.repeats):
                out = Path(tmp) / f"{mode.replace(' ', '_').replace(':', '')}_{r}"
                t0 = time.perf_counter()
                p = subprocess.run([str(REPO / ".venv" / "bin" / "ctxreg"), "simulate", str(camp), "--out", str(out),
                                    *flags], capture_output=True, text=True, cwd=REPO)
                times.append(time.perf_counter() - t0)
                if p.returncode != 0:
                    print(p.stderr, file=sys.stderr)
                    return 1
                manifest = json.loads((out / "manifest.json").read_text())
                sums.setdefault("reference", {k: v["sha256"] for k, v in manifest["shards"].items()})
                if {k: v["sha256"] for k, v in manifest["shards"].items()} != sums["reference"]:
                    print(f"{mode}: the dataset differs from the first run's", file=sys.stderr)
                    return 1
            rows.append((mode, statistics.median(times), min(times), max(times)))
            print(f"{mode}: {statistics.median(times):.1f} s", flush=True)
    base = rows[0][1]
    print(f"\n{total} images of {args.size} x {args.size} px (two subjects, shards of 16), median of {args.repeats} "
          f"whole processes; every dataset identical\n")
    print("| mode | wall s (median) | min | max | images/s | vs --workers 1 |")
    print("|---|---|---|---|---|---|")
    for mode, med, lo, hi in rows:
        print(f"| {mode} | {med:.1f} | {lo:.1f} | {hi:.1f} | {total / med:.1f} | {base / med:.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
