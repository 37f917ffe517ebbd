"""learn.densenet against torchvision's DenseNet, the reference it replaces at registration."""

from __future__ import annotations

import doctest

import pytest
import torch

import learn.densenet
from learn.densenet import densenet_features
from learn.model import _BACKBONE_CONFIG, Backbone

torchvision_models = pytest.importorskip("torchvision.models", reason="torchvision is the reference")


@pytest.mark.parametrize("backbone", [Backbone.TINY, Backbone.SMALL, Backbone.MEDIUM, Backbone.DENSENET121])
def test_the_features_have_torchvisions_names_and_shapes(backbone):
    """Every parameter and buffer under the same name with the same shape, in the same order:
    a torchvision state dict (an ImageNet checkpoint) loads unchanged."""
    growth, blocks, init = _BACKBONE_CONFIG[backbone]
    ours = densenet_features(growth_rate=growth, block_config=blocks, num_init_features=init).state_dict()
    ref = torchvision_models.DenseNet(growth_rate=growth, block_config=blocks, num_init_features=init).features.state_dict()
    assert list(ours) == list(ref)
    assert [tuple(v.shape) for v in ours.values()] == [tuple(v.shape) for v in ref.values()]


@pytest.mark.parametrize("train", [False, True])
def test_the_same_weights_give_torchvisions_outputs_and_gradients(train):
    """torchvision's randomly initialised features (batch norms given non-trivial statistics) loaded
    into ours: the same output in eval and training mode, and the same input gradient, to float32
    rounding over ~10 layers (1e-5 relative to the output's scale)."""
    torch.manual_seed(0)
    growth, blocks, init = _BACKBONE_CONFIG[Backbone.SMALL]
    ref = torchvision_models.DenseNet(growth_rate=growth, block_config=blocks, num_init_features=init).features
    with torch.no_grad():
        for m in ref.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.2, 0.2)
    ours = densenet_features(growth_rate=growth, block_config=blocks, num_init_features=init)
    ours.load_state_dict(ref.state_dict())
    ours.train(train)
    ref.train(train)
    x = torch.randn(3, 3, 64, 96)
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    a, b = ours(xa), ref(xb)
    assert a.shape == b.shape == (3, (((init + 3 * growth) // 2 + 4 * growth) // 2 + 6 * growth) // 2 + 4 * growth, 2, 3)
    scale = b.abs().max().item()
    assert (a - b).abs().max().item() <= 1e-5 * scale
    a.square().sum().backward()
    b.square().sum().backward()
    assert (xa.grad - xb.grad).abs().max().item() <= 1e-5 * xb.grad.abs().max().item()


@pytest.mark.parametrize("backbone", [Backbone.TINY, Backbone.MEDIUM])
def test_a_seeded_network_is_torchvisions_to_the_bit(backbone):
    """After the same seed, every weight equals torchvision's: the same numbers drawn in the same order."""
    growth, blocks, init = _BACKBONE_CONFIG[backbone]
    torch.manual_seed(5)
    ours = densenet_features(growth_rate=growth, block_config=blocks, num_init_features=init).state_dict()
    ours_next = torch.rand(3)  # the stream after the build: the same numbers consumed
    torch.manual_seed(5)
    ref = torchvision_models.DenseNet(growth_rate=growth, block_config=blocks, num_init_features=init).features.state_dict()
    assert all(torch.equal(ours[k], ref[k]) for k in ref)
    assert torch.equal(ours_next, torch.rand(3))


def test_initialised_as_torchvision_initialises():
    """Convolutions Kaiming-normal (std sqrt(2 / fan_in), the sample std within 10 % on the larger
    layers), batch norms weight 1 and bias 0; a one-channel first convolution."""
    torch.manual_seed(1)
    f = densenet_features(growth_rate=24, block_config=(4, 6, 8, 6), num_init_features=48, in_channels=1)
    assert f.conv0.weight.shape == (48, 1, 7, 7)
    for m in f.modules():
        if isinstance(m, torch.nn.Conv2d) and m.weight.numel() >= 2000:
            fan_in = m.weight[0].numel()
            assert m.weight.std().item() == pytest.approx((2.0 / fan_in) ** 0.5, rel=0.1)
        elif isinstance(m, torch.nn.BatchNorm2d):
            assert torch.all(m.weight == 1) and torch.all(m.bias == 0)


def test_the_docstring_example_runs():
    assert doctest.testmod(learn.densenet).failed == 0


def test_registration_does_not_import_torchvision():
    """The registration path (the CLI, the API, a network's predictor) never imports torchvision,
    whose import costs about 3 s of a cold call (docs/benchmarks.md)."""
    import subprocess
    import sys

    code = ("import sys, register.cli, register.api, learn.predict, learn.checkpoint; "
            "print('torchvision' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
