"""Reading and writing X-ray image files (DICOM, PNG, TIFF, JPEG, NumPy): pixels, tags, orientation.

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
  ``register.xray.preprocess`` (``LogCorrect`` for transmission images, ``Invert`` where needed).

Colour: grey stored as RGB (three equal channels, like the paediatric test files) becomes grey
(the channel mean); a coloured image is an error asking for a grey image.

The C-arm geometry of an image (its DICOM geometry tags, the scene, explicit values) is
:mod:`register.xray.geometry`'s.

Intensity tags (``meta["intensity_tags"]``, ``None`` for non-DICOM files): a JSON dict of the DICOM
facts that say how pixel values relate to the radiation and the display - ``PhotometricInterpretation``,
``PresentationLUTShape`` (IDENTITY / INVERSE), ``PixelIntensityRelationship`` (LIN / LOG / DISP),
``PixelIntensityRelationshipSign`` (+1: larger value = more radiation, -1: less), ``RescaleType``,
``VOILUT`` (a window or VOI LUT is given), ``WindowCenter`` / ``WindowWidth`` (first values),
``Modality``, ``PresentationIntentType``, ``BitsStored``, ``SOPClassUID``; absent or empty -> ``None``.
A MONOCHROME2 image with ``PresentationLUTShape`` INVERSE is shown inverted, so it is inverted into
``pixels`` like MONOCHROME1 (``meta["inverted_by"]`` says why; MONOCHROME1 + INVERSE is inverted once).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from sim.core.atomic import atomic_path
from sim.core.errors import InputError
from sim.prepare import checked_image

__all__ = [
    "XRayInputError",
    "XRayImage",
    "load_xray",
    "write_xray_dicom",
    "INTENSITY_TAG_KEYS",
    "ORIENTATIONS",
    "check_orientation",
]

#: How a stored X-ray is turned into the CT's view before registration (``--orient``), named as
#: Pillow's transposes: ``(H, W)`` pixels -> the image as ctxreg's DRRs of the CT show the same
#: view (:mod:`sim.projection.geometry`'s detector, row 0 at the top and column 0 at the left as displayed).
#: Vendors and viewers store frames mirrored or rotated: a frame registered in the wrong
#: orientation finds a wrong (often mirrored) pose, and a mirrored view of a nearly symmetric
#: anatomy such as the pelvis can score as well as the right one, so the orientation is the
#: user's to give, not guessed. Rotations are counter-clockwise as displayed.
ORIENTATIONS = {
    "none": lambda a: a,
    "flip-left-right": lambda a: a[:, ::-1],
    "flip-top-bottom": lambda a: a[::-1, :],
    "rotate-90": lambda a: np.rot90(a, 1),
    "rotate-180": lambda a: np.rot90(a, 2),
    "rotate-270": lambda a: np.rot90(a, 3),
    "transpose": lambda a: a.T,
    "transverse": lambda a: np.rot90(a, 2).T,
}

#: Relative tolerance for treating a (row, column) spacing pair as square.
_SQUARE_RTOL = 1e-4
#: RGB channels count as equal (grey stored as RGB) when they differ by at most this fraction
#: of the image's value range (1 grey level of 8 bits ~ 0.4 %; lossy codecs may add +-1).
_GREY_RTOL = 0.01

#: SOP classes of CT, MR and PET images: a slice of a volume, never a projection X-ray.
_VOLUME_SOP_CLASSES = {
    "1.2.840.10008.5.1.4.1.1.2": "CT", "1.2.840.10008.5.1.4.1.1.2.1": "CT", "1.2.840.10008.5.1.4.1.1.2.2": "CT",
    "1.2.840.10008.5.1.4.1.1.4": "MR", "1.2.840.10008.5.1.4.1.1.4.1": "MR", "1.2.840.10008.5.1.4.1.1.128": "PET",
    "1.2.840.10008.5.1.4.1.1.130": "PET",
}
#: Modalities of volume slices (DICOM Modality).
_VOLUME_MODALITIES = {"CT": "CT", "MR": "MR", "PT": "PET", "NM": "NM"}
#: Modalities of projection X-rays: such a file is never taken for a slice, whatever else it holds.
_XRAY_MODALITIES = {"DX", "CR", "RF", "XA", "MG", "PX", "IO", "RG"}
_DX_PRESENTATION_UID = "1.2.840.10008.5.1.4.1.1.1.1"  # Digital X-Ray Image Storage - For Presentation
_DX_PROCESSING_UID = "1.2.840.10008.5.1.4.1.1.1.1.1"  # Digital X-Ray Image Storage - For Processing
_SC_UID = "1.2.840.10008.5.1.4.1.1.7"  # Secondary Capture Image Storage (any modality)
_PILLOW_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp"}

_ERMF = "EstimatedRadiographicMagnificationFactor"
#: Keys of ``meta["intensity_tags"]``, in order.
INTENSITY_TAG_KEYS = (
    "PhotometricInterpretation",
    "PresentationLUTShape",
    "PixelIntensityRelationship",
    "PixelIntensityRelationshipSign",
    "RescaleType",
    "VOILUT",
    "WindowCenter",
    "WindowWidth",
    "Modality",
    "PresentationIntentType",
    "BitsStored",
    "SOPClassUID",
)


class XRayInputError(InputError):
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
            ``inverted`` and ``inverted_by`` ("MONOCHROME1", "PresentationLUTShape INVERSE" or
            ``None``), ``rgb_to_grey``, ``intensity_tags`` (``None`` unless DICOM); DICOM also
            ``geometry_tags`` (the geometry tags in mm, ``None`` when absent), ``ignored_tags``
            (tags with non-positive / non-finite / malformed values) and ``invalid_tags`` (their
            text), ``bits_stored``, ...
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

    def binned(self, factor: int) -> "XRayImage":
        """This image with its pixels averaged in ``factor`` x ``factor`` blocks: ``(H // f, W // f)``
        px of ``f`` times the pitch (``pixel_spacing_mm``, ``meta["pixel_spacing_rc_mm"]`` and the
        DICOM pitch tags in ``meta["geometry_tags"]``: ImagerPixelSpacing, PixelSpacing; a file
        with only DetectorElementSpacing gets ImagerPixelSpacing = f x it),
        the rows and columns that do not fill a block cut evenly from both sides so that the
        centre (the principal point) stays within half an original pixel. ``meta["binned"]``
        records ``factor``; 1 returns the image itself.

        >>> img = XRayImage(np.arange(36.0).reshape(6, 6), pixel_spacing_mm=0.2)
        >>> b = img.binned(2)
        >>> b.shape, b.pixel_spacing_mm, float(b.pixels[0, 0])
        ((3, 3), 0.4, 3.5)
        """
        f = int(factor)
        if f < 1 or f != factor:
            raise XRayInputError(f"{self.source or 'XRayImage'}: binning factor must be a whole number >= 1, got {factor!r}")
        if f == 1:
            return self
        h, w = self.shape
        if h < 2 * f or w < 2 * f:
            raise XRayInputError(f"{self.source or 'XRayImage'}: {h} x {w} px is too small to bin by {f}")
        top, left = (h % f) // 2, (w % f) // 2
        block = self.pixels[top:top + h // f * f, left:left + w // f * f].astype(np.float64)
        pixels = block.reshape(h // f, f, w // f, f).mean(axis=(1, 3)).astype(np.float32)
        meta = dict(self.meta, binned=f * int(self.meta.get("binned", 1)))
        if meta.get("pixel_spacing_rc_mm") is not None:
            meta["pixel_spacing_rc_mm"] = [float(v) * f for v in meta["pixel_spacing_rc_mm"]]
        tags = meta.get("geometry_tags")
        if isinstance(tags, dict):  # the image's pixel pitch tags follow; the detector's element stays
            tags = dict(tags)
            for key in ("ImagerPixelSpacing", "PixelSpacing"):
                if tags.get(key):
                    tags[key] = [float(v) * f for v in tags[key]]
            if not tags.get("ImagerPixelSpacing") and tags.get("DetectorElementSpacing"):
                tags["ImagerPixelSpacing"] = [float(v) * f for v in tags["DetectorElementSpacing"]]
            meta["geometry_tags"] = tags
        return replace(self, pixels=pixels, meta=meta,
                       pixel_spacing_mm=None if self.pixel_spacing_mm is None else self.pixel_spacing_mm * f)

    def reoriented(self, orientation: str) -> "XRayImage":
        """This image turned by ``orientation`` (a name of :data:`ORIENTATIONS`): the pixels
        ``(H, W)`` mirrored or rotated (``(W, H)`` after a quarter turn), the geometry unchanged (square
        pixels, the principal point at the centre); ``meta["orientation"]`` records it. ``"none"``
        returns the image itself."""
        check_orientation(orientation)
        if orientation == "none":
            return self

        meta = dict(self.meta, orientation=orientation)
        rc = meta.get("pixel_spacing_rc_mm")
        if rc is not None and orientation in ("rotate-90", "rotate-270", "transpose", "transverse"):
            meta["pixel_spacing_rc_mm"] = [rc[1], rc[0]]  # rows and columns swap
        return replace(self, pixels=np.ascontiguousarray(ORIENTATIONS[orientation](self.pixels)), meta=meta)


def check_orientation(orientation: object) -> None:
    """Refuse (:class:`XRayInputError`, one line) a name that is not one of :data:`ORIENTATIONS`."""
    if orientation not in ORIENTATIONS:
        raise XRayInputError(f"--orient must be one of {', '.join(ORIENTATIONS)}, got {orientation!r}")


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
    DICOM: rescale slope/intercept applied, MONOCHROME1 (and MONOCHROME2 with PresentationLUTShape
    INVERSE) inverted, multi-frame rejected; geometry and intensity tags in ``meta`` (module docstring).
    Raises :class:`XRayInputError` naming the file for a missing file, an unreadable / non-image
    file, missing pixel data, arrays that are not 2-D, NaN / infinite pixels, an unsupported
    photometric interpretation or a colour image.
    """
    p = Path(path)
    src = str(p)
    if not p.exists():
        raise XRayInputError(f"{src}: file not found")
    if p.is_dir():
        raise XRayInputError(f"{src}: a folder, not an X-ray file (a CT's DICOM series folder goes to --ct)")
    if not p.is_file():
        raise XRayInputError(f"{src}: not a file")
    if p.name.lower().endswith((".nii", ".nii.gz")):
        raise XRayInputError(f"{src}: a NIfTI volume (a CT?), not an X-ray image; give the CT as --ct")
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


def _tiff_planes(im) -> str | None:
    """What a TIFF whose samples are stored plane by plane (PlanarConfiguration 2) holds, in words
    (e.g. a stack of 3 images that ``tifffile.imwrite`` of a ``(3, H, W)`` array stores as RGB
    planes); None for anything else."""
    tags = getattr(im, "tag_v2", None)
    if tags is None or tags.get(284) != 2:
        return None
    n = int(tags.get(277, 0) or 0)
    shape = ""
    try:
        described = json.loads(str(tags.get(270, "")))
        if isinstance(described, dict) and isinstance(described.get("shape"), list):
            shape = f", shape {described['shape']} in its description"
    except ValueError:
        pass
    return (f"a TIFF of {n} separate planes of {im.height} x {im.width} px (PlanarConfiguration 2{shape}): a "
            f"stack of {n} images, or a colour image stored plane by plane")


def _load_npy(p: Path) -> XRayImage:
    src = str(p)
    try:
        a = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise XRayInputError(f"{src}: not a readable .npy array ({e})") from None
    meta = {"format": "npy", "dtype": str(a.dtype), "inverted": False, "inverted_by": None, "intensity_tags": None}
    return XRayImage(_check_pixels(a, src), True, None, None, None, src, meta)


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
                try:
                    a = _rgb_to_grey(np.asarray(im.convert("RGB")), src)
                except XRayInputError:
                    planes = _tiff_planes(im)
                    if planes is None:
                        raise
                    raise XRayInputError(f"{src}: {planes}; a single 2-D grey image is needed (save one image "
                                         f"per file)") from None
                rgb_to_grey = True
        else:
            raise XRayInputError(f"{src}: unsupported image mode {mode!r}; a grey image is needed")
    meta["rgb_to_grey"] = rgb_to_grey
    meta["dtype"] = str(np.asarray(a).dtype)
    meta.update(inverted=False, inverted_by=None, intensity_tags=None)
    return XRayImage(_check_pixels(a, src), True, None, None, None, src, meta)


def _tag_values(ds: Any, keyword: str) -> list[Any] | None:
    """The values of a DICOM tag as a list, or ``None`` when it is absent or empty."""
    try:
        v = ds.get(keyword)
    except Exception:  # a value pydicom cannot convert: report it as unusable below
        return ["<unreadable>"]
    if v is None:
        return None
    if isinstance(v, (str, bytes)):
        return [v] if str(v).strip() else None
    try:
        vals = list(v)
    except TypeError:
        vals = [v]
    return vals or None


def _tag_numbers(ds: Any, keyword: str, count: int, ignored: dict[str, str]) -> list[float] | None:
    """``count`` positive finite numbers from a DS tag; absent / empty -> ``None``; a value that is
    not ``count`` positive finite numbers -> ``None`` with ``keyword: its text`` added to ``ignored``."""
    vals = _tag_values(ds, keyword)
    if vals is None:
        return None
    try:
        nums = [float(x) for x in vals]
    except (TypeError, ValueError):
        nums = []
    if len(nums) != count or not all(math.isfinite(x) and x > 0 for x in nums):
        ignored[keyword] = "\\".join(str(v) for v in vals)
        return None
    return nums


def _tag_str(ds: Any, keyword: str) -> str | None:
    """A text tag, stripped (first value of a multi-valued one); absent / empty -> ``None``."""
    vals = _tag_values(ds, keyword)
    if vals is None:
        return None
    v = str(vals[0]).strip()
    return v or None


def _tag_first_float(ds: Any, keyword: str) -> float | None:
    vals = _tag_values(ds, keyword)
    if vals is None:
        return None
    try:
        v = float(vals[0])
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _tag_int(ds: Any, keyword: str) -> int | None:
    vals = _tag_values(ds, keyword)
    if vals is None:
        return None
    try:
        return int(vals[0])
    except (TypeError, ValueError):
        return None


def _intensity_tags(ds: Any) -> dict[str, Any]:
    """``meta["intensity_tags"]``: the keys of :data:`INTENSITY_TAG_KEYS`, ``None`` when absent."""
    voi_seq = _tag_values(ds, "VOILUTSequence")
    centre = _tag_first_float(ds, "WindowCenter")
    width = _tag_first_float(ds, "WindowWidth")
    upper = ("PhotometricInterpretation", "PresentationLUTShape", "PixelIntensityRelationship",
             "PresentationIntentType", "Modality")
    out: dict[str, Any] = {}
    for key in INTENSITY_TAG_KEYS:
        if key == "VOILUT":
            out[key] = bool(centre is not None or width is not None or voi_seq)
        elif key == "WindowCenter":
            out[key] = centre
        elif key == "WindowWidth":
            out[key] = width
        elif key in ("PixelIntensityRelationshipSign", "BitsStored"):
            out[key] = _tag_int(ds, key)
        else:
            v = _tag_str(ds, key)
            out[key] = v.upper() if (v is not None and key in upper) else v
    return out


def _geometry_tags(ds: Any, ignored: dict[str, str]) -> dict[str, Any]:
    """``meta["geometry_tags"]``: the geometry tags (mm; pairs as ``[row, col]``), ``None`` when absent."""
    sdd = _tag_numbers(ds, "DistanceSourceToDetector", 1, ignored)
    sod = _tag_numbers(ds, "DistanceSourceToPatient", 1, ignored)
    ermf = _tag_numbers(ds, _ERMF, 1, ignored)
    return {
        "DistanceSourceToDetector": sdd[0] if sdd else None,
        "DistanceSourceToPatient": sod[0] if sod else None,
        _ERMF: ermf[0] if ermf else None,
        "ImagerPixelSpacing": _tag_numbers(ds, "ImagerPixelSpacing", 2, ignored),
        "DetectorElementSpacing": _tag_numbers(ds, "DetectorElementSpacing", 2, ignored),
        "PixelSpacing": _tag_numbers(ds, "PixelSpacing", 2, ignored),
        "PixelSpacingCalibrationType": _tag_str(ds, "PixelSpacingCalibrationType"),
    }


def _is_square(rc: list[float] | tuple[float, float]) -> bool:
    return abs(rc[0] - rc[1]) <= _SQUARE_RTOL * max(rc)


def _native_pixels_short(ds) -> str | None:
    """Where uncompressed pixel data is shorter than its tags say (a file cut short): the words
    saying so; else None."""
    try:
        rows, cols = int(ds.Rows), int(ds.Columns)
        bits = int(ds.get("BitsAllocated", 16) or 16)
        samples = int(ds.get("SamplesPerPixel", 1) or 1)
        have = len(ds.PixelData)
    except (AttributeError, TypeError, ValueError, KeyError):
        return None
    need = rows * cols * samples * bits // 8
    if have >= need:
        return None
    return (f"it holds {have} bytes where {rows} x {cols} px of {bits} bits need {need}: the file is cut short "
            "(a copy not finished, or a damaged file)")


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
    _refuse_volume_slice(ds, src)
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
        if tsyntax is None or not getattr(tsyntax, "is_compressed", True):  # native pixels: no decoder involved
            short = _native_pixels_short(ds)
            raise XRayInputError(f"{src}: cannot read the pixel data (transfer syntax {name}, uncompressed): "
                                 + (short or f"{type(e).__name__}: {e}")) from None
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
    intensity = _intensity_tags(ds)
    inverted_by = None
    if photometric == "MONOCHROME1":
        inverted_by = "MONOCHROME1"  # with PresentationLUTShape INVERSE too: inverted once only
    elif photometric == "MONOCHROME2" and intensity["PresentationLUTShape"] == "INVERSE":
        inverted_by = "PresentationLUTShape INVERSE"
    inverted = inverted_by is not None
    if inverted:
        finite = values[np.isfinite(values)]
        if finite.size:
            values = (finite.max() + finite.min()) - values
    pixels = _check_pixels(values, src)

    ignored: dict[str, str] = {}
    gtags = _geometry_tags(ds, ignored)
    spacing, spacing_tag, spacing_rc = None, None, None
    for tag in ("ImagerPixelSpacing", "PixelSpacing"):
        rc = gtags[tag]
        if rc is not None:
            spacing_tag, spacing_rc = tag, (rc[0], rc[1])
            if _is_square(rc):
                spacing = 0.5 * (rc[0] + rc[1])
            break
    sdd = gtags["DistanceSourceToDetector"]
    sod = gtags["DistanceSourceToPatient"]
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
        "inverted_by": inverted_by,
        "rgb_to_grey": rgb_to_grey,
        "stored_dtype": stored_dtype,
        "bits_stored": intensity["BitsStored"],
        "geometry_tags": gtags,
        "ignored_tags": list(ignored),
        "invalid_tags": ignored,
        "intensity_tags": intensity,
    }
    return XRayImage(pixels, intent != "FOR PROCESSING", spacing, sdd, sod, src, meta)


