"""Virtual patients (sim.ct.patients) against independent truth.

Truth used here: closed forms of the backward map on linear HU ramps (trilinear resampling of
a linear function is exact), box extents and centroids under a known scaling, numerical
gradients of the displacement field (numpy.gradient), the HU curve's stated formulas on a fine
HU ramp, sample statistics of the noise, and voxel-centre distances computed from the affine
in the test itself.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim.ct.anatomy import anatomy_center, mask_centroid_lps
from sim.ct.patients import (
    AIR_HU,
    MAX_DISPLACEMENT_GRADIENT,
    PARAM_LIMITS,
    AugmentConfigError,
    VirtualPatientParams,
    VirtualPatientRanges,
    displacement_field,
    make_virtual_patient,
    perturb_hu,
)
from sim.ct.volume import CTVolume

REPO = Path(__file__).resolve().parents[2]

#: An oblique-free but permuted and flipped grid: index i runs along -y (anterior), j along +x,
#: k along +z, with anisotropic spacing (mm). Catches any mix-up of index and LPS axes.
PERMUTED_AFFINE = np.array([
    [0.0, 2.5, 0.0, -40.0],
    [-2.0, 0.0, 0.0, 35.0],
    [0.0, 0.0, 3.0, -60.0],
    [0.0, 0.0, 0.0, 1.0],
])


def voxel_centres_lps(shape, affine) -> np.ndarray:
    """``(3, I, J, K)`` LPS mm of every voxel centre, computed directly from the affine."""
    ijk = np.stack(np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape], indexing="ij"))
    return np.einsum("rc,cijk->rijk", affine[:3, :3], ijk) + affine[:3, 3, None, None, None]


def box_volume(shape=(40, 48, 36), affine=PERMUTED_AFFINE, box=((14, 26), (16, 32), (10, 26))):
    """Soft tissue (40 HU) with a bone box (1000 HU, label 1) over the index ranges ``box``
    (inclusive), and a 3-voxel air margin at the grid's faces."""
    hu = np.full(shape, 40.0, np.float32)
    hu[:3], hu[-3:], hu[:, :3], hu[:, -3:], hu[:, :, :3], hu[:, :, -3:] = (AIR_HU,) * 6
    labels = np.zeros(shape, np.uint8)
    sl = tuple(slice(lo, hi + 1) for lo, hi in box)
    hu[sl] = 1000.0
    labels[sl] = 1
    return CTVolume(hu, affine, source="box", labels=labels)


def lps_extent(volume: CTVolume, mask: np.ndarray) -> np.ndarray:
    """``(3,)`` mm extent of ``mask`` along LPS x, y, z: span of voxel centres plus one voxel."""
    pts = volume.voxel_to_lps(np.argwhere(mask))
    step = np.abs(volume.affine[:3, :3]).max(axis=1)  # spacing along each LPS axis
    return pts.max(axis=0) - pts.min(axis=0) + step


# ----------------------------------------------------------------------------- identity
def test_identity_params_return_the_ct_unchanged():
    rng = np.random.default_rng(0)
    hu = rng.uniform(-1000, 2000, (20, 22, 18)).astype(np.float32)
    labels = rng.integers(0, 4, hu.shape).astype(np.int32)
    ct = CTVolume(hu, PERMUTED_AFFINE, source="rand", labels=labels)
    out = make_virtual_patient(ct, VirtualPatientParams.identity())
    assert np.array_equal(out.hu, ct.hu)
    assert np.array_equal(out.labels, ct.labels)
    assert np.array_equal(out.affine, ct.affine)
    assert out.source == "rand#vp(seed=0)"
    assert out.hu is not ct.hu  # a copy: editing the patient leaves the CT alone
    # a seed alone changes nothing: the seed only drives the (absent) deformation and noise
    assert np.array_equal(make_virtual_patient(ct, VirtualPatientParams.identity(seed=99)).hu, ct.hu)


