"""Tests of learn.model: the contextual pose-update network (tiny DenseNet unless stated)."""

from __future__ import annotations

import time
from collections import OrderedDict

import pytest
import torch
from torch import nn
from torchvision.models import DenseNet

from learn.model import (
    Backbone,
    PoseInputError,
    PoseUpdateNet,
    Weights,
    WeightsError,
    WeightsMismatchError,
    WeightsNotFoundError,
    _CoordConv2d,
    coordinate_channels,
    load_backbone_weights,
    pose_update_net,
)

# Float32 sums of three terms of size ~0.1-1: 1e-6 is a few ulps above rounding.
TOL = 1e-6


def _tiny(seed: int = 0, **kwargs) -> PoseUpdateNet:
    torch.manual_seed(seed)
    return pose_update_net(backbone="tiny", **kwargs)


def _images(batch: int, h: int, w: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand(batch, 1, h, w, generator=gen) * 2 - 1, torch.rand(batch, 1, h, w, generator=gen) * 2 - 1)


def _tiny_torchvision(seed: int = 3) -> DenseNet:
    """A 3-channel torchvision DenseNet of the tiny architecture, random weights (the 'checkpoint')."""
    torch.manual_seed(seed)
    return DenseNet(growth_rate=8, block_config=(2, 2, 2, 2), num_init_features=16)


# --------------------------------------------------------------------------------------------
# Output shapes and the weighted sum
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("batch", [1, 4])
@pytest.mark.parametrize("size", [(64, 64), (96, 128)])
def test_output_shapes_and_weighted_sum(batch, size):
    model = _tiny().eval()
    a, b = _images(batch, *size)
    with torch.no_grad():
        out = model(a, b)
    assert out.g.shape == (batch, 6)
    assert out.g_levels.shape == (batch, 3, 6)
    assert out.weights.shape == (batch, 3)
    assert bool((out.weights >= 0).all())
    torch.testing.assert_close(out.weights.sum(dim=1), torch.ones(batch), atol=TOL, rtol=0)
    # Independent recomputation of the sum with an explicit loop over levels.
    expected = sum(out.weights[:, i : i + 1] * out.g_levels[:, i] for i in range(3))
    torch.testing.assert_close(out.g, expected, atol=TOL, rtol=0)
    # The weights are not all equal (the logits are learned, not constant): a real softmax.
    assert float(out.weights.std()) > 1e-4


def test_feature_taps_have_the_documented_strides_and_channels():
    model = _tiny()
    a, b = _images(2, 64, 96)
    feats = model.extract_features(a, b)
    # tiny: 16 init + 2 x 8 per block, halved by transitions -> 32 channels at each tap, x2 images.
    assert [tuple(f.shape) for f in feats] == [(2, 64, 8, 12), (2, 64, 4, 6), (2, 64, 2, 3)]


# --------------------------------------------------------------------------------------------
# Weights
# --------------------------------------------------------------------------------------------


def test_first_conv_takes_one_channel_and_loaded_weights_are_the_rgb_mean(tmp_path):
    source = _tiny_torchvision()
    path = tmp_path / "tiny.pth"
    torch.save(source.state_dict(), path)
    model = _tiny(seed=9)
    assert model.backbone.features.conv0.in_channels == 1
    load_backbone_weights(model, path)
    w_rgb = source.features.conv0.weight.detach()
    assert w_rgb.shape[1] == 3
    assert torch.equal(model.backbone.features.conv0.weight.detach(), w_rgb.mean(dim=1, keepdim=True))
    # Every other backbone tensor is copied exactly.
    src = source.features.state_dict()
    for key, value in model.backbone.features.state_dict().items():
        if key != "conv0.weight":
            assert torch.equal(value, src[key]), key


def test_builder_loads_imagenet_local_from_path(tmp_path):
    source = _tiny_torchvision()
    path = tmp_path / "tiny.pth"
    torch.save(source.state_dict(), path)
    model = pose_update_net(backbone="tiny", weights=Weights.IMAGENET_LOCAL, weights_path=str(path))
    key = "denseblock3.denselayer2.conv2.weight"
    assert torch.equal(model.backbone.features.state_dict()[key], source.features.state_dict()[key])


