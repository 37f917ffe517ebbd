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
  ``register.xray.preprocess`` (``LogCorrect`` for transmission images, ``Invert`` where needed).

Colour: grey stored as RGB (three equal channels, like the paediatric test files) becomes grey
(the channel mean); a coloured image is an error asking for a grey image.

Geometry (:func:`resolve_geometry`, :func:`geometry_for`): each of SDD, SOD and the detector pixel
pitch comes from the first of: an explicit argument (the CLI flags ``--sdd``, ``--sod``,
``--pixel-spacing``) > the DICOM tags > the scene (assumed). :func:`resolve_geometry` also says where
each value came from (:class:`GeometrySources`) and refuses tags that contradict each other.

DICOM tags read for the geometry (all lengths in mm; an empty tag counts as absent; the values are
kept in ``meta["geometry_tags"]``). A tag that is present but invalid (non-positive, non-finite,
malformed) is not used: its name is in ``meta["ignored_tags"]`` and its text in
``meta["invalid_tags"]``, and :func:`resolve_geometry` refuses the image naming the tag unless
the value it would give is given explicitly (``--sdd``, ``--sod``, ``--pixel-spacing``): a
broken tag is not silently replaced by the scene's value.

* ``DistanceSourceToDetector`` (0018,1110), SID/SDD: focal spot to the detector surface.
* ``DistanceSourceToPatient`` (0018,1111), SOD: focal spot to the patient (the isocentre, the
  plane where the C-arm model puts the object).
* ``EstimatedRadiographicMagnificationFactor`` (0018,1114), ERMF, dimensionless: the magnification
  of the object plane on the detector, ``SID / SOD`` (> 1).
* ``ImagerPixelSpacing`` (0018,1164), (row, column): pixel pitch **at the detector front plane**
  (after binning), which is what the C-arm model needs.
* ``DetectorElementSpacing`` (0018,7022), (row, column): pitch of the physical detector elements;
  ``ImagerPixelSpacing`` is this times an integer binning factor (>= 1).
* ``PixelSpacing`` (0028,0030), (row, column): pitch "in the patient"; for DX/CR it may be
  calibrated to the patient plane, i.e. ``ImagerPixelSpacing / ERMF`` ...
* ``PixelSpacingCalibrationType`` (0028,0A02): ... which this tag says (``GEOMETRY``: from the
  ERMF, ``FIDUCIAL``: from an object of known size); when present, ``PixelSpacing x ERMF`` gives
  the pitch at the detector back.

``XRayImage.sdd_mm`` / ``sod_mm`` hold ``DistanceSourceToDetector`` / ``DistanceSourceToPatient`` as
written, and ``XRayImage.pixel_spacing_mm`` the first of ``ImagerPixelSpacing``, ``PixelSpacing``
(``meta["pixel_spacing_tag"]`` says which) as written; anisotropic spacing is kept out of
``pixel_spacing_mm`` (``None``, the pair in ``meta["pixel_spacing_rc_mm"]``) and the geometry then
asks for an explicit square spacing. Derived values (SOD from ERMF, spacing from PixelSpacing x
ERMF) are made by :func:`resolve_geometry` only.

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

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sim.atomic import atomic_path
from sim.errors import InputError
from sim.geometry import CArmGeometry

__all__ = [
    "XRayInputError",
    "XRayImage",
    "GeometrySources",
    "load_xray",
    "resolve_geometry",
    "geometry_for",
    "write_xray_dicom",
    "INTENSITY_TAG_KEYS",
    "ORIENTATIONS",
    "check_orientation",
]

#: How a stored X-ray is turned into the CT's view before registration (``--orient``), named as
#: Pillow's transposes: ``(H, W)`` pixels -> the image as ctxreg's DRRs of the CT show the same
#: view (:mod:`sim.geometry`'s detector, row 0 at the top and column 0 at the left as displayed).
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

#: ``EstimatedRadiographicMagnificationFactor`` may differ from ``SDD / SOD`` by this fraction.
_ERMF_RTOL = 0.02
#: ``ImagerPixelSpacing`` may be this fraction below ``DetectorElementSpacing`` (rounding) ...
_BIN_BELOW_RTOL = 0.01
#: ... and this fraction away from an integer multiple (binning factor) of it.
_BIN_RTOL = 0.02
#: The explicit arguments of :func:`resolve_geometry` by their command-line flags.
_FLAGS = {"sdd_mm": "--sdd", "sod_mm": "--sod", "pixel_spacing_mm": "--pixel-spacing"}
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

    def reoriented(self, orientation: str) -> "XRayImage":
        """This image turned by ``orientation`` (a name of :data:`ORIENTATIONS`): the pixels
        ``(H, W)`` mirrored or rotated (``(W, H)`` after a quarter turn), the geometry unchanged (square
        pixels, the principal point at the centre); ``meta["orientation"]`` records it. ``"none"``
        returns the image itself."""
        check_orientation(orientation)
        if orientation == "none":
            return self
        from dataclasses import replace

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
    import json

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


