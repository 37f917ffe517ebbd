"""Pose converters to and from DiffDRR, DeepDRR and DeepFluoro (``register/convert.py``).

Each peer is checked two ways:

* round trips ctxreg -> peer -> ctxreg on 20 random poses from ``pose_from_params`` (rotations up to
  +-60 deg, translations up to +-100 mm): the same ``T`` to 1e-9 (float64 matrix products of values
  up to ~1e3 mm lose ~1e-13 relative; 1e-9 is far above rounding and far below any convention slip,
  which moves entries by O(1));
* a known LPS point projected through ctxreg's ``projection_matrix``/``project_points`` and through the
  peer's own projection written out here from the peer's definitions (not through the converter).

What each peer formula below assumes is stated where it is written; the sources are in
``docs/conventions.md`` ("Converting poses to and from other tools").
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from register.convert import (
    DIFFDRR_REORIENT,
    PoseConversionError,
    deepdrr_lps_from_world,
    deepdrr_mobile_carm_camera3d_from_world,
    deepfluoro_lps_extrinsic,
    diffdrr_detector_kwargs,
    diffdrr_world_from_lps,
    from_deepdrr_camera3d_from_world,
    from_deepdrr_intrinsic,
    from_deepdrr_projection,
    from_deepfluoro,
    from_diffdrr,
    to_deepdrr_camera3d_from_world,
    to_deepdrr_intrinsic,
    to_deepdrr_projection,
    to_deepfluoro,
    to_diffdrr,
)
from sim.projection.geometry import CArmGeometry, pose_from_params, project_points, projection_matrix

SOD = 700.0
CENTER = np.array([12.0, -30.0, 45.0])  # anatomy centre, LPS mm
GEOM = CArmGeometry(sdd_mm=1020.0, sod_mm=SOD, height=300, width=400, pixel_spacing_mm=0.6, cx=210.3, cy=141.7)
F_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])  # LPS <-> RAS: (x, y, z) -> (-x, -y, z)

TOL = 1e-9


def _random_poses(seed: int, n: int = 20) -> np.ndarray:
    rng = np.random.default_rng(seed)
    params = np.concatenate([rng.uniform(-60, 60, (n, 3)), rng.uniform(-100, 100, (n, 3))], axis=1)
    return pose_from_params(params, SOD)


def _rigid(seed: int, t_scale: float = 100.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    M = np.eye(4)
    M[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    M[:3, 3] = rng.uniform(-t_scale, t_scale, 3)
    return M


def _hom(x: np.ndarray) -> np.ndarray:
    return np.append(np.asarray(x, dtype=np.float64), 1.0)


def _translation(v) -> np.ndarray:
    M = np.eye(4)
    M[:3, 3] = v
    return M


# A known point near the anatomy centre, and the ctxreg pixel it projects to.
X_POINT = CENTER + np.array([31.0, -17.0, 22.0])


def _ctxreg_pixel(T: np.ndarray, geometry: CArmGeometry = GEOM, center=CENTER) -> np.ndarray:
    return project_points(projection_matrix(geometry, T, center), X_POINT[None])[0]


# ---------------------------------------------------------------------------------------------
# DiffDRR 0.6.1
# ---------------------------------------------------------------------------------------------

# DiffDRR's reorient for read(orientation="AP"), copied from diffdrr/data.py.
REORIENT_AP = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])
REORIENT_PA = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])
ISO_LPS = np.array([-4.0, 7.0, 20.0])  # where read(center_volume=True) puts DiffDRR's world origin

# (world, world_origin_lps, reorient, reverse_x_axis, world_from_lps written by hand)
DIFFDRR_CASES = {
    "lps": ("lps", None, None, True, np.eye(4)),
    "ras_centred_AP": ("ras", ISO_LPS, "AP", True, _translation(-(F_RAS[:3, :3] @ ISO_LPS)) @ F_RAS),
    "lps_centred_PA_noreverse": ("lps", ISO_LPS, "PA", False, _translation(-ISO_LPS)),
    "matrix_world": (_rigid(5), None, None, True, _rigid(5)),
}
REORIENT_BY_NAME = {None: np.eye(4), "AP": REORIENT_AP, "PA": REORIENT_PA}


def _diffdrr_pixel(pose: np.ndarray, reorient: np.ndarray, reverse_x_axis: bool, x_world: np.ndarray,
                   sdd: float, h: int, w: int, delx: float, dely: float, x0: float, y0: float) -> np.ndarray:
    """(column j, row i) of a world point, from DiffDRR's Detector definitions (diffdrr/detector.py).

    Rays run from the source at the detector-frame origin to the target of pixel (i, j) at
    ``(sx (j - (W-1)/2) delx + x0, -(i - (H-1)/2) dely + y0, sdd)`` with ``sx = -1`` when
    ``reverse_x_axis`` (rows from the outer, columns from the inner loop of ``cartesian_prod``), and
    world = pose @ reorient @ detector frame (``Detector.forward``: ``reorient.compose(pose)``).
    """
    p = np.linalg.inv(pose @ reorient) @ _hom(x_world)
    x, y = p[0] / p[2] * sdd, p[1] / p[2] * sdd
    sx = -1.0 if reverse_x_axis else 1.0
    j = (x - x0) / (sx * delx) + (w - 1) / 2
    i = (y - y0) / (-dely) + (h - 1) / 2
    return np.array([j, i])


def _hand_x0_y0(reverse_x_axis: bool) -> tuple[float, float]:
    """DiffDRR's x0/y0 (mm) that put ctxreg's principal point (cx, cy) on the detector's pixel grid.

    The detector frame is ctxreg's camera with x negated (reverse_x_axis) and y negated, so column j
    must sit at ``sx (j - cx) s`` and row i at ``-(i - cy) s``; solving against the target formula
    of :func:`_diffdrr_pixel` gives ``x0 = sx ((W-1)/2 - cx) s`` and ``y0 = (cy - (H-1)/2) s``.
    """
    s = GEOM.pixel_spacing_mm
    cx, cy = GEOM.principal_point
    sx = -1.0 if reverse_x_axis else 1.0
    return sx * ((GEOM.width - 1) / 2 - cx) * s, (cy - (GEOM.height - 1) / 2) * s


@pytest.mark.parametrize("case", sorted(DIFFDRR_CASES))
def test_diffdrr_round_trip(case: str) -> None:
    world, origin, reorient, rev, _ = DIFFDRR_CASES[case]
    for T in _random_poses(1):
        pose = to_diffdrr(T, CENTER, world=world, world_origin_lps=origin, reorient=reorient, reverse_x_axis=rev)
        assert abs(np.linalg.det(pose[:3, :3]) - 1.0) < 1e-12  # a proper rigid pose
        back = from_diffdrr(pose, CENTER, world=world, world_origin_lps=origin, reorient=reorient, reverse_x_axis=rev)
        np.testing.assert_allclose(back, T, atol=TOL, rtol=0)


@pytest.mark.parametrize("case", sorted(DIFFDRR_CASES))
def test_diffdrr_point_projects_to_same_pixel(case: str) -> None:
    world, origin, reorient, rev, W_hand = DIFFDRR_CASES[case]
    np.testing.assert_allclose(diffdrr_world_from_lps(world, origin) if isinstance(world, str) else world,
                               W_hand, atol=1e-12)
    x0, y0 = _hand_x0_y0(rev)
    kw = diffdrr_detector_kwargs(GEOM, rev)
    assert kw["x0"] == pytest.approx(x0, abs=1e-12) and kw["y0"] == pytest.approx(y0, abs=1e-12)
    x_world = (W_hand @ _hom(X_POINT))[:3]
    for T in _random_poses(2, 5):
        # ctxreg -> DiffDRR: the DiffDRR pixel of the converted pose is ctxreg's pixel.
        pose = to_diffdrr(T, CENTER, world=world, world_origin_lps=origin, reorient=reorient, reverse_x_axis=rev)
        uv_peer = _diffdrr_pixel(pose, REORIENT_BY_NAME[reorient], rev, x_world, GEOM.sdd_mm, GEOM.height,
                                 GEOM.width, GEOM.pixel_spacing_mm, GEOM.pixel_spacing_mm, x0, y0)
        np.testing.assert_allclose(uv_peer, _ctxreg_pixel(T), atol=1e-7)
    # DiffDRR -> ctxreg: a DiffDRR pose made up here (the world point in front of the source).
    # The translation puts the point at detector-frame (7, -9, 650) mm: 650 mm in front of the source.
    pose = _rigid(11)
    R = pose[:3, :3] @ REORIENT_BY_NAME[reorient][:3, :3]
    pose[:3, 3] = x_world - R @ np.array([7.0, -9.0, 650.0])
    uv_peer = _diffdrr_pixel(pose, REORIENT_BY_NAME[reorient], rev, x_world, GEOM.sdd_mm, GEOM.height,
                             GEOM.width, GEOM.pixel_spacing_mm, GEOM.pixel_spacing_mm, x0, y0)
    T = from_diffdrr(pose, CENTER, world=world, world_origin_lps=origin, reorient=reorient, reverse_x_axis=rev)
    np.testing.assert_allclose(_ctxreg_pixel(T), uv_peer, atol=1e-7)


def test_diffdrr_pa_with_reversed_x_axis_is_refused() -> None:
    # PA's reorient is a reflection; with reverse_x_axis=True no rigid pose gives ctxreg's camera.
    with pytest.raises(PoseConversionError, match="reflection"):
        to_diffdrr(np.eye(4), CENTER, reorient="PA", reverse_x_axis=True)
    with pytest.raises(PoseConversionError, match="reflection"):
        to_diffdrr(np.eye(4), CENTER, reorient="AP", reverse_x_axis=False)
    np.testing.assert_array_equal(DIFFDRR_REORIENT["AP"], REORIENT_AP)
    np.testing.assert_array_equal(DIFFDRR_REORIENT["PA"], REORIENT_PA)


# --- with the installed DiffDRR ---------------------------------------------------------------

BEAD_SHAPE = (24, 20, 28)
BEAD_AFFINE = np.diag([1.5, 2.0, 2.5, 1.0])
BEAD_AFFINE[:3, 3] = [-12.0, 5.0, -30.0]
BEAD_INDEX = (18, 4, 21)
SMALL = CArmGeometry(sdd_mm=1020.0, sod_mm=SOD, height=64, width=64, pixel_spacing_mm=2.0, cx=30.2, cy=34.1)


@pytest.fixture(scope="module")
def diffdrr_modules():
    pytest.importorskip("diffdrr.drr", reason="DiffDRR 0.6.1 is not installed (optional 'bench' extra)")
    import torch
    import torchio
    from diffdrr.data import read
    from diffdrr.drr import DRR
    from diffdrr.pose import RigidTransform

    return torch, torchio, read, DRR, RigidTransform


@pytest.mark.parametrize("orientation,reverse_x_axis", [("AP", True), (None, True), ("PA", False)])
def test_diffdrr_installed_projection_and_render_match_ctxreg(diffdrr_modules, orientation, reverse_x_axis) -> None:
    """``diffdrr.data.read`` (RAS world, ``center_volume=True``, ``orientation``) + ``DRR``: bead position."""
    torch, torchio, read, DRR, RigidTransform = diffdrr_modules
    hu = np.zeros(BEAD_SHAPE, dtype=np.float32)  # soft tissue (read() needs some) ...
    hu[BEAD_INDEX] = 3000.0  # ... and one dense voxel
    bead_lps = BEAD_AFFINE[:3, :3] @ np.array(BEAD_INDEX, float) + BEAD_AFFINE[:3, 3]
    box_center = BEAD_AFFINE[:3, :3] @ ((np.array(BEAD_SHAPE) - 1) / 2) + BEAD_AFFINE[:3, 3]
    center = box_center + np.array([3.0, -4.0, 5.0])
    image = torchio.ScalarImage(tensor=torch.from_numpy(hu)[None], affine=F_RAS @ BEAD_AFFINE)  # RAS affine
    subject = read(image, orientation=orientation, center_volume=True)
    drr = DRR(subject, renderer="siddon", reverse_x_axis=reverse_x_axis, **diffdrr_detector_kwargs(SMALL, reverse_x_axis))
    for params in ([20.0, -15.0, 10.0, 5.0, -8.0, 20.0], [-35.0, 25.0, -40.0, -10.0, -6.0, -30.0]):
        T = pose_from_params(np.array(params), SOD)
        u, v = project_points(projection_matrix(SMALL, T, center), bead_lps[None])[0]
        # Precondition: inside the image, away from the centre lines (a flip would move it >= 8 px).
        assert 3 < u < 60 and 3 < v < 60 and abs(u - 31.5) > 4 and abs(v - 31.5) > 4
        pose = to_diffdrr(T, center, world="ras", world_origin_lps=box_center, reorient=orientation,
                          reverse_x_axis=reverse_x_axis)
        rt = RigidTransform(torch.tensor(pose, dtype=torch.float32)[None])
        # DiffDRR's own projection (drr.py) puts pixel j's centre at j + 0.5; float32: 1e-3 px.
        bead_world = (F_RAS @ _hom(bead_lps))[:3] - (F_RAS[:3, :3] @ box_center)
        pp = drr.perspective_projection(rt, torch.tensor(bead_world, dtype=torch.float32)[None, None])
        np.testing.assert_allclose(pp[0, 0].numpy() - 0.5, (u, v), atol=1e-3)
        with torch.no_grad():
            img = drr(rt)[0, 0].numpy()
        i, j = np.unravel_index(int(np.argmax(img)), img.shape)
        win = img[i - 1 : i + 2, j - 1 : j + 2].astype(np.float64)
        rows, cols = np.mgrid[i - 1 : i + 2, j - 1 : j + 2]
        uc, vc = (win * cols).sum() / win.sum(), (win * rows).sum() / win.sum()
        # A 1.5-2.5 mm voxel at ~1.4x magnification on 2 mm pixels: the 3 x 3 centroid is within 1 px.
        assert math.hypot(uc - u, vc - v) < 1.0, ((uc, vc), (u, v))


# ---------------------------------------------------------------------------------------------
# DeepDRR
# ---------------------------------------------------------------------------------------------


def _deepdrr_from_sizes(width: int, height: int, pixel_mm: float, sdd: float) -> np.ndarray:
    """killeengeo ``CameraIntrinsicTransform.from_sizes``: f = SDD / pixel, optical centre (W/2, H/2)."""
    return np.array([[sdd / pixel_mm, 0, width / 2], [0, sdd / pixel_mm, height / 2], [0, 0, 1.0]])


def _deepdrr_index(K: np.ndarray, camera3d_from_world: np.ndarray, x_world: np.ndarray) -> np.ndarray:
    """``CameraProjection.index_from_world = K [R | t]`` applied to a world point, dehomogenised."""
    p = K @ (camera3d_from_world @ _hom(x_world))[:3]
    return p[:2] / p[2]


DEEPDRR_CASES = {
    "LPS_identity": ("LPS", None),
    "RAS_identity": ("RAS", None),
    "RAS_placed": ("RAS", _rigid(21)),
    "LPS_placed": ("LPS", _rigid(22)),
}


def _world_from_lps_hand(anatomical: str, world_from_anatomical) -> np.ndarray:
    anat_from_lps = F_RAS if anatomical == "RAS" else np.eye(4)
    W = np.eye(4) if world_from_anatomical is None else world_from_anatomical
    return W @ anat_from_lps


@pytest.mark.parametrize("case", sorted(DEEPDRR_CASES))
def test_deepdrr_round_trips(case: str) -> None:
    anatomical, wfa = DEEPDRR_CASES[case]
    np.testing.assert_allclose(np.linalg.inv(deepdrr_lps_from_world(anatomical, wfa)),
                               _world_from_lps_hand(anatomical, wfa), atol=1e-12)
    for T in _random_poses(3):
        C = to_deepdrr_camera3d_from_world(T, CENTER, anatomical=anatomical, world_from_anatomical=wfa)
        back = from_deepdrr_camera3d_from_world(C, CENTER, anatomical=anatomical, world_from_anatomical=wfa)
        np.testing.assert_allclose(back, T, atol=TOL, rtol=0)
        P = projection_matrix(GEOM, T, CENTER)
        Pd = to_deepdrr_projection(P, anatomical=anatomical, world_from_anatomical=wfa)
        np.testing.assert_allclose(from_deepdrr_projection(Pd, anatomical=anatomical, world_from_anatomical=wfa),
                                   P, rtol=0, atol=TOL * np.abs(P).max())
    g = from_deepdrr_intrinsic(to_deepdrr_intrinsic(GEOM), pixel_spacing_mm=0.6, height=300, width=400, sod_mm=SOD)
    assert g.sdd_mm == pytest.approx(GEOM.sdd_mm, abs=TOL)
    assert g.principal_point == pytest.approx(GEOM.principal_point, abs=TOL)


@pytest.mark.parametrize("case", sorted(DEEPDRR_CASES))
def test_deepdrr_point_projects_to_same_pixel(case: str) -> None:
    """DeepDRR pixel (row v, col u) is traced through index (u + 0.5, v + 0.5) (project_kernel.cu)."""
    anatomical, wfa = DEEPDRR_CASES[case]
    W_hand = _world_from_lps_hand(anatomical, wfa)
    x_world = (W_hand @ _hom(X_POINT))[:3]
    K_default = _deepdrr_from_sizes(400, 300, 0.6, 1020.0)
    geom_default = CArmGeometry(sdd_mm=1020.0, sod_mm=SOD, height=300, width=400, pixel_spacing_mm=0.6)
    np.testing.assert_allclose(to_deepdrr_intrinsic(geom_default), K_default, atol=1e-12)
    # ctxreg -> DeepDRR.
    for T in _random_poses(4, 5):
        C = to_deepdrr_camera3d_from_world(T, CENTER, anatomical=anatomical, world_from_anatomical=wfa)
        idx = _deepdrr_index(K_default, C, x_world)
        np.testing.assert_allclose(idx - 0.5, _ctxreg_pixel(T, geom_default), atol=1e-7)
        # The whole projection matrix, formed as DeepDRR forms it: K [R | t] on world points.
        P_hand = K_default @ C[:3] @ np.eye(4)
        Pd = to_deepdrr_projection(projection_matrix(geom_default, T, CENTER), anatomical=anatomical,
                                   world_from_anatomical=wfa)
        np.testing.assert_allclose(Pd, P_hand, rtol=0, atol=1e-9 * np.abs(P_hand).max())
    # DeepDRR -> ctxreg: an arbitrary camera3d_from_world with the point 600 mm in front.
    C = _rigid(31)
    C[:3, 3] = np.array([-15.0, 22.0, 600.0]) - C[:3, :3] @ x_world
    K = np.array([[1020.0 / 0.6, 0, 180.0], [0, 1020.0 / 0.6, 170.0], [0, 0, 1.0]])  # off-centre optical centre
    idx = _deepdrr_index(K, C, x_world)
    T = from_deepdrr_camera3d_from_world(C, CENTER, anatomical=anatomical, world_from_anatomical=wfa)
    g = from_deepdrr_intrinsic(K, pixel_spacing_mm=0.6, height=300, width=400, sod_mm=SOD)
    np.testing.assert_allclose(_ctxreg_pixel(T, g), idx - 0.5, atol=1e-7)
    P_ctx = from_deepdrr_projection(K @ C[:3], anatomical=anatomical, world_from_anatomical=wfa)
    np.testing.assert_allclose(project_points(P_ctx, X_POINT[None])[0], idx - 0.5, atol=1e-7)


def test_deepdrr_mobile_carm_closed_forms() -> None:
    """``MobileCArm.camera3d_from_world`` (device/mobile_carm.py) against hand values."""
    iso = np.array([10.0, 20.0, 30.0])
    # alpha = beta = 0: X_cam = Rz(90) (X - iso + (0, 0, 530)); Rz(90) sends x -> y, y -> -x.
    expected = np.array([[0.0, -1, 0, 20], [1, 0, 0, -10], [0, 0, 1, 500], [0, 0, 0, 1]])
    np.testing.assert_allclose(deepdrr_mobile_carm_camera3d_from_world(0.0, 0.0, iso), expected, atol=1e-12)
    for alpha, beta in [(30.0, 0.0), (0.0, -45.0), (25.0, 70.0), (-20.0, 130.0)]:
        C = deepdrr_mobile_carm_camera3d_from_world(alpha, beta, iso)
        world_from_cam = np.linalg.inv(C)
        ray = world_from_cam[:3, :3] @ np.array([0.0, 0, 1])
        # DeepDRR's pose_vector_angles: alpha = -atan2(y, hypot(x, z)), beta = atan2(x, z).
        assert math.degrees(-math.atan2(ray[1], math.hypot(ray[0], ray[2]))) == pytest.approx(alpha, abs=1e-9)
        assert math.degrees(math.atan2(ray[0], ray[2])) == pytest.approx(beta, abs=1e-9)
        # Source 530 mm from the isocentre, against the principal ray; isocentre on the ray.
        np.testing.assert_allclose(world_from_cam[:3, 3], iso - 530.0 * ray, atol=1e-9)
        np.testing.assert_allclose((C @ _hom(iso))[:3], [0.0, 0.0, 530.0], atol=1e-9)
    # gamma turns the image about the principal ray; rotate_camera_left=False drops the 90 deg turn.
    C0 = deepdrr_mobile_carm_camera3d_from_world(0.0, 0.0, iso, rotate_camera_left=False, gamma_deg=90.0)
    np.testing.assert_allclose(C0, expected, atol=1e-12)


def test_deepdrr_default_carm_with_supine_patient_is_ctxreg_pa_view() -> None:
    """MobileCArm at alpha = beta = 0 with ``Volume.supine()`` (RAS) is ctxreg's PA view (phi = 180 deg).

    ``supine()`` sets world_from_anatomical = Rotation.from_euler("xz", [90, -90], degrees=True). The
    source is then 530 mm posterior of the isocentre: patient left is image left, superior is image up.
    """
    wfa = np.eye(4)
    wfa[:3, :3] = Rotation.from_euler("xz", [90, -90], degrees=True).as_matrix()
    C = deepdrr_mobile_carm_camera3d_from_world(0.0, 0.0, (0.0, 0.0, 0.0))
    T = from_deepdrr_camera3d_from_world(C, np.zeros(3), anatomical="RAS", world_from_anatomical=wfa)
    np.testing.assert_allclose(T, pose_from_params(np.array([180.0, 0, 0, 0, 0, 0]), 530.0), atol=1e-12)


# ---------------------------------------------------------------------------------------------
# DeepFluoro
# ---------------------------------------------------------------------------------------------

# The dataset's intrinsic (xReg convention; the value quoted in DeepDRR's MobileCArm docstring).
F_DF = 1020.0 / 0.194
K_DF = np.array([[-F_DF, 0.0, 767.5], [0.0, -F_DF, 767.5], [0.0, 0.0, 1.0]])
DF_GEOM = CArmGeometry(sdd_mm=1020.0, sod_mm=SOD, height=1536, width=1536, pixel_spacing_mm=0.194)


def _deepfluoro_pixel(K: np.ndarray, extrinsic_lps: np.ndarray, x_lps: np.ndarray) -> np.ndarray:
    """(column, row) by the dataset's pinhole model: ``K @ (extrinsic @ X)`` dehomogenised."""
    p = K @ (extrinsic_lps @ _hom(x_lps))[:3]
    return p[:2] / p[2]


