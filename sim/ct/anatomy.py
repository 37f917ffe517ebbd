"""The anatomy centre ``c`` (LPS mm): the point the volume pose rotates about.

``c`` is found in this order (:func:`find_center`; each result says how it was found):

1. **given**: a centre the user states (``--center X Y Z``, LPS mm);
2. **labels**: the centroid of a label map's labels (given, or carried by the volume; the
   DeepFluoro reader passes its pelvis labels);
3. **bone**: the centroid of the pelvis's bone pieces found in the CT alone
   (:func:`pelvis_mask`): the union of the bone pieces (hip bones and sacrum may be separate
   pieces), without the table, contrast-filled organs, metal and small specks, restricted to the
   pelvic girdle's levels (the lumbar spine and ribs above, where the bone is narrow, are left
   out), with the proximal femora that leave the scan below followed up to the hip joint and
   left out;
   On a CT of another region (a chest, an abdomen) the same steps keep the bone at the widest
   levels (the rib cage); where even that fails, the centroid of the largest connected bone
   piece (:func:`bone_mask`).

Centroids average voxel centres and map them to LPS through the volume's affine (exact, the
affine being linear).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import ndimage

from sim.core.errors import InputError
from sim.ct.volume import CTVolume

#: HU above which a voxel counts as bone. Cancellous bone is about 200-400 HU and cortical bone
#: above 1000 HU, while soft tissue stays below about 100 HU, so 200 HU keeps the trabecular
#: interior of the pelvis and vertebrae. Contrast-filled vessels and bowel can exceed it, which
#: :func:`pelvis_mask` handles by the pieces' sizes and texture.
BONE_HU_THRESHOLD = 200.0

#: HU above which a voxel is metal, not bone: dense cortical bone stays below about 2000 HU, while
#: steel and titanium implants read 3000 HU and more (many scanners saturate at 3071).
METAL_HU = 2500.0

#: A bone piece of the pelvis holds at least this volume (ml) and this fraction of the largest
#: piece: smaller pieces are calcifications, contrast in small vessels, noise or cut-off tips.
MIN_PIECE_ML = 5.0
MIN_PIECE_FRACTION = 0.02

#: A piece whose thickness (the standard deviation of its voxels along its thinnest principal
#: axis) is below this fraction of its breadth (the middle axis's), the breadth above
#: :data:`TABLE_MIN_BREADTH_MM`, is a flat plate: the patient table, not bone (a hip bone's
#: ratio is about 0.5, a table's below 0.1).
TABLE_MAX_THINNESS = 0.15
TABLE_MIN_BREADTH_MM = 40.0

#: A piece whose interior (voxels with all six neighbours in the piece) spreads less than this
#: between its 10th and 90th HU percentiles is a contrast-filled organ or vessel: bone's interior
#: mixes cancellous (200-400 HU) and cortical (above 800 HU) bone.
CONTRAST_MAX_SPREAD_HU = 150.0

#: The pelvic girdle's levels: axial slices whose bone spans at least this fraction of the widest
#: slice's left-right width (iliac wings, acetabula, trochanters: 200-300 mm; a lumbar vertebra
#: 50-130 mm).
GIRDLE_WIDTH_FRACTION = 0.5
#: Narrow gaps (mm) inside the girdle's levels that do not split it.
GIRDLE_GAP_MM = 10.0

#: A femur followed up from the scan's lower edge stops where its axial cross-section grows by more
#: than this factor from one slice to the next (it has joined the hip bone at the joint) or is no
#: more than this far (mm) from the girdle's midline.
FEMUR_MAX_GROWTH = 1.6
FEMUR_MIN_LATERAL_MM = 40.0

#: 26-connectivity: voxels touching by a face, an edge or a corner are connected.
_CONNECTIVITY_26 = np.ones((3, 3, 3), dtype=bool)

#: How each kind of centre is named in outputs (``anatomy_center_how``).
CENTER_METHODS = ("given", "labels", "bone")


@dataclass(frozen=True)
class Center:
    """An anatomy centre and how it was found.

    Attributes:
        lps_mm: ``(3,)`` float64 LPS mm.
        method: one of :data:`CENTER_METHODS`.
        detail: one line saying how (what was averaged, what was left out).
    """

    lps_mm: np.ndarray
    method: str
    detail: str

    def describe(self) -> str:
        """``"LPS (x, y, z) mm, <method>: <detail>"``."""
        x, y, z = (float(v) for v in self.lps_mm)
        return f"LPS ({x:.1f}, {y:.1f}, {z:.1f}) mm, {self.method}: {self.detail}"

    def to_dict(self) -> dict:
        """``{"anatomy_center_lps_mm", "anatomy_center_how"}`` for JSON outputs."""
        return {"anatomy_center_lps_mm": [float(v) for v in self.lps_mm],
                "anatomy_center_how": f"{self.method}: {self.detail}"}


#: Default anatomy centres known without computing (:func:`remember_center`: the CT cache's).
_KNOWN_CENTERS: "weakref.WeakKeyDictionary[CTVolume, Center]" = weakref.WeakKeyDictionary()


class AnatomyError(InputError):
    """The anatomy centre or bone mask cannot be computed (empty mask, mismatched label map)."""


def _check_threshold(threshold_hu) -> float:
    threshold = float(threshold_hu)
    if not np.isfinite(threshold):
        raise AnatomyError(f"threshold_hu must be a finite HU value, got {threshold_hu!r}")
    return threshold


def _no_bone(volume: CTVolume, threshold: float) -> AnatomyError:
    return AnatomyError(
        f"{volume.source}: no voxel above the bone threshold {threshold:g} HU "
        f"(max {float(np.max(volume.hu)):.1f} HU); give a label map, --center X Y Z or a lower threshold_hu")


def bone_mask(volume: CTVolume, threshold_hu: float = BONE_HU_THRESHOLD) -> np.ndarray:
    """``(I, J, K)`` bool: the largest 26-connected component of voxels with HU > ``threshold_hu``.

    Ties in size go to the component met first in C order. Raises :class:`AnatomyError` when no
    voxel exceeds the threshold.
    """
    threshold = _check_threshold(threshold_hu)
    above = np.asarray(volume.hu) > threshold
    if not above.any():
        raise _no_bone(volume, threshold)
    labels, n = ndimage.label(above, structure=_CONNECTIVITY_26)
    if n == 1:
        return above
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    sizes[0] = 0
    return labels == int(np.argmax(sizes))


def remember_center(volume: CTVolume, center_lps, how: str = "bone: stored with the CT") -> None:
    """Record ``volume``'s default anatomy centre ``(3,)`` LPS mm (no label map), computed earlier
    (the CT cache, :mod:`sim.ct.cache`) with ``how`` (``"<method>: <detail>"``, as
    :meth:`Center.to_dict` writes it): :func:`find_center` then returns it at once."""
    c = np.asarray(center_lps, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise AnatomyError(f"{volume.source}: an anatomy centre must be 3 finite LPS mm values, got {center_lps}")
    method, _, detail = str(how).partition(": ")
    if method not in CENTER_METHODS:
        method, detail = "bone", str(how)
    _KNOWN_CENTERS[volume] = Center(c, method, detail or "stored with the CT")


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


def _pieces(volume: CTVolume, threshold: float) -> tuple[np.ndarray, list[str]]:
    """``(I, J, K)`` bool union of the bone pieces (module doc, 3.) and what was left out."""
    hu = np.asarray(volume.hu)
    above = (hu > threshold) & (hu < METAL_HU)
    metal = int(np.count_nonzero(hu >= METAL_HU))
    labels, n = ndimage.label(above, structure=_CONNECTIVITY_26)
    if n == 0:
        raise _no_bone(volume, threshold)
    voxel_ml = abs(float(np.linalg.det(volume.affine[:3, :3]))) / 1000.0
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    sizes[0] = 0
    left = {"small": 0, "table": 0, "contrast": 0}
    keep = np.zeros(n + 1, bool)
    slices = ndimage.find_objects(labels)
    for k in np.flatnonzero(sizes >= MIN_PIECE_ML / voxel_ml):
        box = slices[k - 1]
        piece = labels[box] == k
        idx = np.argwhere(piece) + np.array([s.start for s in box])
        lps = volume.voxel_to_lps(idx[:: max(1, len(idx) // 20000)].astype(np.float64))
        sd = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(lps.T)), 0.0))  # ascending
        if sd[1] > TABLE_MIN_BREADTH_MM and sd[0] < TABLE_MAX_THINNESS * sd[1]:
            left["table"] += 1
            continue
        inner = ndimage.binary_erosion(piece, structure=ndimage.generate_binary_structure(3, 1))
        values = hu[box][inner] if inner.sum() >= 20 else hu[box][piece]
        p10, p90 = np.percentile(values, [10, 90])
        if p90 - p10 < CONTRAST_MAX_SPREAD_HU:
            left["contrast"] += 1
            continue
        keep[k] = True
    if keep.any():  # pieces far smaller than the largest bone piece are tips and specks too
        small = keep & (sizes < MIN_PIECE_FRACTION * sizes[keep].max())
        keep &= ~small
    left["small"] = int(np.count_nonzero(sizes > 0)) - int(keep.sum()) - left["table"] - left["contrast"]
    if not keep.any():
        raise AnatomyError(f"{volume.source}: no bone piece of at least {MIN_PIECE_ML:g} ml above {threshold:g} HU "
                           "(only table, contrast or specks); give a label map or --center X Y Z")
    notes = [f"{int(keep.sum())} bone piece{'s' if keep.sum() > 1 else ''}"]
    notes += [f"{v} {k} piece{'s' if v > 1 else ''} left out" for k, v in left.items() if v]
    if metal:
        notes.append(f"{metal * voxel_ml:.1f} ml of metal left out")
    return keep[labels], notes


def _runs(flags: np.ndarray, max_gap: int) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` of the runs of True in ``flags`` (gaps of at most ``max_gap`` closed)."""
    on = np.flatnonzero(flags)
    if on.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(on) > max_gap + 1)
    starts = np.concatenate([[on[0]], on[breaks + 1]])
    stops = np.concatenate([on[breaks], [on[-1]]]) + 1
    return list(zip(starts.tolist(), stops.tolist()))


