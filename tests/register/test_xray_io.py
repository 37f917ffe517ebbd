"""X-ray reading: DICOM round trips, MONOCHROME1, rescale, spacing tags, real compressed DICOM, Pillow
formats, bad inputs, the C-arm geometry for an image (explicit > DICOM tags > scene) with the source
of each value and the refusal of contradicting tags, intensity tags, and the writer's options."""

from __future__ import annotations

import json

import numpy as np
import pydicom
import pytest
from PIL import Image

from register.xray.geometry import GeometrySources, geometry_for, resolve_geometry
from register.xray.io import (
    INTENSITY_TAG_KEYS,
    XRayImage,
    XRayInputError,
    load_xray,
    write_xray_dicom,
)
from sim.projection.scene import load_scene
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


# ------------------------------------------------------------------ geometry sources (resolve_geometry)

ERMF = "EstimatedRadiographicMagnificationFactor"
SCENE = "scene 'cios_fusion' (assumed)"
CIOS = load_scene("cios_fusion").geometry  # SDD 1020, SOD 700, 1536 x 1536 x 0.194 mm


def _dcm(tmp_path, name="g.dcm", shape=(8, 8), pixel_spacing_mm=0.3, **kw):
    return write_xray_dicom(tmp_path / name, _ramp(*shape), pixel_spacing_mm=pixel_spacing_mm, **kw)


def _edit(path, **tags):
    """Set (value) or blank (None / "") tags of a written file with pydicom, then save it."""
    ds = pydicom.dcmread(path)
    for k, v in tags.items():
        setattr(ds, k, v)
    ds.save_as(path)
    return path


def test_sources_for_tag_scene_and_the_one_line_summary(tmp_path):
    x = load_xray(_dcm(tmp_path, sdd_mm=1020.0))
    g, src = resolve_geometry(x)
    assert isinstance(src, GeometrySources)
    assert (g.sdd_mm, g.sod_mm, g.pixel_spacing_mm) == (1020.0, CIOS.sod_mm, 0.3)
    assert (src.sdd_mm, src.sdd_source) == (1020.0, "DICOM DistanceSourceToDetector")
    assert (src.sod_mm, src.sod_source) == (700.0, SCENE)
    assert (src.pixel_spacing_mm, src.pixel_spacing_source) == (0.3, "DICOM ImagerPixelSpacing")
    assert src.assumed == ["sod_mm"]
    assert src.line() == (
        "geometry: SDD 1020 mm (DICOM DistanceSourceToDetector), SOD 700 mm (scene 'cios_fusion' "
        "(assumed)), pixel 0.300 mm (DICOM ImagerPixelSpacing)"
    )
    d = json.loads(json.dumps(src.to_dict()))
    assert d["sod_source"] == SCENE and d["assumed"] == ["sod_mm"] and d["pixel_spacing_mm"] == 0.3
    assert geometry_for(x) == g  # the thin wrapper gives the same geometry


def test_flags_override_tags_and_are_reported_as_flags(tmp_path):
    x = load_xray(_dcm(tmp_path, sdd_mm=1100.0, sod_mm=650.0, magnification_factor=1100 / 650))
    g, src = resolve_geometry(x, sdd_mm=900.0, sod_mm=450.0, pixel_spacing_mm=0.25)
    assert (g.sdd_mm, g.sod_mm, g.pixel_spacing_mm) == (900.0, 450.0, 0.25)
    sources = (src.sdd_source, src.sod_source, src.pixel_spacing_source)
    assert sources == ("flag --sdd", "flag --sod", "flag --pixel-spacing")
    assert src.assumed == []
    line = src.line()
    assert "\n" not in line and all(w in line for w in ("SDD 900 mm", "SOD 450 mm", "pixel 0.250 mm"))


def test_all_from_the_tags(tmp_path):
    x = load_xray(_dcm(tmp_path, sdd_mm=1100.0, sod_mm=650.0))
    _, src = resolve_geometry(x)
    assert (src.sdd_source, src.sod_source, src.pixel_spacing_source) == (
        "DICOM DistanceSourceToDetector", "DICOM DistanceSourceToPatient", "DICOM ImagerPixelSpacing")
    assert (src.sdd_mm, src.sod_mm, src.pixel_spacing_mm) == (1100.0, 650.0, 0.3) and src.assumed == []


