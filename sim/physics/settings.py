"""The physics settings, declared once: name, unit, default, range or choices, levels and help.

:class:`PhysicsSettings` is the declaration: each of its fields carries a :class:`Setting`
(:data:`SETTINGS`, in field order). Everything else is derived from it, with **one spelling**:

* the dataclass field ``anode_angle_deg`` and its validation (:meth:`Setting.check`, run by
  ``PhysicsSettings.__post_init__``, which also normalises the value: ``float`` for numbers,
  ``(("Al", 2.5), ...)`` for filters);
* the campaign file's ``[[physics]]`` key ``anode_angle_deg`` (:class:`sim.campaign.config.PhysicsConfig`
  gets one field per setting with :func:`with_campaign_settings`; the parser checks each key with
  :meth:`Setting.check`, refuses a key at a level outside :attr:`Setting.levels`, and
  :data:`FORMER_NAMES` turns an old spelling into an error naming the key to use);
* the command-line option ``--anode-angle-deg`` (:func:`sim.physics.options.physics_option`: help,
  unit, default, choices; ``_`` -> ``-``), checked with the same :meth:`Setting.check`;
* the table of ``docs/campaigns.md`` (:func:`campaign_table_rows`).

Ranges are closed unless written with a parenthesis: ``kvp`` in [20, 150] kV, ``mas`` > 0 mAs.
A value outside its range is refused with a :class:`sim.physics.PhysicsError` that names the
setting (as the field, the campaign key path or the option), its unit and the range.

This module imports no numpy, no Dr.Jit (the filters' element symbols are checked against
sim.physics.filters.ELEMENT_SYMBOLS). The Monte Carlo's own settings are built from these by
:meth:`sim.physics.scatter.ScatterSettings.of`.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, fields
from typing import Any

from sim.physics import PhysicsError
from sim.physics.filters import parse_filters

#: Physics levels: line integrals, polychromatic, polychromatic + Monte Carlo scatter.
LEVELS: tuple[str, ...] = ("line", "poly", "full")
#: Detector modes: energy-integrating (signal in keV) or photon-counting (signal in counts).
DETECTOR_MODES: tuple[str, ...] = ("integrating", "counting")

_POLY = ("poly", "full")
_FULL = ("full",)
_KINDS = ("float", "int", "bool", "choice", "filters")


@dataclass(frozen=True)
class Setting:
    """One physics setting (see the module doc).

    Attributes:
        name: the dataclass field, the campaign key, and the option ``--name`` with ``_`` -> ``-``.
        default: the default value (as :class:`PhysicsSettings` holds it).
        help: what it is, for the option's help and the docs (without unit or range).
        kind: ``float``, ``int``, ``bool``, ``choice`` or ``filters`` (``SYMBOL:MM`` items).
        unit: e.g. ``kV``, ``deg``, ``mm``, ``mAs``; None for counts and plain numbers.
        low, high: the range (None = unbounded); ``low_open`` / ``high_open`` exclude the bound.
        choices: the allowed values of a ``choice``.
        levels: the physics levels where the setting means something; elsewhere a campaign
            key or a command-line option that sets it is refused.
        campaign: a ``[[physics]]`` key of campaign files (``seed`` is not: the campaign runner
            seeds every shard; ``level`` is read by the parser itself).
        cli: declared by :func:`sim.physics.options.physics_option` (``level`` is not: each
            command declares it with its own help and default, ``line``).
        recorded_always: written to a dataset manifest's config even at its default (the
            settings of the first campaign format); the others only when changed, so that the
            config hash of a campaign written before they existed stays the same.
        metavar: the option's metavar on the command line.
    """

    name: str
    default: Any
    help: str
    kind: str
    unit: str | None = None
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] = ()
    levels: tuple[str, ...] = _POLY
    campaign: bool = True
    cli: bool = True
    recorded_always: bool = False
    metavar: str | None = None

    @property
    def flag(self) -> str:
        """The command-line option, ``--anode-angle-deg``."""
        return "--" + self.name.replace("_", "-")

    @property
    def type_name(self) -> str:
        """The field's annotation."""
        return {"float": "float", "int": "int", "bool": "bool", "choice": "str",
                "filters": "tuple[tuple[str, float], ...]"}[self.kind]

    def range_text(self) -> str:
        """``in [20, 150]``, ``> 0``, ``>= 1000`` or ``""`` (no unit)."""
        lo, hi = self.low, self.high
        if lo is None and hi is None:
            return ""
        if hi is None:
            return f"{'>' if self.low_open else '>='} {lo:g}"
        if lo is None:
            return f"{'<' if self.high_open else '<='} {hi:g}"
        return f"in {'(' if self.low_open else '['}{lo:g}, {hi:g}{')' if self.high_open else ']'}"

    def allowed(self) -> str:
        """What the setting accepts, with its unit: ``a number in [20, 150] kV``."""
        if self.kind == "bool":
            return "true or false"
        if self.kind == "choice":
            return "one of " + ", ".join(self.choices)
        if self.kind == "filters":
            return ("a list of SYMBOL:MM items (an element symbol and a thickness >= 0 mm), "
                    "e.g. Al:2.5 Cu:0.1")
        noun = "an integer" if self.kind == "int" else "a number"
        unit = f" {self.unit}" if self.unit else ""
        rng = self.range_text()
        return f"{noun} {rng}{unit}" if rng else f"{noun}{unit}"

    def _in_range(self, v: float) -> bool:
        if self.low is not None and not (v > self.low if self.low_open else v >= self.low):
            return False
        return self.high is None or (v < self.high if self.high_open else v <= self.high)

    def check(self, value: Any, where: str | None = None) -> Any:
        """``value`` normalised (``float`` for numbers, ``int``, ``bool``, filters as
        ``(("Al", 2.5), ...)``), or :class:`sim.physics.PhysicsError` ``"<where>: must be
        <allowed>, got <value>"``; ``where`` (default: the name) is the spelling of the place the
        value came from: ``physics[0].kvp`` in a campaign, ``--kvp`` on the command line."""
        where = where or self.name
        bad = PhysicsError(f"{where}: must be {self.allowed()}, got {value!r}")
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise bad
            return value
        if self.kind == "choice":
            if not isinstance(value, str) or value not in self.choices:
                raise bad
            return value
        if self.kind == "filters":
            return self._check_filters(value, where)
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise bad
        if self.kind == "int":
            if not isinstance(value, numbers.Integral) or not self._in_range(int(value)):
                raise bad
            return int(value)
        v = float(value)
        if not (math.isfinite(v) and self._in_range(v)):
            raise bad
        return v

    def _check_filters(self, value: Any, where: str) -> tuple[tuple[str, float], ...]:
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            raise PhysicsError(f"{where}: must be {self.allowed()}, got {value!r}")
        try:
            return parse_filters(value)
        except PhysicsError as e:
            raise PhysicsError(f"{where}: {e}") from None

    def text(self, value: Any) -> Any:
        """``value`` as a campaign file or the command line writes it (filters: ``"Al:2.5"``
        items), as plain JSON types."""
        if self.kind == "filters":
            return [f"{s}:{t:g}" for s, t in value]
        return {"float": float, "int": int, "bool": bool, "choice": str}[self.kind](value)


