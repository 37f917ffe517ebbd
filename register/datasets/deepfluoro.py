"""The DeepFluoro data set's full-resolution HDF5 file, read into ctxreg's terms (and written).

DeepFluoro (Grupp et al., "Automatic annotation of hip anatomy in fluoroscopy for robust and
efficient 2D/3D registration", IPCAI 2020) holds six cadaver pelves imaged by a Siemens Cios
Fusion C-arm: 366 frames of 1536 x 1536 px at 0.194 mm, SDD 1020 mm, a 1 mm CT of each specimen, its
segmentation, 3-D anatomical landmarks, and each frame's ground-truth pose and 2-D landmarks, in
``ipcai_2020_full_res_data.h5``. Its layout (``hdf5_layouts/Readme.md`` of
rg2/DeepFluoroLabeling-IPCAI2020), as this module reads and writes it::

    proj-params/                 intrinsic (3, 3), extrinsic (4, 4) C-arm world -> camera,
                                 num-rows, num-cols, pixel-row-spacing, pixel-col-spacing (mm)
    <specimen>/                  e.g. 17-1882
        vol/                     pixels (Z, Y, X) HU, spacing (3,) mm (x, y, z), origin (3,) LPS mm,
                                 dir-mat (3, 3): an ITK image, index (x, y, z) -> LPS
        vol-seg/image/           the label map, the same ITK image group (uint8)
        vol-seg/labels-def/<N>   the name of label N ("left-hemipelvis", ...)
        vol-landmarks/<name>     a 3-D landmark (3,) LPS mm ("FH-l", ...)
        projections/<NNN>/       NNN = 000, 001, ...
            image/               pixels (rows, cols): raw detector intensities; spacing, origin, dir-mat
            gt-landmarks/<name>  a 2-D landmark (column, row) in the stored image's pixels
            gt-poses/            cam-to-pelvis-vol (4, 4): C-arm world -> the CT's LPS mm (and the
                                 femurs' poses, left-/right-femur-good-fov flags)
            gt-seg/              the 2-D segmentation (an ITK image group)
            rot-180-for-up       1 where the image must be turned 180 deg for the patient to be up

Vectors may be stored as columns, ``(3, 1)`` / ``(2, 1)``: the reader flattens them.

Geometry (:mod:`register.convert`, ``docs/conventions.md`` "DeepFluoro dataset"): a frame's LPS ->
camera extrinsic is ``extrinsic @ inv(cam-to-pelvis-vol)``, its projection ``K @ that[:3]``
(``K`` has negative focal lengths: the camera's +z points toward the source). ctxreg's camera sees the
detector from the source, so the ctxreg image is the stored image with its columns reversed, or,
for a frame flagged ``rot-180-for-up``, with its rows reversed (:func:`register.convert.from_deepfluoro`).
:meth:`DeepFluoroProjection.reprojection_px` measures both chains against the file's 2-D landmarks.

Example::

    from register.datasets.deepfluoro import DeepFluoroFile

    with DeepFluoroFile("ipcai_2020_full_res_data.h5") as f:
        spec = f.specimen(1)                       # or "17-1882"
        frame = spec.projection(0)
        T, geometry = frame.truth(spec.center_lps, sod_mm=700.0)  # ctxreg pose (4, 4), CArmGeometry
        xray = frame.xray(sod_mm=700.0)            # an XRayImage for register_xray

Every problem with the file (another layout, a missing specimen or dataset, a truncated file, a
wrong shape, NaN) is a :class:`DeepFluoroError` naming the file and the dataset.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from register.convert import PoseConversionError, deepfluoro_lps_extrinsic, from_deepfluoro, to_deepfluoro
from register.xray.io import XRayImage
from sim.core.atomic import atomic_path
from sim.core.errors import InputError
from sim.projection.geometry import CArmGeometry, project_points, projection_matrix
from sim.ct.volume import CTVolume

__all__ = [
    "DeepFluoroError",
    "DeepFluoroFile",
    "DeepFluoroSpecimen",
    "DeepFluoroProjection",
    "ProjectionParams",
    "SpecimenData",
    "ProjectionData",
    "write_deepfluoro",
    "itk_image_group",
    "SPECIMEN_IDS",
    "LANDMARK_NAMES",
    "LABEL_NAMES",
    "FULL_RES_FILE",
    "I0_RAW",
]

#: The full-resolution file's name as distributed.
FULL_RES_FILE = "ipcai_2020_full_res_data.h5"

#: The six specimens in the order DiffPose and xvr number them 1..6 (``diffpose/deepfluoro.py``).
SPECIMEN_IDS = ("17-1882", "18-1109", "18-0725", "18-2799", "18-2800", "17-1905")

#: The 14 landmarks of the data set (Grupp et al. 2020, Table 1): femoral heads, greater sciatic
#: notches, inferior and medial obturator foramina, superior and inferior pubic symphysis, anterior
#: superior iliac spines; ``-l`` / ``-r`` the patient's left / right.
LANDMARK_NAMES = ("FH-l", "FH-r", "GSN-l", "GSN-r", "IOF-l", "IOF-r", "MOF-l", "MOF-r", "SPS-l", "SPS-r",
                  "IPS-l", "IPS-r", "ASIS-l", "ASIS-r")

#: The label names of ``vol-seg/labels-def`` (the README's example "1 -> left-hemipelvis"; the femurs
#: are labels 5 and 6 in ``examples_dataset/full_res_3d_viz.py``). The reader takes the names from the file.
LABEL_NAMES = {1: "left-hemipelvis", 2: "right-hemipelvis", 3: "vertebrae", 4: "upper-sacrum", 5: "left-femur",
               6: "right-femur"}

#: The flat-field intensity of the raw frames that DiffPose's ``preprocess`` takes the log against.
I0_RAW = 65487.0

_PROJ_PARAMS = "proj-params"
_RIGID_TOL = 1e-4  # orthonormality of a stored rotation (float32 storage rounds at ~1e-7)


class DeepFluoroError(InputError):
    """The DeepFluoro file cannot be used as asked; the message names the file and the dataset."""


# --------------------------------------------------------------------------------------------
# Low-level reads: every failure becomes one line naming the file and the dataset
# --------------------------------------------------------------------------------------------


def _h5py():
    import h5py

    return h5py


class _Reader:
    """The open file and its name, for messages."""

    def __init__(self, path: Path):
        self.path = path
        self.name = str(path)
        h5py = _h5py()
        if not path.exists():
            raise DeepFluoroError(f"{path}: file not found")
        if path.is_dir():
            raise DeepFluoroError(f"{path}: a folder; give the DeepFluoro HDF5 file ({FULL_RES_FILE})")
        try:
            self.h5 = h5py.File(path, "r")
        except OSError as exc:
            raise DeepFluoroError(f"{path}: not a readable HDF5 file (truncated or another format?): "
                                  f"{str(exc).splitlines()[0]}") from None

    def node(self, where: str):
        try:
            return self.h5[where]
        except KeyError:
            parent, _, leaf = where.rpartition("/")
            raise DeepFluoroError(f"{self.name}: no '{where}' in the file: not the DeepFluoro full-resolution "
                                  f"layout{self._around(parent)}") from None
        except OSError as exc:  # a truncated file fails when the object's header is read
            raise DeepFluoroError(f"{self.name}: '{where}' cannot be read (truncated file?): "
                                  f"{str(exc).splitlines()[0]}") from None

    def _around(self, parent: str) -> str:
        try:
            keys = sorted(self.h5[parent].keys()) if parent else sorted(self.h5.keys())
        except (KeyError, OSError):
            return ""
        shown = ", ".join(keys[:12]) + (", ..." if len(keys) > 12 else "")
        return f" ('{parent or '/'}' holds: {shown or 'nothing'})"

    def array(self, where: str, *, shape: tuple[int, ...] | None = None, size: int | None = None,
              finite: bool = True) -> np.ndarray:
        """The dataset ``where`` as a float64 array (``size``: flattened to that many values)."""
        ds = self.node(where)
        if not hasattr(ds, "dtype"):
            raise DeepFluoroError(f"{self.name}: '{where}' is a group, expected a dataset")
        if ds.dtype.kind not in "uifb":
            raise DeepFluoroError(f"{self.name}: '{where}' holds {ds.dtype}, expected numbers")
        try:
            a = np.asarray(ds[()])
        except OSError as exc:
            raise DeepFluoroError(f"{self.name}: '{where}' cannot be read (truncated file?): "
                                  f"{str(exc).splitlines()[0]}") from None
        if size is not None:
            if a.size != size:
                raise DeepFluoroError(f"{self.name}: '{where}' has shape {a.shape}, expected {size} values")
            a = a.reshape(size)
        elif shape is not None and a.shape != shape:
            raise DeepFluoroError(f"{self.name}: '{where}' has shape {a.shape}, expected {shape}")
        if finite and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise DeepFluoroError(f"{self.name}: '{where}' holds NaN or infinite values")
        return a

    def scalar(self, where: str) -> float:
        return float(self.array(where, size=1)[0])

    def text(self, where: str) -> str:
        ds = self.node(where)
        try:
            v = ds[()]
        except OSError as exc:
            raise DeepFluoroError(f"{self.name}: '{where}' cannot be read: {str(exc).splitlines()[0]}") from None
        if isinstance(v, np.ndarray):
            v = v.reshape(-1)[0] if v.size else b""
        return v.decode("utf-8", "replace") if isinstance(v, (bytes, np.bytes_)) else str(v)

    def keys(self, where: str) -> list[str]:
        node = self.node(where)
        if not hasattr(node, "keys"):
            raise DeepFluoroError(f"{self.name}: '{where}' is a dataset, expected a group")
        return list(node.keys())

    def rigid(self, where: str) -> np.ndarray:
        M = self.array(where, shape=(4, 4)).astype(np.float64)
        R = M[:3, :3]
        err = float(np.abs(R.T @ R - np.eye(3)).max())
        if np.abs(M[3] - (0, 0, 0, 1)).max() > 1e-9 or err > _RIGID_TOL or np.linalg.det(R) < 0:
            raise DeepFluoroError(f"{self.name}: '{where}' is not a rigid transform (rotation error {err:.2g}, "
                                  f"det {np.linalg.det(R):+.3f}, last row {M[3].tolist()})")
        return M

    def image(self, where: str, *, dims: int) -> tuple[np.ndarray, np.ndarray]:
        """An ITK image group: ``(pixels as stored, index -> physical (dims + 1, dims + 1))``."""
        pixels = self.array(f"{where}/pixels", finite=True)
        if pixels.ndim != dims:
            raise DeepFluoroError(f"{self.name}: '{where}/pixels' has shape {pixels.shape}, expected {dims} axes")
        spacing = self.array(f"{where}/spacing", size=dims)
        origin = self.array(f"{where}/origin", size=dims)
        # dir-mat: the identity in every image of the data set (the README); taken as such where absent
        direction = (self.array(f"{where}/dir-mat", size=dims * dims).reshape(dims, dims)
                     if "dir-mat" in self.keys(where) else np.eye(dims))
        if np.any(spacing <= 0):
            raise DeepFluoroError(f"{self.name}: '{where}/spacing' must be positive mm, got {spacing.tolist()}")
        err = float(np.abs(direction.T @ direction - np.eye(dims)).max())
        if err > _RIGID_TOL:
            raise DeepFluoroError(f"{self.name}: '{where}/dir-mat' is not orthonormal (error {err:.2g})")
        A = np.eye(dims + 1)
        A[:dims, :dims] = direction @ np.diag(spacing)
        A[:dims, dims] = origin
        return pixels, A


# --------------------------------------------------------------------------------------------
# The file's pieces
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ProjectionParams:
    """``proj-params``: the C-arm's fixed intrinsics and world -> camera extrinsic (one per file).

    Attributes:
        intrinsic: ``(3, 3)`` ``[[-f, 0, cx], [0, -f, cy], [0, 0, 1]]`` (f > 0 px; camera +z toward the source).
        extrinsic: ``(4, 4)`` rigid, C-arm world mm -> camera mm.
        rows, cols: the detector's pixels.
        spacing_mm: the square pixel pitch at the detector (mm).
    """

    intrinsic: np.ndarray
    extrinsic: np.ndarray
    rows: int
    cols: int
    spacing_mm: float

    @property
    def focal_px(self) -> float:
        return float(-self.intrinsic[0, 0])

    @property
    def sdd_mm(self) -> float:
        """Source-to-detector distance: the focal length in px times the pixel pitch (mm)."""
        return self.focal_px * self.spacing_mm

    @property
    def principal_point(self) -> tuple[float, float]:
        """``(cx, cy)`` in the stored image's pixels (column, row)."""
        return float(self.intrinsic[0, 2]), float(self.intrinsic[1, 2])

    def to_h5(self, group) -> None:
        group["intrinsic"] = np.asarray(self.intrinsic, np.float64)
        group["extrinsic"] = np.asarray(self.extrinsic, np.float64)
        group["num-rows"] = np.int64(self.rows)
        group["num-cols"] = np.int64(self.cols)
        group["pixel-row-spacing"] = np.float64(self.spacing_mm)
        group["pixel-col-spacing"] = np.float64(self.spacing_mm)


