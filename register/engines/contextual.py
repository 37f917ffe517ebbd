"""The contextual pose iteration: a network predicts the geodesic gradient, the pose steps along it.

Fixed source, anatomy-centred poses (docs/conventions.md). At each iteration the DRR at the
current pose T and the X-ray go to a predictor that returns ``g`` = -2 log_T(T_target)
(:func:`learn.labels.geodesic_label`; rotation in rad, translation in mm); the pose moves by
``T <- T o Exp(-step g)`` (:func:`learn.labels.apply_update`, rotation about the anatomy centre,
so the anatomy stays in view). The iteration stops when the predicted step is below
``stop_rot_deg`` and ``stop_trans_mm``, or after ``max_iterations``. ``contextual+cmaes`` then
hands the pose to CMA-ES in a narrowed box, after a global search (:mod:`register.engines.search`) where
the network's pose is lost.

Predictors: :class:`learn.predict.NetworkPredictor` (a trained :class:`learn.model.PoseUpdateNet`
checkpoint; importable from here too) or any callable ``(fixed (H, W), drr (H, W)) -> g (6,)``;
the tests use an oracle that returns the true label, which checks the iteration itself.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from register.engines.cmaes import CMAESRegistration, CMAESSettings, RegistrationError, RegistrationResult
from register.engines.metrics import plain_equivalent
from register.engines.search import GlobalSearch, GlobalSearchSettings


@dataclass(frozen=True)
class ContextualSettings:
    """Units: degrees, mm. ``step`` is the fraction of the predicted gradient taken (0.15 originally);
    the iteration stops when ``step * |g_rot|`` < ``stop_rot_deg`` and ``step * |g_trans|`` <
    ``stop_trans_mm``, or after ``max_iterations``; ``keep_drrs`` keeps every iteration's DRR in
    the result's trajectory (for figures)."""

    step: float = 0.15
    max_iterations: int = 60
    stop_rot_deg: float = 0.05
    stop_trans_mm: float = 0.2
    keep_drrs: bool = False

    def __post_init__(self) -> None:
        if not 0 < self.step <= 1:
            raise RegistrationError(f"step must be in (0, 1], got {self.step}")
        if self.max_iterations < 1:
            raise RegistrationError(f"max_iterations must be >= 1, got {self.max_iterations}")


