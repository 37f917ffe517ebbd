"""Tests for sim.ct.phantom, the built-in digital pelvis phantom.

Truth used here is independent of the rasterisation code: closed-form sphere-cap volumes,
the shape parameters and landmarks the phantom is built from (checked against what the voxels
show), mirror symmetry, adult anatomical ranges (femoral heads 150-220 mm apart, intercristal
width 240-340 mm, bone a few % of the body volume), HU of the materials, NIfTI round trips.
Tolerances are stated where used; they come from the 2 mm voxel size (centre-inside labels
locate a centroid to a fraction of a voxel, a volume to a few %).

The phantoms are built once per module at 2 to 8 mm, so the file runs in a few seconds.
"""

from __future__ import annotations

import dataclasses
import math
import os

import nibabel as nib
import numpy as np
import pytest
from scipy import ndimage

from sim.ct.phantom import (
    LABEL_NAMES,
    PelvisShape,
    PhantomInputError,
    make_pelvis_phantom,
    pelvis_landmarks,
    write_phantom_nifti,
)
from sim.ct.volume import CTVolume

MU_WATER = 0.02  # 1/mm, only to turn HU into an attenuation for the projection checks


@pytest.fixture(scope="module")
def default_phantom() -> CTVolume:
    return make_pelvis_phantom(None)  # mean shape, 2 mm


@pytest.fixture(scope="module")
def sampled() -> dict[int, CTVolume]:
    return {seed: make_pelvis_phantom(seed, spacing_mm=3.0) for seed in (1, 2)}


