"""Atomic writes: all or nothing, with the permissions a plain open() would give."""

from __future__ import annotations

import os
import stat

import pytest


def test_written_file_has_umask_permissions_and_no_leftovers(tmp_path):
    from sim.atomic import atomic_path

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
    from sim.atomic import atomic_path

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

    from sim.atomic import jsonable

    data = {1: (np.float32(0.5), np.int64(3), np.bool_(True)), "a": np.arange(4).reshape(2, 2), "n": None}
    out = jsonable(data)
    assert out == {"1": [0.5, 3, True], "a": [[0, 1], [2, 3]], "n": None}
    assert json.loads(json.dumps(out)) == out
    assert type(out["1"][1]) is int and type(out["1"][2]) is bool
    with pytest.raises(TypeError, match="object"):
        jsonable({"x": object()})
