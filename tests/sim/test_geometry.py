"""Tests for sim.projection.geometry against hand-computed pinhole projections, hand-written rotations and
scipy's Euler angles (independent of the module's own rotation code).

Tolerances: everything is float64 with O(10) flops on values up to ~1e3 (mm, px), so results
are exact to ~1e-12; 1e-9 is used throughout (any convention error is >= 1e-3 off).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sim.projection import geometry as g
from sim.projection.geometry import CArmGeometry, GeometryError

ATOL = 1e-9

# The worked example of docs/conventions.md.
GEO = CArmGeometry(sdd_mm=1020.0, sod_mm=700.0, height=512, width=512, pixel_spacing_mm=0.6)
CENTER = np.array([12.0, -30.0, 45.0])  # anatomy centre c, LPS mm


def camera_point(params, x_lps, sod=700.0, center=CENTER):
    """Camera mm of an LPS point under pose params, through the module's pose (R, t)."""
    T = g.pose_from_params(np.asarray(params, dtype=float), sod)
    return T[:3, :3] @ (np.asarray(x_lps) - center) + T[:3, 3]


def project(params, x_lps):
    P = g.projection_matrix(GEO, g.pose_from_params(np.asarray(params, dtype=float), GEO.sod_mm), CENTER)
    return g.project_points(P, np.asarray(x_lps, dtype=float)[None])[0]


ZERO = [0, 0, 0, 0, 0, 0]


# ---------------------------------------------------------------------------------------------
# AP pose and orientation
# ---------------------------------------------------------------------------------------------


def test_identity_params_give_ap_pose():
    T = g.pose_from_params(np.zeros(6), 700.0)
    R_ap = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=float)
    np.testing.assert_array_equal(g.R_AP, R_ap)
    np.testing.assert_allclose(T[:3, :3], R_ap, atol=ATOL)
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.0, 700.0], atol=ATOL)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    assert abs(np.linalg.det(g.R_AP) - 1.0) < 1e-15  # proper rotation (Rx(+90 deg))
    with pytest.raises(ValueError):
        g.R_AP[0, 0] = 2.0  # read-only constant


def test_ap_orientation_left_right_superior_up_posterior_far():
    cx, cy = GEO.principal_point
    assert (cx, cy) == (255.5, 255.5)
    u, v = project(ZERO, CENTER)
    assert abs(u - cx) < ATOL and abs(v - cy) < ATOL  # the centre projects to the principal point
    u, v = project(ZERO, CENTER + [50.0, 0, 0])  # patient left
    assert u > cx + 100 and abs(v - cy) < ATOL  # image right
    u, v = project(ZERO, CENTER + [0, 0, 50.0])  # superior
    assert v < cy - 100 and abs(u - cx) < ATOL  # image up
    z_post = camera_point(ZERO, CENTER + [0, 50.0, 0])[2]  # posterior
    z_ant = camera_point(ZERO, CENTER + [0, -50.0, 0])[2]
    assert abs(z_post - 750.0) < ATOL and abs(z_ant - 650.0) < ATOL  # posterior toward the detector


def test_worked_example_hand_computed_projection():
    """docs/conventions.md: X = c + (50, 30, -40) (left, posterior, inferior) at the AP pose.

    Camera point = R_AP (50, 30, -40) + (0, 0, 700) = (50, 40, 730); f = 1020 / 0.6 = 1700 px;
    u = 1700 * 50 / 730 + 255.5, v = 1700 * 40 / 730 + 255.5."""
    X = CENTER + [50.0, 30.0, -40.0]
    np.testing.assert_allclose(camera_point(ZERO, X), [50.0, 40.0, 730.0], atol=ATOL)
    u, v = project(ZERO, X)
    assert abs(u - (1700.0 * 50.0 / 730.0 + 255.5)) < ATOL
    assert abs(v - (1700.0 * 40.0 / 730.0 + 255.5)) < ATOL
    assert abs(u - 371.9383561643836) < 1e-9 and abs(v - 348.6506849315069) < 1e-9


# ---------------------------------------------------------------------------------------------
# Senses of the three pose rotations (expected camera points computed by hand)
# ---------------------------------------------------------------------------------------------


