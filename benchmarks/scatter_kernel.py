"""Scatter-kernel model (sim/physics/scatter_kernel.py) against the Monte Carlo: error and speed.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/scatter_kernel.py [--size 64] [--photons 200000] [--train 16] [--test 6]
        [--grid-ratio 10] [--json out.json]

On the pelvis CT (``pelvis_abdomen_3mm``): poses drawn uniformly from the training protocol's
angles (phi +-40, theta +-20, psi +-20 deg) with offsets of +-40 mm; one model fitted per
setting (80 and 120 kVp, without and with a ratio ``--grid-ratio`` grid) on ``--train`` poses,
then evaluated on ``--test`` held-out poses, on a held-out kVp (100 kVp from the 80 and 120 kVp
fits by :func:`interpolate_kvp`, 140 kVp extrapolated), and on a held-out subject (the built-in
phantom, seed 0, with the pelvis fits); then the committed table
(``sim/physics/scatter_kernels_pelvis.json``, training's ``sks`` scatter) at tube voltages and
grid ratios between its fits (65 and 110 kVp without a grid, 75 kVp ratio 10, 120 kVp ratio 12) and
on the phantom (80 kVp), unless ``--no-table``.

Reference: the mean of two Monte Carlo runs with different seeds per held-out pose (images as
``XRayImager`` makes them: cells of ``--cell-px`` pixels, 6 mm Gaussian, bilinear). Errors per
pose, then the mean and the worst over the poses:

* SPR field / centre: relative error of the scatter-to-primary ratio ``sum S / sum P`` over
  the whole detector / over its central quarter (half the width and height);
* L2: ``||S_model - S_ref|| / ||S_ref||`` over the pixels; max: ``max |S_model - S_ref| / max S_ref``;
  "L2 beyond ref noise": ``sqrt(L2^2 - (L2_MC / 2)^2)`` with ``L2_MC`` the seed-to-seed L2 (the
  reference's own noise is about half of it): the part of the model's L2 that noise does not
  explain.

The row "MC seed vs seed" gives the same numbers for one Monte Carlo run against the other:
the Monte Carlo's own noise (one run's error against the truth is about that / sqrt(2), the
two-run reference's about half of it). Speed: median time per image of the model
(``predict`` and ``scatter_photons``, batches of 8 poses with their air gaps) against the
``full`` level's own Monte Carlo path (``XRayImager._scatter_images``: one ``run_batch`` of the 8
poses, cells of 8 pixels, smoothing and interpolation of signal and photons) at 64 x 64 with
3 x 10^4 histories (the training targets) and at 128 x 128 with 10^5 (registration's moving
images), same run; both start from the rendered primary. About 2.5 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

from timing import timed  # noqa: E402  (benchmarks/timing.py)


def _poses(rng, n: int, sod_mm: float):
    import numpy as np

    from sim.projection.geometry import pose_from_params

    lim = np.array([40.0, 20.0, 20.0, 40.0, 40.0, 40.0])
    return pose_from_params(rng.uniform(-lim, lim, size=(n, 6)), sod_mm)


def _errors(pred, primary, ref):
    """Per-pose errors of ``pred`` against ``ref`` (both (B, H, W)), with primary (B, H, W)."""
    import numpy as np

    b, h, w = ref.shape
    c = (slice(None), slice(h // 4, h - h // 4), slice(w // 4, w - w // 4))
    spr = lambda s, sl=(slice(None),): s[sl].reshape(b, -1).sum(1) / primary[sl].reshape(b, -1).sum(1)  # noqa: E731
    return {
        "spr_field_signed": spr(pred) / spr(ref) - 1,
        "spr_field": np.abs(spr(pred) / spr(ref) - 1),
        "spr_centre": np.abs(spr(pred, c) / spr(ref, c) - 1),
        "l2": np.linalg.norm((pred - ref).reshape(b, -1), axis=1) / np.linalg.norm(ref.reshape(b, -1), axis=1),
        "max": np.abs(pred - ref).reshape(b, -1).max(1) / ref.reshape(b, -1).max(1),
        "spr_ref": spr(ref),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=64, help="image side in pixels (default: 64)")
    ap.add_argument("--photons", type=int, default=200_000, help="Monte Carlo histories per image (default: 2e5)")
    ap.add_argument("--train", type=int, default=16, help="fitting poses per setting (default: 16)")
    ap.add_argument("--test", type=int, default=6, help="held-out poses (default: 6)")
    ap.add_argument("--cell-px", type=int, default=4, help="Monte Carlo tally cell, pixels (default: 4)")
    ap.add_argument("--grid-ratio", type=float, default=10.0, help="grid ratio of the grid rows (default: 10)")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats (default: 5)")
    ap.add_argument("--json", default=None, help="also write the numbers here")
    ap.add_argument("--no-table", action="store_true", help="leave out the committed table's rows")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import numpy as np

    from sim.core.atomic import write_json
    from sim.ct.io import load_ct
    from sim.ct.phantom import make_pelvis_phantom
    from sim.physics.imaging import PhysicsSettings, XRayImager
    from sim.physics.scatter_kernel import (data_tau_nodes, default_table, detector_gap_mm, fit_maps,
                                            interpolate_kvp, monte_carlo_maps, physics_record)

    ct_path = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"
    if not ct_path.is_file():
        print(f"skipped: {ct_path} not found (see ../shared/data/README)")
        return 0
    t_start = time.perf_counter()
    pelvis = load_ct(ct_path)
    phantom = make_pelvis_phantom(0, spacing_mm=3.0)
    size = (args.size, args.size)
    rng = np.random.default_rng(15)
    imagers: dict = {}

    def imager(subject: str, kvp: float, grid: float, sz=size) -> XRayImager:
        key = (subject, kvp, grid, sz)
        if key not in imagers:
            vol = pelvis if subject == "pelvis" else phantom
            physics = PhysicsSettings(level="poly", noise=False, kvp=kvp, grid_ratio=grid)
            imagers[key] = XRayImager(vol, physics, size=sz)
        return imagers[key]

    sod = imager("pelvis", 120.0, 0.0).geometry.sod_mm
    train_poses = _poses(rng, args.train, sod)
    test_poses = _poses(rng, args.test, sod)
    geometry = imager("pelvis", 120.0, 0.0).geometry
    mcs: dict = {}

    def maps(subject, kvp, grid, poses, seed0):
        im = imager(subject, kvp, grid)
        key = (subject, kvp, grid)
        out = monte_carlo_maps(im, poses, cell_px=args.cell_px, photons=args.photons,
                               seeds=[seed0 + b for b in range(len(poses))], mc=mcs.get(key))
        mcs[key] = out["mc"]
        return out

    grids = (0.0, args.grid_ratio)
    # one set of thickness nodes for every fit (kVp interpolation needs them equal): from the
    # fitting poses' primaries at both kVps
    def primary_log(im, poses):
        return -np.log(im.model.expected(im.renderer.render(poses), **im.exposure) / im.model.flat_field(**im.exposure))

    nodes = data_tau_nodes(np.concatenate([primary_log(imager("pelvis", kvp, 0.0), train_poses)
                                           for kvp in (80.0, 120.0)]))
    models, fit_s = {}, {}
    for kvp in (80.0, 120.0):
        for grid in grids:
            m = maps("pelvis", kvp, grid, train_poses, 100)
            t0 = time.perf_counter()
            models[kvp, grid] = fit_maps(m["log"], m["cells"], geometry, cell_px=args.cell_px, gap_mm=m["gap_mm"],
                                         tau_nodes=nodes, signal_per_photon=m["signal_per_photon"],
                                         settings=physics_record(imager("pelvis", kvp, grid).physics))
            fit_s[kvp, grid] = time.perf_counter() - t0

    rows = []

    def evaluate(label, subject, kvp, grid, model):
        a = maps(subject, kvp, grid, test_poses, 1000)
        b = maps(subject, kvp, grid, test_poses, 2000)
        ref = 0.5 * (a["image"] + b["image"])
        pred = model.predict(a["log"], geometry, flat_signal=a["flat"], gap_mm=a["gap_mm"])
        e = _errors(pred, a["primary"], ref)
        n = _errors(b["image"], a["primary"], a["image"])
        # the reference's own noise is about half the seed-to-seed difference; what exceeds it
        e["l2_excess"] = np.sqrt(np.maximum(e["l2"] ** 2 - (n["l2"] / 2) ** 2, 0.0))
        rows.append((label, kvp, grid, e, n, model.fit_rms))

    for kvp in (80.0, 120.0):
        for grid in grids:
            evaluate("held-out poses", "pelvis", kvp, grid, models[kvp, grid])
    for grid in grids:
        evaluate("held-out kVp (interpolated 80/120)", "pelvis", 100.0, grid,
                 interpolate_kvp([models[80.0, grid], models[120.0, grid]], 100.0))
        evaluate("held-out kVp (120 kVp model as is)", "pelvis", 100.0, grid, models[120.0, grid])
    evaluate("held-out kVp (extrapolated 80/120)", "pelvis", 140.0, 0.0,
             interpolate_kvp([models[80.0, 0.0], models[120.0, 0.0]], 140.0))
    for grid in grids:
        evaluate("held-out subject (phantom)", "phantom", 120.0, grid, models[120.0, grid])
    # the committed table (sim/physics/scatter_kernels_pelvis.json, what training's "sks"
    # scatter draws from) at kVs and grid ratios it was not fitted at, and on the phantom
    if not args.no_table:
        table = default_table()
        for kvp, grid in ((65.0, 0.0), (110.0, 0.0), (75.0, 10.0), (120.0, 12.0)):
            evaluate("committed table, interpolated", "pelvis", kvp, grid, table.model_for(kvp, grid))
        evaluate("committed table, held-out subject (phantom)", "phantom", 80.0, 0.0, table.model_for(80.0, 0.0))

    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, pelvis_abdomen_3mm, {args.size}x{args.size}, "
          f"{args.train} fitting poses, {args.test} held-out poses, {args.photons:.0e} histories per MC image, "
          f"cells of {args.cell_px} px")
    print("| case | kVp | grid | SPR (ref) | SPR field err mean / max (signed mean) | SPR centre err | L2 | "
          "L2 beyond ref noise | max err | MC seed vs seed: SPR field / centre / L2 / max |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    record = []
    for label, kvp, grid, e, n, rms in rows:
        f = lambda d, k: f"{100 * d[k].mean():.1f} / {100 * d[k].max():.1f} %"  # noqa: E731
        print(f"| {label} | {kvp:g} | {grid:g} | {e['spr_ref'].mean():.2f} | {f(e, 'spr_field')} "
              f"({100 * e['spr_field_signed'].mean():+.1f} %) | {f(e, 'spr_centre')} | {f(e, 'l2')} | "
              f"{100 * e['l2_excess'].mean():.1f} % | {f(e, 'max')} | "
              f"{100 * n['spr_field'].mean():.1f} / {100 * n['spr_centre'].mean():.1f} / "
              f"{100 * n['l2'].mean():.1f} / {100 * n['max'].mean():.1f} % |")
        record.append({"case": label, "kvp": kvp, "grid_ratio": grid,
                       "model": {k: v.tolist() for k, v in e.items()},
                       "mc_seed_vs_seed": {k: v.tolist() for k, v in n.items()}})
    print()
    print(f"thickness nodes (tau): {nodes}")
    print("| fit | fit rms (cells, incl. MC noise) | amplitudes | sigma1 / sigma2 at the nodes (mm) | broad share | "
          "aspect | gap exponent (ref gap) | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    for (kvp, grid), m in models.items():
        amps = ", ".join(f"{a:.3g}" for a in m.amplitude)
        widths = ", ".join(f"{a:.0f}/{b:.0f}" for a, b in zip(m.sigma1_mm, m.sigma2_mm))
        print(f"| {kvp:g} kVp, grid {grid:g} | {100 * m.fit_rms:.1f} % | {amps} | {widths} | "
              f"{m.broad_fraction[0]:.2f} | {m.aspect:.2f} | {m.gap_exponent:.2f} ({m.gap_ref_mm:.0f} mm) | "
              f"{fit_s[kvp, grid]:.1f} |")

    # ---- speed: the model against the Monte Carlo, same run
    print()
    print("| image | Monte Carlo ms per image | model ms per image | ratio | model ms per image per kernel |")
    print("|---|---|---|---|---|")
    speed = []
    for side, photons in ((64, 30_000), (128, 100_000)):
        # the full level's own Monte Carlo path (XRayImager._scatter_images: run_batch of the
        # 8 poses, cells of 8 px, smoothing, interpolation of signal and photons) against the
        # model's (predict, then photons); both start from the rendered primary
        full = XRayImager(pelvis, PhysicsSettings(level="full", noise=False, kvp=120.0, scatter_photons=photons),
                          size=(side, side))
        poses = _poses(np.random.default_rng(7), 8, sod)
        prim = full.model.expected(full.renderer.render(poses), **full.exposure)
        log = -np.log(prim / full.flat)
        gaps = detector_gap_mm(poses, full.geometry)
        t_mc = timed(lambda: full._scatter_images(poses, 0), args.repeats)
        model = models[120.0, 0.0]

        def kernel():
            s = model.predict(log, full.geometry, flat_signal=full.flat, gap_mm=gaps)
            return s, model.scatter_photons(s)
        t_model = timed(kernel, 4 * args.repeats)
        k = len(model.tau_nodes)
        print(f"| {side} x {side}, {photons:.0e} histories | {1e3 * t_mc / 8:.1f} | {1e3 * t_model / 8:.2f} | "
              f"{t_mc / t_model:.0f}x | {1e3 * t_model / 8 / k:.3f} |")
        speed.append({"side": side, "photons": photons, "mc_ms": 1e3 * t_mc / 8, "model_ms": 1e3 * t_model / 8,
                      "kernels": k})
    print(f"\n(total {time.perf_counter() - t_start:.0f} s)")
    if args.json:
        write_json(args.json, {"rows": record, "speed": speed,
                                               "models": {f"{k[0]:g}kV_grid{k[1]:g}": m.to_dict()
                                                          for k, m in models.items()}})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