# ----------------------------------------------------------------------------- geometry
def test_pure_scaling_scales_a_bone_box_about_the_anatomy_centre():
    ct = box_volume()
    scale = (1.15, 0.85, 1.1)
    centre = anatomy_center(ct)  # the label-1 box centroid
    out = make_virtual_patient(ct, VirtualPatientParams(seed=3, scale=scale))
    # 520 HU, the midpoint of the 40/1000 HU edge, puts the interpolated edge on the box's
    # faces, so the box size is the span of the voxel centres above it plus one voxel
    size_in = lps_extent(ct, ct.hu > 520)
    size_out = lps_extent(out, out.hu > 520)
    step = np.abs(ct.affine[:3, :3]).max(axis=1)
    # an edge sampled on the voxel grid: within one voxel along each axis
    np.testing.assert_array_less(np.abs(size_out - np.array(scale) * size_in), step)
    # scaling about the centre keeps the centre (half a voxel: discretisation of the mask)
    assert np.all(np.abs(anatomy_center(out) - centre) <= 0.5 * step)
    assert np.all(np.abs(mask_centroid_lps(out, out.hu > 200) - centre) <= 0.5 * step)


@pytest.mark.parametrize("deformation_mm", [0.0, 4.0])
def test_resampling_follows_the_backward_map_exactly_on_linear_ramps(deformation_mm):
    """HU = LPS coordinate r (a linear ramp) must come back as phi(x)_r, with phi(x) =
    c + S^-1 (x + u(x) - c): trilinear interpolation reproduces linear functions exactly."""
    shape = (30, 34, 28)
    x = voxel_centres_lps(shape, PERMUTED_AFFINE)
    centre = np.array([5.0, -7.0, 12.0])
    params = VirtualPatientParams(seed=11, scale=(1.08, 0.93, 1.05), deformation_mm=deformation_mm,
                                  deformation_length_mm=40.0)
    u = displacement_field(shape, PERMUTED_AFFINE, params).astype(np.float64)
    expected = centre[:, None, None, None] + (x + u - centre[:, None, None, None]) / np.array(
        params.scale)[:, None, None, None]
    inv = np.linalg.inv(PERMUTED_AFFINE)
    q = np.einsum("rc,cijk->rijk", inv[:3, :3], expected) + inv[:3, 3, None, None, None]
    inside = np.all((q >= 0) & (q <= np.array(shape)[:, None, None, None] - 1), axis=0)
    assert inside.mean() > 0.7
    for r in range(3):
        ct = CTVolume(x[r].astype(np.float32), PERMUTED_AFFINE, source="ramp")
        out = make_virtual_patient(ct, params, center_lps=centre)
        # float32 storage of values up to ~100 mm: 1e-3 mm
        np.testing.assert_allclose(out.hu[inside], expected[r][inside], atol=2e-3)
        assert np.all(out.hu[~inside] == AIR_HU)  # outside the input: air, exactly


def test_displacement_field_has_the_requested_rms_and_correlation_length():
    spacing = 2.0
    affine = np.diag([spacing, spacing, spacing, 1.0])
    length = 40.0
    params = VirtualPatientParams(seed=5, deformation_mm=3.0, deformation_length_mm=length)
    u = displacement_field((96, 96, 96), affine, params).astype(np.float64)
    assert u.shape == (3, 96, 96, 96)
    rms = np.sqrt(np.mean(np.sum(u * u, axis=0)))
    assert abs(rms - 3.0) <= 0.2 * 3.0
    assert np.all(np.abs(u.mean(axis=(1, 2, 3))) < 0.05)  # zero mean: no net shift

    def corr(lag: int) -> float:
        num = den = 0.0
        for c in range(3):
            for axis in range(3):
                a = np.moveaxis(u[c], axis, 0)
                num += np.mean(a[:-lag] * a[lag:])
                den += np.mean(a * a)
        return num / den

    lag = int(round(length / spacing))
    # exp(-r^2/L^2): 0.998 at 2 mm, 1/e = 0.37 at L, 0.02 at 2L (finite-volume estimates scatter
    # by about +-0.07; mean removal biases them low)
    assert corr(1) > 0.95
    assert 0.15 < corr(lag) < 0.55
    assert abs(corr(2 * lag)) < 0.2
    # a different seed gives a different field
    other = displacement_field((96, 96, 96), affine, dataclasses.replace(params, seed=6))
    assert abs(np.corrcoef(u[0].ravel(), other[0].ravel())[0, 1]) < 0.3


