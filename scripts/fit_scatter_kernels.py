"""Fit the committed scatter-kernel table (sim/physics/scatter_kernels_pelvis.json).

Monte Carlo scatter (:mod:`sim.physics.scatter`) of the pelvis CT (``pelvis_abdomen_3mm``) at
``--poses`` poses drawn from the training protocol (phi +-40, theta +-20, psi +-20 deg, offsets
+-75 mm), at each tube voltage of ``--kvps`` without a grid and with grids of ``--grid-ratios``;
one :class:`sim.physics.scatter_kernel.ScatterKernelModel` fitted per (kVp, grid), all on the
same thickness nodes, written as one :class:`ScatterKernelTable` (atomically). Progress with
rate and ETA on stderr; about 5 minutes on 2 cores at the defaults.

    .venv/bin/python scripts/fit_scatter_kernels.py [--kvps 60 95 130] [--grid-ratios 6 16]
        [--poses 16] [--photons 1000000] [--size 64] [--out sim/physics/scatter_kernels_pelvis.json]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kvps", type=float, nargs="+", default=[60.0, 95.0, 130.0], help="tube voltages, kV (default: 60 95 130)")
    ap.add_argument("--grid-ratios", type=float, nargs="*", default=[6.0, 16.0], help="grid ratios besides no grid (default: 6 16)")
    ap.add_argument("--poses", type=int, default=16, help="fitting poses (default: 16)")
    ap.add_argument("--photons", type=int, default=1_000_000,
                    help="Monte Carlo histories per pose (default: 1e6, the committed table's)")
    ap.add_argument("--size", type=int, default=64, help="image side, px (default: 64)")
    ap.add_argument("--cell-px", type=int, default=4, help="Monte Carlo tally cell, px (default: 4)")
    ap.add_argument("--ct", default=str(REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"),
                    help="the CT (default: ../shared/data/ct/pelvis_abdomen_3mm.nii.gz)")
    ap.add_argument("--out", default=str(REPO / "sim" / "physics" / "scatter_kernels_pelvis.json"),
                    help="the table, written atomically (default: the committed one)")
    args = ap.parse_args(argv)
    if len(args.kvps) < 2 or any(k <= 0 for k in args.kvps) or any(r <= 0 for r in args.grid_ratios):
        ap.error("--kvps needs two or more positive kV values; --grid-ratios positive ratios")
    if not Path(args.ct).is_file():
        print(f"error: CT {args.ct} not found (see ../shared/data/README)", file=sys.stderr)
        return 2
    sys.path.insert(0, str(REPO))
    import numpy as np

    from sim.ct.io import load_ct
    from sim.projection.geometry import pose_from_params
    from sim.physics.imaging import PhysicsSettings, XRayImager
    from sim.physics.scatter_kernel import (ScatterKernelTable, data_tau_nodes, fit_maps, monte_carlo_maps,
                                            physics_record)
    from sim.core.progress import Progress

    volume = load_ct(args.ct)
    size = (args.size, args.size)
    grids = [0.0] + sorted(args.grid_ratios)
    imagers = {(k, g): XRayImager(volume, PhysicsSettings(level="poly", noise=False, kvp=k, grid_ratio=g), size=size)
               for k in args.kvps for g in grids}
    first = imagers[args.kvps[0], 0.0]
    rng = np.random.default_rng(28)
    lim = np.array([40.0, 20.0, 20.0, 75.0, 75.0, 75.0])
    poses = pose_from_params(rng.uniform(-lim, lim, size=(args.poses, 6)), first.geometry.sod_mm)

    def log_primary(im):
        return -np.log(im.model.expected(im.renderer.render(poses), **im.exposure) / im.model.flat_field(**im.exposure))

    nodes = data_tau_nodes(np.concatenate([log_primary(imagers[k, 0.0]) for k in args.kvps]))
    models = []
    progress = Progress(len(imagers), 0, "scatter kernels", unit="fits")
    t0 = time.perf_counter()
    for (k, g), im in imagers.items():
        m = monte_carlo_maps(im, poses, cell_px=args.cell_px, photons=args.photons,
                             seeds=[1000 * int(k) + 10 * int(g) + b for b in range(len(poses))])
        model = fit_maps(m["log"], m["cells"], im.geometry, cell_px=args.cell_px, gap_mm=m["gap_mm"], tau_nodes=nodes,
                         signal_per_photon=m["signal_per_photon"], settings=physics_record(im.physics))
        spr = float(m["cells"].mean() * 1.0)
        print(f"{k:5.0f} kV grid {g:4.1f}: MC {m['seconds']:.1f} s, fit rms {model.fit_rms:.3f}, mean scatter/I0 "
              f"{spr:.3f}, aspect {model.aspect:.2f}, zeta {model.gap_exponent:.2f}", flush=True)
        models.append(model)
        progress.update(1)
    table = ScatterKernelTable(tuple(models), subject=f"{Path(args.ct).name}, {args.poses} poses, "
                                                     f"{args.photons:.0e} histories, {args.size}x{args.size}")
    table.save(args.out)
    print(f"wrote {args.out} ({len(models)} models, {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
