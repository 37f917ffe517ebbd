"""What a C-arm does to the detector signal before a user sees it: collimation and display processing.

:class:`Collimator` is the collimated field on the detector: the blades (iris, rectangular
shutters or a polygon of wedges) pass only a small fraction ``transmission`` of the beam, so
the raw signal outside the field is ``transmission x`` the signal there. Apply it to the raw
detector signal of :meth:`sim.physics.imaging.XRayImager.render` (keV per pixel, or counts),
before the log: the log image outside the field is then ``L - log(transmission)``.

:class:`DisplayChain` is the vendor processing of one fluoroscopy / radiography frame, from the
raw signal and the flat field ``I0`` (``imager.flat``) to the integers a viewer shows:

1. ``log``: ``-log(I / I0)`` (I clipped at ``1e-12 I0``, as :meth:`sim.physics.poly.Polychromatic.log_image`)
   or the linear intensity ``I / I0``;
2. window: the ``window`` percentiles (``numpy.percentile``, linear interpolation) of the
   values *inside the collimated field* are mapped to 0 and 1, and the result clipped to [0, 1];
   ``polarity`` decides which end is dark (``bone-dark``: bone, high ``L``, low intensity, is
   dark, as fluoroscopy shows it; ``bone-bright``: bone is bright, as a radiograph);
3. unsharp masking (edge enhancement): ``x + amount (x - G_sigma(x))``, clipped to [0, 1];
   with a field, the Gaussian is a normalised convolution inside the field (and, separately,
   outside it), so the collimator edge makes no halo;
4. gamma: ``x ** gamma`` (on the displayed brightness, after the polarity);
5. quantisation to integers ``round(x (2^bits - 1))`` (``uint16``);
6. shutter: pixels outside the field set to 0 (``black``), to ``2^bits - 1`` (``white``), or left
   as 1-5 made them (``none``: the collimator shadow as the physics gives it).

Simplifications (documented in ``docs/physics.md`` terms): :meth:`Collimator.apply` is a mask on
the finished signal. A real collimator also shrinks the irradiated volume, so the scatter inside
the field is lower than that of the uncollimated Monte Carlo, and quantum noise in the shadow
would be relatively larger than that of the scaled noisy signal. The display chain has no
temporal recursive filter, no dose-rate control and no noise reduction.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Mapping

import numpy as np

from sim.core.atomic import jsonable
from sim.physics import PhysicsError

SHAPES = ("none", "circle", "rectangle", "iris-blades", "polygon")
POLARITIES = ("bone-dark", "bone-bright")
SHUTTERS = ("black", "white", "none")


# --------------------------------------------------------------------------------------------
# validation helpers: one-line messages naming the setting, its unit and the allowed range
# --------------------------------------------------------------------------------------------


def _is_real(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _number(name: str, v, lo: float, hi: float, unit: str, *, lo_open: bool = False) -> float:
    left = "(" if lo_open else "["
    if not _is_real(v) or not math.isfinite(float(v)) or not (lo < v if lo_open else lo <= v) or not v <= hi:
        raise PhysicsError(f"{name} must be a number in {left}{lo:g}, {hi:g}] {unit}, got {v!r}")
    return float(v)


def _pair(name: str, v, lo: float, hi: float, unit: str, *, lo_open: bool = False) -> tuple[float, float]:
    left = "(" if lo_open else "["
    try:
        items = tuple(v)
    except TypeError:
        items = ()
    if len(items) != 2:
        raise PhysicsError(f"{name} must be a pair of numbers in {left}{lo:g}, {hi:g}] {unit}, got {v!r}")
    return (_number(name, items[0], lo, hi, unit, lo_open=lo_open),
            _number(name, items[1], lo, hi, unit, lo_open=lo_open))


def _choice(name: str, v, allowed: tuple[str, ...]) -> str:
    if v not in allowed:
        raise PhysicsError(f"{name} must be one of {allowed}, got {v!r}")
    return v


def _from_dict(cls, d: Mapping[str, Any]):
    if not isinstance(d, Mapping):
        raise PhysicsError(f"{cls.__name__}.from_dict needs a mapping, got {type(d).__name__}")
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
        raise PhysicsError(f"unknown {cls.__name__} setting(s) {unknown}; allowed: {sorted(names)}")
    return cls(**dict(d))


# --------------------------------------------------------------------------------------------
# collimator
# --------------------------------------------------------------------------------------------


def _polygon_checked(vertices) -> tuple[tuple[float, float], ...]:
    """Vertices as float pairs in [-1, 2], convex (either orientation), simple, area > 0."""
    try:
        verts = tuple(tuple(p) for p in vertices)
    except TypeError:
        raise PhysicsError(f"vertices must be a sequence of (x, y) fraction pairs, got {vertices!r}") from None
    if len(verts) < 3:
        raise PhysicsError(f"vertices must be >= 3 (x, y) pairs (fractions of width, height) of a convex "
                           f"polygon, got {len(verts)}")
    verts = tuple(_pair("vertices", p, -1.0, 2.0, "(fractions of width, height)") for p in verts)
    p = np.asarray(verts, np.float64)
    e = np.roll(p, -1, axis=0) - p  # edge i: p[i] -> p[i+1]
    if np.any(np.hypot(e[:, 0], e[:, 1]) < 1e-12):
        raise PhysicsError("vertices must be distinct consecutive points of a convex polygon (a repeated vertex)")
    en = np.roll(e, -1, axis=0)
    cross = e[:, 0] * en[:, 1] - e[:, 1] * en[:, 0]
    turn = np.arctan2(cross, (e * en).sum(1))
    tol = 1e-12
    if not (np.all(cross >= -tol) or np.all(cross <= tol)) or abs(abs(turn.sum()) - 2 * math.pi) > 1e-6:
        raise PhysicsError("vertices must form a convex polygon (no reflex angle, no self-intersection)")
    if abs(_shoelace(p)) < 1e-9:
        raise PhysicsError("vertices must enclose a convex polygon of area > 0 (fractions of width x height), got 0")
    return verts


def _shoelace(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


@dataclass(frozen=True)
class Collimator:
    """The collimated field on the detector.

    Coordinates are fractions of the image: ``x`` along the columns (of the width), ``y`` along
    the rows (of the height), ``(0, 0)`` the top-left corner of the first pixel, ``(1, 1)`` the
    bottom-right corner of the last. A pixel is inside the field when its centre (column + 0.5,
    row + 0.5 in pixels) is inside the shape or on its boundary.

    Attributes:
        shape (str, default ``"circle"``): ``"none"`` (the whole detector is the field),
            ``"circle"`` (iris collimator), ``"rectangle"`` (shutter blades), ``"iris-blades"``
            (the circle cut by the rectangle's blades: an iris with shutter blades, as on many
            C-arms) or ``"polygon"`` (wedges).
        center (tuple[float, float], default ``(0.5, 0.5)``): field centre ``(x, y)``, fractions
            of the image width, height, each in [0, 1] (circle, rectangle, iris-blades: one centre).
        radius (float, default 0.45): circle radius, a fraction of the image's shorter side, in
            (0, 5].
        half_size (tuple[float, float], default ``(0.4, 0.4)``): rectangle half width and half
            height, fractions of the image width and height, each in (0, 5]. After a rotation the
            half width still is ``half_size[0] x width`` pixels, along the rotated axis.
        vertices (tuple[tuple[float, float], ...], default ``()``): polygon corners ``(x, y)``,
            fractions of width, height, each in [-1, 2]; >= 3, in order (either orientation),
            forming a convex polygon with area > 0 (polygon only).
        rotation_deg (float, default 0.0): rectangle rotation (deg) in [-360, 360], counter-
            clockwise as the image is displayed (rows downward).
        transmission (float, default 0.02): fraction of the signal that passes the blades, in
            [0, 1]: the raw signal outside the field is ``transmission x`` the signal.
    """

    shape: str = "circle"
    center: tuple[float, float] = (0.5, 0.5)
    radius: float = 0.45
    half_size: tuple[float, float] = (0.4, 0.4)
    vertices: tuple[tuple[float, float], ...] = ()
    rotation_deg: float = 0.0
    transmission: float = 0.02

    def __post_init__(self) -> None:
        _choice("collimator shape", self.shape, SHAPES)
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen: normalise tuples)
        set_("center", _pair("center", self.center, 0.0, 1.0, "(fractions of width, height)"))
        set_("radius", _number("radius", self.radius, 0.0, 5.0, "(fraction of the shorter side)", lo_open=True))
        set_("half_size", _pair("half_size", self.half_size, 0.0, 5.0, "(fractions of width, height)",
                                lo_open=True))
        set_("rotation_deg", _number("rotation_deg", self.rotation_deg, -360.0, 360.0, "deg"))
        set_("transmission", _number("transmission", self.transmission, 0.0, 1.0, "(fraction of the signal)"))
        if self.shape == "polygon":
            set_("vertices", _polygon_checked(self.vertices))
        else:
            try:
                verts = tuple(tuple(_pair("vertices", p, -1.0, 2.0, "(fractions of width, height)"))
                              for p in self.vertices)
            except TypeError:
                raise PhysicsError(f"vertices must be a sequence of (x, y) fraction pairs, "
                                   f"got {self.vertices!r}") from None
            set_("vertices", verts)

    def mask(self, height: int, width: int) -> np.ndarray:
        """``(height, width)`` bool, True inside the field (pixel centres tested, boundary inside)."""
        for name, n in (("height", height), ("width", width)):
            if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 1:
                raise PhysicsError(f"mask {name} must be a positive integer number of pixels, got {n!r}")
        h, w = int(height), int(width)
        if self.shape == "none":
            return np.ones((h, w), bool)
        x = (np.arange(w, dtype=np.float64) + 0.5)[None, :]
        y = (np.arange(h, dtype=np.float64) + 0.5)[:, None]
        if self.shape == "polygon":
            p = np.asarray(self.vertices, np.float64) * [w, h]
            s = 1.0 if _shoelace(p) > 0 else -1.0
            inside = np.ones((h, w), bool)
            for a, b in zip(p, np.roll(p, -1, axis=0)):
                cross = (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0])
                inside &= s * cross >= -1e-9 * max(h, w) ** 2
            return inside
        dx = x - self.center[0] * w
        dy = y - self.center[1] * h
        r = self.radius * min(h, w)
        circle = dx * dx + dy * dy <= r * r
        if self.shape == "circle":
            return circle
        # rectangle: local axes u = (cos t, -sin t), v = (-sin t, -cos t) in (column, row) pixels
        t = math.radians(self.rotation_deg)
        c, s = math.cos(t), math.sin(t)
        u = dx * c - dy * s
        v = dx * s + dy * c
        blades = (np.abs(u) <= self.half_size[0] * w) & (np.abs(v) <= self.half_size[1] * h)
        return blades & circle if self.shape == "iris-blades" else blades

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """Raw detector signal ``(H, W)`` or ``(B, H, W)`` -> the same shape (a float array), the
        signal outside the field multiplied by ``transmission``, inside unchanged."""
        raw = np.asarray(raw)
        if raw.ndim not in (2, 3) or not np.issubdtype(raw.dtype, np.number) or np.iscomplexobj(raw):
            raise PhysicsError(f"raw signal must be a real (H, W) or (B, H, W) array, got shape {raw.shape} "
                               f"dtype {raw.dtype}")
        if not np.issubdtype(raw.dtype, np.floating):
            raw = raw.astype(np.float64)
        m = self.mask(raw.shape[-2], raw.shape[-1])
        return np.where(m, raw, raw * raw.dtype.type(self.transmission))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able settings (tuples as lists); :meth:`from_dict` reads them back."""
        return {k: jsonable(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Collimator":
        """Settings from :meth:`to_dict` (or a config); missing keys take the defaults."""
        return _from_dict(cls, d)


# --------------------------------------------------------------------------------------------
# display chain
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DisplayChain:
    """The vendor processing of a fluoroscopy / radiography frame (see the module doc for the order).

    Attributes:
        log (bool, default True): take ``-log(I / I0)`` first (the usual log-corrected image);
            False keeps the linear intensity ``I / I0``.
        polarity (str, default ``"bone-dark"``): ``"bone-dark"`` (bone, i.e. high attenuation /
            low intensity, is dark: fluoroscopy) or ``"bone-bright"`` (bone is bright: a
            radiograph).
        window (tuple[float, float], default ``(1.0, 99.0)``): low and high percentiles (%) of the
            in-field values mapped to the ends of the output range; ``0 <= low < high <= 100``.
            Values beyond them are clipped.
        gamma (float, default 1.0): power curve ``x ** gamma`` on the windowed, displayed [0, 1]
            values; in (0, 10] (< 1 brightens the mid-tones).
        unsharp_sigma_px (float, default 0.0): Gaussian sigma (pixels) of the unsharp mask, in
            [0, 100]; must be > 0 when ``unsharp_amount`` > 0.
        unsharp_amount (float, default 0.0): edge enhancement ``x + amount (x - G_sigma(x))``
            before the gamma, clipped to [0, 1]; in [0, 10] (0 = off).
        bits (int, default 12): output integers ``0 .. 2^bits - 1``, stored as ``uint16``; in
            [8, 16].
        shutter (str, default ``"black"``): what outside the field shows: ``"black"`` (0),
            ``"white"`` (``2^bits - 1``) or ``"none"`` (processed like the field: the collimator
            shadow as the physics gives it).
    """

    log: bool = True
    polarity: str = "bone-dark"
    window: tuple[float, float] = (1.0, 99.0)
    gamma: float = 1.0
    unsharp_sigma_px: float = 0.0
    unsharp_amount: float = 0.0
    bits: int = 12
    shutter: str = "black"

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen: normalise values)
        if not isinstance(self.log, (bool, np.bool_)):
            raise PhysicsError(f"log must be a bool (True: -log(I/I0), False: linear I/I0), got {self.log!r}")
        set_("log", bool(self.log))
        _choice("polarity", self.polarity, POLARITIES)
        win = _pair("window", self.window, 0.0, 100.0, "(percentiles, %)")
        if not win[0] < win[1]:
            raise PhysicsError(f"window must be (low, high) percentiles (%) with 0 <= low < high <= 100, "
                               f"got {self.window!r}")
        set_("window", win)
        set_("gamma", _number("gamma", self.gamma, 0.0, 10.0, "(power, unitless)", lo_open=True))
        set_("unsharp_sigma_px", _number("unsharp_sigma_px", self.unsharp_sigma_px, 0.0, 100.0, "px"))
        set_("unsharp_amount", _number("unsharp_amount", self.unsharp_amount, 0.0, 10.0, "(unitless)"))
        if self.unsharp_amount > 0 and self.unsharp_sigma_px == 0:
            raise PhysicsError("unsharp_sigma_px must be in (0, 100] px when unsharp_amount > 0, got 0")
        if isinstance(self.bits, (bool, np.bool_)) or not isinstance(self.bits, (int, np.integer)) \
                or not 8 <= self.bits <= 16:
            raise PhysicsError(f"bits must be an integer in [8, 16] (output bit depth), got {self.bits!r}")
        set_("bits", int(self.bits))
        _choice("shutter", self.shutter, SHUTTERS)

    @property
    def max_value(self) -> int:
        """The brightest output value, ``2^bits - 1``."""
        return (1 << self.bits) - 1

    def apply(self, raw: np.ndarray, i0: float, field: np.ndarray | None = None) -> np.ndarray:
        """Raw detector signal ``(H, W)`` (or ``(B, H, W)``, each frame windowed on its own),
        flat-field signal ``i0`` (same units, > 0) and the collimated field ``(H, W)`` bool (None:
        the whole image) -> display integers, same shape, ``uint16`` in ``0 .. 2^bits - 1``.

        The imaging chain's display stage (:func:`sim.physics.chain.display`, in float64), the one
        every realistic image of the project goes through."""
        raw = np.asarray(raw)
        if raw.ndim not in (2, 3) or not np.issubdtype(raw.dtype, np.number) or np.iscomplexobj(raw):
            raise PhysicsError(f"raw signal must be a real (H, W) or (B, H, W) array, got shape {raw.shape} "
                               f"dtype {raw.dtype}")
        i0 = _number("i0", i0, 0.0, math.inf, "(flat-field signal, raw signal units)", lo_open=True)
        if field is not None:
            field = np.asarray(field)
            if field.dtype != bool or field.shape != raw.shape[-2:]:
                raise PhysicsError(f"field must be a bool array of the image shape {raw.shape[-2:]}, "
                                   f"got {field.dtype} {field.shape}")
            if not field.any():
                raise PhysicsError("field must contain at least one pixel (the window is taken over it)")
        frames = raw.astype(np.float64).reshape(-1, *raw.shape[-2:])
        if not np.all(np.isfinite(frames)):
            raise PhysicsError("raw signal must be finite (no NaN or inf)")
        if not len(frames):
            return np.zeros(raw.shape, np.uint16)
        import torch  # slow to import: only where a frame is displayed

        from sim.physics.chain import display  # loads torch (above); the chain is below this module

        b = len(frames)
        mask = np.ones(raw.shape[-2:], bool) if field is None else field
        out = display(torch.from_numpy(frames), torch.full((b,), i0, dtype=torch.float64),
                      torch.from_numpy(mask)[None].expand(b, -1, -1),
                      self.tensors(b, dtype=torch.float64))
        return out.numpy().astype(np.uint16).reshape(raw.shape)

    def tensors(self, batch: int, *, dtype=None, device=None) -> dict:
        """This chain's settings for ``batch`` images as the display stage's ``(B,)`` tensors
        (:data:`sim.physics.chain.DISPLAY_KEYS`; the codes: the index in :data:`POLARITIES` and
        :data:`SHUTTERS`), floats in ``dtype`` (None: float32) on ``device``. A ``shutter`` other
        than ``none`` shows its value outside a field only; an open field has no outside."""
        import torch  # slow to import: only where a frame is displayed

        dtype = torch.float32 if dtype is None else dtype
        full = lambda v, kind: torch.full((int(batch),), v, dtype=kind, device=device)  # noqa: E731
        return {"log": full(self.log, torch.bool), "polarity": full(POLARITIES.index(self.polarity), torch.int64),
                "window_low": full(self.window[0], dtype), "window_high": full(self.window[1], dtype),
                "gamma": full(self.gamma, dtype), "unsharp": full(self.unsharp_amount > 0, torch.bool),
                "unsharp_sigma_px": full(self.unsharp_sigma_px, dtype),
                "unsharp_amount": full(self.unsharp_amount, dtype), "max_value": full(float(self.max_value), dtype),
                "shutter": full(SHUTTERS.index(self.shutter), torch.int64)}

    def to_dict(self) -> dict[str, Any]:
        """JSON-able settings (tuples as lists); :meth:`from_dict` reads them back."""
        return {k: jsonable(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "DisplayChain":
        """Settings from :meth:`to_dict` (or a config); missing keys take the defaults."""
        return _from_dict(cls, d)


# --------------------------------------------------------------------------------------------
# the tone: a display's unknown monotone curve undone against known line integrals
# --------------------------------------------------------------------------------------------

#: Whether a display image gets a toned version for registration (and, in training, whether the
#: targets are toned): ``ct`` maps its values by rank onto line integrals of the CT seen through
#: the same field (:func:`apply_tone`), ``off`` makes none.
TONES = ("ct", "off")
#: Number of quantiles of a tone curve (probabilities ``linspace(0, 1, TONE_LEVELS)``).
TONE_LEVELS = 257


def quantile_curve(values: np.ndarray, levels: int = TONE_LEVELS) -> np.ndarray:
    """The tone curve of reference ``values`` (line integrals, any shape): their ``(levels,)``
    quantiles at the probabilities ``linspace(0, 1, levels)``."""
    v = np.asarray(values, np.float64).reshape(-1)
    if v.size == 0 or not np.all(np.isfinite(v)):
        raise PhysicsError(f"tone curve: needs finite reference values, got {v.size} values")
    return np.quantile(v, np.linspace(0.0, 1.0, int(levels)))


def apply_tone(image: np.ndarray, mask: np.ndarray | None, curve: np.ndarray, *, reverse: bool = False) -> np.ndarray:
    """Histogram specification: ``image`` ``(H, W)`` with its valid pixels (``mask`` ``(H, W)``
    bool, None: all) mapped by rank onto ``curve`` (:func:`quantile_curve`).

    The pixel of probability ``p = (rank - 0.5) / n`` (ties share their average rank) becomes the
    curve's value at ``p`` (at ``1 - p`` with ``reverse``: the tone of the inverted image). Any
    strictly monotone display curve (window, gamma, log or linear) is undone exactly when
    ``curve`` holds the true view's own line integrals; with a reference from other poses, up to
    the difference of the two histograms. Pixels outside ``mask`` get the median of the mapped
    values. Returns float64 ``(H, W)``.
    """
    from scipy.stats import rankdata

    img = np.asarray(image, np.float64)
    m = np.ones(img.shape, bool) if mask is None else np.asarray(mask, bool)
    q = np.asarray(curve, np.float64)
    if q.ndim != 1 or q.size < 2 or not np.all(np.isfinite(q)) or np.any(np.diff(q) < 0):
        raise PhysicsError(f"tone curve: expected a finite non-decreasing (levels,) array, got shape {q.shape}")
    if m.shape != img.shape or not m.any():
        raise PhysicsError(f"tone: the mask {m.shape} must match the image {img.shape} and hold a valid pixel")
    p = (rankdata(img[m]) - 0.5) / int(m.sum())
    mapped = np.interp(1.0 - p if reverse else p, np.linspace(0.0, 1.0, q.size), q)
    out = np.full(img.shape, float(np.median(mapped)))
    out[m] = mapped
    return out