def numeric_jacobian(u: np.ndarray, spacing: float) -> np.ndarray:
    """``(I, J, K, 3, 3)`` d u_i / d x_j by central differences (numpy.gradient)."""
    g = np.stack([np.stack(np.gradient(u[i], spacing), axis=0) for i in range(3)])  # [i, j, ...]
    return np.moveaxis(g, (0, 1), (-2, -1))


@pytest.mark.parametrize("deformation_mm, length_mm, guarded", [(3.0, 40.0, False), (20.0, 15.0, True)])
def test_deformation_stays_invertible(deformation_mm, length_mm, guarded):
    spacing = 2.0
    affine = np.diag([spacing, spacing, spacing, 1.0])
    params = VirtualPatientParams(seed=2, deformation_mm=deformation_mm, deformation_length_mm=length_mm)
    u = displacement_field((64, 64, 64), affine, params).astype(np.float64)
    grad = numeric_jacobian(u, spacing)
    det = np.linalg.det(np.eye(3) + grad)
    assert det.min() > 0.0
    fro = np.sqrt(np.sum(grad * grad, axis=(-2, -1)))
    assert fro.max() <= MAX_DISPLACEMENT_GRADIENT  # the guard's bound holds on the voxels too
    rms = np.sqrt(np.mean(np.sum(u * u, axis=0)))
    if guarded:
        # 20 mm at 15 mm would fold: the same field at its requested RMS has det < 0 somewhere
        unguarded = grad * (deformation_mm / rms)
        assert np.linalg.det(np.eye(3) + unguarded).min() < 0.0
        assert rms < 0.5 * deformation_mm
        assert fro.max() > 0.6 * MAX_DISPLACEMENT_GRADIENT  # scaled to the bound, not to nothing
    else:
        assert abs(rms - deformation_mm) < 1e-3 * deformation_mm


# ----------------------------------------------------------------------------- HU changes
def hu_ramp(step: float = 0.5, lo: float = -1100.0, hi: float = 3500.0) -> CTVolume:
    values = np.arange(lo, hi + step / 2, step, dtype=np.float64)
    hu = np.broadcast_to(values[:, None, None], (values.size, 2, 2)).astype(np.float32)
    return CTVolume(hu, np.eye(4), source="hu-ramp")


def check_curve(h: np.ndarray, f: np.ndarray, params: VirtualPatientParams, tol: float) -> None:
    o, s, bs = params.soft_tissue_hu_offset, params.soft_tissue_hu_scale, params.bone_hu_scale
    air = h <= -300
    assert np.array_equal(f[air], h[air])  # air and lung untouched, exactly
    soft = (h >= -200) & (h <= 100)
    np.testing.assert_allclose(f[soft], o + s * h[soft], atol=tol)
    bone = h >= 300
    np.testing.assert_allclose(f[bone], 200 + bs * (h[bone] - 200), atol=tol, rtol=2e-6)
    slope = np.diff(f) / np.diff(h)
    # monotone and continuous: the slope stays in the documented [0.1, 1.9] (a jump of even
    # 1 HU between samples 0.5 HU apart would show as slope 2), and changes smoothly (C1):
    # a kink at a blend edge would change it by >= 0.04 between neighbouring samples
    assert slope.min() >= 0.1 and slope.max() <= 1.9
    assert np.max(np.abs(np.diff(slope))) < 0.03


