"""The imaging chain after the render, in one place: collimator, scatter, noise, display, for a batch of images.

Every realistic image of the project leaves the render through :func:`apply_chain`, a frame of one
as a batch of one:

* the held-out frames of the studies and the demo (``register.evaluation.frames.FrameSimulator``:
  its collimator and display chain, on the imager's signal);
* the per-pair training targets (:func:`sim.randomize.apply_image`: one pair's
  :class:`sim.randomize.Draw`, NumPy in and out, float64);
* the batched training pairs (``learn.batched.BatchedPairs``: a batch of draws on the CPU or a GPU).

The randomized settings are drawn in one place (:meth:`sim.randomize.DomainRandomization.draw`,
turned into ``(B,)`` tensors by :func:`sim.randomize.draw_tensors`) and applied here; a fixed
:class:`sim.physics.display.DisplayChain` becomes the same tensors by its ``tensors`` method, and its
``apply`` is :func:`display` of those. A fix to a stage (a display curve, a noise term) reaches
every image. The stages, in order:

1. collimation: the signal outside the field times ``field_transmission`` (the field: the
   caller's, e.g. :meth:`sim.physics.display.Collimator.mask`, or :func:`field_masks` of the drawn
   settings, equal to it);
2. scatter, each image its own choice: a Gaussian kernel (:func:`gaussian_reflect`), or the
   scatter-kernel superposition fitted to the Monte Carlo (``sks``: :func:`sks_scatter_batched`,
   times a smooth random texture, with its quantum noise); the Monte Carlo transport's own scatter
   is the render's, added by the caller before;
3. electronic noise ``electronic_noise_fraction x i0 x normals``;
4. the display chain (:func:`display`): log or linear, window percentiles over the field
   (:func:`masked_percentile`), polarity, unsharp mask (:func:`field_blur`), gamma, the bit depth,
   the shutter outside the field.

The same code runs on the CPU or a GPU, every image with its own settings, no Python loop over
images or pixels (only over the few discrete choices). Both Gaussians are separable linear
operators with mirrored edges, applied as a ``(H, H)`` and a ``(W, W)`` matrix per image (two
batched matrix products, the mirror folded into the matrices): the kernel scatter's is the
periodic Gaussian of the ``(2H, 2W)`` mirror extension (its transfer function), the unsharp mask's
scipy ``gaussian_filter``'s kernel (mode ``reflect``, truncated at 4 sigma, normalised). The cost
is ``O(H W (H + W))`` per image: cheap for the network's 64-256 px images and a study's 512 px frames.

Exactness: ``tests/sim/test_physics_chain.py`` checks each stage against an independent NumPy /
SciPy implementation (FFT Gaussian, ``scipy.ndimage.gaussian_filter``, ``numpy.percentile``, the
scatter-kernel model's own ``predict``): in float64 the display integers are equal (a level apart
only where ``x (2^bits - 1)`` lies within rounding of a half-integer: none in the tests); in float32
(the GPU default), at most one level on about 0.1 % of the pixels.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from sim.physics import PhysicsError
from sim.physics.scatter_kernel import default_table
from sim.projection.geometry import CArmGeometry

__all__ = ["FIELD_CODES", "GEOMETRY_KEYS", "DISPLAY_KEYS", "field_masks", "gaussian_reflect", "field_blur",
           "kernel_superposition", "sks_scatter_batched", "sks_texture", "masked_percentile", "display", "apply_chain"]

#: ``p["field_code"]`` of :func:`sim.randomize.draw_tensors`: the shape of each pair's collimated
#: field, as :meth:`sim.randomize.Draw.collimator` builds it (a circle with blades is ``iris-blades``).
FIELD_CODES: tuple[str, ...] = ("none", "circle", "rectangle", "iris-blades")

#: The field geometry entries of :func:`sim.randomize.draw_tensors`, kept in float64 whatever the
#: dtype, so that :func:`field_masks` equals the NumPy masks exactly.
GEOMETRY_KEYS = ("field_cx", "field_cy", "field_r", "field_half_u", "field_half_v", "field_cos", "field_sin")

#: scipy.ndimage.gaussian_filter's default kernel radius, in sigmas.
_TRUNCATE = 4.0


def _entries(p, names: Sequence[str], batch: int | None, where: str) -> int:
    """Check that ``p`` holds ``(B,)`` tensors ``names`` of one length; return ``B``."""
    if not isinstance(p, dict):
        raise PhysicsError(f"{where}: p must be the dict of draw_tensors(draws), got {type(p).__name__}")
    missing = [k for k in names if k not in p]
    if missing:
        raise PhysicsError(f"{where}: p lacks {missing} (make p with draw_tensors(draws))")
    for k in names:
        t = p[k]
        if not isinstance(t, torch.Tensor) or t.ndim != 1 or (batch is not None and t.shape[0] != batch):
            shape = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            want = f"({batch},)" if batch is not None else "(B,)"
            raise PhysicsError(f"{where}: p[{k!r}] must be a {want} tensor, got {shape}")
        batch = t.shape[0]
    return batch


def _size(name: str, n, where: str) -> int:
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise PhysicsError(f"{where}: {name} must be a positive integer number of pixels, got {n!r}")
    return n


# --------------------------------------------------------------------------------------------
# collimator
# --------------------------------------------------------------------------------------------


def field_masks(p: dict[str, torch.Tensor], height: int, width: int) -> torch.Tensor:
    """The collimated field of every pair: ``(B, height, width)`` bool, True inside.

    ``p`` is :func:`sim.randomize.draw_tensors`'s dict (its ``field_code`` and ``field_*`` geometry); the
    result is on their device. Pixel ``(row, column)`` is inside when its centre ``(column + 0.5,
    row + 0.5)`` (pixels) is inside the shape or on its boundary, computed in float64 with the
    operations of :meth:`sim.physics.display.Collimator.mask`: equal to
    ``draw.collimator(height, width).mask(height, width)`` (all True for ``field = "none"``).
    A field may hold no pixel (``Draw.collimator`` refuses that; :func:`apply_chain`
    does too).
    """
    names = ("field_code",) + GEOMETRY_KEYS
    _entries(p, names, None, "field_masks")
    h, w = _size("height", height, "field_masks"), _size("width", width, "field_masks")
    code = p["field_code"]
    dev = code.device
    g = {k: p[k].to(device=dev, dtype=torch.float64)[:, None, None] for k in GEOMETRY_KEYS}
    x = (torch.arange(w, dtype=torch.float64, device=dev) + 0.5)[None, None, :]
    y = (torch.arange(h, dtype=torch.float64, device=dev) + 0.5)[None, :, None]
    dx = x - g["field_cx"] * w
    dy = y - g["field_cy"] * h
    r = g["field_r"] * min(h, w)
    circle = dx * dx + dy * dy <= r * r
    c, s = g["field_cos"], g["field_sin"]
    u = dx * c - dy * s
    v = dx * s + dy * c
    blades = (u.abs() <= g["field_half_u"] * w) & (v.abs() <= g["field_half_v"] * h)
    code = code[:, None, None]
    return torch.where(code == 0, True, torch.where(code == 1, circle, torch.where(code == 2, blades, blades & circle)))


# --------------------------------------------------------------------------------------------
# filters and statistics
# --------------------------------------------------------------------------------------------


def _image(name: str, x, where: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or x.ndim != 3 or x.is_complex() or x.dtype == torch.bool:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise PhysicsError(f"{where}: {name} must be a real (B, H, W) tensor, got {shape}")
    return x if x.dtype.is_floating_point else x.to(torch.get_default_dtype())


def _per_pair(name: str, v, batch: int, like: torch.Tensor, where: str) -> torch.Tensor:
    """A ``(B,)`` tensor (or a number, for every pair) as ``like``'s device and dtype."""
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return torch.full((batch,), float(v), dtype=like.dtype, device=like.device)
    if not isinstance(v, torch.Tensor) or v.shape != (batch,) or v.is_complex() or v.dtype == torch.bool:
        shape = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
        raise PhysicsError(f"{where}: {name} must be a ({batch},) real tensor (one value per pair), got {shape}")
    return v.to(device=like.device, dtype=like.dtype)


