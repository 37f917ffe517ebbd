"""The CT volume held by ctxreg: Hounsfield units on a voxel grid placed in LPS millimetres."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim.core.errors import InputError

#: HU values outside this range are not plausible for a CT (air is -1000, dense metal about
#: +3000 to +4000 on a 12-bit scale, extended-range scanners reach +30000). Loaders reject
#: volumes whose robust range (1st/99th percentile) falls outside it.
PLAUSIBLE_HU_RANGE = (-1100.0, 32000.0)


class CTInputError(InputError):
    """A CT (file, array or affine) cannot be used; the message names the input and the problem."""


@dataclass(frozen=True, eq=False)
class CTVolume:
    """A CT in Hounsfield units on a regular grid.

    Attributes:
        hu: ``(I, J, K)`` float32 array of HU values; ``hu[i, j, k]`` is the voxel whose centre
            is at ``affine @ (i, j, k, 1)``.
        affine: ``(4, 4)`` float64 matrix from voxel index ``(i, j, k, 1)`` to LPS mm
            (DICOM/ITK patient frame: +x patient left, +y posterior, +z superior).
        source: where the volume came from (a file path, ``phantom:SEED``, ...), for messages
            and provenance.
        labels: optional ``(I, J, K)`` integer label map on the same grid (0 = background).
    """

    hu: np.ndarray
    affine: np.ndarray
    source: str = "<array>"
    labels: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        hu = np.asarray(self.hu)
        if hu.ndim != 3:
            raise CTInputError(f"{self.source}: expected a 3-D volume, got an array of shape {hu.shape}")
        if min(hu.shape) < 2:
            raise CTInputError(f"{self.source}: volume shape {hu.shape} has an axis shorter than 2 voxels")
        if not np.issubdtype(hu.dtype, np.number):
            raise CTInputError(f"{self.source}: voxel values must be numeric, got dtype {hu.dtype}")
        hu = hu.astype(np.float32, copy=False)
        if not np.all(np.isfinite(hu)):
            n = int(np.size(hu) - np.count_nonzero(np.isfinite(hu)))
            raise CTInputError(f"{self.source}: {n} voxels are NaN or infinite")
        affine = np.asarray(self.affine, dtype=np.float64)
        if affine.shape != (4, 4):
            raise CTInputError(f"{self.source}: affine must be 4 x 4, got shape {affine.shape}")
        if not np.all(np.isfinite(affine)) or not np.allclose(affine[3], (0, 0, 0, 1)):
            raise CTInputError(f"{self.source}: affine is not a finite homogeneous transform "
                               f"({_one_line(affine)})")
        if abs(np.linalg.det(affine[:3, :3])) < 1e-9:
            raise CTInputError(f"{self.source}: affine is singular: voxel spacing "
                               f"{np.round(np.linalg.norm(affine[:3, :3], axis=0), 6).tolist()} mm "
                               f"(a zero spacing?) ({_one_line(affine)})")
        if self.labels is not None:
            labels = np.asarray(self.labels)
            if labels.shape != hu.shape:
                raise CTInputError(
                    f"{self.source}: label map shape {labels.shape} differs from the CT's {hu.shape}"
                )
            object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "hu", hu)
        object.__setattr__(self, "affine", affine)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.hu.shape)  # type: ignore[return-value]

    @property
    def spacing_mm(self) -> np.ndarray:
        """``(3,)`` voxel spacing along i, j, k in mm."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    def voxel_to_lps(self, ijk: np.ndarray) -> np.ndarray:
        """Map ``(N, 3)`` voxel indices to ``(N, 3)`` LPS mm."""
        ijk = np.asarray(ijk, dtype=np.float64)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def lps_to_voxel(self, xyz: np.ndarray) -> np.ndarray:
        """Map ``(N, 3)`` LPS mm to ``(N, 3)`` (fractional) voxel indices."""
        xyz = np.asarray(xyz, dtype=np.float64)
        inv = np.linalg.inv(self.affine)
        return xyz @ inv[:3, :3].T + inv[:3, 3]

    def corners_lps(self) -> np.ndarray:
        """``(8, 3)`` LPS mm corners of the volume's box (outer faces of the border voxels)."""
        n = np.array(self.shape, dtype=np.float64)
        c = np.array([[a, b, d] for a in (0, 1) for b in (0, 1) for d in (0, 1)], dtype=np.float64)
        return self.voxel_to_lps(c * n - 0.5)

    def center_of_box_lps(self) -> np.ndarray:
        """``(3,)`` LPS mm centre of the voxel grid."""
        return self.voxel_to_lps((np.array(self.shape, dtype=np.float64) - 1.0)[None] / 2.0)[0]


def _one_line(m: np.ndarray) -> str:
    """A matrix as one line: rows separated by ``;``."""
    return "; ".join(" ".join(f"{v:.6g}" for v in row) for row in np.asarray(m))
