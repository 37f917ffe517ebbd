"""Coarse global pose search: where to start a local registration when the network's pose is lost.

The search covers the prior box of the poses around a start (by default the original protocol's:
+-40 deg phi, +-20 deg theta and psi, +-75 mm), coarse to fine, at a downsampled detector:

1. **grid**: rotations ``(phi, theta, psi)`` on a regular grid (``step_deg``) and depths ``tz`` on
   ``depths`` values, each rendered once on a detector padded by the largest in-plane shift; the
   in-plane translation ``(tx, ty)`` of each grid pose is the shift that maximises the gradient
   NCC (:func:`register.metrics.gradient_ncc`'s score, the X-ray's field only) against the padded
   DRR, computed for every shift at once by FFT (masked normalized cross-correlation, Padfield,
   IEEE TIP 2012). A shift of ``d`` pixels is a translation of ``d * s * z / SDD`` mm at the
   anatomy centre's depth ``z`` (the anatomy-centred parameters, docs/conventions.md);
2. **local**: a short CMA-ES (:class:`register.cmaes.CMAESRegistration`, one level, no polish) from
   each of the ``candidates`` best grid poses that are apart from each other, and from any poses
   given (the network's), the best similarity kept.

The network's pose is searched first: when its local similarity reaches ``found_above`` the grid
is skipped (a clearly right network costs a short local search, not the grid).

Use (``volume`` a CT, ``xray`` ``(128, 128)`` prepared bone-bright, ``field`` its bool mask)::

    search = GlobalSearch(volume, GlobalSearchSettings(), size=(128, 128))
    start = search.register(xray, np.zeros(6), mask=field).params   # (6,) deg, mm
    # then a local registration from ``start``: register.contextual.REFINE_SETTINGS
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from register.cmaes import CMAESRegistration, CMAESSettings, RegistrationError, RegistrationResult

__all__ = ["GlobalSearchSettings", "GlobalSearch", "masked_ncc_shifts", "describe_search"]


@dataclass(frozen=True)
class GlobalSearchSettings:
    """Settings of :class:`GlobalSearch`. Units: degrees, mm.

    Attributes:
        range_deg: ``(phi, theta, psi)`` half-widths of the rotation grid around the start (deg);
            default the original protocol's (40, 20, 20).
        step_deg: rotation grid step (deg), default 8 (11 x 6 x 6 rotations over the default
            ranges; on the 15 of 50 ``fluoro-65kV`` frames that 10 deg steps and 8 candidates lost,
            8 deg steps and 16 candidates found 7, 10 deg steps and 16 candidates 3).
        range_mm: half-width of the depth (tz) grid and the largest in-plane shift (tx, ty)
            searched (mm), default 75 (the protocol's translations).
        depths: depth (tz) grid values, evenly from ``-range_mm`` to ``+range_mm`` (default 5).
        factor: detector downsampling of the search (default 4: 32 x 32 px for a 128 px X-ray).
        candidates: grid poses handed to the local search (default 16), best first, each apart from
            those before it (more than one step in some angle, or one depth step, or 20 mm in-plane).
        local_sigma_deg / local_sigma_mm: the local CMA-ES's initial steps (3 deg, 8 mm).
        local_range_deg / local_range_mm: its box around each candidate (12 deg, 35 mm).
        local_generations: its generations (default 25); local_popsize: its population (16).
        found_above: the given poses' (the network's) best local similarity at or above which the
            grid is skipped (default 0.85; gradient NCC at the search's resolution: a wrong network
            pose on a realistic radiograph scored 0.75 there, right ones 0.7-0.9, so only a clear
            match skips the grid, and the grid costs 1-3 s).
        seed: CMA-ES seed.
    """

    range_deg: tuple[float, float, float] = (40.0, 20.0, 20.0)
    step_deg: float = 8.0
    range_mm: float = 75.0
    depths: int = 5
    factor: int = 4
    candidates: int = 16
    local_sigma_deg: float = 3.0
    local_sigma_mm: float = 8.0
    local_range_deg: float = 12.0
    local_range_mm: float = 35.0
    local_generations: int = 25
    local_popsize: int = 16
    found_above: float = 0.85
    seed: int = 0

    def __post_init__(self) -> None:
        r = tuple(float(v) for v in np.ravel(self.range_deg))
        if len(r) != 3 or not all(np.isfinite(v) and 0 <= v <= 180 for v in r):
            raise RegistrationError(f"range_deg must be three half-widths in [0, 180] deg, got {self.range_deg}")
        object.__setattr__(self, "range_deg", r)
        for name in ("step_deg", "range_mm", "local_sigma_deg", "local_sigma_mm", "local_range_deg", "local_range_mm"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise RegistrationError(f"{name} must be a positive number, got {v!r}")
        for name, lo in (("depths", 1), ("factor", 1), ("candidates", 1), ("local_generations", 1),
                         ("local_popsize", 4)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise RegistrationError(f"{name} must be an integer >= {lo}, got {v!r}")
        if not (np.isfinite(self.found_above) and -1.0 <= self.found_above <= 1.0):
            raise RegistrationError(f"found_above must be a similarity in [-1, 1], got {self.found_above}")

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
        template: ``(h, w)``; mask: ``(h, w)`` bool, at least 2 pixels; images: ``(B, H, W)``,
            ``H >= h``, ``W >= w``.

    Returns:
        ``(B, H - h + 1, W - w + 1)`` float64 in [-1, 1]; 0 where an image is constant under the mask.
    """
    from scipy import fft

    t = np.asarray(template, np.float64)
    m = np.asarray(mask, bool)
    imgs = np.asarray(images, np.float64)
    if t.ndim != 2 or m.shape != t.shape or imgs.ndim != 3 or imgs.shape[1] < t.shape[0] or imgs.shape[2] < t.shape[1]:
        raise RegistrationError(f"masked_ncc_shifts: template (h, w) and mask of its shape, images (B, H >= h, W >= w); "
                                f"got {t.shape}, {m.shape}, {imgs.shape}")
    if m.sum() < 2:
        raise RegistrationError("masked_ncc_shifts: the mask needs at least 2 pixels")
    h, w = t.shape
    H, W = imgs.shape[1:]
    mf = m.astype(np.float64)
    tm = t * mf
    n = mf.sum()
    st, stt = tm.sum(), (tm * t).sum()
    vt = stt - st * st / n

    def corr(img, kernel):  # out[u, v] = sum_x kernel[x] img[x + (u, v)], valid shifts
        k = fft.rfft2(kernel[::-1, ::-1], (H, W))
        full = fft.irfft2(fft.rfft2(img, (H, W), workers=-1) * k, (H, W), workers=-1)
        return full[..., h - 1:H, w - 1:W]

    si, sii, sit = corr(imgs, mf), corr(imgs * imgs, mf), corr(imgs, tm)
    cov = sit - st * si / n
    vi = sii - si * si / n
    scale = np.sqrt(np.maximum(vi, 0.0) * max(vt, 0.0))
    tiny = 1e-9 * max(float(np.abs(imgs).max()) ** 2 * n, 1e-30)
    return np.where(scale > tiny, cov / np.where(scale > tiny, scale, 1.0), 0.0).clip(-1.0, 1.0)