def _refuse_volume_slice(ds: Any, src: str) -> None:
    """Raise :class:`XRayInputError` for a slice of a CT (MR, PET) volume: its Modality, its SOP
    class, or (without an X-ray modality) the position tags of a slice in a volume."""
    modality = (_tag_str(ds, "Modality") or "").upper()
    if modality in _XRAY_MODALITIES:
        return
    sop = _tag_str(ds, "SOPClassUID") or str(getattr(getattr(ds, "file_meta", None), "MediaStorageSOPClassUID", ""))
    kind = _VOLUME_MODALITIES.get(modality) or _VOLUME_SOP_CLASSES.get(sop)
    why = f"Modality {modality}" if modality in _VOLUME_MODALITIES else f"SOP class {sop}" if kind else None
    if kind is None:
        slice_tags = [k for k in ("ImagePositionPatient", "ImageOrientationPatient", "SliceLocation", "SliceThickness")
                      if _tag_values(ds, k) is not None]
        if "ImagePositionPatient" in slice_tags and len(slice_tags) >= 2:
            kind, why = "CT", f"{', '.join(slice_tags)}: the tags of a slice in a volume"
    if kind is not None:
        what = "a CT slice" if kind == "CT" else f"a slice of an {kind} volume" if kind == "MR" else f"a {kind} slice"
        raise XRayInputError(f"{src}: {what} ({why}), not a projection X-ray; register a radiograph or fluoroscopy "
                             f"frame (DX, CR, RF, XA), and give the CT series as --ct")