def test_hu_perturbation_of_soft_tissue_and_bone_is_smooth_and_monotone():
    ct = hu_ramp()
    params = VirtualPatientParams(seed=0, soft_tissue_hu_offset=15.0, soft_tissue_hu_scale=1.04,
                                  bone_hu_scale=0.88)
    out = make_virtual_patient(ct, params)
    check_curve(ct.hu[:, 0, 0].astype(np.float64), out.hu[:, 0, 0].astype(np.float64), params, tol=2e-3)
    assert np.all(out.hu == out.hu[:, :1, :1])  # voxel-wise: the same HU gives the same HU


@pytest.mark.parametrize("offset", PARAM_LIMITS["soft_tissue_hu_offset"])
@pytest.mark.parametrize("scale", PARAM_LIMITS["soft_tissue_hu_scale"])
@pytest.mark.parametrize("bone", PARAM_LIMITS["bone_hu_scale"])
def test_hu_curve_is_monotone_at_every_corner_of_the_limits(offset, scale, bone):
    params = VirtualPatientParams(seed=0, soft_tissue_hu_offset=offset, soft_tissue_hu_scale=scale,
                                  bone_hu_scale=bone)
    h = np.arange(-1100.0, 3500.0, 0.5)
    check_curve(h, perturb_hu(h, params), params, tol=1e-9)


def test_noise_has_the_requested_std_and_zero_mean():
    rng = np.random.default_rng(1)
    hu = rng.uniform(-100, 300, (64, 64, 64)).astype(np.float32)
    ct = CTVolume(hu, np.diag([1.5, 1.5, 2.0, 1.0]))
    base = VirtualPatientParams(seed=8, soft_tissue_hu_offset=5.0, bone_hu_scale=1.1)
    clean = make_virtual_patient(ct, base).hu.astype(np.float64)
    noisy = make_virtual_patient(ct, dataclasses.replace(base, noise_hu=12.0)).hu.astype(np.float64)
    d = noisy - clean
    n = d.size  # 262144: the sample std scatters by 1/sqrt(2n) = 0.14 %, the mean by 12/sqrt(n)
    assert abs(d.std() - 12.0) <= 0.05 * 12.0
    assert abs(d.mean()) < 5 * 12.0 / np.sqrt(n)
    other = make_virtual_patient(ct, dataclasses.replace(base, noise_hu=12.0, seed=9)).hu - clean
    assert abs(np.corrcoef(d.ravel(), other.ravel())[0, 1]) < 0.01  # seeded, independent streams


def test_noise_is_not_added_where_the_output_left_the_input():
    ct = box_volume()
    out = make_virtual_patient(ct, VirtualPatientParams(seed=1, scale=(0.8, 0.8, 0.8), noise_hu=10.0))
    x = voxel_centres_lps(ct.shape, ct.affine)
    c = anatomy_center(ct)[:, None, None, None]
    q = np.einsum("rc,cijk->rijk", np.linalg.inv(ct.affine)[:3, :3], c + (x - c) / 0.8) + \
        np.linalg.inv(ct.affine)[:3, 3, None, None, None]
    outside = np.any((q < -1e-6) | (q > np.array(ct.shape)[:, None, None, None] - 1 + 1e-6), axis=0)
    assert outside.mean() > 0.2
    assert np.all(out.hu[outside] == AIR_HU)
    assert out.hu[~outside].std() > 0  # noise inside


