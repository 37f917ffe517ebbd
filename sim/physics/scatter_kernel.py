"""Scatter-kernel superposition (SKS): a fast model of the Monte Carlo scatter, fitted to it.

The Monte Carlo of :mod:`sim.physics.scatter` costs several training steps per image. This is
the field's standard fast route (Ohnesorge et al. 1999; Sun & Star-Lack 2010): the scatter
reaching detector pixel ``u`` is a sum over the pixels ``u'`` of the primary image, each
spreading the scatter of its pencil beam with a kernel that depends on its thickness::

    S(u) / I0 = sum_k  [ (a_k g(tau) w_k(tau)) (*) h_k ](u)       (all pixels, 2-D convolution)

    tau(u') = -ln(P(u') / I0)          the log primary (the noise-free ``log`` image), >= 0
    g(tau)  = tau exp(-tau)            single-scatter source strength (Ohnesorge's P ln(I0/P))
    w_k     = hat functions of tau on the nodes tau_1 < ... < tau_K (sum to 1; the first and
              last extend flat below tau_1 and above tau_K)
    h_k(r)  = (1 - f_k) G(r; sigma1_k) + f_k G(r; sigma2_k),  G a 2-D Gaussian of unit integral

and, for an object at another distance from the detector than in the fit (the air gap ``D``,
from the anatomy centre to the detector plane), widths ``x (D / D_ref)^zeta``: the scatter of
a point at height ``h`` above the detector spreads in proportion to ``h`` (same angles,
farther), with the same total over the infinite plane, and more of it then misses the detector
(the convolution is cut at the detector's edges). ``zeta`` is fitted (0-3): 1 is that scaling
about the anatomy centre; more than 1 puts the effective scatter origin nearer the detector
(the pelvis without a grid: 1.3); with an anti-scatter grid the Monte Carlo shows a weaker
dependence (0.5). The Gaussians may be elliptical (``aspect``): with a linear grid the scatter
spreads along its lamellae (the detector columns) and little across them (fitted: 4-5).

``I0`` is the flat-field signal per pixel (with the grid in place, as
:class:`sim.physics.imaging.XRayImager` takes it), ``P`` the expected primary signal. So the
amplitude ``a_k`` (dimensionless) is the scatter that a pixel at thickness ``tau_k`` sends to the
whole (infinite) detector, per ``g`` and per incident flat-field signal; the kernel widths are mm
at the detector. A thicker path gives a wider kernel and a different amplitude through its
node. The spectrum, the detector response (signal per scattered photon) and an anti-scatter
grid's scatter transmission are folded into the fitted parameters: a model holds for the
physics settings it was fitted at (:attr:`ScatterKernelModel.settings`), and
:func:`interpolate_kvp` makes one for a kVp between (or near) fitted ones.

Fitting (:func:`fit_maps`, :func:`fit_scatter_kernel`): least squares
(``scipy.optimize.least_squares``) of the model's cell means against the Monte Carlo's coarse
cell tallies (``MonteCarloScatter.run_batch``; no smoothing), over all pixels of a set of poses,
each image's residuals scaled by its mean scatter. The sources ``g w_k`` do not depend on the
parameters, so their FFTs are taken once; a residual costs one inverse FFT per image.

Prediction (:meth:`ScatterKernelModel.predict`): ``K`` forward real FFTs and one inverse per
image, zero-padded to ``2H x 2W`` (an exact linear convolution: no wrap-around), the kernels'
spectra from pixel-integrated 1-D Gaussians (separable; cached per geometry and air gap).
NumPy/SciPy only; the FFTs in float32.

Not modelled: the field size beyond the detector (the Monte Carlo's field is the detector), the
object's depth extent (only its centre's gap), the composition behind ``tau`` (bone and soft
tissue of the same ``tau`` scatter differently: a model is fitted per subject), and the
asymmetry of real kernels at thickness steps (a pixel behind a thick region receives less than
the symmetric kernel gives).
``docs/physics.md`` reports the error against the Monte Carlo.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from sim.physics import PhysicsError
from sim.core.atomic import write_json
from sim.physics.imaging import XRayImager
from sim.physics.materials import TISSUE_DECOMPOSITION
from sim.physics.scatter import MonteCarloScatter, ScatterSettings, upsample_cells
from sim.projection.geometry import CArmGeometry, extrinsic_lps_to_camera

#: Version of :meth:`ScatterKernelModel.to_dict`.
FORMAT_VERSION = 1

#: The physics settings a model is fitted for (names of :class:`sim.physics.settings.PhysicsSettings`).
MODEL_SETTINGS: tuple[str, ...] = ("kvp", "anode_angle_deg", "filters", "bins", "detector_mm", "detector_mode",
                                   "grid_ratio")

_SIGMA_MM = (1.0, 1000.0)  # allowed kernel widths (mm at the detector)


def _tuple_of_numbers(value: Any, name: str, *, n: int | None = None, low: float = -math.inf,
                      low_open: bool = False, high: float = math.inf) -> tuple[float, ...]:
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple, np.ndarray)):
        raise PhysicsError(f"scatter kernel {name} must be a list of numbers, got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise PhysicsError(f"scatter kernel {name} must be a list of numbers, got {value!r}")
        v = float(v)
        if not (math.isfinite(v) and (v > low if low_open else v >= low) and v <= high):
            lo = f"{'>' if low_open else '>='} {low:g}" if math.isfinite(low) else ""
            hi = f"<= {high:g}" if math.isfinite(high) else ""
            bounds = " and ".join(x for x in (lo, hi) if x)
            raise PhysicsError(f"scatter kernel {name} must hold finite numbers {bounds}, got {v!r}")
        out.append(v)
    if n is not None and len(out) != n:
        raise PhysicsError(f"scatter kernel {name} must have {n} values (one per thickness node), got {len(out)}")
    return tuple(out)


def _settings_tuple(settings: Any) -> tuple[tuple[str, Any], ...]:
    """``settings`` (mapping or pairs) as sorted ``(name, value)`` pairs of plain, hashable values."""
    items = dict(settings).items() if not isinstance(settings, tuple) else settings
    out = []
    for k, v in items:
        if k not in MODEL_SETTINGS:
            raise PhysicsError(f"scatter kernel settings: unknown key {k!r}; allowed: {', '.join(MODEL_SETTINGS)}")
        if k == "filters":
            v = tuple((str(s), float(t)) for s, t in v)
        out.append((k, v))
    return tuple(sorted(out))


@dataclass(frozen=True)
class ScatterKernelModel:
    """Fitted scatter-kernel superposition model (module doc): the manual of its parameters.

    Attributes:
        tau_nodes: ``(K,)`` increasing thickness nodes, in units of the log primary
            ``tau = -ln(P/I0)`` (dimensionless, >= 0).
        amplitude: ``(K,)`` ``a_k`` >= 0 (dimensionless): scatter sent to the whole detector per
            source strength ``g = tau exp(-tau)``, relative to the flat-field signal.
        sigma1_mm: ``(K,)`` narrow Gaussian sigma per node (mm at the detector).
        sigma2_mm: ``(K,)`` broad Gaussian sigma per node (mm at the detector), >= sigma1_mm.
        broad_fraction: ``(K,)`` ``f_k`` in [0, 1], the broad Gaussian's share of the kernel.
        signal_per_photon: mean signal of one scattered photon that interacts in the detector
            (keV for an integrating detector, 1 for a counting one), from the Monte Carlo
            tallies: turns the scatter signal into photons for quantum noise.
        settings: ``((name, value), ...)`` the physics settings of the fit (:data:`MODEL_SETTINGS`).
        fit_rms: relative RMS of the fit's residuals on the Monte Carlo cells (0 if not fitted),
            including the Monte Carlo's own noise.
        gap_ref_mm: the air gap ``D_ref`` (mm, anatomy centre to detector plane) at which the
            widths hold (the fit's mean gap); 0: no gap dependence.
        gap_exponent: ``zeta``: widths ``x (D / D_ref)^zeta`` at air gap ``D``.
        aspect: > 0, the kernels' width along the detector columns (image rows axis; the
            anti-scatter grid's lamellae) over their width along the rows (across the lamellae):
            ``sigma x sqrt(aspect)`` and ``sigma / sqrt(aspect)``; 1 = round.

    Build with :func:`fit_scatter_kernel` / :func:`fit_maps`, or :meth:`from_dict` (a saved
    fit). Values out of range raise :class:`sim.physics.PhysicsError` naming the parameter.
    """

    tau_nodes: tuple[float, ...]
    amplitude: tuple[float, ...]
    sigma1_mm: tuple[float, ...]
    sigma2_mm: tuple[float, ...]
    broad_fraction: tuple[float, ...]
    signal_per_photon: float = 1.0
    settings: tuple[tuple[str, Any], ...] = ()
    fit_rms: float = 0.0
    gap_ref_mm: float = 0.0
    gap_exponent: float = 0.0
    aspect: float = 1.0

    def __post_init__(self) -> None:
        nodes = _tuple_of_numbers(self.tau_nodes, "tau_nodes", low=0.0)
        if not nodes or any(b <= a for a, b in zip(nodes, nodes[1:])):
            raise PhysicsError(f"scatter kernel tau_nodes must be one or more increasing values >= 0, got {nodes}")
        k = len(nodes)
        object.__setattr__(self, "tau_nodes", nodes)
        object.__setattr__(self, "amplitude", _tuple_of_numbers(self.amplitude, "amplitude", n=k, low=0.0))
        s1 = _tuple_of_numbers(self.sigma1_mm, "sigma1_mm", n=k, low=_SIGMA_MM[0], high=_SIGMA_MM[1])
        s2 = _tuple_of_numbers(self.sigma2_mm, "sigma2_mm", n=k, low=_SIGMA_MM[0], high=_SIGMA_MM[1])
        if any(b < a * (1 - 1e-9) for a, b in zip(s1, s2)):
            raise PhysicsError(f"scatter kernel sigma2_mm must be >= sigma1_mm per node, got {s2} and {s1}")
        object.__setattr__(self, "sigma1_mm", s1)
        object.__setattr__(self, "sigma2_mm", s2)
        object.__setattr__(self, "broad_fraction",
                           _tuple_of_numbers(self.broad_fraction, "broad_fraction", n=k, low=0.0, high=1.0))
        for name, low, high in (("signal_per_photon", 0.0, math.inf), ("fit_rms", -1.0, math.inf),
                                ("gap_ref_mm", -1.0, 1e5), ("gap_exponent", -10.0, 10.0), ("aspect", 0.0, 100.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v) \
                    or not (low < v <= high) or (low == -1.0 and v < 0):
                allowed = ">= 0" if low == -1.0 else f"> {low:g}" if math.isinf(high) else f"in ({low:g}, {high:g}]"
                raise PhysicsError(f"scatter kernel {name} must be a finite number {allowed}, got {v!r}")
            object.__setattr__(self, name, float(v))
        object.__setattr__(self, "settings", _settings_tuple(self.settings))

    # ------------------------------------------------------------------ record
    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types: ``{"format": 1, "tau_nodes": [...], ..., "settings": {...}}``."""
        out: dict[str, Any] = {"format": FORMAT_VERSION}
        for name in ("tau_nodes", "amplitude", "sigma1_mm", "sigma2_mm", "broad_fraction"):
            out[name] = list(getattr(self, name))
        for name in ("signal_per_photon", "fit_rms", "gap_ref_mm", "gap_exponent", "aspect"):
            out[name] = getattr(self, name)
        out["settings"] = {k: ([[s, t] for s, t in v] if k == "filters" else v) for k, v in self.settings}
        return out

    @classmethod
    def from_dict(cls, d: Any) -> ScatterKernelModel:
        """The model of :meth:`to_dict`'s output; a missing, unknown or bad key raises
        :class:`sim.physics.PhysicsError` naming it."""
        if not isinstance(d, dict):
            raise PhysicsError(f"scatter kernel model must be a JSON object, got {type(d).__name__}")
        keys = ("format", "tau_nodes", "amplitude", "sigma1_mm", "sigma2_mm", "broad_fraction", "signal_per_photon",
                "fit_rms", "settings", "gap_ref_mm", "gap_exponent", "aspect")
        unknown = sorted(set(d) - set(keys))
        if unknown:
            raise PhysicsError(f"scatter kernel model: unknown key {unknown[0]!r}; allowed: {', '.join(keys)}")
        missing = [k for k in keys if k not in d]
        if missing:
            raise PhysicsError(f"scatter kernel model: missing key {missing[0]!r}")
        if d["format"] != FORMAT_VERSION:
            raise PhysicsError(f"scatter kernel model: format must be {FORMAT_VERSION}, got {d['format']!r}")
        if not isinstance(d["settings"], dict):
            raise PhysicsError(f"scatter kernel model: settings must be an object, got {d['settings']!r}")
        return cls(**{k: d[k] for k in keys if k != "format"})

    @property
    def settings_dict(self) -> dict[str, Any]:
        """:attr:`settings` as a dict."""
        return dict(self.settings)

    # -------------------------------------------------------------- prediction
    def predict(self, log_primary: np.ndarray, geometry, *, flat_signal: float = 1.0, gap_mm=None) -> np.ndarray:
        """Expected scatter signal of noise-free log primary images.

        Args:
            log_primary: ``(H, W)`` or ``(B, H, W)`` ``-ln(P / I0)`` of the expected primary
                (dimensionless; :class:`sim.physics.imaging.XRayImager`'s ``log`` without
                scatter and noise, i.e. ``-ln(primary / flat)``). Values below 0 (brighter than the
                flat field) count as 0: no object.
            geometry: :class:`sim.projection.geometry.CArmGeometry` of the images (``H x W`` pixels of
                ``pixel_spacing_mm`` at the detector).
            flat_signal: ``I0``, the flat-field signal per pixel (signal units, with the grid in
                place); the result is in the same units and scales linearly with it.
            gap_mm: air gap ``D`` (mm), a number or ``(B,)``: anatomy centre to detector plane,
                ``geometry.sdd_mm - pose[2, 3]`` (:func:`detector_gap_mm`); None: ``gap_ref_mm``.
                Rounded to 0.5 mm (the kernels are cached per gap).

        Returns:
            float64 scatter signal per pixel, the shape of ``log_primary``, >= 0. The FFTs run
            in float32 (4x faster than float64 at these sizes): relative error ~1e-6.
        """

        if not isinstance(geometry, CArmGeometry):
            raise PhysicsError(f"geometry must be a CArmGeometry, got {type(geometry).__name__}")
        tau = np.asarray(log_primary, dtype=np.float64)
        if tau.ndim not in (2, 3) or tau.shape[-2:] != (geometry.height, geometry.width):
            raise PhysicsError(f"log_primary must be (H, W) or (B, H, W) with H x W = {geometry.height} x "
                               f"{geometry.width} (the geometry's), got {tau.shape}")
        if not np.all(np.isfinite(tau)):
            raise PhysicsError("log_primary must be finite (-ln(P/I0) of the expected primary)")
        if isinstance(flat_signal, bool) or not isinstance(flat_signal, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(flat_signal) and flat_signal > 0):
            raise PhysicsError(f"flat_signal must be a positive number (signal per pixel), got {flat_signal!r}")
        single = tau.ndim == 2
        if single:
            tau = tau[None]
        gaps = self._gaps(gap_mm, len(tau), geometry)
        spectra = _source_spectra(self.tau_nodes, tau, np.float32)
        out = np.empty(tau.shape)
        for gap in np.unique(gaps):
            sel = gaps == gap
            out[sel] = _superpose(spectra[sel], self._kernel_spectra(geometry, float(gap), np.float32),
                                  geometry.height, geometry.width)
        out *= float(flat_signal)
        return out[0] if single else out

    def _gaps(self, gap_mm, n: int, geometry) -> np.ndarray:
        """``(n,)`` gaps (mm, rounded to 0.5 mm) of :meth:`predict`'s ``gap_mm``."""
        if gap_mm is None or self.gap_ref_mm == 0:
            return np.full(n, self.gap_ref_mm)
        g = np.asarray(gap_mm, dtype=np.float64)
        if g.ndim == 0:
            g = np.full(n, float(g))
        if g.shape != (n,) or not np.all(np.isfinite(g)) or g.min() <= 0 or g.max() >= geometry.sdd_mm:
            raise PhysicsError(f"gap_mm must be a number or ({n},) in (0, sdd_mm={geometry.sdd_mm:g}) mm, "
                               f"got {gap_mm!r}")
        return np.round(g * 2.0) / 2.0

    def scatter_photons(self, scatter_signal: np.ndarray) -> np.ndarray:
        """Interacting scattered photons per pixel of a scatter signal (``/ signal_per_photon``),
        the second half of the ``scatter`` pair of :meth:`sim.physics.poly.Polychromatic.noisy`."""
        return np.asarray(scatter_signal, dtype=np.float64) / self.signal_per_photon

    def scaled(self, gap_mm: float) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        """``(amplitude, sigma1_mm, sigma2_mm)`` at air gap ``gap_mm`` (the attributes' at
        ``gap_ref_mm``, or without a gap dependence)."""
        if self.gap_ref_mm == 0 or gap_mm == self.gap_ref_mm:
            return self.amplitude, self.sigma1_mm, self.sigma2_mm
        fw = (gap_mm / self.gap_ref_mm) ** self.gap_exponent
        return self.amplitude, tuple(s * fw for s in self.sigma1_mm), tuple(s * fw for s in self.sigma2_mm)

    def _kernel_spectra(self, geometry, gap_mm: float, dtype=np.float64) -> np.ndarray:
        a, s1, s2 = self.scaled(gap_mm)
        return _kernel_spectra(a, s1, s2, self.broad_fraction, geometry.height, geometry.width,
                               geometry.pixel_spacing_mm, dtype, self.aspect)


# ------------------------------------------------------------------ numerics
def _node_coordinate(tau_nodes, tau: np.ndarray) -> np.ndarray:
    """The piecewise-linear node coordinate ``p`` of ``tau``: ``k`` at node ``k``, clamped to
    ``[0, K - 1]`` (in ``tau``'s dtype)."""
    p = np.zeros_like(tau)
    for lo, hi in zip(tau_nodes, tau_nodes[1:]):
        p += np.clip((tau - tau.dtype.type(lo)) * tau.dtype.type(1.0 / (hi - lo)), 0.0, 1.0)
    return p


def _source_spectra(tau_nodes, tau: np.ndarray, dtype=np.float64) -> np.ndarray:
    """``(B, K, 2H, W + 1)`` complex: the real FFTs of the sources ``g(tau) w_k(tau)``,
    zero-padded to ``2H x 2W``, in ``dtype`` (float32: complex64). The hat weights are
    ``w_k = max(0, 1 - |p - k|)`` with ``p`` the node coordinate (they sum to 1)."""
    from scipy import fft

    tau = np.maximum(tau, 0.0).astype(dtype, copy=False)
    b, h, w = tau.shape
    k = len(tau_nodes)
    g = tau * np.exp(-tau)
    p = _node_coordinate(tau_nodes, tau)
    # padded in place: scipy's own zero padding (rfft2(s=...)) is twice as slow
    pad = np.zeros((b, k, 2 * h, 2 * w), dtype)
    for j in range(k):
        np.multiply(g, np.maximum(1.0 - np.abs(p - j), 0.0), out=pad[:, j, :h, :w])
    return fft.rfft2(pad, axes=(-2, -1), overwrite_x=True)


def _axis_kernel(n: int, spacing_mm: float, sigma_mm: float) -> np.ndarray:
    """``(2n,)`` pixel integrals of a unit 1-D Gaussian at displacements ``0..n-1, -n..-1``
    pixels (the one at ``-n`` is 0: no two pixels of an ``n``-pixel axis are that far apart)."""
    from scipy.special import ndtr

    d = np.arange(2 * n, dtype=np.float64)
    d = np.where(d < n, d, d - 2 * n)
    g = ndtr((d + 0.5) * spacing_mm / sigma_mm) - ndtr((d - 0.5) * spacing_mm / sigma_mm)
    g[n] = 0.0
    return g


@functools.lru_cache(maxsize=256)
def _kernel_spectra(amplitude, sigma1, sigma2, fraction, h: int, w: int, spacing_mm: float,
                    dtype=np.float64, aspect: float = 1.0) -> np.ndarray:
    """``(K, 2H, W + 1)`` real (``dtype``): ``a_k`` times the spectrum of kernel ``h_k`` on the padded grid.
    A separable Gaussian's 2-D spectrum is the outer product of its axes' spectra; the kernels
    are even, so their spectra are real. Widths along the columns (rows axis) ``x sqrt(aspect)``,
    along the rows ``/ sqrt(aspect)``."""
    out = np.empty((len(amplitude), 2 * h, w + 1))
    ry = math.sqrt(aspect)
    for k, (a, s1, s2, f) in enumerate(zip(amplitude, sigma1, sigma2, fraction)):
        spec = np.zeros((2 * h, w + 1))
        for share, s in ((1.0 - f, s1), (f, s2)):
            if share > 0:
                ky = np.fft.fft(_axis_kernel(h, spacing_mm, s * ry)).real
                kx = np.fft.rfft(_axis_kernel(w, spacing_mm, s / ry)).real
                spec += share * ky[:, None] * kx[None, :]
        out[k] = a * spec
    out = out.astype(dtype)
    out.setflags(write=False)
    return out


def _superpose(source_spectra: np.ndarray, kernel_spectra: np.ndarray, h: int, w: int) -> np.ndarray:
    """``(B, H, W)`` sum over k of source k convolved with kernel k (>= 0: FFT round-off clipped)."""
    from scipy import fft

    total = source_spectra[:, 0] * kernel_spectra[0]
    for j in range(1, len(kernel_spectra)):
        total += source_spectra[:, j] * kernel_spectra[j]
    out = fft.irfft2(total, s=(2 * h, 2 * w), axes=(-2, -1), overwrite_x=True)[:, :h, :w]
    return np.maximum(out, 0.0)


def cell_means(images: np.ndarray, cell_px: int) -> np.ndarray:
    """``(B, H, W)`` -> ``(B, ceil(H/c), ceil(W/c))`` mean over each cell of ``c x c`` pixels
    (a partial last cell: the mean of its pixels), as the Monte Carlo tallies its cells."""
    b, h, w = images.shape
    hc, wc = -(-h // cell_px), -(-w // cell_px)
    pad = np.zeros((b, hc * cell_px, wc * cell_px))
    pad[:, :h, :w] = images
    ones = np.zeros((hc * cell_px, wc * cell_px))
    ones[:h, :w] = 1.0
    sums = pad.reshape(b, hc, cell_px, wc, cell_px).sum(axis=(2, 4))
    return sums / ones.reshape(hc, cell_px, wc, cell_px).sum(axis=(1, 3))


# ------------------------------------------------------------------ fitting
def data_tau_nodes(log_primary, count: int = 4) -> tuple[float, ...]:
    """``count`` thickness nodes evenly spaced between the 2nd and 98th percentiles of the
    object's ``tau`` (pixels with ``tau > 0.05``) in ``log_primary`` (any shape), rounded to 0.01."""
    tau = np.asarray(log_primary, dtype=np.float64).ravel()
    tau = tau[np.isfinite(tau) & (tau > 0.05)]
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise PhysicsError(f"count of thickness nodes must be an integer >= 1, got {count!r}")
    if tau.size == 0:
        raise PhysicsError("log_primary holds no object (no tau > 0.05): no thickness nodes")
    lo, hi = np.percentile(tau, [2.0, 98.0])
    if count == 1 or hi - lo < 0.01 * count:
        return (round(float(np.median(tau)), 2),)
    return tuple(round(float(v), 2) for v in np.linspace(lo, hi, count))


#: Weight of the smoothness penalty on the log amplitudes (second differences over the nodes).
SMOOTHNESS = 0.1


def fit_maps(log_primary: np.ndarray, scatter_cells: np.ndarray, geometry, *, cell_px: int, gap_mm=None,
             gap_exponent: float | None = None, tau_nodes=None, signal_per_photon: float = 1.0, settings=(),
             max_nfev: int = 200) -> ScatterKernelModel:
    """Fit a :class:`ScatterKernelModel` to Monte Carlo cell maps.

    Args:
        log_primary: ``(B, H, W)`` ``-ln(P/I0)`` of the expected primary at the fitting poses.
        scatter_cells: ``(B, Hc, Wc)`` Monte Carlo scatter per pixel over each cell of
            ``cell_px`` pixels, divided by the flat-field signal ``I0`` (dimensionless;
            ``MonteCarloScatter.run_batch``'s ``scatter`` / flat).
        geometry: :class:`sim.projection.geometry.CArmGeometry` of the ``H x W`` images.
        cell_px: pixels per side of a tally cell (``Hc = ceil(H / cell_px)``).
        gap_mm: ``(B,)`` air gaps (mm, anatomy centre to detector plane; :func:`detector_gap_mm`)
            of the images: the kernels scale with the gap about their mean. None: no gap
            dependence.
        gap_exponent: the model's ``zeta``, or None: fitted (with ``gap_mm``).
        tau_nodes: the model's thickness nodes (increasing, >= 0); default
            :func:`data_tau_nodes` of ``log_primary`` (4 nodes). Models to be interpolated in
            kVp (:func:`interpolate_kvp`) need the same nodes.
        signal_per_photon, settings: recorded in the model (see its attributes).
        max_nfev: function evaluations of the least squares.

    The fitted parameters are fewer than the model's (the Monte Carlo cells are noisy): ``K``
    log amplitudes, and kernels whose log widths change linearly over the nodes
    (``ln sigma_i,k = ln sigma_i + gamma_i d_k``, ``d_k`` from -1/2 at the first node to 1/2 at the
    last) with one broad fraction, the aspect, and with ``gap_mm`` the gap exponent: ``K + 6``
    (``K + 7``) in all. Each image's residuals (model cell means
    minus Monte Carlo cells) are divided by its mean Monte Carlo scatter, so every pose weighs
    the same; a penalty :data:`SMOOTHNESS` x the second differences of the log amplitudes keeps
    nodes with little data in line with their neighbours. Start: non-negative least squares of
    the amplitudes for kernels of 20 and 100 mm; then ``scipy.optimize.least_squares`` (trust
    region reflective, bounds: widths 5-400 mm, broad/narrow <= 40, |gamma| <= 3, aspect 0.2-5,
    zeta 0-3).
    """
    from scipy.optimize import least_squares, nnls

    if not isinstance(geometry, CArmGeometry):
        raise PhysicsError(f"geometry must be a CArmGeometry, got {type(geometry).__name__}")
    if isinstance(cell_px, bool) or not isinstance(cell_px, (int, np.integer)) or cell_px < 1:
        raise PhysicsError(f"cell_px must be an integer >= 1, got {cell_px!r}")
    tau = np.asarray(log_primary, dtype=np.float64)
    y = np.asarray(scatter_cells, dtype=np.float64)
    h, w = geometry.height, geometry.width
    if tau.ndim != 3 or tau.shape[1:] != (h, w) or len(tau) == 0:
        raise PhysicsError(f"log_primary must be (B, {h}, {w}) with B >= 1, got {tau.shape}")
    cells = (len(tau), -(-h // cell_px), -(-w // cell_px))
    if y.shape != cells:
        raise PhysicsError(f"scatter_cells must be {cells} (B, ceil(H/cell_px), ceil(W/cell_px)), got {y.shape}")
    if not (np.all(np.isfinite(tau)) and np.all(np.isfinite(y))) or y.min() < 0:
        raise PhysicsError("log_primary and scatter_cells must be finite, scatter_cells >= 0")
    scale = y.reshape(len(y), -1).mean(axis=1)
    if np.any(scale <= 0):
        raise PhysicsError("every fitting image needs some scatter (an image without an object cannot be fitted)")
    if gap_mm is not None:
        gaps = np.asarray(gap_mm, dtype=np.float64)
        if gaps.shape != (len(tau),) or not np.all(np.isfinite(gaps)) or gaps.min() <= 0:
            raise PhysicsError(f"gap_mm must be ({len(tau)},) positive mm (one per image), got {gap_mm!r}")
        gap_ref = float(gaps.mean())
    else:
        gaps, gap_ref = np.zeros(len(tau)), 0.0
    n_gap = 1 if gap_ref > 0 and gap_exponent is None else 0
    zeta0 = 0.0 if gap_exponent is None else float(gap_exponent)
    if tau_nodes is None:
        tau_nodes = data_tau_nodes(tau)
    k = len(tau_nodes) if isinstance(tau_nodes, (list, tuple, np.ndarray)) else 0
    nodes = ScatterKernelModel(tau_nodes, [0.0] * k, [10.0] * k, [10.0] * k, [0.0] * k).tau_nodes  # validated
    spectra = _source_spectra(nodes, tau)
    sp = geometry.pixel_spacing_mm
    weight = 1.0 / (scale[:, None, None] * math.sqrt(y.size))
    d = (np.asarray(nodes) - 0.5 * (nodes[0] + nodes[-1])) / max(nodes[-1] - nodes[0], 1e-9)

    def model_of(x) -> ScatterKernelModel:
        """The model of parameters ``x`` (log amplitudes, then the kernels', then the gap's)."""
        ls1, lratio, g1, g2, f = x[k:k + 5]  # x[k + 5]: log aspect
        s1 = np.clip(np.exp(ls1 + g1 * d), *_SIGMA_MM)
        s2 = np.maximum(np.clip(np.exp(ls1 + lratio + g2 * d), *_SIGMA_MM), s1)
        zeta = x[k + 6] if n_gap else zeta0
        return ScatterKernelModel(nodes, tuple(np.exp(x[:k])), tuple(s1), tuple(s2), (min(max(f, 0.0), 1.0),) * k,
                                  signal_per_photon=signal_per_photon, settings=settings, gap_ref_mm=gap_ref,
                                  gap_exponent=zeta, aspect=math.exp(x[k + 5]))

    def predict_cells(model: ScatterKernelModel) -> np.ndarray:
        out = np.empty((len(tau), h, w))
        for gap in np.unique(gaps):
            sel = gaps == gap
            a, s1, s2 = model.scaled(float(gap))
            kern = _kernel_spectra.__wrapped__(a, s1, s2, model.broad_fraction, h, w, sp, np.float64, model.aspect)
            out[sel] = _superpose(spectra[sel], kern, h, w)
        return cell_means(out, cell_px)

    def residuals(x):
        r = ((predict_cells(model_of(x)) - y) * weight).ravel()
        return np.concatenate([r, SMOOTHNESS * np.diff(x[:k], 2)])

    x0 = np.array([0.0] * k + [math.log(20.0), math.log(5.0), 0.0, 0.0, 0.5, 0.0] + [1.0] * n_gap)
    start = model_of(x0)
    basis = np.stack([predict_cells(replace(start, amplitude=tuple(np.eye(k)[j]))) for j in range(k)])  # (K, B, Hc, Wc)
    a0, _ = nnls((basis * weight[None]).reshape(k, -1).T, (y * weight).ravel())
    x0[:k] = np.log(np.maximum(a0, 1e-3 * max(a0.max(), 1e-12)))
    lo = np.array([-30.0] * k + [math.log(5.0), 0.0, -3.0, -3.0, 0.0, math.log(0.2)] + [0.0] * n_gap)
    hi = np.array([5.0] * k + [math.log(400.0), math.log(40.0), 3.0, 3.0, 1.0, math.log(5.0)] + [3.0] * n_gap)
    fit = least_squares(residuals, np.clip(x0, lo, hi), bounds=(lo, hi), method="trf", x_scale="jac",
                        max_nfev=max_nfev)
    rms = float(np.sqrt(np.sum(fit.fun[:y.size] ** 2)))
    return replace(model_of(fit.x), fit_rms=rms)


def monte_carlo_maps(imager, poses: np.ndarray, *, cell_px: int = 4, photons: int | None = None,
                     seeds=None, mc=None) -> dict[str, Any]:
    """Noise-free primaries and Monte Carlo scatter of one CT at ``B`` poses.

    Args:
        imager: :class:`sim.physics.imaging.XRayImager` (any level: its renderer, spectrum,
            detector and exposure are used; the transport is built here with ``cell_px``).
        poses: ``(B, 4, 4)`` volume poses.
        cell_px: pixels per side of a Monte Carlo tally cell.
        photons: histories per pose (default the physics settings' ``scatter_photons``).
        seeds: ``(B,)`` Monte Carlo seeds (default ``0..B-1``).
        mc: the transport of a former call with the same CT, spectrum, detector, scatter settings
            and ``cell_px`` (reused: its set-up takes seconds; the exposure may differ).

    Returns:
        ``log`` ``(B, H, W)`` ``-ln(P/I0)``; ``primary`` ``(B, H, W)`` and ``flat`` (signal per
        pixel, grid in place); ``cells`` ``(B, Hc, Wc)`` scatter per pixel / flat (dimensionless);
        ``cell_counts`` ``(B, Hc, Wc)`` interacting scattered photons per pixel; ``image``
        ``(B, H, W)`` the scatter signal as ``XRayImager`` makes it (the Gaussian of
        :meth:`sim.physics.scatter.ScatterSettings.smoothing_mm`, bilinear);
        ``gap_mm`` ``(B,)`` (:func:`detector_gap_mm`); ``signal_per_photon``; ``seconds`` of the
        transport; ``mc`` the transport (for ``mc=``).
    """
    import time
    from dataclasses import replace as _replace

    p = imager.physics
    g = imager.geometry
    poses = imager.renderer._check_poses(poses)
    seeds = list(range(len(poses))) if seeds is None else [int(s) for s in seeds]
    settings = _replace(ScatterSettings.of(p), cell_px=int(cell_px))
    gain = settings.grid_transmission if p.grid_ratio > 0 else 1.0
    if mc is None:
        mc = MonteCarloScatter(imager.renderer.materials.partial_densities(imager.renderer.volume.hu),
                               imager.renderer.volume.affine, TISSUE_DECOMPOSITION.names, imager.spectrum,
                               imager.detector, settings)
    elif (mc.settings != settings or mc.detector != imager.detector
          or not np.array_equal(mc.spectrum.fluence, imager.spectrum.fluence)
          or not np.array_equal(mc.spectrum.energies_keV, imager.spectrum.energies_keV)):
        raise PhysicsError("mc: the transport was built for other scatter settings, spectrum or detector")
    L = imager.renderer.render(poses)
    flat = imager.model.flat_field(**imager.exposure) * gain
    primary = imager.model.expected(L, **imager.exposure) * gain
    log = -np.log(np.maximum(primary, 1e-300) / flat)
    ppp = float(imager.model.photons_per_pixel(**imager.exposure).sum())
    cams = np.linalg.inv(extrinsic_lps_to_camera(poses, imager.renderer.center_lps))
    t0 = time.perf_counter()
    runs = mc.run_batch(cams, g, photons_per_pixel=ppp, seeds=seeds, photons=photons)
    seconds = time.perf_counter() - t0
    cells = np.stack([r["scatter"] for r in runs])
    counts = np.stack([r["scatter_counts"] for r in runs])
    sigma = settings.smoothing_mm(g, photons) / (g.pixel_spacing_mm * settings.cell_px)
    image = np.stack([upsample_cells(c, g.height, g.width, settings.cell_px, sigma) for c in cells])
    spp = float(cells.sum() / counts.sum()) if counts.sum() > 0 else 1.0
    return {"log": log, "primary": primary, "flat": flat, "cells": cells / flat, "cell_counts": counts,
            "image": image, "gap_mm": detector_gap_mm(poses, g), "signal_per_photon": spp, "seconds": seconds,
            "cell_px": int(cell_px), "mc": mc}


def detector_gap_mm(poses: np.ndarray, geometry) -> np.ndarray:
    """``(B,)`` air gaps (mm) of ``(B, 4, 4)`` (or ``(4, 4)``: ``(1,)``) volume poses: the distance
    from the anatomy centre (the pose's translation, camera frame) to the detector plane
    ``z = sdd_mm``."""
    p = np.asarray(poses, dtype=np.float64)
    p = p[None] if p.ndim == 2 else p
    if p.ndim != 3 or p.shape[1:] != (4, 4):
        raise PhysicsError(f"poses must be (B, 4, 4) or (4, 4), got {p.shape}")
    return geometry.sdd_mm - p[:, 2, 3]


def physics_record(physics) -> dict[str, Any]:
    """The :data:`MODEL_SETTINGS` of a :class:`sim.physics.settings.PhysicsSettings`."""
    return {k: getattr(physics, k) for k in MODEL_SETTINGS}


def fit_scatter_kernel(volume, physics, poses: np.ndarray, *, size=(64, 64), scene: str = "cios_fusion",
                       center_lps=None, cell_px: int = 4, photons: int | None = None, seed: int = 0,
                       tau_nodes=None, imager=None) -> ScatterKernelModel:
    """Fit a model to the Monte Carlo scatter of ``volume`` at ``poses`` for ``physics``.

    Args:
        volume: :class:`sim.ct.volume.CTVolume`.
        physics: :class:`sim.physics.settings.PhysicsSettings` (spectrum, detector, grid,
            ``scatter_photons``, ``scatter_voxel_mm``; the level and noise do not matter).
        poses: ``(B, 4, 4)`` fitting poses (volume poses of :mod:`sim.projection.geometry`).
        size: ``(H, W)`` of the fitting images (low resolution: scatter is smooth).
        scene, center_lps: as :class:`sim.physics.imaging.XRayImager`.
        cell_px: Monte Carlo tally cell (pixels per side).
        photons: histories per pose (default ``physics.scatter_photons``).
        seed: pose ``b`` uses Monte Carlo seed ``seed + b``.
        tau_nodes: the model's thickness nodes (default: :func:`data_tau_nodes`).
        imager: an :class:`XRayImager` to use instead of building one (its physics must be
            ``physics``).
    """
    from dataclasses import replace as _replace

    if imager is None:
        imager = XRayImager(volume, _replace(physics, level="poly", noise=False), scene=scene, size=size,
                            center_lps=center_lps)
    poses = np.asarray(poses, dtype=np.float64)
    maps = monte_carlo_maps(imager, poses, cell_px=cell_px, photons=photons,
                            seeds=[seed + b for b in range(len(poses))])
    return fit_maps(maps["log"], maps["cells"], imager.geometry, cell_px=cell_px, gap_mm=maps["gap_mm"],
                    tau_nodes=tau_nodes, signal_per_photon=maps["signal_per_photon"],
                    settings=physics_record(physics))


def interpolate_kvp(models, kvp: float) -> ScatterKernelModel:
    """A model at ``kvp`` from models fitted at other kVps (all other settings and the nodes
    equal): :func:`interpolate_setting` of ``"kvp"``."""
    return interpolate_setting(models, "kvp", kvp)


def interpolate_setting(models, name: str, value: float) -> ScatterKernelModel:
    """A model at setting ``name`` (``"kvp"`` in kV or ``"grid_ratio"``) = ``value`` from models
    fitted at other values of it (all other settings and the nodes equal): log amplitudes, log
    widths, log aspect, broad fractions, ``signal_per_photon`` and the gap parameters linear in
    the setting between the two nearest fitted values (linear extrapolation from the two nearest
    outside). ``fit_rms`` of the result is 0 (not fitted)."""
    if name not in ("kvp", "grid_ratio"):
        raise PhysicsError(f"interpolate_setting: name must be 'kvp' or 'grid_ratio', got {name!r}")
    models = list(models)
    if len(models) < 2:
        raise PhysicsError(f"interpolate_{name} needs models at two or more values of {name}, got {len(models)}")
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value) or value < 0 or (name == "kvp" and value == 0):
        what = "a positive number (kV)" if name == "kvp" else "a number >= 0"
        raise PhysicsError(f"{name} must be {what}, got {value!r}")
    value = float(value)
    ref = {k: v for k, v in models[0].settings if k != name}
    for m in models:
        if m.tau_nodes != models[0].tau_nodes or {k: v for k, v in m.settings if k != name} != ref \
                or name not in m.settings_dict:
            raise PhysicsError(f"interpolate_{name} needs models with the same thickness nodes and settings except "
                               f"{name}")
    models.sort(key=lambda m: m.settings_dict[name])
    values = [float(m.settings_dict[name]) for m in models]
    if len(set(values)) != len(values):
        raise PhysicsError(f"interpolate_{name} needs models at different values of {name}, got {values}")
    i = int(np.clip(np.searchsorted(values, value) - 1, 0, len(values) - 2))
    lo, hi = models[i], models[i + 1]
    t = (value - values[i]) / (values[i + 1] - values[i])

    def mix(attr, log):
        a, b = np.asarray(getattr(lo, attr)), np.asarray(getattr(hi, attr))
        if log:
            a, b = np.log(np.maximum(a, 1e-300)), np.log(np.maximum(b, 1e-300))
            return tuple(np.exp(a + t * (b - a)))
        return tuple(a + t * (b - a))

    s1 = np.clip(mix("sigma1_mm", True), *_SIGMA_MM)
    s2 = np.maximum(np.clip(mix("sigma2_mm", True), *_SIGMA_MM), s1)
    lin = {attr: getattr(lo, attr) + t * (getattr(hi, attr) - getattr(lo, attr))
           for attr in ("signal_per_photon", "gap_ref_mm", "gap_exponent")}
    return replace(lo, amplitude=mix("amplitude", True), sigma1_mm=tuple(s1), sigma2_mm=tuple(s2),
                   broad_fraction=tuple(np.clip(mix("broad_fraction", False), 0.0, 1.0)),
                   signal_per_photon=max(lin["signal_per_photon"], 1e-9), gap_ref_mm=max(lin["gap_ref_mm"], 0.0),
                   gap_exponent=lin["gap_exponent"],
                   aspect=float(np.clip(lo.aspect * (hi.aspect / lo.aspect) ** t, 1e-3, 100.0)),
                   settings={**dict(lo.settings), name: value}, fit_rms=0.0)


#: Version of :meth:`ScatterKernelTable.to_dict`.
TABLE_FORMAT_VERSION = 1


@dataclass(frozen=True)
class ScatterKernelTable:
    """Models of one subject fitted over a grid of tube voltages and grid ratios, for any
    ``(kvp, grid_ratio)`` between (:meth:`model_for`): the scatter of the training pairs'
    drawn tube and grid (``scatter = "sks"`` of :mod:`sim.randomize`).

    Attributes:
        models: ``ScatterKernelModel`` s, all with the same thickness nodes and settings except
            ``kvp`` and ``grid_ratio`` (0: no grid); every grid ratio fitted at the same two or
            more kVps.
        subject: what they were fitted on (a CT's name, free text).

    ``model_for(kvp, grid_ratio)``: the models of the two nearest fitted grid ratios (no grid:
    the ratio-0 models alone), each interpolated in kVp (:func:`interpolate_kvp`), then in the
    ratio (:func:`interpolate_setting`); a ratio above 0 is interpolated among the grids only
    (a thin grid is not "half no grid"). Cached per ``(kvp, grid_ratio)`` rounded to 0.01.

    Example::

        >>> table = ScatterKernelTable.load(DEFAULT_TABLE)
        >>> table.model_for(75.0, 0.0).settings_dict["kvp"]
        75.0
    """

    models: tuple[ScatterKernelModel, ...]
    subject: str = ""

    def __post_init__(self) -> None:
        models = tuple(self.models)
        if not models or not all(isinstance(m, ScatterKernelModel) for m in models):
            raise PhysicsError("scatter kernel table: models must be one or more ScatterKernelModel")
        ref = {k: v for k, v in models[0].settings if k not in ("kvp", "grid_ratio")}
        for m in models:
            s = m.settings_dict
            if "kvp" not in s or "grid_ratio" not in s:
                raise PhysicsError("scatter kernel table: every model must record its kvp and grid_ratio settings")
            if m.tau_nodes != models[0].tau_nodes or {k: v for k, v in m.settings if k not in ("kvp", "grid_ratio")} \
                    != ref:
                raise PhysicsError("scatter kernel table: the models must share thickness nodes and settings except "
                                   "kvp and grid_ratio")
        by_ratio: dict[float, list] = {}
        for m in models:
            by_ratio.setdefault(float(m.settings_dict["grid_ratio"]), []).append(float(m.settings_dict["kvp"]))
        kvps = {r: sorted(v) for r, v in by_ratio.items()}
        first = next(iter(kvps.values()))
        if len(first) < 2 or any(v != first for v in kvps.values()) or len(set(first)) != len(first):
            raise PhysicsError(f"scatter kernel table: every grid ratio needs the same two or more distinct kVps, got "
                               f"{kvps}")
        if 0.0 not in kvps:
            raise PhysicsError("scatter kernel table: models without a grid (grid_ratio 0) are required")
        object.__setattr__(self, "models", models)
        object.__setattr__(self, "subject", str(self.subject))

    @property
    def kvps(self) -> tuple[float, ...]:
        """The fitted tube voltages (kV)."""
        return tuple(sorted({float(m.settings_dict["kvp"]) for m in self.models}))

    @property
    def grid_ratios(self) -> tuple[float, ...]:
        """The fitted grid ratios (0: no grid)."""
        return tuple(sorted({float(m.settings_dict["grid_ratio"]) for m in self.models}))

    def model_for(self, kvp: float, grid_ratio: float) -> ScatterKernelModel:
        """The model at ``kvp`` (kV, > 0) and ``grid_ratio`` (>= 0; 0: no grid), class doc."""
        for name, v in (("kvp", kvp), ("grid_ratio", grid_ratio)):
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(v) or v < 0 or (name == "kvp" and v == 0):
                raise PhysicsError(f"scatter kernel table: {name} must be a {'positive' if name == 'kvp' else '>= 0'} "
                                   f"number, got {v!r}")
        return self._model(round(float(kvp), 2), round(float(grid_ratio), 2))

    def drawn(self, kvp: float, grid_ratio: float, amplitude_factor: float = 1.0,
              width_factor: float = 1.0) -> ScatterKernelModel:
        """:meth:`model_for` with its amplitudes times ``amplitude_factor`` (> 0) and its widths times
        ``width_factor`` (> 0; kept within 1-1000 mm): the scatter of a randomized draw (another
        patient, filtration or detector than the fit's; ``sim.randomize.sks_model``)."""
        for name, v in (("amplitude_factor", amplitude_factor), ("width_factor", width_factor)):
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not (math.isfinite(v) and v > 0):
                raise PhysicsError(f"scatter kernel table: {name} must be a positive number, got {v!r}")
        model = self.model_for(kvp, grid_ratio)
        a, wf = float(amplitude_factor), float(width_factor)
        s1 = tuple(min(max(x * wf, _SIGMA_MM[0]), _SIGMA_MM[1]) for x in model.sigma1_mm)
        s2 = tuple(max(min(max(x * wf, _SIGMA_MM[0]), _SIGMA_MM[1]), y) for x, y in zip(model.sigma2_mm, s1))
        return replace(model, amplitude=tuple(x * a for x in model.amplitude), sigma1_mm=s1, sigma2_mm=s2,
                       fit_rms=0.0)

    @functools.lru_cache(maxsize=512)
    def _model(self, kvp: float, grid_ratio: float) -> ScatterKernelModel:
        def at_ratio(r):
            return interpolate_kvp([m for m in self.models if m.settings_dict["grid_ratio"] == r], kvp)

        if grid_ratio == 0.0:
            return at_ratio(0.0)
        grids = [r for r in self.grid_ratios if r > 0]
        if not grids:
            raise PhysicsError(f"scatter kernel table ({self.subject}): no grid was fitted, grid_ratio "
                               f"{grid_ratio:g} asked")
        if len(grids) == 1:
            return replace(at_ratio(grids[0]), settings={**self.models[0].settings_dict, "kvp": kvp,
                                                         "grid_ratio": grid_ratio})
        return interpolate_setting([at_ratio(r) for r in grids], "grid_ratio", grid_ratio)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types: ``{"format": 1, "subject": ..., "models": [model.to_dict(), ...]}``."""
        return {"format": TABLE_FORMAT_VERSION, "subject": self.subject, "models": [m.to_dict() for m in self.models]}

    @classmethod
    def from_dict(cls, d: Any) -> ScatterKernelTable:
        """The table of :meth:`to_dict`'s output (a bad key or model raises :class:`PhysicsError`)."""
        if not isinstance(d, dict) or set(d) != {"format", "subject", "models"}:
            got = sorted(d) if isinstance(d, dict) else type(d).__name__
            raise PhysicsError(f"scatter kernel table must be an object with keys format, subject, models; got {got}")
        if d["format"] != TABLE_FORMAT_VERSION:
            raise PhysicsError(f"scatter kernel table: format must be {TABLE_FORMAT_VERSION}, got {d['format']!r}")
        if not isinstance(d["models"], list):
            raise PhysicsError("scatter kernel table: models must be a list")
        return cls(tuple(ScatterKernelModel.from_dict(m) for m in d["models"]), str(d["subject"]))

    @classmethod
    def load(cls, path) -> ScatterKernelTable:
        """Read a table written by :meth:`save` (JSON; a missing or corrupt file raises
        :class:`PhysicsError` naming it)."""
        import json

        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except OSError as e:
            raise PhysicsError(f"scatter kernel table {path} cannot be read: {e.strerror or e}") from None
        except ValueError as e:
            raise PhysicsError(f"scatter kernel table {path} is not valid JSON: {e}") from None
        try:
            return cls.from_dict(data)
        except PhysicsError as e:
            raise PhysicsError(f"{path}: {e}") from None

    def save(self, path) -> None:
        """Write the table as JSON, atomically."""

        write_json(path, self.to_dict())


#: The committed table: the pelvis CT (``pelvis_abdomen_3mm``) fitted at 60-140 kV without a grid
#: and with grids of ratio 6 and 16 (``scripts/fit_scatter_kernels.py``; ``docs/physics.md``).
DEFAULT_TABLE = Path(__file__).with_name("scatter_kernels_pelvis.json")


@functools.lru_cache(maxsize=4)
def default_table() -> ScatterKernelTable:
    """:data:`DEFAULT_TABLE`, read once."""
    return ScatterKernelTable.load(DEFAULT_TABLE)
