"""The physics options of the command line for ``render``, ``register`` and ``evaluate``, derived
from the settings' declaration (:mod:`sim.physics.settings`).

A command declares the options it takes as dataclass fields made by :func:`physics_option`: the
field's name is the setting's name (``anode_angle_deg`` -> ``--anode-angle-deg``), and its help,
unit, range, choices, default and levels come from the setting's :class:`~sim.physics.settings.Setting`.
:func:`check_level_options` refuses an option given at a physics level where it means nothing
and a value outside its range, naming the option, its unit and the range;
:func:`physics_settings` turns the fields into a :class:`~sim.physics.settings.PhysicsSettings`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Any

from sim.core.cliargs import Range, opt
from sim.physics.settings import LEVELS, SETTINGS, PhysicsSettings
from sim.physics import PhysicsError
from sim.physics.materials import parse_label_materials

#: Command-line physics options that are not settings of :class:`PhysicsSettings`:
#: name -> (default, help, opt() keywords, physics levels where it means something).
_EXTRA: dict[str, tuple[Any, str, dict, tuple[str, ...]]] = {
    "label_material": ((), "the label map overrides the HU-based material where it holds LABEL: "
                           "LABEL:MATERIAL items, e.g. 3:titanium for a segmented implant (needs --label-map)",
                       dict(nargs="+", metavar="LABEL:MATERIAL"), ("poly", "full")),
}


def _option_names() -> list[str]:
    return [s.name for s in SETTINGS.values() if s.cli] + list(_EXTRA)


def _levels(name: str) -> tuple[str, ...]:
    return SETTINGS[name].levels if name in SETTINGS else _EXTRA[name][3]


def physics_option(name: str, *, default: Any = dataclasses.MISSING, help: str | None = None,
                   group: str = "physics") -> Any:
    """A dataclass field for the physics option ``name`` (a setting of
    :mod:`sim.physics.settings`, or ``label_material``).

    ``default`` replaces the setting's default (e.g. fewer Monte Carlo histories for the many
    DRRs of a registration); ``help`` replaces the help text. The levels where the option
    applies are appended to the help; :mod:`sim.core.cliargs` adds the unit, the range (the
    option's ``bounds``, which it also checks) and the default.
    """
    if name in SETTINGS and SETTINGS[name].cli:
        s = SETTINGS[name]
        d = s.default if default is dataclasses.MISSING else default
        if s.kind == "filters":
            d = tuple(s.text(d))  # as typed on the command line: "Al:2.5"
        text = help or s.help
        kwargs: dict[str, Any] = dict(unit=s.unit, metavar=s.metavar)
        if s.low is not None or s.high is not None:  # shown in the help, checked by sim.core.cliargs
            kwargs["bounds"] = Range(s.low, s.high, s.low_open) if not s.high_open else None
        if s.kind == "choice":
            kwargs["choices"] = s.choices
        elif s.kind == "filters":
            kwargs["nargs"] = "+"
        elif s.kind == "bool":
            kwargs["negatable"] = True
    elif name in _EXTRA:
        d0, text, kwargs, _ = _EXTRA[name]
        d = d0 if default is dataclasses.MISSING else default
        text = help or text
    else:
        raise KeyError(f"unknown physics option {name!r}; known: {', '.join(_option_names())}")
    note = " or ".join(_levels(name))
    return field(default=d, metadata=opt(f"{text} ({note})", group=group, **kwargs))


def level_field(*, help: str, group: str = "physics", choices: tuple[str, ...] = LEVELS) -> Any:
    """The ``physics`` field (the level, default ``line``) with a command's own help text."""
    return field(default="line", metadata=opt(help, group=group, choices=choices))


def check_level_options(cmd, *, level_attr: str = "physics", extra: dict[str, tuple[str, ...]] | None = None,
                        flag_of=lambda name: "--" + name.replace("_", "-")) -> None:
    """Raise :class:`sim.physics.PhysicsError` for options given (not at their default) at a
    level where they mean nothing, instead of ignoring them silently, and for a physics option
    whose value is outside its range (``--kvp: must be a number in [20, 150] kV, got 300.0``).

    ``extra`` adds a command's own level-bound options (name -> levels).
    """

    level = getattr(cmd, level_attr)
    defaults = {f.name: f.default for f in dataclasses.fields(cmd)}
    levels = {name: _levels(name) for name in _option_names() if name in defaults}
    levels.update(extra or {})
    given = [n for n, lv in levels.items() if level not in lv and getattr(cmd, n) != defaults[n]]
    if given:
        flags = ", ".join(flag_of(n) for n in given)
        need = " or ".join(sorted({lv for n in given for lv in levels[n]}, key=LEVELS.index))
        raise PhysicsError(f"{flags}: meaningful with {flag_of(level_attr)} {need} only; this run is "
                           f"{flag_of(level_attr)} {level}")
    for s in SETTINGS.values():
        if s.cli and s.name in defaults:
            s.check(getattr(cmd, s.name), flag_of(s.name))


def physics_settings(cmd, *, level_attr: str = "physics", **overrides) -> PhysicsSettings:
    """The :class:`PhysicsSettings` of a command's physics fields (the others keep their defaults);
    a value out of range is refused naming its option (``--kvp``)."""
    kwargs: dict[str, Any] = {"level": getattr(cmd, level_attr)}
    for s in SETTINGS.values():
        if s.cli and hasattr(cmd, s.name):
            kwargs[s.name] = s.check(getattr(cmd, s.name), s.flag)
    kwargs.update(overrides)
    return PhysicsSettings(**kwargs)


def label_materials(cmd) -> dict[int, str] | None:
    """The command's ``--label-material`` items as ``{label: material}``, or None when none."""

    items = getattr(cmd, "label_material", ())
    return parse_label_materials(items) if items else None