def test_truncation_sets_air_outside_the_fov_circle_and_the_z_crop():
    shape = (50, 44, 30)
    affine = np.array([[-3.0, 0, 0, 80.0], [0, 2.5, 0, -30.0], [0, 0, 4.0, 100.0], [0, 0, 0, 1]])
    rng = np.random.default_rng(3)
    hu = rng.uniform(-900, 1500, shape).astype(np.float32)
    labels = rng.integers(1, 5, shape).astype(np.uint8)
    ct = CTVolume(hu, affine, labels=labels)
    params = VirtualPatientParams(seed=0, fov_radius_mm=55.0, z_crop_mm=(10.0, 22.0))
    out = make_virtual_patient(ct, params)
    x = voxel_centres_lps(shape, affine)
    centre = affine[:3, :3] @ ((np.array(shape) - 1) / 2) + affine[:3, 3]
    r = np.hypot(x[0] - centre[0], x[1] - centre[1])
    z_lo = x[2].min() - 2.0  # outer faces: half a 4 mm voxel beyond the extreme centres
    z_hi = x[2].max() + 2.0
    removed = (r > 55.0) | (x[2] < z_lo + 10.0) | (x[2] > z_hi - 22.0)
    assert 0.2 < removed.mean() < 0.8
    assert np.all(out.hu[removed] == AIR_HU) and np.all(out.labels[removed] == 0)
    assert np.array_equal(out.hu[~removed], hu[~removed])
    assert np.array_equal(out.labels[~removed], labels[~removed])
    # z crop alone removes exactly the slabs: 10 mm = 2.5 voxels -> 2 slices (centres at 2, 6 mm
    # from the face), 22 mm -> 5 slices (2, 6, 10, 14, 18 mm)
    zonly = make_virtual_patient(ct, dataclasses.replace(params, fov_radius_mm=None))
    gone = np.all(zonly.hu == AIR_HU, axis=(0, 1))
    assert gone.tolist() == [True] * 2 + [False] * (30 - 7) + [True] * 5


# ----------------------------------------------------------------------------- labels
def test_labels_follow_the_anatomy():
    ct = box_volume()
    c = np.array([10.0, -5.0, 4.0])  # scaling centre away from the box centre
    scale = (1.12, 0.9, 1.06)
    out = make_virtual_patient(ct, VirtualPatientParams(seed=4, scale=scale), center_lps=c)
    step = np.abs(ct.affine[:3, :3]).max(axis=1)
    moved = c + np.array(scale) * (anatomy_center(ct, labels=[1]) - c)
    assert np.all(np.abs(anatomy_center(out, labels=[1]) - moved) <= 0.5 * step)
    assert np.all(np.abs(mask_centroid_lps(out, out.hu > 200) - moved) <= 0.5 * step)
    assert out.labels.dtype == ct.labels.dtype
    # with a deformation too, labels and bone stay together: same voxels up to the boundary
    warped = make_virtual_patient(ct, VirtualPatientParams(seed=4, scale=scale, deformation_mm=4.0,
                                                           deformation_length_mm=40.0), center_lps=c)
    bone, lab = warped.hu > 500, warped.labels == 1  # 500 HU: the midpoint of the 40/1000 edge
    dice = 2 * np.count_nonzero(bone & lab) / (np.count_nonzero(bone) + np.count_nonzero(lab))
    assert dice > 0.97
    assert np.all(np.abs(mask_centroid_lps(warped, lab) - mask_centroid_lps(warped, bone)) <= 0.5 * step)


# ----------------------------------------------------------------------------- determinism
DETERMINISM_PARAMS = dict(seed=1234, scale=[1.04, 0.95, 1.02], deformation_mm=4.0, deformation_length_mm=45.0,
                          soft_tissue_hu_offset=-7.0, soft_tissue_hu_scale=1.02, bone_hu_scale=1.1,
                          noise_hu=9.0, fov_radius_mm=70.0, z_crop_mm=[5.0, 8.0])


def determinism_checksum() -> str:
    """SHA-256 of a virtual patient of the box volume (run here and in a fresh process)."""
    out = make_virtual_patient(box_volume(), VirtualPatientParams.from_dict(DETERMINISM_PARAMS))
    return hashlib.sha256(out.hu.tobytes() + out.labels.tobytes()).hexdigest()


def test_same_params_give_bit_identical_patients_across_processes():
    ct = box_volume()
    params = VirtualPatientParams.from_dict(DETERMINISM_PARAMS)
    a, b = make_virtual_patient(ct, params), make_virtual_patient(ct, params)
    assert np.array_equal(a.hu, b.hu) and np.array_equal(a.labels, b.labels)
    here = determinism_checksum()
    code = "from tests.sim.test_augment import determinism_checksum; print(determinism_checksum())"
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == here
    # and the parameters matter
    changed = make_virtual_patient(ct, dataclasses.replace(params, seed=1235))
    assert not np.array_equal(changed.hu, a.hu)