class ContextualRegistration:
    """The contextual iteration (and its hand-over to CMA-ES) on one CT; see the module doc.

    ``refine``: the CMA-ES settings of the hand-over (narrowed box around the network's pose), or
    None for the contextual iteration alone. ``search`` (with ``refine`` only): the global search
    (:class:`register.engines.search.GlobalSearch`, built from its settings, or one the caller built for
    the same detector and physics, e.g. to share its grid's DRRs with the polarity check
    :func:`register.prepare.confirm_polarity`) between the iteration and the refinement: the
    network's pose is searched locally first and kept when its similarity reaches
    ``search.found_above``; otherwise a grid over the prior box supplies further starts, the
    refinement's CMA-ES runs from each of the search's finalists (its best distinct local results,
    ``search.finalists``), the highest similarity at full resolution wins and only the winner is
    polished (``stage_seconds``, summed over the refinements, and ``history`` record the search;
    the result's ``search`` record adds ``"refined"``, each finalist's similarity before the
    polish, ``"refined_params"``, its pose (deg, mm) then, and ``"chosen"``, the index of the winner). The similarity, not the truth, decides, so a user's registration can take
    it: a network that fails on an image outside its training domain costs time, not the
    registration.
    """

    def __init__(self, volume, predictor, settings: ContextualSettings | None = None, *, size=(128, 128),
                 scene: str = "cios_fusion", geometry=None, center_lps=None, refine: CMAESSettings | None = None,
                 search: GlobalSearchSettings | GlobalSearch | None = None, physics=None,
                 label_materials: dict[int, str] | None = None):
        from sim.anatomy import anatomy_center
        from sim.physics.imaging import moving_renderer

        self.settings = settings or ContextualSettings()
        self.predictor = predictor
        self._view_args = dict(volume=volume, physics=physics, scene=scene, label_materials=label_materials)
        self._view_renderers: dict = {}
        self.center_lps = np.asarray(anatomy_center(volume) if center_lps is None else center_lps, float)
        # the current image at each iteration: physics as CMAESRegistration's ``physics``
        self.renderer = moving_renderer(volume, physics, scene=scene, size=tuple(size), center_lps=self.center_lps,
                                        geometry=geometry, label_materials=label_materials)
        self.geometry = self.renderer.geometry
        self.refine = None
        self.search = None
        if search is not None and refine is None:
            raise RegistrationError("search: the global search needs the refinement (refine settings)")
        if isinstance(search, GlobalSearch):  # built by the caller (its grid shared with the polarity check)
            if not search.built_for(self.geometry, physics):
                raise RegistrationError("search: the given GlobalSearch was built for another detector or physics "
                                        "than this registration's")
            self.search = search
        elif search is not None:
            self.search = GlobalSearch(volume, search, size=size, scene=scene, geometry=geometry,
                                       center_lps=self.center_lps, physics=physics, label_materials=label_materials)
        if refine is not None:
            self.refine = CMAESRegistration(volume, refine, scene=scene, geometry=geometry,
                                            center_lps=self.center_lps, physics=physics,
                                            label_materials=label_materials)

    def _view_renderer(self, geometry):
        """The moving-image renderer of a network view's detector (made once per geometry)."""
        from sim.physics.imaging import moving_renderer

        key = (geometry.height, geometry.width, geometry.pixel_spacing_mm, geometry.principal_point,
               geometry.sdd_mm, geometry.sod_mm)
        if key not in self._view_renderers:
            a = self._view_args
            self._view_renderers[key] = moving_renderer(a["volume"], a["physics"], scene=a["scene"],
                                                        size=(geometry.height, geometry.width),
                                                        center_lps=self.center_lps, geometry=geometry,
                                                        label_materials=a["label_materials"])
        return self._view_renderers[key]

    def register(self, fixed: np.ndarray, init_params=np.zeros(6), *, mask: np.ndarray | None = None,
                 toned: np.ndarray | None = None, network_view: "NetworkView | None" = None) -> RegistrationResult:
        """Register ``fixed`` ``(H, W)`` (preprocessed like the DRRs: bone bright) from ``init_params``
        (deg, mm). ``mask`` ``(H, W)`` bool: the valid pixels (collimated field). The predictor then
        sees the X-ray with the pixels outside the mask filled by the valid pixels' mean
        (:func:`register.prepare.masked_fill`: no contrast of its own), and the DRR filled the same
        way (the same field edge in both images, so the edge says nothing about the pose) unless
        the predictor's ``current_field`` is ``"open"`` (a network trained to see the anatomy
        around the field); CMA-ES and the final similarity use the valid pixels only. ``toned``
        ``(H, W)``: the X-ray's toned version (:attr:`register.prepare.PreparedXRay.toned`) or None;
        the global search ranks its grid on it too, and a network trained on toned targets (its
        checkpoint's ``tone`` is ``"ct"``) sees it instead of ``fixed``. ``network_view``: what a
        network framed by the detector (its ``framing`` is ``"detector"``) sees instead of
        ``fixed``: the X-ray's whole detector at the network's size with its field
        (:class:`NetworkView`, :func:`network_view`); the network's DRRs are then rendered for that
        detector, and ``fixed``, ``mask`` and the renderer of this registration serve CMA-ES and
        the similarity only."""
        from learn.labels import apply_update
        from register.prepare import masked_fill
        from sim.geometry import params_from_pose, pose_from_params

        s = self.settings
        fixed = np.asarray(fixed, np.float64)
        if mask is not None:
            mask = np.asarray(mask, bool)
            if mask.shape != fixed.shape or not mask.any():
                raise RegistrationError(f"mask: expected a non-empty bool array of shape {fixed.shape}, "
                                        f"got {mask.shape} with {int(mask.sum())} valid pixels")
        if toned is not None and np.shape(toned) != fixed.shape:
            raise RegistrationError(f"toned: expected the X-ray's shape {fixed.shape}, got {np.shape(toned)}")
        toned_net = toned is not None and getattr(self.predictor, "tone", "off") == "ct"
        net_fixed = masked_fill(np.asarray(toned, np.float64) if toned_net else fixed, mask)
        net_mask, view_renderer = mask, None
        if network_view is not None:  # a detector-framed network: the whole detector, the field masked
            net_mask = network_view.mask
            net_fixed = masked_fill(network_view.image, net_mask)
            view_renderer = self._view_renderer(network_view.geometry)
        # a network trained on open current images sees the DRR's anatomy around the field too
        open_current = getattr(self.predictor, "current_field", "masked") == "open"
        T = pose_from_params(np.asarray(init_params, float).reshape(6), self.geometry.sod_mm)
        history, drrs, visited, grads = [], [], [], []
        t0 = time.perf_counter()
        renders = 0
        for _ in range(s.max_iterations):
            drr = self.renderer.render(T)[0] if view_renderer is None or s.keep_drrs else None
            net_drr = drr if view_renderer is None else view_renderer.render(T)[0]
            renders += 1 + (drr is not None and view_renderer is not None)
            if s.keep_drrs:
                drrs.append(drr)
            g = np.asarray(self.predictor(net_fixed, net_drr if open_current else masked_fill(net_drr, net_mask)),
                           float).reshape(6)
            if not np.all(np.isfinite(g)):
                raise RegistrationError(f"the predictor returned a non-finite gradient {g.tolist()}")
            params_now = params_from_pose(T, self.geometry.sod_mm)
            visited.append(params_now)
            grads.append(g)
            rot_deg = np.degrees(s.step * np.linalg.norm(g[:3]))
            trans_mm = s.step * np.linalg.norm(g[3:])
            history.append(("contextual", -float(rot_deg + trans_mm), params_now.tolist()))
            if rot_deg < s.stop_rot_deg and trans_mm < s.stop_trans_mm:
                break
            T = apply_update(T, g, s.step)
        stages = {"contextual": time.perf_counter() - t0}
        params = params_from_pose(T, self.geometry.sod_mm)
        trajectory = {"params": np.array(visited + [params]), "g": np.array(grads)}
        if s.keep_drrs:
            trajectory["drrs"] = np.array(drrs)
        if self.refine is not None:
            starts, found = [params], None
            if self.search is not None:
                found = self.search.register(fixed, init_params, mask=mask, poses=[params], toned=toned)
                starts = [np.asarray(f["params"], float) for f in found.search["finalists"]]
                stages.update(found.stage_seconds)
                history += found.history
                renders += found.renders
            # each start refined (CMA-ES, no polish); the highest similarity at full resolution wins
            # (ties: the earlier start) and only the winner is polished
            res, finals, cmaes_s, won = None, [], {}, 0
            several = len(starts) > 1
            # a display image (with a toned version) is scored display-tolerantly, line integrals plainly
            refine = self.refine if toned is not None else self.refine.scored_by(
                tuple(plain_equivalent(m) for m in self.refine.settings.metrics))
            refined = (refine.register_many(fixed, starts, mask=mask, polish=False) if several
                       else [refine.register(fixed, starts[0], mask=mask)])
            for i, r in enumerate(refined):
                finals.append(float(r.similarity))
                for k, v in r.stage_seconds.items():
                    cmaes_s[f"cmaes_{k}"] = cmaes_s.get(f"cmaes_{k}", 0.0) + v
                history += [(stage if i == 0 else f"finalist{i}.{stage}", v, p) for stage, v, p in r.history]
                renders += r.renders
                if res is None or r.similarity > res.similarity:
                    res, won = r, i
            if several and refine.settings.polish:
                polished = refine.polish(fixed, res.params, start=starts[won], mask=mask)
                cmaes_s["cmaes_polish"] = polished.stage_seconds["polish"]
                history += polished.history
                renders += polished.renders
                res = polished
            res.stage_seconds = {**stages, **cmaes_s}
            res.history = history
            res.renders = renders
            res.trajectory = trajectory
            if found is not None:
                res.search = {**found.search, "refined": finals, "chosen": int(np.argmax(finals)),
                              "refined_params": [np.asarray(r.params, float).tolist() for r in refined]}
            return res
        from register.engines.metrics import gradient_ncc

        sim_value = float(gradient_ncc(fixed, self.renderer.render(T), mask=mask)[0])
        return RegistrationResult(params=params, pose=T, projection=self.renderer.projection_matrix(T),
                                  similarity=sim_value, renders=renders + 1, stage_seconds=stages,
                                  history=history, trajectory=trajectory)


