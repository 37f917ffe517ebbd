"""Physics benchmark: median time per 256 x 256 image of the pelvis CT per physics level, and a panel.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/physics.py [--size 256] [--repeats 5] [--panel docs/figures/physics_panel.png]
        [--spr-table]

Rows: ``line`` (the 60 keV line-integral DRR), ``poly`` without and with noise (120 kVp, 2.5 mm
Al, 30 bins, 7 materials, CsI 0.6 mm, 2.5 mAs) and ``full`` (poly + Monte Carlo scatter, 10^6
histories) without and with noise. Each row: the median of ``--repeats`` timed renders of one
pose after a warm-up, and its ratio to ``line`` measured in the same run.

Monte Carlo throughput: histories per second of the Dr.Jit transport alone (median of
``--repeats`` runs of 2 x 10^6 histories) on the pelvis at AP and on a 20 cm water slab, and,
as the peer in the same run, the simple analog NumPy Monte Carlo of ``tests/sim/slab_mc.py``
on the same slab. Batched scatter: 32 poses at 64 x 64 (a training batch's targets), one
transport per pose against one shared transport for all (same seeds, same images).

The panel shows the same AP pose in line, poly, and full physics with noise, and the scatter
image alone. ``--spr-table`` prints the scatter-to-primary ratio at the detector centre for
water slabs of 5-30 cm (120 kVp, 30 x 30 cm field, 100 mm air gap), with and without a
ratio-10 grid, next to the independent NumPy Monte Carlo without a grid.
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
    ap.add_argument("--spr-table", action="store_true", help="also print the SPR table of water slabs")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import numpy as np

    from sim.ct.io import load_ct
    from sim.projection.geometry import pose_from_params
    from sim.physics.imaging import PhysicsSettings, XRayImager
    from sim.projection.drr import DRRRenderer, RenderSettings

    ct = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"
    if not ct.is_file():
        print(f"skipped: {ct} not found (see ../shared/data/README)")
        return 0
    vol = load_ct(ct)
    size = (args.size, args.size)
    line = DRRRenderer(vol, RenderSettings(size=size))
    quiet = XRayImager(vol, PhysicsSettings(noise=False), size=size, center_lps=line.center_lps)
    noisy = XRayImager(vol, PhysicsSettings(noise=True), size=size, center_lps=line.center_lps)
    full_quiet = XRayImager(vol, PhysicsSettings(level="full", noise=False), size=size, center_lps=line.center_lps)
    full = XRayImager(vol, PhysicsSettings(level="full", noise=True), size=size, center_lps=line.center_lps)
    pose = pose_from_params(np.zeros(6), line.geometry.sod_mm)
    rows = [("line", timed(lambda: line.render(pose), args.repeats)),
            ("poly, no noise", timed(lambda: quiet.render(pose), args.repeats)),
            ("poly + noise", timed(lambda: noisy.render(pose), args.repeats)),
            ("full (10^6 histories), no noise", timed(lambda: full_quiet.render(pose), args.repeats)),
            ("full + noise", timed(lambda: full.render(pose), args.repeats))]
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, pelvis_abdomen_3mm, {args.size}x{args.size}, AP, "
          f"median of {args.repeats}")
    print("| physics | ms per image | ratio to line |")
    print("|---|---|---|")
    for name, t in rows:
        print(f"| {name} | {t * 1e3:.1f} | {t / rows[0][1]:.1f} |")
    _throughput(full_quiet, pose, args.repeats)
    _batched(vol, line.center_lps, args.repeats)
    if args.spr_table:
        _spr_table()
    if args.panel:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from sim.core.atomic import save_figure

        f = full.render(pose)
        images = [("line (60 keV line integral)", line.render(pose)[0]),
                  ("poly, 120 kVp: -log(I/I0)", quiet.render(pose)["log"][0]),
                  ("poly + scatter + noise: -log(I/I0)", f["log"][0]),
                  ("scatter alone (keV per pixel)", f["scatter"][0])]
        fig, axes = plt.subplots(1, 4, figsize=(15, 4))
        for ax, (title, im) in zip(axes, images):
            lo, hi = np.percentile(im, [0.5, 99.5])
            ax.imshow(im, cmap="gray", vmin=lo, vmax=hi)
            ax.set_title(title, fontsize=9)
            ax.set_axis_off()
        save_figure(fig, args.panel)
        print(f"wrote {args.panel}")
    return 0


def _slab_transport(thickness_mm, spectrum, detector, **settings):
    import numpy as np

    from sim.physics.scatter import MonteCarloScatter, ScatterSettings

    vox, lat = 5.0, 400.0
    n = (int(lat / vox), int(lat / vox), int(round(thickness_mm / vox)))
    aff = np.diag([vox, vox, vox, 1.0])
    aff[:3, 3] = (-lat / 2 + vox / 2, -lat / 2 + vox / 2, 900.0 - thickness_mm + vox / 2)
    return MonteCarloScatter(np.ones((1,) + n, np.float32), aff, ("water",), spectrum, detector,
                             ScatterSettings(voxel_mm=vox, cell_px=15, **settings))


SLAB_GEOMETRY = dict(sdd_mm=1000.0, sod_mm=800.0, height=150, width=150, pixel_spacing_mm=2.0)


def _throughput(imager, pose, repeats: int) -> None:
    """Histories per second: Dr.Jit transport on the pelvis and a slab; NumPy peer on the slab."""
    import numpy as np

    from sim.projection.geometry import CArmGeometry, extrinsic_lps_to_camera
    from tests.sim.slab_mc import run_slab

    n = 2_000_000
    mc = imager.scatter
    cam = np.linalg.inv(extrinsic_lps_to_camera(pose, imager.renderer.center_lps))
    t_pelvis = timed(lambda: mc.run(cam, imager.geometry, photons_per_pixel=1.0, photons=n), repeats)
    slab = _slab_transport(200.0, imager.spectrum, imager.detector)
    geom = CArmGeometry(**SLAB_GEOMETRY)
    t_slab = timed(lambda: slab.run(np.eye(4), geom, photons_per_pixel=1.0, photons=n), repeats)
    n_ref = 200_000
    t_ref = timed(lambda: run_slab(thickness_mm=200.0, lateral_mm=400.0, z_entry_mm=700.0, sdd_mm=1000.0,
                                   detector_mm=300.0, spectrum=imager.spectrum, detector=imager.detector,
                                   photons=n_ref), max(1, repeats // 2))
    print()
    print("| Monte Carlo (120 kVp) | histories per second | ratio to NumPy peer |")
    print("|---|---|---|")
    ref = n_ref / t_ref
    for name, rate in (("Dr.Jit, pelvis at AP (6 mm grid)", n / t_pelvis), ("Dr.Jit, 20 cm water slab", n / t_slab),
                       ("NumPy analog peer, same slab", ref)):
        print(f"| {name} | {rate:.3g} | {rate / ref:.1f} |")


def _batched(vol, center_lps, repeats: int) -> None:
    """Scatter of 32 poses at 64 x 64 with 3 x 10^4 histories each (a training batch's
    targets): one ``run`` per pose against one ``run_batch`` for all, same seeds and results."""
    import numpy as np

    from sim.campaign.poses import ORIGINAL_PROTOCOL
    from sim.projection.geometry import extrinsic_lps_to_camera, pose_from_params
    from sim.physics.imaging import PhysicsSettings, XRayImager

    small = XRayImager(vol, PhysicsSettings(level="full", noise=False, scatter_photons=30_000), size=(64, 64),
                       center_lps=center_lps)
    poses = pose_from_params(ORIGINAL_PROTOCOL.sample(np.random.default_rng(0), 32), small.geometry.sod_mm)
    cams = np.linalg.inv(extrinsic_lps_to_camera(poses, center_lps))
    mc, g, seeds = small.scatter, small.geometry, list(range(32))
    t_one = timed(lambda: [mc.run(c, g, photons_per_pixel=1.0, seed=s) for c, s in zip(cams, seeds)], repeats)
    t_batch = timed(lambda: mc.run_batch(cams, g, photons_per_pixel=1.0, seeds=seeds), repeats)
    print()
    print("| scatter, 32 poses, 64 x 64, 3e4 histories each | ms per pose | ratio |")
    print("|---|---|---|")
    print(f"| one run per pose | {t_one / 32 * 1e3:.1f} | 1.0 |")
    print(f"| run_batch, all 32 poses | {t_batch / 32 * 1e3:.1f} | {t_one / t_batch:.1f}x faster |")


def _spr_table() -> None:
    """SPR at the detector centre of water slabs (100 mm air gap, 30 x 30 cm field, 120 kVp)."""
    import numpy as np

    from sim.projection.geometry import CArmGeometry
    from sim.physics.poly import Detector, Polychromatic
    from sim.physics.spectrum import tube_spectrum
    from tests.sim.slab_mc import run_slab

    spec, det = tube_spectrum(120.0), Detector()
    geom = CArmGeometry(**SLAB_GEOMETRY)
    model = Polychromatic(spec, det, ("water",))
    exposure = dict(mas=1.0, sdd_mm=1000.0, pixel_area_mm2=4.0)
    n0 = model.photons_per_pixel(**exposure).sum()
    print()
    print("| water slab (cm) | SPR, no grid | SPR, grid r=10 (T_p 0.7) | SPR, NumPy peer, no grid |")
    print("|---|---|---|---|")
    for cm in (5, 10, 20, 30):
        primary = model.expected(np.full((1, 1, 1, 1), float(cm)), **exposure)[0, 0, 0] / n0
        spr = []
        for grid in (0.0, 10.0):
            mc = _slab_transport(10.0 * cm, spec, det, grid_ratio=grid, photons=2_000_000)
            out = mc.run(np.eye(4), geom, photons_per_pixel=1.0, seed=cm)
            spr.append(out["scatter"][4:6, 4:6].mean() / (primary * (0.7 if grid else 1.0)))
        ref = run_slab(thickness_mm=10.0 * cm, lateral_mm=400.0, z_entry_mm=900.0 - 10.0 * cm, sdd_mm=1000.0,
                       detector_mm=300.0, spectrum=spec, detector=det, photons=400_000, seed=cm)
        ref_spr = ref["central"] * 300.0**2 / primary  # per mm^2 per photon -> per photon per pixel
        print(f"| {cm} | {spr[0]:.2f} | {spr[1]:.3f} | {ref_spr:.2f} +- {ref_spr * ref['central_rel_se']:.2f} |")


if __name__ == "__main__":
    sys.exit(main())
