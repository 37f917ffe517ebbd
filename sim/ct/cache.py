"""A cache of loaded CTs: a CT file or DICOM series read once, then from one uncompressed file.

Reading a clinical CT is slow where its use is not: a 512 x 512 x 133 ``.nii.gz`` takes about 2.8 s
to decompress and check and 1.2 s more for its anatomy centre (the bone's largest component) on
a 2-core CPU, while a registration needs well under that once the CT is in memory. The cache keeps
what :func:`sim.ct.io.load_ct` returns, with the anatomy centre, in one ``.npz`` file per CT:

* **Key**: the CT's content hash (BLAKE2b, 160 bits) over the file's bytes, or over every file
  of a DICOM folder (relative name, size and bytes, in sorted order), plus the cache format. A
  CT whose bytes changed has another key: the cache never serves an old CT for a changed one,
  whatever the file's name, size or modification time (hashing costs about 0.1 s per 70 MB).
* **Entry**: ``<key>.npz`` (uncompressed; no pickled objects): ``hu`` (int16 where every value
  is a whole number in int16's range, else float32), ``affine`` ``(4, 4)`` LPS mm, ``center``
  ``(3,)`` LPS mm (NaN where the CT has no bone to centre on) and ``meta`` (JSON text: format,
  key, source path, shape, how the centre was found). Written atomically (:func:`sim.core.atomic.atomic_path`); an entry that
  cannot be read or does not match its key is removed and rebuilt, with a line to ``log``. A
  folder that cannot be written (a full disk, a read-only home) costs the cache, not the CT: a
  line to ``log``, and the CT as read from its file.
* **Folder**: ``$CTXREG_CT_CACHE`` if set, else ``$XDG_CACHE_HOME/ctxreg/ct`` (default
  ``~/.cache/ctxreg/ct``). It holds at most :data:`MAX_CACHE_MB` MB (``$CTXREG_CT_CACHE_MB``):
  after a write, the least recently used entries (by modification time, touched on every hit)
  are removed until the rest fit. The cache owns only what it wrote: a file counts as an entry
  only when its name is ``<40 hex digits>.npz`` *and* its ``meta`` records that very key
  (:func:`is_entry`); any other file in the folder (a user's own ``.npz`` files, when a data
  folder is given as the cache) is neither counted nor ever removed. The folder may be deleted
  at any time.

Label maps, resampling and a chosen DICOM series bypass the cache (:func:`load_ct` then reads the
files as always). Example::

    >>> ct = load_ct_cached("pelvis.nii.gz")           # doctest: +SKIP
    >>> ct = load_ct_cached("pelvis.nii.gz")           # the second time: from the cache
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np

from sim.ct.anatomy import AnatomyError, find_center, remember_center
from sim.core.atomic import atomic_path
from sim.ct.io import load_ct
from sim.core.errors import InputError
from sim.ct.volume import CTVolume

#: Bump when an entry's contents or meaning change: old entries then miss.
CACHE_FORMAT = 2  # 2: the centre of the pelvis's bone pieces and how it was found (meta 'center_how')
#: Default size limit of the cache folder, in MB (``$CTXREG_CT_CACHE_MB`` overrides it).
MAX_CACHE_MB = 4096
#: Bytes read at a time while hashing.
_CHUNK = 1 << 22


class CTCacheError(InputError):
    """The cache folder cannot be used (not a folder, not writable, a bad size limit)."""


def default_cache_dir() -> Path:
    """The cache folder: ``$CTXREG_CT_CACHE``, else ``$XDG_CACHE_HOME/ctxreg/ct``, else ``~/.cache/ctxreg/ct``."""
    if os.environ.get("CTXREG_CT_CACHE"):
        return Path(os.environ["CTXREG_CT_CACHE"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ctxreg" / "ct"


def cache_limit_bytes() -> int:
    """The folder's size limit in bytes (:data:`MAX_CACHE_MB` or ``$CTXREG_CT_CACHE_MB``)."""
    text = os.environ.get("CTXREG_CT_CACHE_MB")
    if not text:
        return MAX_CACHE_MB << 20
    try:
        mb = float(text)
    except ValueError:
        raise CTCacheError(f"CTXREG_CT_CACHE_MB={text!r}: expected a size in MB") from None
    if not (np.isfinite(mb) and mb >= 0):
        raise CTCacheError(f"CTXREG_CT_CACHE_MB={text!r}: expected a size in MB >= 0")
    return int(mb * (1 << 20))


def ct_hash(path: str | os.PathLike) -> str:
    """Hex BLAKE2b-160 of a CT's bytes: a file's, or a folder's files (relative name, size, bytes;
    sorted; hidden files left out), with :data:`CACHE_FORMAT`."""
    path = Path(path)
    h = hashlib.blake2b(digest_size=20)
    h.update(f"ctxreg-ct-cache-{CACHE_FORMAT}\0".encode())
    files = ([path] if path.is_file() else
             sorted(p for p in path.rglob("*") if p.is_file() and not any(part.startswith(".") for part in
                                                                              p.relative_to(path).parts)))
    for f in files:
        name = f.name if f == path else f.relative_to(path).as_posix()
        h.update(f"{name}\0{f.stat().st_size}\0".encode())
        with open(f, "rb") as fh:
            while chunk := fh.read(_CHUNK):
                h.update(chunk)
    return h.hexdigest()