def test_old_style_keys_are_remapped(tmp_path):
    source = _tiny_torchvision()
    old = OrderedDict()
    n_renamed = 0
    for key, value in source.state_dict().items():
        if key.endswith("num_batches_tracked"):
            continue  # torchvision's old checkpoints predate these counters
        new = key
        for part in ("norm1", "norm2", "conv1", "conv2"):
            if "denselayer" in key and f".{part}." in key:
                new = key.replace(f".{part}.", f".{part[:-1]}.{part[-1]}.")
        n_renamed += new != key
        old[new] = value
    assert "features.denseblock1.denselayer1.norm.1.weight" in old and n_renamed > 0
    path = tmp_path / "old.pth"
    torch.save(old, path, _use_new_zipfile_serialization=False)  # the format of torchvision's old files
    model = _tiny(seed=9)
    load_backbone_weights(model, path)
    got = model.backbone.features.state_dict()
    for key, value in source.features.state_dict().items():
        if key != "conv0.weight":
            assert torch.equal(got[key], value), key


def test_missing_file_raises_with_instructions(tmp_path):
    model = pose_update_net(backbone="tiny")
    path = tmp_path / "nowhere" / "densenet161-8d451a50.pth"
    with pytest.raises(WeightsError) as info:
        load_backbone_weights(model, path)
    assert isinstance(info.value, FileNotFoundError) and isinstance(info.value, WeightsNotFoundError)
    msg = str(info.value)
    assert str(path) in msg and "not found" in msg and "cannot download" in msg and "Weights.NONE" in msg


def test_missing_densenet161_weights_message_names_the_checkpoint(tmp_path, monkeypatch):
    # The default path is looked up under torch.hub's directory; point it at an empty folder.
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    with pytest.raises(WeightsNotFoundError) as info:
        pose_update_net(backbone="densenet161", weights=Weights.IMAGENET_LOCAL)
    msg = str(info.value)
    assert msg.startswith("ImageNet weights for densenet161 not found at ")
    assert "densenet161-8d451a50.pth" in msg and "use weights=Weights.NONE" in msg


def test_mismatching_file_names_keys(tmp_path):
    # A densenet121-shaped state dict does not fit the tiny backbone: shapes and keys differ.
    torch.manual_seed(0)
    path = tmp_path / "other.pth"
    torch.save(DenseNet(growth_rate=8, block_config=(3, 2, 2, 2), num_init_features=16).state_dict(), path)
    model = _tiny()
    with pytest.raises(WeightsMismatchError) as info:
        load_backbone_weights(model, path)
    msg = str(info.value)
    assert isinstance(info.value, ValueError)
    assert "does not match the tiny backbone" in msg and "unexpected keys" in msg
    assert "denseblock1.denselayer3" in msg  # the extra layer is named
    # Truncated to at most 5 names per kind: the list ends with "(and N more)".
    assert "more)" in msg


def test_non_state_dict_file_raises(tmp_path):
    path = tmp_path / "junk.pth"
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(WeightsMismatchError, match="weights file .*junk.pth is not a PyTorch file"):
        load_backbone_weights(_tiny(), path)
    # a file that pickles objects is read with weights_only=True: refused, nothing of it runs
    torch.save({"features.conv0.weight": torch.zeros(1), "hook": Weights.NONE}, path)
    with pytest.raises(WeightsMismatchError, match="contains objects other than tensors and plain data"):
        load_backbone_weights(_tiny(), path)


# --------------------------------------------------------------------------------------------
# CoordConv
# --------------------------------------------------------------------------------------------


def test_coordinate_channels_are_linspace():
    c = coordinate_channels(2, 5, 7)
    assert c.shape == (2, 2, 5, 7)
    for j, x in enumerate(torch.linspace(-1, 1, 7)):
        assert torch.equal(c[:, 0, :, j], torch.full((2, 5), float(x)))
    for i, y in enumerate(torch.linspace(-1, 1, 5)):
        assert torch.equal(c[:, 1, i, :], torch.full((2, 7), float(y)))
    assert c[0, 0, 0, 0] == -1 and c[0, 0, 0, -1] == 1 and c[0, 1, -1, 0] == 1


