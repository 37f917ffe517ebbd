"""Tests for sim.projection.se3 against independent truth: scipy's matrix exponential and rotation
vectors, closed-form rotations, round trips, and central finite differences.

Tolerances: float64 results are compared at 1e-10 (rad, or relative for mm values ~100): the
formulas are a few dozen well-conditioned flops, so errors are ~1e-14; 1e-10 leaves room for
BLAS differences while still catching any wrong term (those give errors >= 1e-4). float32 is
compared at 2e-5 relative: float32 has eps = 1.2e-7 and an exp/log round trip chains ~30
operations of condition O(1) plus a sqrt/atan2, giving errors of a few 1e-7..1e-6.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import torch
from scipy.spatial.transform import Rotation

from sim.projection import se3

REPO = Path(__file__).resolve().parents[2]

BACKENDS = [
    ("numpy", np.float64),
    ("numpy", np.float32),
    ("torch", torch.float32),
    ("torch", torch.float64),
]
BACKEND_IDS = ["np64", "np32", "torch32", "torch64"]
LEADING = [(1,), (2,), (5,), (2, 3)]


def to_backend(x, kind, dtype):
    x = np.asarray(x, dtype=np.float64)
    if kind == "numpy":
        return x.astype(dtype)
    return torch.as_tensor(x).to(dtype)


def to_np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy().astype(np.float64)
    return np.asarray(x, dtype=np.float64)


def is_f32(dtype) -> bool:
    return dtype in (np.float32, torch.float32)


def tol(dtype) -> float:
    return 2e-5 if is_f32(dtype) else 1e-10


def assert_kind(out, kind, dtype):
    """The output has the input's kind (numpy/torch) and dtype."""
    if kind == "numpy":
        assert isinstance(out, np.ndarray) and out.dtype == dtype
    else:
        assert isinstance(out, torch.Tensor) and out.dtype == dtype


def random_rotvecs(rng, shape, max_angle=math.pi - 0.2):
    """Rotation vectors with angles in (0.05, max_angle): log is unique there."""
    axis = rng.normal(size=shape + (3,))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = rng.uniform(0.05, max_angle, size=shape + (1,))
    return axis * angle


def random_twists(rng, shape):
    """Twists (omega rad, v mm) with |omega| < pi - 0.2 and |v| ~ 100 mm."""
    return np.concatenate([random_rotvecs(rng, shape), rng.normal(scale=100.0, size=shape + (3,))], -1)


