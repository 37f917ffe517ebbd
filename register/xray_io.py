"""Reading real X-ray images (DICOM, PNG, TIFF, JPEG, NumPy) and the C-arm geometry for them.

Pixel convention of :class:`XRayImage` ("display-like"):

* ``pixels`` are the stored values after the DICOM modality rescale (``value * RescaleSlope +
  RescaleIntercept``); for ``MONOCHROME2`` (and for grey PNG / TIFF / JPEG / ``.npy``) they are kept
  as they are, for ``MONOCHROME1`` they are inverted as ``max + min - value`` (the image's own
  extremes, after rescale). In both cases a **larger value is displayed brighter**; the value range
  is unchanged by the inversion.
* Whether bone (attenuation) is bright in ``pixels`` is a separate flag, ``attenuation_bright``.
  It is ``True`` for radiographs prepared for display (DICOM ``PresentationIntentType`` "FOR
  PRESENTATION" or absent, and every PNG / TIFF / JPEG / ``.npy``), ``False`` for DICOM "FOR
  PROCESSING" images, which hold raw detector values that grow with the transmitted radiation
  (bone dark). Registration compares ``pixels`` with DRRs (line integrals, bone bright); use
  ``register.preprocess`` (``LogCorrect`` for transmission images, ``Invert`` where needed).

Colour: grey stored as RGB (three equal channels, like the paediatric test files) becomes grey
(the channel mean); a coloured image is an error asking for a grey image.

Geometry (:func:`geometry_for`): explicit arguments > DICOM tags > the scene's values.
Pixel spacing is read from ``ImagerPixelSpacing`` (the detector plane, which is what the C-arm
model needs) and only when that is absent from ``PixelSpacing`` (which a DX/CR file may calibrate
to the patient plane); ``meta["pixel_spacing_tag"]`` says which. Anisotropic spacing is kept out
of ``pixel_spacing_mm`` (``None``, the pair in ``meta["pixel_spacing_rc_mm"]``) and
:func:`geometry_for` then asks for an explicit square spacing.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sim.atomic import atomic_path
from sim.geometry import CArmGeometry

__all__ = ["XRayInputError", "XRayImage", "load_xray", "geometry_for", "write_xray_dicom"]

#: Relative tolerance for treating a (row, column) spacing pair as square.
_SQUARE_RTOL = 1e-4
#: RGB channels count as equal (grey stored as RGB) when they differ by at most this fraction
#: of the image's value range (1 grey level of 8 bits ~ 0.4 %; lossy codecs may add +-1).
_GREY_RTOL = 0.01

_DX_PRESENTATION_UID = "1.2.840.10008.5.1.4.1.1.1.1"  # Digital X-Ray Image Storage - For Presentation
_DX_PROCESSING_UID = "1.2.840.10008.5.1.4.1.1.1.1.1"  # Digital X-Ray Image Storage - For Processing
_PILLOW_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp"}


class XRayInputError(ValueError):
    """An X-ray file or its geometry cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class XRayImage:
    """A grey X-ray image and what its file says about the acquisition.

    Attributes:
        pixels: ``(H, W)`` float32, finite; larger = brighter display (see the module docstring).
        attenuation_bright: whether bone / attenuation is bright in ``pixels``.
        pixel_spacing_mm: square detector pixel pitch in mm, or ``None`` when the file gives none
            (or gives an anisotropic one).
        sdd_mm: source-to-detector distance in mm (DICOM ``DistanceSourceToDetector``) or ``None``.
        sod_mm: source-to-patient (isocentre) distance in mm (``DistanceSourceToPatient``) or ``None``.
        source: the file it was read from.
        meta: JSON-serialisable facts: ``format``, ``modality``, ``photometric``,
            ``transfer_syntax``, ``pixel_spacing_tag``, ``rescale_slope`` / ``rescale_intercept``,
            ``inverted`` (MONOCHROME1), ``rgb_to_grey``, ...
    """

    pixels: np.ndarray
    attenuation_bright: bool = True
    pixel_spacing_mm: float | None = None
    sdd_mm: float | None = None
    sod_mm: float | None = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "pixels", _check_pixels(self.pixels, self.source or "pixels"))
        for name in ("pixel_spacing_mm", "sdd_mm", "sod_mm"):
            v = getattr(self, name)
            if v is not None:
                v = float(v)
                if not (math.isfinite(v) and v > 0):
                    raise XRayInputError(f"{self.source or 'XRayImage'}: {name} must be a positive number of mm, got {v}")
                object.__setattr__(self, name, v)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` in pixels."""
        return int(self.pixels.shape[0]), int(self.pixels.shape[1])


# --------------------------------------------------------------------------------------------
# Pixel checks shared by every reader
# --------------------------------------------------------------------------------------------


def _check_pixels(arr: object, source: str) -> np.ndarray:
    """``(H, W)`` finite numeric -> float32 copy, or :class:`XRayInputError` naming ``source``."""
    a = np.asarray(arr)
    if a.dtype.kind not in "uif" or a.dtype == np.bool_:
        raise XRayInputError(f"{source}: pixel data must be numeric, got dtype {a.dtype}")
    if a.ndim != 2:
        raise XRayInputError(f"{source}: expected a 2-D grey image (H, W), got an array of shape {a.shape}")
    if a.shape[0] < 2 or a.shape[1] < 2:
        raise XRayInputError(f"{source}: image of {a.shape[0]} x {a.shape[1]} pixels is too small (need >= 2 x 2)")
    a = a.astype(np.float32)
    if not np.all(np.isfinite(a)):
        n = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        raise XRayInputError(f"{source}: {n} pixel(s) are NaN or infinite")
    return a


def _rgb_to_grey(rgb: np.ndarray, source: str) -> np.ndarray:
    """``(H, W, 3)`` with equal channels -> ``(H, W)`` channel mean; coloured -> error."""
    c = rgb.astype(np.float64)
    span = float(c.max() - c.min()) if c.size else 0.0
    diff = max(float(np.abs(c[..., 0] - c[..., 1]).max()), float(np.abs(c[..., 0] - c[..., 2]).max()))
    if diff > max(1.0, _GREY_RTOL * span):
        raise XRayInputError(
            f"{source}: a colour image (RGB channels differ by up to {diff:g}); a grey image is needed "
            f"(convert it to grey first)"
        )
    return c.mean(axis=-1)


# --------------------------------------------------------------------------------------------
# Readers
# --------------------------------------------------------------------------------------------


def load_xray(path: str | os.PathLike) -> XRayImage:
    """Read an X-ray: DICOM (any transfer syntax pydicom can decode here), PNG/TIFF/JPEG/BMP, ``.npy``.

    The reader is chosen by content (DICOM "DICM" marker) and suffix. PNG/TIFF/JPEG keep their bit
    depth (16-bit PNG/TIFF and float TIFF at full depth) and carry no geometry (``None`` fields).
    DICOM: rescale slope/intercept applied, MONOCHROME1 inverted, multi-frame rejected.
    Raises :class:`XRayInputError` naming the file for a missing file, an unreadable / non-image
    file, missing pixel data, arrays that are not 2-D, NaN / infinite pixels, an unsupported
    photometric interpretation or a colour image.
    """
    p = Path(path)
    src = str(p)
    if not p.exists():
        raise XRayInputError(f"{src}: file not found")
    if not p.is_file():
        raise XRayInputError(f"{src}: not a file")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        return _load_npy(p)
    with open(p, "rb") as fh:
        head = fh.read(132)
    if head[128:132] == b"DICM" or suffix in (".dcm", ".dicom"):
        return _load_dicom(p)
    if suffix in _PILLOW_SUFFIXES:
        return _load_pillow(p)
    # Unknown suffix: try an image library first, then a DICOM file without preamble.
    try:
        return _load_pillow(p)
    except XRayInputError as pil_error:
        try:
            return _load_dicom(p)
        except XRayInputError:
            raise pil_error from None


def _load_npy(p: Path) -> XRayImage:
    src = str(p)
    try:
        a = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise XRayInputError(f"{src}: not a readable .npy array ({e})") from None
    return XRayImage(_check_pixels(a, src), True, None, None, None, src, {"format": "npy", "dtype": str(a.dtype)})


def _load_pillow(p: Path) -> XRayImage:
    from PIL import Image, UnidentifiedImageError

    src = str(p)
    try:
        im = Image.open(p)
        im.load()
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise XRayInputError(f"{src}: not a readable image file ({type(e).__name__}: {e})") from None
    with im:
        n_frames = getattr(im, "n_frames", 1)
        if n_frames > 1:
            raise XRayInputError(f"{src}: {n_frames} frames/pages; a single 2-D image is needed")
        mode = im.mode
        meta: dict[str, Any] = {"format": (im.format or "").lower(), "mode": mode}
        rgb_to_grey = False
        if mode in ("1", "L", "I", "F") or mode.startswith("I;16"):
            a = np.asarray(im)
        elif mode in ("LA", "RGBA", "P", "PA", "RGB", "CMYK", "YCbCr", "LAB", "HSV"):
            if "A" in mode:
                alpha = np.asarray(im.getchannel("A"))
                if alpha.min() < 255:
                    raise XRayInputError(f"{src}: image has transparency (mode {mode}); a grey image is needed")
            if mode in ("LA",):
                a = np.asarray(im.getchannel("L"))
            else:
                a = _rgb_to_grey(np.asarray(im.convert("RGB")), src)
                rgb_to_grey = True
        else:
            raise XRayInputError(f"{src}: unsupported image mode {mode!r}; a grey image is needed")
    meta["rgb_to_grey"] = rgb_to_grey
    meta["dtype"] = str(np.asarray(a).dtype)
    return XRayImage(_check_pixels(a, src), True, None, None, None, src, meta)


def _ds_float(ds: Any, keyword: str) -> float | None:
    v = ds.get(keyword)
    if v is None or v == "":
        return None
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def _load_dicom(p: Path) -> XRayImage:
    import pydicom
    from pydicom.errors import InvalidDicomError

    src = str(p)
    forced = False
    try:
        try:
            ds = pydicom.dcmread(p)
        except InvalidDicomError:
            forced = True  # no 128-byte preamble + "DICM": old-style files still parse
            ds = pydicom.dcmread(p, force=True)
    except Exception as e:  # pydicom raises many types on garbage input; report them as one
        raise XRayInputError(f"{src}: not a readable DICOM file ({type(e).__name__}: {e})") from None
    if "PixelData" not in ds:
        if forced:
            raise XRayInputError(f"{src}: not a readable DICOM file (no DICOM header and no pixel data)")
        raise XRayInputError(f"{src}: not a DICOM image (no pixel data)")
    frames = int(ds.get("NumberOfFrames", 1) or 1)
    if frames > 1:
        raise XRayInputError(f"{src}: multi-frame DICOM ({frames} frames); a single X-ray image is needed")
    photometric = str(ds.get("PhotometricInterpretation", "")).strip().upper()
    supported = ("MONOCHROME1", "MONOCHROME2", "RGB", "YBR_FULL", "YBR_FULL_422", "YBR_ICT", "YBR_RCT")
    if photometric not in supported:
        raise XRayInputError(
            f"{src}: unsupported photometric interpretation {photometric or '(missing)'!r}; "
            f"supported: {', '.join(supported)}"
        )
    tsyntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    try:
        arr = ds.pixel_array  # pydicom 3 converts YBR colour spaces to RGB here
    except Exception as e:  # decoder plugins raise RuntimeError / NotImplementedError / ValueError
        name = getattr(tsyntax, "name", str(tsyntax))
        raise XRayInputError(
            f"{src}: cannot decode the pixel data (transfer syntax {name}): {type(e).__name__}: {e}. "
            f"JPEG 2000 / JPEG-LS / lossless JPEG need a pydicom decoder plugin (Pillow with OpenJPEG, "
            f"pylibjpeg-openjpeg, pylibjpeg-libjpeg or python-gdcm)"
        ) from None
    arr = np.asarray(arr)
    stored_dtype = str(arr.dtype)
    samples = int(ds.get("SamplesPerPixel", 1) or 1)
    rgb_to_grey = False
    if samples == 3:
        if arr.ndim != 3 or arr.shape[-1] != 3:
            raise XRayInputError(f"{src}: 3 samples per pixel but pixel array of shape {arr.shape}")
        arr = _rgb_to_grey(arr, src)
        rgb_to_grey = True
    elif samples != 1:
        raise XRayInputError(f"{src}: {samples} samples per pixel; a grey image is needed")
    if arr.ndim != 2:
        raise XRayInputError(f"{src}: expected a 2-D image, got a pixel array of shape {arr.shape}")

    slope = float(ds.get("RescaleSlope", 1.0) or 1.0)
    intercept = float(ds.get("RescaleIntercept", 0.0) or 0.0)
    values = arr.astype(np.float64) * slope + intercept
    inverted = photometric == "MONOCHROME1"
    if inverted:
        finite = values[np.isfinite(values)]
        if finite.size:
            values = (finite.max() + finite.min()) - values
    pixels = _check_pixels(values, src)

    spacing, spacing_tag, spacing_rc = None, None, None
    for tag in ("ImagerPixelSpacing", "PixelSpacing"):
        v = ds.get(tag)
        if v is not None and len(v) == 2:
            rc = (float(v[0]), float(v[1]))
            if all(math.isfinite(x) and x > 0 for x in rc):
                spacing_tag, spacing_rc = tag, rc
                if abs(rc[0] - rc[1]) <= _SQUARE_RTOL * max(rc):
                    spacing = 0.5 * (rc[0] + rc[1])
                break
    sdd = _ds_float(ds, "DistanceSourceToDetector")
    sod = _ds_float(ds, "DistanceSourceToPatient")
    intent = str(ds.get("PresentationIntentType", "")).strip().upper()
    meta: dict[str, Any] = {
        "format": "dicom",
        "modality": str(ds.get("Modality", "")),
        "photometric": photometric,
        "transfer_syntax": getattr(tsyntax, "name", None) if tsyntax else None,
        "transfer_syntax_uid": str(tsyntax) if tsyntax else None,
        "presentation_intent": intent or None,
        "pixel_spacing_tag": spacing_tag,
        "pixel_spacing_rc_mm": list(spacing_rc) if spacing_rc else None,
        "pixel_spacing_anisotropic": bool(spacing_rc is not None and spacing is None),
        "sdd_tag": "DistanceSourceToDetector" if sdd is not None else None,
        "sod_tag": "DistanceSourceToPatient" if sod is not None else None,
        "rescale_slope": slope,
        "rescale_intercept": intercept,
        "inverted": inverted,
        "rgb_to_grey": rgb_to_grey,
        "stored_dtype": stored_dtype,
    }
    return XRayImage(pixels, intent != "FOR PROCESSING", spacing, sdd, sod, src, meta)


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def _positive(value: object, name: str) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise XRayInputError(f"{name}: expected a number of mm, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise XRayInputError(f"{name}: must be a positive finite number of mm, got {value!r}")
    return v


def geometry_for(
    xray: XRayImage,
    scene: str | os.PathLike | None = "cios_fusion",
    *,
    size: tuple[int, int] | None = None,
    sdd_mm: float | None = None,
    sod_mm: float | None = None,
    pixel_spacing_mm: float | None = None,
) -> CArmGeometry:
    """The C-arm geometry of ``xray``'s detector, optionally resampled to ``size = (H, W)`` pixels.

    Each of SDD, SOD (mm) and the pixel spacing (mm) comes from the first of: the explicit argument,
    the image's DICOM tags, the scene (``None`` = no scene). The detector has the image's own
    ``H x W`` pixels and the default principal point (the image centre). Spacing fallback from the
    scene: ``scene detector width (mm) / W``, allowed only when the image's aspect ratio ``H / W``
    matches the scene detector's to within one pixel (the image then covers the whole detector);
    otherwise, or with no scene, an error names the missing value. ``size`` keeps the physical
    extent (``CArmGeometry.resized``) and must keep the aspect ratio.
    """
    if not isinstance(xray, XRayImage):
        raise XRayInputError(f"xray: expected an XRayImage, got {type(xray).__name__}")
    src = xray.source or "X-ray image"
    H, W = xray.shape
    sc = None
    if scene is not None:
        from sim.scene import load_scene

        sc = load_scene(scene).geometry

    def pick(name: str, explicit: object, tag: float | None, scene_value: float | None) -> float:
        if explicit is not None:
            return _positive(explicit, name)
        if tag is not None:
            return tag
        if scene_value is not None:
            return scene_value
        raise XRayInputError(
            f"{src}: no {name} - the image has none and no scene was given; pass {name} explicitly "
            f"(or a scene)"
        )

    sdd = pick("sdd_mm", sdd_mm, xray.sdd_mm, sc.sdd_mm if sc else None)
    sod = pick("sod_mm", sod_mm, xray.sod_mm, sc.sod_mm if sc else None)

    if pixel_spacing_mm is not None:
        spacing = _positive(pixel_spacing_mm, "pixel_spacing_mm")
    elif xray.pixel_spacing_mm is not None:
        spacing = xray.pixel_spacing_mm
    elif xray.meta.get("pixel_spacing_anisotropic"):
        raise XRayInputError(
            f"{src}: no usable pixel_spacing_mm - {xray.meta.get('pixel_spacing_tag')} is anisotropic "
            f"{xray.meta.get('pixel_spacing_rc_mm')} mm (row, col); pass a square pixel_spacing_mm "
            f"after resampling the image to square pixels"
        )
    elif sc is not None:
        scene_aspect = sc.height / sc.width
        if abs(H / W - scene_aspect) * min(H, W) > 1.0:
            raise XRayInputError(
                f"{src}: no pixel_spacing_mm - the image has none and its {H} x {W} pixels do not "
                f"match the aspect of the scene detector ({sc.height} x {sc.width}); pass "
                f"pixel_spacing_mm explicitly"
            )
        spacing = sc.detector_size_mm[1] / W
    else:
        raise XRayInputError(
            f"{src}: no pixel_spacing_mm - the image has none and no scene was given; pass "
            f"pixel_spacing_mm explicitly (or a scene)"
        )
    if not 0 < sod < sdd:
        raise XRayInputError(
            f"{src}: geometry needs 0 < sod_mm < sdd_mm, got sod_mm={sod:g}, sdd_mm={sdd:g} "
            f"(explicit > DICOM tags > scene)"
        )
    geom = CArmGeometry(sdd_mm=sdd, sod_mm=sod, height=H, width=W, pixel_spacing_mm=spacing)
    if size is not None:
        try:
            h, w = (int(size[0]), int(size[1]))
        except (TypeError, ValueError, IndexError):
            raise XRayInputError(f"size: expected (height, width) in pixels, got {size!r}") from None
        if (h, w) != (H, W):
            try:
                geom = geom.resized(h, w)
            except ValueError as e:
                raise XRayInputError(f"size: {e}") from None
    return geom


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


def write_xray_dicom(
    path: str | os.PathLike,
    pixels: np.ndarray,
    *,
    pixel_spacing_mm: float,
    sdd_mm: float | None = None,
    sod_mm: float | None = None,
    monochrome1: bool = False,
    rescale_slope: float | None = None,
    rescale_intercept: float | None = None,
    attenuation_bright: bool = True,
) -> Path:
    """Write a minimal valid single-frame DX DICOM (explicit VR little endian, uint16), atomically.

    ``pixels``: ``(H, W)`` real values (what :func:`load_xray` returns for MONOCHROME2). Stored
    values are ``round((pixels - intercept) / slope)`` in ``[0, 65535]``. Defaults: integer input
    -> slope 1, intercept 0 (stored as given); float input -> ``intercept = min``, ``slope = (max -
    min) / 65535`` (full 16-bit range; round trip within ``slope / 2``). ``monochrome1=True`` writes
    the same stored values tagged MONOCHROME1 (a viewer and :func:`load_xray` show them inverted).
    Tags: ``ImagerPixelSpacing`` (square, mm), ``DistanceSourceToDetector`` /
    ``DistanceSourceToPatient`` (mm, when given), ``PresentationIntentType`` "FOR PRESENTATION"
    (``attenuation_bright``) or "FOR PROCESSING". Returns the path.
    """
    import pydicom
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, PYDICOM_IMPLEMENTATION_UID, generate_uid

    path = Path(path)
    a = np.asarray(pixels)
    name = f"pixels for {path}"
    if a.dtype.kind not in "uif" or a.dtype == np.bool_:
        raise XRayInputError(f"{name}: must be numeric, got dtype {a.dtype}")
    if a.ndim != 2:
        raise XRayInputError(f"{name}: expected (H, W), got shape {a.shape}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise XRayInputError(f"{name}: contains NaN or infinite values")
    spacing = _positive(pixel_spacing_mm, "pixel_spacing_mm")
    if np.asarray(pixels).dtype.kind in "ui":
        slope = 1.0 if rescale_slope is None else float(rescale_slope)
        intercept = 0.0 if rescale_intercept is None else float(rescale_intercept)
    else:
        lo, hi = float(a.min()), float(a.max())
        intercept = lo if rescale_intercept is None else float(rescale_intercept)
        if rescale_slope is None:
            top = hi - intercept
            slope = top / 65535.0 if top > 0 else 1.0
        else:
            slope = float(rescale_slope)
    if not (math.isfinite(slope) and slope != 0 and math.isfinite(intercept)):
        raise XRayInputError(f"rescale: slope must be finite and non-zero, intercept finite; got {slope}, {intercept}")
    stored = np.rint((a - intercept) / slope)
    if stored.min() < 0 or stored.max() > 65535:
        raise XRayInputError(
            f"{name}: values {a.min():g}..{a.max():g} with slope {slope:g}, intercept {intercept:g} "
            f"do not fit 16-bit unsigned storage"
        )
    stored = stored.astype(np.uint16)

    sop_class = _DX_PRESENTATION_UID if attenuation_bright else _DX_PROCESSING_UID
    sop_instance = generate_uid()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = sop_instance
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID

    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_instance
    ds.StudyInstanceUID = generate_uid()
    ds.SeriesInstanceUID = generate_uid()
    ds.Modality = "DX"
    ds.ImageType = ["DERIVED", "SECONDARY"]
    ds.PatientName = "ctxreg^synthetic"
    ds.PatientID = "ctxreg-synthetic"
    ds.StudyID = "1"
    ds.SeriesNumber = 1
    ds.InstanceNumber = 1
    ds.Manufacturer = "ctxreg"
    ds.PresentationIntentType = "FOR PRESENTATION" if attenuation_bright else "FOR PROCESSING"
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME1" if monochrome1 else "MONOCHROME2"
    ds.Rows, ds.Columns = int(a.shape[0]), int(a.shape[1])
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.RescaleSlope = f"{slope:.10g}"
    ds.RescaleIntercept = f"{intercept:.10g}"
    ds.RescaleType = "US"
    ds.ImagerPixelSpacing = [f"{spacing:.10g}", f"{spacing:.10g}"]
    if sdd_mm is not None:
        ds.DistanceSourceToDetector = f"{_positive(sdd_mm, 'sdd_mm'):.10g}"
    if sod_mm is not None:
        ds.DistanceSourceToPatient = f"{_positive(sod_mm, 'sod_mm'):.10g}"
    ds.PixelData = stored.tobytes()

    with atomic_path(path) as tmp:
        pydicom.dcmwrite(tmp, ds, enforce_file_format=True)
    return path