def test_phi_rotates_about_superior_left_to_posterior():
    # Rz(+90) seen from the head: L (1,0,0) -> P (0,1,0); R_AP sends P to camera +z.
    np.testing.assert_allclose(camera_point([90, 0, 0, 0, 0, 0], CENTER + [50.0, 0, 0]), [0, 0, 750.0], atol=ATOL)
    # Anterior (0,-1,0) -> L (1,0,0): the former anterior surface is now on the image right.
    np.testing.assert_allclose(camera_point([90, 0, 0, 0, 0, 0], CENTER + [0, -50.0, 0]), [50.0, 0, 700.0], atol=ATOL)
    u, v = project([90, 0, 0, 0, 0, 0], CENTER + [50.0, 0, 0])
    assert abs(u - 255.5) < ATOL and abs(v - 255.5) < ATOL


def test_theta_rotates_about_left_posterior_to_superior():
    # Rx(+90) seen from the patient's left: P (0,1,0) -> S (0,0,1); S maps to camera -y (image up).
    np.testing.assert_allclose(camera_point([0, 90, 0, 0, 0, 0], CENTER + [0, 50.0, 0]), [0, -50.0, 700.0], atol=ATOL)
    assert project([0, 90, 0, 0, 0, 0], CENTER + [0, 50.0, 0])[1] < 255.5 - 100


def test_psi_rotates_about_posterior_superior_to_left():
    # Ry(+90) seen from posterior: S (0,0,1) -> L (1,0,0); L maps to camera +x (image right).
    np.testing.assert_allclose(camera_point([0, 0, 90, 0, 0, 0], CENTER + [0, 0, 50.0]), [50.0, 0, 700.0], atol=ATOL)
    assert project([0, 0, 90, 0, 0, 0], CENTER + [0, 0, 50.0])[0] > 255.5 + 100


def test_translation_parameters_are_camera_mm():
    np.testing.assert_allclose(camera_point([0, 0, 0, 5.0, -7.0, 30.0], CENTER), [5.0, -7.0, 730.0], atol=ATOL)


def test_composition_order_matches_scipy_intrinsic_zxy():
    """R_AP^T R = Rz(phi) Rx(theta) Ry(psi) = scipy's intrinsic 'ZXY' Euler rotation."""
    rng = np.random.default_rng(0)
    p = np.concatenate([rng.uniform(-180, 180, (20, 3)), rng.normal(size=(20, 3))], -1)
    T = g.pose_from_params(p, 700.0)
    ref = Rotation.from_euler("ZXY", p[:, :3], degrees=True).as_matrix()
    np.testing.assert_allclose(g.R_AP.T @ T[:, :3, :3], ref, atol=ATOL)


def test_params_round_trip():
    rng = np.random.default_rng(1)
    n = 500
    p = np.stack(
        [
            rng.uniform(-179.9, 179.9, n),
            rng.uniform(-89.0, 89.0, n),
            rng.uniform(-179.9, 179.9, n),
            rng.normal(scale=50, size=n),
            rng.normal(scale=50, size=n),
            rng.normal(scale=100, size=n),
        ],
        -1,
    )
    T = g.pose_from_params(p, 650.0)
    np.testing.assert_allclose(g.params_from_pose(T, 650.0), p, atol=ATOL)
    # Batched over extra leading dims.
    T2 = g.pose_from_params(p[:6].reshape(2, 3, 6), 650.0)
    assert T2.shape == (2, 3, 4, 4)
    np.testing.assert_allclose(g.params_from_pose(T2, 650.0), p[:6].reshape(2, 3, 6), atol=ATOL)


@pytest.mark.parametrize("theta", [90.0, -90.0])
def test_params_gimbal_lock_reproduces_pose(theta):
    p = np.array([30.0, theta, 20.0, 1.0, 2.0, 3.0])
    T = g.pose_from_params(p, 700.0)
    q = g.params_from_pose(T, 700.0)
    assert q[2] == 0.0 and abs(q[1] - theta) < ATOL  # psi = 0 by convention, phi absorbs it
    # Only phi + psi (theta = +90) or phi - psi (theta = -90) is determined.
    assert abs(q[0] - (50.0 if theta > 0 else 10.0)) < 1e-6
    np.testing.assert_allclose(g.pose_from_params(q, 700.0), T, atol=1e-7)


# ---------------------------------------------------------------------------------------------
# Extrinsics, projection matrices, point projection
# ---------------------------------------------------------------------------------------------


