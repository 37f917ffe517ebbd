"""CT input and output: NIfTI files and DICOM series to :class:`sim.ct.volume.CTVolume` (HU, LPS mm).

Conventions (the same for every source):

* ``hu[i, j, k]`` is a float32 Hounsfield value; ``affine @ (i, j, k, 1)`` is the LPS mm position of
  that voxel's centre (DICOM patient frame: +x patient left, +y posterior, +z superior).
* NIfTI: nibabel's array axis order is kept (no transposes); its affine (the sform or qform nibabel
  picks) maps to RAS mm, so ``affine_lps = diag(-1, -1, 1, 1) @ affine_ras``. Scaling
  (``scl_slope`` / ``scl_inter``) is applied.
* DICOM series (a folder): ``i`` = column index, ``j`` = row index, ``k`` = slice index in
  increasing position along the slice normal ``cross(row_dir, col_dir)`` (not InstanceNumber),
  i.e. ``hu[:, :, k] = pixel_array.T``. Affine columns: ``row_dir * PixelSpacing[1]`` (column
  spacing), ``col_dir * PixelSpacing[0]`` (row spacing), ``(IPP_last - IPP_first) / (n - 1)``;
  translation = ImagePositionPatient of the first sorted slice. DICOM patient coordinates are LPS.

HU plausibility (:func:`check_hu_plausible`): a CT must look like Hounsfield units, not a
normalised (0..1) or otherwise rescaled image. The test is robust to outliers (metal, noise)
because it uses the 1st and 99th percentiles ``p1``, ``p99``:

* ``p1`` and ``p99`` both lie inside :data:`sim.ct.volume.PLAUSIBLE_HU_RANGE`, and
* ``p99 - p1 >= 100`` HU (every CT of a body holds at least fat or air and soft tissue or bone,
  hundreds of HU apart; a 0..1 or mu-valued image spans far less).

Scanners fill the region outside the reconstruction circle with one padding value (-2000, -2048,
-3024 are common), which can fill > 1 % of the voxels: when the volume's minimum is below the
plausible range, the voxels holding exactly that minimum are left out of the percentiles (their
values are kept; the renderer clips attenuation at 0). Known limit: an image of raw stored values
(HU + 1024, 0..4095) passes this test.
"""

from __future__ import annotations

import math
import os
import zlib
from collections import defaultdict
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy import ndimage

from sim.core.atomic import atomic_path
from sim.ct.volume import PLAUSIBLE_HU_RANGE, CTInputError, CTVolume

#: RAS <-> LPS: flip x and y (its own inverse).
RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])

#: Minimum spread (HU) between the 1st and 99th percentile of a CT; see the module docstring.
MIN_HU_SPREAD = 100.0

#: Label maps and CTs must share their grid to this tolerance (mm, per affine entry).
AFFINE_TOLERANCE_MM = 1e-3

#: Resampling refuses outputs larger than this many voxels (4 GiB of float32).
MAX_RESAMPLED_VOXELS = 2**30

#: DICOM slice gaps must equal the series' median gap to max(1 % of it, 0.01 mm).
SLICE_SPACING_RTOL = 0.01
SLICE_SPACING_ATOL_MM = 0.01

#: Two DICOM slices closer than this (mm, along the slice normal) are duplicates.
DUPLICATE_TOLERANCE_MM = 0.01

#: Out-of-grid value (HU) when resampling: air.
OUTSIDE_HU = -1000.0

_BORDER_EPS = 1e-6  # voxel

_NIFTI_SUFFIXES = (".nii", ".nii.gz")


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------


def is_phantom_spec(spec) -> bool:
    """Whether a CT named on the command line is the built-in phantom (``phantom[:SEED]``)."""
    text = str(spec)
    return text == "phantom" or text.startswith("phantom:")