def _positive(value: object, name: str) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise XRayInputError(f"{name}: expected a number of mm, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise XRayInputError(f"{name}: must be a positive finite number of mm, got {value!r}")
    return v


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


def write_xray_dicom(
    path: str | os.PathLike,
    pixels: np.ndarray,
    *,
    pixel_spacing_mm: float | None,
    sdd_mm: float | None = None,
    sod_mm: float | None = None,
    monochrome1: bool = False,
    rescale_slope: float | None = None,
    rescale_intercept: float | None = None,
    attenuation_bright: bool = True,
    bits_stored: int = 16,
    modality: str = "DX",
    pixel_intensity_relationship: str | None = None,
    pixel_intensity_sign: int | None = None,
    presentation_lut_shape: str | None = None,
    window: tuple[float, float] | None = None,
    magnification_factor: float | None = None,
    detector_element_spacing_mm: float | None = None,
    patient_pixel_spacing_mm: float | None = None,
    imager_pixel_spacing: bool = True,
) -> Path:
    """Write a minimal valid single-frame DICOM X-ray (explicit VR little endian, 16 bits allocated),
    atomically; for tests and synthetic data. Returns the path.

    Pixels: ``pixels`` are ``(H, W)`` real values (what :func:`load_xray` returns for MONOCHROME2
    without an INVERSE presentation LUT). Stored values are ``round((pixels - intercept) / slope)``
    in ``[0, 2**bits_stored - 1]``. Defaults: integer input -> slope 1, intercept 0 (stored as
    given); float input -> ``intercept = min``, ``slope = (max - min) / (2**bits_stored - 1)`` (the
    full range; round trip within ``slope / 2``). ``monochrome1=True`` writes the same stored values
    tagged MONOCHROME1 (a viewer and :func:`load_xray` show them inverted); so does
    ``presentation_lut_shape="INVERSE"`` with MONOCHROME2.

    Args:
        pixel_spacing_mm: square detector pitch in mm, written as ``ImagerPixelSpacing`` (unless
            ``imager_pixel_spacing=False``); ``None`` writes no ImagerPixelSpacing.
        sdd_mm, sod_mm: ``DistanceSourceToDetector`` / ``DistanceSourceToPatient`` in mm.
        attenuation_bright: ``PresentationIntentType`` "FOR PRESENTATION" (True) or "FOR
            PROCESSING" (False; DX For Processing SOP class).
        bits_stored: 16 (default) or 12 (``BitsStored`` 12, ``HighBit`` 11, values 0..4095); 8 to 16 are
            accepted.
        modality: "DX" (default), "RF" or "XA". The SOP class is Digital X-Ray Image Storage (For
            Presentation / For Processing) for DX, and Secondary Capture Image Storage for RF and XA
            (the DX IOD requires Modality DX; the XA / RF IODs need modules this writer does not
            fill). The same X-ray tags are written in every case.
        pixel_intensity_relationship: ``PixelIntensityRelationship`` ("LIN", "LOG", "DISP", ...).
        pixel_intensity_sign: ``PixelIntensityRelationshipSign``, +1 or -1.
        presentation_lut_shape: ``PresentationLUTShape``, "IDENTITY" or "INVERSE".
        window: ``(WindowCenter, WindowWidth)`` in rescaled units (width > 0).
        magnification_factor: ``EstimatedRadiographicMagnificationFactor`` (SID / SOD), > 0.
        detector_element_spacing_mm: square ``DetectorElementSpacing`` in mm.
        patient_pixel_spacing_mm: square ``PixelSpacing`` in mm, calibrated to the patient plane
            (``PixelSpacingCalibrationType`` "GEOMETRY").
        imager_pixel_spacing: False writes no ``ImagerPixelSpacing`` even with ``pixel_spacing_mm``.
    """
    import pydicom
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, PYDICOM_IMPLEMENTATION_UID, generate_uid

    path = Path(path)
    name = f"pixels for {path}"
    a = checked_image(pixels, name, XRayInputError)
    if isinstance(bits_stored, bool) or not isinstance(bits_stored, (int, np.integer)) or not 8 <= bits_stored <= 16:
        raise XRayInputError(f"bits_stored: expected an integer 8..16 (e.g. 12 or 16), got {bits_stored!r}")
    bits_stored = int(bits_stored)
    top_value = float(2**bits_stored - 1)
    modality = str(modality).strip().upper()
    if modality not in ("DX", "RF", "XA"):
        raise XRayInputError(f"modality: expected 'DX', 'RF' or 'XA', got {modality!r}")
    spacing = None if pixel_spacing_mm is None else _positive(pixel_spacing_mm, "pixel_spacing_mm")
    if np.asarray(pixels).dtype.kind in "ui":
        slope = 1.0 if rescale_slope is None else float(rescale_slope)
        intercept = 0.0 if rescale_intercept is None else float(rescale_intercept)
    else:
        lo, hi = float(a.min()), float(a.max())
        intercept = lo if rescale_intercept is None else float(rescale_intercept)
        if rescale_slope is None:
            top = hi - intercept
            slope = top / top_value if top > 0 else 1.0
        else:
            slope = float(rescale_slope)
    if not (math.isfinite(slope) and slope != 0 and math.isfinite(intercept)):
        raise XRayInputError(f"rescale: slope must be finite and non-zero, intercept finite; got {slope}, {intercept}")
    stored = np.rint((a - intercept) / slope)
    if stored.min() < 0 or stored.max() > top_value:
        raise XRayInputError(
            f"{name}: values {a.min():g}..{a.max():g} with slope {slope:g}, intercept {intercept:g} "
            f"do not fit {bits_stored}-bit unsigned storage (0..{int(top_value)})"
        )
    stored = stored.astype(np.uint16)
    if pixel_intensity_sign is not None and pixel_intensity_sign not in (1, -1):
        raise XRayInputError(f"pixel_intensity_sign: expected +1 or -1, got {pixel_intensity_sign!r}")
    if presentation_lut_shape is not None:
        presentation_lut_shape = str(presentation_lut_shape).strip().upper()
        if presentation_lut_shape not in ("IDENTITY", "INVERSE"):
            raise XRayInputError(
                f"presentation_lut_shape: expected 'IDENTITY' or 'INVERSE', got {presentation_lut_shape!r}"
            )
    if window is not None:
        try:
            centre, width = (float(window[0]), float(window[1]))
        except (TypeError, ValueError, IndexError):
            raise XRayInputError(f"window: expected (centre, width), got {window!r}") from None
        if not (math.isfinite(centre) and math.isfinite(width) and width > 0):
            raise XRayInputError(f"window: centre must be finite and width > 0, got {window!r}")

    if modality == "DX":
        sop_class = _DX_PRESENTATION_UID if attenuation_bright else _DX_PROCESSING_UID
    else:
        sop_class = _SC_UID
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
    ds.Modality = modality
    ds.ImageType = ["DERIVED", "SECONDARY"]
    ds.PatientName = "ctxreg^synthetic"
    ds.PatientID = "ctxreg-synthetic"
    ds.StudyID = "1"
    ds.SeriesNumber = 1
    ds.InstanceNumber = 1
    ds.Manufacturer = "ctxreg"
    if modality != "DX":
        ds.ConversionType = "WSD"  # Secondary Capture: workstation
    ds.PresentationIntentType = "FOR PRESENTATION" if attenuation_bright else "FOR PROCESSING"
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME1" if monochrome1 else "MONOCHROME2"
    ds.Rows, ds.Columns = int(a.shape[0]), int(a.shape[1])
    ds.BitsAllocated = 16
    ds.BitsStored = bits_stored
    ds.HighBit = bits_stored - 1
    ds.PixelRepresentation = 0
    ds.RescaleSlope = f"{slope:.10g}"
    ds.RescaleIntercept = f"{intercept:.10g}"
    ds.RescaleType = "US"
    if pixel_intensity_relationship is not None:
        ds.PixelIntensityRelationship = str(pixel_intensity_relationship).strip().upper()
    if pixel_intensity_sign is not None:
        ds.PixelIntensityRelationshipSign = int(pixel_intensity_sign)
    if presentation_lut_shape is not None:
        ds.PresentationLUTShape = presentation_lut_shape
    if window is not None:
        ds.WindowCenter = f"{centre:.10g}"
        ds.WindowWidth = f"{width:.10g}"
    if spacing is not None and imager_pixel_spacing:
        ds.ImagerPixelSpacing = [f"{spacing:.10g}", f"{spacing:.10g}"]
    if detector_element_spacing_mm is not None:
        de = _positive(detector_element_spacing_mm, "detector_element_spacing_mm")
        ds.DetectorElementSpacing = [f"{de:.10g}", f"{de:.10g}"]
    if patient_pixel_spacing_mm is not None:
        pp = _positive(patient_pixel_spacing_mm, "patient_pixel_spacing_mm")
        ds.PixelSpacing = [f"{pp:.10g}", f"{pp:.10g}"]
        ds.PixelSpacingCalibrationType = "GEOMETRY"
    if magnification_factor is not None:
        m = _positive(magnification_factor, "magnification_factor")
        ds.EstimatedRadiographicMagnificationFactor = f"{m:.10g}"
    if sdd_mm is not None:
        ds.DistanceSourceToDetector = f"{_positive(sdd_mm, 'sdd_mm'):.10g}"
    if sod_mm is not None:
        ds.DistanceSourceToPatient = f"{_positive(sod_mm, 'sod_mm'):.10g}"
    ds.PixelData = stored.tobytes()

    with atomic_path(path) as tmp:
        pydicom.dcmwrite(tmp, ds, enforce_file_format=True)
    return path
