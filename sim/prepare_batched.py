"""The X-ray preparation of :mod:`sim.prepare` batched in torch, with the crop-and-resample of a field.

Training prepares thousands of targets per second on the device that renders them, so each step
of :mod:`sim.prepare` has a twin here over a batch ``(B, H, W)`` with one field per pair (``m``,
``(B, H, W)`` bool, each holding a pixel), no Python loop over pairs:

* :func:`invert_batched`: :func:`sim.prepare.invert` for the pairs selected;
* :func:`field_box_batched`: :func:`sim.prepare.field_box` (no margin) of every pair;
* :func:`crop_resize` (one image, numpy in and out) and :func:`crop_resize_batched` (a batch):
  the field's box resampled to the whole image, ``F.interpolate`` bilinear
  (``align_corners=False``) for images, nearest for the field;
* :func:`normalize_batched`: :func:`sim.prepare.percentile_bounds` and :func:`sim.prepare.normalize`
  (percentiles by :func:`sim.physics.batched.masked_percentile`; a flat pair becomes 0);
* :func:`masked_fill_batched`: :func:`sim.prepare.masked_fill`.

The batched resample computes ``F.interpolate``'s own source indices and weights (float32, as
torch computes them) per pair and gathers, so a batch of different boxes is one gather: the
images equal ``F.interpolate`` on each crop up to float32 rounding, the resampled field exactly.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from sim.physics.batched import masked_percentile

__all__ = ["invert_batched", "field_box_batched", "crop_resize", "crop_resize_batched", "resize_boxes",
           "bilinear_source", "nearest_source", "gather2d", "normalize_batched", "masked_fill_batched"]


def invert_batched(x: torch.Tensor, m: torch.Tensor, which: torch.Tensor) -> torch.Tensor:
    """``max + min - x`` over each pair's field for the pairs where ``which`` ``(B,)`` bool is
    True, the others unchanged: ``(B, H, W)``."""
    vmax = torch.where(m, x, -torch.inf).amax(dim=(1, 2))
    vmin = torch.where(m, x, torch.inf).amin(dim=(1, 2))
    return torch.where(which[:, None, None], (vmax + vmin)[:, None, None] - x, x)


def field_box_batched(m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(r0, r1, c0, c1)``, each ``(B,)`` int64: every pair's field's bounding box (half-open)."""
    _, h, w = m.shape
    rows_any, cols_any = m.any(2), m.any(1)  # (B, H), (B, W)
    first = lambda a: a.to(torch.uint8).argmax(1)  # noqa: E731 (the first True of each row)
    return first(rows_any), h - first(rows_any.flip(1)), first(cols_any), w - first(cols_any.flip(1))


def crop_resize(image: np.ndarray, box: tuple[int, int, int, int], shape: tuple[int, int], mode: str) -> np.ndarray:
    """``image[r0:r1, c0:c1]`` resampled to ``shape`` (``bilinear`` or ``nearest``, in float32 by
    ``F.interpolate``), float64; a box that is the whole image is returned as it is (as float64)."""
    r0, r1, c0, c1 = box
    if (r0, r1, c0, c1) == (0, shape[0], 0, shape[1]):
        return np.asarray(image, np.float64)
    x = torch.from_numpy(np.ascontiguousarray(image[r0:r1, c0:c1], np.float32))[None, None]
    kw = {"align_corners": False} if mode == "bilinear" else {}
    return F.interpolate(x, size=shape, mode=mode, **kw)[0, 0].double().numpy()


