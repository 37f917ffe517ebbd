"""The anatomy centre ``c`` (LPS mm): the point the volume pose rotates about.

``c`` is the centroid of a label map (when one is given or the volume carries one), else the
centroid of the bone: the largest 26-connected component of voxels above
:data:`BONE_HU_THRESHOLD`. Centroids average voxel centres and map them to LPS through the
volume's affine (exact, the affine being linear).
"""

from __future__ import annotations

import weakref
from typing import Sequence

import numpy as np
from scipy import ndimage

from sim.errors import InputError
from sim.volume import CTVolume

#: HU above which a voxel counts as bone. Cancellous bone is about 200-400 HU and cortical bone
#: above 1000 HU, while soft tissue stays below about 100 HU, so 200 HU keeps the trabecular
#: interior of the pelvis and vertebrae. Contrast-filled vessels and bowel can exceed it, which is
#: why only the largest connected component is kept (the skeleton is one large connected piece).
BONE_HU_THRESHOLD = 200.0

#: 26-connectivity: voxels touching by a face, an edge or a corner are connected.
_CONNECTIVITY_26 = np.ones((3, 3, 3), dtype=bool)


#: Default anatomy centres known without computing (:func:`remember_center`: the CT cache's).
_KNOWN_CENTERS: "weakref.WeakKeyDictionary[CTVolume, np.ndarray]" = weakref.WeakKeyDictionary()


class AnatomyError(InputError):
    """The anatomy centre or bone mask cannot be computed (empty mask, mismatched label map)."""


def bone_mask(volume: CTVolume, threshold_hu: float = BONE_HU_THRESHOLD) -> np.ndarray:
    """``(I, J, K)`` bool: the largest 26-connected component of voxels with HU > ``threshold_hu``.

    Ties in size go to the component met first in C order. Raises :class:`AnatomyError` when no
    voxel exceeds the threshold.
    """
    threshold = float(threshold_hu)
    if not np.isfinite(threshold):
        raise AnatomyError(f"threshold_hu must be a finite HU value, got {threshold_hu!r}")
    above = np.asarray(volume.hu) > threshold
    if not above.any():
        raise AnatomyError(
            f"{volume.source}: no voxel above the bone threshold {threshold:g} HU "
            f"(max {float(np.max(volume.hu)):.1f} HU); give a label map or a lower threshold_hu"
        )
    labels, n = ndimage.label(above, structure=_CONNECTIVITY_26)
    if n == 1:
        return above
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    sizes[0] = 0
    return labels == int(np.argmax(sizes))


def remember_center(volume: CTVolume, center_lps) -> None:
    """Record ``volume``'s default anatomy centre ``(3,)`` LPS mm (bone, no label map), computed
    earlier (the CT cache, :mod:`sim.ct_cache`): :func:`anatomy_center` then returns it at once."""
    c = np.asarray(center_lps, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise AnatomyError(f"{volume.source}: an anatomy centre must be 3 finite LPS mm values, got {center_lps}")
    _KNOWN_CENTERS[volume] = c


def mask_centroid_lps(volume: CTVolume, mask: np.ndarray) -> np.ndarray:
    """``(3,)`` LPS mm centroid of the voxel centres where the ``(I, J, K)`` ``mask`` is true."""
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != volume.shape:
        raise AnatomyError(f"{volume.source}: mask shape {mask.shape} differs from the CT's {volume.shape}")
    count = int(np.count_nonzero(mask))
    if count == 0:
        raise AnatomyError(f"{volume.source}: the mask is empty; no centroid")
    # index centroid from the per-axis marginal counts (no (N, 3) index array for big masks)
    ijk = np.empty(3)
    for axis in range(3):
        other = tuple(a for a in range(3) if a != axis)
        marginal = mask.sum(axis=other, dtype=np.int64)
        ijk[axis] = float(np.dot(marginal, np.arange(mask.shape[axis], dtype=np.float64))) / count
    return volume.voxel_to_lps(ijk[None])[0]


def anatomy_center(volume: CTVolume, *, label_map: np.ndarray | None = None,
                   labels: Sequence[int] | None = None,
                   threshold_hu: float = BONE_HU_THRESHOLD) -> np.ndarray:
    """``(3,)`` LPS mm anatomy centre of ``volume``.

    Args:
        volume: the CT.
        label_map: optional ``(I, J, K)`` integer label map on the CT's grid; default
            ``volume.labels``.
        labels: label values whose union is averaged; default every non-zero label. Needs a
            label map.
        threshold_hu: bone threshold (HU) used when there is no label map; see :func:`bone_mask`.

    Raises:
        AnatomyError: the mask (labels or bone) is empty, or the label map does not fit the CT.
    """
    lab = label_map if label_map is not None else volume.labels
    if lab is None:
        if labels is not None:
            raise AnatomyError(f"{volume.source}: labels={list(labels)} given but there is no label map")
        if threshold_hu == BONE_HU_THRESHOLD and volume in _KNOWN_CENTERS:
            return _KNOWN_CENTERS[volume].copy()
        return mask_centroid_lps(volume, bone_mask(volume, threshold_hu))
    lab = np.asarray(lab)
    if lab.shape != volume.shape:
        raise AnatomyError(f"{volume.source}: label map shape {lab.shape} differs from the CT's {volume.shape}")
    if labels is None:
        mask = lab != 0
        what = "non-zero labels"
    else:
        wanted = np.asarray(list(labels))
        if wanted.ndim != 1 or wanted.size == 0:
            raise AnatomyError(f"labels must be a non-empty sequence of label values, got {labels!r}")
        mask = np.isin(lab, wanted)
        what = f"labels {wanted.tolist()}"
    if not mask.any():
        raise AnatomyError(f"{volume.source}: the label map has no voxel with {what}")
    return mask_centroid_lps(volume, mask)
