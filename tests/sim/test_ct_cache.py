"""The CT cache (sim/ct_cache.py): a cached CT is the CT, a changed CT is never served from an old
entry, broken entries are rebuilt, the folder keeps its size limit; and renderers of one CT share
one upload (sim/drr.py) with the same images."""

from __future__ import annotations

import os

import numpy as np
import pytest

import sim
from sim import ct_cache
from sim.anatomy import anatomy_center
from sim.ct_cache import CTCacheError, ct_hash, evict, load_ct_cached
from sim.ct_io import load_ct, save_nifti
from sim.volume import CTInputError, CTVolume


def _ct(seed: int, *, fractional: bool = False) -> CTVolume:
    """A 24 x 20 x 16 CT of soft tissue with a bone block whose place depends on the seed."""
    rng = np.random.default_rng(seed)
    hu = rng.integers(-100, 100, (24, 20, 16)).astype(np.float32)
    i = 4 + seed % 8
    hu[i:i + 8, 5:12, 4:10] = 1200.0
    if fractional:
        hu += 0.25
    affine = np.diag([1.5, 1.5, 2.0, 1.0])
    affine[:3, 3] = (-20.0, -15.0, 10.0)
    return CTVolume(hu=hu, affine=affine, source=f"test:{seed}")


def _saved(tmp_path, seed: int, name: str = "ct.nii", **kw):
    path = tmp_path / name
    save_nifti(_ct(seed, **kw), path)
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
    save_nifti(_ct(2), path)  # uncompressed NIfTI of the same shape: the same size
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


def test_renderers_of_one_ct_share_one_upload_and_render_the_same_images():
    from sim.drr import DRRRenderer, RenderSettings, _UPLOADS
    from sim.geometry import pose_from_params

    ct = _ct(2)
    a = DRRRenderer(ct, RenderSettings(size=(24, 24)))
    b = DRRRenderer(ct, RenderSettings(size=(16, 16), ray_model="trilinear"))
    assert a.integrator.volume is b.integrator.volume and len(_UPLOADS[ct]) == 1
    other_water = DRRRenderer(ct, RenderSettings(size=(24, 24), mu_water_per_mm=0.03))
    assert other_water.integrator.volume is not a.integrator.volume and len(_UPLOADS[ct]) == 2
    # the same CT as a new object: its own upload, the same image
    twin = DRRRenderer(CTVolume(hu=ct.hu.copy(), affine=ct.affine, source="twin"), RenderSettings(size=(24, 24)),
                       center_lps=a.center_lps)
    assert twin.integrator.volume is not a.integrator.volume
    pose = pose_from_params(np.array([10.0, -5.0, 3.0, 2.0, -1.0, 4.0]), a.geometry.sod_mm)
    np.testing.assert_array_equal(a.render(pose), twin.render(pose))
    from sim.materials import MU_WATER_60KEV_PER_MM  # mu is linear in mu_water: the image scales with it

    np.testing.assert_allclose(other_water.render(pose), a.render(pose) * (0.03 / MU_WATER_60KEV_PER_MM),
                               rtol=1e-5, atol=1e-6)


def test_coarsened_keeps_the_mass_and_the_coarse_voxel_centres():
    from sim.drr import coarse_affine, coarsened

    rng = np.random.default_rng(3)
    fine = rng.random((2, 7, 6, 5)).astype(np.float32)
    coarse = coarsened(fine, (2, 4, 1))
    assert coarse.shape == (2, 4, 2, 5)
    np.testing.assert_allclose(coarse.sum(axis=(1, 2, 3)) * 8, fine.sum(axis=(1, 2, 3)), rtol=1e-6)
    np.testing.assert_allclose(coarse[:, 1, 0, 3], fine[:, 2:4, 0:4, 3].mean(axis=(1, 2)), rtol=1e-6)
    affine = np.array([[0.0, 1.5, 0, 3], [2.0, 0, 0, -1], [0, 0, -1.0, 7], [0, 0, 0, 1]])
    ca = coarse_affine(affine, (2, 4, 1))
    centres = affine @ np.array([[2, 3, 2, 3], [4, 4, 7, 7], [3, 3, 3, 3], [1, 1, 1, 1]], float)  # fine (2..3, 4..7, 3)
    np.testing.assert_allclose(ca @ [1, 1, 3, 1], centres.mean(axis=1), atol=1e-12)


def test_coarsening_follows_the_pixel_footprint_and_keeps_the_image():
    """Factors: the largest powers of two keeping voxels at most half the pixel's footprint at the
    isocentre. Image: a fine CT (0.75 mm) rendered at 64 px (footprint 3.2 mm) from 1.5 mm voxels
    stays within 2 % (rel. L2; 1.2 % measured, most of it the phantom's uncorrelated 20 HU noise,
    which the coarse voxels average; the chest CT: 0.4 %) of its own voxels' image; a 3 mm CT at
    64 px is not coarsened."""
    from sim.drr import DRRRenderer, RenderSettings, coarsening
    from sim.geometry import pose_from_params
    from sim.scene import load_scene

    g64 = load_scene("cios_fusion").geometry_at(64, 64)
    footprint = g64.pixel_spacing_mm * g64.sod_mm / g64.sdd_mm
    rng = np.random.default_rng(4)
    n = 128
    x = np.linspace(-1, 1, n)
    r2 = x[:, None, None] ** 2 + x[None, :, None] ** 2 + 0.5 * x[None, None, :] ** 2
    hu = np.where(r2 < 0.7, 40.0, -1000.0) + np.where(r2 < 0.15, 900.0, 0.0) + rng.normal(0, 20, (n, n, n))
    fine = CTVolume(hu=hu.astype(np.float32), affine=np.diag([0.75, 0.75, 0.75, 1.0]), source="fine")
    factors = coarsening(fine, g64)
    assert factors == (2, 2, 2) and all(0.75 * f * 2 > footprint / 2 >= 0.75 * f for f in factors), (factors, footprint)
    coarse_3mm = CTVolume(hu=hu.astype(np.float32), affine=np.diag([3.0, 3.0, 3.0, 1.0]), source="3mm")
    assert coarsening(coarse_3mm, g64) == (1, 1, 1)
    full = DRRRenderer(fine, RenderSettings(size=(64, 64)), center_lps=np.zeros(3) + 0.75 * (n - 1) / 2)
    coarse = DRRRenderer(fine, RenderSettings(size=(64, 64), coarsen=True), center_lps=full.center_lps)
    assert coarse.factors == factors and full.factors == (1, 1, 1)
    poses = pose_from_params(rng.uniform(-1, 1, (4, 6)) * [30, 20, 20, 5, 5, 20], g64.sod_mm)
    a, b = full.render(poses), coarse.render(poses)
    assert np.linalg.norm(a - b) / np.linalg.norm(a) < 0.02
    assert abs(a.sum() - b.sum()) / a.sum() < 0.005  # the mass along the rays is kept
