"""What a detector-framed network sees of a prepared X-ray: its whole detector at the network's size.

A network trained with ``train.framing = "detector"`` sees the X-ray's whole detector (and its
field) rather than the X-ray cropped to its field as CMA-ES does (:func:`network_view`); the
contextual iteration (:class:`register.engines.contextual.ContextualRegistration`) then renders the
network's DRRs for that detector.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from register.engines.result import RegistrationError
from register.xray.prepare import fit_to_size

__all__ = ["NetworkView", "network_view"]


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
    """The :class:`NetworkView` of a prepared X-ray (:class:`register.xray.prepare.PreparedXRay`) for
    ``predictor`` when it is framed by the detector (its ``framing``); None otherwise (the network
    sees the X-ray cropped to its field, as CMA-ES does). The whole detector is fitted into the
    network's image size, aspect kept (:func:`register.xray.prepare.fit_to_size`)."""
    if getattr(predictor, "framing", "field") != "detector":
        return None
    size = getattr(predictor, "size", None) or (64, 64)
    image, mask, geometry = fit_to_size(prepared.full_image, prepared.full_mask, prepared.full_geometry, size)
    if mask is None or not mask.any():
        raise RegistrationError("the X-ray's field holds no valid pixel at the network's size")
    return NetworkView(np.asarray(image, np.float64), np.asarray(mask, bool), geometry)
