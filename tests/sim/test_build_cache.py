"""The build cache (sim.core.build_cache): a value built once per key, then read; any change of its
settings, libraries or code is another key; a damaged entry is built again, an unwritable folder
costs only the cache."""

from __future__ import annotations

import numpy as np
import pytest

import sim.core.build_cache as bc


class Damaged(Exception):
    pass


def _save(a, path):
    with open(path, "wb") as f:
        np.savez(f, a=a)


def _load(path):
    try:
        with np.load(path, allow_pickle=False) as z:
            return np.asarray(z["a"])
    except (OSError, ValueError, KeyError, EOFError) as e:
        raise Damaged(str(e)) from None


def _calls():
    calls = []

    def build(value=(1.0, 2.0)):
        calls.append(1)
        return np.asarray(value)
    return calls, build


def test_a_value_is_built_once_and_then_read(tmp_path):
    calls, build = _calls()
    kw = dict(save=_save, load=_load, errors=(Damaged,), folder=tmp_path)
    first = bc.cached("table", {"kvp": [80.0]}, build=build, **kw)
    again = bc.cached("table", {"kvp": [80.0]}, build=build, **kw)
    assert len(calls) == 1
    np.testing.assert_array_equal(again, first)
    entries = list(tmp_path.glob("table-*.npz"))
    assert len(entries) == 1 and len(entries[0].stem) == len("table-") + 40


def test_settings_libraries_and_code_are_in_the_key(tmp_path, monkeypatch):
    """Another setting, another library version or one changed line of the building code: built again."""
    code = tmp_path / "code"
    code.mkdir()
    (code / "build.py").write_text("X = 1\n")
    calls, build = _calls()
    kw = dict(save=_save, load=_load, errors=(Damaged,), folder=tmp_path / "cache", code=[code])
    bc.cached("table", {"kvp": [80.0]}, build=build, **kw)
    bc.cached("table", {"kvp": [90.0]}, build=build, **kw)
    assert len(calls) == 2
    (code / "build.py").write_text("X = 2\n")
    bc.code_fingerprint.cache_clear()  # a new process would read the changed file
    bc.cached("table", {"kvp": [80.0]}, build=build, **kw)
    assert len(calls) == 3
    real = bc._versions()
    monkeypatch.setattr(bc, "_versions", lambda: {**real, "spekpy": "0.0"})
    bc.cached("table", {"kvp": [80.0]}, build=build, **kw)
    assert len(calls) == 4
    monkeypatch.setattr(bc, "_versions", lambda: real)
    bc.cached("table", {"kvp": [80.0]}, build=build, **kw)
    assert len(calls) == 4  # back to a key it has
    with pytest.raises(ValueError, match="kind must be"):
        bc.entry_key("Bad Kind", {})


def test_a_damaged_entry_is_built_again_and_replaced(tmp_path):
    calls, build = _calls()
    lines = []
    kw = dict(save=_save, load=_load, errors=(Damaged,), folder=tmp_path, log=lines.append)
    bc.cached("table", {}, build=build, **kw)
    (entry,) = tmp_path.glob("table-*.npz")
    entry.write_bytes(b"damaged")
    value = bc.cached("table", {}, build=build, **kw)
    np.testing.assert_array_equal(value, [1.0, 2.0])
    assert len(calls) == 2 and "cannot be used" in lines[0] and str(entry) in lines[0]
    np.testing.assert_array_equal(_load(entry), [1.0, 2.0])  # written again


def test_an_unwritable_folder_or_off_costs_the_cache_not_the_value(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    calls, build = _calls()
    lines = []
    value = bc.cached("table", {}, build=build, save=_save, load=_load, errors=(Damaged,), folder=blocker / "sub",
                      log=lines.append)
    np.testing.assert_array_equal(value, [1.0, 2.0])
    assert "cannot write" in lines[0] and "CTXREG_BUILD_CACHE" in lines[0]
    monkeypatch.setenv("CTXREG_BUILD_CACHE", "off")
    assert bc.cache_dir() is None
    for _ in range(2):
        bc.cached("table", {}, build=build, save=_save, load=_load, errors=(Damaged,))
    assert len(calls) == 3
    monkeypatch.setenv("CTXREG_BUILD_CACHE", str(tmp_path / "mine"))
    assert bc.cache_dir() == tmp_path / "mine"


def test_only_the_least_recently_used_entries_of_a_kind_go(tmp_path, monkeypatch):
    import os

    monkeypatch.setattr(bc, "MAX_ENTRIES", 2)
    kw = dict(save=_save, load=_load, errors=(Damaged,), folder=tmp_path)
    foreign = tmp_path / "table-mine.npz"
    foreign.write_bytes(b"the user's")
    bc.cached("other", {}, build=lambda: np.zeros(1), **kw)
    for k, t in enumerate((100, 300, 200)):
        bc.cached("table", {"k": k}, build=lambda: np.zeros(1), **kw)
        os.utime(tmp_path / f"table-{bc.entry_key('table', {'k': k})}.npz", (t, t))
    bc.cached("table", {"k": 3}, build=lambda: np.zeros(1), **kw)  # the fourth: the two oldest go
    kept = {p.stem[6:] for p in tmp_path.glob("table-*.npz") if p != foreign}
    assert kept == {bc.entry_key("table", {"k": k}) for k in (1, 3)}
    assert foreign.exists() and len(list(tmp_path.glob("other-*.npz"))) == 1


def test_a_truncated_spectral_table_is_refused_in_one_line(tmp_path):
    """A table cut short (a zip without its end, as a full disk leaves one) is the loader's one-line
    error, which the build cache takes as a damaged entry to build again."""
    from sim.physics import PhysicsError
    from sim.physics.two_basis import SpectralTable

    table = SpectralTable.build([80.0], [2.5], [0.0])
    path = table.save(tmp_path / "t.npz")
    np.testing.assert_array_equal(SpectralTable.load(path).fluence, table.fluence)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(PhysicsError, match="cannot be read"):
        SpectralTable.load(path)
