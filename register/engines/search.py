"""Coarse global pose search: where to start a local registration when the network's pose is lost.

The search covers the prior box of the poses around a start (by default the original protocol's:
+-40 deg phi, +-20 deg theta and psi, +-75 mm), coarse to fine, at downsampled detectors:

1. **grid** (``factor``, 1/4 resolution): rotations ``(phi, theta, psi)`` on a regular grid
   (``step_deg``) and depths ``tz`` on ``depths`` values, each rendered once on a detector padded
   by the largest in-plane shift; the in-plane translation ``(tx, ty)`` of each grid pose is the
   shift that maximises the gradient NCC (:func:`register.engines.metrics.gradient_ncc`'s score, the
   X-ray's field only) against the padded DRR, computed for every shift at once by FFT (masked
   normalized cross-correlation, Padfield, IEEE TIP 2012). A shift of ``d`` pixels is a
   translation of ``d * s * z / SDD`` mm at the anatomy centre's depth ``z`` (the anatomy-centred
   parameters, docs/conventions.md);
2. **rescoring** (``local_factor``, 1/2 resolution): the ``rescore`` best grid poses scored again,
   their shifts refined, which ranks realistic frames more sharply;
3. **local**: a short CMA-ES (:class:`register.engines.cmaes.CMAESRegistration`, one level at
   ``local_factor``, no polish) from ``candidates`` poses apart from each other, half the best of
   the rescoring and the rest the best of the grid, and from any poses given (the network's);
   the best distinct results are the ``finalists`` a refinement starts from.

The network's pose is searched first: when its local similarity reaches ``found_above`` the grid
is skipped (a clearly right network costs a short local search, not the grid), unless
``always_grid`` (``ctxreg register --search always``).

Use (``volume`` a CT, ``xray`` ``(128, 128)`` prepared bone-bright, ``field`` its bool mask)::

    search = GlobalSearch(volume, GlobalSearchSettings(), size=(128, 128))
    start = search.register(xray, np.zeros(6), mask=field).params   # (6,) deg, mm
    # then a local registration from ``start``: register.engines.pipeline.REFINE_SETTINGS
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from register.engines.cmaes import CMAESRegistration, CMAESSettings
from register.engines.metrics import (downsample, get_metric, gradient_ncc, image_sobel, local_gradients,
                                      plain_equivalent)
from register.engines.result import RegistrationError, RegistrationResult
from sim.core.errors import InputError
from sim.projection.geometry import CArmGeometry, pose_from_params
from sim.ct.anatomy import anatomy_center
from sim.physics.imaging import moving_renderer

__all__ = ["GlobalSearchSettings", "GlobalSearch", "masked_ncc_shifts", "describe_search"]


@dataclass(frozen=True)
class GlobalSearchSettings:
    """Settings of :class:`GlobalSearch`. Units: degrees, mm.

    Attributes:
        range_deg: ``(phi, theta, psi)`` half-widths of the rotation grid around the start (deg);
            default the original protocol's (40, 20, 20).
        step_deg: rotation grid step (deg), default 8 (11 x 6 x 6 rotations over the default
            ranges).
        range_mm: half-width of the depth (tz) grid and the largest in-plane shift (tx, ty)
            searched (mm), default 75 (the protocol's translations).
        depths: depth (tz) grid values, evenly from ``-range_mm`` to ``+range_mm`` (default 5).
        factor: detector downsampling of the grid (default 4: 32 x 32 px for a 128 px X-ray).
        rescore: the best grid poses scored again, shifts refined, at ``local_factor``'s resolution
            (default 256; 0: none). Half the candidates come from that ranking, the rest from the
            grid's own. At 1/4 resolution a realistic frame's gradients (scatter, display chain,
            noise) separate the right pose from wrong ones poorly (the truth's grid neighbour ranked
            26th-859th on lost ``fluoro-65kV`` frames; gradient NCC at the truth 0.28-0.50 there,
            0.45-0.72 at 1/2 resolution), but a grid pose half a step off still scores there.
        local_factor: detector downsampling of the rescoring and of the local search's last level
            (default 2).
        candidates: starts of the local search (default 16), each apart from those before it (more
            than one step in some angle, or one depth step, or 20 mm in-plane).
        local_sigma_deg / local_sigma_mm: the local CMA-ES's initial steps (3 deg, 8 mm).
        local_range_deg / local_range_mm: its box around each start (12 deg, 35 mm).
        local_sigma_depth_mm / local_range_depth_mm: its step and box in depth ``tz`` (mm; None: the
            translations' ``local_sigma_mm`` / ``local_range_mm``; the grid spans +-``range_mm`` in depth
            already), as :class:`register.engines.cmaes.CMAESSettings`' ``sigma_depth_mm`` /
            ``range_depth_mm`` (the refinement of the network's own pose without a search:
            :data:`register.engines.pipeline.NETWORK_DEPTH_RANGE_MM`).
        local_generations / local_fine_generations: a start from the grid's own ranking (or a given
            one) runs ``local_generations`` (default 25) at ``factor``, whose wide basins reach a
            pose half a grid step away, then ``local_fine_generations`` (default 10; 0: none) at
            ``local_factor``; a start from the rescoring runs ``local_generations`` at
            ``local_factor`` alone. Every start's search runs in lockstep (one render per
            generation for all). local_popsize: the population (16).
        finalists: the best distinct local results (apart by more than 2 deg in some angle or 10 mm
            in some translation; similarity: gradient NCC at full resolution) handed on as starts of
            the refinement (default 3), which keeps the one of highest similarity: the best local
            result is not always the right one (on ``fluoro-65kV`` frames a wrong one scored
            0.22-0.56 where the right one, refined, reached 0.51-0.60). 1 when the grid is skipped.
        metric: the similarity of the local searches and of the finalists' ranking for a display
            image, one registered with its toned version (a name of :data:`register.engines.metrics.METRICS`;
            default ``"tone_tolerant_gncc"``: half gradient NCC, half tone-free gradient NCC,
            :func:`register.engines.metrics.tone_tolerant_gradient_ncc`); an image without one (raw or log
            X-rays, DRRs: line integrals already) by its plain equivalent (gradient NCC), and the grid's FFT
            correlation is gradient NCC whatever it is.
        found_above: the given poses' (the network's) best local similarity (gradient NCC at full
            resolution) at or above which the grid is skipped (default 0.85: a wrong network pose on
            a realistic radiograph scored 0.75, right ones 0.7-0.9, so only a clear match skips the
            grid, which costs 2-4 s).
        refined_above: the refined similarity (the refinement's own score, tone-tolerant for a
            display image) the network's pose must reach after its refinement where the grid was
            skipped, or the grid runs after all (:class:`register.engines.pipeline.ContextualPipeline`;
            default 0.88: a pose the grid was skipped for that refines below it gets the grid's
            alternatives before the verdict judges it). At least ``found_above``.
        always_grid: run the grid even when a given pose reaches ``found_above`` (``ctxreg register
            --search always``: the grid's finalists compete with the network's pose whatever it
            scored); default False.
        local_below: the local similarity (:func:`register.engines.metrics.local_gradient_ncc`: the
            edges window by window) under which the pipeline's pose is searched again by local
            similarity (:meth:`register.engines.pipeline.ContextualPipeline.rescue`; default 0.35,
            the verdict's :attr:`register.verdict.VerdictSettings.min_local_similarity`, which takes
            it: one number for both). A pose under it rests on a few strong edges (a body's outline
            over air), which the whole image's similarity favours wherever they fall.
        local_sigma_px: the window (Gaussian sigma, px of each level) of the locally normalized
            gradients (:func:`register.engines.metrics.local_gradients`) the grid correlates when it
            searches by local similarity (``GlobalSearch.register(local=True)``); default 2.
        seed: CMA-ES seed.
    """

    range_deg: tuple[float, float, float] = (40.0, 20.0, 20.0)
    step_deg: float = 8.0
    range_mm: float = 75.0
    depths: int = 5
    factor: int = 4
    rescore: int = 256
    local_factor: int = 2
    candidates: int = 16
    local_sigma_deg: float = 3.0
    local_sigma_mm: float = 8.0
    local_range_deg: float = 12.0
    local_range_mm: float = 35.0
    local_sigma_depth_mm: float | None = None
    local_range_depth_mm: float | None = None
    local_generations: int = 25
    local_fine_generations: int = 10
    local_popsize: int = 16
    finalists: int = 3
    found_above: float = 0.85
    refined_above: float = 0.88
    metric: str = "tone_tolerant_gncc"
    always_grid: bool = False
    local_below: float = 0.35
    local_sigma_px: float = 2.0
    seed: int = 0

    def __post_init__(self) -> None:
        r = tuple(float(v) for v in np.ravel(self.range_deg))
        if len(r) != 3 or not all(np.isfinite(v) and 0 <= v <= 180 for v in r):
            raise RegistrationError(f"range_deg must be three half-widths in [0, 180] deg, got {self.range_deg}")
        object.__setattr__(self, "range_deg", r)
        for name in ("step_deg", "range_mm", "local_sigma_deg", "local_sigma_mm", "local_range_deg", "local_range_mm",
                     "local_sigma_depth_mm", "local_range_depth_mm", "local_sigma_px"):
            v = getattr(self, name)
            if v is None and name.endswith("depth_mm"):
                continue
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise RegistrationError(f"{name} must be a positive number, got {v!r}")
        for name, lo in (("depths", 1), ("factor", 1), ("local_factor", 1), ("rescore", 0), ("candidates", 1),
                         ("finalists", 1), ("local_generations", 1), ("local_fine_generations", 0),
                         ("local_popsize", 4)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise RegistrationError(f"{name} must be an integer >= {lo}, got {v!r}")
        if not isinstance(self.always_grid, (bool, np.bool_)):
            raise RegistrationError(f"always_grid must be True or False, got {self.always_grid!r}")
        if not (np.isfinite(self.found_above) and -1.0 <= self.found_above <= 1.0):
            raise RegistrationError(f"found_above must be a similarity in [-1, 1], got {self.found_above}")
        if not (np.isfinite(self.local_below) and -1.0 <= self.local_below <= 1.0):
            raise RegistrationError(f"local_below must be a similarity in [-1, 1], got {self.local_below}")
        if not (np.isfinite(self.refined_above) and self.found_above <= self.refined_above <= 1.0):
            raise RegistrationError(f"refined_above must be a similarity in [found_above, 1] "
                                    f"([{self.found_above:g}, 1]), got {self.refined_above}")

        try:
            get_metric(self.metric)
        except InputError as e:
            raise RegistrationError(f"metric: {e}") from None

    def grid_offsets(self) -> np.ndarray:
        """``(N, 6)`` grid offsets (deg, mm) around the start: rotations and depths; tx = ty = 0."""
        axes = [np.arange(-r, r + 1e-9, self.step_deg) if r > 0 else np.zeros(1) for r in self.range_deg]
        tz = np.linspace(-self.range_mm, self.range_mm, self.depths) if self.depths > 1 else np.zeros(1)
        phi, theta, psi, z = np.meshgrid(*axes, tz, indexing="ij")
        zeros = np.zeros(phi.size)
        return np.stack([phi.ravel(), theta.ravel(), psi.ravel(), zeros, zeros, z.ravel()], axis=1)


def masked_ncc_shifts(template: np.ndarray, mask: np.ndarray, images: np.ndarray) -> np.ndarray:
    """Masked NCC of ``template`` with each of ``images`` at every shift, by FFT.

    ``out[b, u, v]`` is the NCC over the pixels ``x`` of ``mask`` between ``template[x]`` and
    ``images[b, x + (u, v)]`` (Padfield 2012, the overlap always complete: "valid" shifts).

    Args:
        template: ``(h, w)``, or ``(K, h, w)``: several templates with the same mask, whose shared
            terms (the images' spectra, their windowed sums and sums of squares) are computed once;
            mask: ``(h, w)`` bool, at least 2 pixels; images: ``(B, H, W)``, ``H >= h``, ``W >= w``.

    Returns:
        ``(B, H - h + 1, W - w + 1)`` float64 in [-1, 1] (``(K, B, ...)`` for ``K`` templates); 0
        where an image is constant under the mask. The FFTs run in single precision (about 0.2 s
        less per grid of 1980 poses on 2 cores): against double precision the scores of a
        realistic frame's grid differ by at most 3e-6, and its 256 best poses are the same.
    """
    from scipy import fft

    ts = np.asarray(template, np.float64)
    single = ts.ndim == 2
    ts = ts[None] if single else ts
    m = np.asarray(mask, bool)
    imgs = np.asarray(images, np.float64)
    if (ts.ndim != 3 or m.shape != ts.shape[1:] or imgs.ndim != 3 or imgs.shape[1] < m.shape[0]
            or imgs.shape[2] < m.shape[1]):
        raise RegistrationError(f"masked_ncc_shifts: template (h, w) or (K, h, w) and mask (h, w), images "
                                f"(B, H >= h, W >= w); got {np.shape(template)}, {m.shape}, {imgs.shape}")
    if m.sum() < 2:
        raise RegistrationError("masked_ncc_shifts: the mask needs at least 2 pixels")
    h, w = m.shape
    H, W = imgs.shape[1:]
    mf = m.astype(np.float64)
    n = mf.sum()

    # circular correlation on a fast FFT length >= the image: valid shifts never wrap around
    shape = (fft.next_fast_len(H, real=True), fft.next_fast_len(W, real=True))

    def corr(spectrum, kernel):  # out[u, v] = sum_x kernel[x] img[x + (u, v)], valid shifts
        k = fft.rfft2(kernel[::-1, ::-1].astype(np.float32), shape)
        full = fft.irfft2(spectrum * k, shape, workers=-1)
        return full[..., h - 1:H, w - 1:W].astype(np.float64)

    i32 = imgs.astype(np.float32)
    spec = fft.rfft2(i32, shape, workers=-1)  # the images' spectrum, shared by every template
    si = corr(spec, mf)
    sii = corr(fft.rfft2(i32 * i32, shape, workers=-1), mf)
    vi = sii - si * si / n
    tiny = 1e-9 * max(float(np.abs(imgs).max()) ** 2 * n, 1e-30)
    out = []
    for t in ts:
        tm = t * mf
        st, stt = tm.sum(), (tm * t).sum()
        vt = stt - st * st / n
        cov = corr(spec, tm) - st * si / n
        scale = np.sqrt(np.maximum(vi, 0.0) * max(vt, 0.0))
        out.append(np.where(scale > tiny, cov / np.where(scale > tiny, scale, 1.0), 0.0).clip(-1.0, 1.0))
    return out[0] if single else np.stack(out)


#: :meth:`GlobalSearch.built_for`'s default: any physics of the local search
_ANY_PHYSICS = object()


class GlobalSearch:
    """The coarse global search (module doc) on one CT and one X-ray geometry.

    Args:
        volume: the CT; settings: :class:`GlobalSearchSettings`.
        size: ``(H, W)`` of the X-rays it registers (divisible by ``settings.factor``).
        scene / geometry: the C-arm (an X-ray's own :class:`sim.projection.geometry.CArmGeometry` at ``size``
            overrides the scene's detector); center_lps: ``(3,)`` anatomy centre (LPS mm).
        physics / label_materials: the moving images' physics of the local search (as
            :class:`register.engines.cmaes.CMAESRegistration`); the grid renders line DRRs whatever they are.
    """

    def __init__(self, volume, settings: GlobalSearchSettings | None = None, *, size=(128, 128),
                 scene: str = "cios_fusion", geometry=None, center_lps=None, physics=None,
                 label_materials: dict[int, str] | None = None):

        self.settings = s = settings or GlobalSearchSettings()
        size = (int(size[0]), int(size[1]))
        for name in ("factor", "local_factor"):
            f = getattr(s, name)
            if size[0] % f or size[1] % f or min(size) // f < 8:
                raise RegistrationError(f"global search: size {size} must be divisible by {name} {f} and give "
                                        f"at least 8 x 8 px")
        self.center_lps = np.asarray(anatomy_center(volume) if center_lps is None else center_lps, float)
        self.physics = physics  # of the local search's moving images (None: line DRRs)
        common = dict(size=size, sigma_deg=s.local_sigma_deg, sigma_mm=s.local_sigma_mm, range_deg=s.local_range_deg,
                      range_mm=s.local_range_mm, sigma_depth_mm=s.local_sigma_depth_mm,
                      range_depth_mm=s.local_range_depth_mm, popsize=s.local_popsize, metrics=(s.metric,), polish=False,
                      seed=s.seed)
        where = dict(scene=scene, geometry=geometry, center_lps=self.center_lps, physics=physics,
                     label_materials=label_materials)
        coarse = ((s.factor, s.local_factor), (s.local_generations, s.local_fine_generations))
        if s.local_fine_generations == 0 or s.factor == s.local_factor:
            coarse = ((s.factor,), (s.local_generations,))
        # the local CMA-ES from starts ranked at the grid's resolution, and from rescored ones
        self.local = CMAESRegistration(volume, CMAESSettings(levels=coarse[0], generations=coarse[1], **common),
                                       **where)
        self.local_fine = CMAESRegistration(volume, CMAESSettings(levels=(s.local_factor,),
                                                                  generations=(s.local_generations,), **common),
                                            **where)
        g = self.local.geometry.resized(size[0] // s.factor, size[1] // s.factor)  # the grid's detector
        if s.range_mm >= g.sod_mm:
            raise RegistrationError(f"range_mm {s.range_mm} must be below the source-isocentre distance {g.sod_mm} mm")
        self.level_geometry = g
        # the largest in-plane shift (range_mm at the nearest depth) in pixels of the grid's detector
        self.pad = int(np.ceil(s.range_mm * g.sdd_mm / (g.sod_mm - s.range_mm) / g.pixel_spacing_mm))
        # the grid ranks poses by their edges, which are the geometry's: line DRRs whatever the moving
        # physics (~2000 poly images would cost ~20 s, full ones minutes); the local search uses ``physics``
        self.padded = self._padded_renderer(volume, scene, g, self.pad)
        # the rescoring refines each grid pose's shift within +-2 grid pixels at local_factor's resolution
        self.rescore_geometry = self.local.geometry.resized(size[0] // s.local_factor, size[1] // s.local_factor)
        self.rescore_pad = 2 * max(s.factor // s.local_factor, 1)
        self.rescore_padded = self._padded_renderer(volume, scene, self.rescore_geometry, self.rescore_pad)
        self._grid_drrs = None  # (key, DRRs) of the last grid rendered (:meth:`_drrs`)
        self._grid_extremes: dict = {}  # each image's best and worst grid score of the last grid (:meth:`_surfaces`)

    def built_for(self, geometry, physics=_ANY_PHYSICS) -> bool:
        """Whether this search renders ``geometry``'s detector (:class:`sim.projection.geometry.CArmGeometry`,
        to 1e-9 relative: a detector resized to its own size may move its principal point by a
        rounding) and, where ``physics`` is given, its local search's moving images are of that
        physics (None: line DRRs), so that a caller may hand it on
        (:func:`register.xray.prepare.confirm_polarity`, which uses the grid's line DRRs alone;
        :class:`register.engines.pipeline.ContextualPipeline`)."""
        g = self.local.geometry
        same = (g.height, g.width) == (geometry.height, geometry.width) and np.allclose(
            [g.sdd_mm, g.sod_mm, g.pixel_spacing_mm, *g.principal_point],
            [geometry.sdd_mm, geometry.sod_mm, geometry.pixel_spacing_mm, *geometry.principal_point],
            rtol=1e-9, atol=1e-9)
        if physics is _ANY_PHYSICS:
            return same
        level = lambda p: "line" if p is None else p.level  # noqa: E731
        mine = self.physics
        if level(physics) == "line" or level(mine) == "line":
            return same and level(physics) == level(mine)
        return same and physics == mine

    def _padded_renderer(self, volume, scene, g, pad):
        """A line-DRR renderer of ``g``'s detector grown by ``pad`` pixels on every side."""

        cx, cy = g.principal_point
        padded = CArmGeometry(g.sdd_mm, g.sod_mm, g.height + 2 * pad, g.width + 2 * pad, g.pixel_spacing_mm,
                              cx + pad, cy + pad)
        return moving_renderer(volume, None, scene=scene, size=(padded.height, padded.width),
                               center_lps=self.center_lps, geometry=padded, coarsen=True)

    def _field(self, fixed, mask, factor):
        """``fixed`` downsampled by ``factor`` and its field eroded by one pixel (as gradient_ncc)."""
        from scipy import ndimage

        f = downsample(np.asarray(fixed, np.float64), factor)
        m = np.ones(f.shape, bool) if mask is None else downsample(np.asarray(mask, np.float64), factor) > 0.999
        m = ndimage.binary_erosion(m, np.ones((3, 3)), border_value=0)
        if m.sum() < 16:
            raise RegistrationError(f"global search: the X-ray's field leaves {int(m.sum())} pixels at 1/{factor} "
                                    f"resolution; too few to search")
        return f, m

    def _drrs(self, params: np.ndarray, renderer, g) -> np.ndarray:
        """The padded DRRs ``(N, h, w)`` of ``params`` ``(N, 6)`` by ``renderer`` (of detector ``g``).
        The grid's own (``self.padded``) are kept for the next call with the same poses: the
        polarity check (:meth:`polarity_scores`) and the search then render the grid once."""
        params = np.ascontiguousarray(params, np.float64)
        key = (params.shape, params.tobytes())
        if renderer is self.padded and self._grid_drrs is not None and self._grid_drrs[0] == key:
            return self._grid_drrs[1]
        drrs = renderer.render(pose_from_params(params, g.sod_mm))
        if renderer is self.padded:
            self._grid_drrs = (key, drrs)
        return drrs

    def _surfaces(self, fields, params, renderer, g, times=None, local: bool = False) -> np.ndarray:
        """The gradient NCC of every in-plane shift of every pose of ``params`` ``(N, 6)`` against
        each ``(f, m)`` of ``fields`` (one field ``m``; the DRRs rendered once): ``(images, N, du,
        dv)``; ``times`` as :meth:`grid`. ``local``: of the locally normalized gradients
        (:func:`register.engines.metrics.local_gradients`, ``local_sigma_px``; the X-ray's over its
        field) instead of the Sobel ones (each DRR's own: :func:`register.engines.metrics.image_sobel`,
        not blended with its neighbours in the batch)."""
        m = fields[0][1]
        if any(mk.shape != m.shape or np.any(mk != m) for _, mk in fields):
            raise RegistrationError("global search: the versions of an X-ray must share one field")
        t0 = time.perf_counter()
        drrs = self._drrs(params, renderer, g)
        t1 = time.perf_counter()
        score = 0.0
        if local:
            sigma = self.settings.local_sigma_px
            fixed_g = [local_gradients(f, mk, sigma) for f, mk in fields]
            moving_g = local_gradients(drrs, None, sigma)
        for i, axis in enumerate((-1, -2)):  # Sobel x, then y: the mean of the two NCCs as gradient NCC
            if local:
                templates, moving = np.stack([fg[i] for fg in fixed_g]), moving_g[i]
            else:
                templates = image_sobel(np.stack([f for f, _ in fields]), axis)
                moving = image_sobel(drrs, axis)
            score = score + 0.5 * masked_ncc_shifts(templates, m, moving)
        if times is not None:
            times["render"] = times.get("render", 0.0) + t1 - t0
            times["ncc"] = times.get("ncc", 0.0) + time.perf_counter() - t1
        if renderer is self.padded and not local:  # the grid's: each image's extremes, for the polarity check after it
            self._grid_extremes = {self._grid_key(f, mk, params): (float(sc.max()), float(sc.min()))
                                   for (f, mk), sc in zip(fields, score)}
        return score

    @staticmethod
    def _grid_key(f, m, params) -> tuple:
        """What makes two grid score surfaces the same: the field image, its mask and the poses."""
        return (f.shape, f.tobytes(), m.tobytes(), np.ascontiguousarray(params, np.float64).tobytes())

    def polarity_scores(self, fixed: np.ndarray, init_params=np.zeros(6), *,
                        mask: np.ndarray | None = None) -> tuple[float, float]:
        """The best grid score of ``fixed`` ``(H, W)`` (at ``size``) and of its inverse: ``(as
        given, inverted)``, gradient NCC at the grid's resolution over every grid pose and in-plane
        shift. The inverse's gradients are the negated ones, so one pass gives both (the score
        surfaces' maximum, and minus their minimum). The grid covers the whole prior box, so the
        right polarity finds the anatomy wherever it lies in it (0.38-0.96 on realistic frames;
        :data:`register.xray.prepare.POLARITY_FLIP_MARGIN` says how far apart the two were)."""
        s = self.settings
        field = self._field(fixed, mask, s.factor)
        params = np.asarray(init_params, float).reshape(6) + s.grid_offsets()
        known = self._grid_extremes.get(self._grid_key(*field, params))
        if known is not None:  # the search ranked this image on this grid already: the same surface
            return known[0], -known[1]
        score = self._surfaces([field], params, self.padded, self.level_geometry)[0]
        return float(score.max()), float(-score.min())

    def _best_shifts(self, fields, params, renderer, g, pad, times=None, local: bool = False):
        """Each pose of ``params`` ``(N, 6)`` moved by its best in-plane shift (within ``pad`` pixels of
        ``g``) against each ``(f, m)`` of ``fields`` (versions of one X-ray with one field ``m``; the
        DRRs are rendered, and their shared FFT terms computed, once): a list with ``(params (N, 6),
        scores (N,))`` per image, best first; ``local`` as :meth:`_surfaces`."""
        score = self._surfaces(fields, params, renderer, g, times, local)
        out = []
        for sc in score:  # (N, du, dv) per image
            moved = np.array(params, float, copy=True)
            flat = sc.reshape(len(moved), -1)
            du, dv = np.unravel_index(flat.argmax(1), sc.shape[1:])
            # fixed(x) matches drr(x + d): the anatomy must move by -d pixels, at its depth
            mm_per_px = (g.sod_mm + moved[:, 5]) * g.pixel_spacing_mm / g.sdd_mm
            moved[:, 3] -= (dv - pad) * mm_per_px
            moved[:, 4] -= (du - pad) * mm_per_px
            best = flat.max(1)
            order = np.argsort(-best, kind="stable")
            out.append((moved[order], best[order]))
        return out

    def grid(self, fixed: np.ndarray, init_params=np.zeros(6), *, mask: np.ndarray | None = None,
             times: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every grid pose with its best in-plane shift at ``factor``'s resolution: ``(params (N, 6)
        deg/mm, scores (N,))``, best score first. ``fixed`` ``(H, W)`` at ``size``; ``mask``
        ``(H, W)`` bool, the field. ``times``: a dict that gets the seconds of ``"render"`` (the
        padded DRRs) and ``"ncc"`` (the FFT NCC of every shift), added to what it holds."""
        return self.grids([fixed], init_params, mask=mask, times=times)[0]

    def grids(self, images, init_params=np.zeros(6), *, mask: np.ndarray | None = None,
              times: dict | None = None, local: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`grid` for several versions of the X-ray (``images``: ``(H, W)`` each, one field
        ``mask``), the grid's DRRs rendered once: a list of ``(params, scores)``, one per image;
        ``local``: ranked by locally normalized gradients (:meth:`_surfaces`)."""
        s = self.settings
        fields = [self._field(image, mask, s.factor) for image in images]
        params = np.asarray(init_params, float).reshape(6) + s.grid_offsets()
        return self._best_shifts(fields, params, self.padded, self.level_geometry, self.pad, times, local)

    def rescored(self, fixed: np.ndarray, params: np.ndarray, *, mask: np.ndarray | None = None,
                 times: dict | None = None, local: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Poses ``(K, 6)`` (grid poses with their shifts) scored again at ``local_factor``'s
        resolution, each shift refined within +-2 grid pixels: ``(params (K, 6), scores (K,))``,
        best first; ``times`` as :meth:`grid`."""
        field = self._field(fixed, mask, self.settings.local_factor)
        return self._best_shifts([field], np.asarray(params, float).reshape(-1, 6), self.rescore_padded,
                                 self.rescore_geometry, self.rescore_pad, times, local)[0]

    def _distinct(self, params: np.ndarray, limit: int, kept=()) -> list:
        """Rows of ``params`` (best first), each apart from ``kept`` and from the rows taken before
        it (more than one grid step in some angle, or one depth step, or 20 mm in-plane), until
        ``limit`` rows are kept in all: ``kept`` and the new rows, as a list."""
        s = self.settings
        dz = 2 * s.range_mm / max(s.depths - 1, 1)
        kept = list(kept)
        for p in params:
            if len(kept) >= limit:
                break
            near = any(np.all(np.abs(p[:3] - q[:3]) <= s.step_deg + 1e-6) and abs(p[5] - q[5]) <= dz + 1e-6
                       and np.hypot(*(p[3:5] - q[3:5])) < 20.0 for q in kept)
            if not near:
                kept.append(p)
        return kept

    def _plain_similarity(self, fixed, result, mask, metric: str) -> float:
        """``result``'s gradient NCC at full resolution (``metric``: the similarity it was scored
        by): the skip decision's score. A tone-free similarity (:data:`GlobalSearchSettings.metric`)
        forgives any display curve, so it is more lenient than the threshold was set for."""
        if metric == "gncc":
            return float(result.similarity)

        return float(gradient_ncc(fixed, self.local.render(np.asarray(result.params, float).reshape(1, 6), 1),
                                  mask=mask)[0])

    def register(self, fixed: np.ndarray, init_params=np.zeros(6), *, mask: np.ndarray | None = None,
                 poses=(), toned: np.ndarray | None = None,
                 before_grid: Callable[[], bool] | None = None, grid: bool = False,
                 local: bool = False) -> RegistrationResult | None:
        """The best pose the search finds for ``fixed`` ``(H, W)`` around ``init_params`` (deg, mm).

        ``toned``: ``(H, W)`` the X-ray's toned version (:attr:`register.xray.prepare.PreparedXRay.toned`)
        or None: the grid ranks both, each supplying its share of the candidates.
        ``poses``: ``(K, 6)`` parameters searched locally first (the network's pose), each clipped
        into the prior box (``init_params`` +- ``range_deg`` / ``range_mm``) first: when the best
        of them reaches ``found_above`` the grid is skipped (unless ``grid`` or ``always_grid``: the
        grid runs whatever they score; ``grid`` is the pipeline's, for a pose whose refinement
        ended below ``refined_above``). The result's similarity is the gradient
        NCC at full resolution at its pose; ``stage_seconds`` has ``search_local`` (and
        ``search_grid`` when the grid ran); ``history`` one row per local search (stage
        ``search``); ``search`` the record ``{"given_similarity": the best given pose's local
        similarity (None without one), "given_score": its gradient NCC at full resolution, the
        score the skip decision tested (None without one), "given_clipped": whether a given pose
        lay outside the prior box, "found_above", "always_grid": whether the grid ran whatever the
        given pose scored, "grid_poses": grid poses rendered (0: skipped), "candidates": grid
        poses searched locally, "start": "given" or "grid", "similarity", "grid_render_s" /
        "grid_ncc_s": the grid's and the rescoring's seconds rendering and correlating (0 when
        skipped), "finalists": the best distinct local results, best first (the first is the
        result), at most ``settings.finalists`` when the grid ran and 1 otherwise: ``[{"params":
        (6,) deg/mm, "similarity", "start": "given" or "grid"}, ...]``}``; the refinement starts
        from each (:class:`register.engines.pipeline.ContextualPipeline`).

        ``before_grid``: called once just before the grid is rendered and ranked (not where it is
        skipped); where it returns True the search stops there and returns None. ``register_xray``
        checks the X-ray's polarity on this search's grid there (its DRRs then serve the ranking), so
        that an image to be inverted costs no grid search on the wrong one.

        ``local``: search by local similarity: the grid correlates locally normalized gradients
        (:func:`register.engines.metrics.local_gradients`) and the local searches score by
        :func:`register.engines.metrics.local_gradient_ncc` (``"local_gncc"``), whatever
        ``settings.metric``; the grid runs whatever the given poses score (the record's ``local``:
        True). The pipeline's second search where its pose's local similarity is below
        ``local_below`` (:meth:`register.engines.pipeline.ContextualPipeline.rescue`)."""
        s = self.settings
        fixed = np.asarray(fixed, np.float64)
        if mask is not None:
            mask = np.asarray(mask, bool)
            if mask.shape != fixed.shape:
                raise RegistrationError(f"mask: expected the X-ray's shape {fixed.shape}, got {mask.shape}")
        if toned is not None and np.shape(toned) != fixed.shape:
            raise RegistrationError(f"toned: expected the X-ray's shape {fixed.shape}, got {np.shape(toned)}")
        stages: dict[str, float] = {}
        history: list[tuple[str, float, list[float]]] = []
        renders = 0
        best = None
        results: list[RegistrationResult] = []

        metric = s.metric if toned is not None else plain_equivalent(s.metric)  # GlobalSearchSettings.metric
        if local:
            metric, grid = "local_gncc", True
        coarse_engine, fine_engine = (e.scored_by((metric,)) for e in (self.local, self.local_fine))

        def search_locally(starts, engine):  # every start's local CMA-ES, in lockstep
            nonlocal best, renders
            starts = np.asarray(starts, float).reshape(-1, 6)
            if not len(starts):
                return
            seen = engine.in_view(starts)  # no start where the CT is out of view
            renders += len(starts)
            for r in engine.register_many(fixed, starts[seen], mask=mask):
                renders += r.renders
                history.append(("search", float(r.similarity), r.params.tolist()))
                results.append(r)
                if best is None or r.similarity > best.similarity:
                    best = r

        t0 = time.perf_counter()
        # the given poses are clipped into the prior box first: a network lost on an unfamiliar image
        # can walk hundreds of mm away, where a nearly empty DRR may correlate by chance with the
        # few edges of a saturated frame (a radiograph frame scored 0.77 at 574 mm mTRE)
        x0 = np.asarray(init_params, float).reshape(6)
        half = np.array([*s.range_deg, s.range_mm, s.range_mm, s.range_mm])
        raw = np.asarray(poses, float).reshape(-1, 6)
        given = np.clip(raw, x0 - half, x0 + half)
        search_locally(given, coarse_engine)
        stages["search_local"] = time.perf_counter() - t0
        given_best = best
        # the skip decision's score: the given poses' best, plain gradient NCC at full resolution
        given_score = None if best is None else self._plain_similarity(fixed, best, mask, metric)
        grid_poses = candidates = 0
        grid_times = {"render": 0.0, "ncc": 0.0}  # the grid's and the rescoring's
        if given_score is None or grid or s.always_grid or given_score < s.found_above:
            if before_grid is not None and before_grid():
                return None
            t0 = time.perf_counter()
            # the grid ranks the X-ray as prepared and, for a display image, its toned version too:
            # the toned one finds strongly curved displays (a gamma 2.6, a linear display), the
            # prepared one the views whose histogram the tone's reference poses do not share
            images = [fixed] if toned is None else [fixed, np.asarray(toned, np.float64)]
            ranked = [p for p, _ in self.grids(images, init_params, mask=mask, times=grid_times, local=local)]
            self._grid_drrs = None  # used (tens of MB freed); the polarity check reads the surfaces' extremes
            grid_poses = len(ranked[0])
            renders += grid_poses
            # half the candidates from the rankings at local_factor's resolution (sharper at the
            # optimum), the rest from the grid's own (wider basins); each image gets its share
            n_fine = (s.candidates + 1) // 2 if s.rescore else 0
            fine = []
            for k, (image, params) in enumerate(zip(images, ranked)):
                if s.rescore:
                    top, _ = self.rescored(image, params[:s.rescore], mask=mask, times=grid_times, local=local)
                    renders += len(top)
                    fine = self._distinct(top, n_fine * (k + 1) // len(images), fine)
            kept = list(fine)
            for k, params in enumerate(ranked):
                kept = self._distinct(params, n_fine + (s.candidates - n_fine) * (k + 1) // len(images), kept)
            coarse = kept[len(fine):]
            stages["search_grid"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            candidates = len(fine) + len(coarse)
            search_locally(fine, fine_engine)
            search_locally(coarse, coarse_engine)
            stages["search_local"] += time.perf_counter() - t0
        if best is None:
            raise RegistrationError("global search: no pose of the grid overlaps the X-ray (every DRR is empty); "
                                    "check the geometry and the anatomy centre")
        finalists = [best]
        for r in sorted(results, key=lambda r: -r.similarity):
            if len(finalists) >= (s.finalists if grid_poses else 1):
                break
            if all(np.any(np.abs(r.params[:3] - f.params[:3]) > 2.0) or np.any(np.abs(r.params[3:] - f.params[3:]) > 10.0)
                   for f in finalists):
                finalists.append(r)
        best.stage_seconds = stages
        best.history = history
        best.renders = renders
        best.search = {"given_similarity": None if given_best is None else float(given_best.similarity),
                       "given_score": given_score, "given_clipped": bool(np.any(given != raw)),
                       "found_above": s.found_above, "always_grid": bool(s.always_grid), "local": bool(local),
                       "grid_poses": grid_poses, "candidates": candidates,
                       "start": "given" if best is given_best else "grid", "similarity": float(best.similarity),
                       "grid_render_s": grid_times["render"], "grid_ncc_s": grid_times["ncc"],
                       "finalists": [{"params": f.params.tolist(), "similarity": float(f.similarity),
                                      "start": "given" if f is given_best else "grid"} for f in finalists]}
        return best


def describe_search(record: dict) -> str:
    """One line for a user from a search record (:meth:`GlobalSearch.register`, with the network's
    pose as the given one; with ``"refined"`` and ``"chosen"`` when the refinement ran from its
    finalists, ``"rescue"`` where the pose was searched again by local similarity, and
    ``"trusted"`` where the verdict judged the network's pose, refined, before the search,
    :class:`register.engines.pipeline.ContextualPipeline`)."""
    rescue = record.get("rescue")
    if rescue is not None:
        why = (f"the pose found first agreed with the X-ray's edges as a whole but not window by window (local "
               f"similarity {rescue['local_before']:.2f} < {rescue['local_below']:g})")
        after = rescue.get("local_after")
        if rescue["kept"] == "rescued":
            return (f"global search: {why}; searched again by local similarity ({record['grid_poses']} grid poses), "
                    f"its pose agrees window by window ({after:.2f}) and replaced it")
        found = "nothing" if after is None else f"nothing better ({after:.2f})"
        return describe_search({k: v for k, v in record.items() if k != "rescue"}) + (
            f"; {why}: searched again by local similarity, {found}, the first pose kept")
    if record.get("trusted"):
        return (f"global search: skipped, the network's pose, refined (similarity {record['similarity']:.2f}), "
                "judged registered by the verdict")
    net = record["given_similarity"]
    after = record.get("after_refinement")
    head = "global search: " + ("no network pose" if net is None else
                                f"the network's pose scored >= {record['found_above']:g}, its refinement "
                                f"{after:.2f}" if after is not None else f"the network's pose scored {net:.2f}")
    below = record.get("refined_above", record["found_above"]) if after is not None else record["found_above"]
    doubted = ("" if record.get("trusted") is not False else  # the verdict doubted the network's pose, refined, first
               f"; the network's pose refined first ({record['trust_similarity']:.2f}) was not judged registered")
    if not record["grid_poses"]:
        return head + f" (>= {record['found_above']:g}): grid skipped, refined from it" + doubted
    finalists = record.get("finalists") or [{"start": record["start"], "similarity": record["similarity"]}]
    chosen = record.get("chosen", 0)
    kept = finalists[chosen]
    origin = ("the network's pose" + (" refined" if after is not None else "")) if kept["start"] == "given" else "a grid pose"
    why = ("grid run whatever it scored, --search always" if record.get("always_grid")
           else f"< {below:g}")
    line = head + f" ({why}): {record['grid_poses']} grid poses, {record['candidates']} searched locally; "
    if "refined" in record and len(record["refined"]) > 1:
        rank = ("best", "second best", "third best")[chosen] if chosen < 3 else f"number {chosen + 1}"
        return line + (f"the best {len(record['refined'])} refined, kept the {rank} ({origin}, similarity "
                       f"{kept['similarity']:.2f}, {record['refined'][chosen]:.2f} after refinement)") + doubted
    return line + f"refined from {origin} (similarity {kept['similarity']:.2f})" + doubted
