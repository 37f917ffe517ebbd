"""Figures of a registration: edge overlay of the final DRR on the X-ray, and convergence."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _window(img: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(img, (0.5, 99.5))
    return np.clip((img - lo) / max(hi - lo, 1e-12), 0, 1)


def overlay_png(xray: np.ndarray, drr: np.ndarray, path: str | Path) -> None:
    """The X-ray in grey with the DRR's strongest edges (top 8 % of Sobel magnitude) in red."""
    from PIL import Image
    from scipy import ndimage

    from sim.atomic import atomic_path

    grey = _window(np.asarray(xray, float))
    mag = np.hypot(ndimage.sobel(drr, 0), ndimage.sobel(drr, 1))
    edges = mag > np.percentile(mag, 92)
    rgb = np.stack([grey] * 3, -1)
    rgb[edges] = (1.0, 0.15, 0.1)
    with atomic_path(path) as tmp:
        Image.fromarray((rgb * 255 + 0.5).astype(np.uint8)).save(tmp, format="PNG")


def convergence_plot(history, path: str | Path) -> None:
    """Best similarity per generation / polish step, one colour per stage."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim.atomic import save_figure

    fig, ax = plt.subplots(figsize=(6, 3.5))
    stages = []
    for stage, *_ in history:
        if stage not in stages:
            stages.append(stage)
    x = 0
    for stage in stages:
        ys = [h[1] for h in history if h[0] == stage]
        ax.plot(range(x, x + len(ys)), ys, marker="." if len(ys) < 3 else None, label=stage)
        x += len(ys)
    ax.set_xlabel("generation (CMA-ES) / polish")
    ax.set_ylabel("best similarity")
    ax.legend()
    save_figure(fig, path)


def trajectory_figure(xray: np.ndarray, drrs: np.ndarray, params: np.ndarray, path: str | Path,
                      panels: int = 6) -> None:
    """The contextual iteration at ``panels`` evenly spaced steps: the X-ray with the DRR's
    strongest edges in red (as :func:`overlay_png`), titled with the iteration and pose.

    ``xray`` ``(H, W)``; ``drrs`` ``(K, H, W)``; ``params`` ``(>= K, 6)`` (deg, mm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import ndimage

    from sim.atomic import save_figure

    k = len(drrs)
    steps = sorted(set(np.linspace(0, k - 1, min(panels, k)).round().astype(int).tolist()))
    fig, axes = plt.subplots(1, len(steps), figsize=(2.6 * len(steps), 2.9), squeeze=False)
    grey = _window(np.asarray(xray, float))
    for ax, i in zip(axes[0], steps):
        drr = drrs[i]
        mag = np.hypot(ndimage.sobel(drr, 0), ndimage.sobel(drr, 1))
        rgb = np.stack([grey] * 3, -1)
        rgb[mag > np.percentile(mag, 92)] = (1.0, 0.1, 0.1)
        ax.imshow(rgb)
        ax.set_axis_off()
        p = params[i]
        ax.set_title(f"iteration {i}\n{p[0]:.0f} {p[1]:.0f} {p[2]:.0f} deg\n{p[3]:.0f} {p[4]:.0f} {p[5]:.0f} mm",
                     fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
