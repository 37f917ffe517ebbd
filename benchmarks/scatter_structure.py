"""The relative structure of a study's Monte Carlo scatter against the ``sks`` texture of the training.

    .venv/bin/python benchmarks/scatter_structure.py [--cases 4] [--study studies/domain_gap.toml]
        [--target fluoro-65kV] [--out runs/bench_search] [--textures 0.12:0.03 0.1:0.06 ...]

The training's ``sks`` scatter (:func:`sim.randomize.apply_image`) is the fitted kernel model's
smooth scatter times a random texture (:func:`sim.randomize.sks_texture`); the study's frames
carry the ``full`` level's Monte Carlo estimate (:mod:`sim.physics.scatter`: 10^6 histories,
8 px tally cells smoothed by 24 mm since 2026-11-27, by 6 mm before, when it was far from smooth:
``benchmarks/scatter_denoise.py``). This script says how far the two differ
and at which scales. For each frame (the first ``--cases`` poses of ``--target`` from AP, as
``benchmarks/network_first_step.py`` takes them) it renders the Monte Carlo scatter ``S_mc``
(no noise: the estimate's expectation given its histories) and the primary, predicts the kernel
model's scatter ``S_k`` from the primary's thickness (the default table at the frame's kV, grid
and air gap, of the whole detector's exposure as the Monte Carlo is), and reports for the ratio
``r = S_mc / S_k`` inside a 16 px border:

* ``SPR``: the mean scatter-to-primary ratio of each (Monte Carlo, kernel model);
* ``large``: the std of ``G_8 * r`` (Gaussian of 8 px: the smooth deviation, the model's shape
  error, which ``sks_amplitude`` / ``sks_width`` and the texture's wide end cover);
* ``fine``: the std of ``r / (G_8 * r) - 1`` (the structure under 8 px: the estimate's noise),
  and the radial power spectrum of the same at a few spatial frequencies (cycles per side).

Then the same ``fine`` numbers for textures ``strength:sigma`` (sigma as a fraction of the shorter
side, ``--textures``), one draw each at the frames' size: the texture whose ``fine`` std and
spectrum match the Monte Carlo's is the one the network must tolerate (docs/training.md, "The
frames' Monte Carlo structure").
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

#: The Gaussian (px) that splits the large-scale deviation from the fine structure.
SPLIT_PX = 8.0
#: Border (px) left out: the 8 px tally cells and the Gaussians' mirrored edges.
BORDER_PX = 16
#: Spatial frequencies (cycles per side) of the printed spectra.
FREQS = (2, 4, 8, 16, 32)


def radial_spectrum(x: np.ndarray) -> np.ndarray:
    """Azimuthally averaged power spectrum of ``x`` ``(H, W)`` (mean removed, ``|FFT|^2 / N``),
    indexed by the integer radius in cycles per side."""
    f = np.abs(np.fft.fftshift(np.fft.fft2(x - x.mean()))) ** 2 / x.size
    yy, xx = np.indices(x.shape)
    r = np.hypot(yy - x.shape[0] // 2, xx - x.shape[1] // 2).astype(int)
    return np.bincount(r.ravel(), f.ravel()) / np.maximum(np.bincount(r.ravel()), 1)


def split(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``r`` ``(H, W)`` -> (its large-scale part ``G * r``, its fine part ``r / (G * r) - 1``),
    both inside the border."""
    from scipy.ndimage import gaussian_filter

    smooth = gaussian_filter(r, SPLIT_PX, mode="nearest")
    c = slice(BORDER_PX, -BORDER_PX)
    return smooth[c, c], (r / smooth - 1.0)[c, c]