def lps_grids(vol: CTVolume) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel-centre x, y, z (LPS mm) as broadcastable ``(I,1,1)``, ``(1,J,1)``, ``(1,1,K)``."""
    i, j, k = (np.arange(n, dtype=np.float64) for n in vol.shape)
    a = vol.affine
    x, y, z = a[0, 0] * i + a[0, 3], a[1, 1] * j + a[1, 3], a[2, 2] * k + a[2, 3]
    return x[:, None, None], y[None, :, None], z[None, None, :]


def head_top_centre(vol: CTVolume, label: int, cap_mm: float = 12.0) -> tuple[np.ndarray, float]:
    """x, y centroid of the top ``cap_mm`` of a femur label (only the femoral head reaches that
    high: the greater trochanter's top is ~20 mm lower), and the label's highest voxel z."""
    x, y, z = lps_grids(vol)
    m = vol.labels == label
    zmax = float(np.broadcast_to(z, m.shape)[m].max())
    cap = m & (z > zmax - cap_mm)
    xs, ys = np.broadcast_to(x, m.shape)[cap], np.broadcast_to(y, m.shape)[cap]
    return np.array([xs.mean(), ys.mean()]), zmax


def dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * float((a & b).sum()) / float(a.sum() + b.sum())


def bone_projection_ap(vol: CTVolume, mask: np.ndarray | None = None) -> np.ndarray:
    """``(I, K)`` parallel AP projection of the attenuation in excess of soft tissue (HU > 100),
    ``sum_y mu_water * (HU - 100)/1000 * dy`` (dimensionless line integral)."""
    mu = MU_WATER * np.clip(vol.hu - 100.0, 0.0, None) / 1000.0
    if mask is not None:
        mu = mu * mask
    return mu.sum(axis=1) * vol.spacing_mm[1]


def pixel(vol: CTVolume, x: float, z: float) -> tuple[int, int]:
    ijk = vol.lps_to_voxel(np.array([[x, 0.0, z]]))[0]
    return int(round(ijk[0])), int(round(ijk[2]))


# ---------------------------------------------------------------------------------------------
# Shape parameters
# ---------------------------------------------------------------------------------------------


def test_default_shape_is_the_mean_of_every_range():
    d = PelvisShape.default()
    assert d == PelvisShape()
    for name, (low, mean, high, unit) in PelvisShape.ranges().items():
        assert low < mean < high, name
        assert getattr(d, name) == mean, name
        assert unit, name


def test_sample_is_deterministic_within_ranges_and_centred_on_the_mean():
    ranges = PelvisShape.ranges()
    assert PelvisShape.sample(7) == PelvisShape.sample(7)
    draws = [PelvisShape.sample(s) for s in range(200)]
    assert len({d.inter_asis_mm for d in draws}) == 200  # every seed a different patient
    for name, (low, mean, high, _) in ranges.items():
        values = np.array([getattr(d, name) for d in draws], dtype=float)
        assert values.min() >= low and values.max() <= high, name
        # the draw is mean + z * half-range with z = 2 Beta(3,3) - 1 (median 0): the sample
        # median lies within 12 % of the half-range of the mean (200 draws: sd of the median
        # ~ 4 % of the half-range), and draws spread over at least a third of the range.
        half = min(high - mean, mean - low)
        assert abs(np.median(values) - mean) <= 0.12 * half + (0.5 if name == "bowel_gas_pockets" else 0), name
        assert values.max() - values.min() >= (high - low) / 3.0, name
    gaps = np.array([d.acetabulum_radius_mm - d.femoral_head_radius_mm for d in draws])
    assert gaps.min() >= 1.0 and gaps.max() <= 5.0


@pytest.mark.parametrize(
    "change, words",
    [
        ({"inter_asis_mm": 150.0}, ["inter_asis_mm", "range"]),
        ({"neck_shaft_angle_deg": float("nan")}, ["neck_shaft_angle_deg"]),
        ({"scale": "big"}, ["scale", "number"]),
        ({"bowel_gas_pockets": 2.5}, ["bowel_gas_pockets", "integer"]),
        ({"bowel_gas_pockets": True}, ["bowel_gas_pockets", "integer"]),
        ({"femoral_head_radius_mm": 27.0, "acetabulum_radius_mm": 27.5}, ["joint space"]),
    ],
)
def test_shape_rejects_implausible_values(change, words):
    with pytest.raises(PhantomInputError) as err:
        dataclasses.replace(PelvisShape.default(), **change)
    for w in words:
        assert w in str(err.value)
    assert isinstance(err.value, ValueError)


@pytest.mark.parametrize(
    "kwargs, word",
    [
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"seed": True}, "seed"),
        ({"spacing_mm": 0.0}, "spacing_mm"),
        ({"spacing_mm": float("inf")}, "spacing_mm"),
        ({"size_mm": (400.0, 300.0)}, "size_mm"),
        ({"size_mm": (400.0, -3.0, 300.0)}, "size_mm"),
        ({"spacing_mm": 0.25}, "voxels"),
        ({"shape": {"scale": 1.0}}, "PelvisShape"),
    ],
)
def test_make_rejects_bad_inputs(kwargs, word):
    with pytest.raises(PhantomInputError, match=word):
        make_pelvis_phantom(**kwargs)


# ---------------------------------------------------------------------------------------------
# Grid, affine, determinism
# ---------------------------------------------------------------------------------------------


def test_grid_and_affine(default_phantom):
    v = default_phantom
    assert v.shape == (200, 150, 150) and v.hu.dtype == np.float32 and v.labels.dtype == np.uint8
    assert v.source == "phantom:None"
    # axis-aligned LPS at 2 mm, grid centre at the LPS origin
    np.testing.assert_allclose(v.affine[:3, :3], 2.0 * np.eye(3), atol=0)
    np.testing.assert_allclose(v.center_of_box_lps(), 0.0, atol=1e-9)
    assert set(np.unique(v.labels)) == set(LABEL_NAMES)


def test_left_femur_is_on_the_patients_left(default_phantom):
    """Label 3 (left femur) lies at +x (LPS: +x is the patient's left) of the grid centre."""
    v = default_phantom
    x, _, _ = lps_grids(v)
    centre_x = v.center_of_box_lps()[0]
    x_left = np.broadcast_to(x, v.shape)[v.labels == 3].mean() - centre_x
    x_right = np.broadcast_to(x, v.shape)[v.labels == 4].mean() - centre_x
    assert x_left > 50.0 and x_right < -50.0
    # the i axis is +x: the voxel of a point at +100 mm has a larger i than the centre's
    assert v.lps_to_voxel(np.array([[100.0, 0, 0]]))[0, 0] > v.lps_to_voxel(np.zeros((1, 3)))[0, 0]


def test_pelvis_centroid_is_near_the_grid_centre(default_phantom, sampled):
    for v in (default_phantom, *sampled.values()):
        x, y, z = lps_grids(v)
        m = np.isin(v.labels, (1, 2))
        c = np.array([np.broadcast_to(a, v.shape)[m].mean() for a in (x, y, z)])
        assert np.linalg.norm(c - v.center_of_box_lps()) < 6.0, c


def test_same_seed_gives_identical_arrays_and_other_seeds_other_patients(sampled):
    a = make_pelvis_phantom(5, spacing_mm=4.0)
    b = make_pelvis_phantom(5, spacing_mm=4.0)
    assert np.array_equal(a.hu, b.hu) and np.array_equal(a.labels, b.labels)
    assert np.array_equal(a.affine, b.affine) and a.source == b.source == "phantom:5"
    c = make_pelvis_phantom(6, spacing_mm=4.0)
    assert not np.array_equal(a.hu, c.hu)
    # seeds 1 and 2: the inter-femoral-head distance measured from the labels follows each
    # seed's own shape (within 1.5 mm at 3 mm voxels) and differs between the seeds
    measured = {}
    for seed, v in sampled.items():
        lm = pelvis_landmarks(PelvisShape.sample(seed))
        (xl, _), _ = head_top_centre(v, 3)
        (xr, _), _ = head_top_centre(v, 4)
        measured[seed] = xl - xr
        truth = lm["hip_centre_left"][0] - lm["hip_centre_right"][0]
        assert measured[seed] == pytest.approx(truth, abs=1.5)
    assert abs(measured[1] - measured[2]) > 8.0


def test_texture_seed_is_separate_from_the_shape():
    """With an explicit shape the seed changes only the texture (noise, gas), not the bones."""
    shape = PelvisShape.sample(3)
    a = make_pelvis_phantom(10, shape=shape, spacing_mm=6.0)
    b = make_pelvis_phantom(11, shape=shape, spacing_mm=6.0)
    assert np.array_equal(a.labels, b.labels)
    assert not np.array_equal(a.hu, b.hu)


def test_geometry_is_in_millimetres_not_voxels(default_phantom):
    """The same patient at 4 mm: same bone volume (within 4 %) and head centres (within 1 mm)."""
    coarse = make_pelvis_phantom(None, spacing_mm=4.0)
    fine = default_phantom
    for label in (1, 2, 3):
        v_fine = (fine.labels == label).sum() * 8.0
        v_coarse = (coarse.labels == label).sum() * 64.0
        assert v_coarse == pytest.approx(v_fine, rel=0.04), label
    np.testing.assert_allclose(head_top_centre(coarse, 3, 16.0)[0], head_top_centre(fine, 3)[0], atol=1.0)


# ---------------------------------------------------------------------------------------------
# HU and anatomy
# ---------------------------------------------------------------------------------------------


def test_hu_ranges(default_phantom):
    hu, labels = default_phantom.hu, default_phantom.labels
    assert hu.min() == -1000.0
    corners = hu[[0, -1]][:, [0, -1]][:, :, [0, -1]]
    assert np.all(corners == -1000.0)  # air outside the body, exactly
    assert 0.2 < np.mean(hu == -1000.0) < 0.6
    assert hu.max() < 2000.0 and (hu > 1000.0).sum() > 10_000  # cortical bone present
    # soft tissue: the histogram mode (5 HU bins) of unlabelled voxels within +-200 HU is 40 +- 10
    soft = hu[(labels == 0) & (np.abs(hu) < 200)]
    counts, edges = np.histogram(soft, bins=np.arange(-200, 205, 5))
    assert abs(edges[counts.argmax()] + 2.5 - 40.0) <= 10.0
    body = hu > -500
    assert 0.1 < np.mean((hu[body] > -150) & (hu[body] < -50)) < 0.5  # subcutaneous + pelvic fat
    assert np.sum(hu < -800) > np.sum(hu == -1000.0)  # some bowel gas inside the body
    # smooth noise: soft tissue is not piecewise constant, and varies by 5-30 HU
    assert 5.0 < np.std(soft[np.abs(soft - 40) < 40]) < 30.0


def test_labels_agree_with_hu(default_phantom):
    hu, labels = default_phantom.hu, default_phantom.labels
    for label in (1, 2, 5):
        assert np.mean(hu[labels == label] > 150.0) > 0.95, label
    for label in (3, 4):  # femoral shafts have a fatty medullary canal
        assert np.mean(hu[labels == label] > 150.0) > 0.85, label
    # every clearly cortical voxel is labelled (partial-volume voxels just outside the bone
    # reach at most soft + (cortex - soft)/2 < 900 HU)
    assert np.mean(labels[hu > 1000.0] > 0) > 0.99


def test_bone_volumes_are_plausible(default_phantom):
    v = default_phantom
    ml = {label: (v.labels == label).sum() * 8.0 / 1000.0 for label in range(1, 6)}
    body_ml = (v.hu > -500).sum() * 8.0 / 1000.0
    bone_fraction = sum(ml.values()) / body_ml
    assert 0.03 < bone_fraction < 0.10, bone_fraction
    assert 400 < ml[1] < 800  # both hip bones (adult: ~200-350 ml each)
    assert 80 < ml[2] < 220  # sacrum and coccyx
    assert ml[3] == ml[4]  # symmetric mean shape


def test_default_phantom_is_mirror_symmetric(default_phantom):
    """The mean shape mirrored about x = 0 (flip of the i axis: the grid is centred on x = 0)."""
    L, hu = default_phantom.labels, default_phantom.hu
    assert dice(L > 0, (L > 0)[::-1]) > 0.99
    assert dice(L == 3, (L == 4)[::-1]) > 0.99
    assert dice(hu > 400, (hu > 400)[::-1]) > 0.9  # noise and gas are not symmetric


def test_femoral_heads_match_their_landmarks_and_sphere_volume(default_phantom):
    v = default_phantom
    shape = PelvisShape.default()
    lm = pelvis_landmarks(shape)
    r = shape.femoral_head_radius_mm
    _, _, z = lps_grids(v)
    centres = {}
    for label, side in ((3, "left"), (4, "right")):
        h = lm[f"hip_centre_{side}"]
        xy, zmax = head_top_centre(v, label)
        centres[side] = xy
        np.testing.assert_allclose(xy, h[:2], atol=0.5)  # symmetric cap: centroid = centre
        assert h[2] + r - 2.0 <= zmax <= h[2] + r  # top voxel centre within one voxel of the top
        # the cap above z = centre + r/2 is a spherical cap: V = pi c^2 (3r - c) / 3, with c
        # measured to the lower face of the lowest voxel layer included (2 mm voxels: 3 %)
        m = (v.labels == label) & (z > h[2] + r / 2.0)
        z_low = float(np.broadcast_to(z, m.shape)[m].min()) - 1.0
        c = h[2] + r - z_low
        assert m.sum() * 8.0 == pytest.approx(math.pi * c * c * (3 * r - c) / 3.0, rel=0.03)
    distance = centres["left"][0] - centres["right"][0]
    assert 150.0 < distance < 220.0


def test_anatomical_relations(default_phantom, sampled):
    for v in (default_phantom, *sampled.values()):
        x, y, z = (np.broadcast_to(a, v.shape) for a in lps_grids(v))
        L = v.labels
        # the sacrum is posterior (+y) to the pubic symphysis (hip bone voxels within 10 mm of x = 0)
        pubis = (L == 1) & (np.abs(x) < 10.0)
        assert pubis.sum() > 100
        assert y[L == 2].mean() > y[pubis].mean() + 60.0
        assert abs(x[L == 2].mean()) < 2.0
        # iliac crests well above the femoral heads; the symphysis below the hip centres
        z_heads = max(z[L == 3].max(), z[L == 4].max())
        assert z[L == 1].max() > z_heads + 50.0
        assert z[pubis].mean() < z_heads - 40.0
        # L5/L4 above the sacrum
        assert z[L == 5].min() > z[L == 2].mean()
        # intercristal width (adult ~ 250-320 mm)
        width = x[L == 1].max() - x[L == 1].min()
        assert 240.0 < width < 340.0


def test_crest_and_symphysis_landmarks(default_phantom):
    v = default_phantom
    lm = pelvis_landmarks()
    x, y, z = (np.broadcast_to(a, v.shape) for a in lps_grids(v))
    left_hip_bone = (v.labels == 1) & (x > 0)
    # the crest landmark is on the crest's mid-line; the crest tube (~6 mm) covers it
    assert lm["iliac_crest_top_left"][2] <= z[left_hip_bone].max() <= lm["iliac_crest_top_left"][2] + 10.0
    pubis = (v.labels == 1) & (np.abs(x) < 10.0)
    np.testing.assert_allclose([y[pubis].mean(), z[pubis].mean()], lm["pubic_symphysis"][1:], atol=5.0)


# ---------------------------------------------------------------------------------------------
# AP "X-ray look" without a renderer: parallel projection along y
# ---------------------------------------------------------------------------------------------


def test_ap_projection_shows_obturator_foramina_as_holes(default_phantom):
    """Each obturator foramen is a hole: (almost) no bone along y at its centre, and bone of the
    ring within 45 mm in every one of 8 directions around it."""
    v = default_phantom
    P = bone_projection_ap(v)
    lm = pelvis_landmarks()
    for side in ("left", "right"):
        c = lm[f"obturator_centre_{side}"]
        i, k = pixel(v, c[0], c[2])
        hole = P[i - 2:i + 3, k - 2:k + 3].mean()
        ring = []
        for ang in np.radians(np.arange(0, 360, 45)):
            pts = [pixel(v, c[0] + r * math.cos(ang), c[2] + r * math.sin(ang)) for r in np.arange(0, 46, 1.0)]
            ring.append(max(P[p] for p in pts))
        assert hole < 0.02, (side, hole)
        assert min(ring) > 0.15, (side, ring)
        # the hole's height follows obturator_height_mm (46 mm; the AP hole is 1-5 mm less:
        # rounded corners, and bone-free means < 0.01 here, i.e. partial-volume rims excluded)
        comp, _ = ndimage.label(P < 0.01)
        ks = np.nonzero(comp == comp[i, k])[1]
        assert 39.0 <= (ks.max() - ks.min() + 1) * 2.0 <= 47.0
    # both holes as seen by the eye: a mean over 10 x 10 mm at the centre < 10 % of the ring
    assert hole < 0.1 * np.median(ring)


def test_ap_projection_shows_two_round_femoral_heads(default_phantom):
    """The projected femora (their attenuation only) show half-discs of the head radius above
    the two hip centres, left and right of the midline; in the full bone projection the two
    heads are equally dense."""
    v = default_phantom
    shape = PelvisShape.default()
    lm = pelvis_landmarks(shape)
    r = shape.femoral_head_radius_mm
    x, _, z = lps_grids(v)
    full = bone_projection_ap(v)
    at_centre = {}
    for label, side in ((3, "left"), (4, "right")):
        h = lm[f"hip_centre_{side}"]
        P = bone_projection_ap(v, v.labels == label)
        # rows above the centre and within r + 3 mm of it in x: the head only (the greater
        # trochanter's top is ~4 mm above the centre but > 35 mm lateral)
        window = (z[0] > h[2]) & (np.abs(x[:, :, 0] - h[0]) <= r + 3.0)
        disc = (P > 0) & window
        # pixel-centre sampling of a half-disc of 2 mm pixels: area within 6 %, centroid 0.5 mm
        assert disc.sum() * 4.0 == pytest.approx(math.pi * r * r / 2.0, rel=0.06)
        assert np.broadcast_to(x[:, :, 0], disc.shape)[disc].mean() == pytest.approx(h[0], abs=0.5)
        i, k = pixel(v, h[0], h[2])
        at_centre[side] = full[i - 2:i + 3, k - 2:k + 3].mean()
        # a solid ball: ~47 mm of trabecular bone (> 0.2 = 36 mm of 280 HU excess at mu_water
        # 0.02/mm) along the central ray, and the centre is (nearly) the brightest part of the
        # inner disc (chord 2 sqrt(r^2 - d^2); 20 % allowed for texture and the neck)
        inner = (x[:, 0, 0][:, None] - h[0]) ** 2 + (z[0, 0][None, :] - h[2]) ** 2 < (0.7 * r) ** 2
        assert P[i, k] > 0.2 and P[i, k] >= 0.8 * P[inner].max()
    assert at_centre["left"] == pytest.approx(at_centre["right"], rel=0.03)


# ---------------------------------------------------------------------------------------------
# NIfTI output
# ---------------------------------------------------------------------------------------------


def test_write_phantom_nifti_round_trip(tmp_path):
    path = tmp_path / "sub" / "phantom.nii.gz"
    labels_path = tmp_path / "sub" / "labels.nii"
    vol = write_phantom_nifti(path, seed=4, labels_path=labels_path, spacing_mm=8.0)
    img = nib.load(path)
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ vol.affine
    np.testing.assert_allclose(img.affine, ras, atol=1e-6)
    assert nib.aff2axcodes(img.affine) == ("L", "P", "S")  # i runs to the patient's left
    np.testing.assert_array_equal(np.asarray(img.dataobj), vol.hu)
    assert img.get_data_dtype() == np.float32
    lab = nib.load(labels_path)
    np.testing.assert_array_equal(np.asarray(lab.dataobj), vol.labels)
    assert sorted(os.listdir(path.parent)) == ["labels.nii", "phantom.nii.gz"]  # no temp files left
    # the same seed and kwargs as make_pelvis_phantom
    np.testing.assert_array_equal(vol.hu, make_pelvis_phantom(4, spacing_mm=8.0).hu)


def test_write_phantom_nifti_rejects_other_suffixes(tmp_path):
    with pytest.raises(PhantomInputError, match=".nii"):
        write_phantom_nifti(tmp_path / "x.png", seed=0, spacing_mm=8.0)
    assert not list(tmp_path.iterdir())