def gaussian_reflect(x: torch.Tensor, sigma_px) -> torch.Tensor:
    """Gaussian blur with mirrored edges, one sigma per image (the kernel scatter, the sks texture, the detector blur).

    ``x`` ``(B, H, W)`` (any unit; float), ``sigma_px`` ``(B,)`` (or one number) Gaussian sigma
    in pixels, >= 0 -> ``(B, H, W)``, same dtype and device. The operator: the circular convolution
    of the ``(2H, 2W)`` mirror extension (edge pixels repeated: scipy's ``reflect``), which is
    periodic, with the Gaussian's transfer function ``exp(-2 pi^2 sigma^2 f^2)`` (one 2-D FFT would
    do it). That transfer function is separable, so the same operator is ``A_H x A_W^T``:
    ``A_n[i, j] = k(i - j) + k(i + j + 1)`` (indices mod ``2n``) with ``k`` the periodic kernel
    of length ``2n``, the inverse 1-D FFT of the pair's transfer function (float64), the mirror
    folded in. Equal to the FFT's result up to rounding (1e-15 relative in float64), and for
    the network's image sizes faster than the 2-D FFTs (two ``(n, n)`` matrix products per pair).
    """
    x = _image("x", x, "gaussian_reflect")
    b, h, w = x.shape
    sigma = _per_pair("sigma_px", sigma_px, b, x.to(torch.float64), "gaussian_reflect")
    if not bool(torch.all(torch.isfinite(sigma) & (sigma >= 0))):
        raise PhysicsError("gaussian_reflect: sigma_px must be finite and >= 0 (pixels)")
    kh = _mirror_gaussian_matrices(sigma, h, x.dtype)
    kw = kh if w == h else _mirror_gaussian_matrices(sigma, w, x.dtype)  # square images: one operator
    return torch.bmm(torch.bmm(kh, x), kw.transpose(1, 2))


