"""Domain randomization of realistic X-ray images: every randomized setting declared once, drawn per pair.

Real C-arm frames differ in tube voltage, filtration, exposure, grid, detector, scatter,
collimation and the vendor's display processing. To train on images as varied as real ones,
each training pair draws all of these from the distributions declared in :data:`DECLARATION`
(one :class:`Randomized` record per setting: name, unit, distribution, range or choices, the
stage it acts on, the condition under which it matters, and its help). ``docs/domain_randomization.md``
lists them; its table is :func:`doc_table_rows` (a test keeps the two equal).

Stages, in the order they act on a pair's target image:

1. ``physics``: a :class:`sim.physics.settings.PhysicsSettings` (:meth:`Draw.physics_settings`):
   tube voltage, Al and Cu filtration, exposure (mAs: the quantum noise), anti-scatter grid,
   detector blur, and whether the Monte Carlo scatter runs (``scatter = "monte-carlo"``: level
   ``full``; otherwise ``poly``). Each such setting's range lies inside the range the physics
   declares for it (:attr:`Randomized.physics`), and an override must too.
2. ``signal``, on the raw detector signal after rendering (:func:`apply_image`): the Monte Carlo
   scatter scaled by ``scatter_scale`` (``raw + (scale - 1) * scatter``), or, for ``scatter =
   "kernel"``, a cheap scatter model ``scatter_spr * G(raw)`` (a Gaussian of ``scatter_sigma``
   times the shorter image side, of the collimated signal, so it spills a little into the
   shadow); then electronic noise, Gaussian with sigma ``electronic_noise_fraction x I0``.
3. ``collimator``: the collimated field (:meth:`Draw.collimator`, a
   :class:`sim.physics.display.Collimator`): none, a circle (cut by a pair of blades or not) or a
   rotated rectangle, off centre,
   the blades passing ``field_transmission`` of the signal.
4. ``display``: the vendor processing (:meth:`Draw.display_chain`, a
   :class:`sim.physics.display.DisplayChain`): log or linear, polarity, window percentiles,
   unsharp masking, gamma, bit depth, and what the outside of the field shows (``shutter``).

:func:`apply_image` runs stages 2-4 in this order: Monte Carlo scatter scale, collimation,
kernel scatter, electronic noise, display chain (whose window is taken over the field).

Simplifications: the kernel scatter is the scatter at the detector, with or without a grid
(the grid acts in the Monte Carlo and on the primary at level ``full`` only); the added scatter
and the electronic noise carry no quantum noise of their own; collimation is a mask on the
finished signal (as :mod:`sim.physics.display`).

Drawing (:meth:`DomainRandomization.draw`): pair ``index`` under ``seed`` reads one uniform number
per setting, in declaration order, from the stream ``(KIND_RANDOMIZE, index, 0)`` of
:mod:`sim.core.seeds`, and turns it into the setting's value by its inverse distribution function.
So a draw depends on ``(seed, index)`` only (not on other draws or their order), and narrowing
one setting's range changes no other setting's value. Every setting is drawn, also where its
condition (:attr:`Randomized.when`) does not hold; :meth:`Draw.to_dict` records the active ones.
New settings must be appended to :data:`DECLARATION` (a setting's position is its place in the
stream). The post-render noise of pair ``index`` comes from :func:`image_rng` ``(KIND_RANDOMIZE,
index, 1)``.

Overrides: a ``[randomize]`` TOML table (:func:`load_randomization`,
:meth:`DomainRandomization.from_table`), one key per setting::

    [randomize]
    kvp = [70, 110]             # uniform / log-uniform: [low, high] in the setting's unit, or one number
    grid = 0.0                  # bernoulli: the probability of true (or true / false)
    field = ["circle"]          # choice: the allowed choices, equally likely ...
    bits = {"8" = 0.25, "12" = 0.75}   # ... or a table choice -> weight (normalised)

Each override is checked against its declaration (known key, type, ``low <= high``, inside the
setting's limits and the physics range, declared choices only); a bad one raises
:class:`RandomizeError` in one line naming ``randomize.<key>``.
"""

from __future__ import annotations

import bisect
import functools
import itertools
import math
import numbers
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from sim.core.errors import InputError
from sim.core.seeds import KIND_RANDOMIZE, rng_for
from sim.core.atomic import read_toml
from sim.physics.display import Collimator, DisplayChain
from sim.physics.scatter_kernel import default_table
from sim.physics.settings import PhysicsSettings, SETTINGS
from sim.distractors import DistractorField, random_tools
from sim.physics import PhysicsError
from sim.projection.geometry import CArmGeometry

__all__ = ["RandomizeError", "Randomized", "DECLARATION", "STAGES", "DISTRIBUTIONS", "DomainRandomization",
           "Draw", "ToolBank", "TOOL_BANK_SIZE", "apply_image", "draw_tensors", "sks_model", "sks_texture",
           "image_rng", "load_randomization",
           "doc_table_rows"]


class RandomizeError(InputError):
    """A domain-randomization setting, override or input cannot be used; the message names it."""


#: The stages a setting acts on, in the order they act (module doc).
STAGES: tuple[str, ...] = ("physics", "signal", "collimator", "display")
#: The distributions of :class:`Randomized`.
DISTRIBUTIONS: tuple[str, ...] = ("uniform", "log-uniform", "choice", "bernoulli")

_FILTER_ELEMENT = {"al_mm": "Al", "cu_mm": "Cu"}


def _is_number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and math.isfinite(float(v))


