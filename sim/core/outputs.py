"""Output paths checked before any work: a command refuses an ``--out`` it could not write at the end.

A command calls :func:`check_output_file` (one file, e.g. ``ctxreg render --out drr.png``) or
:func:`check_output_dir` (a folder of named files, e.g. ``ctxreg register --out out/reg``) before
it loads or computes anything, so a run that would fail only at its last step (an output name
that is an existing folder, a folder name that is an existing file, a parent that is a file or
that cannot be written) fails at once with one line naming the option and the path, and leaves
nothing behind. The checks create nothing: the writers (:mod:`sim.core.atomic`) make the folders.

Example::

    >>> from sim.core.outputs import check_output_dir
    >>> check_output_dir("out/reg", ("result.json", "overlay.png"))  # doctest: +SKIP
    PosixPath('out/reg')
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

from sim.core.errors import InputError

__all__ = ["OutputError", "Written", "check_output_file", "check_output_dir"]


class Written(list):
    """The paths a command wrote (a list), with the line it prints after them (``last_line``, e.g.
    ``register``'s verdict; None: none) and its exit status (``exit_status``, 0 by default;
    ``ctxreg register`` exits 3 on a doubtful or failed registration after writing every output)."""

    def __init__(self, paths=(), *, last_line: str | None = None, exit_status: int = 0):
        super().__init__(paths)
        self.last_line = last_line
        self.exit_status = int(exit_status)


class OutputError(InputError):
    """An output path that cannot be written; the message names the option and the path."""


def _check_parents(path: Path, flag: str, shown: str) -> None:
    """The folders above ``path`` are folders (or can be made) and the nearest existing one is writable."""
    parent = path.parent
    while True:
        if parent.exists():
            if not parent.is_dir():
                raise OutputError(f"{flag} {shown}: {parent} is an existing file, not a folder")
            if not os.access(parent, os.W_OK | os.X_OK):
                raise OutputError(f"{flag} {shown}: cannot write in {parent} (permission denied)")
            return
        if parent == parent.parent:
            return
        parent = parent.parent


def check_output_file(path: str | os.PathLike, *, flag: str = "--out", beside: Iterable[str | os.PathLike] = ()
                      ) -> Path:
    """Refuse ``path`` (and the files written ``beside`` it, e.g. a ``.json`` sidecar) when one is an
    existing folder, a folder above it is a file, or the nearest existing folder is not writable.

    An existing *file* is fine: it is replaced (atomically). Returns ``Path(path)``. Raises
    :class:`OutputError` naming ``flag`` and the path.
    """
    p = Path(path)
    for target in (p, *map(Path, beside)):
        if target.is_dir():
            what = "" if target == p else f" ({target.name} is written beside it)"
            raise OutputError(f"{flag} {path}: {target} is an existing folder; give a file name{what}")
    _check_parents(p, flag, str(path))
    return p


def check_output_dir(path: str | os.PathLike, names: Iterable[str] = (), *, flag: str = "--out") -> Path:
    """Refuse the output folder ``path`` when it is an existing file, one of the file ``names`` it
    will hold is an existing folder, a folder above it is a file, or the nearest existing folder is
    not writable.

    Existing files inside are fine: they are replaced (atomically). Returns ``Path(path)``. Raises
    :class:`OutputError` naming ``flag`` and the path.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputError(f"{flag} {path}: is an existing file; give a folder for the outputs")
    if p.is_dir():
        if not os.access(p, os.W_OK | os.X_OK):
            raise OutputError(f"{flag} {path}: cannot write in this folder (permission denied)")
        for name in names:
            if (p / name).is_dir():
                raise OutputError(f"{flag} {path}: {p / name} is an existing folder where the file {name} "
                                  f"goes; remove it or choose another {flag}")
        return p
    _check_parents(p, flag, str(path))
    return p