def hat_np(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def transform_np(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


# ---------------------------------------------------------------------------------------------
# hat / vee
# ---------------------------------------------------------------------------------------------


def test_hat_is_cross_product_and_vee_inverts_it():
    rng = np.random.default_rng(0)
    w, x = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    W = se3.so3_hat(w)
    assert W.shape == (4, 3, 3)
    np.testing.assert_allclose((W @ x[..., None])[..., 0], np.cross(w, x), atol=1e-14)
    np.testing.assert_allclose(se3.so3_vee(W), w, atol=1e-15)


# ---------------------------------------------------------------------------------------------
# exp / log round trips on all backends and batch shapes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind,dtype", BACKENDS, ids=BACKEND_IDS)
@pytest.mark.parametrize("lead", LEADING, ids=lambda s: "x".join(map(str, s)))
def test_so3_exp_log_round_trip(kind, dtype, lead):
    rng = np.random.default_rng(1)
    w = random_rotvecs(rng, lead)
    R = se3.so3_exp(to_backend(w, kind, dtype))
    assert_kind(R, kind, dtype)
    assert tuple(R.shape) == lead + (3, 3)
    # Independent truth for exp: scipy's rotation vectors.
    R_ref = Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(lead + (3, 3))
    np.testing.assert_allclose(to_np(R), R_ref, atol=tol(dtype))
    w_back = se3.so3_log(R)
    assert_kind(w_back, kind, dtype)
    np.testing.assert_allclose(to_np(w_back), w, atol=tol(dtype) * 4)  # log of a rounded R


@pytest.mark.parametrize("kind,dtype", BACKENDS, ids=BACKEND_IDS)
@pytest.mark.parametrize("lead", LEADING, ids=lambda s: "x".join(map(str, s)))
def test_se3_exp_log_round_trip(kind, dtype, lead):
    rng = np.random.default_rng(2)
    xi = random_twists(rng, lead)
    T = se3.se3_exp(to_backend(xi, kind, dtype))
    assert_kind(T, kind, dtype)
    assert tuple(T.shape) == lead + (4, 4)
    xi_back = to_np(se3.se3_log(T))
    scale = np.array([1.0, 1.0, 1.0, 100.0, 100.0, 100.0])  # rad, and mm values ~100
    np.testing.assert_allclose(xi_back / scale, xi / scale, atol=tol(dtype) * 4)


def test_se3_exp_matches_scipy_expm():
    """Independent truth: the matrix exponential of the 4x4 twist matrix [[hat(w), v], [0, 0]]."""
    rng = np.random.default_rng(3)
    xis = list(random_twists(rng, (6,)))
    xis += [np.zeros(6), np.array([1e-8, -2e-8, 3e-9, 10.0, -5.0, 2.0])]  # zero and tiny angle
    xis += [np.array([0.0, 0.0, math.pi, 1.0, 2.0, 3.0])]  # exactly pi
    xis = np.stack(xis)
    T = se3.se3_exp(xis)
    for xi, Ti in zip(xis, T):
        M = np.zeros((4, 4))
        M[:3, :3], M[:3, 3] = hat_np(xi[:3]), xi[3:]
        ref = scipy.linalg.expm(M)
        np.testing.assert_allclose(Ti[:3, :3], ref[:3, :3], atol=1e-12)
        np.testing.assert_allclose(Ti[:3, 3], ref[:3, 3], atol=1e-10 * max(1.0, np.abs(ref).max()))
        np.testing.assert_array_equal(Ti[3], [0, 0, 0, 1])
    # The log recovers the twist at pi too (angle pi, axis +-z; with +z the translation matches).
    xi_pi = se3.se3_log(T[-1])
    assert abs(abs(xi_pi[2]) - math.pi) < 1e-12
    np.testing.assert_allclose(se3.se3_exp(xi_pi), T[-1], atol=1e-12)


@pytest.mark.parametrize("angle", [1e-3, 9.99e-3, 1.001e-2, 3e-2])
def test_se3_small_angle_series_and_closed_forms_agree_with_expm(angle):
    """Around the series/closed-form switch (1e-2 rad) exp and log stay exact: compared with
    scipy's expm at |v| = 1000 mm to 2e-12 mm (float64 rounding of 1000 mm is ~1e-13 mm; a wrong
    second series coefficient would be off by >= 1e-10 mm here)."""
    n = np.array([0.48, -0.6, 0.64])
    v = np.array([600.0, -800.0, 0.0])
    xi = np.concatenate([angle * n, v])
    M = np.zeros((4, 4))
    M[:3, :3], M[:3, 3] = hat_np(xi[:3]), xi[3:]
    ref = scipy.linalg.expm(M)
    T = se3.se3_exp(xi)
    np.testing.assert_allclose(T[:3, :3], ref[:3, :3], atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], ref[:3, 3], atol=2e-12)
    back = se3.se3_log(ref)
    np.testing.assert_allclose(back[:3], xi[:3], rtol=1e-12, atol=1e-17)
    np.testing.assert_allclose(back[3:], xi[3:], atol=2e-12)


# ---------------------------------------------------------------------------------------------
# so3_log at small angles and near pi
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind,dtype", BACKENDS, ids=BACKEND_IDS)
def test_so3_log_small_angles(kind, dtype):
    rng = np.random.default_rng(4)
    axis = rng.normal(size=(5, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    w = 1e-8 * axis
    R = Rotation.from_rotvec(w).as_matrix()  # independent construction of R
    w_log = to_np(se3.so3_log(to_backend(R, kind, dtype)))
    if is_f32(dtype):
        # float32 cannot store 1 - 5e-17 on the diagonal, but the off-diagonal entries +-1e-8
        # are stored to relative 6e-8: the log reads the angle from them.
        np.testing.assert_allclose(w_log, w, rtol=1e-6, atol=1e-14)
    else:
        # Off-diagonal entries carry absolute rounding ~1e-17, i.e. relative 1e-9 of 1e-8 rad.
        np.testing.assert_allclose(w_log, w, rtol=1e-8, atol=1e-20)
    zero = se3.so3_log(to_backend(np.eye(3), kind, dtype))
    np.testing.assert_array_equal(to_np(zero), np.zeros(3))


@pytest.mark.parametrize("kind,dtype", [b for b in BACKENDS if not is_f32(b[1])], ids=["np64", "torch64"])
@pytest.mark.parametrize("angle", [math.pi - 1e-6, math.pi], ids=["pi-1e-6", "pi"])
def test_so3_log_near_pi(kind, dtype, angle):
    axes = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [0.3, -0.5, 0.8], [-1, 2, -0.1]])
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    # Independent R: Rodrigues with cos/sin evaluated directly (at pi: 2 n n^T - I exactly).
    K = np.stack([hat_np(n) for n in axes])
    R = np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)
    w = to_np(se3.so3_log(to_backend(R, kind, dtype)))
    np.testing.assert_allclose(np.linalg.norm(w, axis=-1), angle, atol=1e-12)
    cos_axis = np.sum(w / np.linalg.norm(w, axis=-1, keepdims=True) * axes, -1)
    if angle < math.pi:
        np.testing.assert_allclose(cos_axis, 1.0, atol=1e-9)  # unique below pi: same sense
    else:
        np.testing.assert_allclose(np.abs(cos_axis), 1.0, atol=1e-12)  # +-n both valid at pi
    np.testing.assert_allclose(Rotation.from_rotvec(w).as_matrix(), R, atol=1e-12)