def _texture_arg(text: str) -> tuple[float, float]:
    try:
        s, sig = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a texture is STRENGTH:SIGMA, got {text!r}") from None
    if not (0 <= s <= 1 and 0 < sig <= 1):
        raise argparse.ArgumentTypeError(f"a texture needs strength in [0, 1] and sigma in (0, 1], got {text!r}")
    return s, sig


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_monte_carlo_frame_arguments(ap, cases=4)
    ap.add_argument("--textures", nargs="+", type=_texture_arg, default=[(0.12, 0.03), (0.1, 0.06), (0.1, 0.015)],
                    help="sks textures STRENGTH:SIGMA to compare: relative std in [0, 1], Gaussian sigma as a "
                         "fraction of the shorter side in (0, 1] (default 0.12:0.03 0.1:0.06 0.1:0.015)")
    a = ap.parse_args()
    problem = input_problem("scatter_structure", a.ct, a.cases)
    if problem:
        print(problem, file=sys.stderr)
        return 2

    from sim.physics.scatter_kernel import default_table, detector_gap_mm
    from sim.randomize import sks_texture

    try:
        cases, frames = monte_carlo_frames(a.study, a.target, a.ct, a.cases, a.out)
    except FrameTargetError as e:
        print(f"scatter_structure: {e}", file=sys.stderr)
        return 2
    im = frames.imager
    g, flat = im.geometry, float(im.flat)
    model = default_table().model_for(float(im.physics.kvp), float(im.physics.grid_ratio))
    t0 = time.perf_counter()
    rows, spectra = [], []
    for i, T, _ in cases:
        out = im.render(T, seed=frames.seeds[i])
        mc, primary = out["scatter"][0].astype(np.float64), out["primary"][0].astype(np.float64)
        tau = -np.log(np.maximum(primary, 1e-12 * flat) / flat)
        sk = model.predict(tau, g, flat_signal=flat, gap_mm=float(detector_gap_mm(T, g)[0]))
        large, fine = split(mc / np.maximum(sk, 1e-12 * flat))
        c = slice(BORDER_PX, -BORDER_PX)
        rows.append((f"frame {i}", (mc / primary)[c, c].mean(), (sk / primary)[c, c].mean(), large.std(), fine.std()))
        spectra.append(radial_spectrum(fine))
        print(f"scatter_structure: frame {i} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    h, w = mc.shape
    mean_spectrum = np.mean(spectra, 0)
    rng = np.random.default_rng(0)
    tex = []
    for s, sig in a.textures:
        t = sks_texture(rng.standard_normal((h, w)), s, sig * min(h, w))
        large, fine = split(t)
        tex.append((f"texture {s:g} at sigma {sig:g} ({sig * min(h, w):.1f} px)", large.std(), fine.std(),
                    radial_spectrum(fine)))
    print(f"\n{a.target}: Monte Carlo scatter against the kernel model, {len(rows)} frames at {h} x {w} "
          f"({im.physics.kvp:g} kV, grid {im.physics.grid_ratio:g}; {time.strftime('%Y-%m-%d %H:%M')})\n")
    print("| scatter | SPR Monte Carlo | SPR kernel model | large (std of G8 r) | fine (std) | "
          + " | ".join(f"power at {f}/side" for f in FREQS) + " |")
    print("|---|---|---|---|---|" + "---|" * len(FREQS))
    for (name, spr_mc, spr_k, large, fine), sp in zip(rows, spectra):
        print(f"| {name} | {spr_mc:.2f} | {spr_k:.2f} | {large:.3f} | {fine:.3f} | "
              + " | ".join(f"{sp[f]:.2g}" for f in FREQS) + " |")
    m = np.mean([r[1:] for r in rows], 0)
    print(f"| mean | {m[0]:.2f} | {m[1]:.2f} | {m[2]:.3f} | {m[3]:.3f} | "
          + " | ".join(f"{mean_spectrum[f]:.2g}" for f in FREQS) + " |")
    for name, large, fine, sp in tex:
        print(f"| {name} | | | {large:.3f} | {fine:.3f} | " + " | ".join(f"{sp[f]:.2g}" for f in FREQS) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