def test_extrinsic_and_projection_matrix():
    p = np.array([20.0, -10.0, 35.0, 4.0, -6.0, 25.0])
    T = g.pose_from_params(p, GEO.sod_mm)
    R, t = T[:3, :3], T[:3, 3]
    E = g.extrinsic_lps_to_camera(T, CENTER)
    np.testing.assert_allclose(E[:3, :3], R, atol=ATOL)
    np.testing.assert_allclose(E[:3, 3], t - R @ CENTER, atol=ATOL)
    np.testing.assert_allclose(E @ np.append(CENTER, 1.0), np.append(t, 1.0), atol=ATOL)  # c -> t
    K = np.array([[1700.0, 0, 255.5], [0, 1700.0, 255.5], [0, 0, 1]])
    np.testing.assert_allclose(GEO.intrinsics(), K, atol=ATOL)
    P = g.projection_matrix(GEO, T, CENTER)
    assert P.shape == (3, 4)
    np.testing.assert_allclose(P, K @ E[:3], atol=ATOL)


def test_project_points_matches_hand_pinhole_and_batches():
    rng = np.random.default_rng(2)
    params = np.concatenate([rng.uniform(-30, 30, (3, 3)), rng.normal(scale=10, size=(3, 3))], -1)
    T = g.pose_from_params(params, GEO.sod_mm)
    X = CENTER + rng.normal(scale=80.0, size=(7, 3))
    P = g.projection_matrix(GEO, T, CENTER)
    assert P.shape == (3, 3, 4)
    uv = g.project_points(P, X)
    assert uv.shape == (3, 7, 2)
    for b in range(3):
        for n in range(7):
            x, y, z = T[b, :3, :3] @ (X[n] - CENTER) + T[b, :3, 3]
            ref = (1700.0 * x / z + 255.5, 1700.0 * y / z + 255.5)
            np.testing.assert_allclose(uv[b, n], ref, atol=ATOL)
        np.testing.assert_allclose(g.project_points(P[b], X), uv[b], atol=0)


def test_points_behind_the_source_get_nan():
    P = g.projection_matrix(GEO, g.pose_from_params(np.zeros(6), GEO.sod_mm), CENTER)
    X = np.array([CENTER, CENTER + [0, -700.0, 0], CENTER + [0, -800.0, 0]])  # z = 700, 0, -100
    uv = g.project_points(P, X)
    assert np.all(np.isfinite(uv[0])) and np.all(np.isnan(uv[1:]))


