"""The convolutional part of a DenseNet (Huang et al. 2017), in torchvision's module layout.

:func:`densenet_features` builds the ``features`` module of torchvision's
``torchvision.models.DenseNet``: the same submodules under the same names
(``conv0``, ``norm0``, ``relu0``, ``pool0``, ``denseblock1``, ``transition1``, ...,
``denseblock4``, ``norm5``; inside a block ``denselayer1.norm1`` ... ``denselayer1.conv2``), so
a torchvision state dict (an ImageNet checkpoint's ``features.*``) loads into it unchanged and
gives the same outputs (``tests/learn/test_densenet.py`` checks both against torchvision).

Why not torchvision's own class: importing ``torchvision.models`` imports its detection ops and
with them ``torch._dynamo``, about 3 s of every ``ctxreg register`` call on a 2-core CPU, for a
module of a few dozen lines (issue 31, docs/benchmarks.md "Start-up"). torchvision stays the
reference in the tests.

Example::

    >>> import torch
    >>> f = densenet_features(growth_rate=8, block_config=(2, 2, 2, 2), num_init_features=16, in_channels=1)
    >>> f(torch.zeros(2, 1, 64, 64)).shape  # stride 32; each block adds 2 x 8 channels, each transition halves
    torch.Size([2, 32, 2, 2])
"""

from __future__ import annotations

import math
from collections import OrderedDict

import torch
from torch import Tensor, nn

__all__ = ["NORMS", "densenet_features", "group_norm"]


class _DenseLayer(nn.Module):
    """BN-ReLU-1x1 conv (``bn_size * growth_rate`` channels), BN-ReLU-3x3 conv (``growth_rate``) over
    the concatenation of every earlier map of the block: ``list of (B, C_i, H, W) -> (B, growth_rate, H, W)``."""

    def __init__(self, in_channels: int, growth_rate: int, bn_size: int, norm) -> None:
        super().__init__()
        width = bn_size * growth_rate
        self.norm1 = norm(in_channels)
        self.relu1 = nn.ReLU(inplace=True)
        self.conv1 = nn.Conv2d(in_channels, width, kernel_size=1, stride=1, bias=False)
        self.norm2 = norm(width)
        self.relu2 = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(width, growth_rate, kernel_size=3, stride=1, padding=1, bias=False)

    def forward(self, maps: list[Tensor]) -> Tensor:
        x = self.conv1(self.relu1(self.norm1(torch.cat(maps, 1))))
        return self.conv2(self.relu2(self.norm2(x)))


class _DenseBlock(nn.ModuleDict):
    """``layers`` dense layers, each fed every map before it: ``(B, C, H, W) -> (B, C + layers * growth_rate, H, W)``."""

    def __init__(self, layers: int, in_channels: int, growth_rate: int, bn_size: int, norm) -> None:
        super().__init__()
        for i in range(layers):
            self.add_module(f"denselayer{i + 1}", _DenseLayer(in_channels + i * growth_rate, growth_rate, bn_size, norm))

    def forward(self, x: Tensor) -> Tensor:
        maps = [x]
        for layer in self.values():
            maps.append(layer(maps))
        return torch.cat(maps, 1)


class _Transition(nn.Sequential):
    """BN-ReLU-1x1 conv to ``out_channels``, 2 x 2 average pooling: ``(B, C, H, W) -> (B, out, H / 2, W / 2)``."""

    def __init__(self, in_channels: int, out_channels: int, norm) -> None:
        super().__init__(OrderedDict([
            ("norm", norm(in_channels)),
            ("relu", nn.ReLU(inplace=True)),
            ("conv", nn.Conv2d(in_channels, out_channels, kernel_size=1, stride=1, bias=False)),
            ("pool", nn.AvgPool2d(kernel_size=2, stride=2)),
        ]))


#: The normalisations a DenseNet may use: torchvision's batch norm, or group norm.
NORMS = ("batch", "group")


def group_norm(channels: int) -> nn.GroupNorm:
    """Group norm over ``gcd(8, channels)`` groups (8 where the channels allow): statistics of each
    image alone, so a batch of one, or a batch of images of one kind, normalises as any other."""
    return nn.GroupNorm(math.gcd(8, channels), channels)


def densenet_features(*, growth_rate: int, block_config: tuple[int, ...], num_init_features: int,
                      bn_size: int = 4, in_channels: int = 3, norm: str = "batch") -> nn.Sequential:
    """The DenseNet's ``features``: ``(B, in_channels, H, W) -> (B, C, H / 32, W / 32)``.

    Args (torchvision's names): ``growth_rate`` channels each dense layer adds; ``block_config``
    dense layers per block; ``num_init_features`` channels of the first 7 x 7 convolution;
    ``bn_size`` the bottleneck's width in growth rates (4); ``in_channels`` of the input (3: RGB);
    ``norm`` ``"batch"`` (torchvision's) or ``"group"`` (:func:`group_norm` in every place of a
    batch norm, under the same names: ``norm0``, ``norm1``, ..., ``norm5``).
    Initialised as torchvision initialises its DenseNet (convolutions Kaiming-normal, batch norms
    weight 1 and bias 0), drawing the same random numbers in the same order: after the same
    ``torch.manual_seed`` the weights are torchvision's to the bit (tested), so seeded runs made
    with torchvision's class start from the same network.
    """
    if norm not in NORMS:
        raise ValueError(f"norm must be one of {NORMS}, got {norm!r}")
    layer_norm = nn.BatchNorm2d if norm == "batch" else group_norm
    features = nn.Sequential(OrderedDict([
        ("conv0", nn.Conv2d(in_channels, num_init_features, kernel_size=7, stride=2, padding=3, bias=False)),
        ("norm0", layer_norm(num_init_features)),
        ("relu0", nn.ReLU(inplace=True)),
        ("pool0", nn.MaxPool2d(kernel_size=3, stride=2, padding=1)),
    ]))
    channels = num_init_features
    for i, layers in enumerate(block_config):
        features.add_module(f"denseblock{i + 1}", _DenseBlock(layers, channels, growth_rate, bn_size, layer_norm))
        channels += layers * growth_rate
        if i < len(block_config) - 1:
            features.add_module(f"transition{i + 1}", _Transition(channels, channels // 2, layer_norm))
            channels //= 2
    features.add_module("norm5", layer_norm(channels))
    nn.Linear(channels, 1000)  # torchvision builds its ImageNet classifier here: the same draws, then dropped
    for m in features.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight)
        elif isinstance(m, (nn.BatchNorm2d, nn.GroupNorm)):
            nn.init.constant_(m.weight, 1.0)
            nn.init.constant_(m.bias, 0.0)
    return features
