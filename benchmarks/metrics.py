"""Similarity-metric benchmark: median ms to score one CMA-ES population against a fixed image.

Usage (from the repository root)::

    .venv/bin/python benchmarks/metrics.py [--repeats 21] [--batch 32] [--sizes 128 64]

For each image size (square, px) it scores a batch of ``--batch`` float32 moving images
(shifted copies of a Gaussian-blurred noise image) against the fixed image, without and with
a mask (a centred disc), and prints the median wall time in ms over ``--repeats`` runs after
one warm-up, one row per metric. The patch metrics use their default 11 px windows; the
multiscale rows use 3 pyramid levels (patch 5 px for the patch metric so the coarsest level fits).
The rows "X-ray bound" score through :func:`register.engines.metrics.bind_metric`, bound once
before the timing as an optimiser binds it once per level: the same scores (tested to the bit),
beside the unbound row of the same metric, its peer (``--batch 1`` is the polish's call).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from register.engines.metrics import (  # noqa: E402
    bind_metric,
    gradient_ncc,
    multiscale,
    ncc,
    patch_gradient_ncc,
    patch_ncc,
    tone_tolerant_gradient_ncc,
)

METRICS = {
    "ncc": lambda f, m, k: ncc(f, m, k),
    "gncc": lambda f, m, k: gradient_ncc(f, m, k),
    "tone_tolerant_gncc": lambda f, m, k: tone_tolerant_gradient_ncc(f, m, k),
    "patch_ncc (11 px)": lambda f, m, k: patch_ncc(f, m, mask=k),
    "patch_gncc (11 px)": lambda f, m, k: patch_gradient_ncc(f, m, mask=k),
    "multiscale ncc (3 levels)": lambda f, m, k: multiscale("ncc", f, m, levels=3, mask=k),
    "multiscale patch_gncc (3 lv, 5 px)": lambda f, m, k: multiscale("patch_gncc", f, m, levels=3, mask=k, patch=5),
}


#: Rows scored through bind_metric: row name -> metric name.
BOUND = {"gncc, X-ray bound": "gncc", "tone_tolerant_gncc, X-ray bound": "tone_tolerant_gncc"}


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=21, help="timed runs per cell (median reported)")
    parser.add_argument("--batch", type=int, default=32, help="moving images per call (population size)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 64], help="image sides in px")
    args = parser.parse_args(argv)

    rng = np.random.default_rng(0)
    print(f"median ms per call, batch of {args.batch} float32 images, {args.repeats} repeats")
    header = f"{'metric':36s}" + "".join(f"{f'{s}x{s}':>10s}{f'{s} mask':>10s}" for s in args.sizes)
    print(header)
    print("-" * len(header))
    cases = {}
    for s in args.sizes:
        fixed = ndimage.gaussian_filter(rng.normal(size=(s, s)), 3.0, mode="wrap").astype(np.float32)
        shifts = np.linspace(-8, 8, args.batch).round().astype(int)
        moving = np.stack([np.roll(fixed, int(d), axis=1) for d in shifts])
        yy, xx = np.mgrid[:s, :s]
        mask = (yy - s / 2) ** 2 + (xx - s / 2) ** 2 < (0.45 * s) ** 2
        cases[s] = (fixed, moving, mask)
    for name in [*METRICS, *BOUND]:
        row = f"{name:36s}"
        for s in args.sizes:
            fixed, moving, mask = cases[s]
            for k in (None, mask):
                if name in BOUND:
                    score = bind_metric(BOUND[name], fixed, k)
                    call = lambda: score(moving)  # noqa: E731
                else:
                    call = lambda: METRICS[name](fixed, moving, k)  # noqa: E731
                row += f"{median_ms(call, args.repeats):10.2f}"
        print(row, flush=True)


if __name__ == "__main__":
    main()