def test_sod_derived_from_sdd_and_the_magnification_factor(tmp_path):
    x = load_xray(_dcm(tmp_path, sdd_mm=1000.0, magnification_factor=1.25))
    assert x.sod_mm is None  # the field keeps what the file says; the derivation is resolve_geometry's
    g, src = resolve_geometry(x)
    assert g.sod_mm == src.sod_mm == pytest.approx(1000.0 / 1.25, rel=1e-12)
    assert src.sod_source == "DICOM DistanceSourceToDetector / EstimatedRadiographicMagnificationFactor"
    assert src.assumed == []
    # an SDD from a flag (or the scene) is divided by the file's factor too, and says so
    _, s2 = resolve_geometry(x, sdd_mm=1200.0)
    assert s2.sod_mm == pytest.approx(960.0) and s2.sod_source == f"flag --sdd / DICOM {ERMF}"
    _, s3 = resolve_geometry(load_xray(_dcm(tmp_path, "m.dcm", magnification_factor=1.5)))
    assert s3.sod_mm == pytest.approx(CIOS.sdd_mm / 1.5) and s3.sod_source == f"{SCENE} / DICOM {ERMF}"
    assert s3.assumed == ["sdd_mm", "sod_mm"]


def test_detector_element_spacing_and_binning(tmp_path):
    x = load_xray(_dcm(tmp_path, "de.dcm", imager_pixel_spacing=False, detector_element_spacing_mm=0.15))
    assert x.pixel_spacing_mm is None and x.meta["geometry_tags"]["DetectorElementSpacing"] == [0.15, 0.15]
    _, src = resolve_geometry(x)
    assert (src.pixel_spacing_mm, src.pixel_spacing_source) == (0.15, "DICOM DetectorElementSpacing")
    # ImagerPixelSpacing = 2 x 2 binning of the elements: consistent, and preferred
    binned = _dcm(tmp_path, "bin.dcm", pixel_spacing_mm=0.3, detector_element_spacing_mm=0.15)
    _, s2 = resolve_geometry(load_xray(binned))
    assert (s2.pixel_spacing_mm, s2.pixel_spacing_source) == (0.3, "DICOM ImagerPixelSpacing")
    # within the tolerances: 0.5 % below the element pitch, 1 % from a multiple
    for ips in (0.14925, 0.303):
        resolve_geometry(load_xray(_dcm(tmp_path, "tol.dcm", pixel_spacing_mm=ips, detector_element_spacing_mm=0.15)))


def test_spacing_from_patient_plane_pixel_spacing_times_the_magnification_factor(tmp_path):
    imager, m = 0.3, 1.2
    path = _dcm(tmp_path, "ps.dcm", pixel_spacing_mm=imager, imager_pixel_spacing=False,
                patient_pixel_spacing_mm=imager / m, magnification_factor=m, sdd_mm=1000.0)
    ds = pydicom.dcmread(path)
    assert "ImagerPixelSpacing" not in ds and ds.PixelSpacingCalibrationType == "GEOMETRY"
    x = load_xray(path)
    assert x.meta["pixel_spacing_tag"] == "PixelSpacing"
    g, src = resolve_geometry(x)
    assert src.pixel_spacing_source == f"DICOM PixelSpacing x {ERMF}"
    assert g.pixel_spacing_mm == src.pixel_spacing_mm == pytest.approx(imager, rel=1e-9)
    assert src.sod_mm == pytest.approx(1000.0 / m)
    # without the calibration type the PixelSpacing is taken as it is
    _edit(path, PixelSpacingCalibrationType=None)
    _, s2 = resolve_geometry(load_xray(path))
    assert s2.pixel_spacing_source == "DICOM PixelSpacing" and s2.pixel_spacing_mm == pytest.approx(imager / m)
    # calibrated to the patient plane but no factor to undo it: used as it is, with a note
    _edit(path, PixelSpacingCalibrationType="GEOMETRY", EstimatedRadiographicMagnificationFactor=None)
    _, s3 = resolve_geometry(load_xray(path))
    assert s3.pixel_spacing_source == "DICOM PixelSpacing" and "PixelSpacingCalibrationType" in s3.notes[0]


