"""Anatomy centre and bone mask against truth: hand-placed bone boxes and label regions whose
centroids are known in voxel indices, mapped to LPS through a non-trivial affine; the pelvis's
centre found without labels against the phantom's own pelvis labels (hip bones and sacrum) on a
whole, split, cut, off-centre pelvis, with table, contrast and metal; and on the real pelves."""

from __future__ import annotations

import numpy as np
import pytest

from sim.ct.anatomy import (BONE_HU_THRESHOLD, AnatomyError, Center, anatomy_center, bone_mask, find_center,
                         mask_centroid_lps, pelvis_mask, remember_center)
from sim.ct.io import load_ct
from sim.ct.phantom import make_pelvis_phantom
from sim.ct.volume import CTVolume
from tests.conftest import shared_file


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
    # index centroid by hand: 480 box voxels centred at (14.5, 15.5, 7.5) plus the voxel (20, 20, 11);
    # the box (1.2 ml, one HU) is no pelvis piece (under 5 ml, homogeneous), so the centre falls
    # back to the largest bone piece
    ijk = (480 * np.array([14.5, 15.5, 7.5]) + np.array([20.0, 20.0, 11.0])) / 481
    expect = oblique_affine()[:3, :3] @ ijk + oblique_affine()[:3, 3]
    found = find_center(vol)
    np.testing.assert_allclose(found.lps_mm, expect, rtol=0, atol=1e-6)
    assert found.method == "bone" and found.detail.startswith("the largest bone piece above 200 HU")


def test_threshold_changes_the_component(bone_scene):
    vol, _ = bone_scene
    # above 1000 HU only the dense blob remains: its centre (31, 3, 21)
    expect = vol.voxel_to_lps([[31.0, 3.0, 21.0]])[0]
    np.testing.assert_allclose(anatomy_center(vol, threshold_hu=1000.0), expect, atol=1e-6)


def test_a_given_centre_wins_and_is_checked(bone_scene):
    vol, _ = bone_scene
    c = find_center(vol, center=[1.0, 2.0, 3.0])
    assert c.method == "given" and c.lps_mm.tolist() == [1.0, 2.0, 3.0]
    assert c.to_dict()["anatomy_center_how"].startswith("given: ")
    with pytest.raises(AnatomyError, match="3 finite LPS mm"):
        find_center(vol, center=[1.0, float("nan"), 3.0])
    with pytest.raises(AnatomyError, match="3 finite LPS mm"):
        find_center(vol, center=[1.0, 2.0])


def test_a_remembered_centre_keeps_how_it_was_found(bone_scene):
    vol, _ = bone_scene
    remember_center(vol, [4.0, 5.0, 6.0], "bone: centroid of 2 bone pieces")
    c = find_center(vol)
    assert c.lps_mm.tolist() == [4.0, 5.0, 6.0] and c.method == "bone" and c.detail == "centroid of 2 bone pieces"


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
    found = find_center(vol)
    c = found.lps_mm
    assert isinstance(found, Center) and "girdle" in found.detail
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
    # the lumbar spine and lower ribs above the iliac crests are left out (the largest piece's
    # centre was LPS (5.9, -126.1, 201.5) mm, pulled up by them)
    assert c[2] < 201.45 - 10.0


# --- the pelvis's centre without labels, against the phantom's pelvis labels ----------------------
# The phantom's labels: 1 hip bones, 2 sacrum, 3/4 femora, 5 lumbar vertebrae. Truth is the
# centroid of labels 1 and 2 (the pelvis's pieces). Tolerance 10 mm: the bar on a split
# pelvis; a femoral head in its acetabulum cannot be told from the hip bone by HU alone at 3 mm,
# and it pulls the centre by up to about 8 mm (measured 0.4-7.5 mm over the cases below).

TOLERANCE_MM = 10.0


def _unlabelled(vol: CTVolume, hu=None, source="unlabelled", affine=None) -> CTVolume:
    return CTVolume(hu=np.asarray(vol.hu if hu is None else hu, np.float32).copy(),
                    affine=vol.affine if affine is None else affine, source=source)


@pytest.fixture(scope="module", params=[0, 3])
def phantom(request):
    return make_pelvis_phantom(request.param, spacing_mm=3.0)


def _truth(vol: CTVolume, lab: np.ndarray) -> np.ndarray:
    return mask_centroid_lps(vol, np.isin(lab, [1, 2]))


def test_whole_pelvis_with_femora_and_spine(phantom):
    vol = _unlabelled(phantom)
    c = find_center(vol)
    assert c.method == "bone" and "femora" in c.detail and "girdle" in c.detail
    assert np.linalg.norm(c.lps_mm - _truth(phantom, phantom.labels)) < TOLERANCE_MM
    # the largest piece's centre (the former rule) is pulled by the femora and the spine
    old = mask_centroid_lps(vol, bone_mask(vol))
    assert np.linalg.norm(old - _truth(phantom, phantom.labels)) > np.linalg.norm(c.lps_mm - _truth(phantom, phantom.labels))