@pytest.mark.parametrize("kind,dtype", [b for b in BACKENDS if is_f32(b[1])], ids=["np32", "torch32"])
def test_so3_log_at_pi_float32(kind, dtype):
    axes = np.array([[1.0, 0, 0], [0, 0, 1], [1, 1, 1], [0.3, -0.5, 0.8]])
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    R = 2.0 * axes[:, :, None] * axes[:, None, :] - np.eye(3)
    w = to_np(se3.so3_log(to_backend(R, kind, dtype)))
    np.testing.assert_allclose(np.linalg.norm(w, axis=-1), math.pi, atol=1e-5)
    np.testing.assert_allclose(np.abs(np.sum(w * axes, -1)) / math.pi, 1.0, atol=1e-5)


# ---------------------------------------------------------------------------------------------
# rotation angle, inverse, compose, make/split
# ---------------------------------------------------------------------------------------------


def test_rotation_angle_matches_arccos_and_is_accurate_at_extremes():
    rng = np.random.default_rng(5)
    Ra = Rotation.random(20, random_state=6).as_matrix()
    Rb = Ra @ Rotation.from_rotvec(random_rotvecs(rng, (20,), max_angle=3.0)).as_matrix()
    M = np.swapaxes(Ra, -1, -2) @ Rb
    ref = np.arccos((np.trace(M, axis1=-2, axis2=-1) - 1.0) / 2.0)
    assert ref.min() > 0.04 and ref.max() < 3.05  # well conditioned for arccos
    np.testing.assert_allclose(se3.rotation_angle(Ra, Rb), ref, atol=1e-10)
    np.testing.assert_allclose(se3.rotation_angle(Rb, Ra), ref, atol=1e-10)  # symmetric
    # Where arccos fails (it returns 0 at 1e-8 rad) the atan2 form is exact.
    for angle in (1e-8, math.pi - 1e-7, math.pi):
        R = Rotation.from_rotvec([0.0, angle, 0.0]).as_matrix()
        assert abs(se3.rotation_angle(np.eye(3), R) - angle) < 1e-14
    assert se3.rotation_angle(Ra[0], Ra[0]) == 0.0


def test_rotation_and_translation_errors_known_values():
    Ta = transform_np(rz(math.radians(30.0)), [3.0, 4.0, 10.0])
    Tb = transform_np(np.eye(3), [0.0, 0.0, 10.0])
    assert abs(se3.rotation_error_deg(Ta, Tb) - 30.0) < 1e-12
    assert abs(se3.translation_error_mm(Ta, Tb) - 5.0) < 1e-12


