"""A cache of what is built from settings and code alone: built once per machine, then read.

Every training or adaptation run with batched pairs needs a spectral table (spekpy and xraylib for
each tube setting the randomization can draw) and a tool bank (metal tools traced by Mitsuba): on
a 2-core CPU about 18 s and 13 s for the default randomization, 5 % of a ten-minute ``ctxreg
adapt``, paid again by every run whose output folder is new. Neither depends on the CT. The run
keeps its own copy (``<out>/tables``, what it trained with); this cache lets the next run skip the
build:

* **Key**: BLAKE2b-160 over the kind, its settings (JSON, sorted keys), :data:`CACHE_FORMAT`, the
  versions of the libraries that compute it (:data:`LIBRARIES`) and the source code that builds
  it (every ``.py`` file under the folders the caller names, :func:`code_fingerprint`). A change
  of a setting, a library or a line of that code is another key: the cache never serves what
  older code built.
* **Entry**: ``<kind>-<key>.npz``, written by the caller's ``save`` (atomically,
  :func:`sim.core.atomic.atomic_path`); an entry its ``load`` refuses is removed and built again,
  with a line to ``log``. A folder that cannot be written costs the cache, not the run: a line to
  ``log``, and the built value.
* **Folder**: ``$CTXREG_BUILD_CACHE`` if set (``off``: no cache), else
  ``$XDG_CACHE_HOME/ctxreg/built`` (default ``~/.cache/ctxreg/built``). At most
  :data:`MAX_ENTRIES` entries of a kind: the least recently used (by modification time, touched
  on every hit) go. The folder may be deleted at any time.

Example::

    >>> import numpy as np, tempfile
    >>> def save(a, path):
    ...     with open(path, "wb") as f:
    ...         np.savez(f, a=a)
    >>> load = lambda path: np.load(path)["a"]
    >>> kw = dict(save=save, load=load, errors=(OSError,), folder=tempfile.mkdtemp())
    >>> cached("squares", {"n": 3}, build=lambda: np.arange(3) ** 2, **kw).tolist()  # built, then stored
    [0, 1, 4]
    >>> cached("squares", {"n": 3}, build=None, **kw).tolist()  # read: not built again
    [0, 1, 4]
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import os
import re
from pathlib import Path
from typing import Callable, Iterable

#: Bump when the meaning of an entry changes in a way its code and settings do not show.
CACHE_FORMAT = 1

#: The libraries whose versions are part of the key (a missing one counts as "none").
LIBRARIES = ("numpy", "spekpy", "xraylib", "mitsuba", "drjit", "torch")

#: Entries of one kind the folder keeps (least recently used removed first).
MAX_ENTRIES = 32

_KIND = re.compile(r"[a-z][a-z0-9_]*")


def cache_dir() -> Path | None:
    """The cache folder (module doc), or None where ``$CTXREG_BUILD_CACHE`` is ``off``."""
    given = os.environ.get("CTXREG_BUILD_CACHE")
    if given == "off":
        return None
    if given:
        return Path(given).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ctxreg" / "built"


@functools.lru_cache(maxsize=None)
def code_fingerprint(folders: tuple[str, ...]) -> str:
    """Hex BLAKE2b-160 of every ``.py`` file under ``folders`` (relative name and bytes, sorted):
    the code a cached value was built by. About 10 ms for the project's packages."""
    h = hashlib.blake2b(digest_size=20)
    for folder in folders:
        root = Path(folder)
        for f in sorted(root.rglob("*.py")):
            h.update(f"{f.relative_to(root.parent).as_posix()}\0".encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def _versions() -> dict[str, str]:
    out = {}
    for name in LIBRARIES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "none"
    return out


def entry_key(kind: str, settings: dict, code: Iterable[str | os.PathLike] = ()) -> str:
    """The key (40 hex digits) of ``kind`` built with ``settings`` by the code under ``code``."""
    if not isinstance(kind, str) or not _KIND.fullmatch(kind):
        raise ValueError(f"build cache: kind must be lowercase letters, digits and _, got {kind!r}")
    h = hashlib.blake2b(digest_size=20)
    text = json.dumps({"kind": kind, "format": CACHE_FORMAT, "settings": settings, "libraries": _versions(),
                       "code": code_fingerprint(tuple(str(Path(c).resolve()) for c in code))}, sort_keys=True)
    h.update(text.encode())
    return h.hexdigest()


def cached(kind: str, settings: dict, *, build: Callable[[], object], save: Callable[[object, Path], object],
           load: Callable[[Path], object], errors: tuple[type[BaseException], ...],
           code: Iterable[str | os.PathLike] = (), log: Callable[[str], None] | None = None,
           folder: str | os.PathLike | None = None):
    """``kind`` built with ``settings`` (JSON values), read from the cache where it was built before.

    Args:
        kind: the kind of value (lowercase letters, digits, ``_``): part of the entry's name.
        settings: everything the value depends on besides the code and :data:`LIBRARIES`.
        build: makes the value (called only on a miss).
        save: ``save(value, path)`` writes it to ``path`` (atomically); load: ``load(path)`` reads it,
            raising one of ``errors`` on a damaged or foreign file (the entry is then built again).
        code: the folders whose ``.py`` files build the value (:func:`code_fingerprint`).
        log: called with a line where an entry is refused or cannot be written (default: silence).
        folder: the cache folder (default :func:`cache_dir`).
    """
    log = log or (lambda line: None)
    folder = cache_dir() if folder is None else Path(folder).expanduser()
    if folder is None:
        return build()
    entry = folder / f"{kind}-{entry_key(kind, settings, code)}.npz"
    if entry.is_file():
        try:
            value = load(entry)
        except errors as e:
            log(f"build cache: {entry} cannot be used ({e}); building it again")
            entry.unlink(missing_ok=True)
        else:
            try:
                os.utime(entry)  # most recently used
            except OSError:
                pass  # another process removed it: the value read stands
            return value
    value = build()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        save(value, entry)
    except OSError as e:  # a full disk or a read-only home must not stop the run the value is for
        log(f"build cache: cannot write {entry} ({e.strerror or e}); built, not cached "
            f"(set CTXREG_BUILD_CACHE to a writable folder, or to off)")
        return value
    _evict(folder, kind)
    return value


def _evict(folder: Path, kind: str) -> None:
    """Keep the :data:`MAX_ENTRIES` most recently used entries of ``kind`` in ``folder``."""
    name = re.compile(rf"{re.escape(kind)}-[0-9a-f]{{40}}\.npz")
    entries = []
    for f in folder.glob(f"{kind}-*.npz"):
        if not name.fullmatch(f.name):
            continue  # not an entry of this kind: never removed
        try:
            entries.append((f.stat().st_mtime, f))
        except FileNotFoundError:  # another process removed it
            continue
    for _, f in sorted(entries, key=lambda e: e[0], reverse=True)[MAX_ENTRIES:]:
        f.unlink(missing_ok=True)