def _read_params(r: _Reader) -> ProjectionParams:
    K = r.array(f"{_PROJ_PARAMS}/intrinsic", shape=(3, 3))
    X = r.rigid(f"{_PROJ_PARAMS}/extrinsic")
    rows, cols = r.scalar(f"{_PROJ_PARAMS}/num-rows"), r.scalar(f"{_PROJ_PARAMS}/num-cols")
    srow, scol = r.scalar(f"{_PROJ_PARAMS}/pixel-row-spacing"), r.scalar(f"{_PROJ_PARAMS}/pixel-col-spacing")
    for name, v in (("num-rows", rows), ("num-cols", cols)):
        if v != int(v) or v < 2:
            raise DeepFluoroError(f"{r.name}: '{_PROJ_PARAMS}/{name}' must be a whole number of pixels >= 2, got {v:g}")
    if not (srow > 0 and scol > 0 and math.isfinite(srow) and math.isfinite(scol)):
        raise DeepFluoroError(f"{r.name}: pixel spacings must be positive mm, got row {srow:g}, column {scol:g}")
    if abs(srow - scol) > 1e-6 * scol:
        raise DeepFluoroError(f"{r.name}: non-square pixels ({srow:g} x {scol:g} mm): ctxreg's detector has square pixels")
    fx, fy = K[0, 0], K[1, 1]
    if not (fx < 0 and abs(fx - fy) <= 1e-6 * abs(fx) and K[0, 1] == 0 and K[1, 0] == 0
            and np.allclose(K[2], (0.0, 0.0, 1.0))):
        raise DeepFluoroError(f"{r.name}: '{_PROJ_PARAMS}/intrinsic' is not DeepFluoro's [[-f, 0, cx], [0, -f, cy], "
                              f"[0, 0, 1]] with f > 0 (camera +z toward the source, square pixels): {K.tolist()}")
    return ProjectionParams(intrinsic=K, extrinsic=X, rows=int(rows), cols=int(cols), spacing_mm=float(scol))