#: The narrowed CMA-ES box after the contextual iteration (degrees, mm): one level at 1/2 resolution,
#: then the polish at full resolution. A first level at 1/4 resolution (as CMA-ES from afar uses)
#: pulled right starts away on realistic frames, whose coarse gradients mislead (scatter, display
#: chain): 5 of 7 lost ``fluoro-65kV`` frames were right before the refinement and kept with this one.
#: The similarity of a display image (one registered with its toned version) is the tone-tolerant
#: gradient NCC (:func:`register.engines.metrics.tone_tolerant_gradient_ncc`): half of it blind to the
#: display's curve. An image of line integrals (a raw or log X-ray, a DRR) is scored by gradient NCC:
#: on 50 line DRRs the tone-tolerant score lost a case (98 % against 100 %) and cost 0.5 s.
REFINE_SETTINGS = CMAESSettings(levels=(2,), sigma_deg=3.0, sigma_mm=8.0, range_deg=10.0, range_mm=30.0,
                                generations=(40,), metrics=("tone_tolerant_gncc",))


@dataclass(frozen=True)
class NetworkView:
    """What a detector-framed network (``train.framing = "detector"``) sees of an X-ray: its whole
    detector at the network's size. ``image`` ``(h, w)`` the preprocessed X-ray, ``mask`` ``(h, w)``
    bool its valid pixels (the field), ``geometry`` the :class:`sim.geometry.CArmGeometry` of
    those pixels (the network's DRRs are rendered for it)."""

    image: np.ndarray
    mask: np.ndarray
    geometry: object


def network_view(predictor, prepared) -> NetworkView | None:
    """The :class:`NetworkView` of a prepared X-ray (:class:`register.prepare.PreparedXRay`) for
    ``predictor`` when it is framed by the detector (its ``framing``); None otherwise (the network
    sees the X-ray cropped to its field, as CMA-ES does). The whole detector is fitted into the
    network's image size, aspect kept (:func:`register.prepare.fit_to_size`)."""
    if getattr(predictor, "framing", "field") != "detector":
        return None
    from register.prepare import fit_to_size

    size = getattr(predictor, "size", None) or (64, 64)
    image, mask, geometry = fit_to_size(prepared.full_image, prepared.full_mask, prepared.full_geometry, size)
    if mask is None or not mask.any():
        raise RegistrationError("the X-ray's field holds no valid pixel at the network's size")
    return NetworkView(np.asarray(image, np.float64), np.asarray(mask, bool), geometry)
