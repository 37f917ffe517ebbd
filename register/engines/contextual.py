"""The contextual pose iteration: a network predicts the geodesic gradient, the pose steps along it.

Fixed source, anatomy-centred poses (docs/conventions.md). At each iteration the DRR at the
current pose T and the X-ray go to a predictor that returns ``g`` = -2 log_T(T_target)
(:func:`learn.labels.geodesic_label`; rotation in rad, translation in mm); the pose moves by
``T <- T o Exp(-step g)`` (:func:`learn.labels.apply_update`, rotation about the anatomy centre,
so the anatomy stays in view). The iteration stops when the predicted step is below
``stop_rot_deg`` and ``stop_trans_mm``, or after ``max_iterations``. ``contextual+cmaes``
(:class:`register.engines.pipeline.ContextualPipeline`) then hands the pose to CMA-ES in a narrowed
box, after a global search (:mod:`register.engines.search`) where the network's pose is lost.

Predictors: :class:`learn.predict.NetworkPredictor` (a trained :class:`learn.model.PoseUpdateNet`
checkpoint) or any callable ``(fixed (H, W), drr (H, W)) -> g (6,)``; the tests use an oracle that
returns the true label, which checks the iteration itself.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from register.engines.metrics import gradient_ncc
from register.engines.result import RegistrationError, RegistrationResult
from sim.projection.geometry import params_from_pose, pose_from_params
from sim.prepare import masked_fill
from sim.ct.anatomy import anatomy_center
from sim.physics.imaging import moving_renderer

__all__ = ["ContextualSettings", "ContextualRegistration", "Iteration", "checked_inputs"]


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


def _detector_key(geometry) -> tuple:
    """What makes two detectors render the same DRR: size, spacing, principal point, distances."""
    return (geometry.height, geometry.width, geometry.pixel_spacing_mm, tuple(geometry.principal_point),
            geometry.sdd_mm, geometry.sod_mm)


def checked_inputs(fixed: np.ndarray, mask: np.ndarray | None, toned: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """``fixed`` as float64 and ``mask`` as bool, checked against each other and ``toned``'s shape
    (:class:`RegistrationError` naming the input)."""
    fixed = np.asarray(fixed, np.float64)
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != fixed.shape or not mask.any():
            raise RegistrationError(f"mask: expected a non-empty bool array of shape {fixed.shape}, "
                                    f"got {mask.shape} with {int(mask.sum())} valid pixels")
    if toned is not None and np.shape(toned) != fixed.shape:
        raise RegistrationError(f"toned: expected the X-ray's shape {fixed.shape}, got {np.shape(toned)}")
    return fixed, mask


@dataclass
class Iteration:
    """Where the network's iteration ended (``T`` ``(4, 4)``, ``params`` ``(6,)`` deg/mm) and what it
    did: ``history`` rows (stage, -(predicted step), params), ``renders``, ``stage_seconds``
    (``{"contextual": s}``) and ``trajectory`` (:attr:`register.engines.result.RegistrationResult.trajectory`)."""

    T: np.ndarray
    params: np.ndarray
    history: list
    renders: int
    stage_seconds: dict
    trajectory: dict


class ContextualRegistration:
    """The contextual iteration on one CT (method ``contextual``); see the module doc.
    :class:`register.engines.pipeline.ContextualPipeline` (``contextual+cmaes``) runs it first."""

    def __init__(self, volume, predictor, settings: ContextualSettings | None = None, *, size=(128, 128),
                 scene: str = "cios_fusion", geometry=None, center_lps=None, physics=None,
                 label_materials: dict[int, str] | None = None):

        self.settings = settings or ContextualSettings()
        self.predictor = predictor
        self._view_args = dict(volume=volume, physics=physics, scene=scene, label_materials=label_materials)
        self._view_renderers: dict = {}
        self.center_lps = np.asarray(anatomy_center(volume) if center_lps is None else center_lps, float)
        # the current image at each iteration: physics as CMAESRegistration's ``physics``
        self.renderer = moving_renderer(volume, physics, scene=scene, size=tuple(size), center_lps=self.center_lps,
                                        geometry=geometry, label_materials=label_materials)
        self.geometry = self.renderer.geometry

    def _view_renderer(self, geometry):
        """The moving-image renderer of a network view's detector (made once per geometry)."""

        key = _detector_key(geometry)
        if key not in self._view_renderers:
            a = self._view_args
            self._view_renderers[key] = moving_renderer(a["volume"], a["physics"], scene=a["scene"],
                                                        size=(geometry.height, geometry.width),
                                                        center_lps=self.center_lps, geometry=geometry,
                                                        label_materials=a["label_materials"])
        return self._view_renderers[key]

    def iterate(self, fixed: np.ndarray, init_params, *, mask: np.ndarray | None = None,
                toned: np.ndarray | None = None, network_view=None) -> Iteration:
        """The iteration from ``init_params`` (deg, mm) on ``fixed`` and ``mask`` as
        :func:`checked_inputs` returns them (``toned``, ``network_view``: see :meth:`register`)."""
        from learn.labels import apply_update  # torch: imported on use

        s = self.settings
        toned_net = toned is not None and getattr(self.predictor, "tone", "off") == "ct"
        net_fixed = masked_fill(np.asarray(toned, np.float64) if toned_net else fixed, mask)
        net_mask, view_renderer = mask, None
        if network_view is not None:  # what the network sees (register.xray.network_view)
            net_mask = network_view.mask
            net_fixed = masked_fill(network_view.image, net_mask)
            if _detector_key(network_view.geometry) != _detector_key(self.geometry):  # the whole detector
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
        return Iteration(T=T, params=params, history=history, renders=renders, stage_seconds=stages,
                         trajectory=trajectory)

    def register(self, fixed: np.ndarray, init_params=np.zeros(6), *, mask: np.ndarray | None = None,
                 toned: np.ndarray | None = None, network_view=None) -> RegistrationResult:
        """Register ``fixed`` ``(H, W)`` (preprocessed like the DRRs: bone bright) from ``init_params``
        (deg, mm). ``mask`` ``(H, W)`` bool: the valid pixels (collimated field). The predictor then
        sees the X-ray with the pixels outside the mask filled by the valid pixels' mean
        (:func:`sim.prepare.masked_fill`: no contrast of its own), and the DRR filled the same
        way (the same field edge in both images, so the edge says nothing about the pose) unless
        the predictor's ``current_field`` is ``"open"`` (a network trained to see the anatomy
        around the field); the final similarity uses the valid pixels only. ``toned``
        ``(H, W)``: the X-ray's toned version (:attr:`register.xray.prepare.PreparedXRay.toned`) or None;
        a network trained on toned targets (its checkpoint's ``tone`` is ``"ct"``) sees it instead
        of ``fixed``. ``network_view``: what the network sees instead of ``fixed`` and ``mask``
        (:class:`register.xray.network_view.NetworkView`): the same pixels masked by the field with
        its clipped plateaus kept, or for a network framed by the detector (its ``framing`` is
        ``"detector"``) the X-ray's whole detector at the network's size with its field, the
        network's DRRs then rendered for that detector; ``fixed``, ``mask`` and the renderer of
        this registration serve the similarity."""
        fixed, mask = checked_inputs(fixed, mask, toned)
        it = self.iterate(fixed, init_params, mask=mask, toned=toned, network_view=network_view)
        sim_value = float(gradient_ncc(fixed, self.renderer.render(it.T), mask=mask)[0])
        return RegistrationResult(params=it.params, pose=it.T, projection=self.renderer.projection_matrix(it.T),
                                  similarity=sim_value, renders=it.renders + 1, stage_seconds=it.stage_seconds,
                                  history=it.history, trajectory=it.trajectory)
