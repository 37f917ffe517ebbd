"""``ctxreg serve`` as a service (register/serve.py): files taken whole, outputs whole or absent,
restarts that continue, signals that finish or abandon a frame, an exit status that says whether
any frame was registered.

The registration is a stand-in here (a few files written with pauses, so that a kill lands in the
middle of a frame's outputs): what is tested is serve's own machinery; the real registration through
``ctxreg serve`` is tested in test_register_cli.py.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from register.verdict import Verdict

from register.serve import FRAME_RECORD, FolderWatch, done_frames, serve_frames
from tests.conftest import REPO

#: The files of a stand-in frame's outputs.
FILES = ("a.txt", "b.txt", "result.json")


class _Outcome:
    params = {"phi": 0.0}
    similarity = 0.5
    search_status = "none"
    timings = {"register": 0.0}
    verdict = Verdict("doubtful", ("similarity 0.50 < 0.60",))

    def __init__(self, pause_s: float = 0.0):
        self.pause_s = pause_s

    def write(self, folder):
        for name in FILES:
            (Path(folder) / name).write_text(name)
            time.sleep(self.pause_s)


class _Refused(Exception):
    pass


def _register(pause_s=0.0):
    def register(path):
        if Path(path).read_text().startswith("bad"):
            raise _Refused(f"{path}: damaged")
        time.sleep(pause_s)
        return _Outcome(pause_s)
    return register


def _whole_or_absent(root: Path) -> list[Path]:
    """The frame folders of ``root``, each checked whole; no partial folder visible."""
    folders = [p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")]
    for f in folders:
        assert sorted(x.name for x in f.iterdir()) == sorted((*FILES, FRAME_RECORD)), f
    return folders


def test_a_watched_file_is_taken_once_it_holds_and_again_when_a_refused_one_changes(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    watch = FolderWatch(folder, poll_s=0.05)
    frames = iter(watch)
    (folder / "f1.dcm").write_text("bad, half copied")
    (folder / ".hidden.dcm").write_text("x")
    (folder / "notes.txt").write_text("x")
    got = next(frames)
    assert got.name == "f1.dcm"
    watch.refused(got)
    writer = threading.Timer(0.3, lambda: (folder / "f1.dcm").write_text("good now, the copy finished"))
    writer.start()
    t0 = time.perf_counter()
    again = next(frames)  # the same file, taken again once it changed and held
    assert again.name == "f1.dcm" and again.read_text().startswith("good") and time.perf_counter() - t0 >= 0.3
    (folder / "f2.dcm").write_text("good")
    assert next(frames).name == "f2.dcm"  # f1 is not taken a third time: it was not refused again


def test_outputs_are_whole_a_restart_skips_done_frames_and_none_registered_is_said(tmp_path):
    folder, root = tmp_path / "in", tmp_path / "out"
    folder.mkdir()
    for name, text in (("a.dcm", "good a"), ("b.dcm", "bad b"), ("c.dcm", "good c")):
        (folder / name).write_text(text)
    lines = []
    watch = FolderWatch(folder, poll_s=0.01)
    s = serve_frames(_register(), watch, root, watch=watch, limit=3, errors=(_Refused,), emit=lines.append,
                     note=lambda _: None)
    assert (s.registered, s.refused, s.skipped) == (2, 1, 0)
    assert [line.get("out") for line in lines] == [str(root / "a"), None, str(root / "c")]
    assert "damaged" in lines[1]["error"]
    assert {p.name for p in _whole_or_absent(root)} == {"a", "c"}
    record = json.loads((root / "a" / FRAME_RECORD).read_text())
    assert record["xray"] == str((folder / "a.dcm").resolve()) and len(record["sha256"]) == 64
    assert set(done_frames(root)) == {(str((folder / n).resolve()), json.loads((root / n[0] / FRAME_RECORD)
                                       .read_text())["sha256"]) for n in ("a.dcm", "c.dcm")}
    # a restart: the done frames are skipped, the refused one (still bad) tried again, a changed one redone
    (folder / "c.dcm").write_text("good c, another frame under the same name")
    notes, lines = [], []
    watch = FolderWatch(folder, poll_s=0.01)
    s = serve_frames(_register(), watch, root, watch=watch, limit=3, errors=(_Refused,), emit=lines.append,
                     note=notes.append)
    assert (s.registered, s.refused, s.skipped) == (1, 1, 1)
    assert any("a.dcm: already registered in" in n for n in notes)
    assert [line.get("out") for line in lines] == [None, str(root / "c_2")]


def _send_later(sig, after_s, times=1):
    def send():
        for _ in range(times):
            os.kill(os.getpid(), sig)
            time.sleep(0.05)
    t = threading.Timer(after_s, send)
    t.start()
    return t


def test_sigterm_finishes_the_frame_in_hand_and_a_second_abandons_it(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("a.dcm", "b.dcm"):
        (folder / name).write_text("good")
    notes = []
    root = tmp_path / "once"
    t = _send_later(signal.SIGTERM, 0.2)
    s = serve_frames(_register(0.15), [folder / "a.dcm", folder / "b.dcm"], root, errors=(_Refused,),
                     emit=lambda _: None, note=notes.append)
    t.join()
    assert s.registered == 1 and s.stopped_by == "SIGTERM" and "SIGTERM: finished a.dcm, stopping" in notes
    assert [p.name for p in _whole_or_absent(root)] == ["a"]
    notes = []
    root = tmp_path / "twice"
    t = _send_later(signal.SIGTERM, 0.2, times=2)
    s = serve_frames(_register(0.15), [folder / "a.dcm", folder / "b.dcm"], root, errors=(_Refused,),
                     emit=lambda _: None, note=notes.append)
    t.join()
    assert s.registered == 0 and any("abandoned a.dcm" in n for n in notes), notes
    assert [p.name for p in root.iterdir()] == [".ctxreg.lock"]  # nothing half-written, no hidden temporary folder
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL or callable(signal.getsignal(signal.SIGTERM))


_SERVER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    sys.path.insert(0, {repo!r})
    from tests.register.test_serve import _register, _Refused
    from register.serve import FolderWatch, serve_frames
    watch = FolderWatch(Path(sys.argv[1]), poll_s=0.01)
    s = serve_frames(_register(0.06), watch, Path(sys.argv[2]), watch=watch, limit=int(sys.argv[3]),
                     errors=(_Refused,))
    print("summary", s.registered, s.skipped, flush=True)
""")


