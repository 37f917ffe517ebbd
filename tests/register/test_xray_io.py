"""X-ray reading: DICOM round trips, MONOCHROME1, rescale, spacing tags, real compressed DICOM, Pillow
formats, bad inputs, and the C-arm geometry for an image (explicit > DICOM tags > scene)."""

from __future__ import annotations

import numpy as np
import pydicom
import pytest
from PIL import Image

from register.xray_io import XRayImage, XRayInputError, geometry_for, load_xray, write_xray_dicom
from sim.scene import load_scene
from tests.conftest import shared_file

PAED = "xray/paediatric_ap_pelvis"


def _ramp(h=24, w=32, lo=100, step=37):
    """Integer test image with distinct values (uint16)."""
    return (lo + step * np.arange(h * w).reshape(h, w) % 60000).astype(np.uint16)


# ------------------------------------------------------------------------------------ DICOM


def test_dicom_round_trip_keeps_pixels_spacing_sdd_sod(tmp_path):
    px = _ramp()
    path = write_xray_dicom(tmp_path / "a.dcm", px, pixel_spacing_mm=0.3, sdd_mm=1000.0, sod_mm=600.0)
    x = load_xray(path)
    assert x.pixels.dtype == np.float32 and x.pixels.shape == (24, 32)
    np.testing.assert_array_equal(x.pixels, px.astype(np.float32))  # uint16, slope 1: exact
    assert (x.pixel_spacing_mm, x.sdd_mm, x.sod_mm) == (0.3, 1000.0, 600.0)
    assert x.meta["pixel_spacing_tag"] == "ImagerPixelSpacing" and x.meta["photometric"] == "MONOCHROME2"
    assert x.attenuation_bright and x.source == str(path)


def test_dicom_round_trip_of_float_pixels_within_half_a_quantum(tmp_path):
    rng = np.random.default_rng(1)
    px = rng.uniform(-3.0, 7.0, (16, 20))
    x = load_xray(write_xray_dicom(tmp_path / "f.dcm", px, pixel_spacing_mm=0.5))
    quantum = (px.max() - px.min()) / 65535  # the writer's automatic slope
    # half a quantum from rounding, plus float32 rounding of values up to 7
    assert np.abs(x.pixels - px).max() <= quantum / 2 + 1e-6
    assert x.sdd_mm is None and x.sod_mm is None


def test_monochrome1_loads_as_the_inverse_of_its_monochrome2_twin(tmp_path):
    px = _ramp()
    m2 = load_xray(write_xray_dicom(tmp_path / "m2.dcm", px, pixel_spacing_mm=0.2))
    m1 = load_xray(write_xray_dicom(tmp_path / "m1.dcm", px, pixel_spacing_mm=0.2, monochrome1=True))
    assert m1.meta["photometric"] == "MONOCHROME1" and m1.meta["inverted"]
    expected = float(px.max()) + float(px.min()) - px.astype(np.float64)
    np.testing.assert_array_equal(m1.pixels, expected.astype(np.float32))
    np.testing.assert_array_equal(m1.pixels, m2.pixels.max() + m2.pixels.min() - m2.pixels)


def test_rescale_slope_and_intercept_are_applied(tmp_path):
    stored = _ramp(10, 12)
    px = stored.astype(np.float64) * 0.5 - 100.0  # on the (0.5, -100) grid: exact round trip
    path = write_xray_dicom(tmp_path / "r.dcm", px, pixel_spacing_mm=0.4, rescale_slope=0.5, rescale_intercept=-100.0)
    ds = pydicom.dcmread(path)  # independent read of the raw stored values and tags
    assert float(ds.RescaleSlope) == 0.5 and float(ds.RescaleIntercept) == -100.0
    np.testing.assert_array_equal(ds.pixel_array, stored)
    x = load_xray(path)
    np.testing.assert_array_equal(x.pixels, (ds.pixel_array * 0.5 - 100.0).astype(np.float32))
    assert x.meta["rescale_slope"] == 0.5 and x.meta["rescale_intercept"] == -100.0


