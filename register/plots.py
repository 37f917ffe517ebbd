"""Figures of a registration: edge overlay of the final DRR on the X-ray, and convergence."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.atomic import atomic_path, save_figure


def _window(img: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """``img`` mapped to [0, 1] by the 0.5 / 99.5 percentiles of the valid pixels."""
    v = img if mask is None or not mask.any() else img[mask]
    lo, hi = np.percentile(v, (0.5, 99.5))
    return np.clip((img - lo) / max(hi - lo, 1e-12), 0, 1)


def drr_edges(drr: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` bool: the DRR's edges (Canny; sigma 1 px per 256 px of the image's longer side,
    thresholds at the 80th / 95th percentile of the gradient magnitude), inside ``mask`` only."""
    from skimage.feature import canny

    sigma = max(1.0, max(drr.shape) / 256.0)
    edges = canny(np.asarray(drr, float), sigma=sigma, low_threshold=0.80, high_threshold=0.95,
                  use_quantiles=True)
    return edges if mask is None else edges & mask


def _outline(mask: np.ndarray) -> np.ndarray:
    """The one-pixel boundary of ``mask`` (its pixels next to an invalid one)."""
    from scipy import ndimage

    return mask & ~ndimage.binary_erosion(mask, border_value=0)


def _thicken(a: np.ndarray, px: int) -> np.ndarray:
    from scipy import ndimage

    return ndimage.binary_dilation(a, iterations=px) if px > 0 else a


