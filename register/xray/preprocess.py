"""Recorded, composable preprocessing that makes real X-rays comparable with DRRs.

A :class:`Pipeline` applies :class:`Step` objects in order to an ``(H, W)`` image (and an optional
``(H, W)`` bool mask of valid pixels) and returns ``(image, mask, record)``: ``record`` is a
JSON-serialisable list with one entry per step, ``{"step": name, "params": {...}, "measured":
{...}}`` (the crop box, the chosen ``I0``, the normalisation percentiles, ...), so a run can say
exactly what was done to its input.

Steps (names for :meth:`Pipeline.from_names` in brackets), in the order of :data:`DEFAULT_STEPS`:

* :class:`Field` (``field``): detects the collimated field (circle, rectangle, polygon, off-centre;
  black or white outside) and excludes burned-in text, markers and saturated or empty plateaus;
  the result is the valid-pixel mask that travels with the image (:mod:`register.xray.field`).
* :class:`Median` (``median``): ``size x size`` median filter (salt-and-pepper / dead pixels).
* :class:`Intensity` (``intensity``): decides whether the pixels are raw intensity, log or
  display-processed, bone bright or dark (DICOM tags, the CT, the image: :mod:`register.xray.intensity`)
  and applies ``log`` and / or ``invert`` accordingly; the decision and its evidence are recorded.
* :class:`LogCorrect` (``log``): ``-ln(I / I0)``; turns *transmitted intensity* (bone dark) into
  line-integral-like values (bone bright, air ~ 0), like a DRR. ``I0`` (the unattenuated intensity)
  is a high percentile of the valid pixels when not given.
* :class:`Normalize` (``normalize``): maps the ``low_pct`` / ``high_pct`` percentiles to 0 and 1
  and clips to ``[0, 1]``.
* :class:`Invert` (``invert``): ``max + min - value`` (same range, reversed).
* :class:`Crop` (``crop``): crops to the valid pixels' bounding box (a consequence of the mask);
  :func:`crop_box` / :func:`cropped_geometry` turn the record into the detector geometry of the
  cropped image (principal point ``cx - col0``, ``cy - row0``).

Every step is a :class:`sim.prepare.Step` (the project's one step protocol) and a frozen
dataclass: ``apply(image (H, W) float64, mask (H, W) bool | None) -> (image, mask, measured)``.
Percentiles and statistics use the valid (mask) pixels only. Images leave the pipeline as float32.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar, Iterable, Sequence

import numpy as np

from register.xray.field import FieldSettings, detect_field
from register.xray.intensity import POLARITIES, SCALES, TONE_LEVELS, TONES, decide, tone_curve
from sim import prepare
from sim.prepare import Step  # the one step protocol: here ``apply(image (H, W) float64, mask (H, W) bool | None)``
from sim.core.atomic import jsonable
from sim.core.errors import InputError
from sim.projection.geometry import CArmGeometry

__all__ = [
    "PreprocessError",
    "Step",
    "Field",
    "Crop",
    "Intensity",
    "DEFAULT_STEPS",
    "Median",
    "LogCorrect",
    "Normalize",
    "Invert",
    "Pipeline",
    "STEPS",
    "crop_box",
    "cropped_geometry",
]


class PreprocessError(InputError):
    """A preprocessing step, its parameters or its input cannot be used; the message says which."""


def _num(value: object, name: str, *, lo: float | None = None, hi: float | None = None,
         lo_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise PreprocessError(f"{name}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise PreprocessError(f"{name}: must be finite, got {v}")
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise PreprocessError(f"{name}: must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    if hi is not None and v > hi:
        raise PreprocessError(f"{name}: must be <= {hi:g}, got {v:g}")
    return v


@dataclass(frozen=True)
class Field(Step):
    """Detect the collimated field of view and exclude what is not anatomy (:mod:`register.xray.field`).

    The valid-pixel mask becomes the detected field (circle, rectangle, polygon or the whole
    image) eroded by ``margin_px``, minus burned-in text, rulers and markers and saturated or empty
    plateaus; with a mask given, the two are intersected. The image is unchanged. Run it first:
    it reads the stored values as the vendor painted them. Measured: :meth:`register.xray.field.Field.to_dict`
    (kind, outside colour, shape parameters, excluded pixel counts, valid fraction).
    """

    name: ClassVar[str] = "field"
    margin_px: float = 2.0
    #: this image's field when already detected (:func:`register.xray.field.detect_field` with
    #: ``margin_px``): :func:`register.xray.prepare.prepare_xray` detects once and keeps its overlays
    found: Any = dataclasses.field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        _num(self.margin_px, "field.margin_px", lo=0.0, hi=50.0)

    def params(self) -> dict[str, Any]:
        return {"margin_px": float(self.margin_px)}

    def apply(self, image, mask):
        found = self.found
        if found is None:
            found = detect_field(image, FieldSettings(margin_px=float(self.margin_px)))
        elif found.mask.shape != image.shape or found.settings.margin_px != float(self.margin_px):
            raise PreprocessError(f"field: the given detection is of a {found.mask.shape} image with margin "
                                  f"{found.settings.margin_px} px, not of this {image.shape} one with {self.margin_px}")
        out = found.mask if mask is None else (mask & found.mask)
        if not out.any():
            raise PreprocessError("field: no valid pixel is left inside the detected field and the given mask")
        return image, out, found.to_dict()


@dataclass(frozen=True)
class Crop(Step):
    """Crop to the bounding box of the valid pixels, ``margin_px`` wider on each side (clipped).

    Cropping follows the mask (a detected field): it only spends the optimiser's pixels on the
    field. Without a mask, nothing is cropped. Measured: ``crop_box = [row0, row1, col0, col1]``
    (half-open, this step's input pixels), ``input_shape``.
    """

    name: ClassVar[str] = "crop"
    margin_px: int = 2

    def __post_init__(self) -> None:
        if isinstance(self.margin_px, bool) or not isinstance(self.margin_px, (int, np.integer)) or self.margin_px < 0:
            raise PreprocessError(f"crop.margin_px: must be a non-negative integer (pixels), got {self.margin_px!r}")

    def apply(self, image, mask):
        H, W = image.shape
        box = [0, H, 0, W] if mask is None else list(prepare.field_box(mask, self.margin_px))
        r0, r1, c0, c1 = box
        out_mask = None if mask is None else mask[r0:r1, c0:c1]
        return image[r0:r1, c0:c1], out_mask, {"crop_box": box, "input_shape": [H, W]}


@dataclass(frozen=True)
class Intensity(Step):
    """Make the pixels line-integral-like (bone bright) from what they are (:mod:`register.xray.intensity`).

    Decides the scale (``linear`` raw intensity, ``log``, ``display``) and the polarity
    (``bone-bright`` / ``bone-dark``) from the DICOM ``tags``, the CT ``reference`` (DRRs) and the
    image (valid pixels only), unless ``scale`` / ``polarity`` are given, then applies
    :class:`LogCorrect` (linear) and / or :class:`Invert` (bone dark). ``tags``: the reader's
    ``meta["intensity_tags"]``; ``inverted``: whether the reader inverted the stored values;
    ``bits``: the stored bit depth.

    ``tone`` (one of :data:`register.xray.intensity.TONES`, default ``"ct"``): a ``display`` image's
    values went through an unknown monotone look-up table; with ``"ct"`` and a CT ``reference``
    the step also records the **tone curve** (``tone_curve``: :data:`register.xray.intensity.TONE_LEVELS`
    quantiles of the line integrals of the CT's reference DRRs seen through the same field,
    :func:`register.xray.intensity.tone_curve`), from which :func:`register.xray.prepare.prepare_xray` makes
    the toned image (:attr:`register.xray.prepare.PreparedXRay.toned`). The image itself is left as
    decided. ``"off"`` records no curve. Raw (``linear``) and ``log`` images are line integrals
    already and get none.

    Measured: the decision with its evidence, the records of the steps it applied, and for a
    display image ``tone`` (what was done, or why not) and ``tone_curve``.
    """

    name: ClassVar[str] = "intensity"
    scale: str = "auto"
    polarity: str = "auto"
    tags: dict | None = dataclasses.field(default=None, compare=False, repr=False)
    inverted: bool = False
    bits: int | None = None
    reference: Any = dataclasses.field(default=None, compare=False, repr=False)
    tone: str = "ct"

    def __post_init__(self) -> None:
        if self.tone not in TONES:
            raise PreprocessError(f"intensity.tone: one of {', '.join(TONES)}, got {self.tone!r}")
        if self.scale != "auto" and self.scale not in SCALES:
            raise PreprocessError(f"intensity.scale: 'auto' or one of {', '.join(SCALES)}, got {self.scale!r}")
        if self.polarity != "auto" and self.polarity not in POLARITIES:
            raise PreprocessError(
                f"intensity.polarity: 'auto' or one of {', '.join(POLARITIES)}, got {self.polarity!r}")

    def params(self) -> dict[str, Any]:
        return {"scale": self.scale, "polarity": self.polarity, "inverted": bool(self.inverted),
                "bits": self.bits, "ct_reference": self.reference is not None, "tone": self.tone}

    def apply(self, image, mask):
        decision = decide(image, mask, tags=self.tags, inverted=self.inverted, scale=self.scale,
                          polarity=self.polarity, reference=self.reference, bits=self.bits)
        applied = []
        for step in (STEPS[n]() for n in decision.steps()):
            image, mask, measured = step.apply(image, mask)
            applied.append({"step": step.name, "params": step.params(), "measured": _jsonable(measured)})
        out = {**decision.to_dict(), "applied": applied}
        if decision.scale == "display":
            curve = None
            if self.tone == "off":
                out["tone"] = "off (option)"
            elif self.reference is None:
                out["tone"] = "none: no CT reference (give the CT)"
            else:
                curve = tone_curve(self.reference, mask, image.shape)
                out["tone"] = ("none: the field holds too few reference pixels" if curve is None else
                               f"ct: {TONE_LEVELS} quantiles of the CT's line integrals in the field")
            if curve is not None:
                out["tone_curve"] = [round(float(v), 5) for v in curve]
        return image, mask, out


@dataclass(frozen=True)
class Median(Step):
    """``size x size`` median filter (odd ``size`` >= 1; edges replicate). Measured: ``changed_fraction``."""

    name: ClassVar[str] = "median"
    size: int = 3

    def __post_init__(self) -> None:
        if isinstance(self.size, bool) or not isinstance(self.size, (int, np.integer)) or self.size < 1 or self.size % 2 == 0:
            raise PreprocessError(f"median.size: must be an odd positive integer (pixels), got {self.size!r}")

    def apply(self, image, mask):
        out = prepare.median_filter(image, int(self.size))
        return out, mask, {"changed_fraction": float(np.mean(out != image))}


@dataclass(frozen=True)
class LogCorrect(Step):
    """``L = -ln(max(I, floor) / I0)``: transmitted intensity -> line-integral-like values.

    ``i0``: the unattenuated intensity (same units as the image); ``None`` -> the ``percentile``-th
    percentile of the valid pixels (the brightest, least attenuated part of the image stands for the
    direct beam; pixels above it get small negative values, which are kept). ``floor = floor_frac *
    I0`` guards ``ln(0)``: pixels below it are clipped to it. Measured: ``i0``, ``i0_source``
    ("given" / "percentile"), ``clipped_pixels``. ``I0 <= 0`` is an error (not a transmission image).
    """

    name: ClassVar[str] = "log"
    i0: float | None = None
    percentile: float = 99.5
    floor_frac: float = 1e-6

    def __post_init__(self) -> None:
        if self.i0 is not None:
            _num(self.i0, "log.i0", lo=0.0, lo_open=True)
        _num(self.percentile, "log.percentile", lo=0.0, hi=100.0)
        _num(self.floor_frac, "log.floor_frac", lo=0.0, hi=1.0, lo_open=True)

    def apply(self, image, mask):
        if self.i0 is None:
            i0 = prepare.i0_percentile(image, mask, self.percentile)
            source = "percentile"
        else:
            i0, source = float(self.i0), "given"
        if not i0 > 0:
            raise PreprocessError(
                f"log: I0 = {i0:g} (the {self.percentile:g}th percentile) is not positive; LogCorrect needs "
                f"a transmitted-intensity image with positive values"
            )
        clipped = int(np.count_nonzero(image < self.floor_frac * i0))
        out = prepare.log_correct(image, i0, self.floor_frac)
        return out, mask, {"i0": i0, "i0_source": source, "clipped_pixels": clipped}


@dataclass(frozen=True)
class Normalize(Step):
    """Map the ``low_pct`` / ``high_pct`` percentiles of the valid pixels to 0 / 1, then clip to ``[0, 1]``.

    Measured: ``low``, ``high`` (the percentile values). Equal percentiles (a flat image) are an error.
    """

    name: ClassVar[str] = "normalize"
    low_pct: float = 1.0
    high_pct: float = 99.0

    def __post_init__(self) -> None:
        lo = _num(self.low_pct, "normalize.low_pct", lo=0.0, hi=100.0)
        hi = _num(self.high_pct, "normalize.high_pct", lo=0.0, hi=100.0)
        if not lo < hi:
            raise PreprocessError(f"normalize: low_pct ({lo:g}) must be < high_pct ({hi:g})")

    def apply(self, image, mask):
        lo, hi = (float(v) for v in prepare.percentile_bounds(image, mask, self.low_pct, self.high_pct))
        if not hi > lo:
            raise PreprocessError(
                f"normalize: the {self.low_pct:g}th and {self.high_pct:g}th percentiles are equal ({lo:g}); "
                f"the image is flat and cannot be normalised"
            )
        return prepare.normalize(image, lo, hi), mask, {"low": lo, "high": hi}


@dataclass(frozen=True)
class Invert(Step):
    """``max + min - value`` over the valid pixels' extremes (range kept). Measured: ``min``, ``max``."""

    name: ClassVar[str] = "invert"

    def apply(self, image, mask):
        out, mn, mx = prepare.invert(image, mask)
        return out, mask, {"min": mn, "max": mx}


#: Step names for :meth:`Pipeline.from_names` -> step classes (built with their defaults).
STEPS: dict[str, type[Step]] = {cls.name: cls for cls in (Field, Median, Intensity, LogCorrect, Normalize, Invert, Crop)}

#: The default preprocessing of ``ctxreg register``: right for raw and display-processed frames alike.
DEFAULT_STEPS = ("field", "median", "intensity", "normalize", "crop")


def _jsonable(obj: Any) -> Any:
    try:
        return jsonable(obj)
    except TypeError as e:
        raise PreprocessError(f"record: {e}") from None


@dataclass(frozen=True)
class Pipeline:
    """An ordered tuple of :class:`Step` objects."""

    steps: tuple[Step, ...] = ()

    def __post_init__(self) -> None:
        steps = tuple(self.steps)
        for k, s in enumerate(steps):
            if not isinstance(s, Step):
                raise PreprocessError(f"steps[{k}]: expected a Step, got {type(s).__name__}")
        object.__setattr__(self, "steps", steps)

    @classmethod
    def from_names(cls, names: Iterable[str], options: dict[str, dict[str, Any]] | None = None) -> Pipeline:
        """Steps by name, e.g. ``["field", "median", "intensity", "normalize", "crop"]``.

        ``options``: keyword arguments per step name (e.g. ``{"intensity": {"tags": ...}}``);
        steps not named there get their defaults."""
        if isinstance(names, str):
            names = [names]
        options = options or {}
        steps = []
        for n in names:
            key = str(n).strip().lower()
            if key not in STEPS:
                raise PreprocessError(f"unknown preprocessing step {n!r}; valid steps: {', '.join(STEPS)}")
            steps.append(STEPS[key](**options.get(key, {})))
        return cls(tuple(steps))

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.steps]

    def apply(self, image: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, list[dict]]:
        """Run the steps: ``image (H, W)`` numeric finite, ``mask (H, W)`` bool valid pixels or None.

        Returns ``(image (H', W') float32, mask (H', W') bool or None, record)``; ``record`` is a
        JSON-serialisable list of ``{"step", "params", "measured"}`` in step order.
        """
        a = prepare.checked_image(image, "image", PreprocessError)
        m = None
        if mask is not None:
            m = np.asarray(mask)
            if m.dtype != np.bool_ or m.shape != a.shape:
                raise PreprocessError(f"mask: expected a bool array of shape {a.shape}, got {m.dtype} {m.shape}")
            if not m.any():
                raise PreprocessError("mask: no valid pixels")
            m = m.copy()
        record: list[dict] = []
        for s in self.steps:
            a, m, measured = s.apply(a, m)
            if a.size == 0:
                raise PreprocessError(f"{s.name}: produced an empty image")
            record.append({"step": s.name, "params": s.params(), "measured": _jsonable(measured)})
        return a.astype(np.float32), m, record


