"""contextual+cmaes as one pipeline: the network's iteration, the global search, CMA-ES from each
start, the winner polished.

:class:`ContextualPipeline` runs its named steps in order (:meth:`ContextualPipeline.register`):

1. :meth:`~ContextualPipeline.iterate`: the contextual iteration
   (:class:`register.engines.contextual.ContextualRegistration`) from the start pose;
1b. :meth:`~ContextualPipeline.trusted`: where the caller gives a ``trust`` (``register_xray``: the
   verdict, :mod:`register.verdict`), the network's pose is refined first as without a search
   (+-:data:`NETWORK_DEPTH_RANGE_MM` in depth) and, where it reaches ``search.refined_above``,
   judged: a pose ``trust`` accepts is the result,
   the grid skipped (the search record's ``trusted``); otherwise the steps below run as without it;
2. :meth:`~ContextualPipeline.starts`: the global search (:class:`register.engines.search.GlobalSearch`)
   searches the network's pose locally and keeps it when its similarity reaches
   ``search.found_above``; otherwise a grid over the prior box supplies further starts, and the
   search's finalists (its best distinct local results, ``search.finalists``) are the starts.
   Without a search the network's pose is the one start;
3. :meth:`~ContextualPipeline.refine`: CMA-ES in a narrowed box (:data:`REFINE_SETTINGS`; without
   a search, +-:data:`NETWORK_DEPTH_RANGE_MM` in depth) from each start (no polish where there are
   several); the highest similarity at full resolution wins (ties: the earlier start);
   Where the grid was skipped but the network's pose, refined, ends below ``search.refined_above``
   by the refinement's score, :meth:`~ContextualPipeline.grid_after` runs the grid after all from
   the refined pose, and step 3 refines its finalists;
4. :meth:`~ContextualPipeline.polish`: only the winner is polished (several starts; the refinement's
   polish is the batched pattern search, ``REFINE_SETTINGS.polish_method``);
5. :meth:`~ContextualPipeline.result`: the winner with the whole run's stage times (summed over
   the refinements), history, renders, the iteration's trajectory and the search's record (adding
   ``"refined"``, each finalist's similarity before the polish, ``"refined_params"``, its pose (deg,
   mm) then, and ``"chosen"``, the index of the winner);
6. :meth:`~ContextualPipeline.rescue`: where the winner's edges agree as a whole but not window by
   window (its local similarity below ``search.local_below``: a few strong edges, such as a body's
   outline over air, carry the whole image's similarity), the search runs again by local
   similarity and its finalists are refined by it; the pose it finds replaces the winner where its
   local similarity reaches ``local_below`` and beats the winner's.

The similarity, not the truth, decides, so a user's registration can take it: a network that fails
on an image outside its training domain costs time, not the registration.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from register.engines.cmaes import CMAESRegistration, CMAESSettings
from register.engines.contextual import ContextualRegistration, ContextualSettings, Iteration, checked_inputs
from register.engines.metrics import NoWindowError, local_gradient_ncc, plain_equivalent
from register.engines.result import RegistrationError, RegistrationResult
from register.engines.search import GlobalSearch, GlobalSearchSettings

__all__ = ["ContextualPipeline", "NETWORK_DEPTH_RANGE_MM", "REFINE_SETTINGS", "local_similarity", "rescue",
           "scored_as_refined"]

#: The narrowed CMA-ES box after the contextual iteration (degrees, mm): one level at 1/2 resolution,
#: then the polish at full resolution. A first level at 1/4 resolution (as CMA-ES from afar uses)
#: pulled right starts away on realistic frames, whose coarse gradients mislead (scatter, display
#: chain): 5 of 7 lost ``fluoro-65kV`` frames were right before the refinement and kept with this one.
#: The similarity of a display image (one registered with its toned version) is the tone-tolerant
#: gradient NCC (:func:`register.engines.metrics.tone_tolerant_gradient_ncc`): half of it blind to the
#: display's curve. An image of line integrals (a raw or log X-ray, a DRR) is scored by gradient NCC:
#: on 50 line DRRs the tone-tolerant score lost a case (98 % against 100 %) and cost 0.5 s.
#: Its polish is the batched pattern search (``polish_method="pattern"``): on 10 frames each of
#: fluoro-65kV, inverted-110kV, radiograph-125kV and linear-70kV it kept every success of Powell's
#: and a mean mTRE within 0.2 mm of it, 1.5-2 s sooner (docs/benchmarks.md, "A registration's seconds").
REFINE_SETTINGS = CMAESSettings(levels=(2,), sigma_deg=3.0, sigma_mm=8.0, range_deg=10.0, range_mm=30.0,
                                generations=(40,), metrics=("tone_tolerant_gncc",), polish_method="pattern")

#: The refinement's half-width in depth ``tz`` (mm) around the network's own pose, where no global
#: search ran (``search="off"``): three times the in-plane box, as the network's depth, read from the
#: magnification alone, is off by 20-75 mm where its in-plane translation is off by 0-13 mm
#: (docs/journal/results.md, "The refinement's box in depth"), and the 30 mm box left such starts on its
#: edge. Its first step stays the translations' 8 mm (CMA-ES lengthens it where the way is long;
#: three times that step sent one of 50 line DRRs into another basin). After a search its starts'
#: depths are searched already (the grid spans +-75 mm), and the narrower box stays: the wide one let
#: a start of a frame whose field was misread follow its similarity 20 mm off in depth.
NETWORK_DEPTH_RANGE_MM = 90.0


def scored_as_refined(refinement: CMAESRegistration, toned) -> CMAESRegistration:
    """``refinement`` as the refinement scores an X-ray: a display image (with a ``toned`` version)
    display-tolerantly, line integrals (``toned`` None) with the plain equivalents of its metrics."""
    if toned is not None:
        return refinement
    return refinement.scored_by(tuple(plain_equivalent(m) for m in refinement.settings.metrics))


#: :meth:`ContextualPipeline.starts`' answer where ``before_grid`` stopped the search.
_STOPPED = object()


class ContextualPipeline:
    """contextual+cmaes on one CT (module doc). ``refine``: the CMA-ES settings of the refinement
    (the narrowed box around each start). ``search``: the global search
    (:class:`register.engines.search.GlobalSearch`, built from its settings, or one the caller built
    for the same detector and physics, e.g. to share its grid's DRRs with the polarity check
    :func:`register.xray.prepare.confirm_polarity`), or None: the network's pose goes straight to the
    refinement, whose box in depth is then +-:data:`NETWORK_DEPTH_RANGE_MM` unless ``refine`` sets
    ``range_depth_mm``. The other arguments are :class:`register.engines.contextual.ContextualRegistration`'s."""

    def __init__(self, volume, predictor, settings: ContextualSettings | None = None, *, refine: CMAESSettings,
                 size=(128, 128), scene: str = "cios_fusion", geometry=None, center_lps=None,
                 search: GlobalSearchSettings | GlobalSearch | None = None, physics=None,
                 label_materials: dict[int, str] | None = None):
        if refine is None:
            raise RegistrationError("refine: the pipeline needs the refinement's CMA-ES settings")
        self.contextual = ContextualRegistration(volume, predictor, settings, size=size, scene=scene,
                                                 geometry=geometry, center_lps=center_lps, physics=physics,
                                                 label_materials=label_materials)
        self.geometry = self.contextual.geometry
        self.center_lps = self.contextual.center_lps
        self.search = None
        if isinstance(search, GlobalSearch):  # built by the caller (its grid shared with the polarity check)
            if not search.built_for(self.geometry, physics):
                raise RegistrationError("search: the given GlobalSearch was built for another detector or physics "
                                        "than this registration's")
            self.search = search
        elif search is not None:
            self.search = GlobalSearch(volume, search, size=size, scene=scene, geometry=geometry,
                                       center_lps=self.center_lps, physics=physics, label_materials=label_materials)
        alone = refine if refine.range_depth_mm is not None else replace(refine, range_depth_mm=NETWORK_DEPTH_RANGE_MM)
        self.refinement = CMAESRegistration(volume, refine if self.search is not None else alone, scene=scene,
                                            geometry=geometry, center_lps=self.center_lps, physics=physics,
                                            label_materials=label_materials)
        #: the refinement of the network's pose as it is (its depth least sure): without a search, and
        #: where a ``trust`` judges it before the search (:meth:`trusted`)
        self.network_refinement = self.refinement if self.search is None else self.refinement.adjusted(
            range_depth_mm=alone.range_depth_mm)

    @property
    def renderer(self):
        """The iteration's moving-image renderer (the optimiser's detector)."""
        return self.contextual.renderer

    def register(self, fixed: np.ndarray, init_params=np.zeros(6), *, mask: np.ndarray | None = None,
                 toned: np.ndarray | None = None, network_view=None,
                 before_grid: Callable[[], bool] | None = None,
                 trust: Callable[[RegistrationResult], bool] | None = None) -> RegistrationResult | None:
        """Register ``fixed`` ``(H, W)`` from ``init_params`` (deg, mm): the steps of the module doc.
        ``mask``, ``toned`` and ``network_view`` as
        :meth:`register.engines.contextual.ContextualRegistration.register`; CMA-ES and the final
        similarity use the valid pixels only, and the global search ranks its grid on ``toned`` too.
        ``before_grid``: :meth:`register.engines.search.GlobalSearch.register`'s; where it stops the
        search, the registration stops too and returns None. ``trust``: whether to keep the
        network's pose, refined, without the search (:meth:`trusted`; None: the search decides;
        not asked where the search always runs its grid)."""
        fixed, mask = checked_inputs(fixed, mask, toned)
        it = self.iterate(fixed, init_params, mask=mask, toned=toned, network_view=network_view)
        tried = None
        if trust is not None and self.search is not None and not self.search.settings.always_grid:
            tried = self.trusted(fixed, it, trust, mask=mask, toned=toned)
            if tried.search["trusted"]:
                return tried
        found = self.starts(fixed, init_params, it, mask=mask, toned=toned, before_grid=before_grid)
        if found is _STOPPED:
            return None
        starts = [it.params] if found is None else [np.asarray(f["params"], float) for f in found.search["finalists"]]
        refine = self.scored(toned)
        refined = self.refine(refine, fixed, starts, mask=mask)
        if found is not None and not found.search["grid_poses"] and refined[0].similarity < self.search.settings.refined_above:
            found = self.grid_after(fixed, init_params, found, refined[0], mask=mask, toned=toned, before_grid=before_grid)
            if found is _STOPPED:
                return None
            starts = [np.asarray(f["params"], float) for f in found.search["finalists"]]
            refined = self.refine(refine, fixed, starts, mask=mask)
        won = self.winner(refined)
        polished = self.polish(refine, fixed, refined[won], starts[won], mask=mask) if len(starts) > 1 else None
        res = self.result(it, found, refined, won, polished)
        if tried is not None:  # the trial's seconds and renders count; the record says it was not trusted
            res.stage_seconds = {**{f"trust_{k}": v for k, v in tried.stage_seconds.items() if k.startswith("cmaes_")},
                                 **res.stage_seconds}
            res.renders += tried.renders
            res.search = {**res.search, "trusted": False, "trust_similarity": tried.similarity}
        return self.rescue(fixed, init_params, res, mask=mask, toned=toned)

    def trusted(self, fixed, it: Iteration, trust: Callable[[RegistrationResult], bool], *, mask=None,
                toned=None) -> RegistrationResult:
        """Step 1b: the network's pose ``it.params`` refined as without a search
        (:attr:`network_refinement`, scored as the refinement scores this X-ray) and judged by
        ``trust`` where it reaches ``search.refined_above`` by that score (below it ``trust`` is not
        asked, as the search's own skip would run the grid after all, :meth:`grid_after`). The
        result's search record says what happened: ``trusted`` (whether ``trust``
        accepted it: then the grid is skipped and this is the registration), ``grid_poses`` 0,
        ``start`` ``"given"``, the refined pose as its one finalist, ``found_above`` the search's.
        A pose the search's local step would have accepted is still judged, so that a right pose
        whose display lifts or lowers its similarity is kept by the evidence, not by one number."""
        refined = self.refine(scored_as_refined(self.network_refinement, toned), fixed, [it.params], mask=mask)
        res = self.result(it, None, refined, 0, None)
        params = np.asarray(res.params, float).tolist()
        res.search = {"given_similarity": None, "given_score": None, "given_clipped": False,
                      "found_above": self.search.settings.found_above, "always_grid": False, "local": False,
                      "grid_poses": 0, "candidates": 0, "start": "given", "similarity": float(res.similarity),
                      "grid_render_s": 0.0, "grid_ncc_s": 0.0,
                      "finalists": [{"params": params, "similarity": float(res.similarity), "start": "given"}],
                      "refined": [float(res.similarity)], "chosen": 0, "refined_params": [params]}
        # below refined_above the search's own skip runs the grid after all (grid_after): the verdict
        # is not asked to keep such a pose alone (a linear display's pose 78 mm off in depth at 0.859
        # passed every check, where the grid's pose 45 mm nearer scored the same and was doubted)
        res.search["trusted"] = bool(res.similarity >= self.search.settings.refined_above and trust(res))
        return res

    def rescue(self, fixed, init_params, res: RegistrationResult, *, mask=None, toned=None) -> RegistrationResult:
        """Step 6 (:func:`rescue`) with this pipeline's search and refinement; ``res`` as it is
        without a search."""
        if self.search is None:
            return res
        return rescue(self.search, self.refinement, fixed, init_params, res, mask=mask, toned=toned)

    def iterate(self, fixed, init_params, *, mask=None, toned=None, network_view=None) -> Iteration:
        """Step 1: the network's iteration."""
        return self.contextual.iterate(fixed, init_params, mask=mask, toned=toned, network_view=network_view)

    def starts(self, fixed, init_params, it: Iteration, *, mask=None, toned=None, before_grid=None):
        """Step 2: the global search from the network's pose (its result, whose record's
        ``finalists`` are the refinement's starts), None without a search, or ``_STOPPED`` where
        ``before_grid`` stopped it."""
        if self.search is None:
            return None
        found = self.search.register(fixed, init_params, mask=mask, poses=[it.params], toned=toned,
                                     before_grid=before_grid)
        return _STOPPED if found is None else found

    def grid_after(self, fixed, init_params, skipped: RegistrationResult, refined: RegistrationResult, *,
                   mask=None, toned=None, before_grid=None):
        """Step 3b: the network's pose reached ``search.found_above`` (the grid skipped), but its
        refinement ended below ``search.refined_above`` by the refinement's own score (the
        tone-tolerant one of a display image: the plain score had been lifted by the display's
        curve, or the refinement moved off):
        the grid runs after all, the refined pose its given one, as where the network's pose had
        scored less. Returns that search (its record's ``after_refinement``: the refined
        similarity that sent it; the skipped search's and the first refinement's seconds and
        renders counted in), or ``_STOPPED`` where ``before_grid`` stopped it. On the
        verdict's rows 7 of the 73 default registrations that skipped the grid ended so
        (docs/results.md)."""
        found = self.search.register(fixed, init_params, mask=mask, poses=[refined.params], toned=toned,
                                     before_grid=before_grid, grid=True)
        if found is None:
            return _STOPPED
        stages = dict(found.stage_seconds)
        for k, v in skipped.stage_seconds.items():
            stages[k] = stages.get(k, 0.0) + v
        stages["cmaes_before_grid"] = sum(refined.stage_seconds.values())
        found.stage_seconds = stages
        found.history = [*skipped.history, *refined.history, *found.history]
        found.renders += skipped.renders + refined.renders
        found.search = {**found.search, "after_refinement": float(refined.similarity),
                        "refined_above": self.search.settings.refined_above}
        return found

    def scored(self, toned) -> CMAESRegistration:
        """The refinement's CMA-ES as it scores this X-ray (:func:`scored_as_refined`)."""
        return scored_as_refined(self.refinement, toned)

    @staticmethod
    def refine(refine: CMAESRegistration, fixed, starts: list, *, mask=None) -> list[RegistrationResult]:
        """Step 3: CMA-ES from each start (several in lockstep, unpolished; one start polished)."""
        if len(starts) > 1:
            return refine.register_many(fixed, starts, mask=mask, polish=False)
        return [refine.register(fixed, starts[0], mask=mask)]

    @staticmethod
    def winner(refined: list[RegistrationResult]) -> int:
        """The index of the highest similarity at full resolution (ties: the earlier start)."""
        won = 0
        for i, r in enumerate(refined):
            if r.similarity > refined[won].similarity:
                won = i
        return won

    @staticmethod
    def polish(refine: CMAESRegistration, fixed, best: RegistrationResult, start, *, mask=None
               ) -> RegistrationResult | None:
        """Step 4: the winner of several starts polished (None where the settings have no polish)."""
        if not refine.settings.polish:
            return None
        return refine.polish(fixed, best.params, start=start, mask=mask)

    @staticmethod
    def result(it: Iteration, found: RegistrationResult | None, refined: list[RegistrationResult], won: int,
               polished: RegistrationResult | None) -> RegistrationResult:
        """Step 5: the winner (polished where it was) with the whole run's record."""
        stages, history, renders = dict(it.stage_seconds), list(it.history), it.renders
        if found is not None:
            stages.update(found.stage_seconds)
            history += found.history
            renders += found.renders
        cmaes_s: dict[str, float] = {}
        for i, r in enumerate(refined):
            for k, v in r.stage_seconds.items():
                cmaes_s[f"cmaes_{k}"] = cmaes_s.get(f"cmaes_{k}", 0.0) + v
            history += [(stage if i == 0 else f"finalist{i}.{stage}", v, p) for stage, v, p in r.history]
            renders += r.renders
        res = refined[won]
        if polished is not None:
            cmaes_s["cmaes_polish"] = polished.stage_seconds["polish"]
            history += polished.history
            renders += polished.renders
            res = polished
        res.stage_seconds = {**stages, **cmaes_s}
        res.history = history
        res.renders = renders
        res.trajectory = it.trajectory
        if found is not None:
            finals = [float(r.similarity) for r in refined]
            res.search = {**found.search, "refined": finals, "chosen": int(np.argmax(finals)),
                          "refined_params": [np.asarray(r.params, float).tolist() for r in refined]}
        return res