def test_image_without_dicom_tags_offers_its_own_fields():
    x = XRayImage(np.ones((10, 20), np.float32), sdd_mm=1000.0, sod_mm=600.0, pixel_spacing_mm=0.4)
    _, src = resolve_geometry(x, scene=None)
    assert (src.sdd_source, src.sod_source, src.pixel_spacing_source) == (
        "XRayImage.sdd_mm", "XRayImage.sod_mm", "XRayImage.pixel_spacing_mm")


IPS_DES = ["ImagerPixelSpacing", "DetectorElementSpacing"]


@pytest.mark.parametrize(
    "tags, flags, words",
    [
        (dict(sdd_mm=800.0, sod_mm=900.0), {}, ["SOD 900", "DistanceSourceToPatient", "SDD 800", "DistanceSourceToDetector"]),
        (dict(sdd_mm=1000.0), dict(sod_mm=1200.0), ["flag --sod", "DICOM DistanceSourceToDetector"]),
        (dict(sdd_mm=1000.0, magnification_factor=1.0), {}, [ERMF, "DistanceSourceToDetector", ">="]),
        (dict(sdd_mm=1000.0, magnification_factor=0.8), {}, [ERMF, "< 1"]),
        (dict(sdd_mm=1000.0, sod_mm=500.0, magnification_factor=1.5), {},
         [ERMF, "DistanceSourceToDetector", "DistanceSourceToPatient", "25.0%"]),
        (dict(pixel_spacing_mm=0.14, detector_element_spacing_mm=0.15), {}, [*IPS_DES, "smaller"]),
        (dict(pixel_spacing_mm=0.148, detector_element_spacing_mm=0.15), {}, [*IPS_DES, "smaller"]),
        (dict(pixel_spacing_mm=0.2, detector_element_spacing_mm=0.15), {}, [*IPS_DES, "integer multiple"]),
        (dict(pixel_spacing_mm=0.31, detector_element_spacing_mm=0.15), {}, [*IPS_DES, "integer multiple"]),
    ],
    ids=["sod>=sdd-tags", "sod-flag>=sdd-tag", "ermf=1", "ermf<1", "ermf-vs-distances", "ips<des",
         "ips<des-1.3%", "ips-not-binning", "ips-binning-3.3%-off"],
)
def test_contradictions_raise_naming_both(tmp_path, tags, flags, words):
    spacing = tags.pop("pixel_spacing_mm", 0.3)
    x = load_xray(_dcm(tmp_path, pixel_spacing_mm=spacing, **tags))
    with pytest.raises(XRayInputError) as e:
        resolve_geometry(x, **flags)
    msg = str(e.value)
    assert "\n" not in msg and str(x.source) in msg
    for w in words:
        assert w in msg, (w, msg)


def test_a_flag_settles_a_contradiction_between_tags(tmp_path):
    x = load_xray(_dcm(tmp_path, "e.dcm", sdd_mm=1000.0, sod_mm=500.0, magnification_factor=1.5))
    g, src = resolve_geometry(x, sod_mm=1000.0 / 1.5)
    assert src.sod_source == "flag --sod" and src.sdd_source == "DICOM DistanceSourceToDetector"
    assert g.sod_mm == pytest.approx(666.6667, rel=1e-6)
    # 1 % off: not a contradiction
    resolve_geometry(load_xray(_dcm(tmp_path, "ok.dcm", sdd_mm=1000.0, sod_mm=500.0, magnification_factor=1.98)))
    y = load_xray(_dcm(tmp_path, "b.dcm", pixel_spacing_mm=0.2, detector_element_spacing_mm=0.15))
    _, s2 = resolve_geometry(y, pixel_spacing_mm=0.2)
    assert s2.pixel_spacing_source == "flag --pixel-spacing"


