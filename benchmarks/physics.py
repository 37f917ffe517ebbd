"""Physics benchmark: median time per 256 x 256 image of the pelvis CT per physics level, and a panel.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/physics.py [--size 256] [--repeats 5] [--panel docs/figures/physics_panel.png]

Rows: ``line`` (the 60 keV line-integral DRR), ``poly`` without noise, ``poly`` with noise
(120 kVp, 2.5 mm Al, 30 bins, 7 materials, CsI 0.6 mm, 2.5 mAs) and ``full``, which is n/a
until the Monte Carlo scatter lands (docs/physics.md). Each row: the median of ``--repeats`` timed
renders of one pose after a warm-up, and its ratio to ``line`` measured in the same run. The
panel shows the same AP pose in line and poly physics, with and without noise.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

from timing import timed  # noqa: E402  (benchmarks/timing.py)



def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=256, help="image side in pixels (default: 256)")
    ap.add_argument("--repeats", type=int, default=5, help="timed renders per row (default: 5)")
    ap.add_argument("--panel", default=None, help="write the PNG panel here (default: none)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import numpy as np

    from sim.ct_io import load_ct
    from sim.geometry import pose_from_params
    from sim.physics.imaging import PhysicsSettings, XRayImager
    from sim.render import DRRRenderer, RenderSettings

    ct = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"
    if not ct.is_file():
        print(f"skipped: {ct} not found (see ../shared/data/README)")
        return 0
    vol = load_ct(ct)
    size = (args.size, args.size)
    line = DRRRenderer(vol, RenderSettings(size=size))
    quiet = XRayImager(vol, PhysicsSettings(noise=False), size=size, center_lps=line.center_lps)
    noisy = XRayImager(vol, PhysicsSettings(noise=True), size=size, center_lps=line.center_lps)
    pose = pose_from_params(np.zeros(6), line.geometry.sod_mm)
    rows = [("line", timed(lambda: line.render(pose), args.repeats)),
            ("poly, no noise", timed(lambda: quiet.render(pose), args.repeats)),
            ("poly + noise", timed(lambda: noisy.render(pose), args.repeats))]
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, pelvis_abdomen_3mm, {args.size}x{args.size}, AP, "
          f"median of {args.repeats}")
    print("| physics | ms per image | ratio to line |")
    print("|---|---|---|")
    for name, t in rows:
        print(f"| {name} | {t * 1e3:.1f} | {t / rows[0][1]:.1f} |")
    print("| full (poly + Monte Carlo scatter) | n/a | not available yet |")
    if args.panel:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from sim.atomic import save_figure

        images = [("line (60 keV line integral)", line.render(pose)[0]),
                  ("poly, 120 kVp: -log(I/I0)", quiet.render(pose)["log"][0]),
                  ("poly + quantum noise + blur", noisy.render(pose)["log"][0])]
        fig, axes = plt.subplots(1, 3, figsize=(11, 4))
        for ax, (title, im) in zip(axes, images):
            lo, hi = np.percentile(im, [0.5, 99.5])
            ax.imshow(im, cmap="gray", vmin=lo, vmax=hi)
            ax.set_title(title, fontsize=9)
            ax.set_axis_off()
        save_figure(fig, args.panel)
        print(f"wrote {args.panel}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