def _mirror_gaussian_matrices(sigma: torch.Tensor, n: int, dtype: torch.dtype) -> torch.Tensor:
    """``(B, n, n)``: the 1-D operator of :func:`gaussian_reflect` along an axis of ``n`` pixels
    for sigma ``(B,)`` float64 (px): the periodic Gaussian of the ``2n`` mirror extension."""
    f = torch.arange(0, n + 1, dtype=torch.float64, device=sigma.device) * (1.0 / (2 * n))  # rfftfreq(2n)
    transfer = torch.exp((-2.0 * math.pi ** 2) * (sigma * sigma)[:, None] * (f * f)[None, :])
    k = torch.fft.irfft(transfer.to(torch.complex128), n=2 * n, dim=1)  # (B, 2n), real
    i = torch.arange(n, device=sigma.device)
    direct = (i[:, None] - i[None, :]) % (2 * n)
    mirrored = (i[:, None] + i[None, :] + 1) % (2 * n)
    return (k[:, direct] + k[:, mirrored]).to(dtype)


def kernel_superposition(tau: torch.Tensor, tau_nodes, amplitude: torch.Tensor, sigma1_mm: torch.Tensor,
                         sigma2_mm: torch.Tensor, broad_fraction: torch.Tensor, aspect: torch.Tensor,
                         spacing_mm: float) -> torch.Tensor:
    """Scatter-kernel superposition (:mod:`sim.physics.scatter_kernel`) of a batch, each pair with
    its own kernels: ``ScatterKernelModel.predict`` batched, divided by the flat-field signal.

    Args:
        tau: ``(B, H, W)`` log primary ``-ln(P / I0)`` (dimensionless; below 0 counts as 0).
        tau_nodes: ``(K,)`` the thickness nodes (shared by the pairs: one table's).
        amplitude, sigma1_mm, sigma2_mm, broad_fraction: ``(B, K)`` each pair's model (widths in
            mm at the detector, already scaled to the pair's air gap: ``ScatterKernelModel.scaled``).
        aspect: ``(B,)`` the kernels' width along the columns over the width along the rows.
        spacing_mm: detector pixel spacing (mm).

    Returns:
        ``(B, H, W)`` scatter per flat-field signal ``S / I0`` (>= 0), ``tau``'s dtype. The
        convolution is linear (cut at the detector's edges, nothing folded back) and separable:
        per pair, node and Gaussian a ``(H, H)`` and a ``(W, W)`` matrix of pixel-integrated 1-D
        Gaussians (``ndtr`` differences, as the numpy model's kernel spectra), two batched matrix
        products. Equal to the NumPy model's ``predict`` to float32 rounding (``tests/sim/test_physics_chain.py``).
    """
    where = "kernel_superposition"
    tau = _image("tau", tau, where)
    b, h, w = tau.shape
    dt, dev = tau.dtype, tau.device
    nodes = torch.as_tensor(tau_nodes, dtype=torch.float64, device=dev).reshape(-1)
    k = nodes.numel()
    params = {}
    for name, v in (("amplitude", amplitude), ("sigma1_mm", sigma1_mm), ("sigma2_mm", sigma2_mm),
                    ("broad_fraction", broad_fraction)):
        if not isinstance(v, torch.Tensor) or v.shape != (b, k):
            shape = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
            raise PhysicsError(f"{where}: {name} must be a ({b}, {k}) tensor (pairs x thickness nodes), got {shape}")
        params[name] = v.to(device=dev, dtype=torch.float64)
    if not bool(torch.all(params["sigma1_mm"] > 0) & torch.all(params["sigma2_mm"] > 0)):
        raise PhysicsError(f"{where}: the kernel widths must be > 0 mm")
    asp = _per_pair("aspect", aspect, b, tau.to(torch.float64), where)
    t = tau.clamp(min=0.0)
    g = t * torch.exp(-t)
    pc = torch.zeros_like(t)  # node coordinate, as scatter_kernel._node_coordinate
    for lo, hi in zip(nodes[:-1].tolist(), nodes[1:].tolist()):
        pc = pc + ((t - lo) * (1.0 / (hi - lo))).clamp(0.0, 1.0)
    j = torch.arange(k, device=dev, dtype=dt)
    src = g[:, None] * (1.0 - (pc[:, None] - j[None, :, None, None]).abs()).clamp(min=0.0)  # (B, K, H, W)
    ry = torch.sqrt(asp)[:, None, None]  # (B, 1, 1)
    f = params["broad_fraction"][:, :, None]
    sig = torch.stack([params["sigma1_mm"], params["sigma2_mm"]], dim=2)  # (B, K, 2)
    share = torch.cat([1.0 - f, f], dim=2) * params["amplitude"][:, :, None]  # (B, K, 2)
    ky = _pixel_gaussian_matrices(sig * ry, h, spacing_mm, dt) * share[..., None, None].to(dt)  # (B, K, 2, H, H)
    kx = _pixel_gaussian_matrices(sig / ry, w, spacing_mm, dt)  # (B, K, 2, W, W)
    x = src[:, :, None].expand(b, k, 2, h, w).reshape(-1, h, w)
    y = torch.bmm(torch.bmm(ky.reshape(-1, h, h), x), kx.reshape(-1, w, w).transpose(1, 2))
    return y.reshape(b, k * 2, h, w).sum(1).clamp(min=0.0)