def _fmt(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


@dataclass(frozen=True)
class Randomized:
    """One randomized setting: its declaration, or (in a :class:`DomainRandomization`) its
    distribution after overrides.

    Attributes:
        name: the key (``randomize.<name>`` in a config, the key of :meth:`Draw.to_dict`).
        stage: one of :data:`STAGES`: what the value acts on.
        dist: one of :data:`DISTRIBUTIONS`.
        help: what it is (without unit or range).
        unit: e.g. ``kV``, ``mm``, ``deg``, ``px``, ``%``; a phrase for fractions; None for plain numbers.
        low, high: the range of ``uniform`` / ``log-uniform`` (closed; ``low <= high``; ``low > 0``
            for ``log-uniform``).
        step: ``uniform`` on the grid ``low, low + step, ... <= high`` instead of continuous
            (kV in 5 kV steps: few distinct spectra, so imagers can be cached per spectrum).
        choices, probs: the values of a ``choice`` and their probabilities (summing to 1).
        p: the probability of True of a ``bernoulli``.
        limits: ``(lo, hi)``: the bounds an override of ``low`` / ``high`` must keep (None =
            unbounded); ``lo_open`` excludes ``lo``.
        physics: the :data:`sim.physics.settings.SETTINGS` name the value becomes (its range is
            checked there too), or None.
        when: ``(setting, values)``: the setting matters only where that setting's value is one
            of ``values`` (e.g. ``("field", ("circle",))``); None: always.
    """

    name: str
    stage: str
    dist: str
    help: str
    unit: str | None = None
    low: float | None = None
    high: float | None = None
    step: float | None = None
    choices: tuple = ()
    probs: tuple[float, ...] = ()
    p: float | None = None
    limits: tuple[float | None, float | None] = (None, None)
    lo_open: bool = False
    physics: str | None = None
    when: tuple[str, tuple] | None = None

    # -- text --------------------------------------------------------------------------------
    def limits_text(self) -> str:
        """``[20, 150] kV``, ``(0, 5]``, ``>= 0 mm``: what an override's ends must lie in."""
        lo, hi = self._limits()
        unit = f" {self.unit}" if self.unit else ""
        if lo is None and hi is None:
            return "any finite number" + unit
        if hi is None:
            return f"{'>' if self._lo_open() else '>='} {lo:g}{unit}"
        if lo is None:
            return f"<= {hi:g}{unit}"
        return f"{'(' if self._lo_open() else '['}{lo:g}, {hi:g}]{unit}"

    def distribution_text(self) -> str:
        """``uniform``, ``uniform, 5 kV steps``, ``log-uniform``, ``choice``, ``bernoulli``."""
        if self.step is not None:
            return f"uniform, {self.step:g}{' ' + self.unit if self.unit else ''} steps"
        return self.dist

    def range_text(self) -> str:
        """``[60, 130]``, ``p = 0.5``, ``"none" 0.3, "circle" 0.35, ...``."""
        if self.dist in ("uniform", "log-uniform"):
            return f"[{self.low:g}, {self.high:g}]"
        if self.dist == "bernoulli":
            return f"p(true) = {self.p:g}"
        return ", ".join(f"`{c!r}`".replace("'", '"') + f" {q:g}" for c, q in zip(self.choices, self.probs))

    def when_text(self) -> str:
        """``grid = true``, ``field in circle, rectangle`` or ``always``."""
        if self.when is None:
            return "always"
        key, values = self.when
        if len(values) == 1:
            v = values[0]
            return f"{key} = {str(v).lower() if isinstance(v, bool) else v}"
        return f"{key} in {', '.join(str(v) for v in values)}"

    # -- checks ------------------------------------------------------------------------------
    def _physics_setting(self):
        if self.physics is None:
            return None

        return SETTINGS[self.physics]

    def _limits(self) -> tuple[float | None, float | None]:
        """The override bounds: the record's ``limits``, narrowed to the physics setting's range."""
        lo, hi = self.limits
        s = self._physics_setting()
        if s is not None and s.kind in ("float", "int"):
            if s.low is not None and (lo is None or s.low > lo):
                lo = s.low
            if s.high is not None and (hi is None or s.high < hi):
                hi = s.high
        return lo, hi

    def _lo_open(self) -> bool:
        s = self._physics_setting()
        lo = self._limits()[0]
        if s is not None and s.kind in ("float", "int") and s.low == lo and s.low_open:
            return True
        return self.lo_open and self.limits[0] == lo

    def _check_end(self, v: float, where: str) -> None:
        lo, hi = self._limits()
        bad = ((lo is not None and (v <= lo if self._lo_open() else v < lo)) or (hi is not None and v > hi)
               or (self.dist == "log-uniform" and v <= 0))
        if bad:
            raise RandomizeError(f"{where}: the range must lie in {self.limits_text()}, got {v:g}")
        s = self._physics_setting()
        if s is not None:
            value = [(_FILTER_ELEMENT[self.name], v)] if s.kind == "filters" else v
            try:
                s.check(value, where=f"{where} (physics setting {s.name})")
            except PhysicsError as e:
                raise RandomizeError(str(e)) from None

    def check_against(self, declared: "Randomized", where: str | None = None) -> None:
        """Refuse (:class:`RandomizeError`) this distribution unless it is an allowed override of
        ``declared``: same name, stage, distribution, step and choices; range inside the limits
        and the physics range with ``low <= high``; probabilities in [0, 1] summing to 1."""
        where = where or f"randomize.{declared.name}"
        fixed = ("name", "stage", "dist", "step", "choices", "limits", "lo_open", "physics", "when", "unit")
        for k in fixed:
            if getattr(self, k) != getattr(declared, k):
                raise RandomizeError(f"{where}: {k} is declared as {getattr(declared, k)!r} and cannot change "
                                     f"(got {getattr(self, k)!r})")
        if self.dist in ("uniform", "log-uniform"):
            if not (_is_number(self.low) and _is_number(self.high)):
                raise RandomizeError(f"{where}: must be [low, high] with finite numbers, got "
                                     f"[{self.low!r}, {self.high!r}]")
            if not self.low <= self.high:
                raise RandomizeError(f"{where}: must be [low, high] with low <= high, got [{self.low:g}, "
                                     f"{self.high:g}]")
            self._check_end(self.low, where)
            self._check_end(self.high, where)
        elif self.dist == "bernoulli":
            if not (_is_number(self.p) and 0.0 <= self.p <= 1.0):
                raise RandomizeError(f"{where}: the probability of true must be a number in [0, 1], got {self.p!r}")
        else:
            q = self.probs
            if (len(q) != len(self.choices) or not all(_is_number(x) and x >= 0 for x in q)
                    or abs(sum(q) - 1.0) > 1e-9):
                raise RandomizeError(f"{where}: the probabilities of {list(self.choices)} must be numbers >= 0 "
                                     f"summing to 1, got {list(q)}")
            if self.physics is not None:
                for c in (c for c, x in zip(self.choices, q) if x > 0):
                    self._check_end(c, where)

    # -- drawing -----------------------------------------------------------------------------
    def value(self, u: float) -> Any:
        """The value of the uniform number ``u`` in [0, 1) (inverse distribution function)."""
        if self.dist == "bernoulli":
            return bool(u < self.p)
        if self.dist == "choice":
            cdf = _cdf(tuple(self.probs))
            i = bisect.bisect_right(cdf, u * cdf[-1])
            i = min(i, len(self.choices) - 1)
            while self.probs[i] == 0:  # u at a cdf plateau's end: the last choice with weight
                i -= 1
            return self.choices[i]
        lo, hi = float(self.low), float(self.high)
        if self.step is not None:
            n = int(math.floor((hi - lo) / self.step + 1e-9)) + 1
            return min(round(lo + min(int(u * n), n - 1) * self.step, 9), hi)
        if self.dist == "log-uniform":
            v = math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
        else:
            v = lo + u * (hi - lo)
        return min(max(v, lo), hi)

    # -- overrides ---------------------------------------------------------------------------
    def overridden(self, value: Any, where: str) -> "Randomized":
        """This record with the range / probabilities of a config value (module doc), checked."""
        if self.dist in ("uniform", "log-uniform"):
            unit = f" ({self.unit})" if self.unit else ""
            if _is_number(value):
                lo = hi = float(value)
            elif isinstance(value, (list, tuple)) and len(value) == 2 and all(_is_number(v) for v in value):
                lo, hi = (float(v) for v in value)
            else:
                raise RandomizeError(f"{where}: must be [low, high]{unit} or one number, got {value!r}")
            new = replace(self, low=lo, high=hi)
        elif self.dist == "bernoulli":
            if isinstance(value, bool):
                p = 1.0 if value else 0.0
            elif _is_number(value):
                p = float(value)
            else:
                raise RandomizeError(f"{where}: must be the probability of true, a number in [0, 1] (or true / "
                                     f"false), got {value!r}")
            new = replace(self, p=p)
        else:
            new = replace(self, probs=self._choice_probs(value, where))
        new.check_against(self, where)
        return new

    def _choice_probs(self, value: Any, where: str) -> tuple[float, ...]:
        shown = ", ".join(_fmt(c) for c in self.choices)
        keys = {_fmt(c): i for i, c in enumerate(self.choices)}
        if isinstance(value, (list, tuple)):
            idx = []
            for v in value:
                i = self._choice_index(v)
                if i is None:
                    raise RandomizeError(f"{where}: {v!r} is not a choice; allowed: {shown}")
                if i in idx:
                    raise RandomizeError(f"{where}: {v!r} is listed twice")
                idx.append(i)
            if not idx:
                raise RandomizeError(f"{where}: must list at least one of {shown}")
            return tuple(1.0 / len(idx) if i in idx else 0.0 for i in range(len(self.choices)))
        if isinstance(value, Mapping):
            w = [0.0] * len(self.choices)
            for k, x in value.items():
                if str(k) not in keys:
                    raise RandomizeError(f"{where}: {k!r} is not a choice; allowed: {shown}")
                if not (_is_number(x) and x >= 0):
                    raise RandomizeError(f"{where}.{k}: the weight must be a number >= 0, got {x!r}")
                w[keys[str(k)]] = float(x)
            total = sum(w)
            if total <= 0:
                raise RandomizeError(f"{where}: at least one weight must be > 0, got {dict(value)!r}")
            return tuple(w) if abs(total - 1.0) <= 1e-12 else tuple(x / total for x in w)
        raise RandomizeError(f"{where}: must be a list of choices or a table choice -> weight (choices: "
                             f"{shown}), got {value!r}")

    def _choice_index(self, v: Any) -> int | None:
        for i, c in enumerate(self.choices):
            if isinstance(c, str):
                if isinstance(v, str) and v == c:
                    return i
            elif _is_number(v) and float(v) == float(c):
                return i
        return None

    def override_value(self) -> Any:
        """The config value of this distribution (:meth:`overridden` reads it back)."""
        if self.dist in ("uniform", "log-uniform"):
            return [float(self.low), float(self.high)]
        if self.dist == "bernoulli":
            return float(self.p)
        return {_fmt(c): float(q) for c, q in zip(self.choices, self.probs)}


def _u(name, stage, low, high, help, unit=None, limits=(None, None), **kw) -> Randomized:
    return Randomized(name, stage, "uniform", help, unit, float(low), float(high), limits=limits, **kw)


def _lu(name, stage, low, high, help, unit=None, limits=(0.0, None), **kw) -> Randomized:
    return Randomized(name, stage, "log-uniform", help, unit, float(low), float(high), limits=limits,
                      lo_open=True, **kw)


def _c(name, stage, choices, probs, help, unit=None, **kw) -> Randomized:
    return Randomized(name, stage, "choice", help, unit, choices=tuple(choices), probs=tuple(probs), **kw)


def _b(name, stage, p, help, **kw) -> Randomized:
    return Randomized(name, stage, "bernoulli", help, p=float(p), **kw)


_FIELD = ("field", ("circle", "rectangle"))
_FRACTION_W, _FRACTION_H = "fraction of the width", "fraction of the height"

#: Every randomized setting, declared once. Append new ones at the end (module doc: a setting's
#: position is its place in the random stream).
DECLARATION: tuple[Randomized, ...] = (
    # -- physics: a PhysicsSettings -------------------------------------------------------------
    _u("kvp", "physics", 60, 130, "tube voltage", "kV", step=5.0, physics="kvp"),
    _u("al_mm", "physics", 2.0, 4.0, "aluminium filtration", "mm", limits=(0.0, None), step=0.5,
       physics="filters"),
    _c("cu_mm", "physics", (0.0, 0.1, 0.2, 0.3, 0.6, 0.9), (0.4, 0.15, 0.15, 0.1, 0.1, 0.1),
       "copper pre-filter (0: none), as a C-arm's filter wheel", "mm", physics="filters"),
    _lu("mas", "physics", 0.25, 8.0, "exposure: the quantum noise level (fewer mAs, more noise)", "mAs",
        physics="mas"),
    _b("grid", "physics", 0.5, "anti-scatter grid in place (acts at level full: Monte Carlo scatter and "
                               "primary transmission)"),
    _u("grid_ratio", "physics", 6, 16, "anti-scatter grid ratio", limits=(0.0, None), physics="grid_ratio",
       when=("grid", (True,))),
    _u("blur_mm", "physics", 0.1, 0.5, "Gaussian sigma of the detector blur at the detector", "mm",
       limits=(0.0, None), physics="blur_mm"),
    _c("scatter", "physics", ("none", "kernel", "monte-carlo", "sks"), (0.25, 0.5, 0.25, 0.0),
       "scatter: none, a Gaussian kernel model on the signal (cheap), Monte Carlo (level full, one "
       "transport per subject and batch), or scatter-kernel superposition fitted to the Monte Carlo for "
       "the drawn kV and grid (sim.physics.scatter_kernel's default table; cheap, physical)"),
    # -- signal: the raw detector signal after rendering (apply_image) ---------------------------
    _lu("scatter_spr", "signal", 0.1, 2.0, "kernel scatter-to-primary ratio: scatter = spr x G(signal)",
        limits=(0.0, 100.0), when=("scatter", ("kernel",))),
    _u("scatter_sigma", "signal", 0.05, 0.25, "Gaussian sigma of the kernel scatter",
       "fraction of the shorter side", limits=(0.0, 5.0), lo_open=True, when=("scatter", ("kernel",))),
    _u("scatter_scale", "signal", 0.5, 2.0, "factor on the Monte Carlo scatter", limits=(0.0, 10.0),
       when=("scatter", ("monte-carlo",))),
    _lu("electronic_noise_fraction", "signal", 1e-5, 1e-3, "Gaussian sigma of the electronic noise",
        "fraction of the flat-field signal I0", limits=(0.0, 1.0)),
    # -- collimator ----------------------------------------------------------------------------
    _c("field", "collimator", ("none", "circle", "rectangle"), (0.3, 0.35, 0.35),
       "collimated field: none (open), an iris (circle) or shutter blades (rectangle)"),
    _u("field_radius", "collimator", 0.3, 0.55, "circle radius", "fraction of the shorter side",
       limits=(0.0, 5.0), lo_open=True, when=("field", ("circle",))),
    _u("field_half_width", "collimator", 0.25, 0.5, "rectangle half width (along its rotated axis)", _FRACTION_W,
       limits=(0.0, 5.0), lo_open=True, when=("field", ("rectangle",))),
    _u("field_half_height", "collimator", 0.25, 0.5, "rectangle half height", _FRACTION_H,
       limits=(0.0, 5.0), lo_open=True, when=("field", ("rectangle",))),
    _u("field_offset_x", "collimator", -0.1, 0.1, "field centre right of the image centre", _FRACTION_W,
       limits=(-0.5, 0.5), when=_FIELD),
    _u("field_offset_y", "collimator", -0.1, 0.1, "field centre below the image centre", _FRACTION_H,
       limits=(-0.5, 0.5), when=_FIELD),
    _u("field_rotation_deg", "collimator", -45, 45, "rectangle rotation, counter-clockwise as displayed", "deg",
       limits=(-360.0, 360.0), when=("field", ("rectangle",))),
    _lu("field_transmission", "collimator", 0.005, 0.1, "fraction of the signal the blades pass",
        "fraction of the signal", limits=(0.0, 1.0), when=_FIELD),
    # -- display -------------------------------------------------------------------------------
    _c("shutter", "display", ("black", "white", "none"), (0.5, 0.25, 0.25),
       "what the outside of the field shows: black, white (electronic shutter) or the processed shadow",
       when=_FIELD),
    _b("log", "display", 0.8, "log image -log(I/I0) (true) or linear intensity I/I0 (false)"),
    _c("polarity", "display", ("bone-dark", "bone-bright"), (0.5, 0.5),
       "bone dark (fluoroscopy) or bone bright (radiograph)"),
    _u("window_low", "display", 0.0, 5.0, "in-field percentile shown as the darkest value", "%",
       limits=(0.0, 100.0)),
    _u("window_high", "display", 95.0, 100.0, "in-field percentile shown as the brightest value", "%",
       limits=(0.0, 100.0)),
    _lu("gamma", "display", 0.5, 2.0, "gamma curve x ** gamma on the displayed brightness", limits=(0.0, 10.0)),
    _b("unsharp", "display", 0.5, "unsharp masking (edge enhancement) on"),
    _u("unsharp_sigma_px", "display", 1.0, 8.0, "Gaussian sigma of the unsharp mask", "px",
       limits=(0.0, 100.0), lo_open=True, when=("unsharp", (True,))),
    _u("unsharp_amount", "display", 0.2, 1.5, "unsharp mask amount: x + amount (x - G(x))",
       limits=(0.0, 10.0), when=("unsharp", (True,))),
    _c("bits", "display", (8, 10, 12, 16), (0.25, 0.25, 0.25, 0.25), "output bit depth (quantisation)", "bits"),
    # -- appended (a setting's position is its place in the stream) -------------------------------
    _b("tools", "physics", 0.3, "metal tools (screws, K-wires, plates, retractors), a table and cables in the "
                                "field: one arrangement of the tool bank (ToolBank), attenuating in the density "
                                "integrals"),
    _u("tools_pick", "physics", 0.0, 1.0, "which arrangement of the tool bank, and its flip / transpose",
       "fraction of the bank", limits=(0.0, 1.0), when=("tools", (True,))),
    _b("ideal", "physics", 0.0, "the target is an ideal line-integral DRR instead, collimated as drawn (only the "
                                "field settings act: the field is geometry, not appearance): a share of ideal "
                                "targets keeps a network's accuracy on DRRs while it learns realistic ones"),
    _b("field_blades", "collimator", 0.4, "the iris cut by a pair of shutter blades (as on many C-arms)",
       when=("field", ("circle",))),
    _u("field_blade_half", "collimator", 0.2, 0.45, "distance of the blades from the field centre",
       _FRACTION_H, limits=(0.0, 5.0), lo_open=True, when=("field_blades", (True,))),
    _u("field_blade_rotation_deg", "collimator", -90, 90, "blades' rotation, counter-clockwise as displayed",
       "deg", limits=(-360.0, 360.0), when=("field_blades", (True,))),
    _lu("bone_scale", "physics", 0.75, 1.5, "factor on bone's attenuation (bone mineral density and the CT's "
                                            "calibration vary between patients): on the bone channels of the "
                                            "density integrals, or the bone basis of the two-basis model",
        limits=(0.0, 10.0)),
    _lu("sks_amplitude", "signal", 0.6, 1.7, "factor on the fitted kernel model's scatter (its subject, "
                                             "filtration and detector are one patient's and one tube's)",
        limits=(0.0, 100.0), when=("scatter", ("sks",))),
    _lu("sks_width", "signal", 0.75, 1.35, "factor on the fitted kernel model's widths", limits=(0.0, 10.0),
        when=("scatter", ("sks",))),
    _b("sks_open", "signal", 0.5, "the sks scatter of the whole detector's exposure, the collimator a mask on the "
                                  "finished signal (as sim's frames and many simulators make it: more scatter in "
                                  "the field), or of the collimated field only (a real collimator)",
       when=("scatter", ("sks",))),
    _lu("sks_texture", "signal", 0.02, 0.3, "relative std of the sks scatter's texture, a smooth random factor "
                                            "on it: the structure the thickness-only kernel model smooths away, "
                                            "and a Monte Carlo estimate's own noise (the frames' scatter)",
        limits=(0.0, 1.0), when=("scatter", ("sks",))),
    _lu("sks_texture_sigma", "signal", 0.02, 0.1, "Gaussian sigma of the sks scatter's texture (a Monte Carlo "
                                                  "estimate's noise at 10^6 histories: about 0.03)",
        "fraction of the shorter side", limits=(0.0, 1.0), when=("scatter", ("sks",))),
    _b("field_missed", "collimator", 0.0, "registration's field detection missed this collimated field: the "
                                         "network is shown the whole detector, the blades' shadow or the "
                                         "shutter outside the field included (what registration shows for a "
                                         "field read as none); realistic targets only (an ideal target has no "
                                         "shadow)", when=_FIELD),
)

_DECLARED: dict[str, Randomized] = {r.name: r for r in DECLARATION}


def _check_declaration() -> None:
    """The declaration's own consistency (run at import: a broken table is a bug, not user input)."""
    if len(_DECLARED) != len(DECLARATION):
        raise TypeError("sim.randomize.DECLARATION: duplicate names")
    for r in DECLARATION:
        if r.stage not in STAGES or r.dist not in DISTRIBUTIONS:
            raise TypeError(f"sim.randomize.DECLARATION: {r.name}: bad stage or distribution")
        if r.when is not None and (r.when[0] not in _DECLARED
                                   or DECLARATION.index(_DECLARED[r.when[0]]) >= DECLARATION.index(r)):
            raise TypeError(f"sim.randomize.DECLARATION: {r.name}: 'when' must name an earlier setting")


_check_declaration()


@functools.lru_cache(maxsize=256)
def _cdf(probs: tuple) -> tuple[float, ...]:
    """The running sums of ``probs`` (as ``np.cumsum``, in order), kept: a draw reads them per pair."""
    return tuple(itertools.accumulate(float(q) for q in probs))


def _check_index(name: str, v) -> int:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < 0:
        raise RandomizeError(f"{name} must be an integer >= 0, got {v!r}")
    return int(v)


def image_rng(seed: int, index: int) -> np.random.Generator:
    """The post-render noise stream of pair ``index`` (``(KIND_RANDOMIZE, index, 1)`` of
    :mod:`sim.core.seeds`): the ``rng`` to pass to :func:`apply_image`."""
    return rng_for(_check_index("seed", seed), KIND_RANDOMIZE, _check_index("index", index), 1)


@dataclass(frozen=True)
class Draw:
    """The drawn values of one pair (:meth:`DomainRandomization.draw`); frozen, hashable.

    ``draw["kvp"]`` is a value (float, bool, or a choice); every declared setting has one, also
    where its condition does not hold (:attr:`active` names those that matter).

    Attributes:
        seed, index: what it was drawn from.
        items: ``((name, value), ...)`` in declaration order.
    """

    seed: int
    index: int
    items: tuple[tuple[str, Any], ...]

    def __getitem__(self, name: str) -> Any:
        for k, v in self.items:
            if k == name:
                return v
        raise KeyError(name)

    @property
    def values(self) -> dict[str, Any]:
        """Every drawn value by name."""
        return dict(self.items)

    @property
    def active(self) -> tuple[str, ...]:
        """The settings whose condition (:attr:`Randomized.when`) holds in this draw."""
        v = self.values
        return tuple(k for k in v if _DECLARED[k].when is None or v[_DECLARED[k].when[0]] in _DECLARED[k].when[1])

    def to_dict(self) -> dict[str, Any]:
        """JSON-able: ``{"seed", "index", "values": {active setting: value}}``."""
        v = self.values
        return {"seed": self.seed, "index": self.index, "values": {k: v[k] for k in self.active}}

    @property
    def filters(self) -> tuple[tuple[str, float], ...]:
        """The drawn filtration ``(("Al", mm),)`` or ``(("Al", mm), ("Cu", mm))``."""
        cu = float(self["cu_mm"])
        return (("Al", float(self["al_mm"])),) + ((("Cu", cu),) if cu > 0 else ())

    def physics_settings(self, base):
        """``base`` (a :class:`sim.physics.settings.PhysicsSettings` at level ``poly`` or ``full``:
        its anode angle, bins, detector, seed and Monte Carlo settings are kept) with the drawn
        tube, filtration, exposure, grid (ratio 0 without), detector blur, ``noise=True``, and level
        ``full`` where the scatter is ``monte-carlo``, else ``poly``."""

        if not isinstance(base, PhysicsSettings):
            raise RandomizeError(f"physics_settings needs a PhysicsSettings, got {type(base).__name__}")
        if base.level == "line":
            raise RandomizeError("domain randomization needs physics level poly or full (line integrals have "
                                 "no spectrum, exposure or detector), got line")
        return replace(base, level="full" if self["scatter"] == "monte-carlo" else "poly", kvp=float(self["kvp"]),
                       filters=self.filters, mas=float(self["mas"]),
                       grid_ratio=float(self["grid_ratio"]) if self["grid"] else 0.0,
                       blur_mm=float(self["blur_mm"]), noise=True)

    def collimator(self, height: int, width: int):
        """The drawn :class:`sim.physics.display.Collimator`, or None for an open field. Refused
        (:class:`RandomizeError`) if its field holds no pixel of a ``height x width`` image."""

        shape = self["field"]
        if shape == "none":
            return None
        center = (0.5 + float(self["field_offset_x"]), 0.5 + float(self["field_offset_y"]))
        common = dict(center=center, transmission=float(self["field_transmission"]))
        if shape == "circle" and self["field_blades"]:
            col = Collimator(shape="iris-blades", radius=float(self["field_radius"]),
                             half_size=(5.0, float(self["field_blade_half"])),
                             rotation_deg=float(self["field_blade_rotation_deg"]), **common)
        elif shape == "circle":
            col = Collimator(shape="circle", radius=float(self["field_radius"]), **common)
        else:
            col = Collimator(shape="rectangle", half_size=(float(self["field_half_width"]),
                                                           float(self["field_half_height"])),
                             rotation_deg=float(self["field_rotation_deg"]), **common)
        if not col.mask(height, width).any():
            raise RandomizeError(f"draw {self.index}: the {shape} field holds no pixel of a {height} x {width} "
                                 f"image: widen randomize.field_radius / field_half_width / field_half_height")
        return col

    def display_chain(self):
        """The drawn :class:`sim.physics.display.DisplayChain` (``shutter`` ``black`` where the
        field is open: it has no outside)."""

        unsharp = bool(self["unsharp"])
        return DisplayChain(log=bool(self["log"]), polarity=self["polarity"],
                            window=(float(self["window_low"]), float(self["window_high"])),
                            gamma=float(self["gamma"]),
                            unsharp_sigma_px=float(self["unsharp_sigma_px"]) if unsharp else 0.0,
                            unsharp_amount=float(self["unsharp_amount"]) if unsharp else 0.0,
                            bits=int(self["bits"]), shutter=self["shutter"] if self["field"] != "none" else "black")


@dataclass(frozen=True)
class DomainRandomization:
    """The distributions of every randomized setting (:data:`DECLARATION`, with overrides).

    Args:
        settings: one :class:`Randomized` per declared setting, in declaration order (default:
            the declaration); each is checked against its declaration
            (:meth:`Randomized.check_against`), and ``window_low``'s high end must be below
            ``window_high``'s low end. Build it from a config with :meth:`from_table` or
            :func:`load_randomization`.

    ``draw(seed, index)`` -> :class:`Draw` (module doc: reproducible from ``(seed, index)``).
    """

    settings: tuple[Randomized, ...] = DECLARATION

    def __post_init__(self) -> None:
        got = tuple(getattr(r, "name", r) for r in self.settings)
        if got != tuple(_DECLARED):
            raise RandomizeError(f"DomainRandomization needs one setting per declared name, in order "
                                 f"{list(_DECLARED)}, got {list(got)}")
        for r in self.settings:
            r.check_against(_DECLARED[r.name])
        s = self.by_name
        if not s["window_low"].high < s["window_high"].low:
            raise RandomizeError(f"randomize.window_low's high end ({s['window_low'].high:g} %) must be below "
                                 f"randomize.window_high's low end ({s['window_high'].low:g} %)")

    @property
    def by_name(self) -> dict[str, Randomized]:
        return {r.name: r for r in self.settings}

    @classmethod
    def from_table(cls, table: Mapping[str, Any] | None, where: str = "randomize") -> "DomainRandomization":
        """The declaration with the overrides of a ``[randomize]`` table (module doc); ``where``
        prefixes the keys in messages."""
        if table is None:
            return cls()
        if not isinstance(table, Mapping):
            raise RandomizeError(f"{where} must be a table of setting = range, got {type(table).__name__}")
        unknown = sorted(set(table) - set(_DECLARED))
        if unknown:
            raise RandomizeError(f"unknown key(s) {', '.join(f'{where}.{k}' for k in unknown)}; allowed: "
                                 f"{', '.join(_DECLARED)}")
        return cls(tuple(r.overridden(table[r.name], f"{where}.{r.name}") if r.name in table else r
                         for r in DECLARATION))

    def to_dict(self) -> dict[str, Any]:
        """Every setting's config value (JSON-able); :meth:`from_table` reads it back."""
        return {r.name: r.override_value() for r in self.settings}

    def draw(self, seed: int, index: int) -> Draw:
        """The values of pair ``index`` under ``seed`` (both integers >= 0)."""
        seed, index = _check_index("seed", seed), _check_index("index", index)
        u = rng_for(seed, KIND_RANDOMIZE, index, 0).random(len(self.settings))
        return Draw(seed, index, tuple((r.name, r.value(float(x))) for r, x in zip(self.settings, u)))


#: Arrangements in a :class:`ToolBank`; with the 8 flips / transposes of a square image, 128 looks.
TOOL_BANK_SIZE = 16


class ToolBank:
    """The tool arrangements that the ``tools`` setting picks from, for one image geometry.

    Arrangement ``j`` (``0 <= j <`` :data:`TOOL_BANK_SIZE`) is :func:`sim.distractors.random_tools`
    drawn from the stream ``(KIND_RANDOMIZE, j, 2)`` under ``seed``: tools in the camera frame, so
    its chords (mm, per material channel) are one image whatever the pose, traced once by
    Mitsuba and kept. A draw's ``tools_pick`` chooses the arrangement and one of the 8 flips and
    transposes of the image (transposes on square images only) -- a target image's tools need
    no anatomical meaning, only a realistic look, and a bank costs a few seconds once instead
    of a trace per pair.

    Args:
        seed: the randomization seed (integer >= 0).
        geometry: the :class:`sim.projection.geometry.CArmGeometry` of the images.
        scene: the C-arm scene whose sensor makes the rays.
    """

    def __init__(self, seed: int, geometry, *, scene: str = "cios_fusion"):
        self.seed = _check_index("seed", seed)
        self.geometry = geometry
        self.scene = scene
        self._cache: dict[int, tuple[np.ndarray, tuple]] = {}

    def arrangement(self, j: int):
        """``(chords (C, H, W) float32 mm, channels ((material, g/cm^3), ...))`` of arrangement ``j``."""
        j = _check_index("arrangement", j)
        if j >= TOOL_BANK_SIZE:
            raise RandomizeError(f"tool bank arrangement must be < {TOOL_BANK_SIZE}, got {j}")
        if j not in self._cache:
            tools = random_tools(rng_for(self.seed, KIND_RANDOMIZE, j, 2), self.geometry)
            field = DistractorField(tools, self.geometry, np.zeros(3), scene=self.scene)
            self._cache[j] = (field.chords(np.eye(4))[0], field.channels)
        return self._cache[j]

    def for_draw(self, draw: "Draw"):
        """The chords and channels of ``draw`` (its arrangement, flipped / transposed), or None
        when the draw has no tools."""
        if not draw["tools"]:
            return None
        pick = min(float(draw["tools_pick"]), 1.0 - 1e-12) * TOOL_BANK_SIZE * 8
        j, look = int(pick) // 8, int(pick) % 8
        chords, channels = self.arrangement(j)
        if look & 1:
            chords = chords[:, ::-1]
        if look & 2:
            chords = chords[:, :, ::-1]
        if look & 4 and chords.shape[1] == chords.shape[2]:
            chords = chords.transpose(0, 2, 1)
        return np.ascontiguousarray(chords), channels


def load_randomization(path: str | Path) -> DomainRandomization:
    """The :class:`DomainRandomization` of a TOML file's ``[randomize]`` table (the declaration
    where the file has none; other tables are left to their readers)."""

    path = Path(path)
    data = read_toml(path, RandomizeError, "randomization config")
    try:
        return DomainRandomization.from_table(data.get("randomize"))
    except RandomizeError as e:
        raise RandomizeError(f"{path}: {e}") from None


def sks_model(draw: Draw, table=None):
    """The :class:`sim.physics.scatter_kernel.ScatterKernelModel` of a draw whose scatter is
    ``sks``: the table's model (default :func:`sim.physics.scatter_kernel.default_table`) at the
    drawn kV and grid ratio (0 without a grid), its amplitudes times ``sks_amplitude`` and its
    widths times ``sks_width`` (:meth:`ScatterKernelTable.drawn`)."""

    table = default_table() if table is None else table
    return table.drawn(float(draw["kvp"]), float(draw["grid_ratio"]) if draw["grid"] else 0.0,
                       float(draw["sks_amplitude"]), float(draw["sks_width"]))


def sks_texture(normals: np.ndarray, strength: float, sigma_px: float) -> np.ndarray:
    """The smooth random factor on the ``sks`` scatter of one image (NumPy ``(H, W)`` in and out,
    float64): :func:`sim.physics.chain.sks_texture`, which the chain applies."""
    import torch  # slow to import: only the chain's callers need it

    from sim.physics.chain import sks_texture as chain_texture  # loads torch (above)

    n = torch.from_numpy(np.asarray(normals, np.float64))[None]
    return chain_texture(n, float(strength), float(sigma_px))[0].numpy()


def apply_image(raw_intensity: np.ndarray, i0: float, draw: Draw, rng: np.random.Generator, *,
                scatter: np.ndarray | None = None, geometry=None, gap_mm: float | None = None,
                sks_table=None) -> tuple[np.ndarray, np.ndarray]:
    """The post-render stages of ``draw`` (module doc): raw detector signal ``(H, W)`` (keV or
    counts per pixel, :meth:`sim.physics.imaging.XRayImager.render`'s ``raw``), its flat-field
    signal ``i0`` (``imager.flat``), the noise stream ``rng`` (:func:`image_rng`) and, where the
    draw's scatter is ``monte-carlo``, the expected scatter image ``(H, W)`` (the render's
    ``scatter``) -> ``(image, field_mask)``: display integers ``(H, W)`` ``uint16`` in
    ``0 .. 2^bits - 1`` and the collimated field ``(H, W)`` bool (all True when open).

    Where the draw's scatter is ``sks``: ``geometry`` (the :class:`sim.projection.geometry.CArmGeometry` of
    the image: the kernels are mm at the detector) is required; ``gap_mm`` the air gap of the
    target pose (anatomy centre to detector, mm; :func:`sim.physics.scatter_kernel.detector_gap_mm`;
    None: the model's reference gap); ``sks_table`` the :class:`ScatterKernelTable` (None: the
    default). The scatter ``S`` of :func:`sks_model` from ``tau = -ln(raw / i0)`` of the
    collimated signal (``sks_open``: of the signal before collimation, ``S`` then collimated as
    the signal is), times its texture (:func:`sks_texture` of a third normal draw of ``rng``), is
    added with its quantum noise (``sqrt(S e)`` times the second normal draw of ``rng``, ``e`` the
    model's signal per scattered photon), after the electronic noise's draw.

    The stages are the imaging chain's (:func:`sim.physics.chain.apply_chain`, this image a batch of
    one in float64, its field :meth:`Draw.collimator`'s mask); the Monte Carlo's scatter, the
    render's, is added before (times ``scatter_scale - 1``: the render holds it once)."""
    raw = np.asarray(raw_intensity)
    if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.number) or np.iscomplexobj(raw) or raw.size == 0:
        raise RandomizeError(f"apply_image needs a real (H, W) raw signal, got shape {raw.shape} dtype {raw.dtype}")
    raw = raw.astype(np.float64)
    if not np.all(np.isfinite(raw)):
        raise RandomizeError("apply_image: the raw signal must be finite (no NaN or inf)")
    if not (_is_number(i0) and i0 > 0):
        raise RandomizeError(f"apply_image: i0 (the flat-field signal) must be a finite number > 0, got {i0!r}")
    if not isinstance(draw, Draw):
        raise RandomizeError(f"apply_image needs a Draw (DomainRandomization.draw), got {type(draw).__name__}")
    if not isinstance(rng, np.random.Generator):
        raise RandomizeError(f"apply_image needs a numpy Generator (image_rng(seed, index)), got "
                             f"{type(rng).__name__}")
    mode = draw["scatter"]
    if mode == "monte-carlo":
        if scatter is None:
            raise RandomizeError("apply_image: the draw's scatter is monte-carlo: pass the render's expected "
                                 "scatter image (render(...)['scatter'])")
        sc = np.asarray(scatter, dtype=np.float64)
        if sc.shape != raw.shape or not np.all(np.isfinite(sc)):
            raise RandomizeError(f"apply_image: scatter must be a finite array of the raw shape {raw.shape}, "
                                 f"got {sc.shape}")
        raw = raw + (float(draw["scatter_scale"]) - 1.0) * sc
    elif scatter is not None:
        raise RandomizeError(f"apply_image: a scatter image was given but the draw's scatter is {mode!r} (render "
                             f"with draw.physics_settings(...), which is level poly there)")
    h, w = raw.shape
    if mode == "sks" and (not isinstance(geometry, CArmGeometry) or (geometry.height, geometry.width) != (h, w)):
        raise RandomizeError(f"apply_image: the draw's scatter is sks: pass the image's geometry (a CArmGeometry "
                             f"of {h} x {w} px), got {geometry!r}")
    import torch  # slow to import: only the chain's callers need it

    from sim.physics.chain import apply_chain  # loads torch (above); the chain is below this module

    col = draw.collimator(h, w)
    field = np.ones((h, w), bool) if col is None else col.mask(h, w)
    p = draw_tensors([draw], dtype=torch.float64)
    if mode == "monte-carlo":  # its scatter is in raw now: the chain adds none
        p["scatter"] = torch.zeros(1, dtype=torch.int64)
    normals = rng.standard_normal((h, w))  # the draws' order: electronic noise, then the sks scatter's two
    scatter_normals = torch.from_numpy(rng.standard_normal((2, h, w)))[None] if mode == "sks" else None
    image, _ = apply_chain(torch.from_numpy(raw)[None], float(i0), p, torch.from_numpy(normals)[None],
                           field=torch.from_numpy(field)[None], geometry=geometry,
                           gap_mm=None if gap_mm is None else [float(gap_mm)], scatter_normals=scatter_normals,
                           sks_table=sks_table)
    return image[0].numpy().astype(np.uint16), field