@dataclass(frozen=True)
class GeometrySources:
    """The geometry values :func:`resolve_geometry` chose and where each came from.

    Attributes:
        sdd_mm: source-to-detector distance (mm).
        sdd_source: where it came from, e.g. ``"flag --sdd"``, ``"DICOM DistanceSourceToDetector"``,
            ``"scene 'cios_fusion' (assumed)"``.
        sod_mm: source-to-patient (isocentre) distance (mm).
        sod_source: e.g. ``"flag --sod"``, ``"DICOM DistanceSourceToPatient"``, ``"DICOM
            DistanceSourceToDetector / EstimatedRadiographicMagnificationFactor"`` (derived),
            ``"scene 'cios_fusion' (assumed)"``.
        pixel_spacing_mm: detector pixel pitch (mm) at the image's own resolution (before any
            ``size`` resampling).
        pixel_spacing_source: e.g. ``"flag --pixel-spacing"``, ``"DICOM ImagerPixelSpacing"``,
            ``"DICOM DetectorElementSpacing"``, ``"DICOM PixelSpacing x
            EstimatedRadiographicMagnificationFactor"``, ``"DICOM PixelSpacing"``, ``"scene
            'cios_fusion' (assumed)"``.
        notes: remarks that are not errors (e.g. a patient-plane PixelSpacing without ERMF).
    """

    sdd_mm: float
    sdd_source: str
    sod_mm: float
    sod_source: str
    pixel_spacing_mm: float
    pixel_spacing_source: str
    notes: tuple[str, ...] = ()

    @property
    def assumed(self) -> list[str]:
        """Names (``sdd_mm``, ``sod_mm``, ``pixel_spacing_mm``) of values that rest on the scene."""
        return [name for name, src in self._items() if "(assumed)" in src]

    def _items(self) -> list[tuple[str, str]]:
        return [
            ("sdd_mm", self.sdd_source),
            ("sod_mm", self.sod_source),
            ("pixel_spacing_mm", self.pixel_spacing_source),
        ]

    def line(self) -> str:
        """One line for a log, e.g. ``geometry: SDD 1020 mm (DICOM DistanceSourceToDetector), SOD 510
        mm (scene 'cios_fusion' (assumed)), pixel 0.300 mm (DICOM ImagerPixelSpacing)``."""
        text = (
            f"geometry: SDD {self.sdd_mm:g} mm ({self.sdd_source}), SOD {self.sod_mm:g} mm ({self.sod_source}), "
            f"pixel {self.pixel_spacing_mm:.3f} mm ({self.pixel_spacing_source})"
        )
        return " ".join(text.split())  # one line whatever a scene path holds

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable: the values (mm), their sources, ``assumed`` and ``notes``."""
        return {
            "sdd_mm": self.sdd_mm,
            "sdd_source": self.sdd_source,
            "sod_mm": self.sod_mm,
            "sod_source": self.sod_source,
            "pixel_spacing_mm": self.pixel_spacing_mm,
            "pixel_spacing_source": self.pixel_spacing_source,
            "assumed": self.assumed,
            "notes": list(self.notes),
        }


def _fmt_rc(rc: list[float] | tuple[float, float]) -> str:
    return f"{rc[0]:g} x {rc[1]:g} mm" if not _is_square(rc) else f"{rc[0]:g} mm"


def _check_binning(src: str, imager: list[float], element: list[float]) -> None:
    """``ImagerPixelSpacing`` must be an integer multiple (>= 1) of ``DetectorElementSpacing``."""
    for axis, ip, de in zip(("row", "column"), imager, element):
        ratio = ip / de
        if ratio < 1.0 - _BIN_BELOW_RTOL:
            raise XRayInputError(
                f"{src}: ImagerPixelSpacing {_fmt_rc(imager)} is smaller than DetectorElementSpacing "
                f"{_fmt_rc(element)} ({axis} ratio {ratio:.4g} < 1 by more than {_BIN_BELOW_RTOL:.0%}); "
                f"pass --pixel-spacing to choose"
            )
        n = max(1, round(ratio))
        if abs(ratio - n) > _BIN_RTOL * n:
            raise XRayInputError(
                f"{src}: ImagerPixelSpacing {_fmt_rc(imager)} is not an integer multiple (binning) of "
                f"DetectorElementSpacing {_fmt_rc(element)} ({axis} ratio {ratio:.4g}, {abs(ratio - n) / n:.1%} "
                f"from {n}, more than {_BIN_RTOL:.0%}); pass --pixel-spacing to choose"
            )


#: The flag that gives the value of each geometry tag instead (:func:`resolve_geometry`'s argument).
_TAG_FLAGS = {"DistanceSourceToDetector": "sdd_mm", "DistanceSourceToPatient": "sod_mm", _ERMF: "sod_mm",
              "ImagerPixelSpacing": "pixel_spacing_mm", "DetectorElementSpacing": "pixel_spacing_mm",
              "PixelSpacing": "pixel_spacing_mm"}


def _refuse_invalid_tags(src: str, meta: dict, **explicit: float | None) -> None:
    """Raise :class:`XRayInputError` naming the geometry tags that are present but invalid (see the
    module docstring), unless the value each would give is ``explicit`` (a flag)."""
    invalid = meta.get("invalid_tags")
    if not isinstance(invalid, dict):
        invalid = {k: None for k in meta.get("ignored_tags") or ()}
    bad = [(tag, text) for tag, text in invalid.items() if explicit.get(_TAG_FLAGS.get(tag, "")) is None]
    if bad:
        items = ", ".join(f"{tag} = {text}" if text is not None else tag for tag, text in bad)
        flags = " / ".join(dict.fromkeys(_FLAGS[_TAG_FLAGS[tag]] for tag, _ in bad if tag in _TAG_FLAGS))
        raise XRayInputError(
            f"{src}: invalid DICOM geometry tag{'s' if len(bad) > 1 else ''} {items} (a positive number of mm, "
            f"or a pair for a spacing, is needed); give the value{'s' if len(bad) > 1 else ''} with {flags}"
        )


def resolve_geometry(
    xray: XRayImage,
    scene: str | os.PathLike | None = "cios_fusion",
    *,
    size: tuple[int, int] | None = None,
    sdd_mm: float | None = None,
    sod_mm: float | None = None,
    pixel_spacing_mm: float | None = None,
) -> tuple[CArmGeometry, GeometrySources]:
    """The C-arm geometry of ``xray``'s detector and where each of its values came from.

    Args:
        xray: the image; its DICOM tags are read from ``meta["geometry_tags"]`` (see the module
            docstring); an image without them (PNG, ``.npy``, built by hand) offers its
            ``sdd_mm`` / ``sod_mm`` / ``pixel_spacing_mm`` fields instead (source ``"XRayImage.<name>"``).
        scene: scene name or file for the fallback values (``None`` = no fallback).
        size: ``(H, W)`` to resample the detector to (keeps the physical extent and must keep the
            aspect ratio); ``None`` = the image's own pixels.
        sdd_mm, sod_mm, pixel_spacing_mm: explicit values in mm (the CLI flags ``--sdd``, ``--sod``,
            ``--pixel-spacing``); each overrides the tags on purpose and is reported as the flag.

    Order, per value (the first that applies):

    * SDD: flag > ``DistanceSourceToDetector`` > scene.
    * SOD: flag > ``DistanceSourceToPatient`` > ``SDD / EstimatedRadiographicMagnificationFactor``
      (SDD as resolved above, the source says from where) > scene.
    * Pixel pitch at the detector: flag > ``ImagerPixelSpacing`` > ``DetectorElementSpacing`` >
      ``PixelSpacing x ERMF`` when ``PixelSpacingCalibrationType`` is present (PixelSpacing is then
      calibrated to the patient plane) > ``PixelSpacing`` > scene (``scene detector width / W``,
      only when the image's aspect ``H / W`` matches the scene detector's to within one pixel).

    The detector has the image's ``H x W`` pixels and the default principal point (the centre).

    Raises:
        XRayInputError (one line, naming both tags / values) when a geometry tag is present but
        invalid (``meta["invalid_tags"]``) and its value is not given explicitly; a value is missing
        and there is no fallback; the chosen spacing tag is anisotropic; the final SOD >= SDD (from any sources);
        ``DistanceSourceToDetector / DistanceSourceToPatient`` and ERMF differ by more than 2 %
        (neither distance given as a flag); an ERMF < 1 is used; ``ImagerPixelSpacing`` is more than
        1 % below ``DetectorElementSpacing`` or more than 2 % from an integer multiple of it (no
        ``--pixel-spacing``). A flag never counts as a contradiction of a tag.
    """
    if not isinstance(xray, XRayImage):
        raise XRayInputError(f"xray: expected an XRayImage, got {type(xray).__name__}")
    src = xray.source or "X-ray image"
    H, W = xray.shape
    sc = None
    scene_src = ""
    if scene is not None:
        from sim.scene import load_scene

        sc = load_scene(scene).geometry
        scene_src = f"scene {os.fspath(scene)!r} (assumed)"
    meta = xray.meta if isinstance(xray.meta, dict) else {}
    tags = meta.get("geometry_tags") if isinstance(meta.get("geometry_tags"), dict) else None
    notes: list[str] = []
    _refuse_invalid_tags(src, meta, sdd_mm=sdd_mm, sod_mm=sod_mm, pixel_spacing_mm=pixel_spacing_mm)

    def explicit(name: str, value: object) -> tuple[float, str] | None:
        if value is None:
            return None
        return _positive(value, f"{name} ({_FLAGS[name]})"), f"flag {_FLAGS[name]}"

    def missing(name: str) -> XRayInputError:
        return XRayInputError(
            f"{src}: no {name} - the image has none and no scene was given; pass {name} explicitly "
            f"({_FLAGS[name]}) or a scene"
        )

    # DICOM values (or an image's own fields when it has no DICOM tags)
    if tags is not None:
        t_sdd = tags.get("DistanceSourceToDetector")
        t_sod = tags.get("DistanceSourceToPatient")
        ermf = tags.get(_ERMF)
        img_sdd = (t_sdd, "DICOM DistanceSourceToDetector") if t_sdd else None
        img_sod = (t_sod, "DICOM DistanceSourceToPatient") if t_sod else None
    else:
        t_sdd = t_sod = ermf = None
        img_sdd = (xray.sdd_mm, "XRayImage.sdd_mm") if xray.sdd_mm else None
        img_sod = (xray.sod_mm, "XRayImage.sod_mm") if xray.sod_mm else None
    scene_sdd = (sc.sdd_mm, scene_src) if sc else None
    scene_sod = (sc.sod_mm, scene_src) if sc else None

    # tag-against-tag check (a flag for either distance settles it)
    if sdd_mm is None and sod_mm is None and t_sdd and t_sod and ermf:
        ratio = t_sdd / t_sod
        rel = abs(ermf - ratio) / ratio
        if rel > _ERMF_RTOL:
            raise XRayInputError(
                f"{src}: {_ERMF} {ermf:g} contradicts DistanceSourceToDetector / DistanceSourceToPatient "
                f"= {t_sdd:g} / {t_sod:g} = {ratio:.4g} (relative difference {rel:.1%} > {_ERMF_RTOL:.0%}); "
                f"pass --sdd / --sod to choose"
            )

    def usable_ermf(purpose: str) -> float:
        assert ermf is not None
        if ermf < 1.0:
            raise XRayInputError(
                f"{src}: {_ERMF} {ermf:g} < 1 is impossible (it is SID / SOD > 1); cannot use it for "
                f"{purpose}; pass {'--sod' if purpose == 'SOD' else '--pixel-spacing'}"
            )
        return ermf

    sdd, sdd_src = explicit("sdd_mm", sdd_mm) or img_sdd or scene_sdd or (None, "")
    if sdd is None:
        raise missing("sdd_mm")
    sod_pick = explicit("sod_mm", sod_mm) or img_sod
    if sod_pick is None and ermf:
        m = usable_ermf("SOD")
        # "DICOM DistanceSourceToDetector / ERMF", "flag --sdd / DICOM ERMF", "scene ... / DICOM ERMF"
        via = f"{sdd_src} / {_ERMF}" if sdd_src.startswith("DICOM ") else f"{sdd_src} / DICOM {_ERMF}"
        sod_pick = (sdd / m, via)
    sod, sod_src = sod_pick or scene_sod or (None, "")
    if sod is None:
        raise missing("sod_mm")

    # pixel pitch at the detector
    spacing: float | None = None
    spacing_src = ""
    chosen: tuple[str, list[float]] | None = None  # (tag, [row, col]) when read from the file
    if pixel_spacing_mm is not None:
        spacing, spacing_src = explicit("pixel_spacing_mm", pixel_spacing_mm)  # type: ignore[misc]
    elif tags is not None:
        ips, des = tags.get("ImagerPixelSpacing"), tags.get("DetectorElementSpacing")
        ps, calib = tags.get("PixelSpacing"), tags.get("PixelSpacingCalibrationType")
        if ips and des:
            _check_binning(src, ips, des)
        if ips:
            chosen, spacing_src = ("ImagerPixelSpacing", ips), "DICOM ImagerPixelSpacing"
        elif des:
            chosen, spacing_src = ("DetectorElementSpacing", des), "DICOM DetectorElementSpacing"
        elif ps and calib and ermf:
            m = usable_ermf("the pixel spacing")
            chosen = ("PixelSpacing", [ps[0] * m, ps[1] * m])
            spacing_src = f"DICOM PixelSpacing x {_ERMF}"
        elif ps:
            chosen, spacing_src = ("PixelSpacing", ps), "DICOM PixelSpacing"
            if calib:
                notes.append(
                    f"PixelSpacing is calibrated to the patient plane (PixelSpacingCalibrationType "
                    f"{calib}) but there is no {_ERMF}: used as the detector pitch"
                )
        if chosen is not None:
            rc = chosen[1]
            if not _is_square(rc):
                raise XRayInputError(
                    f"{src}: no usable pixel_spacing_mm - {chosen[0]} is anisotropic {list(rc)} mm "
                    f"(row, col); pass a square pixel_spacing_mm (--pixel-spacing) after resampling the "
                    f"image to square pixels"
                )
            spacing = 0.5 * (rc[0] + rc[1])
    elif xray.pixel_spacing_mm is not None:
        spacing, spacing_src = xray.pixel_spacing_mm, "XRayImage.pixel_spacing_mm"
    elif meta.get("pixel_spacing_anisotropic"):
        raise XRayInputError(
            f"{src}: no usable pixel_spacing_mm - {meta.get('pixel_spacing_tag')} is anisotropic "
            f"{meta.get('pixel_spacing_rc_mm')} mm (row, col); pass a square pixel_spacing_mm "
            f"(--pixel-spacing) after resampling the image to square pixels"
        )
    if spacing is None:
        if sc is None:
            raise missing("pixel_spacing_mm")
        scene_aspect = sc.height / sc.width
        if abs(H / W - scene_aspect) * min(H, W) > 1.0:
            raise XRayInputError(
                f"{src}: no pixel_spacing_mm - the image has none and its {H} x {W} pixels do not "
                f"match the aspect of the scene detector ({sc.height} x {sc.width}); pass "
                f"pixel_spacing_mm explicitly (--pixel-spacing)"
            )
        spacing, spacing_src = sc.detector_size_mm[1] / W, scene_src

    if not 0 < sod < sdd:
        raise XRayInputError(
            f"{src}: SOD {sod:g} mm ({sod_src}) >= SDD {sdd:g} mm ({sdd_src}); the geometry needs "
            f"0 < sod_mm < sdd_mm (the patient lies between source and detector)"
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
    sources = GeometrySources(float(sdd), sdd_src, float(sod), sod_src, float(spacing), spacing_src, tuple(notes))
    return geom, sources


def geometry_for(
    xray: XRayImage,
    scene: str | os.PathLike | None = "cios_fusion",
    *,
    size: tuple[int, int] | None = None,
    sdd_mm: float | None = None,
    sod_mm: float | None = None,
    pixel_spacing_mm: float | None = None,
) -> CArmGeometry:
    """The C-arm geometry of ``xray``'s detector: :func:`resolve_geometry` without the sources.

    SDD, SOD and the pixel spacing (mm) each come from the explicit argument, else the image's DICOM
    tags, else the scene (``None`` = no scene); ``size = (H, W)`` resamples the detector keeping its
    physical extent. Raises :class:`XRayInputError` as :func:`resolve_geometry` does.
    """
    return resolve_geometry(
        xray, scene, size=size, sdd_mm=sdd_mm, sod_mm=sod_mm, pixel_spacing_mm=pixel_spacing_mm
    )[0]


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
    a = np.asarray(pixels)
    name = f"pixels for {path}"
    if a.dtype.kind not in "uif" or a.dtype == np.bool_:
        raise XRayInputError(f"{name}: must be numeric, got dtype {a.dtype}")
    if a.ndim != 2:
        raise XRayInputError(f"{name}: expected (H, W), got shape {a.shape}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise XRayInputError(f"{name}: contains NaN or infinite values")
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