def _vectors(r: _Reader, where: str, dims: int) -> dict[str, np.ndarray]:
    """A group of named points, each ``(dims,)`` float64 (NaN kept: the point is not given)."""
    return {name: r.array(f"{where}/{name}", size=dims, finite=False).astype(np.float64) for name in r.keys(where)}


@dataclass
class DeepFluoroProjection:
    """One frame of a specimen, as stored and in ctxreg's terms.

    Attributes:
        specimen_id, index: where it is (``<specimen>/projections/<index:03d>``).
        params: the file's :class:`ProjectionParams`.
        pixels: ``(rows, cols)`` float32: the stored raw intensities (air bright, bone dark).
        rot_180_for_up: the file's flag: the image must be turned 180 deg for the patient to be up.
        cam_to_pelvis_vol: ``(4, 4)`` C-arm world -> the CT's LPS mm (the ground truth).
        landmarks_px: ``{name: (2,)}`` the 2-D landmarks (column, row) in the stored image's pixels.
        femurs: ``{"left"|"right": ((4, 4) cam-to-femur-vol, good_fov bool)}`` where the file has them.
        source: ``file:specimen/projections/NNN`` for messages.
    """

    specimen_id: str
    index: int
    params: ProjectionParams
    pixels: np.ndarray
    rot_180_for_up: bool
    cam_to_pelvis_vol: np.ndarray
    landmarks_px: dict[str, np.ndarray]
    femurs: dict[str, tuple[np.ndarray, bool]] = field(default_factory=dict)
    source: str = ""

    @property
    def extrinsic_lps(self) -> np.ndarray:
        """``(4, 4)`` LPS mm -> DeepFluoro camera mm: ``extrinsic @ inv(cam-to-pelvis-vol)``."""
        return deepfluoro_lps_extrinsic(self.params.extrinsic, self.cam_to_pelvis_vol)

    def projection_matrix(self) -> np.ndarray:
        """``(3, 4)`` LPS mm (homogeneous) -> the stored image's pixels: ``K @ extrinsic_lps[:3]``."""
        return self.params.intrinsic @ self.extrinsic_lps[:3]

    def visible(self, uv: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: the ``(N, 2)`` pixel coordinates (column, row) that fall on the detector."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return (np.isfinite(uv).all(axis=1) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= self.params.cols - 0.5)
                    & (uv[:, 1] >= -0.5) & (uv[:, 1] <= self.params.rows - 0.5))

    # ---- ctxreg's terms

    def to_ctxreg_px(self, uv: np.ndarray) -> np.ndarray:
        """``(N, 2)`` stored pixel coordinates (column, row) -> ctxreg's image (columns reversed, or rows
        where the frame is flagged ``rot-180-for-up``)."""
        uv = np.array(uv, np.float64).reshape(-1, 2)
        if self.rot_180_for_up:
            uv[:, 1] = self.params.rows - 1 - uv[:, 1]
        else:
            uv[:, 0] = self.params.cols - 1 - uv[:, 0]
        return uv

    def ctxreg_pixels(self) -> np.ndarray:
        """``(rows, cols)`` float32: the image ctxreg's camera sees (:func:`register.convert.from_deepfluoro`)."""
        flipped = self.pixels[::-1, :] if self.rot_180_for_up else self.pixels[:, ::-1]
        return np.ascontiguousarray(flipped)

    def truth(self, center_lps, *, sod_mm: float) -> tuple[np.ndarray, CArmGeometry]:
        """ctxreg's ground-truth pose ``T`` ``(4, 4)`` about ``center_lps`` ``(3,)`` LPS mm, and the
        :class:`sim.projection.geometry.CArmGeometry` of the ctxreg image (``sod_mm``: the isocentre distance
        the pose parameters are written against; it changes no projection)."""
        try:
            return from_deepfluoro(self.extrinsic_lps, self.params.intrinsic, center_lps, height=self.params.rows,
                                   width=self.params.cols, pixel_spacing_mm=self.params.spacing_mm, sod_mm=sod_mm,
                                   rot_180_for_up=self.rot_180_for_up)
        except PoseConversionError as exc:
            raise DeepFluoroError(f"{self.source}: {exc}") from None

    def xray(self, *, sod_mm: float | None = None, border_px: int = 0) -> XRayImage:
        """The frame as an :class:`register.xray.io.XRayImage` in ctxreg's view: raw intensities
        (``attenuation_bright`` False), the detector's pitch and SDD from ``proj-params``, ``sod_mm``
        (None: the scene's at registration). ``border_px``: pixels cut from every side (the
        collimator's border; the same on all sides, so the principal point stays the centre)."""
        b = int(border_px)
        if b < 0 or 2 * b > min(self.params.rows, self.params.cols) - 32:
            raise DeepFluoroError(f"{self.source}: border_px {border_px} leaves less than 32 px of the "
                                  f"{self.params.rows} x {self.params.cols} frame")
        pixels = self.ctxreg_pixels()
        if b:
            pixels = np.ascontiguousarray(pixels[b:-b, b:-b])
        return XRayImage(pixels=pixels, attenuation_bright=False,
                         pixel_spacing_mm=self.params.spacing_mm, sdd_mm=self.params.sdd_mm, sod_mm=sod_mm,
                         source=self.source,
                         meta={"format": "deepfluoro-hdf5", "specimen": self.specimen_id, "projection": self.index,
                               "rot_180_for_up": self.rot_180_for_up, "border_px": b,
                               "stored_to_ctxreg": "rows reversed" if self.rot_180_for_up else "columns reversed"})

    def reprojection_px(self, landmarks_lps: dict[str, np.ndarray]) -> dict[str, float | int]:
        """The file's geometry checked on its own landmarks: the 3-D landmarks projected with the
        intrinsics and the ground-truth pose against the 2-D landmarks, in pixels.

        ``stored``: ``K @ (extrinsic @ inv(cam-to-pelvis-vol))[:3]`` in the stored image;
        ``ctxreg``: the same points through ctxreg's pose and geometry (:meth:`truth`) against the 2-D
        landmarks moved into ctxreg's image. Means and maxima over the landmarks that have both a 3-D
        and a 2-D point on the detector; ``count`` is their number (0: the means are NaN)."""
        names = [n for n in landmarks_lps if n in self.landmarks_px]
        X = np.array([landmarks_lps[n] for n in names], np.float64).reshape(-1, 3)
        uv = np.array([self.landmarks_px[n] for n in names], np.float64).reshape(-1, 2)
        keep = self.visible(uv) & np.isfinite(X).all(axis=1)
        X, uv = X[keep], uv[keep]
        if not len(X):
            return {"count": 0, "stored_mean_px": math.nan, "stored_max_px": math.nan, "ctxreg_mean_px": math.nan,
                    "ctxreg_max_px": math.nan}
        P = self.projection_matrix()
        h = np.c_[X, np.ones(len(X))] @ P.T
        stored = np.linalg.norm(h[:, :2] / h[:, 2:] - uv, axis=1)
        center = X.mean(axis=0)
        T, g = self.truth(center, sod_mm=self.params.sdd_mm / 2)  # the SOD changes no projection
        ours = np.linalg.norm(project_points(projection_matrix(g, T, center), X) - self.to_ctxreg_px(uv), axis=1)
        return {"count": int(len(X)), "stored_mean_px": float(stored.mean()), "stored_max_px": float(stored.max()),
                "ctxreg_mean_px": float(ours.mean()), "ctxreg_max_px": float(ours.max())}