def test_imager_pixel_spacing_is_preferred_over_pixel_spacing(tmp_path):
    path = write_xray_dicom(tmp_path / "s.dcm", _ramp(8, 8), pixel_spacing_mm=0.3)
    ds = pydicom.dcmread(path)
    ds.PixelSpacing = [0.7, 0.7]  # e.g. calibrated to the patient plane
    ds.save_as(path)
    x = load_xray(path)
    assert x.pixel_spacing_mm == 0.3 and x.meta["pixel_spacing_tag"] == "ImagerPixelSpacing"
    del ds.ImagerPixelSpacing
    ds.save_as(path)
    x = load_xray(path)
    assert x.pixel_spacing_mm == 0.7 and x.meta["pixel_spacing_tag"] == "PixelSpacing"


def test_anisotropic_spacing_is_kept_out_and_geometry_asks_for_a_square_one(tmp_path):
    path = write_xray_dicom(tmp_path / "an.dcm", _ramp(8, 8), pixel_spacing_mm=0.3)
    ds = pydicom.dcmread(path)
    ds.ImagerPixelSpacing = [0.3, 0.4]
    ds.save_as(path)
    x = load_xray(path)
    assert x.pixel_spacing_mm is None and x.meta["pixel_spacing_rc_mm"] == [0.3, 0.4]
    with pytest.raises(XRayInputError, match="anisotropic"):
        geometry_for(x)
    assert geometry_for(x, pixel_spacing_mm=0.35).pixel_spacing_mm == 0.35


# ------------------------------------------------------------------------------- real DICOM


def test_real_paediatric_jpeg2000_rgb_dicom_loads_as_grey():
    path = shared_file(f"{PAED}/dicoms/331_DDH_1.dcm")
    ds = pydicom.dcmread(path)
    x = load_xray(path)
    assert x.pixels.shape == (331, 331) and x.pixels.dtype == np.float32
    assert x.pixel_spacing_mm == float(ds.PixelSpacing[0]) == 1.0  # the file has PixelSpacing only
    assert x.meta["pixel_spacing_tag"] == "PixelSpacing"
    assert x.meta["rgb_to_grey"] and x.meta["photometric"] == "RGB" and x.meta["transfer_syntax_uid"] == ds.file_meta.TransferSyntaxUID
    assert np.all(np.isfinite(x.pixels)) and x.pixels.std() > 5.0  # real anatomy, 8-bit values
    # grey stored as RGB: the grey image equals each decoded channel (pydicom's own decode)
    np.testing.assert_array_equal(x.pixels, ds.pixel_array[..., 1].astype(np.float32))
    assert x.sdd_mm is None and x.sod_mm is None


# dicoms/331_DDH_1.dcm holds the same pixels as 331_DDH_12.dcm and jpg/331_DDH_1.jpg shows another
# child (correlation 0.75), a mix-up in the source data; the other pairs are true twins.
@pytest.mark.parametrize("name", ["331_DDH_10", "331_DDH_12", "331_DDH_138"])
def test_real_dicom_matches_its_jpeg_twin(name):
    dcm = load_xray(shared_file(f"{PAED}/dicoms/{name}.dcm"))
    jpg = load_xray(shared_file(f"{PAED}/jpg/{name}.jpg"))
    assert jpg.pixels.shape == dcm.pixels.shape == (331, 331)
    assert jpg.pixel_spacing_mm is None and jpg.meta["rgb_to_grey"]
    # JPEG 2000 vs baseline JPEG of the same image: only compression differences
    assert np.corrcoef(dcm.pixels.ravel(), jpg.pixels.ravel())[0, 1] > 0.98
    assert np.abs(dcm.pixels - jpg.pixels).mean() < 3.0  # grey levels of 255


# ---------------------------------------------------------------------------- Pillow formats


