"""Command-line options declared once, as dataclass fields.

Each command has one dataclass of defaults; every field carries its help text, unit and
group in ``field(metadata=opt(...))``. :func:`add_options` turns the dataclass into grouped
argparse options whose help shows the default and the unit, and :func:`from_namespace`
turns parsed arguments back into the dataclass. Nothing about an option is written twice.

Values are checked once, here, for every command (:func:`check_options`, run by
:func:`from_namespace`): a float option must be finite, and an option declared with
``bounds=Range(...)`` must lie in its range (image sizes: :data:`IMAGE_SIDE_PX`). A bad value is
an :class:`OptionError` naming the flag, printed by the CLI as one line.
:func:`refuse_unused` refuses an option that the rest of the command line makes meaningless
(e.g. ``--step-fraction`` with ``--ray-model siddon``) instead of ignoring it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import typing
from typing import Any

from sim.core.errors import InputError


class OptionError(InputError):
    """A command-line option's value is outside what it accepts; the message names the flag."""


@dataclasses.dataclass(frozen=True)
class Range:
    """The values a numeric option accepts: ``lo <= v <= hi`` (``lo < v`` when ``lo_open``); a
    ``None`` end is unbounded. ``str()`` is the range as the help and the errors show it."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False

    def __contains__(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return self.hi is None or v <= self.hi

    def __str__(self) -> str:
        if self.hi is None:
            return f"{'>' if self.lo_open else '>='} {self.lo:g}"
        if self.lo is None:
            return f"<= {self.hi:g}"
        return f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}]"


#: Pixels per side of every image size a command takes (``--size``): at least 8 (the registration's
#: coarsest level divides by 4 and keeps 2 px), at most 4096 (a full-resolution flat panel is
#: about 3000 px; 4096^2 float32 images are 64 MB each, a batch of them already needs GBs).
IMAGE_SIDE_PX = Range(8, 4096)


def opt(help: str, *, group: str = "options", unit: str | None = None, metavar: str | None = None,
        choices: tuple[str, ...] | None = None, flag: str | None = None, positional: bool = False,
        nargs: int | str | None = None, negatable: bool = False, bounds: Range | None = None) -> dict[str, Any]:
    """Metadata for a command-line option (see module doc). ``bounds``: the :class:`Range` every
    value (each item of a tuple) must lie in, checked by :func:`check_options` and shown in the help."""
    return dict(help=help, group=group, unit=unit, metavar=metavar, choices=choices, flag=flag,
                positional=positional, nargs=nargs, negatable=negatable, bounds=bounds)


def flag_of(f: dataclasses.Field) -> str:
    """The command-line flag of a dataclass field (``--step-fraction`` for ``step_fraction``)."""
    meta = f.metadata
    if meta.get("positional"):
        return f.name.upper()
    return meta.get("flag") or "--" + f.name.replace("_", "-")


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    def __init__(self, prog):
        super().__init__(prog, max_help_position=34, width=100)


def _base_type(tp):
    origin = typing.get_origin(tp)
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)) and len(args) == 1:
        return _base_type(args[0])
    if origin is tuple:
        return args[0] if args else str
    return tp


def add_options(parser: argparse.ArgumentParser, cls) -> None:
    """Add the dataclass ``cls``'s fields to ``parser`` as grouped options.

    Options the user leaves out are absent from the parsed namespace (``argparse.SUPPRESS``), so
    :func:`from_namespace` keeps the dataclass's defaults: the defaults live in one place.
    """
    hints = typing.get_type_hints(cls)
    groups: dict[str, argparse._ArgumentGroup] = {}
    for f in dataclasses.fields(cls):
        meta = f.metadata
        if "help" not in meta:
            continue
        group = groups.setdefault(meta["group"], parser.add_argument_group(meta["group"]))
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        default = None if required else (
            f.default if f.default is not dataclasses.MISSING else f.default_factory())
        help_text = meta["help"]
        if meta["unit"]:
            help_text += f" [{meta['unit']}]"
        if meta.get("bounds") is not None:
            help_text += f" {meta['bounds']}"
        if default is not None and default != ():
            shown = " ".join(str(v) for v in default) if isinstance(default, tuple) else default
            help_text += f" (default: {shown})"
        tp = _base_type(hints[f.name])
        if meta["positional"]:  # nargs="?": an optional positional, its default the dataclass's
            extra = {"nargs": meta["nargs"], "default": default} if meta["nargs"] is not None else {}
            group.add_argument(f.name, type=tp, help=help_text, metavar=meta["metavar"] or f.name.upper(), **extra)
            continue
        flag = meta["flag"] or "--" + f.name.replace("_", "-")
        if tp is bool:
            action = argparse.BooleanOptionalAction if meta["negatable"] else "store_true"
            group.add_argument(flag, dest=f.name, action=action, help=help_text,
                               default=argparse.SUPPRESS)
            continue
        kwargs: dict[str, Any] = dict(dest=f.name, type=tp, help=help_text, default=argparse.SUPPRESS)
        if required:
            kwargs["required"] = True
        for key in ("nargs", "choices", "metavar"):
            if meta[key] is not None:
                kwargs[key] = meta[key]
        group.add_argument(flag, **kwargs)


def from_namespace(cls, ns: argparse.Namespace):
    """Build ``cls`` from parsed arguments; options left out keep the dataclass defaults. The
    values are checked (:func:`check_options`)."""
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in vars(ns).items() if k in names}
    cmd = cls(**kwargs)
    check_options(cmd)
    return cmd


def check_options(cmd) -> None:
    """Raise :class:`OptionError` for the first option of ``cmd`` (a command dataclass) whose value
    is a float that is not finite, or lies outside its declared ``bounds``."""
    hints = typing.get_type_hints(type(cmd))
    for f in dataclasses.fields(cmd):
        meta = f.metadata
        if "help" not in meta:
            continue
        value = getattr(cmd, f.name)
        if value is None or isinstance(value, (str, bool)):
            continue
        items = value if isinstance(value, tuple) else (value,)
        numbers = [v for v in items if isinstance(v, (int, float)) and not isinstance(v, bool)]
        if not numbers:
            continue
        shown = " ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in items)
        unit = f" {meta['unit']}" if meta.get("unit") and " " not in meta["unit"] else ""
        if _base_type(hints[f.name]) is float and not all(math.isfinite(v) for v in numbers):
            raise OptionError(f"{flag_of(f)} {shown}: must be finite numbers (not inf or nan)"
                              if len(items) > 1 else f"{flag_of(f)} {shown}: must be a finite number (not inf or nan)")
        bounds = meta.get("bounds")
        if bounds is not None and not all(v in bounds for v in numbers):
            each = "each value " if len(items) > 1 else ""
            raise OptionError(f"{flag_of(f)} {shown}: {each}must be {bounds}{unit}")


def _default(f: dataclasses.Field):
    return f.default_factory() if f.default is dataclasses.MISSING and f.default_factory is not dataclasses.MISSING \
        else f.default


def refuse_unused_label_map(cmd) -> None:
    """``--label-map`` serves the anatomy centre (its centroid) and ``--label-material``; with
    ``--center`` given and no ``--label-material`` it would be read for nothing: refuse it."""
    materials = getattr(cmd, "label_material", ())
    refuse_unused(cmd, ("label_map",), applies=cmd.center is None or bool(materials),
                  why="its centroid would be the anatomy centre, which --center gives; it is used otherwise only "
                      "with --label-material")


def refuse_unused(cmd, names: typing.Iterable[str], *, applies: bool, why: str) -> None:
    """Raise :class:`OptionError` when ``applies`` is False and an option of ``names`` was given
    (differs from its default): the rest of the command line makes it meaningless, and a run
    that ignored it would not be what the user asked for. ``why`` says where it applies, e.g.
    ``"meaningful with --ray-model trilinear only; this run is --ray-model siddon"``."""
    if applies:
        return
    fields = {f.name: f for f in dataclasses.fields(cmd)}
    given = [fields[n] for n in names if getattr(cmd, n) != _default(fields[n])]
    if given:
        raise OptionError(f"{', '.join(flag_of(f) for f in given)}: {why}")


def available_memory_bytes() -> int | None:
    """The memory a new allocation can take now: ``MemAvailable`` of ``/proc/meminfo`` (Linux),
    else the physical memory (``os.sysconf``); None where neither is known."""
    import os

    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def check_memory(nbytes: float, option: str, what: str, *, advice: str = "", available: int | None = None) -> None:
    """Refuse, in one :class:`OptionError` line naming ``option``, work whose largest allocation
    (``nbytes``, ``what`` it is) exceeds the memory available now (:func:`available_memory_bytes`;
    ``available`` overrides it). Nothing is refused where the available memory is unknown."""
    free = available_memory_bytes() if available is None else available
    if free is None or nbytes <= free:
        return
    gib = 1024 ** 3
    raise OptionError(f"{option}: {what} would need about {nbytes / gib:.1f} GiB, more than the "
                      f"{free / gib:.1f} GiB of memory available{'; ' + advice if advice else ''}")
