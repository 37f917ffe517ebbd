"""Intensity-based 2D/3D registration with CMA-ES over the six pose parameters.

The pose is searched in ctxreg's anatomy-centred parameters (phi, theta, psi in degrees about
the patient's S, L, P axes through the anatomy centre; tx, ty, tz in mm in the camera frame;
``docs/conventions.md``), coarse to fine:

1. for each resolution level (the detector downsampled by a factor), CMA-ES (the ``cma``
   package) maximises an image similarity (:mod:`register.engines.metrics`) between the X-ray and DRRs;
   each generation's whole population is rendered in one kernel launch;
2. at the finest level an optional local polish (scipy's Powell) refines the best pose.

Per-parameter step sizes are given in degrees and mm (``CMA_stds``); bounds keep the search
inside a box around the start. Everything is seeded.
"""

from __future__ import annotations

import copy
import numbers
import time
from dataclasses import dataclass, replace

import numpy as np

from register.engines.metrics import bind_metric, bind_metric_at, get_metric
from register.engines.result import RegistrationError, RegistrationResult
from sim.core.errors import InputError
from sim.projection.geometry import pose_from_params
from sim.ct.anatomy import anatomy_center
from sim.physics.imaging import moving_renderer


#: The polish's optimisers (:attr:`CMAESSettings.polish_method`).
POLISH_METHODS = ("powell", "pattern")
#: The pattern polish's step sizes (times its first directions) and its most sweeps per size.
PATTERN_SCALES = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125)
PATTERN_SWEEPS = 3


