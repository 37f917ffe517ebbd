"""Image similarity metrics for intensity-based 2D/3D registration (NumPy, batched).

The optimiser (CMA-ES) scores a whole population of ``B`` candidate DRRs against one fixed
X-ray, so every metric takes ``fixed`` ``(H, W)`` and ``moving`` ``(B, H, W)`` (or ``(H, W)``,
treated as a batch of one) and returns ``(B,)`` float64 scores; higher is more similar, 1 is
a perfect match. Images are unitless intensities (any affine scaling of them is irrelevant);
all arithmetic is done in float64 whatever the input dtype (float32 or float64).

Masks are ``(H, W)`` bool arrays; True marks pixels that count. Every metric is built so that
pixels outside the mask have no influence at all on the score (for the gradient metrics the
mask is eroded by one pixel first, for the pyramid the smoothing is mask-normalised).

Metrics (``x`` = pixel column / second-to-last axis ``W``, ``y`` = row / axis ``H``):

* :func:`ncc` -- global normalised cross-correlation over the mask.
* :func:`gradient_ncc` -- mean NCC of the Sobel x and y gradient images.
* :func:`tone_free_gradient_ncc` -- gradient NCC of the X-ray re-valued by rank onto each DRR's
  values (:func:`tone_matched`): blind to the display's monotone curve.
* :func:`tone_tolerant_gradient_ncc` -- the mean of the two (the global search's and the
  refinement's similarity).
* :func:`patch_ncc` -- local NCC in every ``patch x patch`` window (box filters on the
  batch), averaged over the textured, sufficiently masked windows.
* :func:`patch_gradient_ncc` -- patch NCC of the Sobel gradient images, averaged over x and y
  (Grupp et al. 2020, xReg's "patch gradient NCC").
* :func:`local_gradient_ncc` -- patch gradient NCC in windows scaled with the image
  (:func:`local_patch_px`: 15 px at 128 px): whether edges agree window by window, which one
  strong edge cannot carry alone (the verdict's local similarity).
* :func:`local_gradients` -- Sobel gradients divided by their local RMS: every region's edges at
  one strength, for correlations (the global search's grid, by FFT) that one strong edge must not
  carry.
* :func:`multiscale` -- mean of any of the above over a Gaussian pyramid.
* :func:`downsample` -- integer block-mean downsampling for multi-resolution registration.
* :func:`bind_metric` -- a metric with its fixed image bound and prepared once (an optimiser's
  many calls against one X-ray).

Degenerate cases return 0 rather than NaN: an image that is constant over the mask has no
defined correlation with anything.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from scipy import ndimage

from sim.core.errors import InputError

__all__ = [
    "METRICS",
    "MetricError",
    "NoWindowError",
    "bind_metric",
    "bind_metric_at",
    "downsample",
    "get_metric",
    "gradient_ncc",
    "multiscale",
    "ncc",
    "patch_gradient_ncc",
    "local_gradient_ncc",
    "local_gradients",
    "local_patch_px",
    "image_sobel",
    "LOCAL_PATCH_PX",
    "LOCAL_REFERENCE_SIDE_PX",
    "patch_ncc",
    "plain_equivalent",
    "tone_free_gradient_ncc",
    "tone_matched",
    "tone_tolerant_gradient_ncc",
]

#: An image whose standard deviation over the mask is at most this fraction of its largest
#: absolute value (over the mask) is treated as constant (float64 rounding of a constant
#: image after mean subtraction is ~1e-16 relative).
_CONSTANT_REL = 1e-10

#: A window is "textured" when its local variance exceeds this fraction of the image's global
#: variance over the mask (local std > 1e-4 x global std). Rounding in the box-filtered
#: variances is ~1e-12 of the global variance, far below it.
_LOCAL_VAR_REL = 1e-8


class MetricError(InputError):
    """A metric cannot be computed from its inputs; the message names the input and the problem."""


class NoWindowError(MetricError):
    """A patch metric's mask leaves no window with ``min_valid`` of its pixels inside it."""


# ----------------------------------------------------------------------------- input checks


