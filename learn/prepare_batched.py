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

Each step is :mod:`sim.prepare_batched`'s twin of :mod:`sim.prepare`'s (the crop and resample
of each pair equals ``F.interpolate`` on its crop up to float32 rounding, the resampled field
exactly); this module checks the inputs and composes the steps in registration's order.
"""

from __future__ import annotations

import torch

from learn.online import OnlinePairsError
from sim.prepare_batched import (crop_resize_batched, field_box_batched, invert_batched, masked_fill_batched,
                                 normalize_batched)

__all__ = ["prepare_like_registration_batched"]


def _bool_pairs(name: str, v, b: int, device) -> torch.Tensor:
    if isinstance(v, bool):
        return torch.full((b,), v, dtype=torch.bool, device=device)
    if not isinstance(v, torch.Tensor) or v.dtype != torch.bool or v.shape != (b,):
        got = f"{v.dtype} {tuple(v.shape)}" if isinstance(v, torch.Tensor) else type(v).__name__
        raise OnlinePairsError(f"prepare_like_registration_batched: {name} must be a ({b},) bool tensor, got {got}")
    return v.to(device)


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
    pair is resampled in float32 (:func:`sim.prepare_batched.crop_resize`); the rest runs in float64 where ``display``
    or ``current`` is float64, else in float32.
    """
    where = "prepare_like_registration_batched"
    for name, t in (("display", display), ("current", current)):
        if not isinstance(t, torch.Tensor) or t.ndim != 3 or t.is_complex() or t.dtype == torch.bool:
            shape = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise OnlinePairsError(f"{where}: {name} must be a real (B, H, W) tensor, got {shape}")
    b = display.shape[0]
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
    rows_any = m.any(2)  # (B, H)
    if b and not bool(rows_any.any(1).all()):
        empty = torch.nonzero(~rows_any.any(1)).flatten().tolist()[:10]
        raise OnlinePairsError(f"{where}: the fields of pairs {empty} hold no pixel")
    work = torch.float64 if torch.float64 in (display.dtype, current.dtype) else torch.float32
    x = display.to(work)
    cur = current.to(device=dev, dtype=work)

    # 1. bone bright: a bone-dark display inverted over the field
    x = invert_batched(x, m, bone_dark)

    # 2. crop to the field's bounding box, resample to (H, W)
    x, cur, m = crop_resize_batched((x, cur), m, field_box_batched(m), crop)

    # 3. normalise over the field; 4. the outside filled with the mean over the field
    x = masked_fill_batched(normalize_batched(x, m, lo_q, hi_q), m)
    if mask_current:
        cur = masked_fill_batched(cur, m)
    return x.to(torch.float32), cur.to(torch.float32)
