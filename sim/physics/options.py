"""The physics options of the command line, declared once for ``render``, ``register`` and ``evaluate``.

A command declares the options it takes as dataclass fields made by :func:`physics_option`
(help text, unit, group and default come from here, the defaults from
:class:`sim.physics.imaging.PhysicsSettings`); :func:`check_level_options` refuses an option
given at a physics level where it means nothing, and :func:`physics_settings` turns the fields
into a :class:`~sim.physics.imaging.PhysicsSettings`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Any

from sim.cliargs import opt
from sim.physics.imaging import LEVELS, PhysicsSettings

_P = PhysicsSettings()

#: option name -> (default, help, opt() keywords, physics levels where it means something,
#: PhysicsSettings attribute or None)
_SPECS: dict[str, tuple[Any, str, dict, tuple[str, ...], str | None]] = {
    "kvp": (_P.kvp, "tube voltage", dict(unit="kV"), ("poly", "full"), "kvp"),
    "filter": (tuple(f"{s}:{t:g}" for s, t in _P.filters), "added filtration as SYMBOL:MM items",
               dict(nargs="+", metavar="SYMBOL:MM"), ("poly", "full"), "filters"),
    "anode_angle": (_P.anode_angle_deg, "tungsten anode angle", dict(unit="deg"), ("poly", "full"),
                    "anode_angle_deg"),
    "bins": (_P.n_bins, "energy bins of the spectrum", dict(metavar="N"), ("poly", "full"), "n_bins"),
    "detector_mm": (_P.detector_mm, "CsI:Tl thickness", dict(unit="mm"), ("poly", "full"), "detector_mm"),
    "detector_mode": (_P.detector_mode, "energy-integrating (signal in keV) or photon-counting detector",
                      dict(choices=("integrating", "counting")), ("poly", "full"), "detector_mode"),
    "mas": (_P.mas, "exposure", dict(unit="mAs"), ("poly", "full"), "mas"),
    "noise": (_P.noise, "quantum noise, detector blur and electronic noise", dict(negatable=True),
              ("poly", "full"), "noise"),
    "blur_mm": (_P.blur_mm, "Gaussian sigma of the detector blur at the detector, applied with the noise",
                dict(unit="mm"), ("poly", "full"), "blur_mm"),
    "electronic_noise": (_P.electronic_noise, "Gaussian sigma of the electronic noise, in signal units "
                                              "(keV per pixel integrating, counts counting)",
                         dict(metavar="SIGMA"), ("poly", "full"), "electronic_noise"),
    "seed": (_P.seed, "noise and Monte Carlo seed", {}, ("poly", "full"), "seed"),
    "scatter_photons": (_P.scatter_photons, "Monte Carlo histories per image", dict(metavar="N"), ("full",),
                        "scatter_photons"),
    "scatter_voxel": (_P.scatter_voxel_mm, "voxel size of the Monte Carlo transport grid", dict(unit="mm"),
                      ("full",), "scatter_voxel_mm"),
    "grid_ratio": (_P.grid_ratio, "anti-scatter grid ratio, 0 = no grid", dict(metavar="R"), ("full",),
                   "grid_ratio"),
    "label_material": ((), "the label map overrides the HU-based material where it holds LABEL: "
                           "LABEL:MATERIAL items, e.g. 3:titanium for a segmented implant (needs --label-map)",
                       dict(nargs="+", metavar="LABEL:MATERIAL"), ("poly", "full"), None),
}


def physics_option(name: str, *, default: Any = dataclasses.MISSING, help: str | None = None,
                   group: str = "physics") -> Any:
    """A dataclass field for the physics option ``name`` (a key of the table above).

    ``default`` replaces the :class:`PhysicsSettings` default (e.g. fewer Monte Carlo histories
    for the many DRRs of a registration); ``help`` replaces the help text. The levels where the
    option applies are appended to the help.
    """
    if name not in _SPECS:
        raise KeyError(f"unknown physics option {name!r}; known: {', '.join(_SPECS)}")
    d, text, kwargs, levels, _ = _SPECS[name]
    d = d if default is dataclasses.MISSING else default
    note = " or ".join(levels)
    return field(default=d, metadata=opt(f"{help or text} ({note})", group=group, **kwargs))


def level_field(*, help: str, group: str = "physics", choices: tuple[str, ...] = LEVELS) -> Any:
    """The ``physics`` field (the level, default ``line``) with a command's own help text."""
    return field(default="line", metadata=opt(help, group=group, choices=choices))


def check_level_options(cmd, *, level_attr: str = "physics", extra: dict[str, tuple[str, ...]] | None = None,
                        flag_of=lambda name: "--" + name.replace("_", "-")) -> None:
    """Raise :class:`sim.physics.PhysicsError` for options given (not at their default) at a
    level where they mean nothing, instead of ignoring them silently.

    ``extra`` adds a command's own level-bound options (name -> levels).
    """
    from sim.physics import PhysicsError

    level = getattr(cmd, level_attr)
    defaults = {f.name: f.default for f in dataclasses.fields(cmd)}
    levels = {name: spec[3] for name, spec in _SPECS.items() if name in defaults}
    levels.update(extra or {})
    given = [n for n, lv in levels.items() if level not in lv and getattr(cmd, n) != defaults[n]]
    if given:
        flags = ", ".join(flag_of(n) for n in given)
        need = " or ".join(sorted({lv for n in given for lv in levels[n]}, key=LEVELS.index))
        raise PhysicsError(f"{flags}: meaningful with {flag_of(level_attr)} {need} only; this run is "
                           f"{flag_of(level_attr)} {level}")


def physics_settings(cmd, *, level_attr: str = "physics", **overrides) -> PhysicsSettings:
    """The :class:`PhysicsSettings` of a command's physics fields (the others keep their defaults)."""
    from sim.physics.spectrum import parse_filters

    kwargs: dict[str, Any] = {"level": getattr(cmd, level_attr)}
    for name, (_, _, _, _, attr) in _SPECS.items():
        if attr is None or not hasattr(cmd, name):
            continue
        value = getattr(cmd, name)
        kwargs[attr] = parse_filters(value) if name == "filter" else value
    kwargs.update(overrides)
    return PhysicsSettings(**kwargs)


def label_materials(cmd) -> dict[int, str] | None:
    """The command's ``--label-material`` items as ``{label: material}``, or None when none."""
    from sim.physics.materials import parse_label_materials

    items = getattr(cmd, "label_material", ())
    return parse_label_materials(items) if items else None