def crop_box(record: Sequence[dict], shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """The total crop ``(row0, row1, col0, col1)`` (half-open, input pixels) of a pipeline record.

    ``shape``: the ``(H, W)`` of the pipeline's input. Successive crops compose; no crop gives the
    whole image.
    """
    r0, r1, c0, c1 = 0, int(shape[0]), 0, int(shape[1])
    for entry in record:
        box = entry.get("measured", {}).get("crop_box")
        if box is not None:
            br0, br1, bc0, bc1 = (int(v) for v in box)
            r0, r1, c0, c1 = r0 + br0, r0 + br1, c0 + bc0, c0 + bc1
    return r0, r1, c0, c1


def cropped_geometry(geometry: CArmGeometry, record: Sequence[dict]) -> CArmGeometry:
    """The detector geometry of the pipeline's output: size of the crop, principal point shifted.

    ``geometry`` describes the pipeline's input image (``height x width`` must match it); the
    result has ``row1 - row0`` x ``col1 - col0`` pixels and principal point ``(cx - col0, cy -
    row0)`` (same spacing, SDD and SOD), so a pixel keeps its ray.
    """
    if not isinstance(geometry, CArmGeometry):
        raise PreprocessError(f"geometry: expected a CArmGeometry, got {type(geometry).__name__}")
    r0, r1, c0, c1 = crop_box(record, (geometry.height, geometry.width))
    cx, cy = geometry.principal_point
    return dataclasses.replace(geometry, height=r1 - r0, width=c1 - c0, cx=cx - c0, cy=cy - r0)