def test_empty_geometry_tags_are_absent_and_everything_comes_from_the_scene(tmp_path):
    path = _dcm(tmp_path, "empty.dcm", sdd_mm=1000.0, sod_mm=600.0, magnification_factor=1000 / 600,
                detector_element_spacing_mm=0.15, patient_pixel_spacing_mm=0.18)
    blank = ["DistanceSourceToDetector", "DistanceSourceToPatient", ERMF, "ImagerPixelSpacing",
             "DetectorElementSpacing", "PixelSpacing", "PixelSpacingCalibrationType"]
    _edit(path, **{k: None for k in blank})
    ds = pydicom.dcmread(path)
    assert all(k in ds and ds[k].is_empty for k in blank)  # present, but empty (as in raw files)
    x = load_xray(path)
    assert all(v is None for v in x.meta["geometry_tags"].values()) and x.meta["ignored_tags"] == []
    assert (x.sdd_mm, x.sod_mm, x.pixel_spacing_mm) == (None, None, None)
    g, src = resolve_geometry(x)
    assert src.assumed == ["sdd_mm", "sod_mm", "pixel_spacing_mm"]
    assert (src.sdd_source, src.sod_source, src.pixel_spacing_source) == (SCENE, SCENE, SCENE)
    assert (g.sdd_mm, g.sod_mm) == (CIOS.sdd_mm, CIOS.sod_mm)
    assert g.pixel_spacing_mm == pytest.approx(CIOS.detector_size_mm[1] / 8, rel=1e-12)


def test_invalid_tags_are_refused_by_name_unless_a_flag_gives_the_value(tmp_path):
    """A tag that is present but non-positive / non-finite is not replaced by the scene's value
    silently: the geometry is refused naming each tag and its flag, and the flags settle it."""
    path = _dcm(tmp_path, "neg.dcm", sdd_mm=1000.0, sod_mm=600.0, magnification_factor=1.5)
    _edit(path, DistanceSourceToDetector="-5", EstimatedRadiographicMagnificationFactor="0",
          ImagerPixelSpacing=["0", "0.3"])
    with pytest.warns(UserWarning):  # pydicom warns about the invalid DS value
        _edit(path, DistanceSourceToPatient="nan")
    x = load_xray(path)
    assert sorted(x.meta["ignored_tags"]) == sorted(
        ["DistanceSourceToDetector", "DistanceSourceToPatient", ERMF, "ImagerPixelSpacing"])
    assert x.meta["invalid_tags"]["DistanceSourceToDetector"] == "-5"
    assert x.meta["invalid_tags"]["ImagerPixelSpacing"] == "0\\0.3"
    with pytest.raises(XRayInputError) as e:
        resolve_geometry(x)
    msg = str(e.value)
    assert "\n" not in msg and "neg.dcm" in msg
    for piece in ("DistanceSourceToDetector = -5", "DistanceSourceToPatient", ERMF, "ImagerPixelSpacing = 0\\0.3",
                  "--sdd / --sod / --pixel-spacing"):
        assert piece in msg, piece
    with pytest.raises(XRayInputError, match="ImagerPixelSpacing") as e:  # one flag short
        resolve_geometry(x, sdd_mm=1000.0, sod_mm=600.0)
    assert "DistanceSourceTo" not in str(e.value)
    g, src = resolve_geometry(x, sdd_mm=1000.0, sod_mm=600.0, pixel_spacing_mm=0.3)
    assert (g.sdd_mm, g.sod_mm, g.pixel_spacing_mm) == (1000.0, 600.0, 0.3) and src.assumed == []


def test_an_image_built_by_hand_with_ignored_tags_is_refused_too():
    x = XRayImage(np.ones((8, 8), np.float32), source="hand", meta={"ignored_tags": ["PixelSpacing"]})
    with pytest.raises(XRayInputError, match="hand: invalid DICOM geometry tag PixelSpacing .*--pixel-spacing"):
        resolve_geometry(x)
    assert resolve_geometry(x, pixel_spacing_mm=0.2)[0].pixel_spacing_mm == 0.2


