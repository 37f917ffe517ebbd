"""Realistic targets made ready as registration makes a user's X-ray ready, for a batch of pairs in torch.

:func:`learn.online.prepare_like_registration` takes one displayed X-ray, its collimated
field and the pair's current image through registration's preparation (bone bright, crop to
the field, resample, normalise, fill the outside), in numpy, one pair at a time.
:func:`prepare_like_registration_batched` does the same for ``(B, H, W)`` batches in torch, on
the device of its inputs, each pair with its own field, log / linear and polarity, without a
Python loop over pairs: the training pairs of :mod:`sim.physics.batched` go from the render to
the network on one device. It equals the numpy function (``tests/learn/test_prepare_batched.py``)
for the display images training makes (``raw_intensity=False``) without the CT tone
(``tone=False``); those two options are left out: a raw-intensity target is not a display
image, and the tone maps each pair by rank onto its own current image (a per-pair sort and
interpolation; use the numpy function for them).

The crop and resample of each pair (``learn.online._crop_resize``: ``F.interpolate`` of the
bounding box of the field to ``(H, W)``, bilinear with ``align_corners=False`` for the images,
nearest for the field) are computed here with ``F.interpolate``'s own source indices and
weights (float32, as torch computes them) per pair and gathered, so a batch of different boxes
is one gather: the images equal ``F.interpolate`` on the crop up to float32 rounding, the
resampled field exactly.
"""

from __future__ import annotations

import torch

from learn.online import OnlinePairsError
from sim.physics.batched import masked_percentile

__all__ = ["prepare_like_registration_batched"]


def _bool_pairs(name: str, v, b: int, device) -> torch.Tensor:
    if isinstance(v, bool):
        return torch.full((b,), v, dtype=torch.bool, device=device)
    if not isinstance(v, torch.Tensor) or v.dtype != torch.bool or v.shape != (b,):
        got = f"{v.dtype} {tuple(v.shape)}" if isinstance(v, torch.Tensor) else type(v).__name__
        raise OnlinePairsError(f"prepare_like_registration_batched: {name} must be a ({b},) bool tensor, got {got}")
    return v.to(device)


