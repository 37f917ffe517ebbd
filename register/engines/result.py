"""What every registration engine returns, and the error it raises for bad settings or inputs.

:class:`RegistrationResult` (the pose, its projection, the similarity, renders, stage times,
history, the contextual trajectory and the global search's record) and :class:`RegistrationError`
are shared by every engine (:mod:`register.engines.cmaes`, :mod:`register.engines.search`,
:mod:`register.engines.contextual`, :mod:`register.engines.pipeline`) and the API.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim.campaign.poses import PARAM_NAMES
from sim.core.errors import InputError

__all__ = ["RegistrationError", "RegistrationResult"]


class RegistrationError(InputError):
    """Bad registration settings or inputs; the message names the setting."""


@dataclass
class RegistrationResult:
    """A registration's outcome.

    Attributes:
        params: ``(6,)`` pose parameters (deg, mm); pose: ``(4, 4)``; projection: ``(3, 4)``
            LPS mm -> pixels of the finest geometry.
        similarity: the final similarity at the finest level.
        renders: DRRs rendered in all.
        stage_seconds: wall time per stage (``"level0"``, ``"level1"``, ..., ``"polish"``).
        history: one row per generation / polish step: (stage, best similarity so far, params).
        trajectory: for the contextual iteration's K predictions, ``{"params": (K + 1, 6) deg/mm,
            the pose before each prediction and then the pose it ended at; "g": (K, 6) rad/mm, the
            predicted gradients; "drrs": (K, H, W), each prediction's DRR, when kept}``; None for
            CMA-ES alone.
        search: the global search's record (:meth:`register.engines.search.GlobalSearch.register`,
            contextual+cmaes with the search): the network's pose's local similarity, whether the
            grid ran, where the refinement started; None without a search.
    """

    params: np.ndarray
    pose: np.ndarray
    projection: np.ndarray
    similarity: float
    renders: int
    stage_seconds: dict[str, float]
    history: list[tuple[str, float, list[float]]] = field(default_factory=list)
    trajectory: dict | None = None
    search: dict | None = None

    def to_dict(self) -> dict:
        return {
            **({} if self.search is None else {"search": self.search}),
            "params": dict(zip(PARAM_NAMES, map(float, self.params))),
            "params_units": "phi theta psi in degrees, tx ty tz in mm (docs/conventions.md)",
            "pose_4x4": self.pose.tolist(),
            "projection_3x4_lps_to_pixels": self.projection.tolist(),
            "similarity": self.similarity,
            "renders": self.renders,
            "stage_seconds": self.stage_seconds,
        }
