"""``ctxreg serve``: a case's frames registered in one process, as a service.

The CT, its anatomy centre and the network are loaded once and Dr.Jit's kernels compiled once;
then each frame is registered as it arrives, from paths on stdin or from a watched folder, with
one JSON line per frame on stdout. What a service needs:

* **A frame is taken whole.** A watched file is taken once its size and modification time held
  for one look (:data:`SERVE_POLL_S`); a frame refused because it could not be read (a file still
  being copied) is taken again when it changes.
* **Outputs appear whole or not at all.** A frame's outputs are written into a temporary folder
  beside their place and renamed into it (:func:`sim.core.atomic.atomic_folder`); a killed process
  leaves only a hidden temporary folder, which the next start removes. Each frame folder holds
  ``frame.json``: the X-ray's path and SHA-256.
* **A restart continues.** Watching a folder, a frame whose file (path and content) already has
  a frame folder in ``--out`` is not registered again (a line to stderr): a restart after a crash
  registers only the frames that were not done. Paths on stdin are registered as asked, each time.
* **Signals.** The first SIGTERM or Ctrl-C finishes the frame being registered, writes it, and
  stops ("finished <frame>, stopping"); a second abandons it at once (its outputs not written:
  "abandoned <frame>").
* **Huge frames** are binned on reading (:data:`register.api.MAX_XRAY_SIDE_PX`).
* **Exit status**: 0 when at least one frame was registered (or was already done); otherwise
  the run ends with :class:`ServeError` (exit 2), saying how many frames were refused.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from register.engines.result import RegistrationError
from sim.core.atomic import atomic_folder, folder_lock, remove_stale_temps, sha256_file, write_json

__all__ = ["SERVE_SUFFIXES", "SERVE_POLL_S", "FRAME_RECORD", "ServeError", "FolderWatch", "stdin_frames",
           "done_frames", "serve_frames", "ServeSummary"]

#: File names ``ctxreg serve`` takes from a watched folder as X-rays (DICOM files often have no suffix).
SERVE_SUFFIXES = ("", ".dcm", ".dicom", ".ima", ".png", ".tif", ".tiff", ".jpg", ".jpeg", ".npy")
#: Seconds between two looks at a watched folder; a file is taken once its size and time held for one look.
SERVE_POLL_S = 0.5
#: The record in each frame folder: the X-ray's path and SHA-256.
FRAME_RECORD = "frame.json"


class ServeError(RegistrationError):
    """A ``ctxreg serve`` option that cannot work, or a run that registered no frame (the message says)."""


def stdin_frames() -> Iterator[Path]:
    """X-ray paths from stdin, one per line (blank lines skipped), until its end."""
    for line in sys.stdin:
        if line.strip():
            yield Path(line.strip())


class FolderWatch:
    """New X-ray files of ``folder`` as they arrive, in name order, each once its size and
    modification time held for one look (``poll_s`` apart). :meth:`refused` marks a taken file
    whose content was refused: it is taken again if it changes (a copy that was not finished)."""

    def __init__(self, folder: Path, poll_s: float = SERVE_POLL_S):
        self.folder = Path(folder)
        self.poll_s = poll_s
        self._taken: dict[str, tuple[int, int]] = {}  # name -> the (size, mtime ns) it was taken at
        self._looked: dict[str, tuple[int, int]] = {}  # name -> (size, mtime ns) at the last look
        self._retry: set[str] = set()

    def refused(self, path: Path) -> None:
        self._retry.add(path.name)

    def __iter__(self) -> Iterator[Path]:
        while True:
            for path in sorted(self.folder.iterdir()):
                name = path.name
                if name.startswith(".") or path.suffix.lower() not in SERVE_SUFFIXES or not path.is_file():
                    continue
                try:
                    st = path.stat()
                except FileNotFoundError:
                    continue
                sig = (st.st_size, st.st_mtime_ns)
                if name in self._taken and not (name in self._retry and self._taken[name] != sig):
                    continue
                if self._looked.get(name) == sig and st.st_size > 0:
                    self._taken[name] = sig
                    self._retry.discard(name)
                    yield path
                else:
                    self._looked[name] = sig
            time.sleep(self.poll_s)


def done_frames(root: Path) -> dict[tuple[str, str], Path]:
    """``{(X-ray path, SHA-256): frame folder}`` of the whole frame folders in ``root``."""
    done = {}
    for record in root.glob(f"*/{FRAME_RECORD}"):
        try:
            info = json.loads(record.read_text())
            done[(str(info["xray"]), str(info["sha256"]))] = record.parent
        except (OSError, ValueError, KeyError, TypeError):
            continue  # not a frame folder of serve's
    return done


def _frame_out(root: Path, stem: str) -> Path:
    """``root/stem``, or ``root/stem_2``, ``_3``, ... where that is taken."""
    out, k = root / stem, 1
    while out.exists():
        k += 1
        out = root / f"{stem}_{k}"
    return out


class _Signals:
    """SIGTERM and SIGINT while serving: during a frame the first asks to stop after it, a
    second raises :class:`KeyboardInterrupt` (the frame abandoned); between frames (waiting for
    the next) the first raises it at once."""

    def __init__(self):
        self.stop = None  # the signal's name once one came
        self.busy = False  # a frame is being registered or written

    def _handle(self, signum, _frame):
        first = self.stop is None
        self.stop = self.stop or signal.Signals(signum).name
        if not (first and self.busy):
            raise KeyboardInterrupt

    def __enter__(self):
        self._old = {s: signal.signal(s, self._handle) for s in (signal.SIGTERM, signal.SIGINT)}
        return self

    def __exit__(self, *exc):
        for s, handler in self._old.items():
            signal.signal(s, handler)
        return False


@dataclass
class ServeSummary:
    """What a serve run did: frames registered, refused, and skipped as already done."""

    registered: int = 0
    refused: int = 0
    skipped: int = 0
    stopped_by: str | None = None


def serve_frames(register: Callable[[Path], object], frames, root: Path, *, watch: FolderWatch | None = None,
                 limit: int = 0, errors: tuple[type[BaseException], ...] = (), verbose: bool = False,
                 emit: Callable[[dict], None] | None = None, note: Callable[[str], None] | None = None) -> ServeSummary:
    """Register each path of ``frames`` with ``register(path)`` (it returns an outcome with
    ``write(folder)``, ``params``, ``similarity``, ``search_status``, ``timings``) and write its
    outputs whole into ``root`` (module doc). ``watch``: the :class:`FolderWatch` the frames come
    from (done frames are skipped, refused ones retried when they change). ``limit``: stop after
    this many frames (0: none). ``errors``: the exceptions that refuse one frame (its JSON line
    holds ``error``; the next goes on). ``emit``: the JSON line of a frame (default: stdout);
    ``note``: a line to stderr."""
    emit = emit or (lambda line: print(json.dumps(line), flush=True))
    note = note or (lambda text: print(f"ctxreg serve: {text}", file=sys.stderr, flush=True))
    with folder_lock(root, "ctxreg serve"):  # one server per --out: a second is refused at once
        return _serve(register, frames, root, watch, limit, errors, verbose, emit, note)


def _serve(register, frames, root: Path, watch, limit: int, errors, verbose: bool, emit, note) -> ServeSummary:
    for stale in remove_stale_temps(root):
        note(f"removed {stale.name}: the partial outputs of a frame whose process was killed")
    done = done_frames(root) if watch is not None else {}
    summary = ServeSummary()
    current = None
    with _Signals() as signals:
        try:
            for path in frames:
                current, signals.busy = path.name, True
                digest = sha256_file(path) if path.is_file() else None
                key = (str(path.resolve()), digest)
                if watch is not None and digest is not None and key in done:
                    note(f"{path.name}: already registered in {done[key]}; not again")
                    summary.skipped += 1
                else:
                    line = _one_frame(register, path, digest, root, errors, verbose, note)
                    if "error" in line:
                        summary.refused += 1
                        if watch is not None:
                            watch.refused(path)
                    else:
                        summary.registered += 1
                        done[key] = Path(line["out"])
                    emit(line)
                finished, current, signals.busy = current, None, False
                if signals.stop is not None:
                    note(f"{signals.stop}: finished {finished}, stopping")
                    summary.stopped_by = signals.stop
                    break
                if limit and summary.registered + summary.refused + summary.skipped >= limit:
                    break
        except KeyboardInterrupt:
            summary.stopped_by = signals.stop or "SIGINT"
            note(f"{summary.stopped_by}: abandoned {current} (its outputs are not written), stopping" if current
                 else f"{summary.stopped_by}: stopping (no frame in progress)")
    return summary


def _one_frame(register, path: Path, digest: str | None, root: Path, errors, verbose: bool, note) -> dict:
    """Register and write one frame; its JSON line."""
    t0 = time.perf_counter()
    try:
        outcome = register(path)
        out = _frame_out(root, path.stem if path.suffix else path.name)
        with atomic_folder(out) as tmp:
            outcome.write(tmp)
            write_json(tmp / FRAME_RECORD, {"xray": str(path.resolve()), "sha256": digest})
    except errors as e:
        return {"xray": str(path), "error": str(e)}
    if verbose:
        note(f"{path.name}: " + ", ".join(f"{k} {v:.2f} s" for k, v in outcome.timings.items()))
    return {"xray": str(path), "out": str(out), "params": outcome.params, "similarity": outcome.similarity,
            "seconds": round(time.perf_counter() - t0, 3), "search_status": outcome.search_status,
            "verdict": outcome.verdict.label, "verdict_reasons": list(outcome.verdict.reasons)}