def load_ct_cached(path: str | os.PathLike, *, cache_dir: str | os.PathLike | None = None,
                   log: Callable[[str], None] | None = None) -> CTVolume:
    """:func:`sim.ct.io.load_ct` of ``path`` through the cache (module doc); the anatomy centre
    comes with it (:func:`sim.ct.anatomy.anatomy_center` then answers without computing).

    Args:
        path: a NIfTI file or a DICOM series folder.
        cache_dir: the cache folder (default :func:`default_cache_dir`).
        log: called with a line where an entry is written or rebuilt (default: silence).

    Raises :class:`sim.ct.volume.CTInputError` as :func:`load_ct` does (a missing or bad CT), and
    :class:`CTCacheError` when ``cache_dir`` is a file or the size limit is not a number; a folder
    that cannot be written only loses the cache (a line to ``log``).
    """
    log = log or (lambda line: None)
    path = Path(path)
    if not path.exists():
        return load_ct(path)  # its own message names the missing file
    folder = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    if folder.exists() and not folder.is_dir():
        raise CTCacheError(f"CT cache {folder}: not a folder")
    limit = cache_limit_bytes()  # a bad limit is refused before any work
    key = ct_hash(path)
    entry = folder / f"{key}.npz"
    if entry.is_file():
        volume = _read_entry(entry, key, path, log)
        if volume is not None:
            os.utime(entry)  # most recently used
            return volume
    volume = load_ct(path)
    try:
        found = find_center(volume)
        center, how = found.lps_mm, found.to_dict()["anatomy_center_how"]
    except AnatomyError:
        center, how = np.full(3, np.nan), ""
    try:
        _write_entry(entry, key, path, volume, center, how)
    except OSError as e:  # a full disk or a read-only home must not stop the work the CT is for
        log(f"CT cache: cannot write {entry} ({e.strerror or e}); the CT was read from {path} and is not cached "
            f"(set CTXREG_CT_CACHE to a writable folder, or turn the cache off)")
        return volume
    log(f"CT cache: {path} stored as {entry} ({entry.stat().st_size / 1e6:.0f} MB)")
    removed = evict(folder, keep=entry, limit_bytes=limit)
    if removed:
        log(f"CT cache: removed {len(removed)} least recently used entr{'y' if len(removed) == 1 else 'ies'} of "
            f"{folder} to stay within {limit / (1 << 20):g} MB")
    return volume


_ENTRY_NAME = re.compile(r"[0-9a-f]{40}\.npz")


def is_entry(path: str | os.PathLike) -> bool:
    """True when ``path`` is an entry this cache wrote: named ``<key>.npz`` (``key`` 40 hex
    digits) with a ``meta`` member whose ``key`` is that key. Anything else (another program's
    or the user's file, whatever its name) is not the cache's to count or remove."""
    path = Path(path)
    if not _ENTRY_NAME.fullmatch(path.name) or not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError, EOFError):
        return False
    return isinstance(meta, dict) and meta.get("key") == path.name[:-4]


def evict(folder: str | os.PathLike, *, keep: Path | None = None, limit_bytes: int | None = None) -> list[Path]:
    """Remove the least recently used entries of ``folder`` until its entries take at most
    ``limit_bytes`` (default :func:`cache_limit_bytes`); ``keep`` is never removed, nor any file
    that is not an entry (:func:`is_entry`). Returns the removed files."""
    limit = cache_limit_bytes() if limit_bytes is None else int(limit_bytes)
    entries = []
    for f in Path(folder).glob("*.npz"):
        if not is_entry(f):
            continue  # not the cache's: never counted, never removed
        try:
            st = f.stat()
        except FileNotFoundError:  # another process removed it
            continue
        entries.append((st.st_mtime, st.st_size, f))
    total = sum(size for _, size, _ in entries)
    removed = []
    for _, size, f in sorted(entries, key=lambda e: e[0]):
        if total <= limit:
            break
        if keep is not None and f == keep:
            continue
        f.unlink(missing_ok=True)
        total -= size
        removed.append(f)
    return removed


def _write_entry(entry: Path, key: str, path: Path, volume: CTVolume, center: np.ndarray, how: str = "") -> None:
    hu = volume.hu
    as_int = np.rint(hu)
    if np.array_equal(as_int, hu) and as_int.min() >= np.iinfo(np.int16).min and as_int.max() <= np.iinfo(np.int16).max:
        hu = as_int.astype(np.int16)
    meta = {"format": CACHE_FORMAT, "key": key, "source": str(path), "shape": list(volume.shape), "center_how": how}
    entry.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(entry) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, hu=hu, affine=volume.affine, center=np.asarray(center, np.float64),
                     meta=np.array(json.dumps(meta)))


def _read_entry(entry: Path, key: str, path: Path, log) -> CTVolume | None:
    """The entry's CT, or None (the entry removed, with a line to ``log``) where it is unreadable
    or not the entry of ``key``."""
    try:
        with np.load(entry, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            hu, affine, center = z["hu"], z["affine"], z["center"]
        problem = None
        if meta.get("format") != CACHE_FORMAT or meta.get("key") != key:
            problem = "written for another CT or cache format"
        elif list(hu.shape) != meta.get("shape") or affine.shape != (4, 4) or center.shape != (3,):
            problem = "its arrays do not match their description"
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError, EOFError) as e:
        problem = f"unreadable ({type(e).__name__}: {e})"
    if problem is not None:
        log(f"CT cache: {entry} {problem}; rebuilt from {path}")
        entry.unlink(missing_ok=True)
        return None
    volume = CTVolume(hu=hu.astype(np.float32, copy=False), affine=affine, source=str(path))
    if np.all(np.isfinite(center)):
        remember_center(volume, center, str(meta.get("center_how") or "bone: stored with the CT"))
    return volume