def _as_image(name: str, a: Any, ndims: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim not in ndims:
        want = " or ".join(f"{n}-D" for n in ndims)
        raise MetricError(f"{name}: expected a {want} array, got shape {arr.shape}")
    if arr.dtype == bool or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise MetricError(f"{name}: expected real numeric intensities, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    finite = np.isfinite(arr)
    if not finite.all():
        n_nan = int(np.isnan(arr).sum())
        n_inf = int(arr.size - finite.sum()) - n_nan
        raise MetricError(f"{name}: contains {n_nan} NaN and {n_inf} infinite values")
    return arr


def _check_inputs(
    fixed: Any, moving: Any, mask: Any, min_size: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Validate and convert: fixed ``(H, W)``, moving ``(B, H, W)``, mask ``(H, W)`` bool or None."""
    f = _as_image("fixed", fixed, (2,))
    m = _check_moving(moving, f.shape)
    f, k = _check_fixed(f, mask, min_size)
    return f, m, k


def _check_moving(moving: Any, shape: tuple[int, ...]) -> np.ndarray:
    """``moving`` as float64 ``(B, H, W)`` with the fixed image's ``shape`` ``(H, W)``."""
    m = _as_image("moving", moving, (2, 3))
    if m.ndim == 2:
        m = m[None]
    if m.shape[1:] != shape:
        raise MetricError(f"moving: image shape {m.shape[1:]} does not match fixed {shape} "
                          f"(moving must be (B, H, W) or (H, W) with the fixed image's (H, W))")
    if m.shape[0] == 0:
        raise MetricError("moving: empty batch (B = 0)")
    return m


def _check_fixed(fixed: Any, mask: Any, min_size: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate and convert: fixed ``(H, W)`` of at least ``min_size`` px a side, mask ``(H, W)`` bool or None."""
    f = _as_image("fixed", fixed, (2,))
    if min(f.shape) < min_size:
        raise MetricError(f"fixed: image shape {f.shape} is smaller than {min_size} x {min_size} pixels")
    if mask is None:
        return f, None
    k = np.asarray(mask)
    if k.dtype != bool:
        raise MetricError(f"mask: expected a bool array, got dtype {k.dtype}")
    if k.shape != f.shape:
        raise MetricError(f"mask: shape {k.shape} does not match the images' (H, W) = {f.shape}")
    if not k.any():
        raise MetricError("mask: empty (no pixel is True)")
    return f, k


def _check_patch(patch: Any, shape: tuple[int, int]) -> int:
    if isinstance(patch, bool) or not isinstance(patch, (int, np.integer)):
        raise MetricError(f"patch: expected an odd integer >= 3, got {patch!r}")
    p = int(patch)
    if p < 3 or p % 2 == 0:
        raise MetricError(f"patch: expected an odd integer >= 3, got {p}")
    if p > min(shape):
        raise MetricError(f"patch: {p} px windows do not fit in images of shape {shape}")
    return p


# ----------------------------------------------------------------------------- global NCC


class _FixedNCC:
    """The fixed image's part of an NCC over a mask, computed once: ``score(m)`` is the NCC of the
    fixed image ``f`` ``(H, W)`` against each ``m[b]`` ``(B, H, W)`` (checked inputs), ``(B,)``."""

    def __init__(self, f: np.ndarray, mask: np.ndarray | None) -> None:
        self.mask = mask
        fv = f.reshape(-1) if mask is None else f[mask]
        self.fv = fv
        self.fc = fv - fv.mean()
        # einsum, not BLAS matmul: threaded gemv is slower here and contends on busy machines
        self.sff = float(np.einsum("i,i->", self.fc, self.fc))
        self.f_const = self.sff <= fv.size * (_CONSTANT_REL * np.abs(fv).max()) ** 2

    def score(self, m: np.ndarray) -> np.ndarray:
        mv = m.reshape(m.shape[0], -1) if self.mask is None else m[:, self.mask]
        mc = mv - mv.mean(axis=1, keepdims=True)
        smm = np.einsum("bi,bi->b", mc, mc)
        sfm = np.einsum("bi,i->b", mc, self.fc)
        m_const = smm <= self.fv.size * (_CONSTANT_REL * np.abs(mv).max(axis=1)) ** 2
        ok = ~m_const & (not self.f_const)
        out = np.zeros(m.shape[0])
        out[ok] = sfm[ok] / np.sqrt(self.sff * smm[ok])
        return np.clip(out, -1.0, 1.0)


def _ncc_core(f: np.ndarray, m: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """NCC of f ``(H, W)`` against m ``(B, H, W)`` over mask (checked inputs), ``(B,)``."""
    return _FixedNCC(f, mask).score(m)


def ncc(fixed: np.ndarray, moving: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Normalised cross-correlation of one fixed image with a batch of moving images.

    With ``f``, ``m`` the intensities over the ``n`` pixels where ``mask`` is True (all pixels
    without a mask) and bars their means::

        NCC = sum((f - f_bar) (m - m_bar)) / sqrt(sum((f - f_bar)^2) sum((m - m_bar)^2))

    i.e. Pearson's correlation coefficient, in [-1, 1]; 1 for identical images, invariant to
    ``a I + b`` (a > 0) of either image, -1 under a < 0. A constant image (std over the mask
    at most 1e-10 of its largest absolute value) gives 0.

    Args:
        fixed: ``(H, W)`` fixed image (the X-ray).
        moving: ``(B, H, W)`` batch of moving images (DRRs), or one ``(H, W)`` image.
        mask: optional ``(H, W)`` bool; only True pixels count.

    Returns:
        ``(B,)`` float64 scores (``(1,)`` for a 2-D ``moving``).
    """
    f, m, k = _check_inputs(fixed, moving, mask)
    return _ncc_core(f, m, k)


# ----------------------------------------------------------------------------- gradients


def _sobel_xy(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sobel gradients of ``(..., H, W)`` on the interior, each ``(..., H-2, W-2)``.

    ``gx[i, j] = sum_k w_k (I[i+k, j+1] - I[i+k, j-1])``, ``w = (1, 2, 1)`` for ``k = -1, 0, 1``
    (and ``gy`` likewise with rows and columns swapped): exactly ``scipy.ndimage.sobel`` along
    axis -1 / -2 at the pixels whose 3 x 3 neighbourhood lies inside the image. The outer
    one-pixel border (where Sobel would need padding) is dropped.
    """
    dx = img[..., :, 2:] - img[..., :, :-2]  # (..., H, W-2)
    gx = dx[..., :-2, :] + 2.0 * dx[..., 1:-1, :] + dx[..., 2:, :]
    dy = img[..., 2:, :] - img[..., :-2, :]  # (..., H-2, W)
    gy = dy[..., :, :-2] + 2.0 * dy[..., :, 1:-1] + dy[..., :, 2:]
    return gx, gy


def _gradient_mask(mask: np.ndarray | None) -> np.ndarray | None:
    """Mask for the interior gradient images ``(H-2, W-2)``: eroded by one pixel (3 x 3 square).

    A Sobel value at an eroded-mask pixel only reads pixels inside the original mask, so
    pixels outside the mask never influence the gradient metrics.
    """
    if mask is None:
        return None
    eroded = ndimage.binary_erosion(mask, structure=np.ones((3, 3), bool), border_value=0)[1:-1, 1:-1]
    if not eroded.any():
        raise MetricError("mask: empty after erosion by one pixel for the gradient metrics "
                          "(it has no pixel whose 3 x 3 neighbourhood is all True)")
    return eroded


def _mean_defined(scores: list[np.ndarray], defined: list[bool], batch: int) -> np.ndarray:
    use = [s for s, d in zip(scores, defined) if d]
    if not use:
        return np.zeros(batch)
    return np.mean(use, axis=0)


def gradient_ncc(fixed: np.ndarray, moving: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Gradient NCC: mean of the NCCs of the Sobel x and y gradient images.

    ``GNCC = (NCC(Gx f, Gx m) + NCC(Gy f, Gy m)) / 2`` with ``Gx``, ``Gy`` the 3 x 3 Sobel
    derivatives along x (columns, axis -1) and y (rows, axis -2), same kernels as
    ``scipy.ndimage.sobel``. The NCCs run over the mask eroded by one pixel (3 x 3 square) and
    never over the image's outer one-pixel border, so border gradients do not count. A
    direction in which the fixed gradient image is constant (e.g. a fixed image that varies
    only along x has Gy = 0) is left out of the mean; 0 if both are.

    Args:
        fixed: ``(H, W)``, H, W >= 3. moving: ``(B, H, W)`` or ``(H, W)``. mask: ``(H, W)`` bool.

    Returns:
        ``(B,)`` float64 scores in [-1, 1].
    """
    f, m, k = _check_inputs(fixed, moving, mask, min_size=3)
    ke = _gradient_mask(k)
    fgx, fgy = _sobel_xy(f)
    mgx, mgy = _sobel_xy(m)
    return _plain_gradient_scores(fgx, fgy, mgx, mgy, ke)


class _FixedGradients:
    """The fixed image's part of a gradient NCC, computed once: its Sobel images' NCC terms over the
    eroded mask ``ke`` and whether each direction is defined (not constant)."""

    def __init__(self, fgx: np.ndarray, fgy: np.ndarray, ke: np.ndarray | None) -> None:
        self.parts = [_FixedNCC(fg, ke) for fg in (fgx, fgy)]
        self.defined = [bool(p.fv.std() > _CONSTANT_REL * np.abs(p.fv).max()) for p in self.parts]

    def scores(self, mgx: np.ndarray, mgy: np.ndarray) -> np.ndarray:
        """The mean of the x and y NCCs against the moving Sobel images ``(B, H-2, W-2)``, leaving
        out a direction in which the fixed gradient is constant: ``(B,)``."""
        scores = [p.score(mg) for p, mg in zip(self.parts, (mgx, mgy))]
        return _mean_defined(scores, self.defined, mgx.shape[0])


def _plain_gradient_scores(fgx, fgy, mgx, mgy, ke) -> np.ndarray:
    """Gradient NCC from the fixed ``(H, W)`` and moving ``(B, H, W)`` Sobel images over the eroded
    mask ``ke`` (:class:`_FixedGradients`): ``(B,)``."""
    return _FixedGradients(fgx, fgy, ke).scores(mgx, mgy)


class _RankOrder:
    """The rank order of the fixed image's masked pixels (``idx``: ``(H, W)`` bool), computed once:
    ``values(m)`` re-values them by rank onto each ``m[b]``'s masked values, ``(B, n)`` in the pixel
    order of ``f[idx]`` (see :func:`tone_matched`)."""

    def __init__(self, f: np.ndarray, idx: np.ndarray) -> None:
        self.idx = idx
        values = f[idx]
        self.n = n = values.size
        self.order = np.argsort(values, kind="stable")
        ranked = values[self.order]
        new = np.r_[True, ranked[1:] != ranked[:-1]]
        self.ties = not new.all()
        if self.ties:
            self.starts = np.flatnonzero(new)
            self.ends = np.r_[self.starts[1:], n]
            self.group = np.empty(n, np.intp)
            self.group[self.order] = np.cumsum(new) - 1

    def values(self, m: np.ndarray) -> np.ndarray:
        sorted_moving = np.sort(m[:, self.idx], axis=1)  # (B, n)
        if not self.ties:  # a noisy image: the r-th pixel takes the r-th value
            out = np.empty_like(sorted_moving)
            out[:, self.order] = sorted_moving
            return out
        cums = np.concatenate([np.zeros((m.shape[0], 1)), np.cumsum(sorted_moving, axis=1)], axis=1)
        means = (cums[:, self.ends] - cums[:, self.starts]) / (self.ends - self.starts)  # (B, groups)
        return means[:, self.group]


def _tone_matched_values(f: np.ndarray, m: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """The masked pixels of ``f`` (``idx``: ``(H, W)`` bool) re-valued by rank onto each ``m[b]``'s
    masked values: ``(B, n)`` in the pixel order of ``f[idx]`` (see :func:`tone_matched`)."""
    return _RankOrder(f, idx).values(m)


def tone_matched(fixed: np.ndarray, moving: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """``fixed`` re-valued, for each moving image, onto that image's values by rank: ``(B, H, W)``.

    Within the mask, the pixel of ``fixed`` with the ``r``-th smallest value takes the ``r``-th
    smallest value of ``moving[b]`` over the mask (histogram specification onto the moving image);
    pixels of equal value (a tie group, e.g. quantised grey levels) take the mean of the moving
    values of their rank range, so that no ordering the image does not have is made up. Outside the
    mask ``fixed`` is kept. Any strictly increasing map of ``fixed`` (a display's window, gamma,
    log or linear curve) gives the same result, and at the pose whose DRR ``moving[b]`` is the
    X-ray's view the result is the DRR's own values in the X-ray's order.

    Args: fixed ``(H, W)``; moving ``(B, H, W)`` or ``(H, W)``; mask ``(H, W)`` bool or None.
    """
    f, m, k = _check_inputs(fixed, moving, mask, min_size=3)
    return _tone_matched(f, m, k)


def _tone_matched(f, m, k, rank: _RankOrder | None = None):
    """``f`` re-valued by rank onto each ``m[b]`` over ``k`` (``rank``: ``f``'s :class:`_RankOrder`
    over ``k``, where already computed): ``(B, H, W)``."""
    if rank is None:
        rank = _RankOrder(f, np.ones(f.shape, bool) if k is None else k)
    out = np.empty(m.shape)
    out[:] = f
    out[:, rank.idx] = rank.values(m)
    return out


def _tone_free_scores(toned, mgx, mgy, ke) -> np.ndarray:
    """Gradient NCC of each toned fixed image ``(B, H, W)`` against its own moving image's Sobel
    gradients ``mgx``, ``mgy`` over the eroded mask ``ke``: ``(B,)``."""
    tgx, tgy = _sobel_xy(toned)
    scores = []
    for tg, mg in ((tgx, mgx), (tgy, mgy)):
        num, den_f, den_m = _paired_ncc_terms(tg, mg, ke)
        scores.append(num / np.maximum(np.sqrt(den_f * den_m), 1e-300) * ((den_f > 0) & (den_m > 0)))
    return np.mean(scores, axis=0)


def tone_free_gradient_ncc(fixed: np.ndarray, moving: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Gradient NCC of :func:`tone_matched` ``fixed`` against each moving image: ``(B,)``.

    Invariant to any increasing map of ``fixed`` (the display's unknown look-up table): each
    candidate DRR is compared with the X-ray re-valued onto that DRR's own values by rank, so the
    gradients of the X-ray count with the strength they have in line integrals at that pose, not
    with the display's. The polarity must be right (bone bright). Costs one sort of each moving
    image over the mask on top of :func:`gradient_ncc`.
    """
    f, m, k = _check_inputs(fixed, moving, mask, min_size=3)
    mgx, mgy = _sobel_xy(m)
    return _tone_free_scores(_tone_matched(f, m, k), mgx, mgy, _gradient_mask(k))


def tone_tolerant_gradient_ncc(fixed: np.ndarray, moving: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """The mean of :func:`gradient_ncc` and :func:`tone_free_gradient_ncc`: ``(B,)``.

    Half the score is blind to the display's curve, so a strongly curved display (gamma 2.6, a
    linear display of a 70 kV frame) still scores high at the right pose; half is not, so a wrong
    pose whose DRR lets the rank match threshold the X-ray into its own outline (the tone-free
    score alone reached 0.85-0.93 at wrong poses of log-display frames) is held back by the plain
    half. Measured on the search's frames: docs/domain_gap.md ("The tone"). The moving images'
    gradients are computed once for both halves.
    """
    f, m, k = _check_inputs(fixed, moving, mask, min_size=3)
    ke = _gradient_mask(k)
    fgx, fgy = _sobel_xy(f)
    mgx, mgy = _sobel_xy(m)
    plain = _plain_gradient_scores(fgx, fgy, mgx, mgy, ke)
    return 0.5 * (plain + _tone_free_scores(_tone_matched(f, m, k), mgx, mgy, ke))


def _paired_ncc_terms(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None):
    """Per-batch NCC terms of paired ``(B, H, W)`` images over the mask: ``(cov, var_a, var_b)``, each ``(B,)``."""
    if mask is not None:
        a, b = a[:, mask], b[:, mask]
    else:
        a, b = a.reshape(a.shape[0], -1), b.reshape(b.shape[0], -1)
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    return (a * b).sum(axis=1), (a * a).sum(axis=1), (b * b).sum(axis=1)


# ----------------------------------------------------------------------------- patch NCC


def _box_mean(x: np.ndarray, p: int) -> np.ndarray:
    """Means over every p x p window fully inside ``(..., H, W)``: ``(..., H-p+1, W-p+1)``.

    Separable box filter (``scipy.ndimage.uniform_filter1d`` along x, then y: running sums in
    float64), cropped to the windows centred at least ``p // 2`` px from the border, so the
    boundary mode never matters. Output ``[..., i, j]`` is the window centred on pixel
    ``(i + p // 2, j + p // 2)``.
    """
    r = p // 2
    a = ndimage.uniform_filter1d(x, p, axis=-1)[..., r : x.shape[-1] - r]
    return ndimage.uniform_filter1d(a, p, axis=-2)[..., r : x.shape[-2] - r, :]


def _normalise(v: np.ndarray, axis: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and std over ``axis`` (keepdims; 0 and 1 for a constant image) and a flag per image
    that it is not constant."""
    mean = v.mean(axis=axis, keepdims=True)
    std = v.std(axis=axis, keepdims=True)
    scale = np.abs(v).max(axis=axis, keepdims=True)
    ok = std > _CONSTANT_REL * scale
    return np.where(ok, mean, 0.0), np.where(ok, std, 1.0), ok


def _patch_core(
    f: np.ndarray, m: np.ndarray, mask: np.ndarray | None, p: int, min_valid: float
) -> tuple[np.ndarray, bool]:
    """Mean windowed NCC of f ``(H, W)`` vs m ``(B, H, W)`` (checked inputs): ``(B,)`` scores
    and whether the fixed image has any textured window (else the scores are 0)."""
    batch = m.shape[0]
    # Global normalisation over the mask (zero mean, unit std) keeps the box sums well
    # conditioned for any a I + b and makes the texture threshold relative.
    if mask is None:
        fmu, fsd, fok = _normalise(f, None)
        mmu, msd, mok = _normalise(m, (1, 2))
    else:
        fmu, fsd, fok = _normalise(f[mask], None)
        mmu, msd, mok = _normalise(m[:, mask], 1)
        mmu, msd = mmu[:, :, None], msd[:, :, None]
    mok = mok.reshape(-1)
    fn = (f - fmu) / fsd
    mn = m - mmu
    mn /= msd
    # Box means of w x divided by the box mean of w (the window's mask fraction) are the
    # means over the window's masked pixels.
    if mask is None:
        inv_frac: np.ndarray | float = 1.0
        covered = np.ones((f.shape[0] - p + 1, f.shape[1] - p + 1), bool)
    else:
        w = mask.astype(np.float64)
        fn *= w  # zero outside the mask: outside values never enter a sum
        mn *= w
        frac = _box_mean(w, p)
        covered = frac >= max(min_valid, 2.0 / (p * p)) - 1e-9
        if not covered.any():
            raise NoWindowError(f"mask: no {p} x {p} window has at least min_valid = {min_valid} of its "
                              f"pixels inside the mask")
        inv_frac = 1.0 / np.maximum(frac, 1.0 / (p * p))
    sf = _box_mean(fn, p) * inv_frac
    var_f = _box_mean(fn * fn, p) * inv_frac - sf * sf
    sel = covered & (var_f > _LOCAL_VAR_REL)
    n_sel = int(sel.sum())
    if not (bool(fok.all()) and n_sel):
        return np.zeros(batch), False  # fixed image (locally) flat everywhere: no defined correlation
    # Moving statistics on the full window grid (B, H', W'); unselected windows get weight 0.
    sm = _box_mean(mn, p)
    sm *= inv_frac
    var_m = _box_mean(mn * mn, p)
    var_m *= inv_frac
    var_m -= sm * sm
    cov = _box_mean(mn * fn, p)  # fn, mn each carry the 0/1 mask weight: w^2 = w
    cov *= inv_frac
    sm *= sf
    cov -= sm
    flat = var_m <= _LOCAL_VAR_REL  # moving flat in the window: NCC_w = 0
    var_m[flat] = 1.0
    var_m *= np.where(sel, var_f, 1.0)
    np.sqrt(var_m, out=var_m)
    cov /= var_m
    cov[flat] = 0.0
    np.clip(cov, -1.0, 1.0, out=cov)
    out = np.einsum("bij,ij->b", cov, sel.astype(np.float64)) / n_sel
    return np.where(mok, out, 0.0), True


def patch_ncc(
    fixed: np.ndarray,
    moving: np.ndarray,
    patch: int = 11,
    mask: np.ndarray | None = None,
    min_valid: float = 0.5,
) -> np.ndarray:
    """Local (patch-wise) NCC averaged over windows.

    For every ``patch x patch`` window centred on a pixel and lying fully inside the image
    (centres at least ``patch // 2`` px from the border), the NCC of the two images over the
    window's masked pixels is computed from separable box filters on the whole batch::

        NCC_w = cov_w(f, m) / sqrt(var_w(f) var_w(m)),
        cov_w = <f m>_w - <f>_w <m>_w,  var_w(f) = <f^2>_w - <f>_w^2

    with ``<.>_w`` the mean over the window's pixels inside the mask. The score is the mean of
    ``NCC_w`` over the windows that (a) have at least ``min_valid`` of their ``patch^2``
    pixels (and at least 2) inside the mask and (b) are textured in the fixed image: local
    std above 1e-4 x the fixed image's global std over the mask. A window where the moving
    image is flat (same relative threshold) contributes 0. Both images are first normalised
    to zero mean and unit std over the mask (which does not change any ``NCC_w``), so the
    score is invariant to a global ``a I + b`` (a > 0) of either image.

    Args:
        fixed: ``(H, W)``. moving: ``(B, H, W)`` or ``(H, W)``.
        patch: odd window side in pixels, 3 <= patch <= min(H, W).
        mask: optional ``(H, W)`` bool. min_valid: fraction in (0, 1] (used with a mask).

    Returns:
        ``(B,)`` float64 scores in [-1, 1]; 0 if no window of the fixed image is textured.

    Raises:
        MetricError: bad inputs, or no window meets ``min_valid``.
    """
    f, m, k = _check_inputs(fixed, moving, mask)
    p = _check_patch(patch, f.shape)
    mv = _check_min_valid(min_valid)
    return _patch_core(f, m, k, p, mv)[0]


def _check_min_valid(min_valid: Any) -> float:
    try:
        v = float(min_valid)
    except (TypeError, ValueError):
        raise MetricError(f"min_valid: expected a fraction in (0, 1], got {min_valid!r}") from None
    if not 0.0 < v <= 1.0:
        raise MetricError(f"min_valid: expected a fraction in (0, 1], got {v}")
    return v


def patch_gradient_ncc(
    fixed: np.ndarray,
    moving: np.ndarray,
    patch: int = 11,
    mask: np.ndarray | None = None,
    min_valid: float = 0.5,
) -> np.ndarray:
    """Patch gradient NCC (Grupp et al. 2020; xReg's "patch gradient NCC").

    ``(patch_ncc(Gx f, Gx m) + patch_ncc(Gy f, Gy m)) / 2`` with the Sobel gradients of
    :func:`gradient_ncc` on the ``(H-2, W-2)`` interior and the mask eroded by one pixel;
    the windows and their selection are those of :func:`patch_ncc` on the gradient images.
    A direction with no textured window in the fixed gradient is left out of the mean.

    Args:
        fixed: ``(H, W)``. moving: ``(B, H, W)`` or ``(H, W)``.
        patch: odd window side in pixels, 3 <= patch <= min(H, W) - 2.
        mask: optional ``(H, W)`` bool. min_valid: fraction in (0, 1].

    Returns:
        ``(B,)`` float64 scores in [-1, 1].
    """
    f, m, k = _check_inputs(fixed, moving, mask, min_size=3)
    p = _check_patch(patch, (f.shape[0] - 2, f.shape[1] - 2))
    mv = _check_min_valid(min_valid)
    ke = _gradient_mask(k)
    fgx, fgy = _sobel_xy(f)
    mgx, mgy = _sobel_xy(m)
    scores, defined = [], []
    for fg, mg in ((fgx, mgx), (fgy, mgy)):
        s, d = _patch_core(fg, mg, ke, p, mv)
        scores.append(s)
        defined.append(d)
    return _mean_defined(scores, defined, m.shape[0])


#: :func:`local_gradient_ncc`'s window (px, odd) at :data:`LOCAL_REFERENCE_SIDE_PX` on the image's
#: longer side (:func:`local_patch_px` scales it): about 12 % of the image, some 35 mm of a pelvis at
#: the optimiser's 128 px, a bone edge's neighbourhood with room for its shift by a few px.
LOCAL_PATCH_PX = 15
LOCAL_REFERENCE_SIDE_PX = 128


def local_patch_px(shape) -> int:
    """:func:`local_gradient_ncc`'s window (odd px, at least 5) for an image of ``shape`` ``(..., h,
    w)``: :data:`LOCAL_PATCH_PX` scaled from :data:`LOCAL_REFERENCE_SIDE_PX` on the longer side.

    Example::

        >>> local_patch_px((128, 96)), local_patch_px((256, 256)), local_patch_px((32, 32))
        (15, 31, 5)
    """
    side = max(int(shape[-2]), int(shape[-1]))
    return max(5, 2 * int(LOCAL_PATCH_PX * side / LOCAL_REFERENCE_SIDE_PX // 2) + 1)


def local_gradient_ncc(fixed: np.ndarray, moving: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Patch gradient NCC (:func:`patch_gradient_ncc`) in windows of :func:`local_patch_px` of the
    image: the similarity of the edges window by window. The whole image's gradient NCC can rest on
    one strong edge (a body's outline over air dominates both images' gradients, and any pose that
    puts the outline in place scores high); here each textured window counts once, whatever its
    contrast.

    Args:
        fixed: ``(H, W)``. moving: ``(B, H, W)`` or ``(H, W)``. mask: optional ``(H, W)`` bool.

    Returns:
        ``(B,)`` float64 scores in [-1, 1]; :class:`NoWindowError` where no window has half its
        pixels in the mask (a field smaller than one window).

    Example::

        >>> img = np.add.outer(np.arange(64.0), np.arange(64.0) ** 1.5)
        >>> float(local_gradient_ncc(img, img)[0])
        1.0
    """
    return patch_gradient_ncc(fixed, moving, patch=local_patch_px(np.shape(fixed)), mask=mask)


def image_sobel(images: np.ndarray, axis: int) -> np.ndarray:
    """The Sobel gradient of each image of ``images`` ``(..., H, W)`` along ``axis`` (-1: x, -2: y),
    of the same shape: ``scipy.ndimage.sobel`` of each ``(H, W)`` image (borders reflected). Unlike
    ``ndimage.sobel`` on the whole array, whose smoothing runs along every other axis, a batch's
    images are not blended with their neighbours.

    Example::

        >>> imgs = np.random.default_rng(0).random((3, 8, 8))
        >>> bool(np.allclose(image_sobel(imgs, -1)[1], ndimage.sobel(imgs[1], axis=-1)))
        True
    """
    a = np.asarray(images, np.float64)
    if axis not in (-1, -2):
        raise MetricError(f"axis: expected -1 (x) or -2 (y), got {axis!r}")
    d = ndimage.correlate1d(a, [-1.0, 0.0, 1.0], axis=axis, mode="reflect")
    return ndimage.correlate1d(d, [1.0, 2.0, 1.0], axis=-3 - axis, mode="reflect")


#: :func:`local_gradients`' floor: this share of the median local RMS gradient (over the mask) is
#: added to each pixel's, so that a flat region's noise is not raised to the strength of an edge.
LOCAL_GRADIENT_FLOOR = 0.2


def local_gradients(images: np.ndarray, mask: np.ndarray | None = None, sigma_px: float = 2.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The Sobel gradients ``(gx, gy)`` of ``images`` divided by their local RMS magnitude (a
    Gaussian window of ``sigma_px``, over ``mask`` only where one is given) plus
    :data:`LOCAL_GRADIENT_FLOOR` times its median: every textured region's edges at about one
    strength, so that a correlation of them counts each region alike (a body's outline over air no
    longer outweighs the bones; :func:`local_gradient_ncc` does so window by window, this for
    correlations over the whole image, such as the global search's FFT ones).

    Args:
        images: ``(H, W)`` or ``(B, H, W)`` real. mask: optional ``(H, W)`` bool, the pixels that
            count (the local RMS is their Gaussian-weighted mean; outside, the gradients are 0).
        sigma_px: the window's standard deviation (px), > 0.

    Returns:
        ``(gx, gy)``, each of ``images``' shape, float64 (x along the last axis).

    Example::

        >>> img = np.zeros((32, 32)); img[:, 16:] = 100.0; img[8:12, 4:8] += 1.0  # a strong and a weak edge
        >>> gx, _ = local_gradients(img)
        >>> bool(0.5 < abs(gx[10, 4]) / abs(gx[20, 15]) < 2.0)  # alike, where the raw ones differ 100x
        True
    """
    a = np.asarray(images, np.float64)
    if a.ndim not in (2, 3) or min(a.shape[-2:]) < 3:
        raise MetricError(f"images: expected (H, W) or (B, H, W) with H, W >= 3, got shape {a.shape}")
    if not (np.isfinite(sigma_px) and sigma_px > 0):
        raise MetricError(f"sigma_px: expected a positive number, got {sigma_px!r}")
    gx, gy = image_sobel(a, -1), image_sobel(a, -2)
    sig = (0.0,) * (a.ndim - 2) + (float(sigma_px),) * 2
    energy = gx * gx + gy * gy
    if mask is None:
        w = np.ones(a.shape[-2:])
    else:
        w = np.asarray(mask, bool)
        if w.shape != a.shape[-2:]:
            raise MetricError(f"mask: expected shape {a.shape[-2:]}, got {w.shape}")
        w = w.astype(np.float64)
    weight = ndimage.gaussian_filter(w, float(sigma_px))
    rms = np.sqrt(ndimage.gaussian_filter(energy * w, sig) / np.maximum(weight, 1e-12))
    inside = (w > 0) & (weight > 1e-6)
    flat = rms.reshape(-1, *a.shape[-2:])[:, inside]
    floor = LOCAL_GRADIENT_FLOOR * np.median(flat, axis=-1) if flat.size else np.zeros(len(flat))
    floor = np.maximum(floor, 1e-12).reshape((-1, 1, 1) if a.ndim == 3 else ())
    scale = w / (rms + floor)
    return gx * scale, gy * scale


# ----------------------------------------------------------------------------- registry


def _without_options(name: str, metric: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    """The registry entry of a metric that takes no options: ``entry(fixed, moving, mask=None)``."""
    def entry(fixed, moving, mask=None, **kw):
        if kw:
            raise MetricError(f"{name}: unexpected options {sorted(kw)}")
        return metric(fixed, moving, mask)
    return entry


def _patch_ncc_entry(fixed, moving, mask=None, **kw):
    return patch_ncc(fixed, moving, mask=mask, **kw)


def _patch_gncc_entry(fixed, moving, mask=None, **kw):
    return patch_gradient_ncc(fixed, moving, mask=mask, **kw)


#: Metrics by name; each is ``metric(fixed (H, W), moving (B, H, W), mask=None, **kw) -> (B,)``
#: (``patch`` and ``min_valid`` keywords for the patch metrics).
METRICS: dict[str, Callable[..., np.ndarray]] = {
    "ncc": _without_options("ncc", ncc),
    "gncc": _without_options("gncc", gradient_ncc),
    "tone_free_gncc": _without_options("tone_free_gncc", tone_free_gradient_ncc),
    "tone_tolerant_gncc": _without_options("tone_tolerant_gncc", tone_tolerant_gradient_ncc),
    "patch_ncc": _patch_ncc_entry,
    "patch_gncc": _patch_gncc_entry,
    "local_gncc": _without_options("local_gncc", local_gradient_ncc),
}


#: The display-tolerant metrics and what an image of line integrals (a raw or log X-ray, a DRR:
#: no display curve to forgive) is scored by instead.
_PLAIN_EQUIVALENT = {"tone_free_gncc": "gncc", "tone_tolerant_gncc": "gncc"}


def plain_equivalent(name: str) -> str:
    """The metric that scores an image of line integrals where ``name`` is display-tolerant
    (``"tone_tolerant_gncc"`` -> ``"gncc"``); any other name unchanged."""
    return _PLAIN_EQUIVALENT.get(name, name)


def get_metric(name: str) -> Callable[..., np.ndarray]:
    """The metric registered as ``name`` in :data:`METRICS`; MetricError listing the names otherwise."""
    try:
        return METRICS[name]
    except (KeyError, TypeError):
        raise MetricError(f"metric: unknown name {name!r}; valid names: {', '.join(sorted(METRICS))}") from None


#: The metrics :func:`bind_metric` prepares the fixed image of (the others are bound as they are).
_BINDABLE = ("gncc", "tone_free_gncc", "tone_tolerant_gncc")


def bind_metric(name: str, fixed: Any, mask: Any = None) -> Callable[[Any], np.ndarray]:
    """The metric ``name`` with its fixed image ``(H, W)`` and mask ``(H, W)`` bool (or None) bound:
    ``score(moving)`` -> ``(B,)`` for ``moving`` ``(B, H, W)`` or ``(H, W)``, equal to
    ``get_metric(name)(fixed, moving, mask=mask)`` (tested to the bit).

    An optimiser scores hundreds of DRRs against one X-ray; the gradient metrics' work on the
    fixed image alone (its Sobel gradients and their NCC terms, the eroded mask, the rank order of
    its pixels for the tone-free half: about half of a 128 x 128 call) is then done once, here.
    Inputs are checked here (fixed, mask) and at each call (moving).

    Example::

        >>> import numpy as np
        >>> x = np.add.outer(np.arange(8.0), np.arange(8.0) ** 2)
        >>> score = bind_metric("gncc", x)
        >>> bool(np.isclose(score(x)[0], 1.0))
        True
    """
    metric = get_metric(name)
    if name not in _BINDABLE:
        return lambda moving: metric(fixed, moving, mask=mask)
    f, k = _check_fixed(fixed, mask, min_size=3)
    ke = _gradient_mask(k)
    plain = None if name == "tone_free_gncc" else _FixedGradients(*_sobel_xy(f), ke)
    rank = None if name == "gncc" else _RankOrder(f, np.ones(f.shape, bool) if k is None else k)

    def score(moving: Any) -> np.ndarray:
        m = _check_moving(moving, f.shape)
        mgx, mgy = _sobel_xy(m)
        scores = None if plain is None else plain.scores(mgx, mgy)
        if rank is None:
            return scores
        free = _tone_free_scores(_tone_matched(f, m, k, rank), mgx, mgy, ke)
        return free if scores is None else 0.5 * (scores + free)

    return score


def bind_metric_at(name: str, fixed: Any, mask: Any, factor: int) -> Callable[[Any], np.ndarray]:
    """:func:`bind_metric` at ``factor``'s resolution: ``fixed`` ``(H, W)`` block-mean downsampled
    (:func:`downsample`) and ``mask`` ``(H, W)`` bool kept where every pixel of a block is valid;
    ``score(moving)`` then takes ``(B, H/f, W/f)`` DRRs rendered at that resolution. Factor 1 is
    :func:`bind_metric` itself.

    Example::

        >>> import numpy as np
        >>> x = np.add.outer(np.arange(8.0), np.arange(8.0) ** 2)
        >>> score = bind_metric_at("ncc", x, None, 2)
        >>> bool(np.isclose(score(downsample(x, 2))[0], 1.0))
        True
    """
    if factor == 1:
        return bind_metric(name, fixed, mask)
    m = None if mask is None else downsample(np.asarray(mask, np.float64), factor) > 0.999
    return bind_metric(name, downsample(np.asarray(fixed, np.float64), factor), m)


# ----------------------------------------------------------------------------- pyramids


def _pyramid_down(
    f: np.ndarray, m: np.ndarray, mask: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One pyramid level: Gaussian sigma = 1 px (truncated at 4 sigma, edge replicated), every
    second pixel from (0, 0) (size ceil(n / 2)). With a mask, the smoothing is mask-normalised,
    ``G(w I) / G(w)``, so outside pixels carry no weight, and the mask is min-pooled over 2 x 2
    blocks (a coarse pixel is valid only if all the fine pixels of its block are)."""
    if mask is None:
        fs = ndimage.gaussian_filter(f, 1.0, mode="nearest")
        ms = ndimage.gaussian_filter(m, 1.0, mode="nearest", axes=(-2, -1))
        return fs[::2, ::2], ms[:, ::2, ::2], None
    w = mask.astype(np.float64)
    h, wd = mask.shape
    padded = np.pad(mask, ((0, h % 2), (0, wd % 2)), mode="edge")
    pooled = padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2).all(axis=(1, 3))
    if not pooled.any():
        raise MetricError("mask: empty after 2 x 2 min-pooling for a coarser pyramid level")
    gw = ndimage.gaussian_filter(w, 1.0, mode="nearest")[::2, ::2]
    safe = np.where(pooled, gw, 1.0)
    fs = ndimage.gaussian_filter(f * w, 1.0, mode="nearest")[::2, ::2] / safe
    ms = ndimage.gaussian_filter(m * w, 1.0, mode="nearest", axes=(-2, -1))[:, ::2, ::2] / safe
    return np.where(pooled, fs, 0.0), np.where(pooled, ms, 0.0), pooled


def multiscale(
    metric: str | Callable[..., np.ndarray],
    fixed: np.ndarray,
    moving: np.ndarray,
    levels: int = 3,
    mask: np.ndarray | None = None,
    **kw: Any,
) -> np.ndarray:
    """Mean of ``metric`` over a ``levels``-level Gaussian pyramid of both images.

    Level 0 is the full resolution; level ``l + 1`` is level ``l`` smoothed with a Gaussian of
    sigma 1 px and subsampled by taking every second pixel (see :func:`_pyramid_down` for the
    masked case: mask-normalised smoothing and 2 x 2 min-pooled masks, so pixels outside the
    mask still never matter). ``metric`` is a name of :data:`METRICS` or a callable
    ``metric(fixed, moving, mask=..., **kw) -> (B,)``; ``kw`` (e.g. ``patch``) is passed to
    every level, so the coarsest level must still fit the patch.

    Returns:
        ``(B,)`` float64: the mean of the ``levels`` per-level scores.
    """
    fn = get_metric(metric) if isinstance(metric, str) else metric
    if not callable(fn):
        raise MetricError(f"metric: expected a name or a callable, got {metric!r}")
    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or levels < 1:
        raise MetricError(f"levels: expected an integer >= 1, got {levels!r}")
    f, m, k = _check_inputs(fixed, moving, mask)
    if min(f.shape) >> (int(levels) - 1) < 1:
        raise MetricError(f"levels: {levels} levels halve images of shape {f.shape} below one pixel")
    total = np.zeros(m.shape[0])
    for lev in range(int(levels)):
        if lev:
            f, m, k = _pyramid_down(f, m, k)
        total += fn(f, m, mask=k, **kw)
    return total / int(levels)


def downsample(images: np.ndarray, factor: int) -> np.ndarray:
    """Block-mean downsampling of ``(..., H, W)`` images by an integer ``factor``.

    Output pixel ``[..., i, j]`` is the mean of ``images[..., f i : f (i + 1), f j : f (j + 1)]``;
    output shape ``(..., H // f, W // f)``. When H or W is not divisible by the factor, the
    last ``H % f`` rows / ``W % f`` columns are cropped (dropped) first. Floating inputs keep
    their dtype (the mean is accumulated in float64); integer inputs give float64.

    Raises:
        MetricError: ``factor`` not a positive integer, fewer than 2 dimensions, non-numeric
            images, or an image smaller than ``factor`` along H or W.
    """
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise MetricError(f"factor: expected a positive integer, got {factor!r}")
    arr = np.asarray(images)
    if arr.ndim < 2:
        raise MetricError(f"images: expected (..., H, W), got shape {arr.shape}")
    if arr.dtype == bool or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise MetricError(f"images: expected real numeric values, got dtype {arr.dtype}")
    f = int(factor)
    h, w = arr.shape[-2] // f, arr.shape[-1] // f
    if h == 0 or w == 0:
        raise MetricError(f"images: shape {arr.shape[-2:]} is smaller than factor {f}")
    out_dtype = arr.dtype if np.issubdtype(arr.dtype, np.floating) else np.float64
    blocks = arr[..., : h * f, : w * f].reshape(*arr.shape[:-2], h, f, w, f)
    return blocks.mean(axis=(-3, -1), dtype=np.float64).astype(out_dtype, copy=False)