@dataclass
class DeepFluoroSpecimen:
    """One specimen: its CT (with the segmentation as label map), landmarks and frames.

    Attributes:
        id: the group's name (e.g. ``17-1882``); number: 1-6 in DiffPose's and xvr's numbering, or None.
        volume: :class:`sim.ct.volume.CTVolume` (HU, LPS affine from the ITK group, ``labels`` = the
            segmentation where the file has one on the CT's grid).
        labels_def: ``{label: name}`` from ``vol-seg/labels-def``.
        landmarks_lps: ``{name: (3,)}`` LPS mm.
        center_lps: ``(3,)`` the anatomy centre: the centroid of the labels named "*pelvis*" (the
            hemipelves), else of the bone (:func:`sim.ct.anatomy.anatomy_center`).
        center_from: what the centre is the centroid of, in words.
    """

    id: str
    number: int | None
    volume: CTVolume | None
    labels_def: dict[int, str]
    landmarks_lps: dict[str, np.ndarray]
    center_lps: np.ndarray | None
    center_from: str
    projection_names: list[str]
    _file: "DeepFluoroFile" = field(repr=False, default=None)  # type: ignore[assignment]

    def __len__(self) -> int:
        return len(self.projection_names)

    def projection(self, index: int, *, pixels: bool = True) -> DeepFluoroProjection:
        """Frame ``index`` (``projections/<index:03d>``), read now (``pixels=False``: all but the image,
        whose ``pixels`` are then ``(0, 0)``)."""
        name = f"{int(index):03d}"
        if name not in self.projection_names:
            raise DeepFluoroError(f"{self._file.path}: specimen {self.id} has no projection {name} (it has "
                                  f"{len(self.projection_names)}: {self.projection_names[0]}..{self.projection_names[-1]})")
        return self._file._projection(self.id, name, pixels=pixels)

    def __iter__(self) -> Iterator[DeepFluoroProjection]:
        for name in self.projection_names:
            yield self._file._projection(self.id, name)

    def landmark_array(self) -> tuple[list[str], np.ndarray]:
        """``(names, (N, 3) LPS mm)`` of the landmarks with finite coordinates."""
        names = [n for n, p in self.landmarks_lps.items() if np.isfinite(p).all()]
        return names, np.array([self.landmarks_lps[n] for n in names], np.float64).reshape(-1, 3)