# ----------------------------------------------------------------------------- params / ranges
def test_params_round_trip_through_json_exactly():
    rng = np.random.default_rng(7)
    ranges = VirtualPatientRanges(fov_probability=0.5, z_crop_probability=0.5)
    for _ in range(50):
        p = ranges.sample(rng)
        assert VirtualPatientParams.from_dict(json.loads(json.dumps(p.to_dict()))) == p
    assert VirtualPatientParams.from_dict(VirtualPatientParams.identity().to_dict()) == VirtualPatientParams.identity()


@pytest.mark.parametrize("key, value", [
    ("seed", -1), ("seed", True), ("scale", [1.0, 1.0]), ("scale", [1.0, 0.0, 1.0]),
    ("deformation_mm", -0.5), ("deformation_length_mm", 2.0), ("soft_tissue_hu_offset", 80.0),
    ("bone_hu_scale", float("nan")), ("noise_hu", -1.0), ("fov_radius_mm", 0.0), ("z_crop_mm", [5.0]),
    ("z_crop_mm", [-1.0, 3.0]),
])
def test_params_reject_bad_values_naming_the_key(key, value):
    d = VirtualPatientParams.identity().to_dict()
    d[key] = value
    with pytest.raises(AugmentConfigError, match=key):
        VirtualPatientParams.from_dict(d)


def test_params_from_dict_rejects_unknown_and_missing_keys():
    d = VirtualPatientParams.identity().to_dict()
    with pytest.raises(AugmentConfigError, match="noise_std.*allowed keys"):
        VirtualPatientParams.from_dict({**d, "noise_std": 3.0})
    del d["bone_hu_scale"]
    with pytest.raises(AugmentConfigError, match="bone_hu_scale"):
        VirtualPatientParams.from_dict(d)


def test_make_virtual_patient_rejects_bad_inputs():
    ct = box_volume()
    with pytest.raises(AugmentConfigError, match="ct"):
        make_virtual_patient(ct.hu, VirtualPatientParams.identity())
    with pytest.raises(AugmentConfigError, match="params"):
        make_virtual_patient(ct, {"seed": 0})
    with pytest.raises(AugmentConfigError, match="center_lps"):
        make_virtual_patient(ct, VirtualPatientParams.identity(), center_lps=[0, np.nan, 0])


def test_ranges_sample_stays_inside_and_covers_the_ranges():
    ranges = VirtualPatientRanges()
    rng = np.random.default_rng(2024)
    draws = [ranges.sample(rng) for _ in range(1000)]

    def check(values, lo, hi):
        values = np.asarray(values, dtype=np.float64)
        assert values.min() >= lo and values.max() <= hi
        # 1000 uniform draws: the extremes lie within 1 % of the width of the ends with
        # probability 1 - 2 * 0.99^1000 (> 0.9999); 3 % leaves a wide margin
        assert values.min() <= lo + 0.03 * (hi - lo) and values.max() >= hi - 0.03 * (hi - lo)

    check([s for p in draws for s in p.scale], *ranges.scale)
    for key in ("deformation_mm", "deformation_length_mm", "soft_tissue_hu_offset", "soft_tissue_hu_scale",
                "bone_hu_scale", "noise_hu"):
        check([getattr(p, key) for p in draws], *getattr(ranges, key))
    fov = [p.fov_radius_mm for p in draws if p.fov_radius_mm is not None]
    crops = [c for p in draws if p.z_crop_mm is not None for c in p.z_crop_mm]
    check(fov, *ranges.fov_radius_mm)
    check(crops, *ranges.z_crop_mm)
    # probability 0.3 over 1000 draws: binomial sd 0.0145, so +-0.06 is about 4 sd
    assert abs(len(fov) / 1000 - 0.3) < 0.06 and abs(len(crops) / 2000 - 0.3) < 0.06
    assert len({p.seed for p in draws}) == 1000
    # the draws depend only on the generator's state
    again = [ranges.sample(np.random.default_rng(2024)) for _ in range(2)]
    assert again[0] == again[1] == draws[0]