class GlobalSearch:
    """The coarse global search (module doc) on one CT and one X-ray geometry.

    Args:
        volume: the CT; settings: :class:`GlobalSearchSettings`.
        size: ``(H, W)`` of the X-rays it registers (divisible by ``settings.factor``).
        scene / geometry: the C-arm (an X-ray's own :class:`sim.geometry.CArmGeometry` at ``size``
            overrides the scene's detector); center_lps: ``(3,)`` anatomy centre (LPS mm).
        physics / label_materials: the moving images' physics of the local search (as
            :class:`register.cmaes.CMAESRegistration`); the grid renders line DRRs whatever they are.
    """

    def __init__(self, volume, settings: GlobalSearchSettings | None = None, *, size=(128, 128),
                 scene: str = "cios_fusion", geometry=None, center_lps=None, physics=None,
                 label_materials: dict[int, str] | None = None):
        from sim.anatomy import anatomy_center
        from sim.geometry import CArmGeometry
        from sim.physics.imaging import moving_renderer

        self.settings = s = settings or GlobalSearchSettings()
        size = (int(size[0]), int(size[1]))
        if size[0] % s.factor or size[1] % s.factor or min(size) // s.factor < 8:
            raise RegistrationError(f"global search: size {size} must be divisible by factor {s.factor} and give "
                                    f"at least 8 x 8 px")
        self.center_lps = np.asarray(anatomy_center(volume) if center_lps is None else center_lps, float)
        self.local = CMAESRegistration(
            volume, CMAESSettings(levels=(s.factor,), size=size, sigma_deg=s.local_sigma_deg,
                                  sigma_mm=s.local_sigma_mm, range_deg=s.local_range_deg, range_mm=s.local_range_mm,
                                  popsize=s.local_popsize, generations=(s.local_generations,), metrics=("gncc",),
                                  polish=False, seed=s.seed),
            scene=scene, geometry=geometry, center_lps=self.center_lps, physics=physics, label_materials=label_materials)
        g = self.local.by_factor[s.factor].geometry  # the search's detector
        if s.range_mm >= g.sod_mm:
            raise RegistrationError(f"range_mm {s.range_mm} must be below the source-isocentre distance {g.sod_mm} mm")
        self.level_geometry = g
        # the largest in-plane shift (range_mm at the nearest depth) in pixels of the search's detector
        self.pad = int(np.ceil(s.range_mm * g.sdd_mm / (g.sod_mm - s.range_mm) / g.pixel_spacing_mm))
        cx, cy = g.principal_point
        padded = CArmGeometry(g.sdd_mm, g.sod_mm, g.height + 2 * self.pad, g.width + 2 * self.pad, g.pixel_spacing_mm,
                              cx + self.pad, cy + self.pad)
        # the grid ranks poses by their edges, which are the geometry's: line DRRs whatever the moving
        # physics (~2000 poly images would cost ~20 s, full ones minutes); the local search uses ``physics``
        self.padded = moving_renderer(volume, None, scene=scene, size=(padded.height, padded.width),
                                      center_lps=self.center_lps, geometry=padded)

    def grid(self, fixed: np.ndarray, init_params=np.zeros(6), *, mask: np.ndarray | None = None,
             times: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every grid pose with its best in-plane shift: ``(params (N, 6) deg/mm, scores (N,))``,
        best score first. ``fixed`` ``(H, W)`` at ``size``; ``mask`` ``(H, W)`` bool, the field.
        ``times``: a dict that gets the seconds of ``"render"`` (the padded DRRs) and ``"ncc"``
        (the FFT NCC of every shift)."""
        from scipy import ndimage

        from register.metrics import downsample
        from sim.geometry import pose_from_params

        s = self.settings
        g = self.level_geometry
        f = downsample(np.asarray(fixed, np.float64), s.factor)
        m = np.ones(f.shape, bool) if mask is None else downsample(np.asarray(mask, np.float64), s.factor) > 0.999
        # gradients over the field eroded by one pixel and never on the image's border (as gradient_ncc)
        m = ndimage.binary_erosion(m, np.ones((3, 3)), border_value=0)
        if m.sum() < 16:
            raise RegistrationError(f"global search: the X-ray's field leaves {int(m.sum())} pixels at 1/{s.factor} "
                                    f"resolution; too few to search")
        x0 = np.asarray(init_params, float).reshape(6)
        params = x0 + s.grid_offsets()
        t0 = time.perf_counter()
        drrs = self.padded.render(pose_from_params(params, g.sod_mm))
        t1 = time.perf_counter()
        score = 0.0
        for axis in (-1, -2):  # Sobel x, then y: the mean of the two NCCs as gradient NCC
            score = score + 0.5 * masked_ncc_shifts(ndimage.sobel(f, axis=axis), m,
                                                    ndimage.sobel(drrs, axis=axis))
        flat = score.reshape(len(params), -1)
        du, dv = np.unravel_index(flat.argmax(1), score.shape[1:])
        # fixed(x) matches drr(x + d): the anatomy must move by -d pixels, at its depth
        mm_per_px = (g.sod_mm + params[:, 5]) * g.pixel_spacing_mm / g.sdd_mm
        params[:, 3] -= (dv - self.pad) * mm_per_px
        params[:, 4] -= (du - self.pad) * mm_per_px
        best = flat.max(1)
        order = np.argsort(-best, kind="stable")
        if times is not None:
            times.update(render=t1 - t0, ncc=time.perf_counter() - t1)
        return params[order], best[order]

    def _distinct(self, params: np.ndarray) -> np.ndarray:
        """The first ``candidates`` rows of ``params`` (best first) apart from the rows kept before them."""
        s = self.settings
        dz = 2 * s.range_mm / max(s.depths - 1, 1)
        kept = []
        for p in params:
            near = any(np.all(np.abs(p[:3] - q[:3]) <= s.step_deg + 1e-6) and abs(p[5] - q[5]) <= dz + 1e-6
                       and np.hypot(*(p[3:5] - q[3:5])) < 20.0 for q in kept)
            if not near:
                kept.append(p)
            if len(kept) == s.candidates:
                break
        return np.array(kept)

    def register(self, fixed: np.ndarray, init_params=np.zeros(6), *, mask: np.ndarray | None = None,
                 poses=()) -> RegistrationResult:
        """The best pose the search finds for ``fixed`` ``(H, W)`` around ``init_params`` (deg, mm).

        ``poses``: ``(K, 6)`` parameters searched locally first (the network's pose): when the best
        of them reaches ``found_above`` the grid is skipped. The result's similarity is the gradient
        NCC at the search's resolution; ``stage_seconds`` has ``search_local`` (and ``search_grid``
        when the grid ran); ``history`` one row per local search (stage ``search``); ``search``
        the record ``{"given_similarity": the best given pose's local similarity (None without
        one), "found_above", "grid_poses": grid poses rendered (0: skipped), "candidates": grid
        poses searched locally, "start": "given" or "grid", "similarity", "grid_render_s" /
        "grid_ncc_s": the grid's seconds rendering and correlating (0 when skipped)}``."""
        s = self.settings
        fixed = np.asarray(fixed, np.float64)
        if mask is not None:
            mask = np.asarray(mask, bool)
            if mask.shape != fixed.shape:
                raise RegistrationError(f"mask: expected the X-ray's shape {fixed.shape}, got {mask.shape}")
        stages: dict[str, float] = {}
        history: list[tuple[str, float, list[float]]] = []
        renders = 0
        best = None

        def local(starts):
            nonlocal best, renders
            for p in starts:
                drr = self.local.render(p, s.factor)[0]
                renders += 1
                if np.count_nonzero(drr > 1e-3) < 0.01 * drr.size:  # the CT is out of view there: no start
                    continue
                r = self.local.register(fixed, p, mask=mask)
                renders += r.renders
                history.append(("search", float(r.similarity), r.params.tolist()))
                if best is None or r.similarity > best.similarity:
                    best = r

        t0 = time.perf_counter()
        given = np.asarray(poses, float).reshape(-1, 6)
        local(given)
        stages["search_local"] = time.perf_counter() - t0
        given_best = best
        grid_poses = candidates = 0
        grid_times = {"render": 0.0, "ncc": 0.0}
        if best is None or best.similarity < s.found_above:
            t0 = time.perf_counter()
            params, _ = self.grid(fixed, init_params, mask=mask, times=grid_times)
            grid_poses = len(params)
            renders += grid_poses
            stages["search_grid"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            starts = self._distinct(params)
            candidates = len(starts)
            local(starts)
            stages["search_local"] += time.perf_counter() - t0
        if best is None:
            raise RegistrationError("global search: no pose of the grid overlaps the X-ray (every DRR is empty); "
                                    "check the geometry and the anatomy centre")
        best.stage_seconds = stages
        best.history = history
        best.renders = renders
        best.search = {"given_similarity": None if given_best is None else float(given_best.similarity),
                       "found_above": s.found_above, "grid_poses": grid_poses, "candidates": candidates,
                       "start": "given" if best is given_best else "grid", "similarity": float(best.similarity),
                       "grid_render_s": grid_times["render"], "grid_ncc_s": grid_times["ncc"]}
        return best


def describe_search(record: dict) -> str:
    """One line for a user from a :meth:`GlobalSearch.register` record (the network's pose as the
    given one)."""
    net = record["given_similarity"]
    head = "global search: " + ("no network pose" if net is None else f"the network's pose scored {net:.2f}")
    if not record["grid_poses"]:
        return head + f" (>= {record['found_above']:g}): grid skipped, refined from it"
    start = "the network's pose" if record["start"] == "given" else "a grid pose"
    return (head + f" (< {record['found_above']:g}): {record['grid_poses']} grid poses, {record['candidates']} "
            f"searched locally; refined from {start} (similarity {record['similarity']:.2f} at the search's resolution)")