def test_inverse_compose_make_split():
    rng = np.random.default_rng(7)
    T = se3.se3_exp(random_twists(rng, (5,)))
    Tinv = se3.se3_inverse(T)
    np.testing.assert_allclose(Tinv @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    np.testing.assert_allclose(T @ Tinv, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    np.testing.assert_allclose(Tinv, np.linalg.inv(T), atol=1e-12)
    # compose(A, B) applies B first: x -> A(B(x)).
    A, B = T[0], T[1]
    x = np.array([10.0, -20.0, 30.0])
    AB = se3.se3_compose(A, B)
    np.testing.assert_allclose(AB[:3, :3] @ x + AB[:3, 3], A[:3, :3] @ (B[:3, :3] @ x + B[:3, 3]) + A[:3, 3])
    R, t = se3.split(T)
    np.testing.assert_array_equal(se3.make_transform(R, t), T)
    # make_transform broadcasts a single rotation over a batch of translations.
    Tb = se3.make_transform(np.eye(3), rng.normal(size=(2, 3, 3)))
    assert Tb.shape == (2, 3, 4, 4)


@pytest.mark.parametrize("kind,dtype", BACKENDS, ids=BACKEND_IDS)
def test_inverse_on_all_backends(kind, dtype):
    rng = np.random.default_rng(8)
    T = se3.se3_exp(to_backend(random_twists(rng, (2, 3)), kind, dtype))
    I = to_np(se3.se3_compose(se3.se3_inverse(T), T))
    np.testing.assert_allclose(I, np.broadcast_to(np.eye(4), I.shape), atol=tol(dtype) * 100)  # mm ~100


# ---------------------------------------------------------------------------------------------
# Product metric
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind,dtype", BACKENDS, ids=BACKEND_IDS)
def test_product_log_exp_round_trip(kind, dtype):
    rng = np.random.default_rng(9)
    Ta = to_backend(se3.se3_exp(random_twists(rng, (5,))), kind, dtype)
    Tb = to_backend(se3.se3_exp(random_twists(rng, (5,))), kind, dtype)
    g = se3.product_log(Tb, Ta)
    assert_kind(g, kind, dtype)
    back = to_np(se3.product_exp(Tb, g))
    Ta_np = to_np(Ta)
    np.testing.assert_allclose(back[..., :3, :3], Ta_np[..., :3, :3], atol=tol(dtype) * 10)
    np.testing.assert_allclose(back[..., :3, 3], Ta_np[..., :3, 3], atol=tol(dtype) * 1000)
    # Closed-form meaning of the components: |w| = rotation angle, |v| = |t_a - t_b|.
    g = to_np(g)
    np.testing.assert_allclose(np.linalg.norm(g[:, :3], axis=-1), to_np(se3.rotation_angle(Ta[..., :3, :3], Tb[..., :3, :3])), atol=tol(dtype) * 10)
    np.testing.assert_allclose(np.linalg.norm(g[:, 3:], axis=-1), np.linalg.norm(Ta_np[:, :3, 3] - to_np(Tb)[:, :3, 3], axis=-1), rtol=tol(dtype) * 10)


def test_product_log_of_product_exp_is_identity_and_differs_from_se3_log():
    rng = np.random.default_rng(10)
    Tb = se3.se3_exp(random_twists(rng, (4,)))
    g = random_twists(rng, (4,))
    np.testing.assert_allclose(se3.product_log(Tb, se3.product_exp(Tb, g)), g, atol=1e-10)
    # Known point: a pure translation in the body frame of T_b.
    T = transform_np(rz(0.5), [1.0, 2.0, 3.0])
    Ta = transform_np(rz(0.5), [1.0, 2.0, 3.0] + rz(0.5) @ np.array([7.0, 0.0, 0.0]))
    np.testing.assert_allclose(se3.product_log(T, Ta), [0, 0, 0, 7, 0, 0], atol=1e-12)


def test_geodesic_distance_known_value_symmetric_and_zero():
    rng = np.random.default_rng(11)
    theta, t = 0.3, np.array([3.0, -4.0, 12.0])
    Ta = transform_np(rz(theta), t)
    for lam in (1.0, 57.0, se3.DEFAULT_MM_PER_RAD):
        d = se3.geodesic_distance(Ta, np.eye(4), mm_per_rad=lam)
        assert abs(d - math.sqrt((lam * theta) ** 2 + 13.0**2)) < 1e-10
    d2 = se3.geodesic_distance(Ta, np.eye(4), mm_per_rad=2.0, squared=True)
    assert abs(d2 - ((2.0 * theta) ** 2 + 169.0)) < 1e-10
    A = se3.se3_exp(random_twists(rng, (6,)))
    B = se3.se3_exp(random_twists(rng, (6,)))
    np.testing.assert_allclose(se3.geodesic_distance(A, B), se3.geodesic_distance(B, A), rtol=1e-12)
    np.testing.assert_array_equal(se3.geodesic_distance(np.eye(4), np.eye(4)), 0.0)
    np.testing.assert_array_equal(se3.geodesic_distance(A, A), np.zeros(6))


@pytest.mark.parametrize("lam", [1.0, se3.DEFAULT_MM_PER_RAD])
def test_label_is_minus_product_log_finite_differences(lam):
    """The learning label: d/d eps of 1/2 d_lambda^2(product_exp(T_b, eps e_k), T_a) at eps = 0
    equals -(lambda^2 w, v)_k with (w, v) = product_log(T_b, T_a); for lambda = 1 it is exactly
    -product_log, so g = -2 product_log(T_b, T_a) is the gradient of d^2.

    Central differences with h = 1e-5 have truncation error ~h^2 f''' ~ 1e-10 relative and
    rounding error ~eps f / h ~ 1e-11 * f; tolerance 1e-5 relative to the largest component."""
    rng = np.random.default_rng(12)
    for _ in range(3):
        Tb = se3.se3_exp(random_twists(rng, ()))
        Ta = se3.product_exp(Tb, np.concatenate([random_rotvecs(rng, (), 2.5), rng.normal(scale=30, size=3)]))
        wv = se3.product_log(Tb, Ta)
        expected = -np.concatenate([lam**2 * wv[:3], wv[3:]])

        def f(g):
            return 0.5 * se3.geodesic_distance(se3.product_exp(Tb, g), Ta, mm_per_rad=lam) ** 2

        h = 1e-5
        fd = np.array([(f(h * e) - f(-h * e)) / (2 * h) for e in np.eye(6)])
        np.testing.assert_allclose(fd, expected, atol=1e-5 * np.abs(expected).max())


# ---------------------------------------------------------------------------------------------
# torch autograd
# ---------------------------------------------------------------------------------------------


def test_torch_gradients_gradcheck():
    rng = np.random.default_rng(13)
    w = torch.tensor(random_rotvecs(rng, (3,), max_angle=2.5), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(se3.so3_exp, (w,))
    w_small = torch.tensor([[1e-3, -2e-3, 5e-4]], dtype=torch.float64, requires_grad=True)  # series branch
    assert torch.autograd.gradcheck(se3.so3_exp, (w_small,))
    T = torch.tensor(se3.se3_exp(random_twists(rng, (3,))), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(se3.se3_log, (T,))
    Ta = torch.tensor(se3.se3_exp(random_twists(rng, (2,))), dtype=torch.float64, requires_grad=True)
    Tb = torch.tensor(se3.se3_exp(random_twists(rng, (2,))), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(se3.product_log, (Tb, Ta))


def test_torch_gradients_finite_at_identity():
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    se3.so3_exp(w).sum().backward()
    assert torch.isfinite(w.grad).all()
    T = torch.eye(4, dtype=torch.float64, requires_grad=True)
    se3.geodesic_distance(T, torch.eye(4, dtype=torch.float64)).backward()
    assert torch.isfinite(T.grad).all()
    T.grad = None
    se3.se3_log(T).sum().backward()
    assert torch.isfinite(T.grad).all()


# ---------------------------------------------------------------------------------------------
# Input checks and torch-free import
# ---------------------------------------------------------------------------------------------


def test_shape_errors_name_expected_shape():
    with pytest.raises(se3.SE3ShapeError, match=r"expected shape \(\.\.\., 3\), got \(4,\)"):
        se3.so3_exp(np.zeros(4))
    with pytest.raises(se3.SE3ShapeError, match=r"\(\.\.\., 4, 4\)"):
        se3.se3_log(np.eye(3))
    with pytest.raises(se3.SE3ShapeError, match=r"\(\.\.\., 6\)"):
        se3.se3_exp(torch.zeros(2, 5))
    with pytest.raises(se3.SE3ShapeError, match=r"\(\.\.\., 3, 3\)"):
        se3.so3_log(np.zeros((3, 4)))
    with pytest.raises(ValueError):  # SE3ShapeError is a ValueError
        se3.product_exp(np.eye(4), np.zeros(3))


def test_non_finite_and_mixed_inputs_raise():
    xi = np.zeros(6)
    xi[4] = np.nan
    with pytest.raises(se3.SE3NonFiniteError, match="NaN"):
        se3.se3_exp(xi)
    with pytest.raises(se3.SE3NonFiniteError):
        se3.so3_log(torch.full((3, 3), float("nan")))
    T = np.eye(4)
    T[0, 3] = np.inf
    with pytest.raises(ValueError):
        se3.geodesic_distance(T, np.eye(4))
    with pytest.raises(se3.SE3InputError, match="mix"):
        se3.se3_compose(np.eye(4), torch.eye(4))
    with pytest.raises(se3.SE3InputError, match="mm_per_rad"):
        se3.geodesic_distance(np.eye(4), np.eye(4), mm_per_rad=-1.0)


def test_numpy_use_does_not_import_torch():
    code = (
        "import sys, numpy as np\n"
        "from sim.projection import se3\n"
        "T = se3.se3_exp(np.ones((2, 6)))\n"
        "se3.geodesic_distance(T, se3.se3_inverse(T)); se3.se3_log(T)\n"
        "assert 'torch' not in sys.modules, 'sim.projection.se3 imported torch'\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=60)