class DeepFluoroFile:
    """The full-resolution DeepFluoro HDF5 file, opened read-only (a context manager).

    ``specimens``: the specimen groups' names in the file's order. :meth:`specimen` takes a name or
    a number 1-6 (:data:`SPECIMEN_IDS`' order, DiffPose's and xvr's). Raises :class:`DeepFluoroError`
    when the file is missing, not HDF5, truncated, or of another layout (the preprocessed
    ``ipcai_2020_ds_*.h5`` files are named as such).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._r = _Reader(self.path)
        top = list(self._r.h5.keys())
        if _PROJ_PARAMS not in top:
            if "land-names" in top:
                raise DeepFluoroError(f"{self.path}: a preprocessed DeepFluoro file (land-names, projs, segs, lands: "
                                      f"no CT, no poses); ctxreg needs the full-resolution file {FULL_RES_FILE}")
            shown = ", ".join(sorted(top)[:10]) or "nothing"
            raise DeepFluoroError(f"{self.path}: not the DeepFluoro full-resolution layout: no '{_PROJ_PARAMS}' group "
                                  f"at the top (it holds: {shown}); see hdf5_layouts/Readme.md of "
                                  f"rg2/DeepFluoroLabeling-IPCAI2020")
        self.params = _read_params(self._r)
        self.specimens = [k for k in top if k != _PROJ_PARAMS]
        if not self.specimens:
            raise DeepFluoroError(f"{self.path}: no specimen group beside '{_PROJ_PARAMS}'")

    def __enter__(self) -> "DeepFluoroFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._r.h5.close()

    def resolve(self, key: str | int) -> str:
        """A specimen's group name from its name or its number 1-6; :class:`DeepFluoroError` otherwise."""
        text = str(key).strip()
        if text in self.specimens:
            return text
        if text.isdigit() and 1 <= int(text) <= len(SPECIMEN_IDS) and SPECIMEN_IDS[int(text) - 1] in self.specimens:
            return SPECIMEN_IDS[int(text) - 1]
        numbered = [f"{i + 1} = {s}" for i, s in enumerate(SPECIMEN_IDS) if s in self.specimens]
        raise DeepFluoroError(f"{self.path}: no specimen {text!r}; the file has {', '.join(self.specimens)}"
                              + (f" (numbers: {', '.join(numbered)})" if numbered else ""))

    def specimen(self, key: str | int, *, ct: bool = True, log=None) -> DeepFluoroSpecimen:
        """The specimen ``key`` (name or number 1-6) with its CT, segmentation and landmarks read
        (``ct=False``: the landmarks and the frames' list only; ``volume`` and ``center_lps`` are None)."""
        from sim.ct.anatomy import anatomy_center, bone_mask, mask_centroid_lps  # loads SciPy: imported where first needed (start-up)
        from sim.ct.io import ct_from_array  # loads SciPy: imported where first needed (start-up)

        sid = self.resolve(key)
        r = self._r
        number = SPECIMEN_IDS.index(sid) + 1 if sid in SPECIMEN_IDS else None
        landmarks = _vectors(r, f"{sid}/vol-landmarks", 3) if "vol-landmarks" in r.keys(sid) else {}
        if not landmarks:
            raise DeepFluoroError(f"{r.name}: specimen {sid} has no 'vol-landmarks': the mTRE needs them")
        names = sorted(r.keys(f"{sid}/projections"), key=lambda s: (len(s), s))
        if not names:
            raise DeepFluoroError(f"{r.name}: specimen {sid} has no projections")
        if not ct:
            return DeepFluoroSpecimen(id=sid, number=number, volume=None, labels_def={}, landmarks_lps=landmarks,
                                      center_lps=None, center_from="", projection_names=names, _file=self)
        hu_zyx, A = r.image(f"{sid}/vol", dims=3)
        hu = np.ascontiguousarray(hu_zyx.transpose(2, 1, 0), dtype=np.float32)  # (X, Y, Z) = index (i, j, k)
        labels, labels_def = None, {}
        if "vol-seg" in r.keys(sid):
            seg_zyx, A_seg = r.image(f"{sid}/vol-seg/image", dims=3)
            if seg_zyx.shape != hu_zyx.shape or np.abs(A_seg - A).max() > 1e-3:
                raise DeepFluoroError(f"{r.name}: '{sid}/vol-seg/image' is not on the CT's grid (shape {seg_zyx.shape} "
                                      f"against {hu_zyx.shape})")
            if np.any(seg_zyx != np.round(seg_zyx)) or seg_zyx.min() < 0:
                raise DeepFluoroError(f"{r.name}: '{sid}/vol-seg/image/pixels' must hold whole label numbers >= 0")
            labels = np.ascontiguousarray(seg_zyx.transpose(2, 1, 0)).astype(np.int32)
            if "labels-def" in r.keys(f"{sid}/vol-seg"):
                for k in r.keys(f"{sid}/vol-seg/labels-def"):
                    if not k.isdigit():
                        raise DeepFluoroError(f"{r.name}: '{sid}/vol-seg/labels-def/{k}': label names are keyed by number")
                    labels_def[int(k)] = r.text(f"{sid}/vol-seg/labels-def/{k}")
        try:
            volume = ct_from_array(hu, A, source=f"{self.path}:{sid}/vol", labels=labels)
        except InputError as exc:
            raise DeepFluoroError(str(exc)) from None
        pelvis = [k for k, name in labels_def.items() if "pelvis" in name.lower()]
        if labels is not None and pelvis and np.isin(labels, pelvis).any():
            center = anatomy_center(volume, labels=pelvis)
            center_from = "the pelvis labels " + ", ".join(f"{k} ({labels_def[k]})" for k in sorted(pelvis))
        else:
            center = mask_centroid_lps(volume, bone_mask(volume))
            center_from = "the bone (no label named '*pelvis*' in vol-seg)"
        if log is not None:
            log(f"specimen {sid}: CT {volume.shape} at {np.round(volume.spacing_mm, 3).tolist()} mm, "
                f"{len(landmarks)} landmarks, {len(names)} frames; anatomy centre from {center_from}")
        return DeepFluoroSpecimen(id=sid, number=number, volume=volume, labels_def=labels_def, landmarks_lps=landmarks,
                                  center_lps=np.asarray(center, np.float64), center_from=center_from,
                                  projection_names=names, _file=self)

    def _projection(self, sid: str, name: str, *, pixels: bool = True) -> DeepFluoroProjection:
        r = self._r
        base = f"{sid}/projections/{name}"
        p = self.params
        if pixels:  # the detector's spacing is proj-params'; the group's own spacing / origin are not needed
            pixels = r.array(f"{base}/image/pixels")
            if pixels.ndim != 2:
                raise DeepFluoroError(f"{r.name}: '{base}/image/pixels' has shape {pixels.shape}, expected 2 axes")
        else:
            shape = getattr(r.node(f"{base}/image/pixels"), "shape", None)
            pixels = np.zeros((0, 0), np.float32)
            if shape != (p.rows, p.cols):
                raise DeepFluoroError(f"{r.name}: '{base}/image/pixels' is {shape}, proj-params say {(p.rows, p.cols)}")
        if pixels.size and pixels.shape != (p.rows, p.cols):
            raise DeepFluoroError(f"{r.name}: '{base}/image/pixels' is {pixels.shape}, proj-params say "
                                  f"{(p.rows, p.cols)}")
        # rot-180-for-up: in every frame of the data set; a file without it has its frames upright
        flag = r.scalar(f"{base}/rot-180-for-up") if "rot-180-for-up" in r.keys(base) else 0.0
        if flag not in (0.0, 1.0):
            raise DeepFluoroError(f"{r.name}: '{base}/rot-180-for-up' must be 0 or 1, got {flag:g}")
        pose = r.rigid(f"{base}/gt-poses/cam-to-pelvis-vol")
        femurs = {}
        poses = r.keys(f"{base}/gt-poses")
        for side in ("left", "right"):
            if f"cam-to-{side}-femur-vol" in poses:
                good = r.scalar(f"{base}/gt-poses/{side}-femur-good-fov") if f"{side}-femur-good-fov" in poses else 0
                femurs[side] = (r.rigid(f"{base}/gt-poses/cam-to-{side}-femur-vol"), bool(good))
        marks = _vectors(r, f"{base}/gt-landmarks", 2) if "gt-landmarks" in r.keys(base) else {}
        return DeepFluoroProjection(specimen_id=sid, index=int(name), params=p, pixels=pixels.astype(np.float32),
                                    rot_180_for_up=bool(flag), cam_to_pelvis_vol=pose, landmarks_px=marks,
                                    femurs=femurs, source=f"{self.path}:{base}")


