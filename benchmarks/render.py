"""Renderer benchmark: median ms per line-integral DRR, ctxreg against DiffDRR in the same run.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/render.py [--repeats 15] [--peer-repeats 3] [--sizes 256 128]

For each CT of ``../shared/data/ct`` (chest 512 x 512 x 133 at 0.7 x 0.7 x 2.5 mm; pelvis
122 x 101 x 112 at 3 mm) and each detector size, at the AP pose about the anatomy centre of
the Cios Fusion scene, it prints:

* ctxreg Siddon and trilinear: median ms per image after warm-up, the first call (kernel
  compile, measured cold: Dr.Jit's on-disk kernel cache is pointed at an empty folder), and a
  batch of 16 poses per launch (ms per image);
* DiffDRR 0.6.1 (CPU, 2 torch threads) Siddon and trilinear (its default 500 points, and
  a step of half the smallest voxel), when it is installed (``pip install -e ".[bench]"``);
* the relative L2 difference of each image to ctxreg's Siddon image, and the speed ratio;
* the gather floor (:func:`gather_floor`): a Dr.Jit symbolic loop that does nothing but read the
  CT's stored volume (its size and layout), two gathers per iteration, neighbouring lanes reading
  neighbouring voxels and marching along the slowest axis as an AP ray does ("coherent"), or from
  scattered places ("scattered"); and each Siddon row's time over the floor's time for its voxel
  steps ("x floor"): the Siddon loop does one gather per voxel step plus the traversal's
  arithmetic, so this ratio is what the traversal costs beyond its memory reads.

The last lines read ``speedup_vs_diffdrr: R`` (DiffDRR's faster renderer's median over ctxreg
Siddon's median for the 256 x 256 chest case, ``n/a`` without DiffDRR) and ``kernel_vs_floor: R``
(the same Siddon median over the coherent floor's time for its voxel steps).
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
DATA = REPO.parent / "shared" / "data" / "ct"
CTS = {"chest": DATA / "chest_0p7x2p5mm.nii.gz", "pelvis": DATA / "pelvis_abdomen_3mm.nii.gz"}


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def voxel_steps(renderer, pose) -> int:
    """Voxels crossed by all rays of one image (the Siddon loop's iteration count), in NumPy."""
    import numpy as np

    g = renderer.geometry
    m = renderer.world_to_index(pose[None])[0]  # camera mm -> voxel index
    d = g.pixel_centers_camera().reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    o = m[:3, 3] + 0.5  # voxel i spans [i, i + 1]
    dv = d @ m[:3, :3].T
    n = np.array(renderer.volume.shape, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (0.0 - o) / dv, (n - o) / dv
    t_in = np.nanmax(np.minimum(t0, t1), axis=1)
    t_out = np.nanmin(np.maximum(t0, t1), axis=1)
    hit = t_out > t_in
    p_in = np.floor(o + dv[hit] * t_in[hit, None] + 1e-6 * dv[hit])
    p_out = np.floor(o + dv[hit] * t_out[hit, None] - 1e-6 * dv[hit])
    return int((np.abs(p_out - p_in).sum(1) + 1).sum())


def gather_floor(shape_words: tuple[int, int, int], repeats: int, *, coherent: bool,
                 rays: tuple[int, int] = (256, 256)) -> float:
    """Gathers per second of a loop that only gathers: ``rays`` ``(rows, cols)`` lanes each read
    ``shape_words[0] - 1`` voxels of a ``(slow, middle, fast)`` float32 volume (the stored CT), one
    per step along the slow axis, two per loop iteration (the loop's own overhead halved).

    ``coherent``: lane ``(r, c)`` starts at fast index ``2 c`` and middle index ``r // 3`` (an AP
    ray at 256 x 256 over a 512-wide CT: neighbouring lanes two voxels apart, three rows per
    slice), so one SIMD packet's reads share cache lines; else at scattered places (a hash)."""
    import numpy as np

    from sim.projection.backend import ensure_variant

    ensure_variant()
    import drjit as dr
    import mitsuba as mi

    n_slow, n_mid, n_fast = shape_words
    volume = mi.Float(np.random.default_rng(0).random(n_slow * n_mid * n_fast, dtype=np.float32))
    n_rays = rays[0] * rays[1]
    steps = (n_slow - 1) // 2 * 2

    def run():
        lane = dr.arange(mi.UInt32, n_rays)
        row = lane // rays[1]
        col = lane - row * rays[1]
        if coherent:
            base = (col * 2) % n_fast + ((row // 3) % n_mid) * n_fast
        else:
            base = (lane * 2654435761) % (n_mid * n_fast)
        stride = dr.opaque(mi.UInt32, n_mid * n_fast)
        end = dr.opaque(mi.UInt32, steps)

        def body(k, acc):
            at = base + k * stride
            return k + 2, acc + dr.gather(mi.Float, volume, at) + dr.gather(mi.Float, volume, at + stride)

        _, acc = dr.while_loop((mi.UInt32(0), mi.Float(0.0)), lambda k, acc: k < end, body)
        dr.eval(acc)
        dr.sync_thread()

    run()
    return n_rays * steps / (median_ms(run, repeats) / 1e3)


def rel_l2(a, b) -> float:
    import numpy as np

    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=15, help="timed ctxreg renders per case (default: 15)")
    ap.add_argument("--peer-repeats", type=int, default=3, help="timed DiffDRR renders per case (default: 3)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 128], help="square detector sizes (px)")
    ap.add_argument("--cts", nargs="+", default=list(CTS), choices=list(CTS), help="which CTs")
    ap.add_argument("--warm-cache", action="store_true",
                    help="keep Dr.Jit's kernel cache (first-call times then exclude compiling)")
    args = ap.parse_args(argv)
    if not args.warm_cache:  # before Dr.Jit starts: an empty kernel cache makes compiles real
        os.environ["HOME"] = tempfile.mkdtemp(prefix="ctxreg-bench-home-")
    sys.path.insert(0, str(REPO))

    import numpy as np

    from sim.ct.io import load_ct
    from sim.projection.geometry import extrinsic_lps_to_camera, pose_from_params
    from sim.projection.drr import DRRRenderer, RenderSettings

    try:
        sys.path.insert(0, str(REPO / "benchmarks"))
        import diffdrr_peer
        import torch

        diffdrr_peer._import_diffdrr()
        torch.set_num_threads(2)
        peer_ok = True
    except ImportError as e:
        print(f"# DiffDRR not available ({e}); peer columns skipped")
        peer_ok = False

    rows = []
    speedup = floor_ratio = None
    floors = []  # (CT, kind, G gathers/s)
    rng = np.random.default_rng(0)
    for ct_name in args.cts:
        if not CTS[ct_name].is_file():
            print(f"# {CTS[ct_name]} not found; skipping {ct_name}")
            continue
        vol = load_ct(CTS[ct_name])
        from sim.projection.drr import memory_order

        order = memory_order(vol.affine)
        stored = tuple(vol.shape[a] + 2 for a in order)  # the integrator's padded volume, slowest first
        floor = {kind: gather_floor(stored, args.repeats, coherent=kind == "coherent")
                 for kind in ("coherent", "scattered")}
        floors += [(ct_name, stored, kind, rate) for kind, rate in floor.items()]
        for size in args.sizes:
            ref = None
            results, images = {}, {}
            for model in ("siddon", "trilinear"):
                t0 = time.perf_counter()
                r = DRRRenderer(vol, RenderSettings(size=(size, size), ray_model=model))
                setup_ms = (time.perf_counter() - t0) * 1e3
                pose = pose_from_params(np.zeros(6), r.geometry.sod_mm)
                t0 = time.perf_counter()
                img = r.render(pose)[0]
                first_ms = (time.perf_counter() - t0) * 1e3
                ms = median_ms(lambda: r.render(pose), args.repeats)
                batch = pose_from_params(rng.uniform(-1, 1, (16, 6)) * [40, 20, 20, 75, 75, 75],
                                         r.geometry.sod_mm)
                r.render(batch)
                batch_ms = median_ms(lambda: r.render(batch), max(3, args.repeats // 4)) / len(batch)
                if model == "siddon":
                    ref = img
                results[model], images[model] = ms, img
                name = f"ctxreg {model}"
                rows.append((ct_name, size, name, ms, first_ms, batch_ms, setup_ms,
                             rel_l2(img, ref), None, None))
                if model == "siddon":  # loop iterations per second: one gather each
                    steps = voxel_steps(r, pose)
                    over = ms / (steps / floor["coherent"] * 1e3)
                    rows[-1] = rows[-1][:2] + (f"{name} ({steps / ms / 1e6:.2f} G voxel steps/s, "
                                               f"{over:.1f}x floor)",) + rows[-1][3:]
                    if ct_name == "chest" and size == 256:
                        floor_ratio = over
            if peer_ok:
                extr = extrinsic_lps_to_camera(pose, r.center_lps)
                g = r.geometry
                peer_cases = [("siddon", {}), ("trilinear", {}),
                              ("trilinear", {"step_mm": 0.5 * float(vol.spacing_mm.min())})]
                peer_ms = []
                for model, extra in peer_cases:
                    prep = diffdrr_peer.prepare(vol.hu, vol.affine, extr, g.sdd_mm, g.height, g.width,
                                                g.pixel_spacing_mm, renderer=model, **extra)
                    t0 = time.perf_counter()
                    img = diffdrr_peer.render(prep)
                    first_ms = (time.perf_counter() - t0) * 1e3
                    ms = median_ms(lambda: diffdrr_peer.render(prep), args.peer_repeats)
                    label = f"DiffDRR {model}" + (f" n={prep.n_points}" if prep.n_points else "")
                    peer_ms.append(ms)
                    rows.append((ct_name, size, label, ms, first_ms, None, prep.prepare_s * 1e3,
                                 rel_l2(img, ref), rel_l2(img, images[model]), ms / results["siddon"]))
                if ct_name == "chest" and size == 256:
                    speedup = min(peer_ms) / results["siddon"]

    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, {os.cpu_count()} CPU threads, AP pose, scene cios_fusion")
    head = ("CT", "size", "renderer", "median ms", "first call ms", "compile ms", "batch16 ms/img", "set-up ms",
            "rel L2 vs ctxreg siddon", "rel L2 vs ctxreg same model", "ctxreg siddon speedup")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for ct, size, name, ms, first, batch, setup, l2, l2_same, ratio in rows:
        compile_ms = f"{max(first - ms, 0.0):.0f}" if name.startswith("ctxreg") else ""
        cells = [ct, f"{size}x{size}", name, f"{ms:.1f}", f"{first:.0f}", compile_ms,
                 "" if batch is None else f"{batch:.1f}", f"{setup:.0f}", f"{l2:.5f}",
                 "" if l2_same is None else f"{l2_same:.5f}", "" if ratio is None else f"{ratio:.0f}x"]
        print("| " + " | ".join(cells) + " |")
    print()
    print("| CT | stored volume (slow, middle, fast) | gather floor | G gathers/s |")
    print("|---|---|---|---|")
    for ct, shape, kind, rate in floors:
        print(f"| {ct} | {shape} | {kind} | {rate / 1e9:.2f} |")
    print(f"speedup_vs_diffdrr: {'n/a' if speedup is None else f'{speedup:.1f}'}")
    print(f"kernel_vs_floor: {'n/a' if floor_ratio is None else f'{floor_ratio:.2f}'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