def load_ct_spec(spec: str | os.PathLike, *, label_map: str | os.PathLike | None = None) -> CTVolume:
    """A CT named as on the command line or in campaign files: a path, or ``phantom[:SEED]``.

    ``phantom`` / ``phantom:SEED`` is the built-in pelvis phantom (:mod:`sim.ct.phantom`, seed 0 by
    default); anything else goes to :func:`load_ct`.
    """
    text = str(spec)
    if is_phantom_spec(text):
        seed_text = text.partition(":")[2] or "0"
        try:
            seed = int(seed_text)
        except ValueError:
            raise CTInputError(f"{text!r}: the phantom seed must be an integer") from None
        if label_map is not None:
            raise CTInputError(f"{text!r}: a label map cannot be combined with the built-in phantom "
                               "(it has its own labels)")
        from sim.ct.phantom import make_pelvis_phantom  # SciPy's spatial and linalg: only for the phantom, off start-up

        return make_pelvis_phantom(seed)
    return load_ct(spec, label_map=label_map)


def load_ct(path: str | os.PathLike, *, label_map: str | os.PathLike | None = None,
            resample_mm: float | Sequence[float] | None = None,
            series_uid: str | None = None) -> CTVolume:
    """Load a CT as HU (float32) with its voxel-to-LPS-mm affine.

    Args:
        path: a NIfTI file (``.nii`` / ``.nii.gz``) or a folder holding one DICOM series.
        label_map: optional label volume (NIfTI or DICOM folder) on the CT's grid (same shape,
            affine within 1e-3 mm); stored as int32 in ``CTVolume.labels`` (0 = background).
        resample_mm: optional target spacing in mm, one value (isotropic) or 3 (along i, j, k);
            see :func:`resample`.
        series_uid: the SeriesInstanceUID to read when the DICOM folder holds several series.

    Raises:
        CTInputError: naming the file and the problem (missing, unreadable, not 3-D, NaN/inf,
            values that do not look like HU, DICOM series inconsistent or with missing slices,
            label map on another grid).
    """
    hu, affine, source = _load_any(path, series_uid=series_uid)
    check_hu_plausible(hu, source)
    labels = None
    if label_map is not None:
        labels = _load_labels(label_map, hu.shape, affine, series_uid=None)
    volume = CTVolume(hu=hu, affine=affine, source=source, labels=labels)
    if resample_mm is not None:
        volume = resample(volume, resample_mm)
    return volume


def ct_from_array(hu: np.ndarray, affine_lps: np.ndarray, source: str = "<array>",
                  labels: np.ndarray | None = None) -> CTVolume:
    """A :class:`CTVolume` from a ``(I, J, K)`` HU array and a ``(4, 4)`` voxel-to-LPS-mm affine.

    The HU values are checked as for files (finite, :func:`check_hu_plausible`); ``labels`` is
    an optional ``(I, J, K)`` integer label map (cast to int32).
    """
    arr = np.asarray(hu)
    if arr.ndim != 3:
        raise CTInputError(f"{source}: expected a 3-D HU array (I, J, K), got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise CTInputError(f"{source}: HU values must be real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float32, copy=False)
    _check_finite(arr, source)
    check_hu_plausible(arr, source)
    lab = None if labels is None else _as_int_labels(np.asarray(labels), f"{source} (labels)")
    _check_affine(affine_lps, source)
    return CTVolume(hu=arr, affine=np.asarray(affine_lps, dtype=np.float64), source=source, labels=lab)


