"""An X-ray made ready for registration: geometry with its sources, field mask, intensity, size.

:func:`prepare_xray` is what ``ctxreg register`` (and any Python caller) does to a user's X-ray
before an optimiser sees it:

1. the C-arm geometry of the image, each value with its source (flag, DICOM tag, scene default:
   :func:`register.xray.geometry.resolve_geometry`);
2. the preprocessing pipeline (default :data:`register.xray.preprocess.DEFAULT_STEPS`: field mask,
   median, intensity decision, normalisation over the mask, crop to the field), with DRRs of the
   CT around the start pose as the polarity reference (:class:`register.xray.intensity.PolarityReference`);
3. the crop's geometry (each pixel keeps its ray) and the resampling to the optimiser's size,
   where the mask follows the image (:func:`fit_to_size`): the image is scaled, its aspect kept,
   to the largest size that fits inside ``size = (H, W)`` with each side a multiple of 4 (the
   default 128 x 128 makes the longer side 128 px; a 2:1 X-ray becomes 128 x 64).

The result keeps the full-resolution image and mask too, for figures a person can judge.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import ndimage

from register.engines.result import RegistrationError
from register.engines.search import GlobalSearch, GlobalSearchSettings
from register.xray.intensity import PolarityReference
from register.xray.geometry import resolve_geometry
from register.xray.io import XRayImage, load_xray
from register.xray.field import TOOL_OPTIONS, TOOLS_DEFAULT, FieldSettings, attenuating_pieces, detect_field
from register.xray.preprocess import DEFAULT_STEPS, Field as FieldStep, Pipeline, PreprocessError, crop_box, cropped_geometry
from sim.campaign.poses import ORIGINAL_PROTOCOL
from sim.core.cliargs import IMAGE_SIDE_PX
from sim.projection.geometry import pose_from_params
from sim.prepare import invert, masked_fill, normalize, percentile_bounds
from sim.core.seeds import KIND_POLARITY_POSES, rng_for
from sim.physics.display import apply_tone
from sim.projection.drr import DRRRenderer, RenderSettings
from sim.ct.anatomy import anatomy_center

__all__ = ["PreparedXRay", "prepare_xray", "confirm_polarity", "confirm_polarity_by_pose", "polarity_needs_check",
           "fit_to_size", "fit_box", "reference_drrs", "recorded_tone_curve", "toned_image",
           "REFERENCE_POSES", "REFERENCE_SIZE", "POLARITY_FLIP_MARGIN", "POLARITY_CONFIRMED_ABOVE"]

#: Number of DRRs (poses around the start) of the polarity reference, and their longer side (px).
REFERENCE_POSES = 96
REFERENCE_SIZE = 48


def fit_box(size) -> tuple[int, int]:
    """``(H, W)`` of the box an image is fitted into: ``size`` is ``(H, W)``, or one number for a
    square box (the longer side). Raises :class:`register.xray.preprocess.PreprocessError` for sides
    outside :data:`sim.core.cliargs.IMAGE_SIDE_PX`."""
    try:
        box = (int(size), int(size)) if np.ndim(size) == 0 else tuple(int(v) for v in size)
    except (TypeError, ValueError):
        box = ()
    if len(box) != 2 or not all(v in IMAGE_SIDE_PX for v in box):
        raise PreprocessError(f"size {size!r}: give the optimiser's image as (H, W), each side {IMAGE_SIDE_PX} pixels")
    return box


def _fit_plan(shape: tuple[int, int], geometry, size):
    """Sampling of :func:`fit_to_size`: ``(rows, cols, f, geometry)``."""
    h, w = shape
    box_h, box_w = (size, size) if np.ndim(size) == 0 else size
    f = max(h / float(box_h), w / float(box_w))  # old pixels per new pixel
    H = max(4, int(round(h / f / 4)) * 4)
    W = max(4, int(round(w / f / 4)) * 4)
    f = min(h / H, w / W)
    y0, x0 = (h - H * f) / 2.0, (w - W * f) / 2.0
    rows = y0 + (np.arange(H) + 0.5) * f - 0.5
    cols = x0 + (np.arange(W) + 0.5) * f - 0.5
    cx, cy = geometry.principal_point
    geom = replace(geometry, height=H, width=W, pixel_spacing_mm=geometry.pixel_spacing_mm * f,
                   cx=(cx - x0 + 0.5) / f - 0.5, cy=(cy - y0 + 0.5) / f - 0.5)
    return rows, cols, f, geom


def fit_to_size(image: np.ndarray, mask: np.ndarray | None, geometry, size):
    """Centre-crop and resample ``image`` ``(h, w)`` to the largest size, aspect kept, that fits
    inside ``size`` (``(H, W)``, or one number: the longer side), each side a multiple of 4.

    Pixels stay square: the crop removes the fraction of a pixel that keeps both sides an exact
    multiple of the new spacing. The anti-aliasing blur (Gaussian, sigma ``f / 2 - 0.5`` old
    pixels for a reduction by ``f``) is mask-normalised: pixels outside ``mask`` never leak into
    the result, and a new pixel is valid only when at least 99 % of its blur weight falls on valid
    pixels. Returns ``(image (H, W) float64, mask (H, W) bool or None, geometry)`` with the
    geometry's spacing and principal point moved accordingly.
    """
    h, w = image.shape
    rows, cols, f, geom = _fit_plan((h, w), geometry, size)
    sigma = max(f / 2.0 - 0.5, 0.0)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    img = np.asarray(image, np.float64)
    if mask is None:
        smooth = ndimage.gaussian_filter(img, sigma=sigma)
        return ndimage.map_coordinates(smooth, [rr, cc], order=1, mode="nearest"), None, geom
    wgt = mask.astype(np.float64)
    num = ndimage.gaussian_filter(img * wgt, sigma=sigma)
    den = ndimage.gaussian_filter(wgt, sigma=sigma)
    num = ndimage.map_coordinates(num, [rr, cc], order=1, mode="nearest")
    den = ndimage.map_coordinates(den, [rr, cc], order=1, mode="nearest")
    new_mask = den > 0.99
    fill = float(np.median(img[mask])) if mask.any() else 0.0
    out = np.where(den > 1e-6, num / np.maximum(den, 1e-6), fill)
    return out, new_mask, geom


def reference_drrs(volume, center_lps, geometry, init_params, *, poses: int = REFERENCE_POSES,
                   longer: int = REFERENCE_SIZE, seed: int = 0):
    """The polarity reference of an X-ray with detector ``geometry`` (its full ``(H, W)``).

    Line-integral DRRs ``(poses, h, w)`` at the start pose and at ``poses - 1`` poses around it
    (offsets drawn, seeded, from the original capture range :data:`sim.campaign.poses.ORIGINAL_PROTOCOL`:
    up to 40 / 20 / 20 deg and 75 mm), rendered with the X-ray's geometry sampled as
    :func:`fit_to_size` samples the X-ray to ``longer`` px. Returns a
    :class:`register.xray.intensity.PolarityReference`.
    """

    _, _, _, small = _fit_plan((geometry.height, geometry.width), geometry, longer)

    rng = rng_for(seed, KIND_POLARITY_POSES)
    x0 = np.asarray(init_params, float).reshape(1, 6)
    params = np.concatenate([x0, x0 + ORIGINAL_PROTOCOL.sample(rng, poses - 1)])
    renderer = DRRRenderer(volume, RenderSettings(size=(small.height, small.width)), center_lps=center_lps,
                           geometry=small)
    drrs = renderer.render(pose_from_params(params, small.sod_mm))

    def resample(image, mask):
        out, m, _ = fit_to_size(image, mask, geometry, longer)
        return out, m

    return PolarityReference(drrs=np.asarray(drrs, np.float64), resample=resample)


@dataclass
class PreparedXRay:
    """An X-ray ready for an optimiser, and what was done to it.

    Attributes:
        xray: the :class:`register.xray.io.XRayImage` as read.
        image: ``(h, w)`` float64 at the optimiser's size: line-integral-like (bone bright),
            normalised over the valid pixels.
        mask: ``(h, w)`` bool valid pixels (the field minus exclusions), or None.
        geometry: :class:`sim.projection.geometry.CArmGeometry` of ``image`` (cropped and resampled).
        full_geometry: the geometry of the X-ray's own ``(H, W)`` pixels.
        full_image: ``(H, W)`` the preprocessed image at full resolution (outside the crop: the
            median of the valid pixels).
        full_mask: ``(H, W)`` bool the valid pixels at full resolution.
        record: the preprocessing record (one entry per step).
        sources: :class:`register.xray.geometry.GeometrySources` (where each geometry value came from).
        toned: ``(h, w)`` float64 ``image`` with its valid pixels mapped by rank onto the CT's line
            integrals in the field (the intensity step's tone curve, :func:`toned_image`) and
            normalised to [0, 1]; None when the image got no tone curve (not a display image,
            ``tone="off"``, no CT). The global search ranks its grid on it too.
        network_image: ``(h, w)`` float64, the same preprocessed pixels as ``image`` (same crop,
            size and geometry) resampled over ``network_mask`` instead of ``mask``; None: as ``image``.
        network_mask: ``(h, w)`` bool, the pixels the contextual network is shown: the detected
            field minus drawn overlays only (text, rulers, markers), its clipped plateaus kept, as
            the network's training targets keep theirs (``mask`` also drops the plateaus, which
            intensity similarities cannot use). None when the pipeline's first step is not
            ``field`` (then ``mask``).
        tools: ``(H, W)`` bool, the metal tools found in the field and left out of ``mask``
            (``tools="detect"``; at full resolution), or None (not looked for).
    """

    xray: Any
    image: np.ndarray
    mask: np.ndarray | None
    geometry: Any
    full_geometry: Any
    full_image: np.ndarray
    full_mask: np.ndarray
    record: list
    sources: Any
    toned: np.ndarray | None = None
    network_image: np.ndarray | None = None
    network_mask: np.ndarray | None = None
    tools: np.ndarray | None = None

    def step(self, name: str) -> dict | None:
        """The measured values of the first pipeline step called ``name`` (None if it did not run)."""
        for entry in self.record:
            if entry["step"] == name:
                return entry["measured"]
        return None

    def summary(self) -> dict:
        """JSON: the geometry sources, field, intensity decision (and its check against the CT),
        and sizes, for result.json."""
        return {"geometry_sources": self.sources.to_dict(), "orientation": self.xray.meta.get("orientation", "none"),
                "field": self.step("field"), "intensity": self.step("intensity"),
                "polarity_check": self.step("polarity_check"),
                "full_size": [self.full_geometry.height, self.full_geometry.width],
                "optimiser_size": [self.geometry.height, self.geometry.width]}


def prepare_xray(xray, *, volume=None, center_lps=None, init_params=None, scene: str = "cios_fusion",
                 steps=None, scale: str = "auto", polarity: str = "auto", tone: str = "ct", size=(128, 128),
                 sdd_mm: float | None = None, sod_mm: float | None = None,
                 pixel_spacing_mm: float | None = None, tools: str = TOOLS_DEFAULT) -> PreparedXRay:
    """Prepare ``xray`` (a path or :class:`register.xray.io.XRayImage`) for registration.

    Args:
        volume, center_lps, init_params: the CT, its anatomy centre (LPS mm) and the start pose
            (deg, mm); with ``volume`` given, DRRs around the start decide the polarity when the
            DICOM tags do not (:func:`reference_drrs`).
        scene: C-arm scene for geometry values the image does not give.
        steps: preprocessing step names (default :data:`register.xray.preprocess.DEFAULT_STEPS`).
        scale / polarity: ``"auto"`` or an override (:data:`register.xray.intensity.SCALES`,
            :data:`register.xray.intensity.POLARITIES`).
        tone: ``"ct"``: a display image also gets :attr:`PreparedXRay.toned`, its values mapped
            onto the CT's line integrals in its field (with ``volume``;
            :class:`register.xray.preprocess.Intensity`); ``"off"``: not.
        size: ``(H, W)`` px the optimiser's image fits inside (aspect kept, sides multiples of 4;
            :func:`fit_to_size`), each side in [8, 4096]; one number is a square box.
        sdd_mm, sod_mm, pixel_spacing_mm: explicit geometry (override tags and scene).
        tools: ``"detect"`` (default, :data:`register.xray.field.TOOLS_DEFAULT`): those the shipped
            tool segmenter (:class:`learn.tool_mask.ToolMask`) finds in the field are left out of
            ``mask`` as the field's clipped plateaus are (the network's mask keeps them, as its
            training targets do), but for pieces that attenuate less than most of the field
            (:func:`register.xray.field.attenuating_pieces`: not metal; the steps run again
            without them). Only with ``"field"`` as the first step. ``"off"``: not looked for.
    """
    if tools not in TOOL_OPTIONS:
        raise PreprocessError(f"tools must be one of {', '.join(TOOL_OPTIONS)}, got {tools!r}")
    box = fit_box(size)
    if not isinstance(xray, XRayImage):
        xray = load_xray(xray)
    full_geometry, sources = resolve_geometry(xray, scene, sdd_mm=sdd_mm, sod_mm=sod_mm,
                                              pixel_spacing_mm=pixel_spacing_mm)
    steps = tuple(DEFAULT_STEPS if steps is None else steps)
    reference = None
    wants_tone = tone == "ct" and scale in ("auto", "display")
    if "intensity" in steps and volume is not None and (polarity == "auto" or wants_tone):
        center = anatomy_center(volume) if center_lps is None else center_lps
        reference = reference_drrs(volume, center, full_geometry, np.zeros(6) if init_params is None else init_params)
    tags = xray.meta.get("intensity_tags")
    bits = (tags or {}).get("BitsStored") if tags else (8 if xray.meta.get("dtype") == "uint8" else None)
    options = {"intensity": {"scale": scale, "polarity": polarity, "tone": tone, "tags": tags,
                             "inverted": bool(xray.meta.get("inverted", False)), "bits": bits,
                             "reference": reference}}
    found = None
    if steps and steps[0] == "field":  # detected once here: the network's mask keeps its plateaus
        # a raw detector signal (FOR PROCESSING, or declared linear) is searched by its edges
        raw = scale == "linear" or not xray.attenuation_bright
        found = detect_field(xray.pixels, FieldSettings(margin_px=FieldStep().margin_px), raw=raw)
        field = found
        if tools == "detect":
            from learn.tool_mask import ToolMask  # loads torch: imported where first needed (start-up)

            found = field.without_tools(ToolMask.shared().detect(xray.pixels, field.field_mask))
        options["field"] = {"found": found}
    image, mask, record = Pipeline.from_names(list(steps), options).apply(xray.pixels)
    H, W = xray.shape
    r0, r1, c0, c1 = crop_box(record, (H, W))
    if found is not None and found.tools is not None and found.tools.any() and mask is not None:
        # metal attenuates more than most of the field: pieces that do not (air edges, gas) are given
        # back, and the steps run again on the field without them (the intensity step decided the
        # polarity that ranks them; the image it leaves is attenuation bright)
        pieces = found.tools[r0:r1, c0:c1]
        kept = np.zeros((H, W), bool)
        kept[r0:r1, c0:c1] = attenuating_pieces(pieces, image, mask & ~pieces)
        if (kept != found.tools).any():
            found = field.without_tools(kept)
            options["field"] = {"found": found}
            image, mask, record = Pipeline.from_names(list(steps), options).apply(xray.pixels)
            r0, r1, c0, c1 = crop_box(record, (H, W))
    full_mask = np.zeros((H, W), bool)
    full_mask[r0:r1, c0:c1] = True if mask is None else mask
    fill = float(np.median(image[mask])) if mask is not None else float(np.median(image))
    full_image = np.full((H, W), fill, np.float64)
    full_image[r0:r1, c0:c1] = image
    geometry = cropped_geometry(full_geometry, record)  # a crop moves the principal point
    if mask is not None and mask.mean() < 0.02:
        raise PreprocessError(f"{xray.source}: only {mask.sum()} valid pixels are left after preprocessing")
    crop_geometry = geometry
    small, small_mask, geometry = fit_to_size(image, mask, crop_geometry, box)
    if small_mask is not None and not small_mask.any():
        raise PreprocessError(f"{xray.source}: no valid pixel is left at the optimiser's {small.shape[0]} x "
                              f"{small.shape[1]} px")
    net_image = net_mask = None
    if found is not None:
        shown = (found.field_mask & ~found.overlay)[r0:r1, c0:c1]
        net_image, net_mask, _ = fit_to_size(image, shown, crop_geometry, box)
        if not net_mask.any():
            net_image = net_mask = None
    return PreparedXRay(xray=xray, image=small, mask=small_mask, geometry=geometry, full_geometry=full_geometry,
                        full_image=full_image, full_mask=full_mask, record=record, sources=sources,
                        toned=toned_image(small, small_mask, recorded_tone_curve(record)), network_image=net_image,
                        network_mask=net_mask, tools=None if found is None else found.tools)


def toned_image(image: np.ndarray, mask: np.ndarray | None, curve) -> np.ndarray | None:
    """``image`` ``(h, w)`` (bone bright) with its valid pixels mapped by rank onto ``curve``
    (:func:`register.xray.intensity.tone_curve`), normalised as :class:`register.xray.preprocess.Normalize`
    does (1st / 99th percentiles of the valid pixels to 0 / 1, clipped); outside the mask the
    valid median. None when ``curve`` is None."""

    if curve is None:
        return None
    out = apply_tone(image, mask, curve)
    lo, hi = percentile_bounds(out, mask, 1.0, 99.0)
    if not hi > lo:
        return np.full(out.shape, 0.5)
    return normalize(out, lo, hi)




#: Polarity sources that a registration check does not question: the user's option and a decisive tag.
_DECISIVE_POLARITY = ("option", "DICOM PixelIntensityRelationshipSign")

#: A registered pose whose gradient NCC with the X-ray as decided (plain, at the optimiser's size,
#: against a line DRR) reaches this confirms the decided polarity without the grid check
#: (:func:`confirm_polarity_by_pose`): the inverse scores minus that at the same pose, and where a
#: decision was wrong its best grid pose scored at most about 0.5 (:data:`POLARITY_FLIP_MARGIN`'s
#: frames). The global search's skip threshold (``GlobalSearchSettings.found_above``), on the same
#: score.
POLARITY_CONFIRMED_ABOVE = 0.85

#: The inverse must score better by this much (the best gradient NCC over the global search's grid,
#: :meth:`register.engines.search.GlobalSearch.polarity_scores`) to overturn the decided polarity. On
#: realistic frames (four display chains, 22 frames) the right polarity's best was 0.38-0.96; where
#: the decision was wrong the inverse scored 0.27-0.51 more, where it was right at most 0.04 more.
POLARITY_FLIP_MARGIN = 0.15


def confirm_polarity(prepared: PreparedXRay, volume, center_lps, init_params, *, physics=None,
                     label_materials=None, search=None) -> PreparedXRay:
    """Check the decided polarity against the CT, unless an option or a decisive tag set it.

    The global search's grid (:class:`register.engines.search.GlobalSearch`: rotations and depths over the
    prior box around ``init_params``, each pose at its best in-plane shift, gradient NCC at 1/4
    resolution) scores the prepared image and its inverse in one pass (an inverse's gradients are
    negated); the polarity whose best pose scores higher is kept. With the wrong polarity every
    edge of the X-ray points against the DRR's. The inverse wins only by
    :data:`POLARITY_FLIP_MARGIN`: an image without anatomy scores alike either way and the
    decision stands (``verdict`` ``inconclusive``), as it does for an image too small for the grid
    (``reason``). The outcome goes into the record as step ``polarity_check`` (both scores, verdict,
    whether the image was inverted). About a second on 2 cores. ``physics`` and
    ``label_materials`` are accepted for the caller's convenience: the grid's DRRs are line
    integrals, whose edges are the geometry's. ``search``: a :class:`register.engines.search.GlobalSearch`
    built for ``prepared.geometry`` (default settings) to score on; it keeps the grid's DRRs, so a
    registration that searches with it next renders the grid once (about a second saved).
    """
    if not polarity_needs_check(prepared):
        return prepared
    decision = prepared.step("intensity")
    if search is not None and not search.built_for(prepared.geometry):
        raise ValueError("confirm_polarity: search was built for another detector than the prepared X-ray's")
    g = prepared.geometry
    init = np.asarray(init_params, float).reshape(6)
    try:
        grid = search or GlobalSearch(volume, GlobalSearchSettings(), size=(g.height, g.width), geometry=g,
                                      center_lps=center_lps)
        as_decided, inverted = grid.polarity_scores(prepared.image, init, mask=prepared.mask)
    except RegistrationError as exc:  # an image too small for the grid: the decision stands
        measured = {"verdict": "inconclusive", "inverted": False, "polarity": decision["polarity"],
                    "reason": str(exc)}
        return replace(prepared, record=[*prepared.record, {"step": "polarity_check", "params": {}, "measured": measured}])
    flip = inverted >= as_decided + POLARITY_FLIP_MARGIN
    verdict = ("inverted" if flip else "confirmed" if as_decided >= inverted + POLARITY_FLIP_MARGIN
               else "inconclusive")
    measured = {"similarity_as_decided": as_decided, "similarity_inverted": inverted,
                "margin": POLARITY_FLIP_MARGIN, "verdict": verdict, "inverted": bool(flip),
                "polarity": (decision["polarity"] if not flip else
                             ("bone-dark" if decision["polarity"] == "bone-bright" else "bone-bright"))}
    settings = grid.settings
    params = {"grid_poses": int(len(settings.grid_offsets())), "factor": settings.factor,
              "step_deg": settings.step_deg, "depths": settings.depths}
    record = [*prepared.record, {"step": "polarity_check", "params": params, "measured": measured}]
    if not flip:
        return replace(prepared, record=record)
    inverse = invert(prepared.image, prepared.mask)[0]
    full_inverse = invert(prepared.full_image, prepared.full_mask if prepared.full_mask.any() else None)[0]
    net_inverse = (None if prepared.network_image is None else
                   invert(prepared.network_image, prepared.network_mask)[0])
    return replace(prepared, image=inverse, full_image=full_inverse, record=record,
                   toned=toned_image(inverse, prepared.mask, recorded_tone_curve(prepared.record)), network_image=net_inverse)


def polarity_needs_check(prepared: PreparedXRay) -> bool:
    """Whether the decided polarity is open to the check against the CT: an intensity step decided
    it, and neither an option nor a decisive tag."""
    decision = prepared.step("intensity")
    return decision is not None and decision.get("polarity_source") not in _DECISIVE_POLARITY


def confirm_polarity_by_pose(prepared: PreparedXRay, similarity: float, pose_params) -> PreparedXRay | None:
    """The X-ray with its decided polarity confirmed by a registered pose whose gradient NCC with it
    (plain, at the optimiser's size) is ``similarity`` >= :data:`POLARITY_CONFIRMED_ABOVE` (its
    inverse scores ``-similarity`` there), recorded as step ``polarity_check`` with ``"by": "pose"``,
    the pose (``pose_params`` ``(6,)`` deg, mm) and no grid; None where ``similarity`` is lower
    (:func:`confirm_polarity` must decide). The registration then needs no grid of its own for the
    check (about 3 s on 2 cores where the global search is skipped or not part of the method)."""
    if not polarity_needs_check(prepared) or not similarity >= POLARITY_CONFIRMED_ABOVE:
        return None
    decision = prepared.step("intensity")
    measured = {"by": "pose", "similarity_as_decided": float(similarity), "similarity_inverted": -float(similarity),
                "threshold": POLARITY_CONFIRMED_ABOVE, "verdict": "confirmed", "inverted": False,
                "polarity": decision["polarity"], "pose_params": np.asarray(pose_params, float).reshape(6).tolist()}
    return replace(prepared, record=[*prepared.record, {"step": "polarity_check", "params": {"by": "pose"},
                                                        "measured": measured}])


def recorded_tone_curve(record) -> np.ndarray | None:
    """The tone curve ``(levels,)`` the intensity step of a preprocessing ``record`` recorded (None:
    the image has none)."""
    for entry in record:
        if entry["step"] == "intensity":
            curve = entry["measured"].get("tone_curve")
            return None if curve is None else np.asarray(curve, np.float64)
    return None
