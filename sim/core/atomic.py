"""Atomic file output: write to a temporary file beside the target, then rename over it.

A reader (or a restarted run) never sees a half-written file: either the old one or the new.

Temporary files are named ``.NAME.PID@HOST-XXXXXXXX.tmp.SFX`` (:func:`temp_owner` reads the
name back): the target's name, the writing process and its host, random characters and the
target's suffixes. A process killed during a write (``kill -9``, out of memory) cannot remove
its temporary file; :func:`remove_stale_temps` removes the temporary files whose process is
gone (same host, PID no longer running), and :func:`atomic_path` does so for its own target
before every write.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path
from typing import Iterator

from sim.core.errors import InputError

#: ``.NAME.PID@HOST-RANDOM.tmp...``: the target's name, the writer's PID and host.
_TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)@(?P<host>[A-Za-z0-9_-]*)-[a-z0-9_]+\.tmp")


def _host() -> str:
    """This machine's name as it appears in temporary file names (letters, digits, ``_``, ``-``)."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname().split(".")[0])[:64]


def temp_owner(name: str) -> tuple[str, int, str] | None:
    """``(target name, PID, host)`` of a temporary file name made by :func:`atomic_path`, else None."""
    m = _TEMP_NAME.match(name)
    return (m["name"], int(m["pid"]), m["host"]) if m else None


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def remove_stale_temps(folder: str | os.PathLike, name: str | None = None) -> list[Path]:
    """Delete the temporary files of :func:`atomic_path` in ``folder`` whose writer is gone.

    A temporary file is stale when it was made on this host by a process that no longer runs.
    Files of live processes, of other hosts (a folder shared between machines) and files not
    named by :func:`atomic_path` are kept. ``name``: only the temporary files of this target
    file name. Returns the files removed; a missing folder removes nothing.
    """
    folder = Path(folder)
    host = _host()
    removed = []
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return removed
    for entry in entries:
        owner = temp_owner(entry.name)
        if owner is None or (name is not None and owner[0] != name):
            continue
        if owner[2] != host or _pid_alive(owner[1]):
            continue
        with contextlib.suppress(FileNotFoundError):
            if entry.is_dir(follow_symlinks=False):  # a folder of atomic_folder
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; on success rename it to ``path``.

    ``suffix`` (default: the target's own, e.g. ``.png``) lets writers that pick a format by
    extension work on the temporary file. On an exception the temporary file is removed; the
    stale temporary files of earlier, killed writers of the same target are removed first
    (:func:`remove_stale_temps`).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path.parent, path.name)
    sfx = "".join(path.suffixes) if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}@{_host()}-", suffix=f".tmp{sfx}",
                               dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the permissions open() would
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside ``path`` (named as :func:`atomic_path`'s files, so that
    :func:`remove_stale_temps` removes it after a killed writer); on success rename it to
    ``path``, which must not exist then (or be an empty folder): a reader sees the folder whole
    or not at all. On an exception the temporary folder and its contents are removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path.parent, path.name)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.{os.getpid()}@{_host()}-", suffix=".tmp", dir=path.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; give the folder the permissions mkdir would
    try:
        yield tmp
        os.rename(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


class FolderBusyError(InputError):
    """Another live process works in the folder (:func:`folder_lock`); the message names it."""


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, what: str) -> Iterator[Path]:
    """Hold ``folder/.ctxreg.lock`` (an exclusive ``flock``, created if needed) for the ``with``
    block, so that two runs (``what``: e.g. ``"ctxreg train"``) never write into one folder at
    once: a second is refused at once with :class:`FolderBusyError` naming the folder and the
    holder's PID. The lock dies with its process (``kill -9`` included): nothing stale is left
    to remove by hand."""
    import fcntl

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / ".ctxreg.lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
            raise FolderBusyError(f"{folder}: {holder} is working in this folder; wait for it to end, or give "
                                  "another folder") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{what} (PID {os.getpid()} on {_host()})".encode(), 0)
        yield path
    finally:
        os.close(fd)  # closing releases the lock


def jsonable(obj):
    """``obj`` as plain JSON data: dicts (keys as str), lists / tuples -> lists, NumPy arrays ->
    nested lists, NumPy scalars -> bool / int / float; None, str, bool, int, float unchanged.
    Anything else raises ``TypeError`` naming its type."""
    import numpy as np

    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj)
    if obj is None or isinstance(obj, str):
        return obj
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def write_json(path: str | os.PathLike, obj) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2) + "\n")


def read_toml(path: str | os.PathLike, error: type[Exception], what: str) -> dict:
    """The data of the TOML file ``path``; a missing file, undecodable text or bad TOML raises
    ``error`` in one line: ``"<what> <path> not found"`` / ``"<path>: not valid TOML (...)"``."""
    import tomllib

    path = Path(path)
    if not path.is_file():
        raise error(f"{what} {path} not found")
    try:
        return tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise error(f"{path}: not valid TOML ({e})") from None


def write_csv(path: str | os.PathLike, rows: list[dict]) -> None:
    """``rows`` as CSV (the first row's keys are the columns), atomically."""
    import csv

    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


def toml_value(v) -> str:
    """A TOML value for plain data (bool, int, finite float, str, list, dict as an inline table)."""
    import math

    v = jsonable(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"TOML has no value for {v!r}")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a TOML basic string
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def _toml_key(k) -> str:
    k = str(k)
    return k if k and all(c.isalnum() or c in "-_" for c in k) else json.dumps(k)


def toml_text(tables: dict) -> str:
    """TOML text of ``{table name: {key: value}}`` (one level of ``[table]`` headers; values by
    :func:`toml_value`). ``tomllib.loads`` of the text gives the data back."""
    parts = []
    for name, table in tables.items():
        if not isinstance(table, dict):
            raise TypeError(f"TOML table {name!r} must be a dict, got {type(table).__name__}")
        parts.append(f"[{_toml_key(name)}]\n" + "".join(f"{_toml_key(k)} = {toml_value(v)}\n"
                                                          for k, v in table.items() if v is not None))
    return "\n".join(parts)


def write_toml(path: str | os.PathLike, tables: dict) -> None:
    """Write :func:`toml_text` of ``tables`` atomically (``None`` values are left out)."""
    text = toml_text(tables)
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def save_figure(fig, path: str | os.PathLike, *, dpi: int = 110, rect=None) -> None:
    """Lay out a matplotlib figure (``rect``: the part of the figure, ``(left, bottom, right,
    top)`` in figure fractions, the panels fill; default all of it), write it as PNG atomically,
    and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout(rect=rect)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """The SHA-256 hex digest of a file's bytes, read in ``chunk``-byte blocks."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()
