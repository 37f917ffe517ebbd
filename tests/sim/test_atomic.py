"""Atomic writes: all or nothing, with the permissions a plain open() would give."""

from __future__ import annotations

import os
import stat

import pytest


def test_written_file_has_umask_permissions_and_no_leftovers(tmp_path):
    from sim.core.atomic import atomic_path

    old = os.umask(0o022)
    try:
        with atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("x")
    finally:
        os.umask(old)
    assert (tmp_path / "a.txt").read_text() == "x"
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    from sim.core.atomic import atomic_path

    (tmp_path / "a.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert (tmp_path / "a.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_jsonable_turns_numpy_and_tuples_into_plain_json_and_refuses_objects():
    import json

    import numpy as np
    import pytest

    from sim.core.atomic import jsonable

    data = {1: (np.float32(0.5), np.int64(3), np.bool_(True)), "a": np.arange(4).reshape(2, 2), "n": None}
    out = jsonable(data)
    assert out == {"1": [0.5, 3, True], "a": [[0, 1], [2, 3]], "n": None}
    assert json.loads(json.dumps(out)) == out
    assert type(out["1"][1]) is int and type(out["1"][2]) is bool
    with pytest.raises(TypeError, match="object"):
        jsonable({"x": object()})


def _dead_pid() -> int:
    """The PID of a process that has ended (and been reaped)."""
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_temporary_names_say_whose_they_are(tmp_path):
    from sim.core.atomic import _host, atomic_path, temp_owner

    with atomic_path(tmp_path / "manifest.part1-of-2.json") as tmp:
        assert tmp.name.startswith(f".manifest.part1-of-2.json.{os.getpid()}@{_host()}-")
        assert tmp.name.endswith(".tmp.part1-of-2.json")  # the target's suffixes, for writers that need them
        assert temp_owner(tmp.name) == ("manifest.part1-of-2.json", os.getpid(), _host())
        tmp.write_text("{}")
    assert temp_owner("manifest.json") is None
    assert temp_owner(".s0000_00001.h5.abc.tmp.h5") is None  # no PID: not ours to judge


def test_stale_temporaries_of_dead_writers_are_removed_and_no_others(tmp_path):
    from sim.core.atomic import _host, remove_stale_temps

    dead, host = _dead_pid(), _host()
    files = {
        "dead": f".a.h5.{dead}@{host}-abcd1234.tmp.h5",
        "dead_other_target": f".b.h5.{dead}@{host}-abcd1234.tmp.h5",
        "alive": f".a.h5.{os.getpid()}@{host}-abcd1234.tmp.h5",
        "other_host": f".a.h5.{dead}@{host}x-abcd1234.tmp.h5",  # a shared folder: cannot tell, kept
        "legacy": ".a.h5.abcd1234.tmp.h5",
        "target": "a.h5",
    }
    for name in files.values():
        (tmp_path / name).write_bytes(b"x")
    removed = remove_stale_temps(tmp_path, "a.h5")
    assert [p.name for p in removed] == [files["dead"]]
    removed = remove_stale_temps(tmp_path)
    assert [p.name for p in removed] == [files["dead_other_target"]]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        files[k] for k in ("alive", "other_host", "legacy", "target"))
    assert remove_stale_temps(tmp_path / "missing") == []


def test_a_write_killed_midway_leaves_a_temporary_that_the_next_write_removes(tmp_path):
    """kill -9 during a write: the target is untouched, the temporary names its dead writer."""
    import signal
    import subprocess
    import sys
    import time

    from sim.core.atomic import atomic_path, temp_owner

    target = tmp_path / "data.json"
    target.write_text("old")
    code = ("import sys, time; from sim.core.atomic import atomic_path\n"
            "with atomic_path(sys.argv[1]) as tmp:\n"
            "    tmp.write_text('half'); print('writing', flush=True); time.sleep(60)\n")
    p = subprocess.Popen([sys.executable, "-c", code, str(target)], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "writing"
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=30)
    left = [q for q in tmp_path.iterdir() if q.name != "data.json"]
    assert len(left) == 1 and temp_owner(left[0].name)[:2] == ("data.json", p.pid)
    assert target.read_text() == "old"
    t0 = time.monotonic()
    with atomic_path(target) as tmp:  # the next writer of the same file cleans up
        tmp.write_text("new")
    assert time.monotonic() - t0 < 5
    assert [q.name for q in tmp_path.iterdir()] == ["data.json"] and target.read_text() == "new"


def test_toml_text_round_trips_through_tomllib(tmp_path):
    import tomllib

    from sim.core.atomic import toml_text, write_toml

    data = {"model": {"name": "pelvis line", "size": [64, 64], "ok": True, "lr": 1e-3, "n": 3,
                      "steps": ["normalize", {"name": "gaussian", "sigma_px": 1.5}], "quote": 'a "b"\\c'},
            "accuracy": {"success": 0.94, "skipped": None}}
    back = tomllib.loads(toml_text(data))
    assert back == {"model": data["model"], "accuracy": {"success": 0.94}}  # None is left out
    write_toml(tmp_path / "m.toml", data)
    assert tomllib.loads((tmp_path / "m.toml").read_text()) == back
    with pytest.raises(ValueError, match="nan"):
        toml_text({"t": {"x": float("nan")}})