@dataclass(frozen=True)
class CMAESSettings:
    """CMA-ES registration settings. Units: degrees and mm.

    Attributes:
        levels: detector downsampling factor of each level, coarse to fine (the finest level
            renders at ``size / levels[-1]``).
        size: ``(rows, cols)`` of the finest rendering before ``levels`` divide it.
        sigma_deg / sigma_mm: initial CMA-ES step sizes of the rotation / translation parameters
            at the first level; later levels start at ``sigma_shrink`` times them.
        sigma_depth_mm: initial step size of the depth ``tz`` (mm), None = ``sigma_mm``: a single
            view constrains depth (the magnification) least, and a start from the network is off in
            depth by several times its in-plane error (docs/results.md).
        sigma_shrink: step-size factor from one level to the next.
        range_deg / range_mm: the search box: start +- range (rotations, translations).
        range_depth_mm: the box's half-width in depth ``tz`` (mm), None = ``range_mm``.
        popsize: CMA-ES population per generation (rendered as one batch).
        generations: the most generations per level (one number for all levels, or one per level).
        metrics: similarity per level (names of :data:`register.engines.metrics.METRICS`); one name for
            all levels, or one per level.
        polish: run a Powell polish at the finest level after CMA-ES (its first directions: each
            angle, tx, ty, and depth along the view ray through the anatomy centre, the direction an
            X-ray constrains least; :func:`along_view_ray`).
        polish_evals: the most similarity evaluations of the polish.
        polish_method: ``"powell"`` (scipy's Powell, one render per evaluation) or ``"pattern"``
            (a batched pattern search with parabolic moves: 13 evaluations per sweep, 12 of them
            rendered as one batch).
        seed: CMA-ES seed.
        restarts: the most restarts of the whole search (IPOP-CMA-ES, Auger & Hansen 2005: each
            restart starts again at the start pose with a new seed and twice the population) while
            the best final similarity is below ``restart_below``; the result with the highest
            final similarity is kept, so a restart can only improve the similarity. 0 = none.
        restart_below: final similarity under which a search counts as lost (gradient NCC of a
            right pose on realistic frames is 0.65-0.97; lost searches end at 0.1-0.5).
    """

    levels: tuple[int, ...] = (4, 2)
    size: tuple[int, int] = (128, 128)
    sigma_deg: float = 8.0
    sigma_mm: float = 25.0
    sigma_shrink: float = 0.3
    range_deg: float = 60.0
    range_mm: float = 150.0
    sigma_depth_mm: float | None = None
    range_depth_mm: float | None = None
    popsize: int = 24
    generations: tuple[int, ...] = (60, 40)
    metrics: tuple[str, ...] = ("gncc", "gncc")
    polish: bool = True
    polish_evals: int = 300
    polish_method: str = "powell"
    seed: int = 0
    restarts: int = 0
    restart_below: float = 0.6

    def __post_init__(self) -> None:
        if not self.levels or any(int(f) < 1 for f in self.levels):
            raise RegistrationError(f"levels must be downsampling factors >= 1, got {self.levels}")
        if any(s % max(self.levels) for s in self.size):
            raise RegistrationError(f"size {self.size} must be divisible by every level factor {self.levels}")
        for name in ("sigma_deg", "sigma_mm", "range_deg", "range_mm", "sigma_shrink", "sigma_depth_mm",
                     "range_depth_mm"):
            v = getattr(self, name)
            if v is None and name.endswith("depth_mm"):
                continue
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not (np.isfinite(v) and v > 0):
                raise RegistrationError(f"{name} must be a positive number, got {v!r}")
        if not (isinstance(self.restarts, int) and 0 <= self.restarts <= 10):
            raise RegistrationError(f"restarts must be an integer in [0, 10], got {self.restarts}")
        if not (np.isfinite(self.restart_below) and -1.0 <= self.restart_below <= 1.0):
            raise RegistrationError(f"restart_below must be a similarity in [-1, 1], got {self.restart_below}")
        if self.polish_method not in POLISH_METHODS:
            raise RegistrationError(f"polish_method must be one of {POLISH_METHODS}, got {self.polish_method!r}")
        if self.popsize < 4:
            raise RegistrationError(f"popsize must be >= 4, got {self.popsize}")
        for name in ("generations", "metrics"):
            v = getattr(self, name)
            if len(v) not in (1, len(self.levels)):
                raise RegistrationError(f"{name} needs 1 or {len(self.levels)} entries (one per level), got {v}")
        for m in self.metrics:
            try:
                get_metric(m)
            except InputError as e:
                raise RegistrationError(f"metrics: {e}") from None

    def depth(self, what: str) -> float:
        """The depth's ``"sigma"`` or ``"range"`` (mm): ``sigma_depth_mm`` / ``range_depth_mm``, or
        the translations' where None."""
        v = getattr(self, f"{what}_depth_mm")
        return float(getattr(self, f"{what}_mm") if v is None else v)

    def per_level(self, name: str, level: int):
        v = getattr(self, name)
        return v[0] if len(v) == 1 else v[level]


def along_view_ray(params: np.ndarray, depths_mm: np.ndarray, sod_mm: float) -> np.ndarray:
    """Poses moved along the view ray through the anatomy centre: ``(K, 6)`` deg/mm.

    ``params`` ``(6,)``: the pose (deg, mm; the centre at camera ``(tx, ty, sod_mm + tz)``, the
    source at the origin); ``depths_mm`` ``(K,)``: signed moves of the centre's camera depth.
    The rotation stays, and the centre moves on the line from the source through it, so it projects
    to the same pixel and the view's direction is the same: only the magnification changes.
    """
    p = np.asarray(params, float).reshape(6)
    z = sod_mm + p[5]
    if z <= 0:
        raise RegistrationError(f"along_view_ray: the anatomy centre must lie in front of the source, got depth {z} mm")
    scale = (z + np.asarray(depths_mm, float).reshape(-1)) / z
    out = np.repeat(p[None], len(scale), axis=0)
    out[:, 3] = p[3] * scale
    out[:, 4] = p[4] * scale
    out[:, 5] = z * scale - sod_mm
    return out


