"""Figures of a registration: edge overlay of the final DRR on the X-ray, and convergence."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from sim.core.atomic import atomic_path, save_figure


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


#: The overlay's colours (RGB in [0, 1]): the DRR's edges, the outline of the pixels used.
EDGE_RGB = (1.0, 0.15, 0.1)
OUTLINE_RGB = (0.1, 0.9, 1.0)
#: The brightness of the pixels the registration left out (outside the field, text overlays,
#: saturated or empty pixels, metal tools) in the overlay, relative to the rest.
LEFT_OUT_DIM = 0.4
#: The overlay's smallest width (px): a smaller X-ray is shown enlarged (its text would not fit).
OVERLAY_MIN_WIDTH_PX = 512


def _font(px: int):
    """Pillow's built-in font at ``px`` pixels (a FreeType font: no file needed)."""
    from PIL import ImageFont

    return ImageFont.load_default(size=max(8, int(px)))


def _wrapped(draw, text: str, font, width: int) -> list[str]:
    """``text`` broken into lines no wider than ``width`` px in ``font``."""
    lines, line = [], ""
    for word in text.split():
        trial = f"{line} {word}".strip()
        if line and draw.textlength(trial, font=font) > width:
            lines.append(line)
            line = word
        else:
            line = trial
    return [*lines, line] if line else lines


