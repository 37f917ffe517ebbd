"""The CT cache (sim/ct/cache.py): a cached CT is the CT, a changed CT is never served from an old
entry, broken entries are rebuilt, the folder keeps its size limit."""

from __future__ import annotations

import os

import numpy as np
import pytest

import sim
from sim.ct import cache as ct_cache
from sim.ct.anatomy import anatomy_center
from sim.ct.cache import CTCacheError, ct_hash, evict, load_ct_cached
from sim.ct.io import load_ct, save_nifti
from sim.ct.volume import CTInputError

from tests.sim.small_ct import small_ct


def _saved(tmp_path, seed: int, name: str = "ct.nii", **kw):
    path = tmp_path / name
    save_nifti(small_ct(seed, **kw), path)
    return path


def test_a_cached_ct_is_the_ct_and_its_second_read_uses_no_ct_file(tmp_path, monkeypatch):
    path = _saved(tmp_path, 1)
    cache = tmp_path / "cache"
    lines = []
    first = load_ct_cached(path, cache_dir=cache, log=lines.append)
    assert len(list(cache.glob("*.npz"))) == 1 and "stored" in lines[0]
    direct = load_ct(path)

    def no_read(*a, **k):
        raise AssertionError("the CT file was read again")

    monkeypatch.setattr(ct_cache, "load_ct", no_read)
    second = load_ct_cached(path, cache_dir=cache)
    for v in (first, second):
        np.testing.assert_array_equal(v.hu, direct.hu)
        np.testing.assert_array_equal(v.affine, direct.affine)
        assert v.hu.dtype == np.float32 and v.source == direct.source
    # the anatomy centre comes with the entry, and is the one computed from the CT
    np.testing.assert_allclose(anatomy_center(second), anatomy_center(direct), atol=1e-9)


def test_a_changed_ct_is_never_served_from_the_old_entry(tmp_path):
    """The key is the content hash: same name, size and modification time, other voxels -> the new CT."""
    path = _saved(tmp_path, 1)
    cache = tmp_path / "cache"
    old = load_ct_cached(path, cache_dir=cache)
    stat = path.stat()
    save_nifti(small_ct(2), path)  # uncompressed NIfTI of the same shape: the same size
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns
    new = load_ct_cached(path, cache_dir=cache)
    np.testing.assert_array_equal(new.hu, load_ct(path).hu)
    assert not np.array_equal(new.hu, old.hu)
    assert len(list(cache.glob("*.npz"))) == 2
    # its centre is the new CT's, not the old one's
    np.testing.assert_allclose(anatomy_center(new), anatomy_center(load_ct(path)), atol=1e-9)
    assert not np.allclose(anatomy_center(new), anatomy_center(old))


def test_the_hash_of_a_dicom_like_folder_sees_one_changed_byte_and_a_renamed_file(tmp_path):
    folder = tmp_path / "series"
    folder.mkdir()
    for n in range(3):
        (folder / f"s{n}.dcm").write_bytes(bytes(range(n, n + 50)))
    (folder / ".DS_Store").write_bytes(b"ignored")
    h0 = ct_hash(folder)
    (folder / ".DS_Store").write_bytes(b"still ignored")
    assert ct_hash(folder) == h0
    data = bytearray((folder / "s1.dcm").read_bytes())
    data[10] ^= 1
    (folder / "s1.dcm").write_bytes(bytes(data))
    h1 = ct_hash(folder)
    assert h1 != h0
    (folder / "s2.dcm").rename(folder / "s9.dcm")
    assert ct_hash(folder) not in (h0, h1)


@pytest.mark.parametrize("damage", ["truncated", "other key"])
def test_a_broken_entry_is_rebuilt_with_a_line(tmp_path, damage):
    path = _saved(tmp_path, 3)
    cache = tmp_path / "cache"
    load_ct_cached(path, cache_dir=cache)
    entry = next(cache.glob("*.npz"))
    if damage == "truncated":
        entry.write_bytes(entry.read_bytes()[:200])
    else:  # another CT's entry under this CT's name
        other = _saved(tmp_path, 4, "other.nii")
        load_ct_cached(other, cache_dir=cache)
        other_entry = cache / f"{ct_hash(other)}.npz"
        entry.write_bytes(other_entry.read_bytes())
    lines = []
    v = load_ct_cached(path, cache_dir=cache, log=lines.append)
    np.testing.assert_array_equal(v.hu, load_ct(path).hu)
    assert any("rebuilt" in line for line in lines), lines
    # and the rebuilt entry serves the next read
    lines.clear()
    load_ct_cached(path, cache_dir=cache, log=lines.append)
    assert lines == []


def test_whole_hu_are_stored_as_int16_and_fractional_ones_as_float32(tmp_path):
    cache = tmp_path / "cache"
    for seed, fractional, dtype in ((5, False, np.int16), (6, True, np.float32)):
        path = _saved(tmp_path, seed, f"ct{seed}.nii", fractional=fractional)
        v = load_ct_cached(path, cache_dir=cache)
        with np.load(cache / f"{ct_hash(path)}.npz") as z:
            assert z["hu"].dtype == dtype
        np.testing.assert_array_equal(v.hu, load_ct(path).hu)