def test_split_pelvis_two_hip_bones(phantom):
    """Two hip bones apart (the symphysis cut, no sacrum, no femora, no spine): the union's
    centre, not one hip bone's (the largest piece's centre is about 80 mm to one side)."""
    lab, hu = phantom.labels, phantom.hu.copy()
    hu[np.isin(lab, [2, 3, 4, 5])] = 40.0
    hu[(lab == 0) & (hu > BONE_HU_THRESHOLD)] = 40.0  # the partial-volume rims that join the bones
    x = phantom.voxel_to_lps(np.argwhere(lab == 1).astype(float))[:, 0]
    hu[tuple(np.argwhere(lab == 1)[np.abs(x) < 25.0].T)] = 40.0  # the symphysis cut
    vol = _unlabelled(phantom, hu, "split")
    truth = mask_centroid_lps(vol, (lab == 1) & (hu > BONE_HU_THRESHOLD))
    c = find_center(vol)
    assert "2 bone pieces" in c.detail
    assert np.linalg.norm(c.lps_mm - truth) < TOLERANCE_MM
    one_bone = mask_centroid_lps(vol, bone_mask(vol))
    assert abs(one_bone[0] - truth[0]) > 50.0  # what the largest piece gave: one hip bone


def test_ct_cut_at_the_iliac_crest(phantom):
    lab = phantom.labels
    z = phantom.voxel_to_lps(np.argwhere(lab == 1).astype(float))[:, 2]
    k = int(np.floor(phantom.lps_to_voxel(np.array([[0.0, 0.0, z.max() - 20.0]]))[0][2]))
    vol = CTVolume(hu=phantom.hu[:, :, :k].copy(), affine=phantom.affine, source="cut")
    c = find_center(vol)
    assert np.linalg.norm(c.lps_mm - _truth(vol, lab[:, :, :k])) < TOLERANCE_MM


def test_pelvis_off_centre_in_a_large_field_with_table_metal_and_contrast(phantom):
    """The phantom placed off-centre in a 2x wider field of view, on a table (a 15 mm plate
    under the body, 400 HU), a steel rod in one femur (3000 HU) and a contrast-filled bladder
    (600 HU): none of them moves the centre."""
    lab = phantom.labels
    # a field of view twice as wide in-plane, the body far from its centre, and longer upwards;
    # the femora still leave the scan at its lower edge, as they do in a pelvis CT
    shape = (2 * phantom.shape[0], 2 * phantom.shape[1], phantom.shape[2] + 30)
    hu = np.full(shape, -1000.0, np.float32)
    off = (5, 40, 0)  # voxels
    region = tuple(slice(o, o + n) for o, n in zip(off, phantom.shape))
    hu[region] = phantom.hu
    labels = np.zeros(shape, np.uint8)
    labels[region] = lab
    body = hu > -500
    # bladder: the soft-tissue blob just behind the symphysis, filled with contrast
    ijk = np.argwhere(lab == 1).mean(axis=0) + np.array(off)
    ball = np.linalg.norm(np.indices(shape).reshape(3, -1).T - (ijk + [0, -8, 4]), axis=1).reshape(shape) < 7
    assert not (ball & (hu > BONE_HU_THRESHOLD)).any()  # apart from the bone
    hu[ball & body] = 600.0
    # a steel nail in the left femur's shaft: its core over 15 slices above the scan's edge
    femur = np.argwhere(labels == 3)
    femur = femur[(femur[:, 2] >= 3) & (femur[:, 2] < 18)]
    axis = np.array([femur[femur[:, 2] == k][:, :2].mean(axis=0) for k in range(3, 18)])
    near = np.linalg.norm(femur[:, :2] - axis[femur[:, 2] - 3], axis=1) < 1.5
    hu[tuple(femur[near].T)] = 3000.0
    # the table: a plate under the body (posterior, +y), along the whole scan
    back = np.flatnonzero(body.any(axis=(0, 2))).max() + 2
    hu[10:-10, back:back + 5, :] = 400.0
    a = phantom.affine.copy()
    vol = CTVolume(hu=hu, affine=a, source="large")
    c = find_center(vol)
    assert "table piece left out" in c.detail and "metal left out" in c.detail and "contrast piece" in c.detail
    truth = mask_centroid_lps(vol, np.isin(labels, [1, 2]))
    assert np.linalg.norm(c.lps_mm - truth) < TOLERANCE_MM
    # the volume's own grid centre is far away: the centre is found, not assumed
    assert np.linalg.norm(vol.center_of_box_lps() - truth) > 100.0


def test_pelvis_mask_refuses_soft_tissue(bone_scene):
    vol, _ = bone_scene
    soft = CTVolume(hu=np.where(vol.hu > 100, 40.0, vol.hu), affine=vol.affine, source="soft")
    with pytest.raises(AnatomyError, match="no voxel above the bone threshold"):
        pelvis_mask(soft)


def test_split_real_pelvis_centre_is_both_hip_bones():
    """The validation pelvis (two hip bones of another person, separate pieces): the centre is
    within 10 mm of the centroid of both pieces (it was 86 mm away, on one hip bone)."""
    vol = load_ct(shared_file("ct/pelvis_chiconasa_2mm.nii.gz"))
    bone = vol.hu > BONE_HU_THRESHOLD
    from scipy import ndimage

    lab, n = ndimage.label(bone, np.ones((3, 3, 3), bool))
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    two = np.argsort(sizes)[-2:]
    assert sizes[two].min() > 0.8 * sizes[two].max()  # two hip bones of nearly equal size
    truth = mask_centroid_lps(vol, np.isin(lab, two))
    c = find_center(vol)
    assert "2 bone pieces" in c.detail
    assert np.linalg.norm(c.lps_mm - truth) < TOLERANCE_MM