# --------------------------------------------------------------------------------------------
# Writing the layout (synthetic files: tests, benchmarks, a user's own cases)
# --------------------------------------------------------------------------------------------


@dataclass
class ProjectionData:
    """One frame to write. ``pixels`` ``(rows, cols)`` as stored (DeepFluoro's view, raw intensity);
    ``cam_to_pelvis_vol`` ``(4, 4)``; ``landmarks_px`` ``{name: (2,)}`` (column, row), stored pixels."""

    pixels: np.ndarray
    cam_to_pelvis_vol: np.ndarray
    landmarks_px: dict[str, np.ndarray]
    rot_180_for_up: bool = False
    segmentation: np.ndarray | None = None


@dataclass
class SpecimenData:
    """One specimen to write: the CT (its ``labels`` become ``vol-seg``), label names, 3-D landmarks
    (LPS mm) and frames."""

    id: str
    volume: CTVolume
    landmarks_lps: dict[str, np.ndarray]
    projections: Sequence[ProjectionData]
    labels_def: dict[int, str] = field(default_factory=lambda: dict(LABEL_NAMES))


def itk_image_group(group, pixels: np.ndarray, affine: np.ndarray) -> None:
    """Write an ITK image group (``pixels``, ``spacing``, ``origin``, ``dir-mat``; vectors as columns)
    from ``pixels`` in index order reversed (``(Z, Y, X)`` or ``(rows, cols)``) and the index ->
    physical ``affine`` ``(d + 1, d + 1)``."""
    d = affine.shape[0] - 1
    spacing = np.linalg.norm(affine[:d, :d], axis=0)
    group["pixels"] = pixels
    group["spacing"] = spacing.reshape(d, 1)
    group["origin"] = np.asarray(affine[:d, d], np.float64).reshape(d, 1)
    group["dir-mat"] = affine[:d, :d] / spacing