@pytest.mark.parametrize("rot", [False, True])
def test_deepfluoro_round_trip(rot: bool) -> None:
    geom = CArmGeometry(sdd_mm=1020.0, sod_mm=SOD, height=1536, width=1536, pixel_spacing_mm=0.194, cx=760.2, cy=771.9)
    for T in _random_poses(5):
        E, K = to_deepfluoro(T, geom, CENTER, rot_180_for_up=rot)
        assert abs(np.linalg.det(E[:3, :3]) - 1.0) < 1e-12 and K[0, 0] < 0 and K[1, 1] < 0
        back, g = from_deepfluoro(E, K, CENTER, sod_mm=SOD, rot_180_for_up=rot)
        np.testing.assert_allclose(back, T, atol=TOL, rtol=0)
        assert g.sdd_mm == pytest.approx(1020.0, abs=TOL)
        assert g.principal_point == pytest.approx(geom.principal_point, abs=TOL)


@pytest.mark.parametrize("rot", [False, True])
def test_deepfluoro_point_projects_to_mirrored_pixel(rot: bool) -> None:
    """Assumed (dataset README): camera +x along columns, +y along rows, +z toward the source, right-handed.

    So the ctxreg image is the DeepFluoro image with its columns reversed (u = W - 1 - u_df), or, for
    a projection flagged rot-180-for-up, its rows reversed (v = H - 1 - v_df).
    """
    # ctxreg -> DeepFluoro.
    for T in _random_poses(6, 5):
        E, K = to_deepfluoro(T, DF_GEOM, CENTER, rot_180_for_up=rot)
        np.testing.assert_allclose(K, K_DF, atol=1e-9)
        u_df, v_df = _deepfluoro_pixel(K_DF, E, X_POINT)
        expected = (u_df, 1535.0 - v_df) if rot else (1535.0 - u_df, v_df)
        np.testing.assert_allclose(_ctxreg_pixel(T, DF_GEOM), expected, atol=1e-6)
    # DeepFluoro -> ctxreg: an extrinsic made up here, the centre 750 mm in front (z < 0).
    E = _rigid(41)
    E[:3, 3] = np.array([12.0, -25.0, -750.0]) - E[:3, :3] @ CENTER
    T, g = from_deepfluoro(E, K_DF, CENTER, rot_180_for_up=rot)
    assert g.sod_mm == pytest.approx(750.0) and g.pixel_spacing_mm == 0.194 and (g.height, g.width) == (1536, 1536)
    u_df, v_df = _deepfluoro_pixel(K_DF, E, X_POINT)
    assert 0 < u_df < 1535 and 0 < v_df < 1535
    expected = (u_df, 1535.0 - v_df) if rot else (1535.0 - u_df, v_df)
    np.testing.assert_allclose(_ctxreg_pixel(T, g), expected, atol=1e-6)


