"""What the contextual network sees of a prepared X-ray: its pixels, its mask and their detector.

Two framings, the network's own (its checkpoint's ``train.framing``):

* ``"field"`` (every shipped network): the X-ray cropped to its field at the optimiser's size, as
  CMA-ES sees it (:class:`register.xray.prepare.PreparedXRay`), but masked by the field with its
  clipped plateaus kept (:attr:`~register.xray.prepare.PreparedXRay.network_mask`): the network's
  training targets keep their clipped pixels, and only drawn overlays are foreign to it;
* ``"detector"``: the X-ray's whole detector (and its field) fitted into the network's size; the
  contextual iteration (:class:`register.engines.contextual.ContextualRegistration`) then renders
  the network's DRRs for that detector.

A network trained on toned targets (its ``tone`` is ``"ct"``) sees the toned pixels
(:func:`register.xray.prepare.toned_image`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from register.engines.result import RegistrationError
from register.xray.prepare import fit_to_size, recorded_tone_curve, toned_image

__all__ = ["NetworkView", "network_view"]


@dataclass(frozen=True)
class NetworkView:
    """What the network sees of an X-ray. ``image`` ``(h, w)`` the preprocessed X-ray, ``mask``
    ``(h, w)`` bool its pixels shown to the network, ``geometry`` the
    :class:`sim.projection.geometry.CArmGeometry` of those pixels (the network's DRRs are rendered for it)."""

    image: np.ndarray
    mask: np.ndarray
    geometry: object


def network_view(predictor, prepared) -> NetworkView | None:
    """The :class:`NetworkView` of a prepared X-ray (:class:`register.xray.prepare.PreparedXRay`) for
    ``predictor`` (its ``framing``, ``size`` and ``tone``; module doc). None where the network sees
    what CMA-ES sees (a field-framed network of an X-ray prepared without the ``field`` step)."""
    if getattr(predictor, "framing", "field") == "detector":
        size = getattr(predictor, "size", None) or (64, 64)
        image, mask, geometry = fit_to_size(prepared.full_image, prepared.full_mask, prepared.full_geometry, size)
        if mask is None or not mask.any():
            raise RegistrationError("the X-ray's field holds no valid pixel at the network's size")
        return NetworkView(np.asarray(image, np.float64), np.asarray(mask, bool), geometry)
    if prepared.network_mask is None:
        return None
    image, mask = np.asarray(prepared.network_image, np.float64), np.asarray(prepared.network_mask, bool)
    if getattr(predictor, "tone", "off") == "ct":
        toned = toned_image(image, mask, recorded_tone_curve(prepared.record))
        image = image if toned is None else toned
    return NetworkView(image, mask, prepared.geometry)