def _pixel_gaussian_matrices(sigma_mm: torch.Tensor, n: int, spacing_mm: float, dtype: torch.dtype) -> torch.Tensor:
    """``sigma_mm.shape + (n, n)`` in ``dtype``: entry ``[i, j]`` the integral over pixel ``i`` of a
    unit 1-D Gaussian of ``sigma_mm`` centred on pixel ``j`` (``scatter_kernel._axis_kernel``): the
    ``2n - 1`` displacements' integrals (float64 ``ndtr`` differences) gathered into a Toeplitz matrix."""
    edges = (torch.arange(-n, n, dtype=torch.float64, device=sigma_mm.device) + 0.5) * float(spacing_mm)  # (2n,)
    cdf = torch.special.ndtr(edges / sigma_mm[..., None])
    kernel = (cdf[..., 1:] - cdf[..., :-1]).to(dtype)  # displacements -(n-1) .. n-1
    i = torch.arange(n, device=sigma_mm.device)
    return kernel[..., i[:, None] - i[None, :] + n - 1]


def _reflect_index(i: torch.Tensor, n: int) -> torch.Tensor:
    """scipy's ``reflect`` extension (``d c b a | a b c d | d c b a``, period ``2n``) of indices ``i``."""
    m = torch.remainder(i, 2 * n)
    return torch.where(m >= n, 2 * n - 1 - m, m)


def _gaussian_matrices(sigma: torch.Tensor, n: int, dtype: torch.dtype) -> torch.Tensor:
    """``(B, n, n)``: row ``i`` holds the weights of scipy's 1-D ``gaussian_filter`` (``reflect``,
    truncate 4) of output pixel ``i`` on the input pixels, for the sigma ``(B,)`` (px) of each pair."""
    s = sigma.to(torch.float64)
    radius = torch.floor(_TRUNCATE * s + 0.5).to(torch.int64)  # int(truncate * sd + 0.5)
    big = int(radius.max()) if radius.numel() else 0
    k = torch.arange(-big, big + 1, device=s.device)
    phi = torch.exp((-0.5 / (s * s))[:, None] * (k * k).to(torch.float64)[None, :])
    phi = torch.where(k.abs()[None, :] <= radius[:, None], phi, 0.0)
    phi = phi / phi.sum(1, keepdim=True)
    cols = _reflect_index(torch.arange(n, device=s.device)[:, None] + k[None, :], n)  # (n, 2R+1)
    mat = torch.zeros(s.shape[0], n, n, dtype=torch.float64, device=s.device)
    mat.scatter_add_(2, cols[None].expand(s.shape[0], -1, -1), phi[:, None, :].expand(-1, n, -1).contiguous())
    return mat.to(dtype)