def check_hu_plausible(hu: np.ndarray, source: str) -> None:
    """Raise :class:`CTInputError` unless ``hu`` (any shape) looks like Hounsfield units.

    Criterion (module docstring): after leaving out a single padding value below the plausible
    range, the 1st and 99th percentiles lie inside ``PLAUSIBLE_HU_RANGE`` and are at least
    ``MIN_HU_SPREAD`` HU apart. Percentiles use at most ~4 M evenly strided voxels.
    """
    lo, hi = PLAUSIBLE_HU_RANGE
    flat = np.asarray(hu).ravel()
    if flat.size == 0:
        raise CTInputError(f"{source}: the volume has no voxels")
    sample = flat[:: max(1, flat.size // 4_000_000)].astype(np.float64)
    vmin = float(np.min(flat))
    padding = ""
    if vmin < lo:
        kept = sample[sample != vmin]
        if kept.size == 0:
            raise CTInputError(f"{source}: every voxel holds {vmin:g}, which does not look like HU")
        if kept.size < sample.size:
            padding = f" (after leaving out padding value {vmin:g} in {sample.size - kept.size} sampled voxels)"
        sample = kept
    p1, p99 = (float(v) for v in np.percentile(sample, [1.0, 99.0]))
    why = None
    if not (lo <= p1 <= hi and lo <= p99 <= hi):
        why = f"outside the plausible HU range [{lo:g}, {hi:g}]"
    elif p99 - p1 < MIN_HU_SPREAD:
        why = f"less than {MIN_HU_SPREAD:g} HU apart (a CT of a body spans air/fat to tissue/bone)"
    if why is not None:
        raise CTInputError(
            f"{source}: voxel values do not look like HU: 1st percentile {p1:.4g}, 99th percentile "
            f"{p99:.4g}{padding} are {why}; is this a normalised or rescaled image rather than a CT in HU?"
        )


def resample(volume: CTVolume, spacing_mm: float | Sequence[float]) -> CTVolume:
    """Resample to a new voxel spacing (mm), keeping the grid centre and axis directions.

    Along each axis the new count is ``n' = round((n - 1) * s / s') + 1``, so the span between the
    outermost voxel centres is kept (up to rounding to whole voxels) and the grid centre in LPS
    is kept exactly; the affine's columns are scaled to the new spacing. HU use trilinear
    interpolation (``scipy.ndimage``, order 1), labels nearest neighbour; samples beyond the
    original grid's outermost voxel centres (by more than 1e-6 voxel) are -1000 HU (air) and
    label 0. With an integer refinement (3 mm -> 1 mm or
    1.5 mm) every original voxel centre is also a new one.
    """
    old_sp = volume.spacing_mm
    new_sp = _parse_spacing(spacing_mm, volume.source)
    n_old = np.array(volume.shape, dtype=np.int64)
    n_new = np.array([int(round((n - 1) * s / t)) + 1 for n, s, t in zip(n_old, old_sp, new_sp)], dtype=np.int64)
    if np.prod(n_new.astype(np.float64)) > MAX_RESAMPLED_VOXELS:
        raise CTInputError(
            f"{volume.source}: resampling {volume.shape} at {tuple(old_sp.round(4))} mm to "
            f"{tuple(new_sp)} mm gives {tuple(int(n) for n in n_new)} voxels, more than {MAX_RESAMPLED_VOXELS}"
        )
    if np.any(n_new < 2):
        raise CTInputError(f"{volume.source}: spacing {tuple(new_sp)} mm leaves fewer than 2 voxels on an axis")
    # old index = scale * new index + offset, per axis (same directions, centres aligned)
    scale = new_sp / old_sp
    offset = (n_old - 1) / 2.0 - scale * (n_new - 1) / 2.0
    shape = tuple(int(n) for n in n_new)
    # Samples within 1e-6 voxel of the border are clamped onto it (a float32-stored affine moves the
    # outermost samples by ~1e-8 voxel); samples farther out are "outside" (air, label 0).
    outside = np.zeros(shape, dtype=bool)
    for axis in range(3):
        coord = scale[axis] * np.arange(shape[axis]) + offset[axis]
        out_axis = (coord < -_BORDER_EPS) | (coord > n_old[axis] - 1 + _BORDER_EPS)
        outside |= out_axis.reshape([-1 if a == axis else 1 for a in range(3)])
    hu = ndimage.affine_transform(volume.hu, scale, offset=offset, output_shape=shape, output=np.float32,
                                  order=1, mode="nearest", prefilter=False)
    hu[outside] = OUTSIDE_HU
    labels = None
    if volume.labels is not None:
        labels = ndimage.affine_transform(np.asarray(volume.labels, dtype=np.int32), scale, offset=offset,
                                          output_shape=shape, output=np.int32, order=0, mode="nearest",
                                          prefilter=False)
        labels[outside] = 0
    affine = volume.affine.copy()
    affine[:3, :3] = volume.affine[:3, :3] * scale[None, :]
    affine[:3, 3] = volume.affine[:3, :3] @ offset + volume.affine[:3, 3]
    return CTVolume(hu=hu, affine=affine, source=volume.source, labels=labels)


def save_nifti(volume: CTVolume, path: str | os.PathLike) -> Path:
    """Write the HU volume as NIfTI-1 (RAS affine in sform and, when orthogonal, qform), atomically.

    HU are stored as int16 when every value is an integer within int16, else float32. NIfTI-1
    stores the affine in float32, so a round trip through :func:`load_ct` gives the affine to
    float32 precision (~1e-7 relative, ~1e-5 mm on 100 mm offsets) and the HU exactly.
    Returns the path written.
    """
    import nibabel as nib

    path = Path(path)
    if not path.name.lower().endswith(_NIFTI_SUFFIXES):
        raise CTInputError(f"{path}: a NIfTI file name must end in .nii or .nii.gz")
    hu = np.asarray(volume.hu, dtype=np.float32)
    info = np.iinfo(np.int16)
    if np.all(hu == np.round(hu)) and float(hu.min()) >= info.min and float(hu.max()) <= info.max:
        data = hu.astype(np.int16)
    else:
        data = hu
    ras = RAS_TO_LPS @ volume.affine
    img = nib.Nifti1Image(data, ras)
    img.header.set_xyzt_units("mm", "sec")
    img.set_sform(ras, code=1)
    directions = ras[:3, :3] / np.linalg.norm(ras[:3, :3], axis=0)
    if np.allclose(directions.T @ directions, np.eye(3), atol=1e-6):
        img.set_qform(ras, code=1)
    else:  # sheared grid (gantry tilt): the qform cannot hold it
        img.set_qform(None, code=0)
    img.header["scl_slope"] = 1.0
    img.header["scl_inter"] = 0.0
    with atomic_path(path) as tmp:
        nib.save(img, tmp)
    return path


# --------------------------------------------------------------------------------------------
# dispatch
# --------------------------------------------------------------------------------------------


def _load_any(path: str | os.PathLike, *, series_uid: str | None) -> tuple[np.ndarray, np.ndarray, str]:
    """``(hu (I, J, K) float32, affine (4, 4) LPS, source)`` from a NIfTI file or a DICOM folder."""
    p = Path(path)
    source = str(p)
    if not p.exists():
        raise CTInputError(f"{source}: file or folder not found")
    if p.is_dir():
        data, affine = _load_dicom_series(p, series_uid=series_uid)
    elif p.name.lower().endswith(_NIFTI_SUFFIXES):
        data, affine = _load_nifti(p)
    else:
        raise CTInputError(
            f"{source}: unsupported input; expected a NIfTI file (.nii, .nii.gz) or a folder holding a "
            "DICOM series (pass the folder, not one of its files)"
        )
    _check_finite(data, source)
    _check_affine(affine, source)
    return data, affine, source


def _check_affine(affine: np.ndarray, source: str) -> None:
    """One line for an affine a :class:`CTVolume` cannot use (non-finite, not homogeneous, singular)."""
    a = np.asarray(affine, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise CTInputError(f"{source}: the voxel-to-patient affine has NaN or infinite entries (a broken header)")
    if not np.allclose(a[3], (0, 0, 0, 1)):
        raise CTInputError(f"{source}: the voxel-to-patient affine's last row is {a[3].tolist()}, not 0 0 0 1")
    det = float(np.linalg.det(a[:3, :3]))
    if abs(det) < 1e-9:
        spacing = ", ".join(f"{v:.3g}" for v in np.linalg.norm(a[:3, :3], axis=0))
        raise CTInputError(f"{source}: the voxel-to-patient affine is singular (voxel spacing along i, j, k "
                           f"{spacing} mm, determinant {det:.3g} mm^3): the header's sform/qform or slice "
                           f"positions are broken")


def _check_finite(arr: np.ndarray, source: str) -> None:
    finite = np.isfinite(arr)
    if not finite.all():
        bad = np.argwhere(~finite)
        raise CTInputError(
            f"{source}: {len(bad)} voxels are NaN or infinite (first at index {tuple(int(v) for v in bad[0])})"
        )


def _load_labels(path: str | os.PathLike, shape: tuple[int, ...], affine: np.ndarray,
                 series_uid: str | None) -> np.ndarray:
    data, lab_affine, source = _load_any(path, series_uid=series_uid)
    if data.shape != tuple(shape):
        raise CTInputError(f"{source}: label map shape {data.shape} differs from the CT's shape {tuple(shape)}")
    err = float(np.max(np.abs(lab_affine - affine)))
    if err > AFFINE_TOLERANCE_MM:
        fmt = lambda m: "[" + "; ".join(" ".join(f"{v:.6g}" for v in row) for row in m[:3]) + "]"  # noqa: E731
        raise CTInputError(
            f"{source}: label map affine differs from the CT's by up to {err:.4g} mm "
            f"(tolerance {AFFINE_TOLERANCE_MM:g} mm); label map affine (LPS, rows 1-3) {fmt(lab_affine)}, "
            f"CT affine {fmt(affine)}"
        )
    return _as_int_labels(data, source)


def _as_int_labels(data: np.ndarray, source: str) -> np.ndarray:
    if not np.issubdtype(data.dtype, np.number):
        raise CTInputError(f"{source}: label map must be numeric, got dtype {data.dtype}")
    if np.issubdtype(data.dtype, np.floating):
        if not np.all(np.isfinite(data)) or not np.all(data == np.round(data)):
            raise CTInputError(f"{source}: label map values are not all integers")
    info = np.iinfo(np.int32)
    if data.size and (float(data.min()) < info.min or float(data.max()) > info.max):
        raise CTInputError(f"{source}: label values exceed the int32 range")
    return data.astype(np.int32)


def _parse_spacing(spacing_mm: float | Sequence[float], source: str) -> np.ndarray:
    try:
        sp = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,)).copy()
    except (TypeError, ValueError):
        raise CTInputError(
            f"{source}: resample_mm must be one spacing in mm or three (i, j, k), got {spacing_mm!r}"
        ) from None
    if not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise CTInputError(f"{source}: resample_mm must be positive finite mm, got {spacing_mm!r}")
    return sp


# --------------------------------------------------------------------------------------------
# NIfTI
# --------------------------------------------------------------------------------------------


def _load_nifti(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import nibabel as nib
    from nibabel.filebasedimages import ImageFileError

    try:
        img = nib.load(str(path))
        if not isinstance(img, (nib.Nifti1Image, nib.Nifti2Image)):
            raise CTInputError(f"{path}: not a NIfTI image (nibabel read it as {type(img).__name__})")
        data = np.asarray(img.get_fdata(dtype=np.float32))
        affine_ras = np.asarray(img.affine, dtype=np.float64)
    except CTInputError:
        raise
    except (OSError, EOFError, ValueError, zlib.error, ImageFileError) as exc:
        raise CTInputError(f"{path}: cannot read as a NIfTI image (not an image or corrupt file): {exc}") from None
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        what = {1: "a 1-D", 2: "a 2-D"}.get(data.ndim, f"a {data.ndim}-D")
        raise CTInputError(f"{path}: {what} image of shape {data.shape}; a CT must be 3-D (I, J, K)")
    if min(data.shape) < 2:
        raise CTInputError(f"{path}: shape {data.shape} is a 2-D image (an axis has one voxel); a CT must be 3-D")
    return np.ascontiguousarray(data, dtype=np.float32), RAS_TO_LPS @ affine_ras


# --------------------------------------------------------------------------------------------
# DICOM series
# --------------------------------------------------------------------------------------------


def _load_dicom_series(folder: Path, *, series_uid: str | None) -> tuple[np.ndarray, np.ndarray]:
    import pydicom
    from pydicom.errors import InvalidDicomError

    files = sorted(f for f in folder.iterdir() if f.is_file())
    n_dicom = 0
    series: dict[str, list[tuple[Path, object]]] = defaultdict(list)
    for f in files:
        try:
            ds = pydicom.dcmread(f, defer_size="1 KB")
        except InvalidDicomError:
            continue  # not a DICOM file (README, thumbnails, ...)
        except Exception as exc:  # a DICOM header that pydicom cannot parse
            raise CTInputError(f"{f}: DICOM file cannot be read: {exc}") from None
        n_dicom += 1
        if "PixelData" not in ds:
            continue  # DICOMDIR, structured reports, presentation states
        image_type = [str(v).upper() for v in (ds.get("ImageType") or [])]
        if "LOCALIZER" in image_type:
            continue  # scout views are images, not slices of the volume
        series[str(ds.get("SeriesInstanceUID", "") or "")].append((f, ds))
    if not series:
        what = "no DICOM files" if n_dicom == 0 else f"{n_dicom} DICOM files but no image slices with pixel data"
        raise CTInputError(
            f"{folder}: {what} found among {len(files)} files (files without the DICM header are skipped)"
        )
    if series_uid is not None:
        if series_uid not in series:
            raise CTInputError(f"{folder}: no series with SeriesInstanceUID {series_uid!r}; found {_list_series(series)}")
        slices = series[series_uid]
    elif len(series) > 1:
        raise CTInputError(
            f"{folder}: the folder holds {len(series)} DICOM series (SeriesInstanceUID: {_list_series(series)}); "
            "give a folder holding one series (copy one series' files into a folder of their own), or in Python "
            "sim.load_ct(folder, series_uid=UID)"
        )
    else:
        slices = next(iter(series.values()))
    return _assemble_series(folder, slices)


def _list_series(series: dict) -> str:
    return ", ".join(f"{uid or '<empty>'!r} ({len(v)} slices)" for uid, v in sorted(series.items()))


def _floats(ds, keyword: str, n: int, f: Path) -> np.ndarray:
    value = ds.get(keyword)
    try:
        arr = np.array([float(v) for v in value], dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise CTInputError(f"{f}: missing or invalid {keyword} ({value!r}); it is needed to place the slice")
    return arr


def _optional_float(ds, keyword: str, default: float, f: Path) -> float:
    value = ds.get(keyword)
    if value is None or value == "":
        return default
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = math.nan
    if not math.isfinite(out):
        raise CTInputError(f"{f}: invalid {keyword} {value!r}")
    return out


def _assemble_series(folder: Path, slices: list) -> tuple[np.ndarray, np.ndarray]:
    n = len(slices)
    if n < 2:
        raise CTInputError(f"{folder}: the series has a single slice ({slices[0][0].name}), a 2-D image; a CT needs >= 2")
    f0, ds0 = slices[0]
    iop0 = _floats(ds0, "ImageOrientationPatient", 6, f0)
    ps0 = _floats(ds0, "PixelSpacing", 2, f0)
    rows0, cols0 = int(ds0.get("Rows", 0)), int(ds0.get("Columns", 0))
    row_dir, col_dir = iop0[:3], iop0[3:]
    if (abs(np.linalg.norm(row_dir) - 1) > 1e-3 or abs(np.linalg.norm(col_dir) - 1) > 1e-3
            or abs(row_dir @ col_dir) > 1e-3):
        raise CTInputError(f"{f0}: ImageOrientationPatient {iop0.tolist()} is not two orthonormal direction cosines")
    if np.any(ps0 <= 0):
        raise CTInputError(f"{f0}: PixelSpacing {ps0.tolist()} must be positive mm")
    normal = np.cross(row_dir, col_dir)
    positions = []
    for f, ds in slices:
        iop = _floats(ds, "ImageOrientationPatient", 6, f)
        if not np.allclose(iop, iop0, atol=1e-4):
            raise CTInputError(f"{f}: ImageOrientationPatient {iop.tolist()} differs from {f0.name}'s {iop0.tolist()}")
        ps = _floats(ds, "PixelSpacing", 2, f)
        if not np.allclose(ps, ps0, rtol=1e-4, atol=1e-6):
            raise CTInputError(f"{f}: PixelSpacing {ps.tolist()} mm differs from {f0.name}'s {ps0.tolist()} mm")
        rows, cols = int(ds.get("Rows", 0)), int(ds.get("Columns", 0))
        if (rows, cols) != (rows0, cols0):
            raise CTInputError(f"{f}: Rows x Columns {rows} x {cols} differs from {f0.name}'s {rows0} x {cols0}")
        if int(ds.get("NumberOfFrames", 1) or 1) > 1:
            raise CTInputError(f"{f}: multi-frame (enhanced) DICOM images are not supported; export single-frame slices")
        positions.append(_floats(ds, "ImagePositionPatient", 3, f))
    ipp = np.array(positions)
    along = ipp @ normal
    order = np.argsort(along, kind="stable")
    ipp, along = ipp[order], along[order]
    slices = [slices[o] for o in order]
    gaps = np.diff(along)
    dup = np.flatnonzero(gaps <= DUPLICATE_TOLERANCE_MM)
    if dup.size:
        a = dup[0]
        raise CTInputError(
            f"{folder}: duplicate slice position {along[a]:.4f} mm along the slice normal "
            f"({slices[a][0].name} and {slices[a + 1][0].name})"
        )
    spacing = float(np.median(gaps))
    tol = max(SLICE_SPACING_RTOL * spacing, SLICE_SPACING_ATOL_MM)
    bad = np.flatnonzero(np.abs(gaps - spacing) > tol)
    if bad.size:
        a = bad[0]
        g = gaps[a]
        missing = int(round(g / spacing)) - 1
        if missing >= 1 and abs(g - (missing + 1) * spacing) <= tol * (missing + 1):
            raise CTInputError(
                f"{folder}: missing slice(s): gap of {g:.4f} mm between positions {along[a]:.4f} and "
                f"{along[a + 1]:.4f} mm along the slice normal ({slices[a][0].name}, {slices[a + 1][0].name}); "
                f"expected spacing {spacing:.4f} mm, so about {missing} slice(s) are missing"
            )
        raise CTInputError(
            f"{folder}: non-uniform slice spacing: gap of {g:.4f} mm between positions {along[a]:.4f} and "
            f"{along[a + 1]:.4f} mm along the slice normal, expected spacing {spacing:.4f} mm (tolerance {tol:.3g} mm)"
        )
    step = (ipp[-1] - ipp[0]) / (n - 1)
    drift = np.linalg.norm(ipp - (ipp[0] + np.arange(n)[:, None] * step), axis=1)
    if drift.max() > tol:
        k = int(np.argmax(drift))
        raise CTInputError(
            f"{folder}: slice {slices[k][0].name} is {drift[k]:.4f} mm off the line through the first and last "
            "ImagePositionPatient; the slices do not form a regular grid"
        )
    hu = np.empty((cols0, rows0, n), dtype=np.float32)
    for k, (f, ds) in enumerate(slices):
        try:
            pix = ds.pixel_array
        except Exception as exc:  # decoder missing or corrupt pixel data
            ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", "?")
            raise CTInputError(f"{f}: cannot decode pixel data (transfer syntax {ts}): {exc}") from None
        if pix.shape != (rows0, cols0):
            raise CTInputError(f"{f}: pixel data of shape {pix.shape}, expected one grey frame {rows0} x {cols0}")
        slope = _optional_float(ds, "RescaleSlope", 1.0, f)
        intercept = _optional_float(ds, "RescaleIntercept", 0.0, f)
        if slope == 0.0:
            raise CTInputError(f"{f}: RescaleSlope is 0")
        hu[:, :, k] = (pix.astype(np.float64) * slope + intercept).T
    affine = np.eye(4)
    affine[:3, 0] = row_dir * ps0[1]
    affine[:3, 1] = col_dir * ps0[0]
    affine[:3, 2] = step
    affine[:3, 3] = ipp[0]
    return hu, affine
