"""Collimated field of view of an X-ray image and the mask of the pixels registration may use.

Real C-arm and radiography images show the anatomy only inside a collimated field: a round field
(image intensifiers, Siemens Cios: black outside the circle), rectangular shutters, fields whose
circle runs off the image, polygonal fields (shutter blades at angles). Outside the field the
vendor paints a constant black or white, or (raw images) the collimator shadow is nearly constant
with noise. Images also carry burned-in text, rulers and side markers drawn at an extreme grey
value, and plateaus clipped at the maximum (saturated) or minimum (empty). :func:`detect_field`
finds all of these and returns a :class:`Field` whose ``mask`` holds the valid pixels.

Method (deterministic; about 0.1 s for 512 x 512):

1. **Outside level.** The image is 3 x 3 median filtered (isolated noisy pixels and 1-px strokes
   go). The outside level ``L`` is the mode of the border ring (the outer 2 px); the in-field level
   is the median of the pixels far from ``L``; their difference is the contrast ``C``. The outside
   region is grown from the image border (4-neighbours) over the pixels that are near the level,
   ``|median - L| <= tol`` with ``tol = max(level_tolerance * C, noise_k * sigma)`` (``sigma``: the
   outside's noise after the median; ``tol`` at most ``C / 2``), and locally flat (3 x 3 standard
   deviation at most 3 x the outside's own, or 1 % of ``C``; overlay strokes do not count against
   the flatness of the pixels around them): anatomy that comes near ``L`` has texture and noise
   and stops the growth. Collimation is only considered when at least ``min_border_fraction`` of
   the border ring lies at ``L``, ``L`` is an extreme (at most 2 % of the pixels lie beyond it),
   the outside covers at least ``min_outside_fraction`` of the image and is flat (robust spread of
   its 7 x 7 local means, after removing a plane for smooth shading, at most
   ``max_outside_texture * C``: a painted or noise-only shadow, not dark anatomy).
   **1b. A second outside level** (leaky blades). Where the outside of one level leaves no shape
   model (steps 2-3), the border ring's pixels outside that region give a second level (the mode
   of their values, at least ``min_border_fraction`` of the ring, at least ``level_tolerance`` of
   the contrast from the first): the air behind blades that pass a few per cent of the beam,
   clipped at the other extreme or a smooth grey, while the body's shadow lies at the first level.
   Its region is grown from those border pixels over pixels within half its distance from the
   first level and locally flat, must be flat as in step 1, and the seam between the two regions
   (within 10 px of both: the blurred skin edge behind the blades) joins them. Up to
   ``_MAX_OUTSIDE_LEVELS`` (3) levels are tried, each kept only where a model then fits
   (``params["outside_levels"]``), so the air inside a field that runs off the image is never
   taken out of a field that fits without it.
2. **Candidate.** The rest, opened with a radius-2 disk (glyph strokes crossing the field edge go),
   its largest 8-connected component with holes filled (glyphs in the outside corners and text
   over the anatomy go). A second component larger than 10 % of it means no single field (a body
   outline, two legs). The candidate's boundary layer (5 px, and 5 px along the image edges,
   where a thin shutter may be all blur) is then re-thresholded at the midpoint between ``L`` and
   the local in-field level (mean of the layer 5-10 px deep in a 21 x 21 window), so that a soft
   (blurred) edge is placed at its 50 % point and dark anatomy at the edge is not cut.
3. **Shape model**, the simplest that agrees with the candidate (mean boundary deviation =
   ``|model XOR candidate| / model boundary length`` at most ``max_boundary_px``): an axis-aligned
   **rectangle** (rows and columns where the candidate fills at least half of its widest
   row / column), a **circle** (RANSAC over triples of boundary points away from the image
   border, then geometric least squares on the inliers; works for circles clipped by the image
   edges; needs ``circle_min_inliers`` of the points within ``circle_inlier_px``), a convex
   **polygon** (convex hull of the candidate's sub-pixel boundary, simplified by Douglas-Peucker
   with ``polygon_tolerance_px``, then each edge refitted as a line to its boundary points and
   neighbouring lines intersected, so corners are sharp and corner cuts go). Where none of these
   fits because anatomy at the outside's level (dense bone shown dark next to a black outside)
   notches the candidate's edge, an **iris with blades**: a circle fitted to the boundary points
   (at least 30 % of them) and up to four straight blade edges fitted by RANSAC to the rest, each
   a supporting line of the field (refitted on its outer points; the strip just beyond it is not
   candidate; it cuts at least 15 % of the radius into the circle; what it cuts off is the
   outside region of step 1, not anatomy), together explaining 60 % of the boundary; it is
   accepted one-sided: the candidate may not run beyond it (1 px per boundary px), the notches
   inside it may reach 4 px per boundary px (both at a 256 px image, scaled with a larger
   image's side: 8 x at 1024 px, where the notches of clipped anatomy measured 15 px per
   boundary px; the other px thresholds do not scale yet). Without blades this is a notched ``"circle"``;
   with them, kind ``"iris-blades"``. Last, a **deeply notched circle**: where clipped anatomy
   notches a round field beyond those limits (20-40 px per boundary px on 1024 px irises, up to a
   third of the circle), a circle is fitted (RANSAC, inlier distance scaled with the side) to the
   boundary points, and accepted when its inliers cover at least half of its circumference inside
   the image (1-degree bins; ``params["arc_cover"]``), the candidate runs beyond it by at most
   1 px per boundary px (scaled), and at least 70 % of what it lacks inside the circle is the
   outside region (clipped at the outside's level, not textured anatomy). This one model is also
   tried on a candidate split into large parts by a notch running through the field (otherwise
   "not one field"). And a **notched polygon**: the convex polygon of step 3 accepted one-sided
   where dark anatomy at the edge (cut by the 50 % threshold) notches shutter blades: at most 8
   vertices, the candidate's boundary within ``circle_inlier_px`` (scaled) of at least 80 % of its
   perimeter inside the image and 30 % of each edge (``params["edge_cover"]``), the iris's limits on
   what runs beyond it and what it lacks, and at least a quarter of the image (smaller one-sided
   polygons were parts of a field on the study frames: the air in it, a region of bone). A candidate that none fits (not convex: a body outline,
   dark anatomy) means no collimation: kind ``"none"``, the field is the whole image (a painted
   outside is then still excluded as an empty / saturated plateau).
   The field mask is the model's mask (not the raw candidate) eroded by ``margin_px`` from the
   model's boundary (the image edges do not erode it).
4. **Exclusions inside the field**, from the connected components (8-neighbours) of the pixels
   within one quantisation step (the smallest difference between the image's values) of the
   image's maximum or minimum. A component whose surroundings (the ring 2 px away) differ from the
   extreme by at least ``max(overlay_contrast * in-field range, overlay_noise_k * noise)`` (an
   abrupt step: drawn, not clipped), with at least ``overlay_min_px`` pixels, thin (stroke width
   at most ``overlay_max_width_px``) or small (fewer than ``plateau_min_px``), is an **overlay**
   (text, ruler, marker); overlays are dilated by ``overlay_dilate_px``. Every other component of
   at least ``plateau_min_px`` pixels is a **saturated** (maximum) or **empty** (minimum) plateau,
   dilated by ``plateau_dilate_px``. Smaller pieces within 4 px of an overlay / plateau (dots of
   i, full stops, the frayed rim of a clipped region) join it; isolated ones (noise touching the
   extreme) are kept.
5. ``mask = field_mask & ~(overlay | saturated | empty)``.
6. **Linear displays.** Where steps 1-5 leave too little field (under ``min_fraction``), or fit no
   shape model (kind ``"none"``), they run again on a logarithmic view of the image (:func:`log_view`: the log of each pixel's distance
   from the extreme nearer the median, then from the other): a display of intensity rather than
   its logarithm squeezes a thick body into the few grey levels next to one extreme, where the
   outside's level swallows it (a 70 kV pelvis at 10 bits lies within 20 levels of black). The
   mask is of the image's pixels either way; ``view`` records which view found it. For an image
   that fits no model a view's result is taken only where a model fits it and it leaves at least
   a quarter of the image valid (a leaky iris behind a linear display: the collimator's shadow and
   tools at black join the anatomy's few grey levels next to it, and the image as stored shows no
   outside that a model fits; its logarithm does).

Result (:class:`Field`): ``mask`` and ``field_mask`` ``(H, W)`` bool; ``kind`` (``"none"``,
``"circle"``, ``"rectangle"``, ``"polygon"``, ``"iris-blades"``); ``outside`` (``"black"``, ``"white"``
or ``None``); ``params`` in pixels (circle: ``centre_x`` = column, ``centre_y`` = row, ``radius``;
iris-blades: the circle's and ``blades`` ``[[[x0, y0], [x1, y1]], ...]``, each blade edge's fitted
extent; rectangle:
half-open ``row0, row1, col0, col1``; polygon: ``vertices`` ``[[x, y], ...]`` with x = column,
y = row, pixel centres at integers; kind ``"none"``: ``reason``, why no field was accepted);
``excluded`` pixel counts (disjoint, inside ``field_mask``): ``overlay``, ``saturated``, ``empty``;
:meth:`Field.to_dict` for the record.

Errors (:class:`FieldError`, a :class:`~register.xray.io.XRayInputError`): input not 2-D, not
real, smaller than 16 x 16, NaN / inf, constant, or valid pixels under ``min_fraction``.

Known limits: text must reach the extreme value (anti-aliased glyphs whose strokes stay below
it, as Pillow's default anti-aliased font draws them, or JPEG-blurred text, are not found);
where the anatomy itself reaches the outside's value at the field edge (saturated or empty
anatomy touching the edge) the edge is invisible there: circles and rectangles are fitted to the
rest of the edge, a polygon loses that corner; a convex dark body outline on a flat black
background can be taken for a polygonal field; a field that is not convex is reported as
``"none"``; a rotated rectangle is reported as a 4-vertex polygon. Behind leaky blades on a linear
display the body's shadow and the anatomy in the field share the few grey levels next to the
extreme (a 70 kV pelvis at 10 bits: both within 20 levels of black), no level tells them apart, and
the field is reported as ``"none"`` (its outside partly kept); a circle seen along less than half of
its circumference (the rest clipped anatomy or leaked air) is not fitted.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from register.xray.io import XRayInputError
from sim.core.atomic import jsonable

__all__ = ["FieldError", "FieldSettings", "Field", "detect_field", "log_view", "LOG_VIEWS", "TOOL_OPTIONS",
           "TOOLS_DEFAULT", "TOOL_MIN_ATTENUATION_RANK", "attenuating_pieces"]

#: What registration does about metal tools in the field (``prepare_xray(tools=...)``, ``--tools``):
#: ``"detect"``: the shipped segmenter's (:class:`learn.tool_mask.ToolMask`) are left out
#: (:meth:`Field.without_tools`); ``"off"``: not looked for.
TOOL_OPTIONS = ("detect", "off")
#: The one default of ``tools`` (``prepare_xray``, ``register_xray``, ``ctxreg register --tools``,
#: the benchmarks): ``"detect"``. The verdict's thresholds are calibrated on registrations made
#: both ways (benchmarks/verdict_rows/calib.jsonl and calib_detect.jsonl; docs/results.md).
TOOLS_DEFAULT = "detect"

#: A detected tool piece is kept only where its median pixel attenuates more than this share of the
#: field's valid pixels (:func:`attenuating_pieces`): metal adds attenuation to whatever it lies
#: over. The segmenter's pieces on tool-free frames of a linear display lay at air edges (ranks
#: 0.02-0.38 on ``studies/heldout.toml``'s ``linear-70kV``), tools' at 0.55-0.98 on log frames.
TOOL_MIN_ATTENUATION_RANK = 0.5

#: Width (px) of the border ring whose mode gives the outside level.
_RING_PX = 2
#: Bins of the border-ring histogram over the image's value range.
_HIST_BINS = 128
#: Largest fraction of the pixels allowed beyond the outside level (it must be an extreme).
_MAX_BEYOND = 0.02
#: Radius (px) of the disk opening the candidate (removes glyphs / fringes touching the field).
_OPEN_RADIUS = 2
#: A second part of the candidate larger than this fraction of the largest: not one field
#: (a body outline, two legs); glyphs left in the corners are far smaller.
_MAX_SECOND_PART = 0.1
#: Depth (px) of the candidate's boundary layer re-thresholded at the 50 % level.
_EDGE_BAND_PX = 5
#: Window (px) averaging the in-field level next to the boundary for the 50 % threshold.
_LOCAL_LEVEL_PX = 21
#: RANSAC trials of the circle fit (seeded: deterministic).
_RANSAC_TRIALS = 300
#: Small overlay pieces (dots, full stops) join an overlay within this distance (px).
_DOT_REACH_PX = 4
#: Polygon edges shorter than this (px) are corner cuts; the neighbouring edges are intersected.
_POLY_MIN_EDGE_PX = 8.0
#: Consecutive polygon edges turning by less than this (degrees) are one edge.
_POLY_MERGE_DEG = 3.0
_MIN_SIZE = 16
#: Share of the boundary points (away from the image edges) an iris with blades keeps on its circle.
_IRIS_MIN_ARC = 0.3
#: Boundary points (about px of boundary) a blade's straight edge must span.
_IRIS_MIN_BLADE_PTS = 8
#: Share of a blade's chord through the circle its straight edge must show (boundary points per px).
_IRIS_BLADE_COVER = 0.3
#: Least depth a blade cuts into the circle (its sagitta), a fraction of the radius.
_IRIS_MIN_CUT = 0.15
#: Share of the boundary points (away from the image edges) the circle and blades must explain.
_IRIS_MIN_EXPLAINED = 0.6
#: Largest notch area per boundary px (px) an iris with blades allows inside its model: anatomy
#: at the outside's level along the edge (the candidate must not run beyond the model at all).
_IRIS_MAX_NOTCH_PX = 4.0
#: Largest area of the candidate beyond an iris-with-blades model per boundary px (px): a blade's
#: edge fitted through notches may tilt by a px or two over its length.
_IRIS_MAX_BEYOND_PX = 1.0
#: The image side (px) at which the two limits above hold; a larger image scales them with its
#: side: a notch's mean depth (its area per boundary px) grows with the pixel count across it.
_IRIS_REFERENCE_SIDE_PX = 256.0
#: Width (px) of the strip just beyond a blade (past ``circle_inlier_px``, inside the circle) that
#: must be outside: a blade is a supporting line of the field.
_IRIS_STRIP_PX = 3.0
#: Share of that strip the candidate may fill (a line through notches' rims cuts the field there).
_IRIS_BLADE_SPILL = 0.2
#: Share of the circle's part cut off by a blade that must be the outside region (step 1).
_IRIS_CUT_OUTSIDE = 0.7
#: Share of a notched circle's circumference inside the image its clean arc must cover.
_NOTCHED_MIN_COVER = 0.5
#: Share of a notched circle's notches (inside it, not candidate) that must be the outside region.
_NOTCHED_OUTSIDE = 0.7
#: Most vertices of a notched polygon (shutter blades: a rotated rectangle and two corner cuts).
_NOTCHED_POLY_MAX_VERTICES = 8
#: Share of a notched polygon's perimeter inside the image its candidate's boundary must follow.
#: On the study frames the right notched polygons measured 0.83-0.99; polygons around a part of
#: the field (the air in it, a dark bone region; linear displays) 0.67-0.75, one 0.99.
_NOTCHED_POLY_COVER = 0.8
#: Least share of the image a notched polygon must cover: that one (a 0.99 cover) covered 16 % of
#: the image, the right ones 48-67 %, the smallest field of the studies (a small iris) 41 %.
_NOTCHED_POLY_MIN_AREA = 0.25
#: Share of each of its edges inside the image the boundary must follow.
_NOTCHED_POLY_EDGE_COVER = 0.3
#: Least share of the image a logarithmic view's fitted field must leave valid to replace the image's
#: own kind ``"none"``: of 27 study frames where a log view fitted one, 26 left 0.33-0.74 valid; the
#: other, 0.12, was a strip of the field between clipped air and anatomy at the view's extremes.
_LOG_FIT_MIN_VALID = 0.25
#: A fitted field of the image as stored under this share of the image may be the air inside the field
#: (a display that puts the body within a few grey levels of its painted outside: the body read as
#: outside, the air beside it as the field); a logarithmic view's fitted field then replaces it where
#: it holds at least :data:`_AROUND_HELD` of it and is :data:`_AROUND_LARGER` times larger. On 340
#: study frames: 7 such fields (12-25 % of the image, 0.18-0.40 recall of the collimator's mask) were
#: the air, each found whole in a log view (0.88-0.99); the smallest right field, a synthetic tight
#: one of 17 %, has no larger field around it in any view.
_SMALL_FIELD = 0.3
_AROUND_HELD = 0.9
_AROUND_LARGER = 1.5
#: Most outside levels (step 1b): the body's shadow, the air's clipped and the air's grey.
_MAX_OUTSIDE_LEVELS = 3
#: Most blades cutting an iris (two pairs of shutter blades).
_IRIS_MAX_BLADES = 4


class FieldError(XRayInputError):
    """The image cannot give a usable field of view; the message names the problem in one line."""


def _num(value: object, name: str, lo: float, hi: float, *, lo_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise FieldError(f"FieldSettings.{name}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo):
        rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise FieldError(f"FieldSettings.{name}: must be in {rng}, got {value!r}")
    return v


@dataclass(frozen=True)
class FieldSettings:
    """Thresholds of :func:`detect_field` (unit, default, allowed range; why this default).

    Attributes:
        margin_px: px, 2.0, [0, 50]. Erosion of the fitted field from its boundary: the penumbra
            of the collimator and the blur of the edge spread over 1-2 px.
        min_fraction: fraction of the image, 0.10, [0, 1]. Fewer valid pixels than this raise
            :class:`FieldError`: too little anatomy to register.
        min_border_fraction: fraction of the border ring, 0.05, (0, 1]. Part of the outer 2 px that
            must lie at the outside level before collimation is considered. A large circle clipped
            by all four image edges leaves only its corners outside (~12 % of the ring for a
            radius of 2/3 of the side); the other tests (extreme, flat, model fit) reject anatomy.
        level_tolerance: fraction of the outside / in-field contrast, 0.15, (0, 0.5]. Pixels this
            close to the outside level are outside-like when growing the outside from the border.
            Large enough for the shading of a raw shadow, small enough to stay off dark anatomy
            (the boundary itself is then placed at 50 %).
        noise_k: multiples of the outside's noise (after the 3 x 3 median), 4.0, [1, 20]. Lower
            bound of the growing tolerance, so a noisy shadow grows as one region.
        min_outside_fraction: fraction of the image, 0.005, [0, 0.9]. A smaller outside (a thin
            frame, a dark pixel group at the border) is not a collimator; four small corners of a
            large round field (~1 %) are.
        max_outside_texture: fraction of the contrast, 0.05, (0, 1]. Robust spread of the outside's
            7 x 7 local means allowed: a painted outside has 0, a noise-only shadow ~noise / 7,
            dark anatomy (structure at all scales) more.
        max_boundary_px: px, 0.5, (0, 10]. Largest mean boundary deviation between a model and the
            candidate. True fields measure 0.01-0.15 px (pixel staircases, small notches where
            glyphs or dark anatomy touch the edge); a convex hull around a non-convex outline (a
            blob with solidity 0.98) measures ~0.85 px.
        circle_inlier_px: px, 1.5, (0, 10]. Distance from the circle for a boundary point to count
            as an inlier (staircase error <= 0.5 px, plus the noise of the edge).
        circle_min_inliers: fraction of the boundary points, 0.8, (0, 1]. Inliers needed to accept
            a circle (glyphs or dark anatomy at the edge may spoil up to 20 %).
        polygon_tolerance_px: px, 1.0, (0, 10]. Douglas-Peucker tolerance simplifying the convex
            hull: straight pixelated edges stay within 0.7 px of their line.
        polygon_max_vertices: count, 64, [3, 1000]. More vertices than this after simplification:
            not a shutter polygon (64 allows a circle cut by shutters).
        overlay_contrast: fraction of the in-field value range (1st-99th percentile), 0.10, [0, 1].
            Smallest step between an extreme-valued component and its surroundings for it to be
            drawn (text) rather than clipped (a saturated plateau blends into its surroundings).
        overlay_noise_k: multiples of the in-field noise, 4.0, [0, 50]. Same step in noise units.
            With the other conditions (at least ``overlay_min_px`` pixels exactly at the extreme),
            noise reaches the extreme in clusters only where the anatomy comes within ~2 noise
            sigmas of it, so such clusters stand < 4 sigmas above their surroundings.
        overlay_min_px: px (pixel count), 3, [1, 1000]. An overlay has at least this many pixels
            exactly at the extreme. Smaller extreme components are noise unless within 4 px of an
            overlay (dots, full stops) or cut by the field's edge (then judged by contrast alone).
        overlay_max_width_px: px, 8.0, [1, 100]. Widest stroke (2 x the largest inner distance - 1)
            of an overlay; thicker high-contrast components of at least ``plateau_min_px`` pixels
            count as saturated / empty plateaus.
        overlay_dilate_px: px, 2.0, [0, 20]. Overlays are grown by this (anti-aliased fringes,
            blur of the strokes).
        plateau_min_px: px (pixel count), 20, [1, 1e6]. Smallest saturated / empty plateau.
        plateau_dilate_px: px, 1.0, [0, 20]. Plateaus are grown by this (partly clipped rim).
    """

    margin_px: float = 2.0
    min_fraction: float = 0.10
    min_border_fraction: float = 0.05
    level_tolerance: float = 0.15
    noise_k: float = 4.0
    min_outside_fraction: float = 0.005
    max_outside_texture: float = 0.05
    max_boundary_px: float = 0.5
    circle_inlier_px: float = 1.5
    circle_min_inliers: float = 0.8
    polygon_tolerance_px: float = 1.0
    polygon_max_vertices: int = 64
    overlay_contrast: float = 0.10
    overlay_noise_k: float = 4.0
    overlay_min_px: int = 3
    overlay_max_width_px: float = 8.0
    overlay_dilate_px: float = 2.0
    plateau_min_px: int = 20
    plateau_dilate_px: float = 1.0

    def __post_init__(self) -> None:
        _num(self.margin_px, "margin_px", 0.0, 50.0)
        _num(self.min_fraction, "min_fraction", 0.0, 1.0)
        _num(self.min_border_fraction, "min_border_fraction", 0.0, 1.0, lo_open=True)
        _num(self.level_tolerance, "level_tolerance", 0.0, 0.5, lo_open=True)
        _num(self.noise_k, "noise_k", 1.0, 20.0)
        _num(self.min_outside_fraction, "min_outside_fraction", 0.0, 0.9)
        _num(self.max_outside_texture, "max_outside_texture", 0.0, 1.0, lo_open=True)
        _num(self.max_boundary_px, "max_boundary_px", 0.0, 10.0, lo_open=True)
        _num(self.circle_inlier_px, "circle_inlier_px", 0.0, 10.0, lo_open=True)
        _num(self.circle_min_inliers, "circle_min_inliers", 0.0, 1.0, lo_open=True)
        _num(self.polygon_tolerance_px, "polygon_tolerance_px", 0.0, 10.0, lo_open=True)
        _num(self.overlay_contrast, "overlay_contrast", 0.0, 1.0)
        _num(self.overlay_noise_k, "overlay_noise_k", 0.0, 50.0)
        _num(self.overlay_max_width_px, "overlay_max_width_px", 1.0, 100.0)
        _num(self.overlay_dilate_px, "overlay_dilate_px", 0.0, 20.0)
        _num(self.plateau_dilate_px, "plateau_dilate_px", 0.0, 20.0)
        for name, lo, hi in (("polygon_max_vertices", 3, 1000), ("overlay_min_px", 1, 1000),
                             ("plateau_min_px", 1, 1_000_000)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise FieldError(f"FieldSettings.{name}: must be an integer in [{lo}, {hi}], got {v!r}")


@dataclass(frozen=True, eq=False)
class Field:
    """The detected field of view and the valid pixels of one image.

    Attributes:
        mask: ``(H, W)`` bool, the valid pixels: inside the field, minus the exclusions.
        field_mask: ``(H, W)`` bool, the collimated field alone (the model's mask after the margin);
            all True for kind ``"none"``.
        kind: ``"none"`` (no collimation found), ``"circle"``, ``"rectangle"``, ``"polygon"`` or
            ``"iris-blades"`` (a circle cut by straight shutter blades).
        outside: colour outside the field, ``"black"``, ``"white"`` or ``None`` (kind ``"none"``).
        params: the model in px (x = column, y = row, pixel centres at integers): circle
            ``centre_x, centre_y, radius`` (iris-blades: and ``blades``, each edge's two fitted
            ends ``[[x, y], [x, y]]``); rectangle ``row0, row1, col0, col1`` (half-open, before
            the margin); polygon ``vertices [[x, y], ...]`` (a vertex may lie beyond the image
            where the field runs off it); kind ``"none"``: ``reason``.
        excluded: disjoint pixel counts inside ``field_mask``: ``overlay`` (text, rulers, markers),
            ``saturated`` (plateaus at the maximum), ``empty`` (plateaus at the minimum); and
            ``tools`` after :meth:`without_tools`.
        settings: the :class:`FieldSettings` used.
        overlay: ``(H, W)`` bool, the overlay pixels (drawn text, rulers, markers, dilated) inside
            ``field_mask``, or None; ``field_mask & ~overlay`` is the field with its clipped
            plateaus kept (what a network trained on clipped displays is shown:
            :attr:`register.xray.prepare.PreparedXRay.network_mask`).
        view: ``"display"`` or the logarithmic view the field was found in (step 6).
        tools: ``(H, W)`` bool, metal tools left out by :meth:`without_tools`, or None.
    """

    mask: np.ndarray
    field_mask: np.ndarray
    kind: str
    outside: str | None
    params: dict
    excluded: dict
    settings: FieldSettings = dataclasses.field(default_factory=FieldSettings)
    overlay: np.ndarray | None = None
    view: str = "display"
    tools: np.ndarray | None = None

    def without_tools(self, tools: np.ndarray) -> "Field":
        """This field with the metal tools ``tools`` ``(H, W)`` bool also left out of ``mask`` (a tool
        segmenter's pixels, :class:`learn.tool_mask.ToolMask`): ``excluded["tools"]`` counts those
        that were still valid (the counts stay disjoint), :attr:`tools` keeps them (inside the field)."""
        tools = np.asarray(tools)
        if tools.shape != self.mask.shape or tools.dtype != bool:
            raise FieldError(f"without_tools: a bool mask of the image's shape {self.mask.shape}, got {tools.dtype} "
                             f"{tools.shape}")
        tools = tools & self.field_mask
        return dataclasses.replace(self, mask=self.mask & ~tools, tools=tools,
                                   excluded={**self.excluded, "tools": int((tools & self.mask).sum())})

    @property
    def valid_fraction(self) -> float:
        """Fraction of the image's pixels in ``mask``."""
        return float(self.mask.mean())

    @property
    def field_fraction(self) -> float:
        """Fraction of the image's pixels in ``field_mask``."""
        return float(self.field_mask.mean())

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary (no arrays): kind, outside, params, excluded, fractions, settings."""
        return {
            "kind": self.kind,
            "view": self.view,
            "outside": self.outside,
            "params": jsonable(self.params),
            "excluded": {k: int(v) for k, v in self.excluded.items()},
            "valid_fraction": round(self.valid_fraction, 6),
            "field_fraction": round(self.field_fraction, 6),
            "settings": jsonable(dataclasses.asdict(self.settings)),
        }


# --------------------------------------------------------------------------------------------
# input


def _validated(image: object) -> np.ndarray:
    """The image as ``(H, W)`` float64, or :class:`FieldError` naming what is wrong with it."""
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise FieldError(f"the image must be 2-D (H, W), got shape {arr.shape}")
    if arr.dtype.kind not in "biuf":
        raise FieldError(f"the image must hold real numbers, got dtype {arr.dtype}")
    if min(arr.shape) < _MIN_SIZE:
        raise FieldError(f"the image is too small ({arr.shape[0]} x {arr.shape[1]}; at least "
                         f"{_MIN_SIZE} x {_MIN_SIZE} pixels)")
    img = arr.astype(np.float64)
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(img)
        if bad.any():
            raise FieldError(f"the image has {int(bad.sum())} NaN / inf pixels; give finite values")
    return img


def _quant_step(img: np.ndarray, lo: float, hi: float) -> float:
    """Smallest positive difference between the image's values (its quantisation step), capped."""
    u = np.unique(img)
    step = float(np.diff(u).min()) if u.size > 1 else 0.0
    return min(step, (hi - lo) / 64.0)


def _disk(radius: float) -> np.ndarray:
    """Disk structuring element of ``radius`` px, ``(2r+1, 2r+1)`` bool."""
    r = int(math.floor(radius))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    return (yy * yy + xx * xx) <= radius * radius + 1e-9


def _dilate(mask: np.ndarray, radius: float) -> np.ndarray:
    """``mask`` grown by a disk of ``radius`` px (pixel centres within ``radius`` of it)."""
    if radius <= 0 or not mask.any():
        return mask.copy()
    if radius < 2:
        return ndimage.binary_dilation(mask, structure=_disk(radius))
    return ndimage.distance_transform_edt(~mask) <= radius


def _mad_sigma(x: np.ndarray) -> float:
    """Robust standard deviation (1.4826 x median absolute deviation); 0 for no values."""
    if x.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


# --------------------------------------------------------------------------------------------
# step 1: the outside


@dataclass
class _Outside:
    level: float
    inside_level: float
    tol: float
    region: np.ndarray
    colour: str


def _border_ring(shape: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` bool: the outer :data:`_RING_PX` px of the image, whose levels give the outside's."""
    ring = np.zeros(shape, dtype=bool)
    ring[:_RING_PX] = ring[-_RING_PX:] = True
    ring[:, :_RING_PX] = ring[:, -_RING_PX:] = True
    return ring


def _thin_parts(mask: np.ndarray, max_width: float) -> np.ndarray:
    """The 8-connected components of ``mask`` no wider than ``max_width`` px (strokes, not blobs)."""
    if not mask.any():
        return mask
    lab, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    inner = ndimage.distance_transform_edt(mask)
    widest = 2.0 * np.asarray(ndimage.maximum(inner, lab, np.arange(1, n + 1))) - 1.0
    thin = np.concatenate([[False], widest <= max_width])
    return thin[lab]


def _find_outside(img: np.ndarray, med: np.ndarray, ext_hi: np.ndarray, ext_lo: np.ndarray,
                  lo: float, hi: float, s: FieldSettings) -> tuple[_Outside | None, str]:
    """Step 1: the outside level and region grown from the border, or ``None`` and the reason
    (one line) why the image shows no collimator."""
    H, W = img.shape
    rng = hi - lo
    ring = _border_ring((H, W))
    v = med[ring]
    hist, edges = np.histogram(v, bins=_HIST_BINS, range=(lo, hi))
    k = int(np.argmax(hist))
    m0 = 0.5 * (edges[k] + edges[k + 1])
    near0 = np.abs(v - m0) <= rng / _HIST_BINS
    level = float(np.median(v[near0]))
    sigma = _mad_sigma(v[np.abs(v - level) <= 0.1 * rng])
    far = np.abs(med - level) > max(0.1 * rng, 5.0 * sigma)
    if far.mean() < 0.01:
        return None, "no structure away from the border level"
    inside_level = float(np.median(med[far]))
    contrast = abs(inside_level - level)
    if contrast < 0.05 * rng:
        return None, "the border level lies amid the image's values"
    tol = min(max(s.level_tolerance * contrast, s.noise_k * sigma), 0.5 * contrast)
    f_border = float(np.mean(np.abs(v - level) <= tol))
    if f_border < s.min_border_fraction:
        return None, f"only {100 * f_border:.1f} % of the image border lies at one level"
    sign = 1.0 if inside_level > level else -1.0  # +1: outside darker than the field
    beyond = float(np.mean(sign * (level - med) > tol))
    if beyond > _MAX_BEYOND:
        return None, f"the border level is not an extreme ({100 * beyond:.1f} % of the pixels lie beyond it)"
    # Grow over pixels near the level and locally flat: 3 x 3 standard deviation no larger than
    # the outside's own (noise) or 1 % of the contrast, which keeps the growth out of anatomy
    # that happens to come near the level (it has texture and noise). Overlay strokes (all
    # pixels at the outside's own extreme, thin components at the other one) count as the level
    # for the flatness of the pixels around them, but are not outside themselves: strokes that
    # cross into the field become thin protrusions of it, which the opening of step 2 removes,
    # rather than notches in it.
    same, other = (ext_lo, ext_hi) if sign > 0 else (ext_hi, ext_lo)
    extreme = same | _thin_parts(other, s.overlay_max_width_px)
    flat_img = np.where(extreme, level, img)
    m1 = ndimage.uniform_filter(flat_img, size=3, mode="nearest")
    m2 = ndimage.uniform_filter(flat_img * flat_img, size=3, mode="nearest")
    sd3 = np.sqrt(np.maximum(m2 - m1 * m1, 0.0))
    ring_sd = sd3[ring][np.abs(v - level) <= tol]
    flat_thr = max(3.0 * float(np.median(ring_sd)) if ring_sd.size else 0.0, 0.01 * contrast)
    compat = (np.abs(med - level) <= tol) & (sd3 <= flat_thr)
    lab, _ = ndimage.label(compat)  # 4-neighbours
    edge_labels = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    edge_labels = edge_labels[edge_labels > 0]
    region = np.isin(lab, edge_labels)
    frac = float(region.mean())
    if frac < s.min_outside_fraction:
        return None, f"the outside region covers only {100 * frac:.1f} % of the image"
    core = ndimage.binary_erosion(region & ~extreme, structure=np.ones((3, 3), bool), iterations=3)
    if core.sum() < 50:
        core = region & ~extreme
        vals = med[core]
    else:
        vals = ndimage.uniform_filter(img, size=7, mode="nearest")[core]
    rr, cc = np.nonzero(core)
    if vals.size >= 3:  # a smooth shading (scatter, heel effect) is flat too: remove a plane
        design = np.column_stack([np.ones(vals.size), rr / H, cc / W])
        coef, *_ = np.linalg.lstsq(design[::7], vals[::7], rcond=None)
        vals = vals - design @ coef
    texture = _mad_sigma(vals) / contrast
    if texture > s.max_outside_texture:
        return None, f"the border region is not flat (texture {texture:.3f} of the contrast)"
    colour = "black" if sign > 0 else "white"
    return _Outside(level, inside_level, tol, region, colour), ""


def _with_second_level(out: _Outside, img: np.ndarray, med: np.ndarray, lo: float, hi: float,
                       s: FieldSettings) -> _Outside | None:
    """Step 1b: ``out`` with a second outside level added to its region, or ``None`` where the
    border shows none.

    Leaky blades (a collimator passing a few per cent of the beam) show a dimmed copy of what lies
    behind them: the body's shadow at the outside's own level, and the air's, far brighter, as a
    second flat level (clipped at the other extreme, or a smooth grey), into which the field
    candidate runs. The second level is the mode of the border ring (the outer 2 px) outside the
    first region, when at least ``min_border_fraction`` of the ring lies there; its region is
    grown from those border pixels, as in step 1, over pixels within half its distance from the
    first level and locally flat (3 x 3 standard deviation at most 3 x the seeds' median, or 1 %
    of the contrast): a bright air shadow is smooth, anatomy is not. It must cover at least
    ``min_outside_fraction`` of the image and be flat (``max_outside_texture``, after a plane). The
    seam between the two regions (pixels within 10 px, twice the edge band, of both: a blurred
    skin edge behind the blades) joins them.
    :func:`_detect` tries this only where the outside of one level leaves no field model, and
    keeps it only where a model then fits, so the air inside a field that runs off the image is not
    taken out of fields that fit without it."""
    H, W = img.shape
    ring = _border_ring((H, W))
    seeds = ring & ~out.region
    if seeds.sum() < s.min_border_fraction * ring.sum():
        return None
    v = med[seeds]
    hist, edges = np.histogram(v, bins=_HIST_BINS, range=(lo, hi))
    k = int(np.argmax(hist))
    level = float(np.median(v[np.abs(v - 0.5 * (edges[k] + edges[k + 1])) <= (hi - lo) / _HIST_BINS]))
    contrast = abs(out.inside_level - out.level)
    apart = abs(level - out.level)
    if apart < s.level_tolerance * contrast:
        return None
    m1 = ndimage.uniform_filter(med, size=3, mode="nearest")
    m2 = ndimage.uniform_filter(med * med, size=3, mode="nearest")
    sd3 = np.sqrt(np.maximum(m2 - m1 * m1, 0.0))
    near = seeds & (np.abs(med - level) <= 0.5 * apart)
    if near.sum() < s.min_border_fraction * ring.sum():
        return None
    flat_thr = max(3.0 * float(np.median(sd3[near])), 0.01 * contrast)
    compat = (np.abs(med - level) <= 0.5 * apart) & (sd3 <= flat_thr) & ~out.region
    lab, _ = ndimage.label(compat)  # 4-neighbours
    start = np.unique(lab[near])
    region = np.isin(lab, start[start > 0])
    if region.mean() < s.min_outside_fraction:
        return None
    rr, cc = np.nonzero(region)
    vals = med[region]
    if vals.size >= 3:  # a smooth shading (heel effect, scatter) is flat too: remove a plane
        design = np.column_stack([np.ones(vals.size), rr / H, cc / W])
        coef, *_ = np.linalg.lstsq(design[::7], vals[::7], rcond=None)
        vals = vals - design @ coef
    if _mad_sigma(vals) > s.max_outside_texture * contrast:
        return None
    # the seam between the two levels (a blurred skin edge behind the blades, between the body's
    # shadow and the air's) is neither flat nor at a level: it joins the outside where it lies
    # within twice the edge band of both regions
    seam = _dilate(out.region, 2 * _EDGE_BAND_PX) & _dilate(region, 2 * _EDGE_BAND_PX)
    return dataclasses.replace(out, region=out.region | region | seam)


# --------------------------------------------------------------------------------------------
# step 2: the candidate


def _largest_filled(mask: np.ndarray) -> tuple[np.ndarray, float]:
    """The largest 8-connected component with its holes filled, and the size of the second
    largest relative to it (0 when there is one)."""
    lab, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return mask, 0.0
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    order = np.argsort(-sizes, kind="stable")
    second = float(sizes[order[1]] / sizes[order[0]]) if n > 1 else 0.0
    return ndimage.binary_fill_holes(lab == int(order[0])), second


def _candidate(med: np.ndarray, out: _Outside) -> tuple[np.ndarray, str]:
    """The field candidate ``(H, W)`` bool and ``""``, or the reason there is none and an empty
    mask, or, where the region inside the outside level is split into large parts, the parts
    (holes filled) and that reason."""
    # padded with the edge values: the field continues beyond the image, so the opening must
    # not round the corners where the field's boundary meets the image edge
    p = _OPEN_RADIUS + 1
    rest = ndimage.binary_opening(np.pad(~out.region, p, mode="edge"), structure=_disk(_OPEN_RADIUS))[p:-p, p:-p]
    cand, second = _largest_filled(rest)
    if not cand.any():
        return cand, "nothing but the outside level"
    if second > _MAX_SECOND_PART:  # the parts, for a round field notched through (:func:`_fit_outside`)
        lab, _ = ndimage.label(rest, structure=np.ones((3, 3), bool))
        sizes = np.bincount(lab.ravel())
        sizes[0] = 0
        parts = ndimage.binary_fill_holes(np.isin(lab, np.flatnonzero(sizes >= _MAX_SECOND_PART * sizes.max())))
        return parts, (f"the region inside the outside level is split into parts "
                       f"(the second is {100 * second:.0f} % of the largest): not one field")
    full = np.ones((3, 3), bool)
    inner = ndimage.binary_erosion(cand, structure=full, iterations=_EDGE_BAND_PX, border_value=1)
    deep = ndimage.binary_erosion(inner, structure=full, iterations=_EDGE_BAND_PX, border_value=1)
    ref = inner & ~deep
    if ref.sum() < 10:
        ref = cand
    v_in = float(np.median(med[ref]))
    sign = 1.0 if v_in > out.level else -1.0
    # the in-field level next to each boundary pixel: the mean of the reference layer (5-10 px
    # deep) in a 21 x 21 window, so dark anatomy at the edge is not cut as outside
    refw = ref.astype(np.float64)
    num = ndimage.uniform_filter(np.where(ref, med, 0.0), size=_LOCAL_LEVEL_PX, mode="nearest")
    den = ndimage.uniform_filter(refw, size=_LOCAL_LEVEL_PX, mode="nearest")
    v_local = np.where(den > 0.02, num / np.maximum(den, 1e-12), v_in)
    mid = out.level + 0.5 * (v_local - out.level)
    band = cand & ~inner
    # a shutter only a few px wide at an image edge is mostly blur: its flat core is too thin to
    # grow from, so the layer along the image edges is re-thresholded too
    b = _EDGE_BAND_PX
    edge = np.zeros_like(cand)
    edge[:b] = edge[-b:] = True
    edge[:, :b] = edge[:, -b:] = True
    band |= cand & edge
    refined = cand & ~(band & (sign * (med - mid) < 0))
    refined = _largest_filled(refined)[0]
    return (refined if refined.sum() > 0.5 * cand.sum() else cand), ""


# --------------------------------------------------------------------------------------------
# step 3: shape models


def _boundary_len(model: np.ndarray) -> int:
    """Number of boundary pixels of ``model`` (px), not counting the image edges."""
    inner = ndimage.binary_erosion(model, structure=np.ones((3, 3), bool), border_value=1)
    return int((model & ~inner).sum())


def _deviation(model: np.ndarray, cand: np.ndarray) -> float:
    """Mean boundary deviation (px): pixels where model and candidate differ per boundary pixel."""
    return float((model ^ cand).sum()) / max(1, _boundary_len(model))


def _contour(cand: np.ndarray, *, every: bool = False) -> np.ndarray:
    """Sub-pixel outer contour (N, 2) as (row, col); runs along the image edge at -0.5 / H-0.5.
    ``every``: the points of every contour (a candidate in parts), not only the longest's."""
    from skimage import measure  # imported on use: the command line starts without it

    contours = measure.find_contours(np.pad(cand, 1).astype(np.float32), 0.5)
    if every:
        return np.concatenate(contours) - 1.0
    pts = max(contours, key=len) - 1.0
    return pts


def _fit_rectangle(cand: np.ndarray) -> tuple[np.ndarray, dict]:
    """Axis-aligned rectangle: the rows / columns where the candidate fills at least half of its
    widest row / column (robust to notches and rounded corners); half-open bounds."""
    rows = cand.sum(axis=1)
    cols = cand.sum(axis=0)
    rsel = np.nonzero(rows >= 0.5 * rows.max())[0]
    csel = np.nonzero(cols >= 0.5 * cols.max())[0]
    r0, r1, c0, c1 = int(rsel[0]), int(rsel[-1]) + 1, int(csel[0]), int(csel[-1]) + 1
    model = np.zeros_like(cand)
    model[r0:r1, c0:c1] = True
    return model, {"row0": r0, "row1": r1, "col0": c0, "col1": c1}


def _circle_mask(shape: tuple[int, int], cx: float, cy: float, r: float) -> np.ndarray:
    """``(H, W)`` bool: pixel centres within ``r`` px of (``cx`` = column, ``cy`` = row)."""
    H, W = shape
    yy = np.arange(H, dtype=np.float64)[:, None] - cy
    xx = np.arange(W, dtype=np.float64)[None, :] - cx
    return yy * yy + xx * xx <= r * r


def _fit_circle_points(x: np.ndarray, y: np.ndarray, inlier_px: float) -> tuple[float, float, float, np.ndarray] | None:
    """Robust circle through points (x, y) px: seeded RANSAC over triples, then geometric least
    squares on the inliers (within ``inlier_px``), repeated until the inliers settle.
    Returns ``(cx, cy, r, inlier mask)`` or ``None``."""
    n = x.size
    rng = np.random.default_rng(20240611)
    idx = rng.integers(0, n, size=(_RANSAC_TRIALS, 3))
    ax, bx, cxp = x[idx[:, 0]], x[idx[:, 1]], x[idx[:, 2]]
    ay, by, cyp = y[idx[:, 0]], y[idx[:, 1]], y[idx[:, 2]]
    d = 2.0 * (ax * (by - cyp) + bx * (cyp - ay) + cxp * (ay - by))
    ok = np.abs(d) > 1e-6
    if not ok.any():
        return None
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cxp * cxp + cyp * cyp
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (a2 * (by - cyp) + b2 * (cyp - ay) + c2 * (ay - by)) / d
        uy = (a2 * (cxp - bx) + b2 * (ax - cxp) + c2 * (bx - ax)) / d
    r = np.hypot(ax - ux, ay - uy)
    ok &= np.isfinite(r) & (r > 2.0)
    if not ok.any():
        return None
    ux, uy, r = ux[ok], uy[ok], r[ok]
    step = max(1, n // 800)
    xs, ys = x[::step], y[::step]
    res = np.abs(np.hypot(xs[None, :] - ux[:, None], ys[None, :] - uy[:, None]) - r[:, None])
    best = int(np.argmax((res <= inlier_px).sum(axis=1)))
    cx, cy, rad = float(ux[best]), float(uy[best]), float(r[best])
    inl = np.abs(np.hypot(x - cx, y - cy) - rad) <= inlier_px
    for _ in range(4):
        if inl.sum() < 3:
            return None
        xi, yi = x[inl], y[inl]
        for _ in range(8):  # geometric least squares (Gauss-Newton)
            dx, dy = xi - cx, yi - cy
            dist = np.hypot(dx, dy)
            dist = np.where(dist < 1e-9, 1e-9, dist)
            J = np.stack([-dx / dist, -dy / dist, -np.ones_like(dist)], axis=1)
            delta, *_ = np.linalg.lstsq(J, -(dist - rad), rcond=None)
            cx, cy, rad = cx + delta[0], cy + delta[1], rad + delta[2]
            if np.abs(delta).max() < 1e-4:
                break
        new = np.abs(np.hypot(x - cx, y - cy) - rad) <= inlier_px
        if np.array_equal(new, inl):
            break
        inl = new
    return float(cx), float(cy), float(abs(rad)), inl


def _fit_circle(cand: np.ndarray, pts: np.ndarray, s: FieldSettings) -> tuple[np.ndarray, dict] | None:
    """Circle fitted to the candidate's boundary points away from the image edges (so a circle
    clipped by the image works); ``(mask, params)`` or ``None`` when too few points agree."""
    fit = _circle_off_edges(cand, pts, s, s.circle_min_inliers)
    if fit is None:
        return None
    _, cx, cy, rad, _ = fit
    return _circle_mask(cand.shape, cx, cy, rad), {"centre_x": cx, "centre_y": cy, "radius": rad}


def _circle_off_edges(cand: np.ndarray, pts: np.ndarray, s: FieldSettings,
                      min_inliers: float) -> tuple[np.ndarray, float, float, float, np.ndarray] | None:
    """The circle through the boundary points ``pts`` (N, 2) (row, col) that do not run along the
    image edges, if at least ``min_inliers`` of those agree and its radius is sane: ``(off_edges
    (N,) bool, cx, cy, radius, inliers (M,) bool over the off-edge points)`` or ``None``."""
    H, W = cand.shape
    r, c = pts[:, 0], pts[:, 1]
    off_edges = (r > -0.25) & (r < H - 0.75) & (c > -0.25) & (c < W - 0.75)
    if off_edges.sum() < 20:
        return None
    fit = _fit_circle_points(c[off_edges], r[off_edges], s.circle_inlier_px)
    if fit is None:
        return None
    cx, cy, rad, inl = fit
    if inl.mean() < min_inliers or not (3.0 < rad < 4.0 * max(H, W)):
        return None
    return off_edges, cx, cy, rad, inl


def _ransac_line(q: np.ndarray, inlier_px: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best line through points ``q`` (N, 2) (row, col) by seeded RANSAC over pairs, refitted by
    total least squares on its inliers: ``(point, unit direction, inlier mask)``."""
    n = len(q)
    idx = rng.integers(0, n, size=(_RANSAC_TRIALS, 2))
    a, b = q[idx[:, 0]], q[idx[:, 1]]
    d = b - a
    ln = np.hypot(d[:, 0], d[:, 1])
    ok = ln > 2.0
    if not ok.any():
        return q.mean(axis=0), np.array([1.0, 0.0]), np.zeros(n, bool)
    a, d = a[ok], d[ok] / ln[ok, None]
    across = np.abs((q[None, :, 0] - a[:, None, 0]) * d[:, None, 1] - (q[None, :, 1] - a[:, None, 1]) * d[:, None, 0])
    best = int(np.argmax((across <= inlier_px).sum(axis=1)))
    m, u = a[best], d[best]
    inl = across[best] <= inlier_px
    for _ in range(3):  # total least squares on the inliers, then new inliers
        if inl.sum() < 2:
            break
        m = q[inl].mean(axis=0)
        u = np.linalg.svd(q[inl] - m, full_matrices=False)[2][0]
        inl = np.abs((q[:, 0] - m[0]) * u[1] - (q[:, 1] - m[1]) * u[0]) <= inlier_px
    return m, u, inl


def _fit_iris_blades(cand: np.ndarray, pts: np.ndarray, s: FieldSettings,
                     outside: np.ndarray | None = None) -> tuple[np.ndarray, dict] | None:
    """Circle cut by straight blades (an iris with shutter blades, common on C-arms).

    The circle is fitted to the boundary points on it (at least ``_IRIS_MIN_ARC`` of them), then
    up to ``_IRIS_MAX_BLADES`` straight lines to the points off it (seeded RANSAC, each line with
    at least ``_IRIS_MIN_BLADE_PTS`` points covering ``_IRIS_BLADE_COVER`` of its chord through
    the circle); the field is the circle's inside
    on the candidate's side of every line. The circle and lines together must explain
    ``_IRIS_MIN_EXPLAINED`` of the points (notches where anatomy at the outside's level or a glyph
    touches the edge spoil the rest). ``(mask, params)`` or ``None``."""
    H, W = cand.shape
    fit = _circle_off_edges(cand, pts, s, _IRIS_MIN_ARC)
    if fit is None:
        return None
    inside, cx, cy, rad, on_circle = fit
    q_all = pts[inside]
    rest = ~on_circle
    explained = on_circle.copy()
    fill = np.argwhere(cand).mean(axis=0)  # (row, col): the field's side of every blade
    circle = _circle_mask((H, W), cx, cy, rad)
    model = circle.copy()
    rows = np.arange(H, dtype=np.float64)[:, None]
    cols = np.arange(W, dtype=np.float64)[None, :]
    rng = np.random.default_rng(20261124)
    blades = []
    for _ in range(_IRIS_MAX_BLADES):
        if rest.sum() < _IRIS_MIN_BLADE_PTS:
            break
        m, u, inl = _ransac_line(q_all[rest], s.circle_inlier_px, rng)
        if inl.sum() < _IRIS_MIN_BLADE_PTS:
            break
        nrm = np.array([-u[1], u[0]])  # (row, col) normal, towards the field
        if (fill - m) @ nrm < 0:
            nrm = -nrm
        # a blade is a supporting line of the field: refit on the outer half of its points
        # (notches of anatomy at the outside's level lie inside), then the strip just beyond it
        # must be outside (a line through notches' rims cuts the field: the candidate fills it)
        q = q_all[rest][inl]
        for _ in range(2):
            depth = (q - m) @ nrm
            outer = q[depth <= np.median(depth)]
            if len(outer) < 3:
                break
            m = outer.mean(axis=0)
            u = np.linalg.svd(outer - m, full_matrices=False)[2][0]
            nrm = np.array([-u[1], u[0]]) if (fill - m) @ np.array([-u[1], u[0]]) >= 0 else np.array([u[1], -u[0]])
        depth_px = (rows - m[0]) * nrm[0] + (cols - m[1]) * nrm[1]
        strip = circle & (depth_px < -s.circle_inlier_px) & (depth_px >= -s.circle_inlier_px - _IRIS_STRIP_PX)
        if strip.any() and (cand & strip).sum() > _IRIS_BLADE_SPILL * strip.sum():
            break
        # and what it cuts off the circle is the outside (grown from the border over the flat
        # outside level), not anatomy near that level whose rim happens to be straight
        cut = circle & (depth_px < -s.circle_inlier_px)
        if outside is not None and cut.any() and (outside & cut).sum() < _IRIS_CUT_OUTSIDE * cut.sum():
            break
        dist = abs((np.array([cy, cx]) - m) @ nrm)
        chord = 2.0 * math.sqrt(max(rad * rad - dist * dist, 0.0))  # px of the line inside the circle
        if inl.sum() < _IRIS_BLADE_COVER * chord or rad - dist < _IRIS_MIN_CUT * rad:
            break  # a notch (dark anatomy, a glyph), a line missing the circle or grazing it where
            # the circle meets the image edge: not a blade
        model &= ((rows - m[0]) * nrm[0] + (cols - m[1]) * nrm[1]) >= -0.5
        idx = np.nonzero(rest)[0][inl]
        explained[idx] = True
        rest[idx] = False
        t = (q_all[idx] - m) @ u
        blades.append([[float(e[1]), float(e[0])] for e in (m + t.min() * u, m + t.max() * u)])
    if not model.any() or explained.mean() < _IRIS_MIN_EXPLAINED:
        return None
    params = {"centre_x": float(cx), "centre_y": float(cy), "radius": float(rad)}
    return model, (params | {"blades": blades} if blades else params)

def _fit_notched_circle(cand: np.ndarray, pts: np.ndarray, s: FieldSettings,
                        outside: np.ndarray | None) -> tuple[np.ndarray, dict] | None:
    """A round field whose edge is clean along most of its visible circumference, notched deeply
    elsewhere by anatomy clipped at the outside's level (dense bone shown black next to a black
    outside, at high resolution: notches of 20-40 px per boundary px at 1024 px).

    The circle is fitted (seeded RANSAC) to the boundary points off the image edges, its inlier
    distance scaled with the image side like the iris limits (:data:`_IRIS_REFERENCE_SIDE_PX`: the
    edge's blur spans more pixels at a finer pixel). It is accepted when its inliers cover at least
    :data:`_NOTCHED_MIN_COVER` of the circumference inside the image (1-degree bins: the ragged
    outlines of the notches add boundary points, not arc), the candidate runs beyond it by at most
    ``_IRIS_MAX_BEYOND_PX`` (scaled) per boundary px, and what it lacks inside the circle (the
    notches) lies in the outside region grown over the flat outside level (step 1), not in
    textured anatomy. ``(mask, params)`` or ``None``."""
    H, W = cand.shape
    if outside is None:
        return None
    scale = max(1.0, max(H, W) / _IRIS_REFERENCE_SIDE_PX)
    r, c = pts[:, 0], pts[:, 1]
    off = (r > -0.25) & (r < H - 0.75) & (c > -0.25) & (c < W - 0.75)
    if off.sum() < 20:
        return None
    inlier_px = s.circle_inlier_px * scale
    fit = _fit_circle_points(c[off], r[off], inlier_px)
    if fit is None:
        return None
    cx, cy, rad, inl = fit
    if not (3.0 < rad < 4.0 * max(H, W)) or inl.sum() < 20:
        return None
    ang = np.deg2rad(np.arange(360) + 0.5)
    ax, ay = cx + rad * np.cos(ang), cy + rad * np.sin(ang)
    visible = (ax >= -0.5) & (ax <= W - 0.5) & (ay >= -0.5) & (ay <= H - 0.5)
    if visible.sum() < 90:  # a quarter of the circle at least in view
        return None
    hit = np.zeros(360, bool)
    hit[(np.rad2deg(np.arctan2(r[off][inl] - cy, c[off][inl] - cx)).astype(np.int64) % 360)] = True
    cover = float((hit & visible).sum() / visible.sum())
    if cover < _NOTCHED_MIN_COVER:
        return None
    model = _circle_mask((H, W), cx, cy, rad)
    n = max(1, _boundary_len(model))
    if float((cand & ~model).sum()) / n > _IRIS_MAX_BEYOND_PX * scale:
        return None
    notches = model & ~cand
    if notches.any() and (outside & notches).sum() < _NOTCHED_OUTSIDE * notches.sum():
        return None
    return model, {"centre_x": float(cx), "centre_y": float(cy), "radius": float(rad),
                   "arc_cover": round(cover, 3), "notched": round(float(notches.sum()) / n, 2)}


def _fit_polygon(cand: np.ndarray, pts: np.ndarray, s: FieldSettings) -> tuple[np.ndarray, dict] | None:
    """Convex polygon: hull of the boundary points, simplified and refined to straight edges."""
    from scipy.spatial import ConvexHull, QhullError  # imported on use: the command line starts without it

    H, W = cand.shape
    pts = np.column_stack([np.clip(pts[:, 0], -0.5, H - 0.5), np.clip(pts[:, 1], -0.5, W - 0.5)])
    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError):
        return None
    poly = _simplify_closed(pts[hull.vertices], s.polygon_tolerance_px)
    if len(poly) < 3 or len(poly) > s.polygon_max_vertices:
        return None
    # shutter edges are long; edges of a few px are corner cuts left by the median filter, the
    # opening and blur: drop as many as still gives a clean convex polygon that fits the
    # candidate at least as well (a field with arcs keeps its many short edges)
    model = _convex_polygon_mask((H, W), poly)
    dev = _deviation(model, cand)
    for min_edge in (3 * _POLY_MIN_EDGE_PX, 2 * _POLY_MIN_EDGE_PX, _POLY_MIN_EDGE_PX):
        refined = _refine_polygon(poly, pts, (H, W), min_edge)
        if refined is None:
            continue
        refined_model = _convex_polygon_mask((H, W), refined)
        if _deviation(refined_model, cand) <= dev:
            poly, model = refined, refined_model
            break
    vertices = [[float(p[1]), float(p[0])] for p in poly]
    return model, {"vertices": vertices}


def _notched_polygon(cand: np.ndarray, pts: np.ndarray, fit: tuple[np.ndarray, dict],
                     s: FieldSettings) -> tuple[np.ndarray, dict] | None:
    """The convex polygon ``fit`` (:func:`_fit_polygon`) accepted one-sided, as the notched circle
    is: shutter blades whose straight edges are notched by anatomy clipped at the outside's level.

    Accepted when it has at most :data:`_NOTCHED_POLY_MAX_VERTICES` vertices (shutters, not the
    hull of a rounded outline), covers at least :data:`_NOTCHED_POLY_MIN_AREA` of the image (a
    small one-sided polygon was a part of the field: the air in it, a region of bone), the candidate's boundary points lie within ``circle_inlier_px``
    (scaled with the side) of at least :data:`_NOTCHED_POLY_COVER` of its perimeter inside the image
    and of :data:`_NOTCHED_POLY_EDGE_COVER` of each edge's (a hull edge bridging a concavity of a
    body outline has support at its ends only; 1 px samples, not counting the image's edges, where
    the field runs off it), and the candidate runs beyond it and lacks inside it no more than the
    iris's limits allow (``_IRIS_MAX_BEYOND_PX``, ``_IRIS_MAX_NOTCH_PX`` per boundary px, scaled):
    the notches are dark anatomy at the edge that the 50 % threshold of step 2 cut, not clipped
    (the hull of a lobed outline lacks whole bays). ``(mask, params)`` with ``edge_cover`` and
    ``notched`` added, or ``None``."""
    from scipy.spatial import cKDTree  # imported on use: the command line starts without it

    model, params = fit
    H, W = cand.shape
    verts = np.array([[v[1], v[0]] for v in params["vertices"]])  # (row, col)
    if len(verts) > _NOTCHED_POLY_MAX_VERTICES or len(pts) < 20:
        return None
    scale = max(1.0, max(H, W) / _IRIS_REFERENCE_SIDE_PX)
    tree = cKDTree(pts)
    covered = total = 0
    for a, b in zip(verts, np.roll(verts, -1, axis=0)):
        t = np.linspace(0.0, 1.0, max(2, int(np.ceil(np.hypot(*(b - a))))) + 1)
        q = a[None, :] + t[:, None] * (b - a)[None, :]
        inside = (q[:, 0] > 0.0) & (q[:, 0] < H - 1.0) & (q[:, 1] > 0.0) & (q[:, 1] < W - 1.0)
        if inside.sum() < 10:
            continue
        d, _ = tree.query(q[inside])
        hit = d <= s.circle_inlier_px * scale
        if hit.mean() < _NOTCHED_POLY_EDGE_COVER:
            return None
        covered += int(hit.sum())
        total += int(inside.sum())
    if total == 0 or covered < _NOTCHED_POLY_COVER * total:
        return None
    if model.mean() < _NOTCHED_POLY_MIN_AREA:
        return None
    n = max(1, _boundary_len(model))
    notched = float((model & ~cand).sum()) / n
    if float((cand & ~model).sum()) / n > _IRIS_MAX_BEYOND_PX * scale or notched > _IRIS_MAX_NOTCH_PX * scale:
        return None
    return model, {**params, "edge_cover": round(covered / total, 3), "notched": round(notched, 2)}


def _convex_polygon_mask(shape: tuple[int, int], poly: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: pixel centres inside (or on) the convex polygon ``poly`` (N, 2) (row, col)."""
    H, W = shape
    p = np.asarray(poly, dtype=np.float64)
    q = np.roll(p, -1, axis=0)
    # inside: the same side of every edge as the centroid; edge (p -> q): a*col + b*row + c >= 0
    a = -(q[:, 0] - p[:, 0])
    b = q[:, 1] - p[:, 1]
    c = -(a * p[:, 1] + b * p[:, 0])
    centre = p.mean(axis=0)
    flip = (a * centre[1] + b * centre[0] + c) < 0
    a, b, c = np.where(flip, -a, a), np.where(flip, -b, b), np.where(flip, -c, c)
    rows = np.arange(H, dtype=np.float64)[:, None]
    rhs = -(b[None, :] * rows + c[None, :])  # a * col >= rhs
    eps = 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = rhs / a[None, :]
    lo = np.max(np.where(a[None, :] > eps, bound, -np.inf), axis=1)
    hi = np.min(np.where(a[None, :] < -eps, bound, np.inf), axis=1)
    flat_ok = np.all(np.where(np.abs(a)[None, :] <= eps, rhs <= eps, True), axis=1)
    cols = np.arange(W, dtype=np.float64)[None, :]
    return (cols >= lo[:, None] - eps) & (cols <= hi[:, None] + eps) & flat_ok[:, None]


def _douglas_peucker(chain: np.ndarray, tol: float) -> list[int]:
    """Indices kept by Douglas-Peucker on an open chain (K, 2) (both ends kept)."""
    keep = [0, len(chain) - 1]
    stack = [(0, len(chain) - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        a, b = chain[i], chain[j]
        ab = b - a
        norm = math.hypot(ab[0], ab[1])
        rel = chain[i + 1:j] - a
        if norm < 1e-12:
            dist = np.hypot(rel[:, 0], rel[:, 1])
        else:
            dist = np.abs(rel[:, 0] * ab[1] - rel[:, 1] * ab[0]) / norm
        k = int(np.argmax(dist))
        if dist[k] > tol:
            keep.append(i + 1 + k)
            stack += [(i, i + 1 + k), (i + 1 + k, j)]
    return sorted(keep)


def _simplify_closed(ring: np.ndarray, tol: float) -> np.ndarray:
    """Douglas-Peucker on a closed polygon (N, 2), split at vertex 0 and the vertex farthest from it."""
    far = int(np.argmax(np.hypot(*(ring - ring[0]).T)))
    if far == 0:
        return ring[:1]
    first = ring[: far + 1]
    second = np.vstack([ring[far:], ring[:1]])
    k1 = _douglas_peucker(first, tol)
    k2 = [far + k for k in _douglas_peucker(second, tol)]
    idx = [k % len(ring) for k in k1[:-1] + k2[:-1]]
    return ring[idx]


def _refine_polygon(poly: np.ndarray, pts: np.ndarray, shape: tuple[int, int],
                    min_edge: float) -> np.ndarray | None:
    """Straight edges fitted to the boundary points, intersected: corners rounded by the median
    filter and the opening become sharp again, and the edges shorter than ``min_edge`` px that
    cut them go.

    ``poly`` (N, 2) (row, col) convex, ``pts`` (M, 2) the boundary points. Returns the refined
    polygon, or ``None`` when the refinement is not a clean convex polygon near ``poly``.
    """
    # merge edges that continue each other (Douglas-Peucker may split a long edge)
    poly = np.asarray(poly, dtype=np.float64)
    changed = True
    while changed and len(poly) > 3:
        changed = False
        d_in = poly - np.roll(poly, 1, axis=0)
        d_out = np.roll(poly, -1, axis=0) - poly
        cross = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
        norm = np.hypot(*d_in.T) * np.hypot(*d_out.T)
        sin_turn = np.abs(cross) / np.maximum(norm, 1e-12)
        k = int(np.argmin(sin_turn))
        if sin_turn[k] < math.sin(math.radians(_POLY_MERGE_DEG)):
            poly = np.delete(poly, k, axis=0)
            changed = True
    nxt = np.roll(poly, -1, axis=0)
    lengths = np.hypot(*(nxt - poly).T)
    long_edges = np.nonzero(lengths >= min_edge)[0]
    if len(long_edges) < 3:
        return None
    def tls(q: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - c, full_matrices=False)
        return c, (vt[0] if vt[0] @ u >= 0 else -vt[0])

    lines = []  # (point, direction, supporting points)
    for i in long_edges:
        a, b = poly[i], nxt[i]
        u = (b - a) / lengths[i]
        c, d, support = a, u, pts[:0]
        lo_t, hi_t = 2.0, lengths[i] - 2.0  # along the edge, clear of its ends
        for _ in range(3):  # total least squares on the points near the line, then refit
            rel = pts - c
            along = rel @ d + (c - a) @ d
            across = rel[:, 0] * d[1] - rel[:, 1] * d[0]
            sel = (np.abs(across) <= 1.5) & (along >= lo_t) & (along <= hi_t)
            if sel.sum() < 5:
                break
            support = pts[sel]
            c, d = tls(support, u)
        lines.append((c, d, support))
    # consecutive lines that continue each other are one edge
    sin_merge = math.sin(math.radians(_POLY_MERGE_DEG))
    k = 0
    while len(lines) > 3 and k < len(lines):
        (c1, d1, s1), (c2, d2, s2) = lines[k], lines[(k + 1) % len(lines)]
        if abs(d1[0] * d2[1] - d1[1] * d2[0]) < sin_merge and d1 @ d2 > 0:
            both = np.vstack([s1, s2])
            merged = tls(both, d1) + (both,) if len(both) >= 5 else lines[k]
            lines[k] = merged
            del lines[(k + 1) % len(lines)]
            k = 0
            continue
        k += 1
    if len(lines) < 3:
        return None
    out = []
    m = len(lines)
    for k in range(m):
        (c1, d1, _), (c2, d2, _) = lines[k], lines[(k + 1) % m]
        den = d1[0] * d2[1] - d1[1] * d2[0]
        if abs(den) < math.sin(math.radians(2.0)):
            return None
        t = ((c2[0] - c1[0]) * d2[1] - (c2[1] - c1[1]) * d2[0]) / den
        out.append(c1 + t * d1)
    out = np.array(out)  # vertices may lie beyond the image: the field continues there
    # sanity: convex, same orientation, every vertex near the simplified hull
    e = np.roll(out, -1, axis=0) - out
    cross = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
    if not (np.all(cross >= -1e-6) or np.all(cross <= 1e-6)):
        return None
    dmin = np.min(np.hypot(out[:, None, 0] - pts[None, :, 0], out[:, None, 1] - pts[None, :, 1]), axis=1)
    if dmin.max() > 2.0 * min_edge:
        return None
    return out


def _fit_model(cand: np.ndarray, s: FieldSettings, outside: np.ndarray | None = None) -> tuple[str, np.ndarray | None, dict]:
    """Step 3: the simplest model (rectangle, circle, polygon) within ``max_boundary_px`` of the
    candidate: ``(kind, mask, params)``, or ``("none", None, {"reason": ...})``."""
    pts = _contour(cand)
    devs = {}
    model, params = _fit_rectangle(cand)
    devs["rectangle"] = _deviation(model, cand)
    if devs["rectangle"] <= s.max_boundary_px:
        return "rectangle", model, params
    fit = _fit_circle(cand, pts, s)
    if fit is not None:
        devs["circle"] = _deviation(fit[0], cand)
        if devs["circle"] <= s.max_boundary_px:
            return "circle", fit[0], fit[1]
    polygon = _fit_polygon(cand, pts, s)
    if polygon is not None:
        devs["polygon"] = _deviation(polygon[0], cand)
        if devs["polygon"] <= s.max_boundary_px:
            return "polygon", polygon[0], polygon[1]
    fit = _fit_iris_blades(cand, pts, s, outside)
    if fit is not None:
        # one-sided: dark (or bright) anatomy at the outside's level may notch the candidate deeply
        # along an iris's edge and its blades; the candidate must not run beyond the model
        kind = "iris-blades" if "blades" in fit[1] else "circle"
        n = max(1, _boundary_len(fit[0]))
        devs[f"notched {kind} (beyond)"] = float((cand & ~fit[0]).sum()) / n
        devs[f"notched {kind} (notches)"] = float((fit[0] & ~cand).sum()) / n
        scale = max(1.0, max(cand.shape) / _IRIS_REFERENCE_SIDE_PX)  # the same iris at a finer pixel
        if (devs[f"notched {kind} (beyond)"] <= _IRIS_MAX_BEYOND_PX * scale
                and devs[f"notched {kind} (notches)"] <= _IRIS_MAX_NOTCH_PX * scale):
            return kind, fit[0], fit[1]
    fit = _fit_notched_circle(cand, pts, s, outside)
    if fit is not None:
        return "circle", fit[0], fit[1]
    fit = _notched_polygon(cand, pts, polygon, s) if polygon is not None else None
    if fit is not None:
        return "polygon", fit[0], fit[1]
    txt = ", ".join(f"{k} {v:.2f} px" for k, v in devs.items())
    return "none", None, {"reason": f"no field model fits the candidate (mean boundary deviation: {txt})"}


def _erode_model(kind: str, model: np.ndarray, params: dict, margins: tuple[float, ...]) -> list[np.ndarray]:
    """The model's mask ``(H, W)`` eroded by each of ``margins`` px from its boundary (not from
    the image edges: the field continues beyond them)."""
    if kind == "circle":
        return [_circle_mask(model.shape, params["centre_x"], params["centre_y"], params["radius"] - m)
                for m in margins]
    p = int(math.ceil(max(margins))) + 1
    dist = ndimage.distance_transform_edt(np.pad(model, p, mode="edge"))[p:-p, p:-p]
    return [model.copy() if m <= 0 else dist > m for m in margins]


# --------------------------------------------------------------------------------------------
# step 4: exclusions


def _classify_extreme(img: np.ndarray, ext: np.ndarray, value: float, within: np.ndarray,
                      step_thr: float, s: FieldSettings) -> tuple[np.ndarray, np.ndarray]:
    """Overlay and plateau masks among the components of ``ext & within`` (at ``value``)."""
    H, W = img.shape
    overlay = np.zeros((H, W), dtype=bool)
    plateau = np.zeros((H, W), dtype=bool)
    comp = ext & within
    if not comp.any():
        return overlay, plateau
    full = np.ones((3, 3), bool)
    lab, n = ndimage.label(comp, structure=full)
    sizes = np.bincount(lab.ravel())
    # pieces of glyphs cut by the field's edge (extreme pixels continue beyond it) are judged
    # whatever their size
    cut = np.zeros(n + 1, dtype=bool)
    cut[lab[comp & ndimage.binary_dilation(ext & ~within, structure=full)]] = True
    cut[0] = False
    small = np.zeros(n + 1, dtype=bool)  # too small to judge alone: joins a neighbour, if any
    for i, sl in enumerate(ndimage.find_objects(lab), start=1):
        size = int(sizes[i])
        if size < s.overlay_min_px and not cut[i]:
            small[i] = True
            continue
        r0, r1 = max(0, sl[0].start - 3), min(H, sl[0].stop + 3)
        c0, c1 = max(0, sl[1].start - 3), min(W, sl[1].stop + 3)
        sub = lab[r0:r1, c0:c1] == i
        d1 = ndimage.binary_dilation(sub, structure=full)
        d2 = ndimage.binary_dilation(d1, structure=full)
        around = ~ext[r0:r1, c0:c1] & within[r0:r1, c0:c1]
        ring = d2 & ~d1 & around
        if ring.sum() < 3:
            ring = d2 & ~sub & around
        high = bool(ring.any()) and abs(value - float(np.median(img[r0:r1, c0:c1][ring]))) >= step_thr
        width = 2.0 * float(ndimage.distance_transform_edt(np.pad(sub, 1)).max()) - 1.0
        thin = width <= s.overlay_max_width_px
        # drawn strokes sit exactly at the extreme; a sharp anatomical peak touching it does not
        exact = int((img[r0:r1, c0:c1][sub] == value).sum())
        high = high and exact >= min(size, s.overlay_min_px)
        if high and (thin or size < s.plateau_min_px):
            overlay[r0:r1, c0:c1] |= sub
        elif size >= s.plateau_min_px:
            plateau[r0:r1, c0:c1] |= sub
        else:
            small[i] = True
    # pieces next to a found overlay / plateau belong to it (dots of i, the frayed rim of a
    # clipped region); isolated ones are noise touching the extreme and stay
    for found, allowed in ((overlay, sizes < s.overlay_min_px), (plateau, small)):
        if found.any() and small.any():
            allowed = allowed & small
            reach = _dilate(found, _DOT_REACH_PX)
            near = np.unique(lab[reach & allowed[lab]])
            found |= np.isin(lab, near[near > 0])
    return overlay, plateau


def _exclusions(img: np.ndarray, within: np.ndarray, field: np.ndarray, lo: float, hi: float, q: float,
                med: np.ndarray, s: FieldSettings) -> dict[str, np.ndarray]:
    """Overlay / saturated / empty masks ``(H, W)`` bool inside ``field``; the extreme-valued
    components are judged inside ``within`` (the model 1 px in: glyphs crossing into the margin
    are judged whole, the outside itself stays out)."""
    ext_hi = img >= hi - q
    ext_lo = img <= lo + q
    vals = img[within & ~ext_hi & ~ext_lo]
    if vals.size < 10:
        vals = img[within]
    p1, p99 = np.percentile(vals, [1, 99])
    noise = _mad_sigma((img - med)[within & ~ext_hi & ~ext_lo]) if vals.size >= 10 else 0.0
    step_thr = max(s.overlay_contrast * float(p99 - p1), s.overlay_noise_k * noise, q)
    ov_hi, sat = _classify_extreme(img, ext_hi, hi, within, step_thr, s)
    ov_lo, emp = _classify_extreme(img, ext_lo, lo, within, step_thr, s)
    overlay = _dilate(ov_hi | ov_lo, s.overlay_dilate_px) & field
    saturated = _dilate(sat, s.plateau_dilate_px) & field & ~overlay
    empty = _dilate(emp, s.plateau_dilate_px) & field & ~overlay & ~saturated
    return {"overlay": overlay, "saturated": saturated, "empty": empty}


# --------------------------------------------------------------------------------------------


def attenuating_pieces(tools: np.ndarray, image: np.ndarray, valid: np.ndarray,
                       min_rank: float = TOOL_MIN_ATTENUATION_RANK) -> np.ndarray:
    """The pieces of ``tools`` ``(H, W)`` bool (8-connected) whose median pixel of ``image`` ``(H, W)``
    (attenuation bright: line-integral-like, as the intensity step leaves it) is above more than
    ``min_rank`` of ``image``'s values over ``valid`` ``(H, W)`` bool (the field less the tools);
    ``(H, W)`` bool. A piece that attenuates less than most of the field is not metal.

    Example::

        >>> import numpy as np
        >>> img = np.tile(np.linspace(0.0, 1.0, 8), (8, 1))   # attenuation rises to the right
        >>> tools = np.zeros((8, 8), bool); tools[2:4, 0] = tools[2:4, 7] = True
        >>> attenuating_pieces(tools, img, ~tools)[2:4].nonzero()[1].tolist()
        [7, 7]
    """
    tools, valid = np.asarray(tools, bool), np.asarray(valid, bool)
    if tools.shape != image.shape or valid.shape != image.shape:
        raise FieldError(f"attenuating_pieces: tools {tools.shape}, image {image.shape} and valid {valid.shape} "
                         "must have one shape")
    if not 0.0 <= min_rank < 1.0:
        raise FieldError(f"attenuating_pieces: min_rank must be a share in [0, 1), got {min_rank}")
    values = np.sort(np.asarray(image, float)[valid])
    if not tools.any() or values.size == 0:
        return tools.copy()
    labels, n = ndimage.label(tools, structure=np.ones((3, 3), bool))
    medians = np.asarray(ndimage.median(image, labels, index=np.arange(1, n + 1)), float).reshape(n)
    ranks = np.searchsorted(values, medians, side="left") / values.size
    return np.isin(labels, 1 + np.flatnonzero(ranks > min_rank))


def detect_field(image: np.ndarray, settings: FieldSettings | None = None, *, raw: bool = False) -> Field:
    """Find the collimated field and the valid pixels of an X-ray image (method: module docstring).

    ``raw=True``: ``image`` is the detector's raw signal (proportional to the transmitted intensity:
    DICOM "FOR PROCESSING", a data set's raw frames). There the collimator's shadow is not one flat
    level: it is the signal behind it times the blades' transmission, so it keeps the anatomy's
    texture, and air beside the body is a bright flat plateau that a painted outside would look like.
    The field is then found by its edge instead (:func:`_detect_raw`): the one place where the
    signal drops by :data:`RAW_EDGE_RATIO` or more within two pixels all along a closed shape.

    Where the image as stored leaves too little field (:class:`FieldError`, the field or the valid
    pixels under ``settings.min_fraction``), the detection runs again on its logarithmic views
    (:data:`LOG_VIEWS`), the end where most pixels lie first: a linear display (intensity, not its
    logarithm) squeezes the anatomy into the few grey levels next to one extreme, where it is hard
    to tell from a painted or leaky-blade outside at that extreme (a 70 kV pelvis at 10 bits: the
    anatomy within 20 counts of black), and the logarithm spreads those levels apart as a log
    display would. The mask is of the image's own pixels either way; :attr:`Field.view` says which
    view found it. Where the image as stored fits no shape model (kind ``"none"``), a logarithmic
    view's fitted model (leaving at least a quarter of the image valid) replaces it; where it fits
    one to less than :data:`_SMALL_FIELD` of the image, a log view's fitted field that holds it and
    is larger (:data:`_AROUND_HELD`, :data:`_AROUND_LARGER`) replaces it: the small one was the air
    inside the field, the body beside it taken for the outside.

    Args:
        image: ``(H, W)`` real, finite values of any range and dtype (8-, 12-, 16-bit integers or
            floats), in the file's polarity (the outside may be black or white).
        settings: thresholds; :class:`FieldSettings` defaults when ``None``.

    Returns:
        A :class:`Field` (``mask`` / ``field_mask`` ``(H, W)`` bool, shape model in px).

    Raises:
        FieldError: input not 2-D / real / finite, a constant image, or valid pixels under
            ``settings.min_fraction`` of the image in every view.
    """
    s = FieldSettings() if settings is None else settings
    if not isinstance(s, FieldSettings):
        raise FieldError(f"settings must be a FieldSettings, got {type(s).__name__}")
    img = _validated(image)
    lo, hi = float(img.min()), float(img.max())
    if hi == lo:
        raise FieldError(f"the image is constant (every pixel = {lo:g}): no anatomy to register")
    if raw:
        if lo < 0:
            raise FieldError(f"raw=True: a raw detector signal is not negative, but the image reaches {lo:g}")
        return dataclasses.replace(_detect_raw(img, s), view="raw")
    try:
        found = _detect(img, s)
    except _TooLittleField as first:
        found = _in_log_views(img, lo, hi, s)
        if found is None:
            raise FieldError(f"{first} (in the image and in its logarithmic views)") from None
        return found
    if found.kind != "none":
        if found.field_mask.mean() < _SMALL_FIELD:  # maybe the air inside the field, taken for it
            around = _in_log_views(img, lo, hi, s, around=found.field_mask)
            if around is not None:
                return around
        return found
    # no model fits the image as stored: one may fit its logarithm (a linear display's leaky blades)
    logged = _in_log_views(img, lo, hi, s, fitted_only=True)
    return found if logged is None or logged.valid_fraction < _LOG_FIT_MIN_VALID else logged


def _in_log_views(img: np.ndarray, lo: float, hi: float, s: FieldSettings, *,
                  fitted_only: bool = False, around: np.ndarray | None = None) -> Field | None:
    """:func:`_detect` on the logarithmic views of ``img`` (the end where most pixels lie first):
    the first that leaves enough field (with ``fitted_only``: the first whose field a shape model
    fits, not kind ``"none"``; with ``around`` ``(H, W)`` bool: the first fitted one that holds
    :data:`_AROUND_HELD` of it and is :data:`_AROUND_LARGER` times larger), its excluded plateaus
    named in the image's own polarity; None if none does."""
    for view in _log_view_order(img, lo, hi):
        try:
            found = _detect(log_view(img, view), s)
        except _TooLittleField:
            continue
        if (fitted_only or around is not None) and found.kind == "none":
            continue
        if around is not None and not (
                (found.field_mask & around).sum() >= _AROUND_HELD * around.sum()
                and found.field_mask.sum() >= _AROUND_LARGER * around.sum()):
            continue
        changes = {"view": view}
        if view == "log-bright":  # the view is inverted: its black is the image's white, its empty saturated
            ex = found.excluded
            changes.update(outside={"black": "white", "white": "black"}.get(found.outside),
                           excluded={**ex, "saturated": ex.get("empty", 0), "empty": ex.get("saturated", 0)})
        return dataclasses.replace(found, **changes)
    return None


#: A collimator's edge in a raw image (:func:`_detect_raw`): the signal falls by at least this factor
#: within two pixels (the 3 x 3 range of its logarithm). Blades pass a few per cent of the beam or
#: less (a factor 20-50 and more); anatomy changes the signal within two pixels by less than a
#: factor 5 away from metal (a skin edge seen at its tangent: 1.2-1.5 in the log at 0.8-1.6 mm pixels).
RAW_EDGE_RATIO = 8.0
#: Gaps in a collimator's edge of up to this radius (px) are closed before the field is flooded:
#: where the skin meets the edge the two sides' signals can come close.
_RAW_CLOSE_PX = 2


def _detect_raw(img: np.ndarray, s: FieldSettings) -> Field:
    """:func:`detect_field` for a raw (linear) image: the region inside the steep edges, fitted by
    the shape models; no edge, or no model that fits it: kind ``"none"`` (the whole image, minus
    empty or saturated plateaus)."""
    lo, hi = float(img.min()), float(img.max())
    q = _quant_step(img, lo, hi)
    med = ndimage.median_filter(img, size=3, mode="nearest")
    v = np.log(np.maximum(med, max(hi * 1e-9, q, 1e-30)))
    steep = (ndimage.maximum_filter(v, 3, mode="nearest") - ndimage.minimum_filter(v, 3, mode="nearest")
             > math.log(RAW_EDGE_RATIO))
    reason = f"no edge where the raw signal drops by x{RAW_EDGE_RATIO:g} (no collimator)"
    kind, model, params = "none", None, {}
    if steep.any():
        walls = _dilate(steep, _RAW_CLOSE_PX)
        inside, _ = _largest_filled(~walls)
        # back out to the edge's 50 % point: the band next to the flooded region, on its bright side
        # (pixels of the band that see no edge within 2 px are inside)
        band = _dilate(inside, _RAW_CLOSE_PX + 2) & ~inside
        hi5, lo5 = ndimage.maximum_filter(v, 5, mode="nearest"), ndimage.minimum_filter(v, 5, mode="nearest")
        bright = (v >= 0.5 * (hi5 + lo5)) | (hi5 - lo5 <= math.log(RAW_EDGE_RATIO))
        cand, _ = _largest_filled(ndimage.binary_opening(inside | (band & bright), _disk(_OPEN_RADIUS)))
        outside = 1.0 - float(cand.mean())
        if cand.any() and outside >= max(s.min_outside_fraction, 0.001):
            kind, model, params = _fit_model(cand, s, ~cand)
            reason = params.pop("reason", "") if model is None else ""
        elif cand.any():
            reason = f"the steep edges enclose {100 * (1 - outside):.1f} % of the image: no collimator"
    if model is not None:
        try:
            return _field_result(img, med, lo, hi, q, s, kind, model, params, "black")
        except _TooLittleField:
            reason = f"the {kind} inside the steep edges leaves too little of the image"
    return _field_result(img, med, lo, hi, q, s, "none", None, {"reason": reason}, None)


#: The logarithmic views :func:`detect_field` falls back on (:func:`log_view`): ``"log-dark"``
#: spreads the grey levels next to the image's minimum, ``"log-bright"`` those next to its maximum.
LOG_VIEWS = ("log-dark", "log-bright")


def log_view(image: np.ndarray, view: str) -> np.ndarray:
    """``(H, W)`` the logarithm of each pixel's distance from the image's minimum (``"log-dark"``:
    ``log(x - min + q)``) or maximum (``"log-bright"``: ``log(max - x + q)``, so that the maximum
    becomes the minimum), ``q`` the image's quantisation step (its smallest difference between
    values): neighbouring levels next to that extreme differ by a factor of two or more, those far
    from it by little. For a linear display this is its log display, inverted or not."""
    img = np.asarray(image, np.float64)
    if view not in LOG_VIEWS:
        raise FieldError(f"log view must be one of {LOG_VIEWS}, got {view!r}")
    lo, hi = float(img.min()), float(img.max())
    q = _quant_step(img, lo, hi)
    if not q > 0:
        raise FieldError("the image is constant: it has no logarithmic view")
    return np.log((img - lo) + q) if view == "log-dark" else np.log((hi - img) + q)


def _log_view_order(img: np.ndarray, lo: float, hi: float) -> tuple[str, ...]:
    """:data:`LOG_VIEWS`, the one of the end nearer the image's median first."""
    return LOG_VIEWS if np.median(img) - lo <= hi - np.median(img) else LOG_VIEWS[::-1]


class _TooLittleField(FieldError):
    """The field or the valid pixels cover less than ``min_fraction`` of the image."""


def _fit_outside(med: np.ndarray, out: _Outside, s: FieldSettings) -> tuple[str, np.ndarray | None, dict, str]:
    """Steps 2-3 for one outside region: ``(kind, model mask or None, params, reason)``."""
    cand, reason = _candidate(med, out)
    if reason and cand.any():  # in parts: one round field whose notches reach through it may join them
        fit = _fit_notched_circle(cand, _contour(cand, every=True), s, out.region)
        return ("circle", fit[0], fit[1], "") if fit is not None else ("none", None, {}, reason)
    if not reason and (cand.sum() < 0.001 * cand.size or cand.all()):
        reason = "no field candidate inside the outside region"
    if reason:
        return "none", None, {}, reason
    kind, model, params = _fit_model(cand, s, out.region)
    return kind, model, params, ""


def _detect(img: np.ndarray, s: FieldSettings) -> Field:
    """:func:`detect_field` on one view ``img`` ``(H, W)`` float64, validated and not constant."""
    lo, hi = float(img.min()), float(img.max())
    q = _quant_step(img, lo, hi)
    med = ndimage.median_filter(img, size=3, mode="nearest")

    kind, params, model, leveled = "none", {}, None, False
    out, reason = _find_outside(img, med, img >= hi - q, img <= lo + q, lo, hi, s)
    if out is not None:
        kind, model, params, reason = _fit_outside(med, out, s)
        more, levels = out, 1
        while model is None and levels < _MAX_OUTSIDE_LEVELS:  # step 1b: leaky blades
            more = _with_second_level(more, img, med, lo, hi, s)
            if more is None:
                break
            levels += 1
            fit = _fit_outside(med, more, s)
            if fit[1] is not None:
                kind, model, params, _ = fit
                params, leveled = {**params, "outside_levels": levels}, True
    if model is not None:
        try:
            return _field_result(img, med, lo, hi, q, s, kind, model, params, out.colour)
        except _TooLittleField:
            if not (leveled or "arc_cover" in params or "edge_cover" in params):
                raise
            # a field of a second level or a one-sided fit (a notched circle or polygon) that
            # leaves too little (a region of the air taken for the field) is not kept: the image
            # reads as without a fitted field, as before those models
    return _field_result(img, med, lo, hi, q, s, "none", None, {"reason": reason}, None)


def _field_result(img: np.ndarray, med: np.ndarray, lo: float, hi: float, q: float, s: FieldSettings, kind: str,
                  model: np.ndarray | None, params: dict, outside_colour: str | None) -> Field:
    """Steps 4-5 for a fitted model (``None``: kind ``"none"``, the whole image): the
    :class:`Field`, or :class:`_TooLittleField` where the field or the valid pixels are too few."""
    if model is None:
        field_mask = within = np.ones(img.shape, dtype=bool)
    else:
        field_mask, within = _erode_model(kind, model, params, (s.margin_px, min(s.margin_px, 1.0)))
    excl = _exclusions(img, within, field_mask, lo, hi, q, med, s)
    mask = field_mask & ~(excl["overlay"] | excl["saturated"] | excl["empty"])
    result = Field(mask=mask, field_mask=field_mask, kind=kind, outside=outside_colour, params=params,
                   excluded={k: int(v.sum()) for k, v in excl.items()}, settings=s, overlay=excl["overlay"])
    n = img.size
    if field_mask.sum() < s.min_fraction * n:
        raise _TooLittleField(
            f"the detected field ({kind}) covers only {100 * field_mask.sum() / n:.1f} % of the image "
            f"(< {100 * s.min_fraction:g} %): too little anatomy to register")
    if mask.sum() < s.min_fraction * n:
        ex = ", ".join(f"{k} {v}" for k, v in result.excluded.items())
        raise _TooLittleField(
            f"the valid pixels cover only {100 * mask.sum() / n:.1f} % of the image "
            f"(< {100 * s.min_fraction:g} %) after excluding overlays / plateaus ({ex} px)")
    return result
