"""The registration methods, chosen and built in one place for ``ctxreg register``, ``ctxreg
evaluate`` and the Python API (:func:`register.api.register_xray`).

``cmaes``
    Multi-resolution CMA-ES from the start pose (:class:`register.engines.cmaes.CMAESRegistration`).
``contextual``
    The trained pose-update network's iteration (:class:`register.engines.contextual.ContextualRegistration`).
``contextual+cmaes``
    The contextual iteration, then CMA-ES in a narrowed box (:data:`register.engines.pipeline.REFINE_SETTINGS`);
    with ``search``, the global search (:mod:`register.engines.search`) between the two where the network's
    pose is lost (:class:`register.engines.pipeline.ContextualPipeline`).

:func:`check_method` validates a method name with its model before any work;
:func:`build_method` returns a :class:`RegistrationMethod`: anything with ``name`` and
``register(fixed (H, W), init_params (6,), mask=None) -> RegistrationResult``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, Protocol

import numpy as np

from register.engines.cmaes import CMAESRegistration, CMAESSettings
from register.engines.contextual import ContextualRegistration, ContextualSettings
from register.engines.pipeline import REFINE_SETTINGS, ContextualPipeline
from register.engines.result import RegistrationError, RegistrationResult
from learn.predict import NetworkPredictor

__all__ = ["METHOD_NAMES", "RegistrationMethod", "check_method", "load_predictor", "build_method"]

#: The registration methods, in the order the help lists them.
METHOD_NAMES = ("cmaes", "contextual", "contextual+cmaes")


class RegistrationMethod(Protocol):
    name: str

    def register(self, fixed: np.ndarray, init_params: np.ndarray, *, mask: np.ndarray | None = None,
                 toned: np.ndarray | None = None) -> RegistrationResult: ...


def needs_model(method: str) -> bool:
    """Whether ``method`` runs the trained network."""
    return method.startswith("contextual")


def check_method(method: str, model) -> None:
    """Raise :class:`RegistrationError` for an unknown ``method`` or a model given to ``cmaes`` (it
    would be ignored). A contextual method without a ``model`` uses the default shipped model
    (:data:`learn.shipped.DEFAULT_MODEL`)."""
    if method not in METHOD_NAMES:
        raise RegistrationError(f"--method {method}: unknown; choose one of {', '.join(METHOD_NAMES)}")
    if not needs_model(method) and model is not None:
        raise RegistrationError(f"--model: meaningful with the contextual methods only; this run is --method {method}")


def load_predictor(model):
    """The network predictor of ``model``: a ``ctxreg train`` checkpoint path or a shipped model's
    name (read and checked now, before any other work; None: the default shipped model,
    :func:`learn.shipped.resolve_model`) or an already loaded predictor (returned as it is)."""
    if callable(model):
        return model

    return NetworkPredictor(model)


class _Method:
    """A built method: ``name`` and the engine's ``register``."""

    def __init__(self, name: str, engine):
        self.name = name
        self.engine = engine

    def register(self, fixed, init_params, *, mask=None, toned=None, network_view=None,
                 before_grid=None, trust=None) -> RegistrationResult | None:
        """``toned``: the X-ray's toned version (:attr:`register.xray.prepare.PreparedXRay.toned`), used by
        the contextual methods (their search's grid, a network trained on toned targets); CMA-ES
        alone registers ``fixed``. ``network_view``: what a detector-framed network sees
        (:func:`register.xray.network_view.network_view`), contextual methods only. ``before_grid``:
        :meth:`register.engines.pipeline.ContextualPipeline.register`'s (None where it stopped), for
        contextual+cmaes with a global search only; ``trust`` likewise (whether the network's pose,
        refined, is kept without the search)."""
        for name, hook in (("before_grid", before_grid), ("trust", trust)):
            if hook is not None and not isinstance(self.engine, ContextualPipeline):
                raise RegistrationError(f"{name}: method {self.name} has no global search's grid")
        if isinstance(self.engine, ContextualPipeline):
            return self.engine.register(fixed, init_params, mask=mask, toned=toned, network_view=network_view,
                                        before_grid=before_grid, trust=trust)
        if not isinstance(self.engine, CMAESRegistration):
            return self.engine.register(fixed, init_params, mask=mask, toned=toned, network_view=network_view)
        return self.engine.register(fixed, init_params, mask=mask)


def build_method(method: str, volume, *, center_lps, size: tuple[int, int], geometry=None,
                 scene: str = "cios_fusion", model=None, physics=None, label_materials: dict[int, str] | None = None,
                 restarts: int = 0, search=None, keep_drrs: bool = False,
                 note: Callable[[str], None] | None = None) -> RegistrationMethod:
    """Build the registration method ``method`` on ``volume``.

    Args:
        method: one of :data:`METHOD_NAMES`.
        volume: the CT; center_lps: ``(3,)`` its anatomy centre (LPS mm).
        size: ``(H, W)`` of the images the method registers (the X-ray after preparation).
        geometry: the :class:`sim.projection.geometry.CArmGeometry` of those images (an X-ray's own); None =
            the ``scene``'s detector at ``size``.
        model: a checkpoint path or a loaded predictor (:func:`load_predictor`) for the contextual methods.
        physics: :class:`sim.physics.imaging.PhysicsSettings` of the moving images (None = line DRRs);
            label_materials: ``{label: material}`` overrides for poly / full.
        restarts: CMA-ES restarts of ``cmaes`` (:class:`register.engines.cmaes.CMAESSettings`).
        search: :class:`register.engines.search.GlobalSearchSettings` of ``contextual+cmaes``'s global
            search (:class:`register.engines.pipeline.ContextualPipeline`), or a
            :class:`register.engines.search.GlobalSearch` built for these images (``geometry``, ``physics``);
            None = none.
        keep_drrs: keep the contextual iteration's DRRs in the result's trajectory (for figures).
        note: called with a sentence when the network's training physics differ from ``physics``.
    """
    check_method(method, model)
    if search is not None and method != "contextual+cmaes":
        raise RegistrationError(f"the global search is part of contextual+cmaes; this method is {method}")
    size = (int(size[0]), int(size[1]))
    if method == "cmaes":
        engine = CMAESRegistration(volume, CMAESSettings(size=size, restarts=restarts), scene=scene, geometry=geometry,
                                   center_lps=center_lps, physics=physics, label_materials=label_materials)
        return _Method(method, engine)
    predictor = load_predictor(model)
    mismatch = getattr(predictor, "physics_mismatch", lambda _: None)(physics)
    if mismatch and note is not None:
        note(mismatch)
    settings = ContextualSettings(keep_drrs=keep_drrs)
    if method == "contextual+cmaes":
        engine = ContextualPipeline(volume, predictor, settings, refine=replace(REFINE_SETTINGS, size=size), size=size,
                                    scene=scene, geometry=geometry, center_lps=center_lps, search=search,
                                    physics=physics, label_materials=label_materials)
    else:
        engine = ContextualRegistration(volume, predictor, settings, size=size, scene=scene, geometry=geometry,
                                        center_lps=center_lps, physics=physics, label_materials=label_materials)
    return _Method(method, engine)