def test_ranges_from_dict_validates_keys_and_values():
    r = VirtualPatientRanges.from_dict({"noise_hu": [0, 5], "fov_probability": 0})
    assert r.noise_hu == (0.0, 5.0) and r.fov_probability == 0.0
    assert r.scale == VirtualPatientRanges().scale  # missing keys keep their defaults
    assert VirtualPatientRanges.from_dict({"bone_hu_scale": 1}).bone_hu_scale == (1.0, 1.0)  # fixed
    assert VirtualPatientRanges.from_dict(r.to_dict()) == r
    with pytest.raises(AugmentConfigError, match=r"deformation\b.*allowed keys.*deformation_mm"):
        VirtualPatientRanges.from_dict({"deformation": [0, 5]})
    with pytest.raises(AugmentConfigError, match=r"scale.*0\.5 <= low <= high <= 2"):
        VirtualPatientRanges.from_dict({"scale": [0.3, 1.1]})
    with pytest.raises(AugmentConfigError, match="noise_hu"):
        VirtualPatientRanges.from_dict({"noise_hu": [10, 5]})  # low > high
    with pytest.raises(AugmentConfigError, match="soft_tissue_hu_offset"):
        VirtualPatientRanges.from_dict({"soft_tissue_hu_offset": [-50, 0]})
    with pytest.raises(AugmentConfigError, match=r"z_crop_probability.*\[0, 1\]"):
        VirtualPatientRanges.from_dict({"z_crop_probability": 1.5})
    with pytest.raises(AugmentConfigError, match="fov_radius_mm"):
        VirtualPatientRanges.from_dict({"fov_radius_mm": "wide"})
    with pytest.raises(AugmentConfigError, match="mapping"):
        VirtualPatientRanges.from_dict([("noise_hu", [0, 1])])


# ----------------------------------------------------------------------------- real CT
def test_virtual_patient_of_the_real_pelvis_ct_is_a_plausible_ct(pelvis_ct_path):
    from sim.ct.anatomy import bone_mask
    from sim.ct.io import check_hu_plausible, load_ct
    from sim.projection.drr import DRRRenderer, RenderSettings

    ct = load_ct(pelvis_ct_path)
    centre = anatomy_center(ct)
    params = VirtualPatientRanges(fov_probability=1.0, z_crop_probability=1.0).sample(np.random.default_rng(3))
    vp = make_virtual_patient(ct, params, center_lps=centre)
    assert vp.shape == ct.shape and np.array_equal(vp.affine, ct.affine)
    check_hu_plausible(vp.hu, vp.source)  # raises if not HU-like
    bone0 = np.count_nonzero(bone_mask(ct))
    assert abs(np.count_nonzero(bone_mask(vp)) / bone0 - 1.0) < 0.35
    # without truncation, bone volume scales with det(S): HU > 200 is kept by the HU curve
    # (f(200) = 200, monotone), the zero-mean deformation changes volume only locally; 5 %
    # covers noise at the threshold and partial voxels
    whole = make_virtual_patient(ct, dataclasses.replace(params, fov_radius_mm=None, z_crop_mm=None),
                                 center_lps=centre)
    ratio = np.count_nonzero(whole.hu > 200) / np.count_nonzero(ct.hu > 200)
    assert abs(ratio / np.prod(params.scale) - 1.0) < 0.05
    image = DRRRenderer(vp, RenderSettings(size=(64, 64)), center_lps=centre).render_params(np.zeros(6))[0]
    assert np.all(np.isfinite(image)) and image.max() > 1.0 and image.std() > 0.1