@pytest.mark.parametrize("tags, words", [
    (dict(Modality="CT", SOPClassUID="1.2.840.10008.5.1.4.1.1.2"), "a CT slice (Modality CT)"),
    (dict(Modality="OT", SOPClassUID="1.2.840.10008.5.1.4.1.1.2"), "a CT slice (SOP class 1.2.840.10008.5.1.4.1.1.2)"),
    (dict(Modality="MR"), "a slice of an MR volume"),
    (dict(Modality="OT", ImagePositionPatient=[0, 0, 0], SliceThickness="1.5"), "ImagePositionPatient, SliceThickness"),
])
def test_a_slice_of_a_volume_is_refused_as_an_x_ray(tmp_path, tags, words):
    path = _edit(_dcm(tmp_path, "slice.dcm"), **tags)
    with pytest.raises(XRayInputError) as e:
        load_xray(path)
    assert words in str(e.value) and "not a projection X-ray" in str(e.value) and "--ct" in str(e.value)


def test_an_x_ray_modality_with_position_tags_is_still_an_x_ray(tmp_path):
    path = _edit(_dcm(tmp_path, "dx.dcm"), ImagePositionPatient=[0, 0, 0], SliceThickness="1.5")
    assert load_xray(path).shape == (8, 8)  # Modality DX: a radiograph, whatever else it holds


def test_a_real_ct_slice_is_refused():
    series = shared_file("ct/abdomen_dicom_series")
    first = sorted(p for p in series.rglob("*") if p.is_file())[0]
    with pytest.raises(XRayInputError, match="a CT slice"):
        load_xray(first)


def test_a_nifti_volume_or_a_folder_is_not_taken_for_an_x_ray(tmp_path):
    (tmp_path / "ct.nii.gz").write_bytes(b"")
    with pytest.raises(XRayInputError, match="NIfTI volume .* --ct"):
        load_xray(tmp_path / "ct.nii.gz")
    with pytest.raises(XRayInputError, match="a folder"):
        load_xray(tmp_path)


# ------------------------------------------------------------------------------ intensity tags


@pytest.mark.parametrize("modality, sop", [("DX", "1.2.840.10008.5.1.4.1.1.1.1"), ("XA", "1.2.840.10008.5.1.4.1.1.7"),
                                           ("RF", "1.2.840.10008.5.1.4.1.1.7")])
def test_intensity_tags_round_trip(tmp_path, modality, sop):
    path = write_xray_dicom(tmp_path / "i.dcm", _ramp() % 4096, pixel_spacing_mm=0.3, bits_stored=12, modality=modality,
                            pixel_intensity_relationship="LOG", pixel_intensity_sign=-1,
                            presentation_lut_shape="IDENTITY", window=(2000.0, 3500.5))
    x = load_xray(path)
    t = x.meta["intensity_tags"]
    assert tuple(t) == INTENSITY_TAG_KEYS
    assert t == {
        "PhotometricInterpretation": "MONOCHROME2",
        "PresentationLUTShape": "IDENTITY",
        "PixelIntensityRelationship": "LOG",
        "PixelIntensityRelationshipSign": -1,
        "RescaleType": "US",
        "VOILUT": True,
        "WindowCenter": 2000.0,
        "WindowWidth": 3500.5,
        "Modality": modality,
        "PresentationIntentType": "FOR PRESENTATION",
        "BitsStored": 12,
        "SOPClassUID": sop,
    }
    assert json.loads(json.dumps(t)) == t and not x.meta["inverted"] and x.meta["inverted_by"] is None


def test_intensity_tags_absent_are_none_and_non_dicom_has_none(tmp_path):
    t = load_xray(_dcm(tmp_path, attenuation_bright=False)).meta["intensity_tags"]
    assert t["VOILUT"] is False and t["PresentationIntentType"] == "FOR PROCESSING" and t["BitsStored"] == 16
    for k in ("PresentationLUTShape", "PixelIntensityRelationship", "PixelIntensityRelationshipSign",
              "WindowCenter", "WindowWidth"):
        assert t[k] is None
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "z.png")
    np.save(tmp_path / "z.npy", np.zeros((4, 4)))
    assert load_xray(tmp_path / "z.png").meta["intensity_tags"] is None
    assert load_xray(tmp_path / "z.npy").meta["intensity_tags"] is None