def write_deepfluoro(path: str | os.PathLike, params: ProjectionParams, specimens: Sequence[SpecimenData]) -> Path:
    """Write ``specimens`` in the full-resolution layout (module docstring) to ``path``, atomically.

    The CT is written as stored (``hu`` transposed to ``(Z, Y, X)``) with its affine's direction
    (the real file's is the identity); landmarks and spacings as column vectors, as in the real file."""
    h5py = _h5py()
    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            params.to_h5(f.create_group(_PROJ_PARAMS))
            for spec in specimens:
                g = f.create_group(spec.id)
                vol = spec.volume
                itk_image_group(g.create_group("vol"), np.ascontiguousarray(vol.hu.transpose(2, 1, 0), np.float32),
                                vol.affine)
                seg = g.create_group("vol-seg")
                if vol.labels is not None:
                    itk_image_group(seg.create_group("image"),
                                    np.ascontiguousarray(vol.labels.transpose(2, 1, 0)).astype(np.uint8), vol.affine)
                defs = seg.create_group("labels-def")
                for k, name in spec.labels_def.items():
                    defs[str(int(k))] = name
                marks = g.create_group("vol-landmarks")
                for name, p in spec.landmarks_lps.items():
                    marks[name] = np.asarray(p, np.float64).reshape(3, 1)
                projs = g.create_group("projections")
                pixel = np.diag([params.spacing_mm, params.spacing_mm, 1.0])
                for i, pd in enumerate(spec.projections):
                    pg = projs.create_group(f"{i:03d}")
                    itk_image_group(pg.create_group("image"), np.asarray(pd.pixels, np.float32), pixel)
                    lm = pg.create_group("gt-landmarks")
                    for name, uv in pd.landmarks_px.items():
                        lm[name] = np.asarray(uv, np.float64).reshape(2, 1)
                    gp = pg.create_group("gt-poses")
                    gp["cam-to-pelvis-vol"] = np.asarray(pd.cam_to_pelvis_vol, np.float64)
                    for side in ("left", "right"):  # the femurs move with the pelvis here
                        gp[f"cam-to-{side}-femur-vol"] = np.asarray(pd.cam_to_pelvis_vol, np.float64)
                        gp[f"{side}-femur-good-fov"] = np.uint8(0)
                    seg2 = (np.zeros(np.shape(pd.pixels), np.uint8) if pd.segmentation is None
                            else np.asarray(pd.segmentation, np.uint8))
                    itk_image_group(pg.create_group("gt-seg"), seg2, pixel)
                    pg["rot-180-for-up"] = np.uint8(bool(pd.rot_180_for_up))
    return path


def projection_params_for(geometry: CArmGeometry, *, extrinsic: np.ndarray) -> ProjectionParams:
    """The :class:`ProjectionParams` of a ctxreg detector ``geometry`` (DeepFluoro's intrinsic of the
    same detector: :func:`register.convert.to_deepfluoro`) with the C-arm world -> camera ``extrinsic``."""
    _, K = to_deepfluoro(np.eye(4), geometry, np.zeros(3))
    return ProjectionParams(intrinsic=K, extrinsic=np.asarray(extrinsic, np.float64), rows=geometry.height,
                            cols=geometry.width, spacing_mm=geometry.pixel_spacing_mm)