def test_deepfluoro_lps_extrinsic_chains_world_and_gt_pose() -> None:
    """``gt-poses/cam-to-pelvis-vol`` maps C-arm world -> CT LPS; the LPS extrinsic is ``E @ inv(P)``."""
    E_world, P_gt = _rigid(51), _rigid(52)
    x_world = np.array([5.0, -3.0, 40.0])
    x_lps = (P_gt @ _hom(x_world))[:3]
    np.testing.assert_allclose(deepfluoro_lps_extrinsic(E_world, P_gt) @ _hom(x_lps), E_world @ _hom(x_world), atol=1e-9)


# ---------------------------------------------------------------------------------------------
# Input checks
# ---------------------------------------------------------------------------------------------


def test_bad_inputs_raise_named_errors() -> None:
    T = pose_from_params(np.zeros(6), SOD)
    with pytest.raises(PoseConversionError, match="T:"):
        to_diffdrr(np.eye(3), CENTER)
    skew = T.copy()
    skew[0, 1] = 0.3
    with pytest.raises(PoseConversionError, match="T: .*orthonormal"):
        to_deepdrr_camera3d_from_world(skew, CENTER)
    with pytest.raises(PoseConversionError, match="center_lps"):
        to_diffdrr(T, [1.0, 2.0])
    with pytest.raises(PoseConversionError, match="world"):
        to_diffdrr(T, CENTER, world="xyz")
    with pytest.raises(PoseConversionError, match="reorient"):
        to_diffdrr(T, CENTER, reorient="LR")
    with pytest.raises(PoseConversionError, match="anatomical"):
        to_deepdrr_camera3d_from_world(T, CENTER, anatomical="RAI")  # type: ignore[arg-type]
    with pytest.raises(PoseConversionError, match="intrinsic"):
        from_deepfluoro(np.eye(4), np.abs(K_DF), CENTER)  # positive focal length: not DeepFluoro's
    with pytest.raises(PoseConversionError, match="intrinsic"):
        from_deepdrr_intrinsic(K_DF, pixel_spacing_mm=0.194, height=1536, width=1536, sod_mm=SOD)
    reflection = np.diag([-1.0, 1.0, 1.0, 1.0])
    with pytest.raises(PoseConversionError, match="reflection"):
        from_deepfluoro(reflection, K_DF, CENTER)
    nan = T.copy()
    nan[0, 3] = np.nan
    with pytest.raises(PoseConversionError, match="NaN"):
        from_diffdrr(nan, CENTER)
    with pytest.raises(PoseConversionError, match="sod_mm"):
        from_deepfluoro(np.eye(4), K_DF, CENTER)  # centre at depth 0: no SOD can be inferred