def overlay_png(xray: np.ndarray, drr: np.ndarray, path: str | Path, mask: np.ndarray | None = None, *,
                title: str | None = None) -> tuple[int, int]:
    """The X-ray in grey (windowed over the valid pixels) at the resolution of ``xray`` ``(H, W)``
    with the DRR's edges in red (``drr`` the same shape: render it with the X-ray's own geometry),
    the outline of the valid pixels ``mask`` in cyan and the pixels left out dimmed
    (:data:`LEFT_OUT_DIM`); above it ``title`` (e.g. the verdict), below it a legend. An X-ray
    narrower than :data:`OVERLAY_MIN_WIDTH_PX` is shown enlarged by a whole factor (each pixel a
    block: nothing interpolated). Lines are 1 px per 512 px of the longer side; the text scales
    with the width (at least 13 px). Returns ``(top, factor)``: the X-ray's first row in the PNG
    (px) and its enlargement."""
    from PIL import Image, ImageDraw

    xray = np.asarray(xray, float)
    if drr.shape != xray.shape:
        raise ValueError(f"overlay: the DRR {drr.shape} must have the X-ray's shape {xray.shape}")
    h, w = xray.shape
    width = max(0, int(max(xray.shape) // 512))
    grey = _window(xray, mask)
    rgb = np.stack([grey] * 3, -1)
    partial = mask is not None and not mask.all()
    if partial:
        rgb[~mask] *= LEFT_OUT_DIM
    rgb[_thicken(drr_edges(drr, mask), width)] = EDGE_RGB
    if partial:
        rgb[_thicken(_outline(mask), width)] = OUTLINE_RGB
    factor = max(1, -(-OVERLAY_MIN_WIDTH_PX // w))
    if factor > 1:
        rgb = np.repeat(np.repeat(rgb, factor, axis=0), factor, axis=1)
        h, w = h * factor, w * factor
    image = Image.fromarray((rgb * 255 + 0.5).astype(np.uint8))
    font = _font(max(13, w // 45))
    pad = max(4, w // 100)
    probe = ImageDraw.Draw(image)
    line_h = int(font.size * 1.25)
    head = _wrapped(probe, title, font, w - 2 * pad) if title else []
    legend = [(EDGE_RGB, "DRR edges at the registered pose"),
              *([(OUTLINE_RGB, "outline of the pixels used"),
                 (tuple(LEFT_OUT_DIM * 0.6 for _ in range(3)), "dimmed: left out (outside the field, overlays, "
                                                              "clipped plateaus, metal tools)")] if partial else [])]
    swatch = font.size
    legend_lines = [(c, _wrapped(probe, text, font, w - 3 * pad - swatch)) for c, text in legend]
    top = pad + line_h * len(head) + (pad if head else 0)
    bottom = pad + sum(line_h * len(ls) for _, ls in legend_lines) + pad
    canvas = Image.new("RGB", (w, top + h + bottom), (20, 20, 20))
    canvas.paste(image, (0, top))
    draw = ImageDraw.Draw(canvas)
    y = pad
    for line in head:
        draw.text((pad, y), line, fill=(255, 255, 255), font=font)
        y += line_h
    y = top + h + pad
    for colour, lines in legend_lines:
        c = tuple(int(255 * v) for v in colour)
        draw.rectangle((pad, y + 2, pad + swatch - 2, y + swatch), fill=c, outline=(200, 200, 200))
        for line in lines:
            draw.text((2 * pad + swatch, y), line, fill=(235, 235, 235), font=font)
            y += line_h
    with atomic_path(path) as tmp:
        canvas.save(tmp, format="PNG")
    return top, factor


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


def _stage_kind(stage: str) -> str:
    """A history row's stage (:attr:`register.engines.result.RegistrationResult.history`) by kind:
    ``network`` (the contextual iteration), ``search`` (the global search's local searches),
    ``refine`` (CMA-ES levels, a finalist's too) or ``polish``."""
    if stage == "contextual":
        return "network"
    if stage == "search":
        return "search"
    return "polish" if stage.split(".")[-1] == "polish" else "refine"


def convergence_plot(history, path: str | Path, *, title: str | None = None, search_status: str | None = None) -> None:
    """The registration by stage, each on its own scale, a stage that did not run not drawn.

    Left (where the network ran): the network's predicted step per iteration (deg + mm; the
    iteration stops when it is small). Right: the similarity (1 = identical edges) of the global
    search's local searches (one point each, best first; ``search_status`` says whether its grid
    ran), then each CMA-ES refinement's best per generation (one line per start) and the polish,
    the final value starred. The refinement's levels score at their own resolution (1/2: higher
    than at full), so only the polish and the final value compare. Where the pipeline searched
    again by local similarity (stages ``rescue.*``), a third panel shows that search and its
    refinements on their own scale, and the second panel's last value is the pose it replaced.
    ``history``: rows
    ``(stage, value, params)``; ``title``: the figure's
    title (e.g. the verdict). A PNG, written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(str(stage), float(v)) for stage, v, *_ in history]
    network = [-v for stage, v in rows if _stage_kind(stage) == "network"]
    rescue = [(stage[len("rescue."):], v) for stage, v in rows if stage.startswith("rescue.")]
    other = [(stage, v) for stage, v in rows if _stage_kind(stage) != "network" and not stage.startswith("rescue.")]
    panels = int(bool(network)) + int(bool(other)) + int(bool(rescue))
    fig, axes = plt.subplots(1, max(panels, 1), figsize=(5.5 * max(panels, 1), 5.2), squeeze=False)
    axes = list(axes[0])
    if network:
        ax = axes.pop(0)
        ax.plot(range(len(network)), network, marker="o", ms=3, color="tab:purple")
        ax.set_xlabel("network iteration")
        ax.set_ylabel("predicted step (deg + mm)")
        ax.set_title("1. the network's iteration", fontsize=10)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    for part, rows_of in (("usual", other), ("rescue", rescue)):
        if rows_of:
            star = "found first, replaced" if part == "usual" and rescue else "final"
            _search_panel(axes.pop(0), rows_of, part, bool(network), search_status, star)
    if title:
        fig.suptitle(textwrap.fill(title, width=70 * max(panels, 1)), fontsize=10)
    save_figure(fig, path)


def _search_panel(ax, other, part: str, network: bool, search_status: str | None, star: str = "final") -> None:
    """:func:`convergence_plot`'s panel of the search and the refinement (``part`` ``"usual"``) or of
    the search again by local similarity (``"rescue"``: the pipeline's step 6, its own scale);
    ``star``: what the last value is called."""
    import matplotlib.pyplot as plt

    x = 0
    search = sorted((v for stage, v in other if stage == "search"), reverse=True)
    if search:
        what = "the network's pose searched locally" if len(search) == 1 else f"{len(search)} local searches"
        ax.plot(range(len(search)), search, "o", ms=4, color="tab:orange",
                label=f"{what}" + (f"; grid {search_status}" if search_status and part == "usual" else ""))
        x = len(search) + 1
    runs = list(dict.fromkeys(stage for stage, _ in other if stage != "search"))
    finals = []
    for k, stage in enumerate(runs):
        ys = [v for st, v in other if st == stage]
        kind = _stage_kind(stage)
        start = stage.split(".")[0].replace("finalist", "") if "." in stage else "0"
        level = stage.split(".")[-1]
        label = ("polish of the winner (full resolution)" if kind == "polish" else
                 f"refinement{'' if len(runs) < 3 else f' of start {start}'} (CMA-ES, {level}: reduced resolution)")
        ax.plot(range(x, x + len(ys)), ys, marker="o" if len(ys) < 3 else None,
                color="k" if kind == "polish" else plt.cm.Dark2(k % 8), label=label)
        finals.append((x + len(ys) - 1, ys[-1]))
        x += len(ys)
    if finals:  # the last value (the polish of the winner); of the search again, the best refinement
        fx, fy = finals[-1] if part == "usual" else max(finals, key=lambda f: f[1])
        ax.plot([fx], [fy], "*", ms=12, color="gold", mec="k", label=f"{star} {fy:.3f}")
    ax.set_xlabel("search results (best first), then CMA-ES generations / polish steps")
    if part == "usual":
        ax.set_ylabel("similarity (1 = identical edges)")
        ax.set_title(("2. " if network else "") + "search and refinement", fontsize=10)
    else:
        ax.set_ylabel("local similarity (edges window by window)")
        ax.set_title(("3. " if network else "2. ") + "searched again by local similarity", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=1, frameon=False)


#: The trajectory figures' palette (indices of an 8-bit palette image): :data:`_GREYS` grey levels,
#: then the edges' red, white (separators, captions) and the errors' yellow. Built as indices, the
#: frames need no colour quantisation (an adaptive palette per frame took 0.8 s of a registration's
#: outputs) and no matplotlib.
_GREYS = 250
_RED, _WHITE, _YELLOW = _GREYS, _GREYS + 1, _GREYS + 2
_PALETTE = ([v for i in range(_GREYS) for v in (round(255 * i / (_GREYS - 1)),) * 3]
            + [255, 26, 26, 255, 255, 255, 255, 220, 120])


def _equalized(img: np.ndarray) -> np.ndarray:
    """``img`` mapped to [0, 1] by its own histogram (equalised: every grey level equally used), so
    that a display image whose anatomy lies in a few grey levels (a linear display, a toned image)
    shows it as a DRR does."""
    from skimage.exposure import equalize_hist

    img = np.asarray(img, float)
    return equalize_hist(img, nbins=1024) if np.ptp(img) > 0 else np.zeros_like(img)


def _indices(img: np.ndarray, edges_of: np.ndarray | None = None) -> np.ndarray:
    """``img`` ``(H, W)`` equalised (:func:`_equalized`) to grey palette indices ``(H, W)`` uint8, with
    the strongest edges of ``edges_of`` (its Sobel magnitude above the 92nd percentile) in red."""
    from scipy import ndimage

    idx = np.rint(_equalized(img) * (_GREYS - 1)).astype(np.uint8)
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
                   errors: list[str] | None = None, labels: list[str] | None = None, scale: int = 3,
                   frame_ms: int = 250, title: str | None = None) -> None:
    """An animated GIF of the contextual iteration: each frame the X-ray (left) beside the DRR of
    that iteration (right), the DRR's strongest edges in red over the X-ray, and a caption with the
    iteration (or ``labels[i]``), its pose and, when given, ``errors[i]`` (e.g. its error against
    the truth); ``title`` (e.g. the verdict) on the last frame.

    ``xray`` ``(H, W)``; ``drrs`` ``(K, H, W)``; ``params`` ``(>= K, 6)`` (deg, mm); ``scale``
    pixels per image pixel (default 3: 774 px wide for two 128 px images); the text is 1/40 of
    the width (at least 14 px); the last frame is held for 3 s. Written atomically (Pillow)."""
    from PIL import Image, ImageDraw

    xray = np.asarray(xray, float)
    h, w = xray.shape
    font = _font(max(14, (2 * w + 2) * scale // 40))
    line_h = int(font.size * 1.3)
    caption = 3 * line_h + 6
    frames = []
    for i, drr in enumerate(np.asarray(drrs, float)):
        canvas = np.concatenate([_indices(xray, drr), np.full((h, 2), _WHITE, np.uint8), _indices(drr)], axis=1)
        img = _palette_image(canvas, scale)
        frame = Image.new("P", (img.width, img.height + caption), 0)
        frame.putpalette(_PALETTE)
        frame.paste(img, (0, caption))
        p = params[i]
        name = labels[i] if labels is not None and i < len(labels) else f"iteration {i}"
        draw = ImageDraw.Draw(frame)
        draw.text((6, 3), f"{name}: {p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f} deg; {p[3]:.0f}, {p[4]:.0f}, {p[5]:.0f} mm",
                  fill=_WHITE, font=font)
        draw.text((6, 3 + line_h), "left: X-ray with the DRR's edges (red); right: the DRR", fill=_WHITE, font=font)
        extra = errors[i] if errors is not None and i < len(errors) else None
        if title is not None and i == len(drrs) - 1:
            extra = title if extra is None else f"{extra}; {title}"
        if extra:
            draw.text((6, 3 + 2 * line_h), extra, fill=_YELLOW, font=font)
        frames.append(frame)
    if not frames:
        raise ValueError("trajectory_gif: no DRRs to animate")  # a caller's bug: the iteration keeps one per step
    durations = [frame_ms] * (len(frames) - 1) + [3000]
    with atomic_path(Path(path)) as tmp:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:], duration=durations, loop=0)
