"""learn.image_term: the image-space term's value at the truth, its gradient against finite
differences, and the differentiable ray march it rests on."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from learn.image_term import ImageTerm, ImageTermError, ncc
from learn.labels import LabelNormalizer, geodesic_label
from sim.projection.geometry import pose_from_params
from sim.projection.raymarch import TorchVolumes
from sim.projection.scene import load_scene


def _blobs(step_fraction=0.5):
    """Two Gaussian blobs (sigma 15 and 10 mm) in a 128 mm cube of 2 mm voxels, centred on the
    anatomy centre: a smooth volume, so the trilinear march's image is smooth in the pose."""
    n = 64
    ax = (np.arange(n) - n / 2) * 2.0
    x, y, z = np.meshgrid(ax, ax, ax, indexing="ij")
    vol = 0.02 * (np.exp(-((x - 10) ** 2 + y ** 2 + (z + 5) ** 2) / (2 * 15.0 ** 2))
                  + 0.6 * np.exp(-((x + 20) ** 2 + (y - 10) ** 2 + z ** 2) / (2 * 10.0 ** 2)))
    affine = np.diag([2.0, 2.0, 2.0, 1.0])
    affine[:3, 3] = -n
    geometry = load_scene("cios_fusion").geometry_at(32, 32)
    return TorchVolumes([vol[None].astype(np.float32)], [affine], [np.zeros(3)], geometry,
                        step_fraction=step_fraction, dtype=torch.float64)


def _poses():
    sod = load_scene("cios_fusion").geometry.sod_mm
    t_a = pose_from_params(np.array([[5.0, -3.0, 4.0, 10.0, -5.0, 20.0]]), sod)
    t_b = pose_from_params(np.zeros((1, 6)), sod)
    return t_a, t_b


def test_the_term_is_zero_at_the_true_pose_and_grows_away_from_it():
    volumes, norm = _blobs(), LabelNormalizer()
    term = ImageTerm(volumes, norm)
    t_a, t_b = _poses()
    y = norm.normalize(geodesic_label(torch.from_numpy(t_a), torch.from_numpy(t_b)))
    at_truth = float(term([0], t_a, t_b, y))
    assert at_truth < 1e-5  # the half step lands on T_A to rounding: the same image
    values = [float(term([0], t_a, t_b, y + s * torch.tensor([[0.0, 0.0, 0.0, 0.1, 0.0, 0.0]]))) for s in (0.5, 1, 2)]
    assert at_truth < values[0] < values[1] < values[2]


def test_the_gradient_is_the_finite_differences():
    """Autograd through the pose update and the trilinear march against central differences
    (step 1e-4 in normalised units, ~0.008 deg or 0.015 mm): within 1 % of the largest component
    (the march is piecewise linear in the sample positions; at this step the kinks average out
    over ~10^5 samples)."""
    volumes, norm = _blobs(), LabelNormalizer()
    term = ImageTerm(volumes, norm)
    t_a, t_b = _poses()
    y0 = norm.normalize(geodesic_label(torch.from_numpy(t_a), torch.from_numpy(t_b)))
    y = (y0 + 0.05 * torch.randn(1, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64))
    y.requires_grad_()
    term([0], t_a, t_b, y).backward()
    fd = []
    for i in range(6):
        e = torch.zeros(1, 6, dtype=torch.float64)
        e[0, i] = 1e-4
        fd.append((float(term([0], t_a, t_b, y.detach() + e)) - float(term([0], t_a, t_b, y.detach() - e))) / 2e-4)
    fd = torch.tensor(fd, dtype=torch.float64)
    assert fd.abs().max() > 0.1  # the term does depend on the pose here
    assert (y.grad[0] - fd).abs().max() <= 0.01 * fd.abs().max()


def test_a_pose_that_requires_grad_renders_the_same_image():
    """The torch path of the march (poses that require grad) is the numpy path's image."""
    volumes = _blobs()
    t_a, _ = _poses()
    plain = volumes.line_integrals([0], t_a)
    graph = volumes.line_integrals([0], torch.from_numpy(t_a).requires_grad_())
    assert graph.requires_grad
    assert torch.allclose(plain, graph.detach(), rtol=1e-12, atol=1e-12)


def test_ncc_is_one_for_an_affine_copy_and_zero_for_a_blank_image():
    a = torch.rand(2, 1, 8, 8, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    assert torch.allclose(ncc(a, 3 * a + 1), torch.ones(2, dtype=torch.float64))
    assert torch.allclose(ncc(a, torch.zeros_like(a)), torch.zeros(2, dtype=torch.float64))


def test_shapes_that_do_not_fit_are_refused():
    term = ImageTerm(_blobs(), LabelNormalizer())
    t_a, t_b = _poses()
    with pytest.raises(ImageTermError, match="K = 2"):
        term([0], t_a, t_b, torch.zeros(2, 6))
    with pytest.raises(ImageTermError, match="TorchVolumes"):
        ImageTerm(object(), LabelNormalizer())