def _bilinear_source(in_size: torch.Tensor, out_size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
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


def _nearest_source(in_size: torch.Tensor, out_size: int) -> torch.Tensor:
    """``F.interpolate(..., mode="nearest")``'s source indices ``(B, out_size)`` for crop lengths
    ``in_size`` ``(B,)``: ``min(floor(o * (float)in / out), in - 1)`` in float32, as torch."""
    scale = in_size.to(torch.float32) / torch.tensor(float(out_size), dtype=torch.float32, device=in_size.device)
    o = torch.arange(out_size, dtype=torch.float32, device=in_size.device)
    return torch.minimum(torch.floor(o[None, :] * scale[:, None]).to(torch.int64), (in_size - 1)[:, None])


def _gather2d(x: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """``x[b, rows[b, i], cols[b, j]]``: ``(B, H, W)`` from ``(B, Hin, Win)``, rows ``(B, H)``, cols ``(B, W)``."""
    b, _, win = x.shape
    r = x.gather(1, rows[:, :, None].expand(b, rows.shape[1], win))
    return r.gather(2, cols[:, None, :].expand(b, rows.shape[1], cols.shape[1]))


def _resize_boxes(x: torch.Tensor, box: tuple[torch.Tensor, ...], size: tuple[int, int]) -> torch.Tensor:
    """Each pair's ``x[b, r0:r1, c0:c1]`` resampled bilinearly (``align_corners=False``) to
    ``size``, as ``F.interpolate`` in float32: ``(B, Hin, Win)`` -> ``(B, H, W)`` float32."""
    r0, r1, c0, c1 = box
    h0, h1, lh = _bilinear_source(r1 - r0, size[0])
    w0, w1, lw = _bilinear_source(c1 - c0, size[1])
    h0, h1, w0, w1 = h0 + r0[:, None], h1 + r0[:, None], w0 + c0[:, None], w1 + c0[:, None]
    x = x.to(torch.float32)
    lw1, lw0 = lw[:, None, :], (1.0 - lw)[:, None, :]
    lh1, lh0 = lh[:, :, None], (1.0 - lh)[:, :, None]
    top = _gather2d(x, h0, w0) * lw0 + _gather2d(x, h0, w1) * lw1
    bottom = _gather2d(x, h1, w0) * lw0 + _gather2d(x, h1, w1) * lw1
    return top * lh0 + bottom * lh1


def prepare_like_registration_batched(display: torch.Tensor, field: torch.Tensor, current: torch.Tensor, *,
                                      log_display, bone_dark, mask_current: bool, low_pct: float = 1.0,
                                      high_pct: float = 99.0, crop: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`learn.online.prepare_like_registration` (``raw_intensity=False``, ``tone=False``) for a batch.

    Args:
        display: ``(B, H, W)`` displayed X-rays (the display chain's integers, any real dtype:
            :func:`sim.physics.batched.apply_image_batched`'s image).
        field: ``(B, H, W)`` bool, each pair's collimated field (each must hold a pixel).
        current: ``(B, H, W)`` the pairs' current (moving) images (line integrals, any unit).
        log_display: ``(B,)`` bool (or one bool): the display chain's log, kept for the record
            (display images are not log-corrected: see the numpy function).
        bone_dark: ``(B,)`` bool (or one bool): the display shows bone dark (polarity
            ``bone-dark``): inverted to bone bright, ``max + min - x`` over the field.
        mask_current: fill the current images' pixels outside the field with their mean over
            it too (``current_field = "masked"``), as the targets'.
        low_pct, high_pct: the normalisation percentiles (%) over the field, ``0 <= low < high <= 100``.
        crop: step 2 (crop to the field's box and resample, as registration does today); False
            keeps the whole detector, the field masked (``train.framing = "detector"``): the image
            scale and CoordConv coordinates then stay the detector's whatever the field.

    Returns:
        ``(target, current)``, ``(B, H, W)`` float32 on ``display``'s device: the target in
        [0, 1] (the ``low_pct`` / ``high_pct`` percentiles over the resampled field to 0 / 1,
        clipped; all 0 where they are equal), both cropped to the bounding box of the field and
        resampled to ``(H, W)``, the pixels outside the resampled field set to the mean over it.

    As the numpy function, a pair whose box is the whole image is not resampled, and a cropped
    pair is resampled in float32 (``_crop_resize``); the rest runs in float64 where ``display``
    or ``current`` is float64, else in float32.
    """
    where = "prepare_like_registration_batched"
    for name, t in (("display", display), ("current", current)):
        if not isinstance(t, torch.Tensor) or t.ndim != 3 or t.is_complex() or t.dtype == torch.bool:
            shape = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise OnlinePairsError(f"{where}: {name} must be a real (B, H, W) tensor, got {shape}")
    b, h, w = display.shape
    dev = display.device
    if current.shape != display.shape:
        raise OnlinePairsError(f"{where}: current must have display's shape {tuple(display.shape)}, "
                               f"got {tuple(current.shape)}")
    if not isinstance(field, torch.Tensor) or field.dtype != torch.bool or field.shape != display.shape:
        got = f"{field.dtype} {tuple(field.shape)}" if isinstance(field, torch.Tensor) else type(field).__name__
        raise OnlinePairsError(f"{where}: field must be a bool tensor of display's shape {tuple(display.shape)}, "
                               f"got {got}")
    _bool_pairs("log_display", log_display, b, dev)
    bone_dark = _bool_pairs("bone_dark", bone_dark, b, dev)
    if not isinstance(mask_current, bool) or not isinstance(crop, bool):
        raise OnlinePairsError(f"{where}: mask_current and crop must be bools, got {mask_current!r}, {crop!r}")
    try:
        lo_q, hi_q = float(low_pct), float(high_pct)
    except (TypeError, ValueError):
        raise OnlinePairsError(f"{where}: low_pct and high_pct must be percentiles (%), got {low_pct!r}, "
                               f"{high_pct!r}") from None
    if not 0.0 <= lo_q < hi_q <= 100.0:
        raise OnlinePairsError(f"{where}: low_pct and high_pct must satisfy 0 <= low < high <= 100 (%), got "
                               f"{lo_q:g}, {hi_q:g}")
    m = field.to(dev)
    rows_any, cols_any = m.any(2), m.any(1)  # (B, H), (B, W)
    if b and not bool(rows_any.any(1).all()):
        empty = torch.nonzero(~rows_any.any(1)).flatten().tolist()[:10]
        raise OnlinePairsError(f"{where}: the fields of pairs {empty} hold no pixel")
    work = torch.float64 if torch.float64 in (display.dtype, current.dtype) else torch.float32
    x = display.to(work)
    cur = current.to(device=dev, dtype=work)

    # 1. bone bright: a bone-dark display inverted over the field
    vmax = torch.where(m, x, -torch.inf).amax(dim=(1, 2))
    vmin = torch.where(m, x, torch.inf).amin(dim=(1, 2))
    x = torch.where(bone_dark[:, None, None], (vmax + vmin)[:, None, None] - x, x)

    # 2. crop to the field's bounding box, resample to (H, W)
    first = lambda a: a.to(torch.uint8).argmax(1)  # noqa: E731 (the first True of each row)
    r0, c0 = first(rows_any), first(cols_any)
    r1, c1 = h - first(rows_any.flip(1)), w - first(cols_any.flip(1))
    box = (r0, r1, c0, c1)
    cropped = ((r0 != 0) | (r1 != h) | (c0 != 0) | (c1 != w))[:, None, None] & crop
    x = torch.where(cropped, _resize_boxes(x, box, (h, w)).to(work), x)
    cur = torch.where(cropped, _resize_boxes(cur, box, (h, w)).to(work), cur)
    rows = _nearest_source(r1 - r0, h) + r0[:, None]
    cols = _nearest_source(c1 - c0, w) + c0[:, None]
    m = torch.where(cropped, _gather2d(m, rows, cols), m)
    m = torch.where(m.flatten(1).any(1)[:, None, None], m, True)

    # 3. normalise over the field; 4. the outside filled with the mean over the field
    lohi = masked_percentile(x, m, [lo_q, hi_q])
    lo, hi = lohi[:, 0, None, None], lohi[:, 1, None, None]
    span = hi - lo
    x = torch.where(span > 0, ((x - lo) / torch.where(span > 0, span, 1.0)).clamp(0.0, 1.0), 0.0)
    count = m.sum(dim=(1, 2))[:, None, None].to(work)
    mean = lambda a: torch.where(m, a, 0.0).sum(dim=(1, 2))[:, None, None] / count  # noqa: E731
    x = torch.where(m, x, mean(x))
    if mask_current:
        cur = torch.where(m, cur, mean(cur))
    return x.to(torch.float32), cur.to(torch.float32)