def test_coordconv_appends_exactly_the_coordinates():
    # A 1x1 CoordConv whose weights pick input channel k reproduces channel k of cat(x, coords).
    conv = _CoordConv2d(3, 5, 1)
    with torch.no_grad():
        conv.weight.zero_()
        conv.bias.zero_()
        for k in range(5):
            conv.weight[k, k, 0, 0] = 1.0
    x = torch.randn(2, 3, 4, 6)
    y = conv(x)
    assert torch.equal(y[:, :3], x)
    xs, ys = torch.linspace(-1, 1, 6), torch.linspace(-1, 1, 4)
    assert torch.equal(y[:, 3], xs.expand(2, 4, 6))
    assert torch.equal(y[:, 4], ys[:, None].expand(2, 4, 6))


# --------------------------------------------------------------------------------------------
# Cached features, frozen backbone
# --------------------------------------------------------------------------------------------


def test_heads_forward_of_features_equals_forward():
    model = _tiny().eval()
    a, b = _images(3, 64, 80)
    with torch.no_grad():
        direct = model(a, b)
        cached = model.heads_forward(model.extract_features(a, b))
    for x, y in zip(direct, cached):
        torch.testing.assert_close(x, y, atol=TOL, rtol=0)


def test_channels_last_layout_computes_what_the_plain_layout_does():
    """The network runs channels last (NHWC, the fast layout of oneDNN and cuDNN): same output as
    the plain NCHW layout to float32 rounding (another summation order; 1e-4 of outputs of
    order 0.1-1), and weights loaded from a plain state dict keep the layout."""
    torch.manual_seed(0)
    fast = pose_update_net(backbone="tiny").eval()
    w = fast.heads[0].blocks[0].conv1.weight  # (C, C + 2, 3, 3)
    assert w.is_contiguous(memory_format=torch.channels_last) and not w.is_contiguous()
    plain = pose_update_net(backbone="tiny").eval()
    plain.load_state_dict({k: v.contiguous() for k, v in fast.state_dict().items()})
    assert plain.heads[0].blocks[0].conv1.weight.is_contiguous(memory_format=torch.channels_last)
    plain.to(memory_format=torch.contiguous_format)
    plain.backbone.memory_format = torch.contiguous_format
    a, b = torch.randn(3, 1, 64, 64), torch.randn(3, 1, 64, 64)
    with torch.no_grad():
        got, ref = fast(a, b), plain(a, b)
    torch.testing.assert_close(got.g, ref.g, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(got.weights, ref.weights, rtol=1e-4, atol=1e-5)


def _one_adam_step(model) -> None:
    """One Adam step (rate 1e-3) of ``model``'s trainable weights on 4 random 48 x 48 pairs."""
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-3)
    a, b = _images(4, 48, 48)
    loss = model.loss(model(a, b), torch.randn(4, 6))
    opt.zero_grad()
    loss.backward()
    opt.step()


def test_frozen_backbone_step_changes_heads_only():
    model = _tiny(freeze_backbone=True)
    assert all(not p.requires_grad for p in model.backbone.parameters())
    assert all(p.requires_grad for p in model.heads.parameters())
    model.train()
    assert not model.backbone.training and model.heads[0].training  # BN stats stay fixed
    before_bb = {k: v.clone() for k, v in model.backbone.state_dict().items()}  # includes BN buffers
    before_heads = [p.detach().clone() for p in model.heads.parameters()]
    _one_adam_step(model)
    for k, v in model.backbone.state_dict().items():
        assert torch.equal(v, before_bb[k]), k
    changed = [not torch.equal(p, q) for p, q in zip(model.heads.parameters(), before_heads)]
    assert all(changed), f"{changed.count(False)} head tensors did not change"


def test_a_frozen_backbone_trained_from_a_stage_changes_that_stage_on_and_keeps_its_statistics():
    """train_backbone_from: the stages from the one named train again, those before stay as they
    were, and every batch norm keeps its running statistics (eval mode) through a training step."""
    model = _tiny(freeze_backbone=True)
    names = [n for n, _ in model.backbone.features.named_children()]
    trained = model.train_backbone_from("denseblock4")
    assert trained == names[names.index("denseblock4"):] == ["denseblock4", "norm5"]
    model.train()
    assert not model.backbone.training and not model.backbone.features.denseblock4.training
    before = {k: v.clone() for k, v in model.backbone.features.state_dict().items()}
    _one_adam_step(model)
    after = model.backbone.features.state_dict()
    for k, v in after.items():
        stage = k.split(".")[0]
        if stage in trained and k.endswith(("weight", "bias")):
            assert not torch.equal(v, before[k]), f"{k} did not train"
        else:  # the stages before, and the running statistics everywhere
            assert torch.equal(v, before[k]), k