def _setting(default: Any, help: str, *, kind: str | None = None, **kw) -> Any:
    """A :class:`PhysicsSettings` field declaring its :class:`Setting` (name and default from the field)."""
    if kind is None:
        kind = ("bool" if isinstance(default, bool) else "int" if isinstance(default, int)
                else "float" if isinstance(default, float) else "choice")
    if kind not in _KINDS:
        raise TypeError(f"setting kind must be one of {_KINDS}, got {kind!r}")
    return field(default=default, metadata={"setting": dict(help=help, kind=kind, **kw)})


@dataclass(frozen=True)
class PhysicsSettings:
    """The physics of realistic images (:class:`sim.physics.imaging.XRayImager`): the declaration
    of every physics setting (module doc). Each field's :class:`Setting` below holds its unit,
    default, range, levels and help (``docs/campaigns.md`` lists them).

    Attributes:
        level: ``line``, ``poly`` or ``full`` (``poly`` + Monte Carlo scatter).
        kvp: tube voltage (kV); anode_angle_deg: tungsten anode angle (deg).
        filters: ``((symbol, mm), ...)`` added filtration, e.g. ``(("Al", 2.5), ("Cu", 0.1))``;
            ``"Al:2.5"`` items are accepted and converted.
        bins: energy bins of the spectrum.
        mas: tube current-time product (mAs) of the exposure.
        detector_mm: CsI:Tl thickness (mm); detector_mode: ``integrating`` or ``counting``.
        noise: add quantum noise, blur and electronic noise; seed: their random seed.
        blur_mm: Gaussian sigma of the detector blur at the detector (mm).
        electronic_noise: Gaussian sigma in signal units (keV per pixel integrating, counts
            per pixel counting).
        scatter_photons: Monte Carlo histories per image (``full``).
        scatter_voxel_mm: voxel size (mm) of the transport grid (``full``).
        grid_ratio: anti-scatter grid ratio, 0 = no grid (``full``).

    Raises:
        PhysicsError: a value out of its range, naming the setting, its unit and the range.
    """

    level: str = _setting("poly", "physics level: line integrals of mu (line), polychromatic (poly), "
                                  "poly + Monte Carlo scatter (full)", choices=LEVELS, levels=LEVELS,
                          campaign=False, cli=False)
    kvp: float = _setting(120.0, "tube voltage", unit="kV", low=20.0, high=150.0, recorded_always=True,
                          metavar="KV")
    anode_angle_deg: float = _setting(12.0, "tungsten anode angle", unit="deg", low=1.0, high=45.0, metavar="DEG")
    filters: tuple[tuple[str, float], ...] = _setting(
        (("Al", 2.5),), "added filtration, an element symbol and a thickness per item", kind="filters",
        unit="mm", recorded_always=True, metavar="SYMBOL:MM")
    bins: int = _setting(30, "energy bins of the spectrum", low=1, high=1000, metavar="N")
    mas: float = _setting(2.5, "exposure (tube current-time product)", unit="mAs", low=0.0, low_open=True,
                          recorded_always=True)
    detector_mm: float = _setting(0.6, "CsI:Tl thickness", unit="mm", low=0.0, low_open=True, metavar="MM")
    detector_mode: str = _setting("integrating", "energy-integrating (signal in keV) or photon-counting "
                                                 "(signal in counts) detector", choices=DETECTOR_MODES)
    noise: bool = _setting(True, "quantum noise, detector blur and electronic noise", recorded_always=True)
    seed: int = _setting(0, "noise and Monte Carlo seed", low=0, campaign=False)
    blur_mm: float = _setting(0.3, "Gaussian sigma of the detector blur at the detector, applied with the noise",
                              unit="mm", low=0.0, metavar="MM")
    electronic_noise: float = _setting(0.0, "Gaussian sigma of the electronic noise in signal units: keV per "
                                            "pixel (integrating) or counts per pixel (counting)", low=0.0,
                                       metavar="SIGMA")
    scatter_photons: int = _setting(1_000_000, "Monte Carlo histories per image", low=1000, levels=_FULL,
                                    recorded_always=True, metavar="N")
    scatter_voxel_mm: float = _setting(6.0, "voxel size of the Monte Carlo transport grid", unit="mm", low=0.0,
                                       low_open=True, high=100.0, levels=_FULL, metavar="MM")
    grid_ratio: float = _setting(0.0, "anti-scatter grid ratio, 0 = no grid", low=0.0, high=50.0, levels=_FULL,
                                 recorded_always=True, metavar="R")

    def __post_init__(self) -> None:
        for s in SETTINGS.values():
            object.__setattr__(self, s.name, s.check(getattr(self, s.name)))