def _gaussian_filter(x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """scipy ``gaussian_filter(x, sigma, mode="reflect")`` (truncate 4) of ``x`` ``(B, C, H, W)``,
    one sigma ``(B,)`` (px, > 0) per pair (shared by its ``C`` images)."""
    b, c, h, w = x.shape
    kh = _gaussian_matrices(sigma, h, x.dtype)
    kw = kh if w == h else _gaussian_matrices(sigma, w, x.dtype)
    y = torch.bmm(x.reshape(b, c * h, w), kw.transpose(1, 2)).reshape(b, c, h, w)  # along the rows
    y = torch.bmm(kh, y.permute(0, 2, 1, 3).reshape(b, h, c * w))  # along the columns
    return y.reshape(b, h, c, w).permute(0, 2, 1, 3)


def field_blur(x: torch.Tensor, sigma: torch.Tensor, field: torch.Tensor) -> torch.Tensor:
    """The unsharp mask's blur: ``(B, H, W)`` -> ``(B, H, W)``; the normalised
    Gaussian inside the field and, separately, outside it; the plain one where the field is
    the whole image."""
    mf = field.to(x.dtype)
    out_f = (~field).to(x.dtype)
    g = _gaussian_filter(torch.stack([x * mf, mf, x * out_f, out_f], dim=1), sigma)
    full = field.flatten(1).all(1)[:, None, None]
    inside = g[:, 0] / g[:, 1].clamp_min(torch.finfo(x.dtype).tiny)
    outside = g[:, 2] / g[:, 3].clamp_min(torch.finfo(x.dtype).tiny)
    return torch.where(full, g[:, 0], torch.where(field, inside, outside))


def masked_percentile(x: torch.Tensor, mask: torch.Tensor | None, q) -> torch.Tensor:
    """``numpy.percentile`` (its default linear interpolation) of each pair's masked values.

    Args:
        x: ``(B, N)`` or ``(B, H, W)`` real values (any unit), finite where masked.
        mask: bool of ``x``'s shape (None: every value); each pair must have a masked value.
        q: percentiles in [0, 100] (%): a number, a sequence of ``K`` numbers, or a ``(K,)``
            or ``(B, K)`` tensor (a ``(B, K)`` one: each pair its own).

    Returns:
        ``(B, K)``, ``x``'s dtype and device: ``numpy.percentile(x[b][mask[b]], q[b])`` per pair,
        computed as numpy does (virtual index ``(n - 1) q / 100`` in float64, its neighbours in
        the sorted values -- the unmasked ones pushed to +inf by the sort -- and numpy's lerp).
    """
    where = "masked_percentile"
    if not isinstance(x, torch.Tensor) or x.ndim not in (2, 3) or x.is_complex() or x.dtype == torch.bool:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise PhysicsError(f"{where}: x must be a real (B, N) or (B, H, W) tensor, got {shape}")
    if not x.dtype.is_floating_point:
        x = x.to(torch.get_default_dtype())
    b = x.shape[0]
    flat = x.reshape(b, math.prod(x.shape[1:]))
    if mask is None:
        mflat = torch.ones_like(flat, dtype=torch.bool)
    else:
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != x.shape:
            got = f"{mask.dtype} {tuple(mask.shape)}" if isinstance(mask, torch.Tensor) else type(mask).__name__
            raise PhysicsError(f"{where}: mask must be a bool tensor of x's shape {tuple(x.shape)}, got {got}")
        mflat = mask.reshape(flat.shape).to(x.device)
    if isinstance(q, torch.Tensor):
        qt = q.to(device=x.device, dtype=torch.float64)
    else:
        try:
            qt = torch.tensor(q, dtype=torch.float64, device=x.device)
        except (TypeError, ValueError, RuntimeError):
            raise PhysicsError(f"{where}: q must be percentiles in [0, 100] (%), got {q!r}") from None
    if qt.ndim == 0:
        qt = qt[None]
    if qt.ndim == 1:
        qt = qt[None].expand(b, -1)
    if qt.ndim != 2 or qt.shape[0] != b:
        raise PhysicsError(f"{where}: q must be (K,) or ({b}, K) percentiles, got shape {tuple(qt.shape)}")
    if not bool(torch.all((qt >= 0) & (qt <= 100))):
        raise PhysicsError(f"{where}: q must be percentiles in [0, 100] (%)")
    n = mflat.sum(1)
    if b and not bool(torch.all(n > 0)):
        raise PhysicsError(f"{where}: every pair's mask must hold a value (pairs "
                           f"{torch.nonzero(n == 0).flatten().tolist()[:10]} hold none)")
    last = (n - 1)[:, None]
    vi = last.to(torch.float64) * (qt / 100.0)
    prev = torch.floor(vi)
    gamma = (vi - prev).to(x.dtype)
    i0 = torch.minimum(prev.to(torch.int64), last)
    ranks = torch.cat([i0, torch.minimum(i0 + 1, last)], dim=1)  # (B, 2K) ranks in the sorted masked values
    a, c = _order_statistics(flat, mflat, ranks, last).chunk(2, dim=1)
    diff = c - a
    return torch.where(gamma >= 0.5, c - diff * (1 - gamma), a + diff * gamma)


def _order_statistics(flat: torch.Tensor, mflat: torch.Tensor, ranks: torch.Tensor, last: torch.Tensor
                      ) -> torch.Tensor:
    """The values of ``ranks`` ``(B, R)`` (0: the smallest) among each row's masked values of
    ``flat`` ``(B, N)`` (``last`` ``(B, 1)``: their count - 1). Window percentiles need only the
    few lowest and highest ranks: then two ``topk`` (unmasked values pushed to +inf / -inf),
    about twice as fast as sorting the rows; otherwise the sort."""
    low_side = ranks <= last - ranks
    k_low = int(torch.where(low_side, ranks + 1, 0).max()) if ranks.numel() else 0
    k_up = int(torch.where(low_side, 0, last - ranks + 1).max()) if ranks.numel() else 0
    if 2 * (k_low + k_up) >= flat.shape[1]:
        return torch.where(mflat, flat, torch.inf).sort(dim=1).values.gather(1, ranks)
    out = torch.zeros(ranks.shape, dtype=flat.dtype, device=flat.device)
    if k_low:
        low = torch.where(mflat, flat, torch.inf).topk(k_low, dim=1, largest=False).values  # ascending
        out = torch.where(low_side, low.gather(1, ranks.clamp(max=k_low - 1)), out)
    if k_up:
        up = torch.where(mflat, flat, -torch.inf).topk(k_up, dim=1, largest=True).values  # descending
        out = torch.where(low_side, out, up.gather(1, (last - ranks).clamp(0, k_up - 1)))
    return out


# --------------------------------------------------------------------------------------------
# the chain
# --------------------------------------------------------------------------------------------

#: The settings of the display stage (:func:`display`), one ``(B,)`` tensor each: ``log`` (bool),
#: ``polarity`` (int64, the index in ``sim.physics.display.POLARITIES``: 1 bone-bright),
#: ``window_low`` / ``window_high`` (%), ``gamma``, ``unsharp`` (bool), ``unsharp_sigma_px`` (px),
#: ``unsharp_amount``, ``max_value`` (``2^bits - 1``), ``shutter`` (int64, the index in
#: ``sim.physics.display.SHUTTERS``: 0 black, 1 white, 2 none).
DISPLAY_KEYS = ("log", "polarity", "window_low", "window_high", "gamma", "unsharp", "unsharp_sigma_px",
                "unsharp_amount", "max_value", "shutter")

#: The settings of the stages before the display (:func:`apply_chain`): ``scatter`` (int64, the index
#: in ``("none", "kernel", "monte-carlo", "sks")``), ``field_transmission`` (fraction); and where
#: used, ``electronic_noise_fraction`` (of ``i0``), the kernel scatter's ``scatter_spr`` and
#: ``scatter_sigma`` (fraction of the shorter side), the sks scatter's settings.
_SIGNAL_KEYS = ("scatter", "field_transmission")
_KERNEL_KEYS = ("scatter_spr", "scatter_sigma")
_SKS_KEYS = ("sks_amplitude", "sks_width", "sks_open", "sks_texture", "sks_texture_sigma", "kvp", "grid", "grid_ratio")


def sks_scatter_batched(raw: torch.Tensor, i0: torch.Tensor, models, geometry, gap_mm=None) -> torch.Tensor:
    """Expected scatter signal ``(B, H, W)`` of ``B`` :class:`ScatterKernelModel` s (one per pair,
    one table's: the same thickness nodes) on the log of the signal ``raw`` ``(B, H, W)`` over
    ``i0`` ``(B,)``: ``ScatterKernelModel.predict(-ln(raw / i0), geometry, flat_signal=i0,
    gap_mm=gap)`` of each pair (:func:`kernel_superposition`; ``gap_mm`` ``(B,)`` mm or None: each
    model's reference gap; rounded to 0.5 mm as ``predict`` does)."""
    where = "sks_scatter_batched"
    b, h, w = raw.shape
    models = list(models)
    if len(models) != b or not models or any(m.tau_nodes != models[0].tau_nodes for m in models):
        raise PhysicsError(f"{where}: one model per pair ({b}), all with the same thickness nodes")
    if (geometry.height, geometry.width) != (h, w):
        raise PhysicsError(f"{where}: the geometry is {geometry.height} x {geometry.width} px, raw {h} x {w}")
    gaps = [None] * b if gap_mm is None else [float(x) for x in gap_mm]
    if len(gaps) != b:
        raise PhysicsError(f"{where}: gap_mm must be ({b},) mm, got {len(gaps)} values")
    scaled = [m.scaled(m.gap_ref_mm if g is None or m.gap_ref_mm == 0 else round(g * 2.0) / 2.0)
              for m, g in zip(models, gaps)]
    dev = raw.device
    amp, s1, s2 = (torch.tensor([sc[j] for sc in scaled], dtype=torch.float64, device=dev) for j in range(3))
    frac = torch.tensor([m.broad_fraction for m in models], dtype=torch.float64, device=dev)
    aspect = torch.tensor([m.aspect for m in models], dtype=torch.float64, device=dev)
    tau = -torch.log(torch.maximum(raw, 1e-12 * i0[:, None, None]) / i0[:, None, None])
    return kernel_superposition(tau, models[0].tau_nodes, amp, s1, s2, frac, aspect,
                                geometry.pixel_spacing_mm) * i0[:, None, None]


def sks_texture(normals: torch.Tensor, strength, sigma_px) -> torch.Tensor:
    """The smooth random factor on the ``sks`` scatter: ``max(0, 1 + strength n)`` with ``n`` the
    standard normal numbers ``normals`` ``(B, H, W)`` blurred by a Gaussian of ``sigma_px`` ``(B,)``
    (mirrored edges, :func:`gaussian_reflect`) and scaled back to unit standard deviation
    (``x 2 sqrt(pi) sigma``, white noise's under a 2-D Gaussian; exact away from the edges for
    sigma >= 1 px). ``strength`` ``(B,)`` (or one number); the result in ``normals``' dtype."""
    n = _image("normals", normals, "sks_texture")
    b = n.shape[0]
    sigma = _per_pair("sigma_px", sigma_px, b, n.to(torch.float64), "sks_texture")
    strength = _per_pair("strength", strength, b, n, "sks_texture")
    texture = gaussian_reflect(n, sigma) * ((2.0 * math.sqrt(math.pi)) * sigma)[:, None, None].to(n.dtype)
    return (1.0 + strength[:, None, None] * texture).clamp(min=0.0)


def display(signal: torch.Tensor, i0: torch.Tensor, field: torch.Tensor, d: dict[str, torch.Tensor]) -> torch.Tensor:
    """The display chain (:class:`sim.physics.display.DisplayChain`) of each image, its own settings.

    Args:
        signal: ``(B, H, W)`` detector signal (keV or counts per pixel), finite.
        i0: ``(B,)`` flat-field signal (same unit, > 0).
        field: ``(B, H, W)`` bool, the collimated field (the window's pixels; each holds one).
        d: the :data:`DISPLAY_KEYS` settings, ``(B,)`` tensors.

    Returns:
        ``(B, H, W)`` in ``signal``'s dtype, integers in ``0 .. 2^bits - 1``: ``-log(max(I, 1e-12 i0) /
        i0)`` or ``I / i0``; the window percentiles over the field (:func:`masked_percentile`) to 0 / 1,
        clipped (a flat field: 1 above its value, 0 below, 0.5 at it); ``1 - x`` where the polarity
        asks (log images are bone bright, linear ones bone dark); the unsharp mask ``x + amount (x -
        G(x))`` (:func:`field_blur`), clipped; ``x ** gamma``; ``round(x (2^bits - 1))`` half to even;
        outside the field the shutter's 0 or ``2^bits - 1`` (``none``: the processed shadow).
    """
    dt = signal.dtype
    col = lambda k: k[:, None, None]  # noqa: E731 (B,) -> (B, 1, 1)
    f = {k: d[k].to(device=signal.device, dtype=dt) if d[k].dtype.is_floating_point else d[k].to(signal.device)
         for k in DISPLAY_KEYS}
    i0 = i0.to(device=signal.device, dtype=dt)
    log = f["log"]
    v = torch.where(col(log), -torch.log(torch.maximum(signal, col(1e-12 * i0)) / col(i0)), signal / col(i0))
    window = torch.stack([d["window_low"], d["window_high"]], dim=1).to(device=signal.device, dtype=torch.float64)
    lohi = masked_percentile(v, field, window)
    lo, hi = col(lohi[:, 0]), col(lohi[:, 1])
    span = hi - lo
    flat = torch.where(v > lo, 1.0, torch.where(v < lo, 0.0, 0.5)).to(dt)
    x = torch.where(span > 0, ((v - lo) / torch.where(span > 0, span, 1.0)).clamp(0.0, 1.0), flat)
    flip = log != (f["polarity"] == 1)  # bone-bright is POLARITIES[1]
    x = torch.where(col(flip), 1.0 - x, x)
    sharp = torch.nonzero(f["unsharp"] & (f["unsharp_amount"] > 0)).flatten()
    if sharp.numel():
        xs, fs = x[sharp], field[sharp]
        blurred = field_blur(xs, d["unsharp_sigma_px"][sharp].to(device=signal.device, dtype=torch.float64), fs)
        xs = (xs + col(f["unsharp_amount"][sharp]) * (xs - blurred)).clamp(0.0, 1.0)
        x = x.index_copy(0, sharp, xs)
    x = torch.pow(x, col(f["gamma"]))
    top = col(f["max_value"])
    out = torch.round(x * top)  # half to even, as numpy.rint
    shutter = col(f["shutter"])
    return torch.where(field, out, torch.where(shutter == 0, 0.0, torch.where(shutter == 1, top, out)).to(dt))


def apply_chain(raw: torch.Tensor, i0, p: dict[str, torch.Tensor], normals: torch.Tensor | None = None, *,
                field: torch.Tensor | None = None, geometry=None, gap_mm=None,
                scatter_normals: torch.Tensor | None = None, sks_table=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The imaging chain after the render (module doc) for a batch of images, each with its own settings.

    Args:
        raw: ``(B, H, W)`` raw detector signal (keV or counts per pixel, the render's ``raw``; a
            Monte Carlo render's scatter already in it).
        i0: ``(B,)`` flat-field signal per image (same unit, > 0), or one number for all.
        p: the settings, ``(B,)`` tensors: :func:`sim.randomize.draw_tensors` of the images' draws, or
            a fixed chain's (``DisplayChain.tensors`` with ``scatter`` and ``field_transmission``).
            Their ``scatter`` must be ``none``, ``kernel`` or ``sks`` (the Monte Carlo's is the
            render's: add it before, as :func:`sim.randomize.apply_image` does).
        normals: ``(B, H, W)`` standard normal numbers, the electronic noise (image ``b`` of a
            per-pair draw: ``image_rng(seed, index).standard_normal((H, W))``); None: no electronic
            noise (an imager that adds its own).
        field: ``(B, H, W)`` bool, the collimated field (each holding a pixel); None:
            :func:`field_masks` of ``p``.
        geometry, gap_mm, scatter_normals, sks_table: for images whose scatter is ``sks``: the
            images' :class:`sim.projection.geometry.CArmGeometry` (required then), the target poses'
            air gaps ``(B,)`` mm (None: the models' reference gap), ``(B, 2, H, W)`` standard normal
            numbers for the scatter's quantum noise and its texture (required then; a per-pair draw's
            second and third draws of its ``rng``), the :class:`ScatterKernelTable` (None: the default).

    Returns:
        ``(image, field)``: ``image`` ``(B, H, W)`` in ``raw``'s floating dtype (float32 for integer
        input), integer values in ``0 .. 2^bits - 1``; ``field`` ``(B, H, W)`` bool. Both on ``raw``'s device.
    """
    where = "apply_chain"
    raw = _image("raw", raw, where)
    b, h, w = raw.shape
    _entries(p, _SIGNAL_KEYS + DISPLAY_KEYS, b, where)
    if normals is not None and (not isinstance(normals, torch.Tensor) or normals.shape != raw.shape):
        shape = tuple(normals.shape) if isinstance(normals, torch.Tensor) else type(normals).__name__
        raise PhysicsError(f"{where}: normals must be a tensor of raw's shape {tuple(raw.shape)}, got {shape}")
    dt, dev = raw.dtype, raw.device
    i0 = _per_pair("i0", i0, b, raw, where)
    if not bool(torch.all(torch.isfinite(i0) & (i0 > 0))):
        raise PhysicsError(f"{where}: i0 (the flat-field signal) must be finite and > 0 for every image")
    if not bool(torch.all(torch.isfinite(raw))):
        raise PhysicsError(f"{where}: raw must be finite (no NaN or inf)")
    scatter = p["scatter"].to(dev)
    mc = scatter == 2
    if bool(mc.any()):
        raise PhysicsError(f"{where}: images {torch.nonzero(mc).flatten().tolist()[:10]} have scatter monte-carlo; "
                           f"its scatter is the render's (add it to raw and pass scatter none: "
                           f"sim.randomize.apply_image)")
    kern = torch.nonzero(scatter == 1).flatten()
    sks = torch.nonzero(scatter == 3).flatten()
    _entries(p, (("electronic_noise_fraction",) if normals is not None else ()) + (_KERNEL_KEYS if kern.numel() else ())
             + (_SKS_KEYS if sks.numel() else ()), b, where)
    if field is None:
        field = field_masks(p, h, w).to(dev)
    elif not isinstance(field, torch.Tensor) or field.dtype != torch.bool or field.shape != raw.shape:
        got = f"{field.dtype} {tuple(field.shape)}" if isinstance(field, torch.Tensor) else type(field).__name__
        raise PhysicsError(f"{where}: field must be a bool tensor of raw's shape {tuple(raw.shape)}, got {got}")
    field = field.to(dev)
    if b and not bool(field.flatten(1).any(1).all()):
        empty = torch.nonzero(~field.flatten(1).any(1)).flatten().tolist()[:10]
        raise PhysicsError(f"{where}: the fields of images {empty} hold no pixel of a {h} x {w} image")
    col = lambda k: k[:, None, None]  # noqa: E731 (B,) -> (B, 1, 1)
    num = lambda k: p[k].to(device=dev, dtype=dt)  # noqa: E731 (a float setting in raw's dtype)

    # 1. collimation; 2. scatter; 3. electronic noise
    transmission = num("field_transmission")
    x = torch.where(field, raw, raw * col(transmission))
    if kern.numel():
        xk = x[kern]
        sigma = p["scatter_sigma"].to(device=dev, dtype=torch.float64)[kern] * min(h, w)
        x = x.index_copy(0, kern, xk + col(num("scatter_spr")[kern]) * gaussian_reflect(xk, sigma))
    if sks.numel():
        if not isinstance(geometry, CArmGeometry) or (geometry.height, geometry.width) != (h, w):
            raise PhysicsError(f"{where}: images with scatter sks need their geometry (a CArmGeometry of {h} x "
                               f"{w} px), got {geometry!r}")
        if not isinstance(scatter_normals, torch.Tensor) or scatter_normals.shape != (b, 2, h, w):
            raise PhysicsError(f"{where}: images with scatter sks need scatter_normals of shape {(b, 2, h, w)}")
        table = default_table() if sks_table is None else sks_table
        rows = sks.tolist()
        kv, grid, ratio, amp, wid = (p[k].to(dev)[sks].tolist() for k in ("kvp", "grid", "grid_ratio",
                                                                         "sks_amplitude", "sks_width"))
        models = [table.drawn(kv[j], ratio[j] if grid[j] else 0.0, amp[j], wid[j]) for j in range(len(rows))]
        gaps = None if gap_mm is None else [float(gap_mm[r]) for r in rows]
        opened = p["sks_open"].to(dev)[sks][:, None, None]
        source = torch.where(opened, raw[sks], x[sks])  # sks_open: the exposure before collimation
        sc = sks_scatter_batched(source, i0[sks], models, geometry, gaps)
        sc = torch.where(opened & ~field[sks], sc * col(transmission[sks]), sc)
        spp = torch.tensor([m.signal_per_photon for m in models], dtype=dt, device=dev)[:, None, None]
        sn = scatter_normals[sks].to(device=dev, dtype=dt)
        sigma = p["sks_texture_sigma"].to(device=dev, dtype=torch.float64)[sks] * min(h, w)
        sc = sc * sks_texture(sn[:, 1], num("sks_texture")[sks], sigma)
        scatter_add = sc + torch.sqrt(sc * spp) * sn[:, 0]
    if normals is not None:
        x = x + col(num("electronic_noise_fraction") * i0) * normals.to(device=dev, dtype=dt)
    if sks.numel():
        x = x.index_add(0, sks, scatter_add)

    # 4. the display chain
    return display(x, i0, field, p), field