def test_png_8_and_16_bit_grey_keep_their_values(tmp_path):
    a8 = (np.arange(20 * 30).reshape(20, 30) % 256).astype(np.uint8)
    a16 = (np.arange(20 * 30).reshape(20, 30) * 97 % 65536).astype(np.uint16)
    Image.fromarray(a8).save(tmp_path / "g8.png")
    Image.fromarray(a16).save(tmp_path / "g16.png")
    x8, x16 = load_xray(tmp_path / "g8.png"), load_xray(tmp_path / "g16.png")
    np.testing.assert_array_equal(x8.pixels, a8.astype(np.float32))
    np.testing.assert_array_equal(x16.pixels, a16.astype(np.float32))  # full 16-bit depth
    assert a16.max() > 255 and x16.pixels.max() == a16.max()
    assert x8.pixel_spacing_mm is None and x8.sdd_mm is None and x8.sod_mm is None


def test_rgb_png_with_equal_channels_becomes_grey_and_colour_is_refused(tmp_path):
    g = (np.arange(16 * 16).reshape(16, 16) % 256).astype(np.uint8)
    Image.fromarray(np.stack([g, g, g], -1)).save(tmp_path / "rgb.png")
    x = load_xray(tmp_path / "rgb.png")
    np.testing.assert_array_equal(x.pixels, g.astype(np.float32))
    assert x.meta["rgb_to_grey"]
    c = np.stack([g, g, 255 - g], -1)
    Image.fromarray(c).save(tmp_path / "colour.png")
    with pytest.raises(XRayInputError, match="grey") as e:
        load_xray(tmp_path / "colour.png")
    assert "colour.png" in str(e.value)


def test_float_tiff_keeps_values(tmp_path):
    a = np.linspace(-2.5, 7.25, 12 * 9, dtype=np.float32).reshape(12, 9)
    Image.fromarray(a).save(tmp_path / "f.tiff")
    np.testing.assert_array_equal(load_xray(tmp_path / "f.tiff").pixels, a)


# ------------------------------------------------------------------------------- bad inputs


def _no_pixel_data(tmp_path):
    p = write_xray_dicom(tmp_path / "nopix.dcm", _ramp(4, 4), pixel_spacing_mm=1.0)
    ds = pydicom.dcmread(p)
    del ds.PixelData
    ds.save_as(p)
    return p


def _nan_tiff(tmp_path):
    a = np.ones((8, 8), np.float32)
    a[3, 4] = np.nan
    p = tmp_path / "nan.tiff"
    Image.fromarray(a).save(p)
    return p


def _text_dcm(tmp_path):
    p = tmp_path / "notes.dcm"
    p.write_text("this is not a DICOM file\n" * 20)
    return p


def _one_d(tmp_path):
    p = tmp_path / "line.npy"
    np.save(p, np.arange(10.0))
    return p


def _three_d(tmp_path):
    p = tmp_path / "stack.npy"
    np.save(p, np.zeros((2, 5, 5)))
    return p


def _multi_frame(tmp_path):
    p = write_xray_dicom(tmp_path / "multi.dcm", _ramp(4, 4), pixel_spacing_mm=1.0)
    ds = pydicom.dcmread(p)
    ds.NumberOfFrames = 2
    ds.PixelData = ds.PixelData * 2
    ds.save_as(p)
    return p


def _palette(tmp_path):
    p = write_xray_dicom(tmp_path / "palette.dcm", _ramp(4, 4), pixel_spacing_mm=1.0)
    ds = pydicom.dcmread(p)
    ds.PhotometricInterpretation = "PALETTE COLOR"
    ds.save_as(p)
    return p


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda d: d / "missing.dcm", "not found"),
        (_text_dcm, "not a readable DICOM"),
        (_no_pixel_data, "no pixel data"),
        (_nan_tiff, "NaN"),
        (_one_d, "2-D"),
        (_three_d, "2-D"),
        (_multi_frame, "multi-frame"),
        (_palette, "photometric"),
    ],
    ids=["missing", "text-as-dcm", "no-pixel-data", "nan-tiff", "1d", "3d", "multi-frame", "palette"],
)
def test_bad_inputs_raise_xray_input_error_naming_the_file(tmp_path, make, words):
    path = make(tmp_path)
    with pytest.raises(XRayInputError) as e:
        load_xray(path)
    assert str(path) in str(e.value) and words in str(e.value)
    assert isinstance(e.value, ValueError)