#: Every setting by name, in the field order of :class:`PhysicsSettings`.
SETTINGS: dict[str, Setting] = {
    f.name: Setting(name=f.name, default=f.default, **f.metadata["setting"]) for f in fields(PhysicsSettings)
}

#: Former spellings (of the dataclass, the options or the campaign keys) -> the setting's name.
#: A campaign key spelled the old way is refused with a message naming the new one.
FORMER_NAMES: dict[str, str] = {"n_bins": "bins", "filter": "filters", "anode_angle": "anode_angle_deg",
                                "scatter_voxel": "scatter_voxel_mm"}


def campaign_settings() -> tuple[Setting, ...]:
    """The settings that are ``[[physics]]`` keys of campaign files, in declaration order."""
    return tuple(s for s in SETTINGS.values() if s.campaign)


def with_campaign_settings(cls):
    """Class decorator, applied before ``@dataclass``: one field per campaign setting, with its
    annotation and default (after the class's own fields)."""
    annotations = dict(cls.__dict__.get("__annotations__", {}))
    for s in campaign_settings():
        if s.name in annotations:
            raise TypeError(f"{cls.__name__}.{s.name} is declared by sim.physics.settings")
        annotations[s.name] = s.type_name
        setattr(cls, s.name, s.default)
    cls.__annotations__ = annotations
    return cls


def campaign_table_rows() -> list[str]:
    """The rows of the ``[[physics]]`` table of ``docs/campaigns.md`` for the settings (key,
    type, default, unit, levels and meaning)."""
    types = {"float": "number", "int": "integer", "bool": "bool", "choice": "string", "filters": "list of strings"}
    rows = []
    for s in campaign_settings():
        default = s.text(s.default)
        shown = ("[" + ", ".join(f'"{v}"' for v in default) + "]" if s.kind == "filters"
                 else f'"{default}"' if s.kind == "choice" else str(default).lower() if s.kind == "bool"
                 else str(default))
        levels = " and ".join(s.levels) + " only"
        allowed = ("one of " + ", ".join(f'`"{c}"`' for c in s.choices) if s.kind == "choice"
                   else "`SYMBOL:MM` items, e.g. `[\"Al:2.5\", \"Cu:0.1\"]`" if s.kind == "filters"
                   else s.range_text() if s.kind in ("int", "float") else "true or false")
        unit = f" {s.unit} " if s.unit else " "
        rows.append(f"| `{s.name}` | {types[s.kind]} | `{shown}` |{unit}| {levels}; {s.help}; {allowed} |")
    return rows
