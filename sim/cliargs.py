"""Command-line options declared once, as dataclass fields.

Each command has one dataclass of defaults; every field carries its help text, unit and
group in ``field(metadata=opt(...))``. :func:`add_options` turns the dataclass into grouped
argparse options whose help shows the default and the unit, and :func:`from_namespace`
turns parsed arguments back into the dataclass. Nothing about an option is written twice.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from typing import Any


def opt(help: str, *, group: str = "options", unit: str | None = None, metavar: str | None = None,
        choices: tuple[str, ...] | None = None, flag: str | None = None, positional: bool = False,
        nargs: int | str | None = None, negatable: bool = False) -> dict[str, Any]:
    """Metadata for a command-line option (see module doc)."""
    return dict(help=help, group=group, unit=unit, metavar=metavar, choices=choices, flag=flag,
                positional=positional, nargs=nargs, negatable=negatable)


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
        if default is not None and default != ():
            shown = " ".join(str(v) for v in default) if isinstance(default, tuple) else default
            help_text += f" (default: {shown})"
        tp = _base_type(hints[f.name])
        if meta["positional"]:
            group.add_argument(f.name, type=tp, help=help_text, metavar=meta["metavar"] or f.name.upper())
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
    """Build ``cls`` from parsed arguments; options left out keep the dataclass defaults."""
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in vars(ns).items() if k in names}
    return cls(**kwargs)
