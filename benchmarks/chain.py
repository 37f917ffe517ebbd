"""The imaging chain (sim/physics/chain.py) on one image, against the NumPy / SciPy peer it replaced.

Every realistic image leaves the render through ``apply_chain`` in torch, a single frame as a batch
of one: a per-pair training target (``sim.randomize.apply_image``) and a study's frame
(``DisplayChain.apply``). The peer is the NumPy / SciPy implementation the chain is tested against
(``tests/sim/reference_chain.py``: FFT Gaussians, ``scipy.ndimage.gaussian_filter``,
``numpy.percentile``), which these paths ran before the chain was made one. Prints one table:
median seconds per image over ``--repeats`` calls after a warm-up, and chain / peer, per size and
case (kernel scatter with the unsharp mask; sks scatter; the display chain alone)::

    .venv/bin/python benchmarks/chain.py                  # about 1 min on 2 cores
    .venv/bin/python benchmarks/chain.py --sizes 64 512 --repeats 20
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from timing import timed  # noqa: E402  (benchmarks/timing.py)

from sim.physics.display import Collimator, DisplayChain  # noqa: E402
from sim.projection.geometry import CArmGeometry  # noqa: E402
from sim.randomize import DomainRandomization, apply_image, image_rng  # noqa: E402
from tests.sim import reference_chain  # noqa: E402  (the peer)


def _raw(size: int) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size] / size
    return 2000.0 * np.exp(-2.5 * np.exp(-((yy - 0.45) ** 2 + (xx - 0.55) ** 2) / 0.05))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256, 512], help="image sides (px)")
    ap.add_argument("--repeats", type=int, default=7, help="timed calls per cell (after one warm-up)")
    a = ap.parse_args()
    if a.repeats < 1 or any(s < 16 for s in a.sizes):
        print("chain.py: --repeats must be >= 1 and --sizes >= 16 px", file=sys.stderr)
        return 2
    kernel = DomainRandomization.from_table({"scatter": ["kernel"], "unsharp": 1.0, "field": ["circle"]}).draw(0, 0)
    sks = DomainRandomization.from_table({"scatter": ["sks"], "field": ["rectangle"]}).draw(0, 1)
    chain = DisplayChain(gamma=0.8, unsharp_sigma_px=4.0, unsharp_amount=0.6)
    print("| case | size (px) | chain s | peer s | chain / peer |")
    print("|---|---|---|---|---|")
    for size in a.sizes:
        raw = _raw(size)
        g = CArmGeometry(sdd_mm=1020.0, sod_mm=620.0, height=size, width=size, pixel_spacing_mm=384.0 / size)
        field = Collimator(shape="circle", radius=0.45).mask(size, size)
        cases = {
            "per-pair target, kernel scatter + unsharp": (
                lambda: apply_image(raw, 2000.0, kernel, image_rng(0, 0)),
                lambda: reference_chain.apply_image(raw, 2000.0, kernel, image_rng(0, 0))),
            "per-pair target, sks scatter": (
                lambda: apply_image(raw, 2000.0, sks, image_rng(0, 1), geometry=g, gap_mm=300.0),
                lambda: reference_chain.apply_image(raw, 2000.0, sks, image_rng(0, 1), geometry=g, gap_mm=300.0)),
            "display chain (a study's frame)": (
                lambda: chain.apply(raw, 2000.0, field),
                lambda: reference_chain.display(chain, raw, 2000.0, field)),
        }
        for name, (ours, peer) in cases.items():
            t, p = timed(ours, a.repeats), timed(peer, a.repeats)
            print(f"| {name} | {size} | {t:.4f} | {p:.4f} | {t / p:.2f}x |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