def test_the_folder_keeps_its_limit_least_recently_used_first(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    paths = [_saved(tmp_path, s, f"ct{s}.nii") for s in (1, 2, 3)]
    for n, p in enumerate(paths):
        load_ct_cached(p, cache_dir=cache)
        e = cache / f"{ct_hash(p)}.npz"
        os.utime(e, (1000 + n, 1000 + n))
    load_ct_cached(paths[0], cache_dir=cache)  # a hit: now the most recently used
    size = (cache / f"{ct_hash(paths[0])}.npz").stat().st_size
    removed = evict(cache, limit_bytes=2 * size)
    assert removed == [cache / f"{ct_hash(paths[1])}.npz"]
    monkeypatch.setenv("CTXREG_CT_CACHE_MB", "0")
    fresh = _saved(tmp_path, 7, "ct7.nii")
    load_ct_cached(fresh, cache_dir=cache)  # a limit of 0 keeps only the entry just written
    assert [e.name for e in cache.glob("*.npz")] == [f"{ct_hash(fresh)}.npz"]


def test_a_folder_of_the_users_files_keeps_every_file_whatever_the_limit(tmp_path, monkeypatch):
    """A data folder given as the cache: the user's own .npz files (one even named like an entry,
    and one like an entry with another key in its meta), a text file and a subfolder survive a
    limit of 0 bytes, byte for byte; only the cache's own older entries are removed."""
    data = tmp_path / "userdata"
    data.mkdir()
    np.savez(data / "experiment.npz", x=np.arange(5))
    np.savez(data / "my_results.npz", meta=np.array('{"key": "mine"}'))
    lookalike = data / ("ab" * 20 + ".npz")
    np.savez(lookalike, hu=np.zeros(3))
    impostor = data / ("cd" * 20 + ".npz")
    np.savez(impostor, meta=np.array('{"key": "' + "ef" * 20 + '"}'))
    (data / "notes.txt").write_text("keep me")
    (data / "sub").mkdir()
    np.savez(data / "sub" / "deep.npz", x=np.ones(2))
    before = {p: p.read_bytes() for p in data.rglob("*") if p.is_file()}
    old = _saved(tmp_path, 1, "old.nii")
    load_ct_cached(old, cache_dir=data)
    monkeypatch.setenv("CTXREG_CT_CACHE_MB", "0")
    lines = []
    new = _saved(tmp_path, 2, "new.nii")
    load_ct_cached(new, cache_dir=data, log=lines.append)
    assert {p: p.read_bytes() for p in before} == before  # every file of the user's, unchanged
    assert not (data / f"{ct_hash(old)}.npz").exists() and (data / f"{ct_hash(new)}.npz").is_file()
    assert any("removed 1 least recently used entry" in line for line in lines)
    assert ct_cache.is_entry(data / f"{ct_hash(new)}.npz")
    assert not any(ct_cache.is_entry(p) for p in before)


def test_bad_settings_and_inputs_are_named(tmp_path, monkeypatch):
    path = _saved(tmp_path, 1)
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("x")
    with pytest.raises(CTCacheError, match="not a folder"):
        load_ct_cached(path, cache_dir=not_a_folder)
    monkeypatch.setenv("CTXREG_CT_CACHE_MB", "lots")
    with pytest.raises(CTCacheError, match="CTXREG_CT_CACHE_MB"):
        load_ct_cached(path, cache_dir=tmp_path / "c2")
    monkeypatch.delenv("CTXREG_CT_CACHE_MB")
    with pytest.raises(CTInputError, match="not found"):
        load_ct_cached(tmp_path / "missing.nii.gz", cache_dir=tmp_path / "c3")
    bad = tmp_path / "bad.nii.gz"
    bad.write_bytes(b"not a nifti")
    with pytest.raises(CTInputError):
        load_ct_cached(bad, cache_dir=tmp_path / "c4")
    assert not list((tmp_path / "c4").glob("*.npz"))


def test_a_folder_that_cannot_be_written_costs_the_cache_not_the_ct(tmp_path, monkeypatch):
    path = _saved(tmp_path, 1)

    def full_disk(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ct_cache.np, "savez", full_disk)
    lines = []
    v = load_ct_cached(path, cache_dir=tmp_path / "cache", log=lines.append)
    np.testing.assert_array_equal(v.hu, load_ct(path).hu)
    assert len(lines) == 1 and "cannot write" in lines[0] and "No space left" in lines[0]
    assert not list((tmp_path / "cache").glob("*"))  # no half-written entry left


def test_sim_load_ct_uses_the_cache_for_files_only(tmp_path, monkeypatch):
    monkeypatch.setenv("CTXREG_CT_CACHE", str(tmp_path / "default"))
    path = _saved(tmp_path, 1)
    v = sim.load_ct(str(path), cache=True)
    assert len(list((tmp_path / "default").glob("*.npz"))) == 1
    np.testing.assert_array_equal(v.hu, load_ct(path).hu)
    sim.load_ct("phantom", cache=True)
    sim.load_ct(str(path), cache=False)
    assert len(list((tmp_path / "default").glob("*.npz"))) == 1