def overlay_png(xray: np.ndarray, drr: np.ndarray, path: str | Path, mask: np.ndarray | None = None) -> None:
    """The X-ray in grey (windowed over the valid pixels) with the DRR's edges in red and the
    valid-pixel mask's outline in cyan, at the resolution of ``xray`` ``(H, W)`` (``drr`` the same
    shape: render it with the X-ray's own geometry). Lines are 1 px per 512 px of the longer side."""
    from PIL import Image

    xray = np.asarray(xray, float)
    if drr.shape != xray.shape:
        raise ValueError(f"overlay: the DRR {drr.shape} must have the X-ray's shape {xray.shape}")
    width = max(0, int(max(xray.shape) // 512))
    grey = _window(xray, mask)
    rgb = np.stack([grey] * 3, -1)
    rgb[_thicken(drr_edges(drr, mask), width)] = (1.0, 0.15, 0.1)
    if mask is not None and not mask.all():
        rgb[_thicken(_outline(mask), width)] = (0.1, 0.9, 1.0)
    with atomic_path(path) as tmp:
        Image.fromarray((rgb * 255 + 0.5).astype(np.uint8)).save(tmp, format="PNG")


def checkerboard_png(xray: np.ndarray, drr: np.ndarray, path: str | Path, mask: np.ndarray | None = None,
                     tiles: int = 8) -> None:
    """Alternating square tiles (``tiles`` along the longer side) of the preprocessed X-ray and the
    DRR, each windowed over the valid pixels (so both are bone bright on the same grey scale);
    pixels outside ``mask`` are dimmed to a quarter. Continuous structures across tile borders
    mean a good registration."""
    from PIL import Image

    xray = np.asarray(xray, float)
    if drr.shape != xray.shape:
        raise ValueError(f"checkerboard: the DRR {drr.shape} must have the X-ray's shape {xray.shape}")
    a, b = _window(xray, mask), _window(np.asarray(drr, float), mask)
    side = max(1, int(np.ceil(max(xray.shape) / tiles)))
    i, j = np.indices(xray.shape)
    img = np.where(((i // side) + (j // side)) % 2 == 0, a, b)
    if mask is not None:
        img = np.where(mask, img, 0.25 * img)
    with atomic_path(path) as tmp:
        Image.fromarray((img * 255 + 0.5).astype(np.uint8)).save(tmp, format="PNG")


def convergence_plot(history, path: str | Path) -> None:
    """Best similarity per generation / polish step, one colour per stage."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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


#: The trajectory figures' palette (indices of an 8-bit palette image): :data:`_GREYS` grey levels,
#: then the edges' red, white (separators, captions) and the errors' yellow. Built as indices, the
#: frames need no colour quantisation (an adaptive palette per frame took 0.8 s of a registration's
#: outputs) and no matplotlib.
_GREYS = 250
_RED, _WHITE, _YELLOW = _GREYS, _GREYS + 1, _GREYS + 2
_PALETTE = ([v for i in range(_GREYS) for v in (round(255 * i / (_GREYS - 1)),) * 3]
            + [255, 26, 26, 255, 255, 255, 255, 220, 120])


def _indices(img: np.ndarray, edges_of: np.ndarray | None = None) -> np.ndarray:
    """``img`` ``(H, W)`` windowed (:func:`_window`) to grey palette indices ``(H, W)`` uint8, with the
    strongest edges of ``edges_of`` (its Sobel magnitude above the 92nd percentile) in red."""
    from scipy import ndimage

    idx = np.rint(_window(np.asarray(img, float)) * (_GREYS - 1)).astype(np.uint8)
    if edges_of is not None:
        mag = np.hypot(ndimage.sobel(edges_of, 0), ndimage.sobel(edges_of, 1))
        idx[mag > np.percentile(mag, 92)] = _RED
    return idx


def _palette_image(idx: np.ndarray, scale: int):
    """A palette image of indices ``idx`` ``(H, W)``, each pixel ``scale x scale``."""
    from PIL import Image

    im = Image.fromarray(np.repeat(np.repeat(idx, scale, axis=0), scale, axis=1), mode="P")
    im.putpalette(_PALETTE)
    return im


def trajectory_figure(xray: np.ndarray, drrs: np.ndarray, params: np.ndarray, path: str | Path,
                      panels: int = 6, *, scale: int = 2) -> None:
    """The contextual iteration at ``panels`` evenly spaced steps, side by side: the X-ray with the
    DRR's strongest edges in red (as :func:`overlay_png`), captioned with the iteration and pose.

    ``xray`` ``(H, W)``; ``drrs`` ``(K, H, W)``; ``params`` ``(>= K, 6)`` (deg, mm); ``scale``
    pixels per image pixel. A PNG, written atomically (Pillow)."""
    from PIL import ImageDraw

    k = len(drrs)
    if k == 0:
        raise ValueError("trajectory_figure: no DRRs to show")  # a caller's bug: the iteration keeps one per step
    steps = sorted(set(np.linspace(0, k - 1, min(panels, k)).round().astype(int).tolist()))
    xray = np.asarray(xray, float)
    h, w = xray.shape
    caption, gap = 40, 4
    tiles = [np.pad(_indices(xray, np.asarray(drrs[i], float)), ((0, 0), (0, gap)), constant_values=_WHITE)
             for i in steps]
    canvas = np.concatenate(tiles, axis=1)[:, :-gap]
    img = _palette_image(np.pad(canvas, ((caption // scale + 1, 0), (0, 0)), constant_values=_WHITE), scale)
    draw = ImageDraw.Draw(img)
    for j, i in enumerate(steps):
        p = params[i]
        draw.multiline_text((j * (w + gap) * scale + 2, 1), f"iteration {i}\n{p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f} deg\n"
                            f"{p[3]:.0f}, {p[4]:.0f}, {p[5]:.0f} mm", fill=0, spacing=1)
    with atomic_path(Path(path)) as tmp:
        img.save(tmp, format="PNG")


def trajectory_gif(xray: np.ndarray, drrs: np.ndarray, params: np.ndarray, path: str | Path, *,
                   errors: list[str] | None = None, labels: list[str] | None = None, scale: int = 2,
                   frame_ms: int = 250) -> None:
    """An animated GIF of the contextual iteration: each frame the X-ray (left) beside the DRR of
    that iteration (right), the DRR's strongest edges in red over the X-ray, and a caption with the
    iteration (or ``labels[i]``), its pose and, when given, ``errors[i]`` (e.g. its error against
    the truth).

    ``xray`` ``(H, W)``; ``drrs`` ``(K, H, W)``; ``params`` ``(>= K, 6)`` (deg, mm); ``scale``
    pixels per image pixel; the last frame is held for 2 s. Written atomically (Pillow)."""
    from PIL import Image, ImageDraw

    xray = np.asarray(xray, float)
    h, w = xray.shape
    caption = 30
    frames = []
    for i, drr in enumerate(np.asarray(drrs, float)):
        canvas = np.concatenate([_indices(xray, drr), np.full((h, 2), _WHITE, np.uint8), _indices(drr)], axis=1)
        img = _palette_image(canvas, scale)
        frame = Image.new("P", (img.width, img.height + caption), 0)
        frame.putpalette(_PALETTE)
        frame.paste(img, (0, caption))
        p = params[i]
        name = labels[i] if labels is not None and i < len(labels) else f"iteration {i}"
        text = f"{name}: {p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f} deg; {p[3]:.0f}, {p[4]:.0f}, {p[5]:.0f} mm"
        draw = ImageDraw.Draw(frame)
        draw.text((4, 2), text, fill=_WHITE)
        if errors is not None and i < len(errors):
            draw.text((4, 15), errors[i], fill=_YELLOW)
        frames.append(frame)
    if not frames:
        raise ValueError("trajectory_gif: no DRRs to animate")  # a caller's bug: the iteration keeps one per step
    durations = [frame_ms] * (len(frames) - 1) + [2000]
    with atomic_path(Path(path)) as tmp:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:], duration=durations, loop=0)