def test_kills_at_random_moments_leave_whole_folders_and_a_restart_registers_the_rest(tmp_path):
    """8 trials (the suite's size; benchmarks/serve_kills.py kills ctxreg serve itself, 20 times):
    serve is killed (SIGKILL or SIGTERM) at a random moment while registering 4 frames (each
    writing its outputs over ~0.2 s); after each kill every frame folder is whole or absent; a
    restart registers the frames not done, each frame exactly once in all."""
    script = tmp_path / "server.py"
    script.write_text(_SERVER.format(repo=str(REPO)))
    rng = random.Random(7)
    for trial in range(8):
        folder, root = tmp_path / f"in{trial}", tmp_path / f"out{trial}"
        folder.mkdir()
        for k in range(4):
            (folder / f"f{k}.dcm").write_text(f"good {trial} {k}")
        p = subprocess.Popen([sys.executable, str(script), str(folder), str(root), "4"], cwd=REPO,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(rng.uniform(0.3, 1.4))  # the interpreter's start-up, then some of the frames
        sig = signal.SIGKILL if trial % 2 == 0 else signal.SIGTERM
        p.send_signal(sig)
        p.communicate(timeout=60)
        before = _whole_or_absent(root) if root.exists() else []
        r = subprocess.run([sys.executable, str(script), str(folder), str(root), "4"], cwd=REPO, capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 0, r.stderr[-2000:]
        assert f"summary {4 - len(before)} {len(before)}" in r.stdout, (trial, r.stdout, r.stderr[-2000:])
        after = _whole_or_absent(root)
        assert sorted(p.name for p in after) == [f"f{k}" for k in range(4)], (trial, after)
        assert [p.name for p in root.iterdir() if p.name.startswith(".")] == [".ctxreg.lock"], trial  # no partial


def test_a_second_server_on_one_out_folder_is_refused_at_once(tmp_path):
    """Two servers writing frames into one --out would collide: while one holds the folder, a
    second is refused in one line naming the holder."""
    from sim.core.atomic import FolderBusyError, folder_lock

    root = tmp_path / "out"
    with folder_lock(root, "ctxreg serve"):
        with pytest.raises(FolderBusyError, match=r"ctxreg serve \(PID \d+ on .*\) is working in this folder"):
            serve_frames(_register(), [], root, emit=lambda _: None, note=lambda _: None)
    assert serve_frames(_register(), [], root, emit=lambda _: None, note=lambda _: None).registered == 0  # released