def test_backproject_pixel_inverts_projection():
    geo = CArmGeometry(1020.0, 700.0, 300, 400, 0.5, cx=210.0, cy=140.0)
    d = g.backproject_pixel(geo, 210.0, 140.0)
    np.testing.assert_allclose(d, [0, 0, 1], atol=ATOL)
    u = np.array([0.0, 399.0, 37.25])
    v = np.array([0.0, 299.0, 250.5])
    d = g.backproject_pixel(geo, u, v)
    assert d.shape == (3, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    # A point at depth 800 mm along the ray projects back to (u, v) (hand pinhole: f = 2040 px).
    p = 800.0 * d / d[:, 2:3]
    np.testing.assert_allclose(2040.0 * p[:, 0] / p[:, 2] + 210.0, u, atol=ATOL)
    np.testing.assert_allclose(2040.0 * p[:, 1] / p[:, 2] + 140.0, v, atol=ATOL)


# ---------------------------------------------------------------------------------------------
# Detector: pixel centres, size, field of view, resizing
# ---------------------------------------------------------------------------------------------


def test_pixel_centers_camera_corners():
    geo = CArmGeometry(1000.0, 600.0, 4, 6, 0.25, cx=2.0, cy=1.0)
    pc = geo.pixel_centers_camera()
    assert pc.shape == (4, 6, 3)
    np.testing.assert_allclose(pc[0, 0], [-0.5, -0.25, 1000.0], atol=ATOL)  # ((0-2)s, (0-1)s)
    np.testing.assert_allclose(pc[0, 5], [0.75, -0.25, 1000.0], atol=ATOL)  # column 5
    np.testing.assert_allclose(pc[3, 0], [-0.5, 0.5, 1000.0], atol=ATOL)  # row 3
    np.testing.assert_allclose(pc[3, 5], [0.75, 0.5, 1000.0], atol=ATOL)
    # Default principal point: the detector centre.
    pc = CArmGeometry(1000.0, 600.0, 4, 6, 0.25).pixel_centers_camera()
    np.testing.assert_allclose(pc[0, 0, :2], [-2.5 * 0.25, -1.5 * 0.25], atol=ATOL)
    np.testing.assert_allclose(pc[3, 5, :2], [2.5 * 0.25, 1.5 * 0.25], atol=ATOL)


def test_detector_size_and_fov():
    assert GEO.detector_size_mm == pytest.approx((307.2, 307.2), abs=1e-12)
    assert GEO.fov_x_deg == pytest.approx(2 * math.degrees(math.atan(153.6 / 1020.0)), abs=1e-12)


@pytest.mark.parametrize(
    "geo,new",
    [
        (CArmGeometry(1020.0, 700.0, 512, 384, 0.6, cx=200.3, cy=250.1), (200, 150)),
        (CArmGeometry(1020.0, 700.0, 512, 512, 0.6), (128, 128)),
        (CArmGeometry(1020.0, 700.0, 100, 100, 1.0, cx=40.0, cy=61.5), (300, 300)),
    ],
)
def test_resized_keeps_physical_detector_positions(geo, new):
    small = geo.resized(*new)
    assert (small.height, small.width) == new
    assert small.detector_size_mm == pytest.approx(geo.detector_size_mm, rel=1e-12)
    assert small.sdd_mm == geo.sdd_mm and small.sod_mm == geo.sod_mm
    rng = np.random.default_rng(3)
    T = g.pose_from_params([10.0, -5.0, 3.0, 4.0, 2.0, -20.0], geo.sod_mm)
    X = CENTER + rng.normal(scale=60.0, size=(10, 3))
    uv_old = g.project_points(g.projection_matrix(geo, T, CENTER), X)
    uv_new = g.project_points(g.projection_matrix(small, T, CENTER), X)
    # Continuous detector position in mm from the first pixel's outer edge: (u + 0.5) * s.
    np.testing.assert_allclose((uv_new + 0.5) * small.pixel_spacing_mm, (uv_old + 0.5) * geo.pixel_spacing_mm, atol=ATOL)
    if geo.cx is None:
        assert small.cx is None and small.principal_point == ((new[1] - 1) / 2, (new[0] - 1) / 2)


def test_resized_rejects_aspect_change():
    with pytest.raises(GeometryError, match="aspect"):
        GEO.resized(256, 128)


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(sod_mm=1020.0), "sod_mm"),  # SOD == SDD
        (dict(sod_mm=1100.0), "sod_mm"),  # SOD > SDD
        (dict(sod_mm=-5.0), "sod_mm"),
        (dict(pixel_spacing_mm=-0.6), "pixel_spacing_mm"),
        (dict(pixel_spacing_mm=0.0), "pixel_spacing_mm"),
        (dict(sdd_mm=float("nan")), "sdd_mm"),
        (dict(height=0), "height"),
        (dict(width=12.5), "width"),
        (dict(cx=float("inf")), "cx"),
    ],
)
def test_geometry_validation(kwargs, match):
    base = dict(sdd_mm=1020.0, sod_mm=700.0, height=64, width=64, pixel_spacing_mm=0.6)
    base.update(kwargs)
    with pytest.raises(GeometryError, match=match):
        CArmGeometry(**base)
    assert issubclass(GeometryError, ValueError)


def test_pose_input_errors():
    with pytest.raises(GeometryError, match=r"\(\.\.\., 6\)"):
        g.pose_from_params(np.zeros(5), 700.0)
    with pytest.raises(GeometryError, match="NaN"):
        g.pose_from_params([0, float("nan"), 0, 0, 0, 0], 700.0)
    with pytest.raises(GeometryError, match="rotation"):
        g.params_from_pose(np.diag([2.0, 1.0, 1.0, 1.0]), 700.0)
    with pytest.raises(GeometryError, match="rotation"):
        g.params_from_pose(np.diag([-1.0, 1.0, 1.0, 1.0]), 700.0)  # reflection
    with pytest.raises(GeometryError, match=r"\(N, 3\)"):
        g.project_points(np.zeros((3, 4)), np.zeros(3))
