"""Anatomy centre and bone mask against truth: hand-placed bone boxes and label regions whose
centroids are known in voxel indices, mapped to LPS through a non-trivial affine."""

from __future__ import annotations

import numpy as np
import pytest

from sim.anatomy import BONE_HU_THRESHOLD, AnatomyError, anatomy_center, bone_mask
from sim.ct_io import load_ct
from sim.volume import CTVolume


def oblique_affine() -> np.ndarray:
    """Voxel-to-LPS: rotation (30 deg about z, then 20 deg about x), spacing 0.8/1.2/2.5 mm, offset."""
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    c, s = np.cos(np.radians(20)), np.sin(np.radians(20))
    rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    a = np.eye(4)
    a[:3, :3] = rx @ rz @ np.diag([0.8, 1.2, 2.5])
    a[:3, 3] = (-101.3, 57.9, -420.0)
    return a


@pytest.fixture
def bone_scene():
    """Soft tissue with a 10x8x6 bone box (700 HU), a corner-touching voxel, and a denser small blob."""
    hu = np.full((40, 36, 30), 40.0, np.float32)
    hu[:3] = -1000.0
    hu[10:20, 12:20, 5:11] = 700.0  # the box: 480 voxels
    hu[20, 20, 11] = 700.0  # touches the box's corner (19, 19, 10) only: 26-connected, not 6-connected
    hu[30:33, 2:5, 20:23] = 1500.0  # 27 voxels, denser but smaller: must be ignored
    box = np.zeros(hu.shape, bool)
    box[10:20, 12:20, 5:11] = True
    box[20, 20, 11] = True
    return CTVolume(hu=hu, affine=oblique_affine(), source="scene"), box


def test_bone_mask_is_the_largest_26_connected_component(bone_scene):
    vol, box = bone_scene
    np.testing.assert_array_equal(bone_mask(vol), box)


def test_anatomy_center_is_the_box_centroid_in_lps(bone_scene):
    vol, _ = bone_scene
    # index centroid by hand: 480 box voxels centred at (14.5, 15.5, 7.5) plus the voxel (20, 20, 11)
    ijk = (480 * np.array([14.5, 15.5, 7.5]) + np.array([20.0, 20.0, 11.0])) / 481
    expect = oblique_affine()[:3, :3] @ ijk + oblique_affine()[:3, 3]
    np.testing.assert_allclose(anatomy_center(vol), expect, rtol=0, atol=1e-6)


def test_threshold_changes_the_component(bone_scene):
    vol, _ = bone_scene
    # above 1000 HU only the dense blob remains: its centre (31, 3, 21)
    expect = vol.voxel_to_lps([[31.0, 3.0, 21.0]])[0]
    np.testing.assert_allclose(anatomy_center(vol, threshold_hu=1000.0), expect, atol=1e-6)


def test_label_map_centroid(bone_scene):
    vol, _ = bone_scene
    lab = np.zeros(vol.shape, np.int32)
    lab[2:6, 4:10, 0:4] = 1  # centroid (3.5, 6.5, 1.5), 96 voxels
    lab[30:40, 30:36, 20:30] = 2  # centroid (34.5, 32.5, 24.5), 600 voxels
    c1 = vol.voxel_to_lps([[3.5, 6.5, 1.5]])[0]
    c2 = vol.voxel_to_lps([[34.5, 32.5, 24.5]])[0]
    np.testing.assert_allclose(anatomy_center(vol, label_map=lab, labels=[2]), c2, atol=1e-6)
    np.testing.assert_allclose(anatomy_center(vol, label_map=lab, labels=[1]), c1, atol=1e-6)
    both = (96 * c1 + 600 * c2) / 696  # union: voxel-count weighted (affine is linear)
    np.testing.assert_allclose(anatomy_center(vol, label_map=lab), both, atol=1e-6)
    # the volume's own labels are used when no label map is passed (and win over the bone)
    with_labels = CTVolume(hu=vol.hu, affine=vol.affine, source="scene", labels=lab)
    np.testing.assert_allclose(anatomy_center(with_labels, labels=[1]), c1, atol=1e-6)
    np.testing.assert_allclose(anatomy_center(with_labels), both, atol=1e-6)


def test_errors(bone_scene):
    vol, _ = bone_scene
    assert issubclass(AnatomyError, ValueError)
    with pytest.raises(AnatomyError, match=r"threshold 2000 HU"):
        anatomy_center(vol, threshold_hu=2000.0)
    soft = CTVolume(hu=np.where(vol.hu > 100, 40.0, vol.hu), affine=vol.affine, source="soft")
    with pytest.raises(AnatomyError, match=rf"soft: no voxel above the bone threshold {BONE_HU_THRESHOLD:g} HU"):
        anatomy_center(soft)
    lab = np.zeros(vol.shape, np.int32)
    lab[1, 1, 1] = 4
    with pytest.raises(AnatomyError, match=r"labels \[5\]"):
        anatomy_center(vol, label_map=lab, labels=[5])
    with pytest.raises(AnatomyError, match="non-zero labels"):
        anatomy_center(vol, label_map=np.zeros(vol.shape, np.int32))
    with pytest.raises(AnatomyError, match="no label map"):
        anatomy_center(vol, labels=[1])
    with pytest.raises(AnatomyError, match="shape"):
        anatomy_center(vol, label_map=lab[:-1])


def test_real_pelvis_centre(pelvis_ct_path):
    vol = load_ct(pelvis_ct_path)
    c = anatomy_center(vol)
    ijk = vol.lps_to_voxel(c[None])[0]
    assert np.all(ijk >= 0) and np.all(ijk <= np.array(vol.shape) - 1)  # inside the volume
    # The pelvic girdle: slices where thresholded bone spans > 200 mm left-right (iliac wings,
    # acetabula, femoral heads); above them only the narrow lumbar spine. The centre must lie at
    # one of those levels and near the middle of the bone's left-right extent (bilateral anatomy).
    bone = vol.hu > BONE_HU_THRESHOLD
    rows = [np.flatnonzero(bone[:, :, k].any(axis=1)) for k in range(vol.shape[2])]
    width_mm = np.array([(r.max() - r.min()) * vol.spacing_mm[0] if r.size else 0.0 for r in rows])
    pelvic = np.flatnonzero(width_mm > 200.0)
    assert pelvic.min() <= ijk[2] <= pelvic.max()
    k = int(round(ijk[2]))
    assert abs(ijk[0] - (rows[k].min() + rows[k].max()) / 2) * vol.spacing_mm[0] < 20.0
    # value found: LPS (5.9, -126.1, 201.5) mm, voxel (57.3, 38.2, 35.7) of (122, 101, 112)
    np.testing.assert_allclose(c, (5.91, -126.07, 201.45), atol=0.05)