def local_similarity(refinement: CMAESRegistration, fixed, params, *, mask=None) -> float:
    """The local similarity (:func:`register.engines.metrics.local_gradient_ncc`) of ``fixed``
    ``(H, W)`` with ``refinement``'s moving image at ``params`` (deg, mm); NaN where the field is
    smaller than one window."""
    try:
        return float(local_gradient_ncc(fixed, refinement.render(np.asarray(params, float).reshape(1, 6)),
                                        mask=mask)[0])
    except NoWindowError:
        return float("nan")


def rescue(search: GlobalSearch, refinement: CMAESRegistration, fixed, init_params, res: RegistrationResult, *,
           mask=None, toned=None) -> RegistrationResult:
    """The pipeline's step 6: ``res`` (its winner, registered from ``init_params``) searched again by
    local similarity where its own (:func:`local_similarity`) is below ``search.settings.local_below``:
    the grid of locally normalized gradients and local searches by local similarity
    (:meth:`register.engines.search.GlobalSearch.register` with ``local=True``), its finalists refined
    by local similarity (``refinement``'s box and level, scored by ``"local_gncc"``). The best of
    them by local similarity replaces ``res`` where it reaches ``local_below`` and beats ``res``'s:
    its ``similarity`` and the search record's ``refined`` are then local similarities (the score
    that found it, which the verdict then judges it by: :func:`register.verdict.judge_result`); its ``history``
    is ``res``'s and then the second search's and refinements' (local similarities), their stages
    named ``rescue.search`` and ``rescue.finalist<i>.<level>``. The record's
    ``"rescue"`` says what happened (``local_before``, ``local_after``, ``local_below``, ``kept``:
    ``"rescued"`` or ``"first"``, ``seconds``; rescued: ``first_params``, ``first_similarity``),
    ``stage_seconds["rescue"]`` its time. Where ``res`` reaches ``local_below`` (or its field is
    smaller than one window), ``res`` as it is.

    A pose that the whole image's similarity holds by one strong edge is another answer than the
    one the edges window by window give: on realistic frames of linear and bright displays the
    first was 25-150 mm off where the second was within 2 mm (docs/results.md)."""
    below = search.settings.local_below
    before = local_similarity(refinement, fixed, res.params, mask=mask)
    if not before < below:  # NaN (no window): nothing to compare window by window
        return res
    t0 = time.perf_counter()
    record = {"local_below": below, "local_before": before}

    def kept_first(after):
        seconds = time.perf_counter() - t0
        res.search = {**(res.search or {}), "rescue": {**record, "local_after": after, "kept": "first",
                                                     "seconds": seconds}}
        res.stage_seconds = {**res.stage_seconds, "rescue": seconds}
        return res

    try:
        found = search.register(fixed, init_params, mask=mask, poses=[res.params], toned=toned, local=True)
        starts = [np.asarray(f["params"], float) for f in found.search["finalists"]]
        refined = ContextualPipeline.refine(refinement.scored_by(("local_gncc",)), fixed, starts, mask=mask)
    except NoWindowError:  # a field too small for the local windows at the search's coarse levels
        return kept_first(None)
    won = ContextualPipeline.winner(refined)
    after = local_similarity(refinement, fixed, refined[won].params, mask=mask)
    if not (after >= below and after > before):
        return kept_first(after)
    scores = [float(r.similarity) for r in refined]
    out = refined[won]
    out.trajectory = res.trajectory
    out.history = [*res.history, *[(f"rescue.{stage}", v, q) for stage, v, q in found.history],
                   *[(f"rescue.finalist{i}.{stage}", v, q) for i, r in enumerate(refined) for stage, v, q in r.history]]
    out.renders = res.renders + found.renders + sum(r.renders for r in refined)
    seconds = time.perf_counter() - t0
    out.stage_seconds = {**res.stage_seconds, "rescue": seconds}
    out.search = {**found.search, "refined": scores, "chosen": won,
                  "refined_params": [np.asarray(r.params, float).tolist() for r in refined],
                  "rescue": {**record, "local_after": after, "kept": "rescued", "seconds": seconds,
                             "first_params": np.asarray(res.params, float).tolist(),
                             "first_similarity": float(res.similarity)}}
    return out
