"""How much to smooth the Monte Carlo scatter estimate: its error against a many-history reference.

    .venv/bin/python benchmarks/scatter_denoise.py [--cases 3] [--study studies/domain_gap.toml]
        [--target fluoro-65kV] [--reference 16] [--photons 250000 1000000 4000000]
        [--smooth-mm 0 6 12 18 24 32 48]

The ``full`` level's scatter image is a Monte Carlo *estimate* (:mod:`sim.physics.scatter`):
tallies on cells of ``cell_px`` detector pixels, smoothed by a Gaussian of ``smooth_mm`` at the
detector and interpolated to pixels. The estimate's noise is not physics: the scatter of a real
exposure (10^9 photons and more) is smooth at the scale of a few cells, and its quantum noise is
drawn separately, per pixel (:meth:`sim.physics.poly.Polychromatic.noisy`). Smoothing trades that
noise for a bias where the true scatter curves; this script measures the trade.

For each frame (the first ``--cases`` poses of ``--target`` from AP) it runs the pose's Monte Carlo
``--reference`` times at the largest ``--photons`` with independent seeds; their mean, unsmoothed,
is the reference ``R``. For each history count ``N`` of ``--photons`` and each ``--smooth-mm``
``s`` it runs one more independent estimate ``X`` and reports, over the pixels inside a 16 px
border, the relative RMS error of ``X`` smoothed by ``s`` against the truth,

    e(N, s)^2 = mean((X_s - R)^2) - var(R)          (relative to mean(R)),

where ``var(R)`` (the reference's own noise, estimated from the spread of its runs over their
number) is independent of ``X`` and is subtracted, so ``e`` estimates the error against the
expected scatter. The smoothing that minimises ``e`` at the default histories is the default of
:class:`sim.physics.scatter.ScatterSettings` (docs/physics.md, "The Monte Carlo estimate's noise").
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository first: benchmarks/learn.py and register.py are not the packages
from network_on_frames import (  # noqa: E402  (benchmarks/)
    FrameTargetError, add_monte_carlo_frame_arguments, monte_carlo_frames)
from timing import input_problem  # noqa: E402  (benchmarks/timing.py)

#: Border (px) left out: the Gaussians' mirrored edges.
BORDER_PX = 16


def _histories(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = -1
    if v < 1000:
        raise argparse.ArgumentTypeError(f"histories must be an integer >= 1000, got {text!r}")
    return v


def _smoothing_mm(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (np.isfinite(v) and 0 <= v <= 1000):
        raise argparse.ArgumentTypeError(f"a smoothing must be a number of mm in [0, 1000], got {text!r}")
    return v


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_monte_carlo_frame_arguments(ap, cases=3)
    ap.add_argument("--reference", type=int, default=16,
                    help="independent runs at the largest --photons averaged into the reference (default 16)")
    ap.add_argument("--photons", nargs="+", type=_histories, default=[250_000, 1_000_000, 4_000_000],
                    help="history counts of the estimates (default 250000 1000000 4000000)")
    ap.add_argument("--smooth-mm", nargs="+", type=_smoothing_mm, default=[0, 6, 12, 18, 24, 32, 48],
                    help="Gaussian sigmas at the detector, mm (default 0 6 12 18 24 32 48)")
    a = ap.parse_args()
    problem = input_problem("scatter_denoise", a.ct, a.cases)
    if problem is None and a.reference < 2:
        problem = f"scatter_denoise: --reference must be >= 2 (its spread is its noise), got {a.reference}"
    if problem:
        print(problem, file=sys.stderr)
        return 2

    from sim.projection.geometry import extrinsic_lps_to_camera
    from sim.physics.scatter import upsample_cells

    try:
        cases, frames = monte_carlo_frames(a.study, a.target, a.ct, a.cases, a.out)
    except FrameTargetError as e:
        print(f"scatter_denoise: {e}", file=sys.stderr)
        return 2
    im = frames.imager
    mc = im.scatter
    g = im.geometry
    cp = mc.settings.cell_px
    ppp = float(im.model.photons_per_pixel(**im.exposure).sum())
    c = slice(BORDER_PX, -BORDER_PX)
    n_ref = max(a.photons)
    t0 = time.perf_counter()
    err = np.zeros((len(cases), len(a.photons), len(a.smooth_mm)))
    ref_noise = []
    for k, (i, T, _) in enumerate(cases):
        cam = np.linalg.inv(extrinsic_lps_to_camera(T[None], im.renderer.center_lps))
        runs = [mc.run_batch(cam, g, photons_per_pixel=ppp, seeds=[10_000 + 97 * j + i], photons=n_ref)[0]["scatter"]
                for j in range(a.reference)]
        cells = np.stack(runs)
        ref = upsample_cells(cells.mean(0), g.height, g.width, cp, 0.0)[c, c]
        each = np.stack([upsample_cells(r, g.height, g.width, cp, 0.0)[c, c] for r in cells])
        var_ref = each.var(0, ddof=1).mean() / a.reference
        scale = ref.mean()
        ref_noise.append(np.sqrt(var_ref) / scale)
        for p, n in enumerate(a.photons):
            x = mc.run_batch(cam, g, photons_per_pixel=ppp, seeds=[20_000 + 31 * p + i], photons=n)[0]["scatter"]
            for q, s in enumerate(a.smooth_mm):
                xs = upsample_cells(x, g.height, g.width, cp, s / (g.pixel_spacing_mm * cp))[c, c]
                err[k, p, q] = np.sqrt(max(np.mean((xs - ref) ** 2) - var_ref, 0.0)) / scale
        print(f"scatter_denoise: frame {i} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

    print(f"\n{a.target}: relative RMS error of the Monte Carlo scatter estimate against {a.reference} x "
          f"{n_ref:,} histories, mean of {len(cases)} frames at {g.height} x {g.width} px "
          f"({g.pixel_spacing_mm:.2f} mm pixels, {cp} px cells of {g.pixel_spacing_mm * cp:.1f} mm; "
          f"{im.physics.kvp:g} kV, grid {im.physics.grid_ratio:g}; reference noise "
          f"{np.mean(ref_noise):.3f}; {time.strftime('%Y-%m-%d %H:%M')})\n")
    print("| histories | " + " | ".join(f"{s:g} mm" for s in a.smooth_mm) + " | best |")
    print("|---|" + "---|" * (len(a.smooth_mm) + 1))
    m = err.mean(0)
    for p, n in enumerate(a.photons):
        best = int(np.argmin(m[p]))
        print(f"| {n:,} | " + " | ".join(f"{v:.3f}" for v in m[p]) + f" | {a.smooth_mm[best]:g} mm |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
