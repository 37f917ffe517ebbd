"""An independent NumPy / SciPy implementation of the imaging chain after the render, for the tests.

The project's chain (:mod:`sim.physics.chain`) is torch: its Gaussians are separable matrices, its
percentiles order statistics, its scatter-kernel superposition matrix products. This reference
computes the same stages another way, one image at a time: the kernel scatter and the sks texture
by one 2-D FFT of the mirror extension, the unsharp mask with ``scipy.ndimage.gaussian_filter``,
the window with ``numpy.percentile``, the sks scatter with the fitted model's own ``predict`` (FFT
spectra). It is the chain's implementation before the chain was made one (git history:
``sim.randomize.apply_image`` and ``DisplayChain.apply`` at a58615b), kept here as the truth the
chain is tested against and used nowhere else.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter

from sim.projection.geometry import CArmGeometry
from sim.randomize import Draw, sks_model


def mirror_gaussian(x: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian of ``x`` ``(H, W)`` (sigma in px) with mirrored edges: the circular convolution of
    the ``(2H, 2W)`` mirror extension, which is periodic, with the Gaussian's transfer function."""
    xp = np.concatenate([x, x[::-1]], axis=0)
    xp = np.concatenate([xp, xp[:, ::-1]], axis=1)
    fy = np.fft.fftfreq(xp.shape[0])[:, None]
    fx = np.fft.rfftfreq(xp.shape[1])[None, :]
    transfer = np.exp(-2.0 * math.pi**2 * sigma_px**2 * (fx * fx + fy * fy))
    return np.fft.irfft2(np.fft.rfft2(xp) * transfer, s=xp.shape)[:x.shape[0], :x.shape[1]]


def field_blur(x: np.ndarray, sigma: float, field: np.ndarray | None) -> np.ndarray:
    """Gaussian of ``x``; with a field, the normalised convolution inside it and, separately, outside it."""
    if field is None or field.all() or not field.any():
        return gaussian_filter(x, sigma, mode="reflect")
    out = np.empty_like(x)
    for m in (field, ~field):
        mf = m.astype(np.float64)
        num = gaussian_filter(x * mf, sigma, mode="reflect")
        den = gaussian_filter(mf, sigma, mode="reflect")
        out[m] = num[m] / den[m]
    return out


def sks_texture(normals: np.ndarray, strength: float, sigma_px: float) -> np.ndarray:
    """``max(0, 1 + strength n)``, ``n`` the normals blurred and scaled back to unit deviation."""
    n = mirror_gaussian(np.asarray(normals, np.float64), sigma_px) * (2.0 * math.sqrt(math.pi) * sigma_px)
    return np.maximum(1.0 + strength * n, 0.0)


def display(chain, raw: np.ndarray, i0: float, field: np.ndarray | None) -> np.ndarray:
    """The display chain ``chain`` (a :class:`sim.physics.display.DisplayChain`) of one frame ``(H, W)``."""
    raw = raw.astype(np.float64)
    v = -np.log(np.maximum(raw, 1e-12 * i0) / i0) if chain.log else raw / i0
    lo, hi = np.percentile(v if field is None else v[field], chain.window)
    span = hi - lo
    if span > 0:
        x = np.clip((v - lo) / span, 0.0, 1.0)
    else:
        x = np.where(v > lo, 1.0, np.where(v < lo, 0.0, 0.5))
    if chain.log != (chain.polarity == "bone-bright"):
        x = 1.0 - x
    if chain.unsharp_amount > 0:
        x = np.clip(x + chain.unsharp_amount * (x - field_blur(x, chain.unsharp_sigma_px, field)), 0.0, 1.0)
    if chain.gamma != 1.0:
        x = x ** chain.gamma
    out = np.rint(x * chain.max_value).astype(np.uint16)
    if field is not None and chain.shutter != "none":
        out[~field] = 0 if chain.shutter == "black" else chain.max_value
    return out


def apply_image(raw: np.ndarray, i0: float, draw: Draw, rng: np.random.Generator, *, scatter=None,
                geometry: CArmGeometry | None = None, gap_mm: float | None = None, sks_table=None):
    """``sim.randomize.apply_image`` computed the reference's way: ``(image uint16, field bool)``."""
    raw = np.asarray(raw, np.float64)
    mode = draw["scatter"]
    if mode == "monte-carlo":
        raw = raw + (float(draw["scatter_scale"]) - 1.0) * np.asarray(scatter, np.float64)
    h, w = raw.shape
    col = draw.collimator(h, w)
    field = np.ones((h, w), bool) if col is None else col.mask(h, w)
    open_raw = raw
    if col is not None:
        raw = col.apply(raw)
    if mode == "kernel":
        raw = raw + float(draw["scatter_spr"]) * mirror_gaussian(raw, float(draw["scatter_sigma"]) * min(h, w))
    if mode == "sks":
        model = sks_model(draw, sks_table)
        source = open_raw if draw["sks_open"] else raw
        tau = -np.log(np.maximum(source, 1e-12 * float(i0)) / float(i0))
        sc = model.predict(tau, geometry, flat_signal=float(i0), gap_mm=gap_mm)
        if draw["sks_open"] and col is not None:
            sc = col.apply(sc)
    raw = raw + rng.normal(0.0, float(draw["electronic_noise_fraction"]) * float(i0), raw.shape)
    if mode == "sks":
        quantum = rng.standard_normal(raw.shape)
        sc = sc * sks_texture(rng.standard_normal(raw.shape), float(draw["sks_texture"]),
                              float(draw["sks_texture_sigma"]) * min(h, w))
        raw = raw + sc + np.sqrt(sc * model.signal_per_photon) * quantum
    return display(draw.display_chain(), raw, float(i0), None if col is None else field), field