def test_xray_image_rejects_bad_arrays_directly():
    with pytest.raises(XRayInputError, match="2-D"):
        XRayImage(np.zeros(5))
    with pytest.raises(XRayInputError, match="NaN"):
        XRayImage(np.full((3, 3), np.nan))


# --------------------------------------------------------------------------------- geometry


def test_geometry_uses_dicom_tags_and_explicit_values_override(tmp_path):
    x = load_xray(write_xray_dicom(tmp_path / "g.dcm", _ramp(30, 40), pixel_spacing_mm=0.3, sdd_mm=1100.0, sod_mm=650.0))
    g = geometry_for(x)
    assert (g.sdd_mm, g.sod_mm, g.pixel_spacing_mm, g.height, g.width) == (1100.0, 650.0, 0.3, 30, 40)
    assert g.principal_point == (19.5, 14.5)  # image centre, (W-1)/2, (H-1)/2
    g2 = geometry_for(x, sdd_mm=900.0, sod_mm=500.0, pixel_spacing_mm=0.25)
    assert (g2.sdd_mm, g2.sod_mm, g2.pixel_spacing_mm) == (900.0, 500.0, 0.25)
    # resampled detector keeps the physical extent (H s, W s)
    g3 = geometry_for(x, size=(15, 20))
    assert (g3.height, g3.width) == (15, 20)
    np.testing.assert_allclose(g3.detector_size_mm, g.detector_size_mm, rtol=1e-12)
    with pytest.raises(XRayInputError, match="size"):
        geometry_for(x, size=(15, 15))


def test_geometry_falls_back_to_the_scene_for_missing_tags(tmp_path):
    scene = load_scene("cios_fusion").geometry
    x = load_xray(write_xray_dicom(tmp_path / "nodist.dcm", _ramp(8, 8), pixel_spacing_mm=0.3))
    g = geometry_for(x)
    assert (g.sdd_mm, g.sod_mm, g.pixel_spacing_mm) == (scene.sdd_mm, scene.sod_mm, 0.3)


def test_png_geometry_from_a_scene_of_matching_aspect(tmp_path):
    scene = load_scene("cios_fusion").geometry  # square 1536 x 1536 detector, 0.194 mm
    Image.fromarray(np.zeros((256, 256), np.uint8) + np.arange(256, dtype=np.uint8)).save(tmp_path / "sq.png")
    g = geometry_for(load_xray(tmp_path / "sq.png"))
    assert (g.height, g.width, g.sdd_mm, g.sod_mm) == (256, 256, scene.sdd_mm, scene.sod_mm)
    # the image covers the whole scene detector: same physical width
    assert g.pixel_spacing_mm == pytest.approx(scene.width * scene.pixel_spacing_mm / 256, rel=1e-12)
    np.testing.assert_allclose(g.detector_size_mm, scene.detector_size_mm, rtol=1e-12)


def test_missing_geometry_names_the_missing_value(tmp_path):
    Image.fromarray(np.arange(100 * 200, dtype=np.uint16).reshape(100, 200)).save(tmp_path / "wide.png")
    x = load_xray(tmp_path / "wide.png")
    with pytest.raises(XRayInputError, match="pixel_spacing_mm") as e:
        geometry_for(x)  # 1:2 image vs the square scene detector
    assert "wide.png" in str(e.value)
    assert geometry_for(x, pixel_spacing_mm=0.5).pixel_spacing_mm == 0.5
    with pytest.raises(XRayInputError, match="sdd_mm"):
        geometry_for(x, scene=None, pixel_spacing_mm=0.5)
    with pytest.raises(XRayInputError, match="sod_mm"):
        geometry_for(x, scene=None, pixel_spacing_mm=0.5, sdd_mm=1000.0)
    g = geometry_for(x, scene=None, pixel_spacing_mm=0.5, sdd_mm=1000.0, sod_mm=700.0)
    assert (g.height, g.width) == (100, 200)
