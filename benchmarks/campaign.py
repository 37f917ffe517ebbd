"""Campaign benchmark: images per second, and what the original campaign would cost here.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/campaign.py [--images 96] [--workers 1]

For each subject (the real pelvis CT ``../shared/data/ct/pelvis_abdomen_3mm.nii.gz`` and the
built-in phantom) and detector size (128 x 128, 256 x 256) it runs a one-subject campaign of
``--images`` images (default 480) with line physics (Siddon) through :func:`sim.campaign.runner.run_campaign`
(shards of 32 images written to HDF5 with checksums, as in production) and prints the median of
three runs: the subject's set-up (CT load, anatomy centre, renderer), seconds per image after
it, images per second, and per core (Dr.Jit's kernels use every core of the machine). The
``full`` physics level (Monte Carlo scatter) is not implemented yet: its rows read ``n/a``
until then (poly physics costs are in benchmarks/physics.py). The last lines estimate the original campaign (3 CTs x 4311 images at
128 x 128) on this machine from the measured rates.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PELVIS = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"

TEMPLATE = """
[campaign]
name = "bench"
seed = 0
images_per_ct = {n}
shard_size = 32
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
split = "train"
[outputs]
projected_center = true
"""


def run_once(ct: str, size: int, n: int, workers: int) -> tuple[float, float]:
    """(set-up s, total s) of one campaign run: set-up = a 1-image campaign's time."""
    from sim.campaign.config import load_campaign
    from sim.campaign.runner import run_campaign

    times = []
    for images in (1, n):
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "c.toml"
            path.write_text(TEMPLATE.format(n=images, size=size, ct=ct))
            cfg = load_campaign(path)
            t0 = time.perf_counter()
            run_campaign(cfg, Path(d) / "out", workers=workers, progress=False)
            times.append(time.perf_counter() - t0)
    return times[0], times[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=480, help="images per timed campaign (default: 480)")
    ap.add_argument("--workers", type=int, default=1, help="worker processes (default: 1)")
    ap.add_argument("--repeats", type=int, default=3, help="runs per case, median reported (default: 3)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    cores = os.cpu_count() or 1
    subjects = [("phantom", "phantom:0")]
    if PELVIS.is_file():
        subjects.insert(0, ("pelvis_abdomen_3mm", str(PELVIS)))
    else:
        print(f"# {PELVIS} not found: pelvis rows skipped")
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, {cores} CPU threads, {args.workers} worker(s), "
          f"{args.images} images per run, median of {args.repeats}")
    head = ("subject", "size", "physics", "set-up s", "s/image", "images/s", "images/s/core")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    rates = {}
    for name, ct in subjects:
        for size in (128, 256):
            runs = [run_once(ct, size, args.images, args.workers) for _ in range(args.repeats)]
            setup = statistics.median(r[0] for r in runs)
            per_image = statistics.median((r[1] - r[0]) / (args.images - 1) for r in runs)
            rate = 1.0 / per_image
            rates[(name, size)] = (setup, rate)
            print(f"| {name} | {size}x{size} | line | {setup:.2f} | {per_image * 1e3:.1f} ms | "
                  f"{rate:.1f} | {rate / cores:.1f} |")
            print(f"| {name} | {size}x{size} | full | n/a | n/a | n/a | n/a |")
    key = ("pelvis_abdomen_3mm", 128) if ("pelvis_abdomen_3mm", 128) in rates else ("phantom", 128)
    setup, rate = rates[key]
    total_s = 3 * (setup + 4311 / rate)
    print(f"original campaign (3 CTs x 4311 images, 128 x 128, line physics, rate of {key[0]}): "
          f"{total_s / 60:.1f} min on this machine")
    print(f"original_campaign_minutes: {total_s / 60:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