def pelvis_mask(volume: CTVolume, threshold_hu: float = BONE_HU_THRESHOLD) -> tuple[np.ndarray, str]:
    """``(I, J, K)`` bool mask of the pelvis's bone found in the CT alone, and one line saying how.

    1. The bone pieces: 26-connected components of ``threshold_hu < HU <`` :data:`METAL_HU` of at
       least :data:`MIN_PIECE_ML` ml, without flat plates (the table) and homogeneous pieces
       (contrast).
    2. The pelvic girdle's levels: along the CT's axial slices (the voxel axis nearest LPS z),
       the runs of slices whose bone spans at least :data:`GIRDLE_WIDTH_FRACTION` of the widest
       slice left to right; of the runs holding at least a quarter of the largest run's bone, the
       most inferior (the ribs are above the pelvis, the narrow lumbar spine between them).
    3. The femora: where the girdle's bone reaches the scan's lower edge (femora leave the scan
       there; a pelvis that ends inside the scan has none to follow), the largest cross-section on
       each side of the midline in the lowest slice is followed slice by slice upwards while it
       stays one piece lateral of the midline and grows by at most :data:`FEMUR_MAX_GROWTH` (it
       stops where it joins the hip bone at the joint), and left out.

    Raises :class:`AnatomyError` when no voxel exceeds the threshold or no bone piece is left.
    Where no girdle stands out (every slice is wide, or bone is in one run only) the pieces'
    union is the mask.
    """
    threshold = _check_threshold(threshold_hu)
    if not (np.asarray(volume.hu) > threshold).any():
        raise _no_bone(volume, threshold)
    mask, notes = _pieces(volume, threshold)
    si = int(np.argmax(np.abs(volume.affine[2, :3])))  # the voxel axis nearest LPS z
    upward = volume.affine[2, si] > 0  # index grows towards superior
    idx = np.argwhere(mask)
    lps = volume.voxel_to_lps(idx.astype(np.float64))
    level = idx[:, si]
    n_slices = volume.shape[si]
    counts = np.bincount(level, minlength=n_slices)
    width = np.zeros(n_slices)
    order = np.argsort(level, kind="stable")
    bounds = np.searchsorted(level[order], np.arange(n_slices + 1))
    for s in range(n_slices):
        x = lps[order[bounds[s]:bounds[s + 1]], 0]
        if x.size >= 10:
            lo, hi = np.percentile(x, [1, 99])
            width[s] = hi - lo
    step_mm = float(np.linalg.norm(volume.affine[:3, si]))
    runs = _runs(width >= GIRDLE_WIDTH_FRACTION * width.max(), int(GIRDLE_GAP_MM // step_mm))
    volumes = [int(counts[a:b].sum()) for a, b in runs]
    major = [r for r, v in zip(runs, volumes) if v >= 0.25 * max(volumes)]
    a, b = min(major, key=lambda r: r[0]) if upward else max(major, key=lambda r: r[1])
    # below the girdle only the pelvis's narrower lower part (ischia, pubis) and the legs follow,
    # so the levels are cut above it only
    a, b = (0, b) if upward else (a, n_slices)
    dropped = int(counts[:a].sum() + counts[b:].sum())
    if dropped:  # mentioned from 0.5 % of the bone on
        sl = [slice(None)] * 3
        for s in (*range(0, a), *range(b, n_slices)):
            sl[si] = s
            mask[tuple(sl)] = False
        top = b - 1 if upward else a
        z = float(volume.voxel_to_lps(np.array([[top if i == si else 0 for i in range(3)]], float))[0, 2])
        if dropped >= 0.005 * len(idx):
            notes.append(f"the bone above the girdle's top at z {z:.0f} mm left out ({100 * dropped / len(idx):.0f} %: "
                         "spine, ribs)")
    present = np.flatnonzero(counts[a:b]) + a
    bottom = int(present.min()) if upward else int(present.max())
    edge = 0 if upward else n_slices - 1
    if abs(bottom - edge) <= 1:  # the girdle's bone leaves the scan below: femora to follow
        midline = float(np.median(lps[mask[tuple(idx.T)], 0]))
        femur = _follow_femora(volume, mask, si, bottom, 1 if upward else -1, b if upward else a - 1, midline)
        if femur.any() and (femur & mask).sum() < mask.sum():
            mask &= ~femur
            notes.append(f"femora from the scan's lower edge up to the hip joints left out "
                         f"({abs(float(np.linalg.det(volume.affine[:3, :3]))) * femur.sum() / 1000:.0f} ml)")
    if not mask.any():
        raise AnatomyError(f"{volume.source}: no pelvic bone left after leaving out femora; give --center X Y Z")
    return mask, "; ".join(notes)


def _follow_femora(volume: CTVolume, mask: np.ndarray, si: int, start: int, step: int, stop: int,
                   midline: float) -> np.ndarray:
    """``mask``'s voxels of the femora followed from slice ``start`` in direction ``step`` (up to,
    not including, ``stop``), each lateral of ``midline`` (LPS x mm): :func:`pelvis_mask`'s step 3."""
    femur = np.zeros_like(mask)
    moved = np.moveaxis(mask, si, 0)
    out = np.moveaxis(femur, si, 0)
    plane_axes = [a for a in range(3) if a != si]
    # the LPS x of every in-plane voxel (the slice's offset along si does not change x much; the
    # axial slice's own x is used)
    ii, jj = np.meshgrid(np.arange(volume.shape[plane_axes[0]]), np.arange(volume.shape[plane_axes[1]]), indexing="ij")

    def x_of(s: int) -> np.ndarray:
        ijk = np.zeros(ii.shape + (3,))
        ijk[..., plane_axes[0]], ijk[..., plane_axes[1]], ijk[..., si] = ii, jj, s
        return volume.voxel_to_lps(ijk.reshape(-1, 3)).reshape(ii.shape + (3,))[..., 0]

    x0 = x_of(start)
    area_floor = max(4, int(100.0 / np.prod([np.linalg.norm(volume.affine[:3, a]) for a in plane_axes])))  # 1 cm^2
    eight = np.ones((3, 3), bool)
    lab, n = ndimage.label(moved[start], eight)
    tracks = []
    for side in (-1, 1):
        best, best_area = None, 0
        for k in range(1, n + 1):
            blob = lab == k
            area = int(blob.sum())
            if area >= area_floor and side * (float(x0[blob].mean()) - midline) > FEMUR_MIN_LATERAL_MM and area > best_area:
                best, best_area = blob, area
        if best is not None:
            tracks.append(best)
    for blob in tracks:
        s = start
        while True:
            out[s] |= blob
            nxt = s + step
            if nxt == stop or not (0 <= nxt < moved.shape[0]):
                break
            lab, n = ndimage.label(moved[nxt], eight)
            hit = np.unique(lab[blob & (lab > 0)])
            if hit.size == 0:  # the femur ends (or leaves the girdle's levels)
                break
            cand = np.isin(lab, hit)  # every cross-section it overlaps: a trochanter breaks into several
            xs = x_of(nxt)[cand]
            if cand.sum() > FEMUR_MAX_GROWTH * blob.sum() or abs(float(xs.mean()) - midline) <= FEMUR_MIN_LATERAL_MM:
                break
            blob, s = cand, nxt
    return femur


def find_center(volume: CTVolume, *, center=None, label_map: np.ndarray | None = None,
                labels: Sequence[int] | None = None, threshold_hu: float = BONE_HU_THRESHOLD) -> Center:
    """The anatomy centre of ``volume`` and how it was found (module doc: given, labels, bone).

    Args:
        volume: the CT.
        center: ``(3,)`` LPS mm that the user gives (``--center``): returned as it is.
        label_map: optional ``(I, J, K)`` integer label map on the CT's grid; default
            ``volume.labels``.
        labels: label values whose union is averaged; default every non-zero label. Needs a
            label map.
        threshold_hu: bone threshold (HU) used when there is no label map.

    Raises:
        AnatomyError: a bad given centre, the mask (labels or bone) is empty, or the label map
        does not fit the CT.

    Example::

        >>> from sim.ct.phantom import make_pelvis_phantom
        >>> ct = make_pelvis_phantom(0, spacing_mm=4.0)
        >>> find_center(ct).method                          # the phantom carries its labels
        'labels'
    """
    if center is not None:
        c = np.asarray(center, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise AnatomyError(f"a given centre must be 3 finite LPS mm values (X Y Z), got {center!r}")
        return Center(c, "given", "stated by the user (LPS mm)")
    lab = label_map if label_map is not None else volume.labels
    if lab is None:
        if labels is not None:
            raise AnatomyError(f"{volume.source}: labels={list(labels)} given but there is no label map")
        threshold = _check_threshold(threshold_hu)
        if threshold == BONE_HU_THRESHOLD and volume in _KNOWN_CENTERS:
            known = _KNOWN_CENTERS[volume]
            return Center(known.lps_mm.copy(), known.method, known.detail)
        try:
            mask, how = pelvis_mask(volume, threshold)
        except AnatomyError as e:
            if "no voxel above" in str(e):
                raise
            return Center(mask_centroid_lps(volume, bone_mask(volume, threshold)), "bone",
                          f"the largest bone piece above {threshold:g} HU ({e})")
        return Center(mask_centroid_lps(volume, mask), "bone",
                      f"centroid of the pelvis's bone above {threshold:g} HU: {how}")
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
    return Center(mask_centroid_lps(volume, mask), "labels", f"centroid of the label map's {what}")


def anatomy_center(volume: CTVolume, *, label_map: np.ndarray | None = None,
                   labels: Sequence[int] | None = None,
                   threshold_hu: float = BONE_HU_THRESHOLD) -> np.ndarray:
    """``(3,)`` LPS mm anatomy centre of ``volume``: :func:`find_center`'s point (labels, else
    the pelvis's bone pieces, else the largest bone piece). Raises :class:`AnatomyError` as it does."""
    return find_center(volume, label_map=label_map, labels=labels, threshold_hu=threshold_hu).lps_mm