def test_train_backbone_from_names_the_stages_and_needs_a_frozen_backbone():
    model = _tiny(freeze_backbone=True)
    with pytest.raises(PoseInputError, match="no stage 'block11'.*conv0, norm0, relu0"):
        model.train_backbone_from("block11")
    with pytest.raises(PoseInputError, match="needs a frozen backbone"):
        _tiny().train_backbone_from("denseblock4")


# --------------------------------------------------------------------------------------------
# Learning, asymmetry, loss
# --------------------------------------------------------------------------------------------


@pytest.fixture
def one_thread():
    """One intra-op thread: on a shared 2-core machine this avoids oversubscription stalls."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_tiny_model_overfits_four_pairs(one_thread):
    model = _tiny(seed=0)
    a, b = _images(4, 48, 48, seed=5)
    g_true = torch.randn(4, 6, generator=torch.Generator().manual_seed(6))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model.train()
    with torch.no_grad():
        first = float(model.loss(model(a, b), g_true))
    last = first
    for _ in range(300):
        loss = model.loss(model(a, b), g_true)
        opt.zero_grad()
        loss.backward()
        opt.step()
        last = loss.item()
        if last < first / 20:
            break
    with torch.no_grad():
        final = float(model.loss(model(a, b), g_true))
    assert final < first / 10, f"loss {first:.4f} -> {final:.4f} (last step {last:.4f})"


def test_swapping_target_and_current_changes_the_output():
    model = _tiny().eval()
    a, b = _images(2, 64, 64)
    with torch.no_grad():
        ab, ba = model(a, b), model(b, a)
    # Output magnitudes are ~0.1; a swap-invariant network would agree to ~1e-7.
    assert float((ab.g - ba.g).abs().max()) > 1e-3
    assert float((ab.g_levels - ba.g_levels).abs().max()) > 1e-3


def test_loss_is_mean_level_mse_plus_sum_mse():
    torch.manual_seed(0)
    g_levels = torch.randn(2, 3, 6)
    weights = torch.softmax(torch.randn(2, 3), dim=1)
    g = (weights[..., None] * g_levels).sum(1)
    from learn.model import PoseUpdateOutput

    out = PoseUpdateOutput(g=g, g_levels=g_levels, weights=weights)
    t = torch.randn(2, 6)
    mse = nn.functional.mse_loss
    expected = sum(mse(g_levels[:, i], t) for i in range(3)) / 3 + mse(g, t)
    torch.testing.assert_close(PoseUpdateNet.loss(out, t), expected, atol=TOL, rtol=0)
    cw = torch.tensor([2.0, 2.0, 2.0, 0.0, 0.0, 0.0])
    expected_w = (((g_levels - t[:, None]) ** 2 * cw).mean() + ((g - t) ** 2 * cw).mean())
    torch.testing.assert_close(PoseUpdateNet.loss(out, t, cw), expected_w, atol=TOL, rtol=0)
    # Perfect predictions give zero loss.
    exact = PoseUpdateOutput(g=t, g_levels=t[:, None].expand(2, 3, 6), weights=weights)
    assert float(PoseUpdateNet.loss(exact, t)) == 0.0
    with pytest.raises(PoseInputError, match="target_g must have shape"):
        PoseUpdateNet.loss(out, torch.randn(2, 5))


# --------------------------------------------------------------------------------------------
# Bad inputs
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "target, current, fragment",
    [
        (torch.zeros(1, 1, 64, 64), torch.zeros(1, 1, 64, 48), "same shape"),
        (torch.zeros(1, 3, 64, 64), torch.zeros(1, 3, 64, 64), "target must have 1 channel"),
        (torch.zeros(1, 64, 64), torch.zeros(1, 64, 64), "target must be 4-D"),
        (torch.zeros(1, 1, 16, 64), torch.zeros(1, 1, 16, 64), "at least 32 x 32"),
        (torch.zeros(1, 1, 64, 64), torch.full((1, 1, 64, 64), float("nan")), "current has 4096 NaN"),
    ],
)
def test_bad_inputs_raise_naming_the_problem(target, current, fragment):
    model = _tiny()
    with pytest.raises(PoseInputError, match=fragment) as info:
        model(target, current)
    assert isinstance(info.value, ValueError)


def test_bad_builder_arguments():
    with pytest.raises(PoseInputError, match="backbone must be one of"):
        pose_update_net(backbone="resnet50")
    with pytest.raises(PoseInputError, match="weights_path is given"):
        pose_update_net(backbone="tiny", weights_path="x.pth")
    with pytest.raises(TypeError):
        pose_update_net("tiny")  # keyword-only
    assert pose_update_net(backbone=Backbone.TINY).backbone_kind is Backbone.TINY


# --------------------------------------------------------------------------------------------
# The full-size backbone
# --------------------------------------------------------------------------------------------


def test_densenet161_builds_and_runs():
    t0 = time.perf_counter()
    torch.manual_seed(0)
    model = pose_update_net(backbone="densenet161", weights=Weights.NONE).eval()
    n_backbone = sum(p.numel() for p in model.backbone.parameters())
    n_total = sum(p.numel() for p in model.parameters())
    # torchvision's densenet161 features: 26,472,000 parameters with a 3-channel conv0
    # (96 x 3 x 7 x 7 = 14,112 weights); ours takes 1 channel -> 2 x 96 x 49 = 9,408 fewer.
    expected_backbone = sum(p.numel() for p in DenseNet(48, (6, 12, 36, 24), 96).features.parameters()) - 9408
    assert n_backbone == expected_backbone, f"backbone {n_backbone:,} params, total {n_total:,}"
    a, b = _images(1, 64, 64)
    with torch.no_grad():
        out = model(a, b)
    assert bool(torch.isfinite(out.g).all()), f"non-finite output; {n_total:,} params"
    assert model.backbone.channels == (768, 2112, 2208), f"{n_total:,} params"
    assert time.perf_counter() - t0 < 10, f"{n_total:,} params, took {time.perf_counter() - t0:.1f} s"


def test_the_medium_backbone_is_the_small_one_wider_and_deeper():
    """``medium`` (growth 24, blocks 4-6-8-6, 48 init): DenseNet's feature counts follow from the
    config (init + blocks x growth, halved at each transition), so its taps' channels are known in
    closed form; about twice ``small``'s parameters, and the same output shapes."""
    import torch

    from learn.model import pose_update_net

    small, medium = pose_update_net(backbone="small"), pose_update_net(backbone="medium")
    n_small = sum(p.numel() for p in small.parameters())
    n_medium = sum(p.numel() for p in medium.parameters())
    assert 1.8 * n_small < n_medium < 2.2 * n_small, (n_small, n_medium)
    # features: 48 -> +4x24 = 144 -> 72 -> +6x24 = 216 -> 108 -> +8x24 = 300 -> 150 -> +6x24 = 294
    assert medium.backbone.channels[-1] == 294, medium.backbone.channels
    x = torch.randn(2, 1, 64, 64)
    out = medium(x, x)
    assert out.g.shape == (2, 6) and out.g_levels.shape == (2, 3, 6)
    assert bool(torch.isfinite(out.g).all())


def test_the_small_backbone_is_the_tiny_one_wider_and_deeper():
    """``small`` (growth 16, blocks 3-4-6-4): more parameters than ``tiny``, the same outputs' shapes
    and taps at the same strides, so checkpoints record it and heads fit it like the others."""
    import torch

    from learn.model import pose_update_net

    tiny, small = pose_update_net(backbone="tiny"), pose_update_net(backbone="small")
    assert sum(p.numel() for p in small.parameters()) > 1.4 * sum(p.numel() for p in tiny.parameters())
    x = torch.randn(2, 1, 64, 64)
    out = small(x, x)
    assert out.g.shape == (2, 6) and out.g_levels.shape == (2, 3, 6)