class CMAESRegistration:
    """Registers X-rays to one CT; renderers for every level are built once and reused.

    Args:
        volume: the CT (:class:`sim.ct.volume.CTVolume`).
        settings: :class:`CMAESSettings`.
        scene: C-arm scene name or path (the finest geometry is the scene's detector at
            ``settings.size``) — or pass ``geometry`` to use an X-ray's own geometry.
        geometry: :class:`sim.projection.geometry.CArmGeometry` at ``settings.size`` (overrides ``scene``).
        center_lps: anatomy centre (LPS mm); None = :func:`sim.ct.anatomy.anatomy_center`.
        physics: :class:`sim.physics.imaging.PhysicsSettings` of the moving images; None or level
            ``line`` = line-integral DRRs, ``poly`` / ``full`` = noise-free ``-log(I/I0)`` images
            (:func:`sim.physics.imaging.moving_renderer`).
        label_materials: ``{label: material}`` overrides of the CT's label map (poly, full).
    """

    def __init__(self, volume, settings: CMAESSettings | None = None, *, scene: str = "cios_fusion",
                 geometry=None, center_lps=None, ray_model: str = "siddon", physics=None,
                 label_materials: dict[int, str] | None = None):

        self.settings = s = settings or CMAESSettings()
        if center_lps is None:
            center_lps = anatomy_center(volume)
        self.center_lps = np.asarray(center_lps, float)
        self.renderers = []
        for factor in sorted(set(s.levels), reverse=True) + ([1] if 1 not in s.levels else []):
            size = (s.size[0] // factor, s.size[1] // factor)
            r = moving_renderer(volume, physics, scene=scene, size=size, ray_model=ray_model,
                                center_lps=self.center_lps, label_materials=label_materials,
                                geometry=None if geometry is None else geometry.resized(*size), coarsen=True)
            self.renderers.append((factor, r))
        self.by_factor = dict(self.renderers)
        self.geometry = self.by_factor[1].geometry

    def scored_by(self, metrics: tuple[str, ...]) -> "CMAESRegistration":
        """This registration with another similarity per level (``settings.metrics``), sharing its
        renderers (nothing is rebuilt): e.g. plain gradient NCC for a line-integral image where the
        settings name a display-tolerant one."""
        if tuple(metrics) == tuple(self.settings.metrics):
            return self
        return self.adjusted(metrics=tuple(metrics))

    def adjusted(self, **changes) -> "CMAESRegistration":
        """This registration with ``changes`` to its :class:`CMAESSettings` (checked as there),
        sharing its renderers: the levels must be ones it renders, and the size stays."""
        settings = replace(self.settings, **changes)
        if tuple(settings.size) != tuple(self.settings.size):
            raise RegistrationError(f"adjusted: the size stays {self.settings.size} (its renderers'), got {settings.size}")
        missing = sorted(set(settings.levels) - set(self.by_factor))
        if missing:
            raise RegistrationError(f"adjusted: no renderer for the level factor(s) {missing}; it renders "
                                    f"{sorted(self.by_factor)}")
        other = copy.copy(self)
        other.settings = settings
        return other

    def render(self, params: np.ndarray, factor: int = 1) -> np.ndarray:
        """``(B, H/f, W/f)`` DRRs for ``(B, 6)`` parameters at a level's factor."""
        r = self.by_factor[factor]
        return r.render(pose_from_params(np.atleast_2d(params), r.geometry.sod_mm))

    def register(self, fixed: np.ndarray, init_params=np.zeros(6), *, mask: np.ndarray | None = None,
                 progress=None, polish: bool | None = None) -> RegistrationResult:
        """Register the image ``fixed`` ``(H, W)`` (at ``settings.size``), starting at ``init_params``.

        ``fixed`` must already be preprocessed like the DRRs (line-integral-like: bone bright);
        ``mask`` ``(H, W)`` bool excludes pixels (collimator, tools) from the similarity.
        ``polish``: False leaves the polish out whatever ``settings.polish`` (a caller that compares
        several registrations first and polishes the winner, :meth:`polish`).
        """
        s = self.settings
        fixed = self._checked(fixed)
        x0 = np.asarray(init_params, dtype=np.float64).reshape(6)
        if not np.all(np.isfinite(x0)):
            raise RegistrationError(f"the start pose must be finite, got {x0}")
        if not self.in_view(x0)[0]:
            raise RegistrationError("the CT does not overlap the view at the start pose (its DRR is "
                                    "empty): check the scene geometry, the anatomy centre and --init")
        scale = self._scale()
        lo, hi = self._box(x0)
        renders = 0
        stages: dict[str, float] = {}
        history: list[tuple[str, float, list[float]]] = []
        best, final = x0, -np.inf
        for attempt in range(s.restarts + 1):
            prefix = "" if attempt == 0 else f"restart{attempt}."
            params, value, n = self._search(self._scorer(fixed, mask), x0, lo, hi, scale, seed=s.seed + 100 * attempt,
                                            popsize=s.popsize * 2 ** attempt, prefix=prefix, stages=stages,
                                            history=history, progress=progress,
                                            polish=s.polish if polish is None else polish and s.polish)
            renders += n
            if value > final:
                best, final = params, value
            if final >= s.restart_below:
                break
        pose = pose_from_params(best, self.geometry.sod_mm)
        return RegistrationResult(params=best, pose=pose,
                                  projection=self.by_factor[1].projection_matrix(pose),
                                  similarity=final, renders=renders, stage_seconds=stages, history=history)

    def register_many(self, fixed: np.ndarray, starts, *, mask: np.ndarray | None = None,
                      polish: bool | None = None) -> list[RegistrationResult]:
        """:meth:`register` from each row of ``starts`` ``(K, 6)`` (deg, mm), the K searches in
        lockstep: each generation renders all their populations in one batch (K times fewer kernel
        launches; the same result per start as :meth:`register` without restarts). Returns K
        results, in the order of ``starts``; each one's ``stage_seconds`` is its share (1/K) of the
        lockstep's wall time. ``settings.restarts`` does not apply."""
        s = self.settings
        fixed = self._checked(fixed)
        x0s = np.asarray(starts, dtype=np.float64).reshape(-1, 6)
        if len(x0s) == 0:
            return []
        if not np.all(np.isfinite(x0s)):
            raise RegistrationError("the start poses must be finite")
        if not np.all(self.in_view(x0s)):
            raise RegistrationError("the CT does not overlap the view at a start pose (its DRR is empty): check "
                                    "the scene geometry, the anatomy centre and the starts")
        boxes = [self._box(x) for x in x0s]
        stages: dict[str, float] = {}
        histories: list[list] = [[] for _ in x0s]
        out = self._search_many(self._scorer(fixed, mask), x0s, np.array([b[0] for b in boxes]), np.array([b[1] for b in boxes]),
                                self._scale(), seed=s.seed,
                                popsize=s.popsize, prefix="", stages=stages, histories=histories, progress=None,
                                polish=s.polish if polish is None else polish and s.polish)
        results = []
        for (best, final, n), history in zip(out, histories):
            pose = pose_from_params(best, self.geometry.sod_mm)
            results.append(RegistrationResult(params=best, pose=pose, projection=self.by_factor[1].projection_matrix(pose),
                                              similarity=final, renders=n,
                                              stage_seconds={k: v / len(x0s) for k, v in stages.items()},
                                              history=history))
        return results

    def in_view(self, params) -> np.ndarray:
        """``(K,)`` bool for ``(K, 6)`` (or ``(6,)``) poses: whether the CT shows in the view there
        (at least 1 % of the DRR's pixels above 1e-3 at the coarsest level); a search cannot start
        where it does not."""
        drrs = self.render(np.atleast_2d(params), max(self.settings.levels))
        return np.count_nonzero(drrs > 1e-3, axis=(1, 2)) >= 0.01 * drrs[0].size

    def _scale(self) -> np.ndarray:
        """``(6,)``: CMA-ES searches in deg-like units: in-plane translations divided by
        sigma_mm / sigma_deg, the depth by its own first step (:meth:`CMAESSettings.depth`) / sigma_deg."""
        s = self.settings
        return np.array([1.0] * 3 + [s.sigma_mm / s.sigma_deg] * 2 + [s.depth("sigma") / s.sigma_deg])

    def _checked(self, fixed) -> np.ndarray:
        """``fixed`` as float64 ``(H, W)`` at ``settings.size``, finite."""
        s = self.settings
        fixed = np.asarray(fixed, dtype=np.float64)
        if fixed.shape != tuple(s.size):
            raise RegistrationError(f"the X-ray must be {s.size} (rows, cols) after preprocessing, got {fixed.shape}")
        if not np.all(np.isfinite(fixed)):
            raise RegistrationError("the X-ray contains NaN or infinite pixels")
        return fixed

    def _box(self, x0):
        """The search box ``(lo, hi)`` ``(6,)`` around a start (deg, mm)."""
        s = self.settings
        half = np.array([s.range_deg] * 3 + [s.range_mm] * 2 + [s.depth("range")])
        return x0 - half, x0 + half

    def polish(self, fixed: np.ndarray, params, *, start=None, mask: np.ndarray | None = None
               ) -> RegistrationResult:
        """The polish alone (Powell at full resolution, ``settings.polish_evals``) from ``params``
        ``(6,)`` (deg, mm), inside the box around ``start`` (default ``params``): the result of a
        :meth:`register` run with ``polish=False``, finished. ``stage_seconds`` has ``"polish"``."""
        s = self.settings
        fixed = self._checked(fixed)
        x = np.asarray(params, float).reshape(6)
        lo, hi = self._box(x if start is None else np.asarray(start, float).reshape(6))
        score = bind_metric(s.per_level("metrics", len(s.levels) - 1), fixed, mask)
        t0 = time.perf_counter()
        best, value, renders = self._polish(score, x, lo, hi)
        pose = pose_from_params(best, self.geometry.sod_mm)
        return RegistrationResult(params=best, pose=pose, projection=self.by_factor[1].projection_matrix(pose),
                                  similarity=value, renders=renders, stage_seconds={"polish": time.perf_counter() - t0},
                                  history=[("polish", value, best.tolist())])

    def _polish(self, score, best, lo, hi):
        """The polish from ``best`` inside ``[lo, hi]``, ``score`` the finest level's metric with the
        X-ray bound (:func:`register.engines.metrics.bind_metric`): ``(params, similarity at full
        resolution, renders)``. Its first directions: each angle (0.5 deg) and tx, ty (1 mm), then
        depth along the view ray (2 mm). ``settings.polish_method``: ``"powell"`` (scipy's Powell,
        ``polish_evals``) or ``"pattern"`` (:meth:`_pattern_polish`)."""
        direc = np.diag([0.5, 0.5, 0.5, 1.0, 1.0, 2.0])
        direc[5] = along_view_ray(best, [2.0], self.geometry.sod_mm)[0] - best
        if self.settings.polish_method == "pattern":
            return self._pattern_polish(score, best, lo, hi, direc)
        from scipy.optimize import minimize

        renders = 0

        def polish_cost(x):
            nonlocal renders
            renders += 1
            return -float(score(self.render(np.clip(x, lo, hi), 1))[0])

        res = minimize(polish_cost, best, method="Powell",
                       options={"maxfev": self.settings.polish_evals, "xtol": 1e-3, "ftol": 1e-7, "direc": direc})
        start_cost = polish_cost(best)
        if res.fun <= start_cost:
            return np.clip(res.x, lo, hi), float(-res.fun), renders
        return best, float(-start_cost), renders

    def _pattern_polish(self, score, best, lo, hi, direc):
        """A batched pattern search: at each step size (``direc``'s rows times :data:`PATTERN_SCALES`),
        the 12 poses one step either side of the pose along each direction are rendered and
        scored as one batch; a parabola through each direction's three scores gives its best move,
        and the pose moves to the best of the probes and the combined parabolic move (one more
        render); a step size is swept again while it improves (at most :data:`PATTERN_SWEEPS`
        times). At most ``polish_evals`` evaluations."""
        renders = 0

        def costs(xs):
            nonlocal renders
            xs = np.clip(np.atleast_2d(xs), lo, hi)
            renders += len(xs)
            return -np.asarray(score(self.render(xs, 1)), float), xs

        (f,), (x,) = costs(best)
        x, f = x.copy(), float(f)
        for scale in PATTERN_SCALES:
            for _ in range(PATTERN_SWEEPS):
                if renders + 13 > self.settings.polish_evals:
                    return x, -f, renders
                probes = np.concatenate([x + scale * direc, x - scale * direc])  # (12, 6): + then -
                fp, probes = costs(probes)
                f_plus, f_minus = fp[:6], fp[6:]
                curvature = f_plus + f_minus - 2.0 * f
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = np.where(curvature > 0, 0.5 * (f_minus - f_plus) / curvature,
                                 np.where(f_plus < f_minus, 1.0, -1.0))
                t = np.clip(np.nan_to_num(t), -2.0, 2.0)
                (f_move,), (moved,) = costs(x + scale * (t @ direc))
                k = int(np.argmin(fp))
                if min(f_move, fp[k]) >= f:
                    break
                x, f = (moved.copy(), float(f_move)) if f_move <= fp[k] else (probes[k].copy(), float(fp[k]))
        return x, -f, renders

    def maximise(self, objective, init_params) -> RegistrationResult:
        """CMA-ES as :meth:`register` searches (these settings' levels, box around ``init_params``
        ``(6,)`` deg/mm, steps and generations; no restarts, no polish), on any score of the DRRs:
        ``objective(factor)`` returns the score of a level, ``(B, H/f, W/f)`` DRRs -> ``(B,)``, higher
        better (e.g. two similarities summed, each with its own fixed image bound). The result's
        ``similarity`` is the objective at full resolution (factor 1).

        Example::

            >>> import numpy as np
            >>> from sim import load_ct
            >>> reg = CMAESRegistration(load_ct("phantom"), CMAESSettings(size=(32, 32), levels=(2,), generations=(10,),
            ...                                                       metrics=("gncc",)))
            >>> target = reg.render(np.zeros(6))[0]
            >>> def closeness(f):  # minus the mean absolute difference from the target at factor f
            ...     t = target.reshape(32 // f, f, 32 // f, f).mean(axis=(1, 3))
            ...     return lambda m: -np.abs(m - t).mean(axis=(1, 2))
            >>> r = reg.maximise(closeness, [0, 0, 0, 8.0, 0, 0])
            >>> bool(abs(r.params[3]) < 8.0 and r.similarity > closeness(1)(reg.render([0, 0, 0, 8.0, 0, 0]))[0])
            True
        """
        x0 = np.asarray(init_params, dtype=np.float64).reshape(6)
        if not np.all(np.isfinite(x0)):
            raise RegistrationError(f"the start pose must be finite, got {x0}")
        if not self.in_view(x0)[0]:
            raise RegistrationError("the CT does not overlap the view at the start pose (its DRR is empty)")
        lo, hi = self._box(x0)
        stages: dict[str, float] = {}
        history: list = []
        best, final, renders = self._search(lambda level, factor: objective(factor), x0, lo, hi, self._scale(),
                                            seed=self.settings.seed, popsize=self.settings.popsize, prefix="",
                                            stages=stages, history=history, progress=None, polish=False)
        pose = pose_from_params(best, self.geometry.sod_mm)
        return RegistrationResult(params=best, pose=pose, projection=self.by_factor[1].projection_matrix(pose),
                                  similarity=final, renders=renders, stage_seconds=stages, history=history)

    def _scorer(self, fixed, mask):
        """``score_at(level, factor)``: the settings' similarity of that level with ``fixed``
        ``(H, W)`` and ``mask`` bound at ``factor``'s resolution (:func:`register.engines.metrics.bind_metric_at`)."""
        s = self.settings

        return lambda level, factor: bind_metric_at(s.per_level("metrics", level), fixed, mask, factor)

    def _search(self, score_at, x0, lo, hi, scale, *, seed, popsize, prefix, stages, history, progress,
                polish):
        """One coarse-to-fine CMA-ES search and polish from ``x0``; returns (params, final similarity,
        renders) and appends to ``stages`` / ``history`` under stage names ``prefix + level<i>``."""
        (best, final, renders), = self._search_many(score_at, x0[None], lo[None], hi[None], scale, seed=seed,
                                                    popsize=popsize, prefix=prefix, stages=stages,
                                                    histories=[history], progress=progress, polish=polish)
        return best, final, renders

    def _search_many(self, score_at, x0s, los, his, scale, *, seed, popsize, prefix, stages, histories,
                     progress, polish):
        """Independent coarse-to-fine searches from each row of ``x0s`` ``(K, 6)`` (boxes ``los`` /
        ``his``), scored by ``score_at(level, factor)`` (:meth:`_scorer`), in lockstep: each generation renders every search's population in one batch. Each
        search is the one :meth:`_search` would run alone (same seed). Returns ``[(params, final
        similarity, renders)]`` per start; ``stages`` gets the lockstep's wall time,
        ``histories[k]`` search k's rows."""
        import cma

        s = self.settings
        K = len(x0s)
        bests = [x.copy() for x in x0s]
        renders = [0] * K
        sigma = s.sigma_deg
        for level, factor in enumerate(s.levels):
            t0 = time.perf_counter()
            score = score_at(level, factor)  # the X-ray's part once
            opts = {"popsize": popsize, "seed": seed + 1 + level, "verbose": -9,
                    "maxiter": s.per_level("generations", level), "tolfun": 1e-6, "tolx": 1e-3}
            # each search draws from its own generator (cma's default is numpy's global one, seeded by
            # "seed"): the same samples as alone, whatever the other searches draw
            ess = [cma.CMAEvolutionStrategy(bests[k] / scale, sigma,
                                            {**opts, "bounds": [list(los[k] / scale), list(his[k] / scale)],
                                             "randn": np.random.RandomState(seed + 1 + level).randn})
                   for k in range(K)]
            stage = f"{prefix}level{level}"
            active = [k for k in range(K) if not ess[k].stop()]
            while active:
                zs = [ess[k].ask() for k in active]
                xs = [np.clip(np.asarray(z) * scale, los[k], his[k]) for z, k in zip(zs, active)]
                values = -score(self.render(np.concatenate(xs), factor))
                at = 0
                for z, x, k in zip(zs, xs, active):
                    ess[k].tell(z, values[at:at + len(x)].tolist())
                    at += len(x)
                    renders[k] += len(x)
                    histories[k].append((stage, float(-ess[k].result.fbest), (ess[k].result.xbest * scale).tolist()))
                if progress:
                    progress(stage, max(histories[k][-1][1] for k in active))
                active = [k for k in active if not ess[k].stop()]
            bests = [np.clip(np.asarray(ess[k].result.xbest) * scale, los[k], his[k]) for k in range(K)]
            sigma *= s.sigma_shrink
            stages[stage] = time.perf_counter() - t0
        finest = score_at(len(s.levels) - 1, 1)
        if polish:
            t0 = time.perf_counter()
            out = []
            for k in range(K):
                best, final, n = self._polish(finest, bests[k], los[k], his[k])
                histories[k].append((f"{prefix}polish", final, best.tolist()))
                out.append((best, final, renders[k] + n))
            stages[f"{prefix}polish"] = time.perf_counter() - t0
            return out
        finals = finest(self.render(np.array(bests), 1))
        return [(bests[k], float(finals[k]), renders[k] + 1) for k in range(K)]