def bilinear_source(in_size: torch.Tensor, out_size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``F.interpolate(..., mode="bilinear", align_corners=False)``'s source indices and weight
    along one axis: crop lengths ``in_size`` ``(B,)`` -> ``(i0, i1, lambda1)`` ``(B, out_size)``
    (output pixel ``o`` is ``(1 - lambda1) in[i0] + lambda1 in[i1]``), in float32 as torch."""
    scale = in_size.to(torch.float32) / torch.tensor(float(out_size), dtype=torch.float32, device=in_size.device)
    o = torch.arange(out_size, dtype=torch.float32, device=in_size.device)
    # scale (o + 0.5) - 0.5 rounded once, as torch's kernels compute it (a fused multiply-add;
    # the float32 product is exact in float64): without, lambda differs by up to ~1e-5
    src = (scale[:, None].double() * (o[None, :] + 0.5).double() - 0.5).float().clamp_min(0.0)
    last = (in_size - 1)[:, None]
    i0 = torch.minimum(torch.floor(src).to(torch.int64), last)
    lam = (src - i0.to(torch.float32)).clamp(0.0, 1.0)
    i1 = torch.where(i0 < last, i0 + 1, i0)
    return i0, i1, lam


def nearest_source(in_size: torch.Tensor, out_size: int) -> torch.Tensor:
    """``F.interpolate(..., mode="nearest")``'s source indices ``(B, out_size)`` for crop lengths
    ``in_size`` ``(B,)``: ``min(floor(o * (float)in / out), in - 1)`` in float32, as torch."""
    scale = in_size.to(torch.float32) / torch.tensor(float(out_size), dtype=torch.float32, device=in_size.device)
    o = torch.arange(out_size, dtype=torch.float32, device=in_size.device)
    return torch.minimum(torch.floor(o[None, :] * scale[:, None]).to(torch.int64), (in_size - 1)[:, None])


def gather2d(x: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """``x[b, rows[b, i], cols[b, j]]``: ``(B, H, W)`` from ``(B, Hin, Win)``, rows ``(B, H)``, cols ``(B, W)``."""
    b, _, win = x.shape
    r = x.gather(1, rows[:, :, None].expand(b, rows.shape[1], win))
    return r.gather(2, cols[:, None, :].expand(b, rows.shape[1], cols.shape[1]))


def resize_boxes(x: torch.Tensor, box: tuple[torch.Tensor, ...], size: tuple[int, int]) -> torch.Tensor:
    """Each pair's ``x[b, r0:r1, c0:c1]`` resampled bilinearly (``align_corners=False``) to
    ``size``, as ``F.interpolate`` in float32: ``(B, Hin, Win)`` -> ``(B, H, W)`` float32."""
    r0, r1, c0, c1 = box
    h0, h1, lh = bilinear_source(r1 - r0, size[0])
    w0, w1, lw = bilinear_source(c1 - c0, size[1])
    h0, h1, w0, w1 = h0 + r0[:, None], h1 + r0[:, None], w0 + c0[:, None], w1 + c0[:, None]
    x = x.to(torch.float32)
    lw1, lw0 = lw[:, None, :], (1.0 - lw)[:, None, :]
    lh1, lh0 = lh[:, :, None], (1.0 - lh)[:, :, None]
    top = gather2d(x, h0, w0) * lw0 + gather2d(x, h0, w1) * lw1
    bottom = gather2d(x, h1, w0) * lw0 + gather2d(x, h1, w1) * lw1
    return top * lh0 + bottom * lh1


def crop_resize_batched(images: tuple[torch.Tensor, ...], m: torch.Tensor, box, crop: bool = True):
    """:func:`crop_resize` of a batch: each of ``images`` ``(B, H, W)`` (bilinear, back in its own
    dtype) and the field ``m`` (nearest) cropped to each pair's ``box`` (:func:`field_box_batched`)
    and resampled to ``(H, W)``; a pair whose box is the whole image, or every pair with ``crop``
    False, is left as it is. A resampled field that lost every pixel becomes the whole image.
    Returns ``(*images, m)``."""
    _, h, w = m.shape
    r0, r1, c0, c1 = box
    cropped = ((r0 != 0) | (r1 != h) | (c0 != 0) | (c1 != w))[:, None, None] & crop
    out = [torch.where(cropped, resize_boxes(x, box, (h, w)).to(x.dtype), x) for x in images]
    rows = nearest_source(r1 - r0, h) + r0[:, None]
    cols = nearest_source(c1 - c0, w) + c0[:, None]
    m = torch.where(cropped, gather2d(m, rows, cols), m)
    m = torch.where(m.flatten(1).any(1)[:, None, None], m, True)
    return (*out, m)


def normalize_batched(x: torch.Tensor, m: torch.Tensor, low_pct: float, high_pct: float) -> torch.Tensor:
    """Each pair's ``low_pct`` / ``high_pct`` percentiles over its field to 0 / 1, clipped to
    ``[0, 1]``; a pair whose percentiles are equal becomes 0."""
    lohi = masked_percentile(x, m, [low_pct, high_pct])
    lo, hi = lohi[:, 0, None, None], lohi[:, 1, None, None]
    span = hi - lo
    return torch.where(span > 0, ((x - lo) / torch.where(span > 0, span, 1.0)).clamp(0.0, 1.0), 0.0)


def masked_fill_batched(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Each pair's pixels outside its field set to its mean over the field (fields not empty)."""
    count = m.sum(dim=(1, 2))[:, None, None].to(x.dtype)
    return torch.where(m, x, torch.where(m, x, 0.0).sum(dim=(1, 2))[:, None, None] / count)