def test_monochrome2_with_inverse_presentation_lut_loads_inverted(tmp_path):
    px = _ramp()
    m2 = load_xray(write_xray_dicom(tmp_path / "m2.dcm", px, pixel_spacing_mm=0.2))
    inv = load_xray(write_xray_dicom(tmp_path / "inv.dcm", px, pixel_spacing_mm=0.2, presentation_lut_shape="INVERSE"))
    assert inv.meta["inverted"] and inv.meta["inverted_by"] == "PresentationLUTShape INVERSE"
    np.testing.assert_array_equal(inv.pixels, m2.pixels.max() + m2.pixels.min() - m2.pixels)
    # MONOCHROME1 (+ INVERSE, as the DX IOD pairs them) is inverted once only
    m1 = load_xray(write_xray_dicom(tmp_path / "m1.dcm", px, pixel_spacing_mm=0.2, monochrome1=True,
                                    presentation_lut_shape="INVERSE"))
    assert m1.meta["inverted_by"] == "MONOCHROME1"
    np.testing.assert_array_equal(m1.pixels, inv.pixels)


def test_12_bit_round_trip_within_half_a_quantum(tmp_path):
    rng = np.random.default_rng(2)
    px = rng.uniform(-1.0, 3.0, (16, 20))
    path = write_xray_dicom(tmp_path / "b12.dcm", px, pixel_spacing_mm=0.5, bits_stored=12)
    ds = pydicom.dcmread(path)
    assert (ds.BitsAllocated, ds.BitsStored, ds.HighBit) == (16, 12, 11)
    assert ds.pixel_array.min() == 0 and ds.pixel_array.max() == 4095  # the automatic slope fills 12 bits
    x = load_xray(path)
    quantum = (px.max() - px.min()) / 4095
    assert np.abs(x.pixels - px).max() <= quantum / 2 + 1e-6
    assert x.meta["bits_stored"] == 12
    with pytest.raises(XRayInputError, match="12-bit"):
        write_xray_dicom(tmp_path / "big.dcm", np.full((4, 4), 5000, np.uint16), pixel_spacing_mm=0.5, bits_stored=12)


def test_writer_without_spacing_tags(tmp_path):
    ds = pydicom.dcmread(write_xray_dicom(tmp_path / "n.dcm", _ramp(4, 4), pixel_spacing_mm=None))
    assert not any(k in ds for k in ("ImagerPixelSpacing", "PixelSpacing", "DetectorElementSpacing", ERMF))
    with pytest.raises(XRayInputError, match="modality"):
        write_xray_dicom(tmp_path / "ct.dcm", _ramp(4, 4), pixel_spacing_mm=None, modality="CT")


# ------------------------------------------------------------------------- real DICOM: tags


def _real_dicoms():
    folder = shared_file(f"{PAED}/dicoms")
    paths = sorted(folder.glob("*.dcm"))
    if not paths:
        pytest.skip(f"no .dcm files in {folder}")
    return paths


def test_real_dicoms_intensity_tags_and_geometry_sources():
    for path in _real_dicoms():
        ds = pydicom.dcmread(path, stop_before_pixels=True)
        x = load_xray(path)
        t = x.meta["intensity_tags"]
        assert tuple(t) == INTENSITY_TAG_KEYS
        assert t["Modality"] == str(ds.Modality) and t["PhotometricInterpretation"] == str(ds.PhotometricInterpretation)
        assert t["SOPClassUID"] == str(ds.SOPClassUID) and t["BitsStored"] == int(ds.BitsStored)
        g, src = resolve_geometry(x)
        # what the file holds decides each source: these files have PixelSpacing only, no distances
        expect_sdd = "DICOM DistanceSourceToDetector" if ds.get("DistanceSourceToDetector") else SCENE
        assert src.sdd_source == expect_sdd
        if ds.get("DistanceSourceToPatient"):
            assert src.sod_source == "DICOM DistanceSourceToPatient"
        elif ds.get(ERMF):
            assert src.sod_source.endswith(ERMF)
        else:
            assert src.sod_source == SCENE
        if ds.get("ImagerPixelSpacing"):
            assert src.pixel_spacing_source == "DICOM ImagerPixelSpacing"
        elif ds.get("PixelSpacing") and not ds.get("PixelSpacingCalibrationType"):
            assert src.pixel_spacing_source == "DICOM PixelSpacing"
            assert src.pixel_spacing_mm == float(ds.PixelSpacing[1])
        assert (g.height, g.width) == x.shape and g.pixel_spacing_mm == src.pixel_spacing_mm
        line = src.line()
        assert line.startswith("geometry: SDD ") and "\n" not in line
        assert set(src.assumed) == {n for n, s in [("sdd_mm", src.sdd_source), ("sod_mm", src.sod_source),
                                                   ("pixel_spacing_mm", src.pixel_spacing_source)] if "(assumed)" in s}


