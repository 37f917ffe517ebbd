"""The post-render stages of domain randomization, batched in torch: many training pairs at once, on any device.

:func:`sim.randomize.apply_image` turns one pair's raw detector signal into the integers a
C-arm displays (collimation, kernel scatter, electronic noise, the display chain of
:mod:`sim.physics.display`), in numpy, one pair at a time. Training draws thousands of pairs
per second, so this module does the same for a batch ``(B, H, W)`` in torch: the same code
on the CPU or a GPU, every pair with its own drawn settings, no Python loop over pairs or
pixels (only over the few discrete choices). Each function equals its numpy counterpart
(``tests/sim/test_physics_batched.py``):

* :func:`draw_tensors`: a list of :class:`sim.randomize.Draw` -> one ``(B,)`` tensor per
  declared setting (and a few derived ones);
* :func:`field_masks`: :meth:`sim.physics.display.Collimator.mask` of every pair (exact: the
  geometry is computed in float64 with the numpy code's operations);
* :func:`gaussian_reflect`: ``sim.randomize._kernel_scatter`` (the Gaussian of the mirror
  extension, by its transfer function), one sigma per pair;
* :func:`kernel_superposition`, :func:`sks_scatter_batched`: ``ScatterKernelModel.predict``
  (:mod:`sim.physics.scatter_kernel`), each pair with its own fitted kernels (``scatter = "sks"``);
* :func:`masked_percentile`: ``numpy.percentile`` (linear interpolation) over each pair's
  masked values;
* :func:`apply_image_batched`: stages 2-4 of :func:`sim.randomize.apply_image` for draws whose
  scatter is ``none``, ``kernel`` or ``sks`` (a Monte Carlo transport per pair is not a batch job).

Both Gaussians are separable linear operators with mirrored edges, so both are applied as a
``(H, H)`` and a ``(W, W)`` matrix per pair (two batched matrix products, the mirror folded
into the matrices): the kernel scatter's with the periodic Gaussian of numpy's FFT (its
transfer function), the display chain's unsharp mask with scipy ``gaussian_filter``'s kernel
(mode ``reflect``, truncated at 4 sigma, normalised). Both equal their numpy / scipy
counterparts up to rounding (1e-15 in float64), not merely up to the difference between a
truncated and an FFT Gaussian. The cost is ``O(H W (H + W))`` per pair: cheap for the
network's 64-256 px images (an FFT would be cheaper for much larger ones).

Exactness: in float64, :func:`apply_image_batched` gives ``apply_image``'s integers (a level
apart only where ``x (2^bits - 1)`` lies within rounding of a half-integer: none in the tests);
in float32 (the GPU default), at most one level on about 0.1 % of the pixels.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from sim.physics import PhysicsError
from sim.randomize import DECLARATION, Draw
from sim.physics.scatter_kernel import default_table
from sim.projection.geometry import CArmGeometry

__all__ = ["FIELD_CODES", "draw_tensors", "field_masks", "gaussian_reflect", "kernel_superposition",
           "sks_scatter_batched", "masked_percentile", "apply_image_batched"]

#: ``p["field_code"]`` of :func:`draw_tensors`: the shape of each pair's collimated field, as
#: :meth:`sim.randomize.Draw.collimator` builds it (a circle with blades is ``iris-blades``).
FIELD_CODES: tuple[str, ...] = ("none", "circle", "rectangle", "iris-blades")

#: The derived entries of :func:`draw_tensors` kept in float64 whatever ``dtype``: the field
#: geometry, so that :func:`field_masks` equals the numpy masks exactly.
_GEOMETRY = ("field_cx", "field_cy", "field_r", "field_half_u", "field_half_v", "field_cos", "field_sin")

#: scipy.ndimage.gaussian_filter's default kernel radius, in sigmas.
_TRUNCATE = 4.0


# --------------------------------------------------------------------------------------------
# draws -> tensors
# --------------------------------------------------------------------------------------------


def draw_tensors(draws: Sequence, *, device=None, dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
    """The drawn settings of a batch as tensors, one ``(B,)`` tensor per entry.

    Args:
        draws: ``B`` :class:`sim.randomize.Draw` (``DomainRandomization.draw``), one per pair.
        device: where the tensors live (None: torch's default device).
        dtype: the floating dtype of the numeric settings.

    Returns:
        ``{name: (B,) tensor}`` with, for every declared setting (:data:`sim.randomize.DECLARATION`)
        under its own name and in its own unit:

        * ``uniform`` / ``log-uniform`` settings: the value, ``dtype``;
        * ``bernoulli`` settings: bool;
        * ``choice`` settings: int64 codes, the index of the value in the setting's declared
          ``choices`` (e.g. ``scatter``: 0 ``none``, 1 ``kernel``, 2 ``monte-carlo``; ``bits``:
          0 for 8, 1 for 10, 2 for 12, 3 for 16); a choice among numbers (``cu_mm``, ``bits``)
          also gets ``<name>_value``, the value itself, ``dtype``;

        and the derived entries

        * ``field_code`` int64: the field's shape, an index into :data:`FIELD_CODES` (0 none,
          1 circle, 2 rectangle, 3 iris-blades, as :meth:`sim.randomize.Draw.collimator`);
        * ``field_cx``, ``field_cy``: the field centre, fractions of the width and height
          (``0.5 + field_offset_x``, ``0.5 + field_offset_y``);
        * ``field_r``: the circle radius, a fraction of the shorter side (circle, iris-blades);
        * ``field_half_u``, ``field_half_v``: the blades' half width (fraction of the width) and
          half height (fraction of the height) along their rotated axes (rectangle:
          ``field_half_width``, ``field_half_height``; iris-blades: 5.0, ``field_blade_half``);
        * ``field_cos``, ``field_sin``: cosine and sine of the blades' rotation
          (``field_rotation_deg``, or ``field_blade_rotation_deg`` for iris-blades), computed as
          :meth:`Collimator.mask` does (Python's ``math``);
        * ``max_value``: ``2^bits - 1``, ``dtype``.

        The seven ``field_*`` geometry entries are float64 whatever ``dtype`` (the masks of
        :func:`field_masks` are then exactly the numpy ones); the device must support float64.
    """

    try:
        draws = list(draws)
    except TypeError:
        raise PhysicsError(f"draw_tensors: draws must be a list of sim.randomize.Draw, got {type(draws).__name__}") \
            from None
    bad = [type(d).__name__ for d in draws if not isinstance(d, Draw)]
    if bad:
        raise PhysicsError(f"draw_tensors: draws must be sim.randomize.Draw (DomainRandomization.draw), got {bad[0]}")
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise PhysicsError(f"draw_tensors: dtype must be a torch floating dtype, got {dtype!r}")
    values = [d.values for d in draws]
    out: dict[str, torch.Tensor] = {}

    def put(name, column, kind):
        out[name] = torch.tensor(column, dtype=kind, device=device).reshape(len(draws))

    for r in DECLARATION:
        column = [v[r.name] for v in values]
        if r.dist == "bernoulli":
            put(r.name, [bool(c) for c in column], torch.bool)
        elif r.dist == "choice":
            put(r.name, [r.choices.index(c) for c in column], torch.int64)
            if all(not isinstance(c, str) for c in r.choices):
                put(f"{r.name}_value", [float(c) for c in column], dtype)
        else:
            put(r.name, [float(c) for c in column], dtype)

    geo = {k: [] for k in ("field_code",) + _GEOMETRY}
    for v in values:
        shape, blades = v["field"], v["field_blades"]
        code = FIELD_CODES.index("iris-blades" if shape == "circle" and blades else shape)
        if code == 3:
            half, rot = (5.0, float(v["field_blade_half"])), float(v["field_blade_rotation_deg"])
        else:
            half, rot = (float(v["field_half_width"]), float(v["field_half_height"])), float(v["field_rotation_deg"])
        t = math.radians(rot)
        for k, x in zip(geo, (code, 0.5 + float(v["field_offset_x"]), 0.5 + float(v["field_offset_y"]),
                              float(v["field_radius"]), half[0], half[1], math.cos(t), math.sin(t))):
            geo[k].append(x)
    put("field_code", geo.pop("field_code"), torch.int64)
    for k, column in geo.items():
        put(k, column, torch.float64)
    put("max_value", [float((1 << int(v["bits"])) - 1) for v in values], dtype)
    return out


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

    ``p`` is :func:`draw_tensors`'s dict (its ``field_code`` and ``field_*`` geometry); the
    result is on their device. Pixel ``(row, column)`` is inside when its centre ``(column + 0.5,
    row + 0.5)`` (pixels) is inside the shape or on its boundary, computed in float64 with the
    operations of :meth:`sim.physics.display.Collimator.mask`: equal to
    ``draw.collimator(height, width).mask(height, width)`` (all True for ``field = "none"``).
    A field may hold no pixel (``Draw.collimator`` refuses that; :func:`apply_image_batched`
    does too).
    """
    names = ("field_code",) + _GEOMETRY
    _entries(p, names, None, "field_masks")
    h, w = _size("height", height, "field_masks"), _size("width", width, "field_masks")
    code = p["field_code"]
    dev = code.device
    g = {k: p[k].to(device=dev, dtype=torch.float64)[:, None, None] for k in _GEOMETRY}
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
    """Gaussian blur with mirrored edges, one sigma per pair: ``sim.randomize._kernel_scatter`` batched.

    ``x`` ``(B, H, W)`` (any unit; float), ``sigma_px`` ``(B,)`` (or one number) Gaussian sigma
    in pixels, >= 0 -> ``(B, H, W)``, same dtype and device. The numpy function convolves the
    ``(2H, 2W)`` mirror extension (edge pixels repeated: scipy's ``reflect``), which is
    periodic, circularly with the Gaussian's transfer function ``exp(-2 pi^2 sigma^2 f^2)`` by
    one 2-D FFT. That transfer function is separable, so the same operator is ``A_H x A_W^T``:
    ``A_n[i, j] = k(i - j) + k(i + j + 1)`` (indices mod ``2n``) with ``k`` the periodic kernel
    of length ``2n``, the inverse 1-D FFT of the pair's transfer function (float64), the mirror
    folded in. Equal to the numpy function up to rounding (1e-15 relative in float64), and for
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
        products. Equal to the numpy model to float32 rounding (``tests/sim/test_physics_batched.py``).
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


def _field_blur(x: torch.Tensor, sigma: torch.Tensor, field: torch.Tensor) -> torch.Tensor:
    """``sim.physics.display._blur`` batched: ``(B, H, W)`` -> ``(B, H, W)``; the normalised
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
# apply_image, batched
# --------------------------------------------------------------------------------------------

_APPLY_NEEDS = ("scatter", "scatter_spr", "scatter_sigma", "sks_amplitude", "sks_width", "sks_open", "sks_texture",
                "sks_texture_sigma", "kvp", "grid", "grid_ratio",
                "electronic_noise_fraction", "field_transmission",
                "shutter", "log", "polarity", "window_low", "window_high", "gamma", "unsharp", "unsharp_sigma_px",
                "unsharp_amount", "max_value", "field_code") + _GEOMETRY


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


def apply_image_batched(raw: torch.Tensor, i0, p: dict[str, torch.Tensor], normals: torch.Tensor, *,
                        geometry=None, gap_mm=None, scatter_normals: torch.Tensor | None = None, sks_table=None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Stages 2-4 of :func:`sim.randomize.apply_image` for a batch of pairs, each with its own draw.

    Args:
        raw: ``(B, H, W)`` raw detector signal (keV or counts per pixel, the render's ``raw``).
        i0: ``(B,)`` flat-field signal per pair (same unit, > 0), or one number for all.
        p: :func:`draw_tensors` of the pairs' draws; their ``scatter`` must be ``none``,
            ``kernel`` or ``sks`` (``monte-carlo`` needs the render's scatter image: use ``apply_image``).
        normals: ``(B, H, W)`` standard normal numbers, the electronic noise (pair ``b`` as
            ``apply_image`` with ``image_rng(seed, index)``:
            ``image_rng(seed, index).standard_normal((H, W))``).
        geometry, gap_mm, scatter_normals, sks_table: for pairs whose scatter is ``sks``
            (``apply_image``'s): the images' :class:`sim.projection.geometry.CArmGeometry` (required then),
            the target poses' air gaps ``(B,)`` mm (None: the models' reference gap), ``(B, 2, H,
            W)`` standard normal numbers for the scatter's quantum noise and its texture (required
            then; ``apply_image``'s second and third draws of the pair's ``rng``), the
            :class:`ScatterKernelTable` (None: the default).

    Returns:
        ``(image, field)``: ``image`` ``(B, H, W)`` in ``raw``'s floating dtype (float32 for
        integer input), integer values in ``0 .. 2^bits - 1`` (``apply_image``'s ``uint16``);
        ``field`` ``(B, H, W)`` bool, the collimated field (all True when open). Both on
        ``raw``'s device.

    The stages, as ``apply_image``: the signal outside the field times ``field_transmission``;
    kernel scatter ``scatter_spr * G(raw)`` (:func:`gaussian_reflect`, sigma ``scatter_sigma x
    min(H, W)`` px); electronic noise ``electronic_noise_fraction x i0 x normals``; then the
    display chain (:meth:`sim.physics.display.DisplayChain.apply`): ``-log(max(I, 1e-12 i0) /
    i0)`` or ``I / i0``, the window percentiles over the field (:func:`masked_percentile`), the
    polarity, the unsharp mask (field-normalised blur inside and outside, scipy's truncated
    kernel), gamma, ``rint`` to the bit depth, and the shutter outside the field (an open field
    has no outside). In float64 it equals ``apply_image`` up to rounding (a level where
    ``x (2^bits - 1)`` lies within rounding of a half-integer); float32 adds float32 rounding.
    """
    where = "apply_image_batched"
    raw = _image("raw", raw, where)
    b, h, w = raw.shape
    _entries(p, _APPLY_NEEDS, b, where)
    if not isinstance(normals, torch.Tensor) or normals.shape != raw.shape:
        shape = tuple(normals.shape) if isinstance(normals, torch.Tensor) else type(normals).__name__
        raise PhysicsError(f"{where}: normals must be a tensor of raw's shape {tuple(raw.shape)}, got {shape}")
    dt, dev = raw.dtype, raw.device
    i0 = _per_pair("i0", i0, b, raw, where)
    if not bool(torch.all(torch.isfinite(i0) & (i0 > 0))):
        raise PhysicsError(f"{where}: i0 (the flat-field signal) must be finite and > 0 for every pair")
    if not bool(torch.all(torch.isfinite(raw))):
        raise PhysicsError(f"{where}: raw must be finite (no NaN or inf)")
    q = {k: p[k].to(dev) for k in _APPLY_NEEDS}
    f = {k: v.to(dt) for k, v in q.items() if v.dtype.is_floating_point and k not in _GEOMETRY}
    mc = q["scatter"] == 2
    if bool(mc.any()):
        raise PhysicsError(f"{where}: pairs {torch.nonzero(mc).flatten().tolist()[:10]} have scatter monte-carlo; "
                           f"only none, kernel and sks can be batched (use sim.randomize.apply_image)")

    field = field_masks(q, h, w)
    if b and not bool(field.flatten(1).any(1).all()):
        empty = torch.nonzero(~field.flatten(1).any(1)).flatten().tolist()[:10]
        raise PhysicsError(f"{where}: the fields of pairs {empty} hold no pixel of a {h} x {w} image")
    col = lambda k: k[:, None, None]  # noqa: E731 (B,) -> (B, 1, 1)

    # 2-3: collimation, kernel scatter, electronic noise
    x = torch.where(field, raw, raw * col(f["field_transmission"]))
    kern = torch.nonzero(q["scatter"] == 1).flatten()
    if kern.numel():
        xk = x[kern]
        sigma = q["scatter_sigma"][kern].to(torch.float64) * min(h, w)
        x = x.index_copy(0, kern, xk + col(f["scatter_spr"][kern]) * gaussian_reflect(xk, sigma))
    sks = torch.nonzero(q["scatter"] == 3).flatten()
    if sks.numel():
        if not isinstance(geometry, CArmGeometry) or (geometry.height, geometry.width) != (h, w):
            raise PhysicsError(f"{where}: pairs with scatter sks need the images' geometry (a CArmGeometry of {h} x "
                               f"{w} px), got {geometry!r}")
        if not isinstance(scatter_normals, torch.Tensor) or scatter_normals.shape != (b, 2, h, w):
            raise PhysicsError(f"{where}: pairs with scatter sks need scatter_normals of shape {(b, 2, h, w)}")
        table = default_table() if sks_table is None else sks_table
        rows = sks.tolist()
        kv, grid, ratio, amp, wid = (q[k][sks].tolist() for k in ("kvp", "grid", "grid_ratio", "sks_amplitude",
                                                                     "sks_width"))
        models = [table.drawn(kv[j], ratio[j] if grid[j] else 0.0, amp[j], wid[j]) for j in range(len(rows))]
        gaps = None if gap_mm is None else [float(gap_mm[r]) for r in rows]
        opened = q["sks_open"][sks][:, None, None]
        source = torch.where(opened, raw[sks], x[sks])  # sks_open: the exposure before collimation
        sc = sks_scatter_batched(source, i0[sks], models, geometry, gaps)
        sc = torch.where(opened & ~field[sks], sc * col(f["field_transmission"][sks]), sc)
        spp = torch.tensor([m.signal_per_photon for m in models], dtype=dt, device=dev)[:, None, None]
        sn = scatter_normals[sks].to(device=dev, dtype=dt)
        sigma = q["sks_texture_sigma"][sks].to(torch.float64) * min(h, w)  # sim.randomize.sks_texture
        texture = gaussian_reflect(sn[:, 1], sigma) * col((2.0 * math.sqrt(math.pi)) * sigma).to(dt)
        sc = sc * (1.0 + col(f["sks_texture"][sks]) * texture).clamp(min=0.0)
        scatter_add = sc + torch.sqrt(sc * spp) * sn[:, 0]
    x = x + col(f["electronic_noise_fraction"] * i0) * normals.to(device=dev, dtype=dt)
    if sks.numel():
        x = x.index_add(0, sks, scatter_add)

    # 4: display chain
    log = q["log"]
    v = torch.where(col(log), -torch.log(torch.maximum(x, col(1e-12 * i0)) / col(i0)), x / col(i0))
    window = torch.stack([q["window_low"], q["window_high"]], dim=1).to(torch.float64)
    lohi = masked_percentile(v, field, window)
    lo, hi = col(lohi[:, 0]), col(lohi[:, 1])
    span = hi - lo
    flat = torch.where(v > lo, 1.0, torch.where(v < lo, 0.0, 0.5)).to(dt)
    x = torch.where(span > 0, ((v - lo) / torch.where(span > 0, span, 1.0)).clamp(0.0, 1.0), flat)
    flip = log != (q["polarity"] == 1)  # bone-bright is choice 1
    x = torch.where(col(flip), 1.0 - x, x)
    sharp = torch.nonzero(q["unsharp"] & (f["unsharp_amount"] > 0)).flatten()
    if sharp.numel():
        xs, fs = x[sharp], field[sharp]
        blurred = _field_blur(xs, q["unsharp_sigma_px"][sharp].to(torch.float64), fs)
        xs = (xs + col(f["unsharp_amount"][sharp]) * (xs - blurred)).clamp(0.0, 1.0)
        x = x.index_copy(0, sharp, xs)
    x = torch.pow(x, col(f["gamma"]))
    top = col(f["max_value"])
    out = torch.round(x * top)  # half to even, as numpy.rint
    shutter = col(q["shutter"])
    out = torch.where(field, out, torch.where(shutter == 0, 0.0, torch.where(shutter == 1, top, out)).to(dt))
    return out, field