# --------------------------------------------------------------------------------------------
# draws -> the chain's settings
# --------------------------------------------------------------------------------------------


def draw_tensors(draws, *, device=None, dtype=None) -> dict:
    """The drawn settings of a batch as tensors, one ``(B,)`` tensor per entry.

    Args:
        draws: ``B`` :class:`sim.randomize.Draw` (``DomainRandomization.draw``), one per pair.
        device: where the tensors live (None: torch's default device).
        dtype: the floating torch dtype of the numeric settings (None: float32).

    Returns:
        ``{name: (B,) tensor}`` with, for every declared setting (:data:`sim.randomize.DECLARATION`)
        under its own name and in its own unit:

        * ``uniform`` / ``log-uniform`` settings: the value, ``dtype``;
        * ``bernoulli`` settings: bool;
        * ``choice`` settings: int64 codes, the index of the value in the setting's declared
          ``choices`` (e.g. ``scatter``: 0 ``none``, 1 ``kernel``, 2 ``monte-carlo``; ``bits``:
          0 for 8, 1 for 10, 2 for 12, 3 for 16); a choice among numbers (``cu_mm``, ``bits``)
          also gets ``<name>_value``, the value itself, ``dtype``;

        and the derived entries

        * ``field_code`` int64: the field's shape, an index into
          :data:`sim.physics.chain.FIELD_CODES` (0 none,
          1 circle, 2 rectangle, 3 iris-blades, as :meth:`sim.randomize.Draw.collimator`);
        * ``field_cx``, ``field_cy``: the field centre, fractions of the width and height
          (``0.5 + field_offset_x``, ``0.5 + field_offset_y``);
        * ``field_r``: the circle radius, a fraction of the shorter side (circle, iris-blades);
        * ``field_half_u``, ``field_half_v``: the blades' half width (fraction of the width) and
          half height (fraction of the height) along their rotated axes (rectangle:
          ``field_half_width``, ``field_half_height``; iris-blades: 5.0, ``field_blade_half``);
        * ``field_cos``, ``field_sin``: cosine and sine of the blades' rotation
          (``field_rotation_deg``, or ``field_blade_rotation_deg`` for iris-blades), computed as
          :meth:`Collimator.mask` does (Python's ``math``);
        * ``max_value``: ``2^bits - 1``, ``dtype``.

        The seven ``field_*`` geometry entries are float64 whatever ``dtype`` (the masks of
        :func:`field_masks` are then exactly the numpy ones); the device must support float64.

    The settings of :func:`sim.physics.chain.apply_chain`: the one place where draws become the
    chain's input.
    """
    import torch  # slow to import: only the chain's callers need it

    from sim.physics.chain import FIELD_CODES, GEOMETRY_KEYS  # loads torch (above); the chain is below this module

    dtype = torch.float32 if dtype is None else dtype
    try:
        draws = list(draws)
    except TypeError:
        raise RandomizeError(f"draw_tensors: draws must be a list of sim.randomize.Draw, got {type(draws).__name__}") \
            from None
    bad = [type(d).__name__ for d in draws if not isinstance(d, Draw)]
    if bad:
        raise RandomizeError(f"draw_tensors: draws must be sim.randomize.Draw (DomainRandomization.draw), got {bad[0]}")
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise RandomizeError(f"draw_tensors: dtype must be a torch floating dtype, got {dtype!r}")
    values = [d.values for d in draws]
    out: dict[str, torch.Tensor] = {}

    def put(name, column, kind):
        out[name] = torch.tensor(column, dtype=kind, device=device).reshape(len(draws))

    for r in DECLARATION:
        column = [v[r.name] for v in values]
        if r.dist == "bernoulli":
            put(r.name, [bool(c) for c in column], torch.bool)
        elif r.dist == "choice":
            put(r.name, [r.choices.index(c) for c in column], torch.int64)
            if all(not isinstance(c, str) for c in r.choices):
                put(f"{r.name}_value", [float(c) for c in column], dtype)
        else:
            put(r.name, [float(c) for c in column], dtype)

    geo = {k: [] for k in ("field_code",) + GEOMETRY_KEYS}
    for v in values:
        shape, blades = v["field"], v["field_blades"]
        code = FIELD_CODES.index("iris-blades" if shape == "circle" and blades else shape)
        if code == 3:
            half, rot = (5.0, float(v["field_blade_half"])), float(v["field_blade_rotation_deg"])
        else:
            half, rot = (float(v["field_half_width"]), float(v["field_half_height"])), float(v["field_rotation_deg"])
        t = math.radians(rot)
        for k, x in zip(geo, (code, 0.5 + float(v["field_offset_x"]), 0.5 + float(v["field_offset_y"]),
                              float(v["field_radius"]), half[0], half[1], math.cos(t), math.sin(t))):
            geo[k].append(x)
    put("field_code", geo.pop("field_code"), torch.int64)
    for k, column in geo.items():
        put(k, column, torch.float64)
    put("max_value", [float((1 << int(v["bits"])) - 1) for v in values], dtype)
    return out


# --------------------------------------------------------------------------------------------
# docs
# --------------------------------------------------------------------------------------------

_DOC_HEADER = ("| setting | acts on | unit | distribution | default range / choices | drawn when | override "
               "limits | meaning |")


def doc_table_rows() -> list[str]:
    """The Markdown table of ``docs/domain_randomization.md``: header, separator, one row per
    declared setting (grouped by stage, in declaration order within a stage)."""
    rows = [_DOC_HEADER, "|---|---|---|---|---|---|---|---|"]
    for stage in STAGES:
        for r in (r for r in DECLARATION if r.stage == stage):
            limits = ("declared choices" if r.dist == "choice" else "[0, 1]" if r.dist == "bernoulli"
                      else r.limits_text())
            if r.physics is not None:
                limits += f" (physics `{r.physics}`)"
            rows.append(f"| `{r.name}` | {r.stage} | {r.unit or '-'} | {r.distribution_text()} | {r.range_text()} "
                        f"| {r.when_text()} | {limits} | {r.help} |")
    return rows


if __name__ == "__main__":  # print the docs table
    print("\n".join(doc_table_rows()))