def test_binning_averages_blocks_scales_the_pitch_and_keeps_the_centre():
    """XRayImage.binned: each output pixel the mean of its f x f block (a block-constant image
    comes back exactly); the pitch (and an anisotropic one in meta) times f; rows and columns that
    do not fill a block cut evenly, so the centre moves by at most half an original pixel; bad
    factors refused."""
    from register.xray.io import XRayImage, XRayInputError

    rng = np.random.default_rng(0)
    blocks = rng.uniform(0, 1, (7, 5)).astype(np.float32)
    img = XRayImage(np.repeat(np.repeat(blocks, 3, axis=0), 3, axis=1), pixel_spacing_mm=0.15, source="x",
                    meta={"pixel_spacing_rc_mm": [0.15, 0.2],
                          "geometry_tags": {"ImagerPixelSpacing": [0.15, 0.15], "DetectorElementSpacing": [0.15, 0.15],
                                            "DistanceSourceToDetector": 1000.0}})
    b = img.binned(3)
    tags = b.meta["geometry_tags"]
    assert tags["ImagerPixelSpacing"] == pytest.approx([0.45, 0.45]) and tags["DetectorElementSpacing"] == [0.15, 0.15]
    assert tags["DistanceSourceToDetector"] == 1000.0 and img.meta["geometry_tags"]["ImagerPixelSpacing"] == [0.15, 0.15]
    np.testing.assert_allclose(b.pixels, blocks, rtol=1e-6)
    assert b.pixel_spacing_mm == pytest.approx(0.45) and b.meta["pixel_spacing_rc_mm"] == pytest.approx([0.45, 0.6])
    assert b.meta["binned"] == 3 and img.binned(1) is img
    # 23 x 22 px by 4: 5 x 5 blocks from rows 1..20 and columns 1..20; centres 11 / 10.5 -> 10.5
    odd = XRayImage(np.arange(23 * 22, dtype=np.float32).reshape(23, 22))
    o = odd.binned(4)
    assert o.shape == (5, 5) and o.pixel_spacing_mm is None
    np.testing.assert_allclose(o.pixels[0, 0], odd.pixels[1:5, 1:5].mean())
    for bad in (0, 2.5, -1):
        with pytest.raises(XRayInputError, match="binning factor"):
            odd.binned(bad)
    with pytest.raises(XRayInputError, match="too small to bin by 20"):
        odd.binned(20)


def test_a_truncated_uncompressed_dicom_is_called_cut_short_not_a_missing_decoder(tmp_path):
    """An uncompressed DICOM cut inside its pixel data: the message says how many bytes it holds
    and needs, and blames no JPEG decoder."""
    from register.xray.io import XRayInputError, load_xray, write_xray_dicom

    p = write_xray_dicom(tmp_path / "a.dcm", np.random.default_rng(0).uniform(0, 1000, (64, 64)).astype(np.float32),
                         pixel_spacing_mm=0.3, sdd_mm=1000.0, sod_mm=700.0)
    cut = tmp_path / "cut.dcm"
    cut.write_bytes(p.read_bytes()[:-3000])
    with pytest.raises(XRayInputError) as e:
        load_xray(cut)
    msg = str(e.value)
    assert "holds 5192 bytes where 64 x 64 px of 16 bits need 8192: the file is cut short" in msg
    assert "JPEG" not in msg and "\n" not in msg
