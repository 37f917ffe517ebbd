"""CT input/output against truth: hand-computed RAS/LPS positions, DICOM geometry written by the test
(IPP + i * column spacing * row direction + j * row spacing * column direction), rescale
slope/intercept, NIfTI round trips, resampling of linear ramps, and one-line errors for bad input."""

from __future__ import annotations

import gzip

import nibabel as nib
import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

from sim.ct.io import RAS_TO_LPS, ct_from_array, load_ct, resample, save_nifti
from sim.ct.volume import CTInputError, CTVolume
from tests.conftest import shared_file

# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def rotation(axis, angle_deg: float) -> np.ndarray:
    """(3, 3) rotation about ``axis`` by ``angle_deg`` (Rodrigues), an independent closed form."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    t = np.radians(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


def oblique_affine(spacing=(0.8, 1.3, 2.5), offset=(-120.25, 45.75, -310.5)) -> np.ndarray:
    """A voxel-to-LPS affine with a rotation, non-isotropic spacing and an offset."""
    a = np.eye(4)
    a[:3, :3] = rotation((1.0, -2.0, 0.5), 23.0) @ np.diag(spacing)
    a[:3, 3] = offset
    return a


def ct_like(shape, seed=0) -> np.ndarray:
    """Air, soft tissue and a bone slab with noise: values that pass the HU plausibility test."""
    rng = np.random.default_rng(seed)
    hu = np.full(shape, -1000.0)
    s = tuple(slice(n // 5, n - n // 5) for n in shape)
    hu[s] = 40.0
    hu[shape[0] // 2:shape[0] // 2 + 2] += 900.0
    return (hu + rng.normal(0, 20, shape)).astype(np.float32)


ROW_DIR_OBLIQUE = (0.6, 0.8, 0.0)
COL_DIR_OBLIQUE = (-0.48, 0.36, 0.8)  # orthonormal to ROW_DIR_OBLIQUE (3-4-5 triples, exact decimals)


def write_series(folder, *, n=7, rows=6, cols=5, row_dir=ROW_DIR_OBLIQUE, col_dir=COL_DIR_OBLIQUE,
                 pixel_spacing=(0.7, 0.9), slice_spacing=2.5, ipp0=(-120.5, 30.25, -400.0),
                 dtype=np.int16, slope=2.0, intercept=-1024.0, series_uid=None, seed=0,
                 spacing_of=None, skip=()):
    """Write a CT series: slices shuffled over file names, InstanceNumber scrambled.

    Returns the truth: ``stored`` (n, rows, cols) by position index, ``ipp`` (n, 3) floats parsed
    from the strings written, the directions and spacings; ``skip`` leaves those positions out.
    """
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    row_dir, col_dir = np.array(row_dir, float), np.array(col_dir, float)
    normal = np.cross(row_dir, col_dir)
    lo = -30 if dtype == np.int16 else 0
    stored = rng.integers(lo, 1200, size=(n, rows, cols)).astype(dtype)
    ipp_text = [[f"{v:.4f}" for v in np.array(ipp0) + k * slice_spacing * normal] for k in range(n)]
    ipp = np.array([[float(v) for v in row] for row in ipp_text])
    uid = series_uid or generate_uid()
    study = generate_uid()
    order = rng.permutation(n)  # file name order differs from position order
    instance = rng.permutation(n) + 1  # InstanceNumber unrelated to position
    for slot, k in enumerate(order):
        if k in skip:
            continue
        sop = generate_uid()
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = sop
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = sop
        ds.StudyInstanceUID = study
        ds.SeriesInstanceUID = uid
        ds.Modality = "CT"
        ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
        ds.InstanceNumber = int(instance[k])
        ds.ImagePositionPatient = ipp_text[k]
        ds.ImageOrientationPatient = [f"{v:g}" for v in (*row_dir, *col_dir)]
        ps = pixel_spacing if spacing_of is None or k != spacing_of[0] else spacing_of[1]
        ds.PixelSpacing = [f"{v:g}" for v in ps]
        ds.SliceThickness = f"{slice_spacing:g}"
        ds.RescaleSlope = f"{slope:g}"
        ds.RescaleIntercept = f"{intercept:g}"
        ds.Rows, ds.Columns = rows, cols
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated = ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 1 if dtype == np.int16 else 0
        ds.PixelData = stored[k].tobytes()
        ds.save_as(folder / f"slice_{slot:03d}.dcm", enforce_file_format=True)
    return dict(stored=stored, ipp=ipp, row_dir=row_dir, col_dir=col_dir, pixel_spacing=pixel_spacing,
                slope=slope, intercept=intercept, uid=uid, normal=normal)


def raises_ct_error(*words):
    """Context: a CTInputError whose message contains every word (case-insensitive)."""

    class _Check:
        def __enter__(self):
            self.ctx = pytest.raises(CTInputError)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *exc):
            out = self.ctx.__exit__(*exc)
            msg = str(self.info.value).lower()
            for w in words:
                assert w.lower() in msg, f"{w!r} not in error message: {self.info.value}"
            return out

    return _Check()


# --------------------------------------------------------------------------------------------
# NIfTI
# --------------------------------------------------------------------------------------------


def test_nifti_ras_affine_becomes_lps_on_a_hand_computed_voxel(tmp_path):
    # RAS affine: voxel (i, j, k) -> RAS (10 + 2i, 20 + 3j, 30 + 4k); voxel (3, 4, 5) is RAS (16, 32, 50)
    ras = np.array([[2.0, 0, 0, 10], [0, 3.0, 0, 20], [0, 0, 4.0, 30], [0, 0, 0, 1]])
    hu = ct_like((8, 9, 10))
    hu[3, 4, 5] = 3000.0
    path = tmp_path / "known.nii.gz"
    nib.save(nib.Nifti1Image(hu, ras), path)
    v = load_ct(path)
    assert v.shape == (8, 9, 10)  # nibabel's axis order, no transpose
    assert v.hu[3, 4, 5] == 3000.0
    np.testing.assert_allclose(v.voxel_to_lps([[3, 4, 5]])[0], (-16.0, -32.0, 50.0), atol=1e-9)
    np.testing.assert_array_equal(v.hu, hu)
    assert v.source == str(path)


def test_nifti_scl_slope_intercept_applied(tmp_path):
    raw = np.random.default_rng(1).integers(0, 2000, size=(6, 7, 8)).astype(np.int16)
    img = nib.Nifti1Image(raw, np.eye(4))
    img.header.set_slope_inter(2.0, -1024.0)
    nib.save(img, tmp_path / "scaled.nii")
    v = load_ct(tmp_path / "scaled.nii")
    np.testing.assert_array_equal(v.hu, 2.0 * raw.astype(np.float32) - 1024.0)


def test_nifti_trailing_singleton_4th_dim_squeezed(tmp_path):
    hu = ct_like((5, 6, 7))
    nib.save(nib.Nifti1Image(hu[..., None], np.eye(4)), tmp_path / "t1.nii.gz")
    np.testing.assert_array_equal(load_ct(tmp_path / "t1.nii.gz").hu, hu)
    nib.save(nib.Nifti1Image(np.stack([hu, hu], axis=-1), np.eye(4)), tmp_path / "t2.nii.gz")
    with raises_ct_error("t2.nii.gz", "4-d"):
        load_ct(tmp_path / "t2.nii.gz")


@pytest.mark.parametrize("integer", [True, False])
def test_save_nifti_round_trip_with_oblique_affine(tmp_path, integer):
    affine = oblique_affine()
    hu = ct_like((9, 7, 6), seed=3)
    if integer:
        hu = np.round(hu)
    vol = CTVolume(hu=hu, affine=affine, source="mem")
    path = save_nifti(vol, tmp_path / "rt.nii.gz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rt.nii.gz"]  # no temporary file left
    assert nib.load(path).get_data_dtype() == (np.int16 if integer else np.float32)
    back = load_ct(path)
    np.testing.assert_array_equal(back.hu, hu)
    # NIfTI-1 stores the sform in float32: the loaded affine is exactly the float32 values of the
    # RAS affine, flipped back to LPS ...
    stored = RAS_TO_LPS @ (RAS_TO_LPS @ affine).astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(back.affine, stored)
    # ... which is within 1e-6 mm of the original (offsets chosen float32-exact; direction entries
    # below 2.5 mm carry a relative float32 error of 6e-8, i.e. < 2e-7 mm)
    np.testing.assert_allclose(back.affine, affine, rtol=0, atol=1e-6)
    # the qform agrees with the sform (orthogonal directions), so any reader sees the same grid
    img = nib.load(path)
    np.testing.assert_allclose(img.get_qform(), img.get_sform(), atol=1e-4)


def test_save_nifti_rejects_other_suffix(tmp_path):
    vol = CTVolume(hu=ct_like((4, 4, 4)), affine=np.eye(4))
    with raises_ct_error("out.nrrd", ".nii"):
        save_nifti(vol, tmp_path / "out.nrrd")


# --------------------------------------------------------------------------------------------
# synthetic DICOM series
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.int16, np.uint16])
@pytest.mark.parametrize("oblique", [True, False])
def test_dicom_series_geometry_rescale_and_order(tmp_path, dtype, oblique):
    dirs = dict(row_dir=ROW_DIR_OBLIQUE, col_dir=COL_DIR_OBLIQUE) if oblique else \
        dict(row_dir=(1.0, 0.0, 0.0), col_dir=(0.0, 1.0, 0.0))
    truth = write_series(tmp_path / "series", dtype=dtype, **dirs)
    (tmp_path / "series" / "README.txt").write_text("not a DICOM file\n")  # skipped silently
    v = load_ct(tmp_path / "series")
    n, rows, cols = truth["stored"].shape
    assert v.shape == (cols, rows, n)  # i = column, j = row, k = slice
    row_sp, col_sp = truth["pixel_spacing"]
    for k in range(n):  # position order, not file or InstanceNumber order
        np.testing.assert_array_equal(v.hu[:, :, k], (2.0 * truth["stored"][k].astype(np.float64) - 1024.0).T)
        for i, j in [(0, 0), (cols - 1, 0), (0, rows - 1), (cols - 1, rows - 1), (2, 3)]:
            expect = truth["ipp"][k] + i * col_sp * truth["row_dir"] + j * row_sp * truth["col_dir"]
            np.testing.assert_allclose(v.voxel_to_lps([[i, j, k]])[0], expect, rtol=0, atol=1e-9)
    np.testing.assert_allclose(v.spacing_mm, (col_sp, row_sp, 2.5), atol=1e-9)
    along = truth["ipp"] @ truth["normal"]
    assert np.all(np.diff(along) > 0)  # slices written with increasing position along the normal


def test_dicom_series_uid_selects_one_of_two_series(tmp_path):
    folder = tmp_path / "two"
    a = write_series(folder / "a", n=4, seed=1)
    b = write_series(folder / "b", n=5, seed=2, ipp0=(0.0, 0.0, 0.0))
    for sub in ("a", "b"):
        for f in (folder / sub).iterdir():
            f.rename(folder / f"{sub}_{f.name}")
    with raises_ct_error("two", "series", a["uid"], b["uid"]):
        load_ct(folder)
    v = load_ct(folder, series_uid=b["uid"])
    assert v.shape == (5, 6, 5)
    np.testing.assert_allclose(v.affine[:3, 3], b["ipp"][0], atol=1e-9)
    with raises_ct_error("1.2.3.4", "no series"):
        load_ct(folder, series_uid="1.2.3.4")


def test_dicom_missing_middle_slice_is_an_error(tmp_path):
    write_series(tmp_path / "gap", n=8, skip=(4,))
    with raises_ct_error("gap", "missing slice", "expected spacing 2.5"):
        load_ct(tmp_path / "gap")


def test_dicom_inconsistent_pixel_spacing_is_an_error(tmp_path):
    write_series(tmp_path / "ps", spacing_of=(3, (0.7, 0.8)))
    with raises_ct_error("ps", "PixelSpacing"):
        load_ct(tmp_path / "ps")


def test_dicom_duplicate_position_is_an_error(tmp_path):
    write_series(tmp_path / "dup", n=5, seed=4)
    write_series(tmp_path / "other", n=5, seed=4)  # same positions (same seed/geometry)
    files = sorted((tmp_path / "dup").iterdir())
    uid = pydicom.dcmread(files[0]).SeriesInstanceUID
    extra = pydicom.dcmread(sorted((tmp_path / "other").iterdir())[0])
    extra.SeriesInstanceUID = uid
    extra.save_as(tmp_path / "dup" / "extra.dcm", enforce_file_format=True)
    with raises_ct_error("dup", "duplicate"):
        load_ct(tmp_path / "dup")


def test_dicom_folder_without_dicom_files_is_an_error(tmp_path):
    folder = tmp_path / "notdicom"
    folder.mkdir()
    (folder / "a.txt").write_text("hello")
    (folder / "b.dcm").write_bytes(b"\x00" * 300)
    with raises_ct_error("notdicom", "no DICOM"):
        load_ct(folder)


def test_dicom_single_slice_is_an_error(tmp_path):
    write_series(tmp_path / "one", n=3, skip=(0, 2))
    with raises_ct_error("one", "single slice"):
        load_ct(tmp_path / "one")


# --------------------------------------------------------------------------------------------
# real data
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real_series():
    folder = shared_file("ct/abdomen_dicom_series")
    return folder, load_ct(folder)


def test_real_dicom_series(real_series):
    folder, v = real_series
    assert v.shape == (512, 512, 20)
    np.testing.assert_allclose(v.spacing_mm, (0.9765625, 0.9765625, 2.0), atol=1e-6)
    assert np.mean(v.hu < -900) > 0.05 and np.min(v.hu) >= -1100  # air / outside the body near -1000
    assert np.count_nonzero(v.hu > 300) > 1000  # bone (spine, ribs)
    # truth from the headers, read here independently: the slice at the lowest z is k = 0
    files = sorted(folder.iterdir())
    headers = [pydicom.dcmread(f) for f in files]
    z = np.array([float(h.ImagePositionPatient[2]) for h in headers])
    assert np.all(v.affine[:3, :3] == np.diag([0.9765625, 0.9765625, 2.0]))
    for idx in (int(np.argmin(z)), int(np.argmax(z)), 7):
        h = headers[idx]
        k = int(round((z[idx] - z.min()) / 2.0))
        np.testing.assert_allclose(v.voxel_to_lps([[0, 0, k]])[0], [float(x) for x in h.ImagePositionPatient],
                                   atol=1e-9)
        expect = h.pixel_array.astype(np.float64) * float(h.RescaleSlope) + float(h.RescaleIntercept)
        np.testing.assert_array_equal(v.hu[:, :, k], expect.T)


def test_real_nifti_pelvis(pelvis_ct_path):
    v = load_ct(pelvis_ct_path)
    ras = nib.load(pelvis_ct_path).affine
    assert v.shape == (122, 101, 112)
    np.testing.assert_allclose(v.spacing_mm, 3.0, atol=1e-6)
    np.testing.assert_array_equal(np.sign(v.affine[:3, :3]), np.diag([-1, -1, 1]) @ np.sign(ras[:3, :3]))
    np.testing.assert_allclose(v.affine[:3, 3], ras[:3, 3] * (-1, -1, 1), atol=1e-9)
    assert -1100 <= np.percentile(v.hu, 1) < -900 and v.hu.max() > 1000


def test_real_chest_with_padding_value_is_accepted(chest_ct_path):
    # this scan fills the outside of its reconstruction circle with -2048 (its 1st percentile):
    # the single padding value is left out of the plausibility test, and the voxels are kept
    v = load_ct(chest_ct_path)
    assert v.shape == (512, 512, 133)
    assert np.mean(v.hu == -2048) > 0.01


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------


def test_missing_file(tmp_path):
    with raises_ct_error("nothere.nii.gz", "not found"):
        load_ct(tmp_path / "nothere.nii.gz")


def test_text_file_named_nifti(tmp_path):
    (tmp_path / "x.nii.gz").write_text("this is not an image\n")
    with raises_ct_error("x.nii.gz", "NIfTI"):
        load_ct(tmp_path / "x.nii.gz")


def test_truncated_gzip_nifti(tmp_path):
    nib.save(nib.Nifti1Image(ct_like((20, 20, 20)), np.eye(4)), tmp_path / "full.nii.gz")
    data = (tmp_path / "full.nii.gz").read_bytes()
    (tmp_path / "cut.nii.gz").write_bytes(data[: len(data) // 2])
    with raises_ct_error("cut.nii.gz", "NIfTI"):
        load_ct(tmp_path / "cut.nii.gz")
    (tmp_path / "garbage.nii.gz").write_bytes(gzip.compress(b"\x01" * 500))
    with raises_ct_error("garbage.nii.gz", "NIfTI"):
        load_ct(tmp_path / "garbage.nii.gz")


def test_2d_nifti(tmp_path):
    nib.save(nib.Nifti1Image(ct_like((16, 16, 3))[:, :, 0], np.eye(4)), tmp_path / "flat.nii")
    with raises_ct_error("flat.nii", "2-D"):
        load_ct(tmp_path / "flat.nii")
    nib.save(nib.Nifti1Image(ct_like((16, 16, 3))[:, :, :1], np.eye(4)), tmp_path / "slab.nii")
    with raises_ct_error("slab.nii", "2-D"):
        load_ct(tmp_path / "slab.nii")


def test_nan_nifti(tmp_path):
    hu = ct_like((6, 6, 6))
    hu[1, 2, 3] = np.nan
    nib.save(nib.Nifti1Image(hu, np.eye(4)), tmp_path / "nan.nii.gz")
    with raises_ct_error("nan.nii.gz", "NaN", "(1, 2, 3)"):
        load_ct(tmp_path / "nan.nii.gz")


def test_normalised_volume_is_not_hu(tmp_path):
    norm = np.random.default_rng(0).random((10, 10, 10)).astype(np.float32)  # values in 0..1
    nib.save(nib.Nifti1Image(norm, np.eye(4)), tmp_path / "norm.nii.gz")
    with raises_ct_error("norm.nii.gz", "not look like HU"):
        load_ct(tmp_path / "norm.nii.gz")
    with raises_ct_error("<array>", "not look like HU"):
        ct_from_array(norm, np.eye(4))


def test_hu_plausibility_criterion_edges():
    hu = ct_like((20, 20, 20))
    ct_from_array(hu, np.eye(4))  # a CT passes
    padded = hu.copy()
    padded[:6] = -3024.0  # 30 % out-of-field padding: one value below the plausible range
    v = ct_from_array(padded, np.eye(4))
    assert v.hu.min() == -3024.0  # kept, not replaced
    spread = np.where(padded < -2000, -3024.0 + np.arange(padded.size).reshape(padded.shape) % 50, padded)
    with raises_ct_error("not look like HU", "outside the plausible"):  # not one padding value
        ct_from_array(spread.astype(np.float32), np.eye(4))
    with raises_ct_error("not look like HU", "100 HU"):  # tissue only, 20 HU spread
        ct_from_array(np.random.default_rng(1).uniform(30, 50, (10, 10, 10)), np.eye(4))


def test_label_map_checks(tmp_path):
    affine_ras = RAS_TO_LPS @ oblique_affine()
    hu = ct_like((8, 9, 10))
    nib.save(nib.Nifti1Image(hu, affine_ras), tmp_path / "ct.nii.gz")
    lab = np.zeros((8, 9, 10), np.uint8)
    lab[2:5, 3:6, 4:7] = 3
    nib.save(nib.Nifti1Image(lab, affine_ras), tmp_path / "lab.nii.gz")
    v = load_ct(tmp_path / "ct.nii.gz", label_map=tmp_path / "lab.nii.gz")
    assert v.labels.dtype == np.int32
    np.testing.assert_array_equal(v.labels, lab)
    nib.save(nib.Nifti1Image(lab[:, :, :9], affine_ras), tmp_path / "short.nii.gz")
    with raises_ct_error("short.nii.gz", "shape"):
        load_ct(tmp_path / "ct.nii.gz", label_map=tmp_path / "short.nii.gz")
    moved = affine_ras.copy()
    moved[0, 3] += 0.01  # 10 micrometres > 1e-3 mm tolerance
    nib.save(nib.Nifti1Image(lab, moved), tmp_path / "moved.nii.gz")
    with raises_ct_error("moved.nii.gz", "affine") as e:
        load_ct(tmp_path / "ct.nii.gz", label_map=tmp_path / "moved.nii.gz")
    assert "\n" not in str(e.value)  # both affines on the one line
    nib.save(nib.Nifti1Image(lab.astype(np.float32) + 0.5, affine_ras), tmp_path / "frac.nii.gz")
    with raises_ct_error("frac.nii.gz", "integer"):
        load_ct(tmp_path / "ct.nii.gz", label_map=tmp_path / "frac.nii.gz")


def test_unsupported_file_type(tmp_path):
    (tmp_path / "scan.mha").write_bytes(b"ObjectType = Image\n")
    with raises_ct_error("scan.mha", "unsupported"):
        load_ct(tmp_path / "scan.mha")


# --------------------------------------------------------------------------------------------
# resampling
# --------------------------------------------------------------------------------------------


def test_resample_3mm_to_1p5mm_keeps_centre_and_original_samples():
    affine = oblique_affine(spacing=(3.0, 3.0, 3.0))
    hu = ct_like((10, 8, 6), seed=5)
    labels = np.zeros(hu.shape, np.int32)
    labels[2:6, 3:5, 1:4] = 7
    v = CTVolume(hu=hu, affine=affine, source="mem", labels=labels)
    r = resample(v, 1.5)
    assert r.shape == (19, 15, 11)  # (n - 1) * 3 / 1.5 + 1: span of voxel centres kept
    np.testing.assert_allclose(r.center_of_box_lps(), v.center_of_box_lps(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(r.spacing_mm, 1.5, rtol=0, atol=1e-12)
    np.testing.assert_allclose(r.affine[:3, :3], affine[:3, :3] / 2.0, atol=1e-12)  # same directions
    # new voxel 2 * (i, j, k) sits on original voxel (i, j, k): same LPS point, same HU (weights 0/1)
    ijk = np.argwhere(np.ones(hu.shape, bool))
    np.testing.assert_allclose(r.voxel_to_lps(2 * ijk), v.voxel_to_lps(ijk), atol=1e-9)
    np.testing.assert_allclose(r.hu[::2, ::2, ::2], hu, rtol=0, atol=1e-3)
    # midpoints are the average of their two neighbours (trilinear)
    np.testing.assert_allclose(r.hu[1::2, ::2, ::2], (hu[:-1] + hu[1:]) / 2, rtol=0, atol=1e-3)
    np.testing.assert_array_equal(r.labels[::2, ::2, ::2], labels)


def test_resample_reproduces_linear_ramp_along_x():
    affine = oblique_affine(spacing=(3.0, 3.0, 3.0))
    shape = (12, 10, 8)
    ijk = np.stack(np.meshgrid(*map(np.arange, shape), indexing="ij"), -1).reshape(-1, 3)
    x = affine[:3, :3] @ ijk.T + affine[:3, 3:4]
    ramp = (-200.0 + 2.5 * x[0]).reshape(shape)  # HU linear in LPS x (mm)
    v = CTVolume(hu=ramp.astype(np.float64), affine=affine, source="mem")
    r = resample(v, (1.1, 2.0, 1.7))
    np.testing.assert_allclose(r.spacing_mm, (1.1, 2.0, 1.7), atol=1e-12)
    np.testing.assert_allclose(r.center_of_box_lps(), v.center_of_box_lps(), atol=1e-6)
    new = np.stack(np.meshgrid(*map(np.arange, r.shape), indexing="ij"), -1).reshape(-1, 3)
    old = v.lps_to_voxel(r.voxel_to_lps(new))
    # rounding the counts to whole voxels puts some border samples just outside the original grid
    inside = np.all((old >= -1e-9) & (old <= np.array(shape) - 1 + 1e-9), axis=1)
    assert inside.mean() > 0.8
    expect = -200.0 + 2.5 * r.voxel_to_lps(new)[:, 0]
    # float32 storage of values up to ~1000 HU: 6e-5; 1e-3 leaves margin for interpolation rounding
    np.testing.assert_allclose(r.hu.reshape(-1)[inside], expect[inside], rtol=0, atol=1e-3)
    assert np.all(r.hu.reshape(-1)[~inside] == -1000.0)  # outside the original grid: air


def test_load_ct_resamples_ct_and_labels(tmp_path):
    affine_lps = oblique_affine(spacing=(3.0, 3.0, 3.0))
    hu = ct_like((8, 8, 8), seed=6)
    lab = np.zeros(hu.shape, np.int16)
    lab[2:4, 2:6, 3:5] = 2
    nib.save(nib.Nifti1Image(hu, RAS_TO_LPS @ affine_lps), tmp_path / "c.nii.gz")
    nib.save(nib.Nifti1Image(lab, RAS_TO_LPS @ affine_lps), tmp_path / "l.nii.gz")
    v = load_ct(tmp_path / "c.nii.gz", label_map=tmp_path / "l.nii.gz", resample_mm=1.0)
    assert v.shape == v.labels.shape == (22, 22, 22)
    np.testing.assert_array_equal(v.labels[::3, ::3, ::3], lab)
    np.testing.assert_allclose(v.hu[::3, ::3, ::3], hu, atol=1e-3)
    with raises_ct_error("resample_mm", "positive"):
        load_ct(tmp_path / "c.nii.gz", resample_mm=(1.0, -1.0, 1.0))


@pytest.mark.parametrize("kind", ["tiny spacing", "flat axis", "nan"])
def test_a_broken_affine_is_one_line_naming_the_file(tmp_path, kind):
    """A singular (or non-finite) voxel-to-patient affine is refused in one line, with the spacing
    it implies, from a file and from an array."""
    affine = {"tiny spacing": np.diag([1e-4, 1e-4, 1e-4, 1.0]), "flat axis": np.diag([1.0, 1.0, 0.0, 1.0]),
              "nan": np.diag([1.0, np.nan, 1.0, 1.0])}[kind]
    hu = ct_like((8, 9, 10))
    words = ("nan or infinite",) if kind == "nan" else ("singular", "spacing along i, j, k")
    if kind != "nan":  # nibabel refuses to write a NaN affine
        path = tmp_path / "broken.nii.gz"
        img = nib.Nifti1Image(hu, np.eye(4))
        img.set_sform(affine, code=2)  # the header nibabel reads the affine from
        img.set_qform(None, code=0)
        nib.save(img, path)
        with raises_ct_error("broken.nii.gz", *words) as e:
            load_ct(path)
        assert "\n" not in str(e.value)
    with raises_ct_error("arr", *words) as e:
        ct_from_array(hu, affine, source="arr")
    assert "\n" not in str(e.value)
