"""Tests of learn.labels against independent truth: the defining formula, finite differences
of the squared distance (written out here), exact landing of a half step, and sampling rules."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from learn.labels import (
    DEFAULT_ROT_SCALE_RAD,
    DEFAULT_TRANS_SCALE_MM,
    LabelNormalizer,
    LearnLabelError,
    apply_update,
    geodesic_label,
    label_scale,
    sample_pairs,
)
from sim.projection.se3 import product_exp, product_log, so3_exp


def _random_poses(gen: torch.Generator, shape: tuple[int, ...], dtype=torch.float64,
                  max_angle: float = 2.5) -> torch.Tensor:
    """Random poses with rotation angle < max_angle rad (< pi: the log is smooth) and t in +-100 mm."""
    axis = torch.randn(*shape, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(*shape, 1, generator=gen, dtype=torch.float64) * max_angle
    R = so3_exp(axis * angle)
    t = (torch.rand(*shape, 3, generator=gen, dtype=torch.float64) - 0.5) * 200.0
    T = torch.zeros(*shape, 4, 4, dtype=torch.float64)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T.to(dtype)


def _half_sq_dist(Ta: torch.Tensor, Tb: torch.Tensor) -> torch.Tensor:
    """0.5 d^2 with lambda = 1, written independently: theta from arccos of the trace (fine away
    from 0 and pi, where the test poses are), translation difference in mm."""
    M = Ta[..., :3, :3].transpose(-1, -2) @ Tb[..., :3, :3]
    tr = M.diagonal(dim1=-2, dim2=-1).sum(-1)
    theta = torch.arccos(((tr - 1.0) / 2.0).clamp(-1.0, 1.0))
    dt = Ta[..., :3, 3] - Tb[..., :3, 3]
    return 0.5 * (theta**2 + (dt**2).sum(-1))


def test_label_is_minus_two_product_log_and_explicit_formula():
    gen = torch.Generator().manual_seed(0)
    Ta, Tb = _random_poses(gen, (5,)), _random_poses(gen, (5,))
    g = geodesic_label(Ta, Tb)
    torch.testing.assert_close(g, -2.0 * product_log(Tb, Ta), rtol=0, atol=0)
    # Explicit: translation part -2 R_b^T (t_a - t_b) (mm); rotation part -2 w with
    # so3_exp(w) = R_b^T R_a (checked through exp to avoid reusing so3_log).
    Rb, Ra = Tb[:, :3, :3], Ta[:, :3, :3]
    v = (Rb.transpose(-1, -2) @ (Ta[:, :3, 3] - Tb[:, :3, 3])[..., None])[..., 0]
    torch.testing.assert_close(g[:, 3:], -2.0 * v, rtol=0, atol=1e-12)
    torch.testing.assert_close(so3_exp(-0.5 * g[:, :3]), Rb.transpose(-1, -2) @ Ra, rtol=0, atol=1e-12)


def test_label_is_gradient_of_squared_distance_finite_differences():
    # d/d eps_k [0.5 d^2(product_exp(T_b, eps e_k), T_a)] at 0 = -log_k = 0.5 g_k.
    # Central differences with h = 1e-5 in float64: truncation O(h^2 * |third derivative|) ~1e-10
    # and rounding ~1e-16 * 1e4 / 1e-5 ~ 1e-7 absolute on gradients of order 1-100, so 1e-5
    # relative (to the gradient's norm) is a meaningful bound; a sign or factor error fails it.
    gen = torch.Generator().manual_seed(1)
    Ta, Tb = _random_poses(gen, (6,)), _random_poses(gen, (6,))
    g = geodesic_label(Ta, Tb)
    h = 1e-5
    fd = torch.empty_like(g)
    for k in range(6):
        e = torch.zeros(6, dtype=torch.float64)
        e[k] = h
        fp = _half_sq_dist(product_exp(Tb, e.expand(6, 6)), Ta)
        fm = _half_sq_dist(product_exp(Tb, -e.expand(6, 6)), Ta)
        fd[:, k] = (fp - fm) / (2 * h)
    err = (fd - 0.5 * g).norm(dim=-1) / g.norm(dim=-1)
    assert float(err.max()) < 1e-5, err


def test_half_step_lands_on_target_and_default_step_moves_30_percent():
    gen = torch.Generator().manual_seed(2)
    Ta, Tb = _random_poses(gen, (7,)), _random_poses(gen, (7,))
    g = geodesic_label(Ta, Tb)
    torch.testing.assert_close(apply_update(Tb, g, step=0.5), Ta, rtol=0, atol=1e-9)
    # step 0.15: the remaining log is (1 - 0.3) of the initial one (straight geodesic).
    T1 = apply_update(Tb, g)
    torch.testing.assert_close(product_log(T1, Ta), _rotate_log(Tb, T1, 0.7 * product_log(Tb, Ta)),
                               rtol=0, atol=1e-9)


def _rotate_log(Tb, T1, log_b):
    """Body coordinates change from T_b to T_1: rotation vector w is invariant (the rotation step
    is about w itself), translation re-expressed: R_1^T R_b v."""
    R = T1[..., :3, :3].transpose(-1, -2) @ Tb[..., :3, :3]
    return torch.cat([log_b[..., :3], (R @ log_b[..., 3:, None])[..., 0]], -1)


def test_batch_shapes_and_dtypes():
    gen = torch.Generator().manual_seed(3)
    Ta = _random_poses(gen, (1, 4, 7))
    Tb = _random_poses(gen, (1, 4, 7))
    for dtype in (torch.float32, torch.float64):
        g = geodesic_label(Ta.to(dtype), Tb.to(dtype))
        assert g.shape == (1, 4, 7, 6) and g.dtype == dtype
        T = apply_update(Tb.to(dtype), g)
        assert T.shape == (1, 4, 7, 4, 4) and T.dtype == dtype
    # Broadcasting one target against a batch.
    assert geodesic_label(Ta[0, 0, 0], Tb).shape == (1, 4, 7, 6)
    # float32 agrees with float64 to float32 accuracy (labels of order 1-400).
    g32 = geodesic_label(Ta.float(), Tb.float()).double()
    torch.testing.assert_close(g32, geodesic_label(Ta, Tb), rtol=0, atol=1e-3)


def test_label_errors():
    with pytest.raises(LearnLabelError, match="T_a"):
        geodesic_label(torch.eye(3), torch.eye(4))
    with pytest.raises(LearnLabelError, match="g"):
        apply_update(torch.eye(4), torch.zeros(5))
    with pytest.raises(LearnLabelError, match="step"):
        apply_update(torch.eye(4), torch.zeros(6), step=-1.0)
    with pytest.raises(LearnLabelError, match="rot_scale_rad"):
        LabelNormalizer(rot_scale_rad=0.0)


def test_normalizer_round_trip_and_defaults():
    assert DEFAULT_ROT_SCALE_RAD == pytest.approx(math.radians(80.0))
    assert DEFAULT_TRANS_SCALE_MM == 150.0
    s = label_scale(dtype=torch.float64)
    torch.testing.assert_close(s, torch.tensor([math.radians(80)] * 3 + [150.0] * 3, dtype=torch.float64))
    norm = LabelNormalizer()
    gen = torch.Generator().manual_seed(4)
    g = geodesic_label(_random_poses(gen, (50,)), _random_poses(gen, (50,)))
    y = norm.normalize(g)
    # Independent truth: component-wise division.
    torch.testing.assert_close(y[:, :3], g[:, :3] / math.radians(80), rtol=1e-15, atol=0)
    torch.testing.assert_close(y[:, 3:], g[:, 3:] / 150.0, rtol=1e-15, atol=0)
    # Round trip: one division and one multiplication, at most ~1 ulp (2.2e-16) relative.
    torch.testing.assert_close(norm.denormalize(y), g, rtol=4.5e-16, atol=0)
    g32 = g.float()
    torch.testing.assert_close(norm.denormalize(norm.normalize(g32)), g32, rtol=2.4e-7, atol=0)
    # Power-of-two scales round-trip bit-exactly.
    p2 = LabelNormalizer(rot_scale_rad=2.0, trans_scale_mm=128.0)
    assert torch.equal(p2.denormalize(p2.normalize(g)), g)
    assert norm.to_dict() == {"rot_scale_rad": DEFAULT_ROT_SCALE_RAD, "trans_scale_mm": 150.0}


def test_sample_pairs_same_subject_never_self_and_deterministic():
    groups = np.array([3, 3, 7, 7, 7, 1, 3, 9, 9, 7])  # subject 1 has a single image (index 5)
    pairs = sample_pairs(10, 5000, np.random.default_rng(0), groups=groups)
    assert pairs.shape == (5000, 2) and pairs.dtype == np.int64
    i, j = pairs[:, 0], pairs[:, 1]
    assert np.all(groups[i] == groups[j])
    single = i == 5
    assert single.any() and np.all(j[single] == 5)
    assert np.all(i[~single] != j[~single])
    # Every ordered same-subject pair (i != j) occurs (uniform: ~5000/10/(size-1) each).
    expected = {(a, b) for a in range(10) for b in range(10)
                if a != b and groups[a] == groups[b]} | {(5, 5)}
    assert set(map(tuple, pairs.tolist())) == expected
    again = sample_pairs(10, 5000, np.random.default_rng(0), groups=groups)
    assert np.array_equal(pairs, again)
    other = sample_pairs(10, 5000, np.random.default_rng(1), groups=groups)
    assert not np.array_equal(pairs, other)


def test_sample_pairs_errors_and_no_groups():
    p = sample_pairs(4, 100, np.random.default_rng(0))
    assert np.all(p[:, 0] != p[:, 1]) and p.min() >= 0 and p.max() < 4
    with pytest.raises(LearnLabelError, match="groups"):
        sample_pairs(4, 10, np.random.default_rng(0), groups=np.zeros(3))
    with pytest.raises(LearnLabelError, match="rng"):
        sample_pairs(4, 10, 0)
    with pytest.raises(LearnLabelError, match="n_images"):
        sample_pairs(0, 10, np.random.default_rng(0))
