"""Metal tools in an X-ray: a small segmenter learned from simulated frames with the simulator's truth.

Screws, K-wires, plates, retractors and cables in the field are not in the CT: a registration's
intensity similarity, tone fit and local similarity all suffer where they lie. The field detection
(:mod:`register.xray.field`) leaves out the tools a display clips at black or white, about half of
them; the rest look like bone to any threshold (not near the display's extreme: unsharp masking
and partial thickness keep them off it). This module learns them instead:

* :class:`ToolFrames`: realistic displayed frames of a campaign's subjects at
  :data:`SEGMENTER_SIDE` px with every randomized setting of the batched pairs
  (:class:`learn.batched.BatchedPairs`: spectrum, scatter, noise, blur, collimator, display
  chain of either polarity, log or linear, window, gamma, unsharp masking, bits) and tools drawn
  from several :class:`sim.randomize.ToolBank` seeds, each pixel labelled by the simulator's own
  chords: a tool pixel where the metal's line integral (``mu(60 keV) x chord`` of titanium,
  stainless steel and copper; not the carbon table or a cable's PVC sheath, smooth and faint) is
  at least :data:`TOOL_LINE_INTEGRAL` and the metal is visible: it moves the displayed value by
  at least :data:`VISIBLE` of the field's range (the frame rendered again without its metal);
* :class:`ToolSegmenter`: a U-Net of four scales (``(B, 2, H, W)`` in: the image normalised over
  its field and the field; ``(B, 1, H, W)`` logits out), built by :func:`tool_segmenter`;
* :func:`segmenter_input`: the one normalisation training and use share;
* :class:`ToolMask`: a trained segmenter from a model folder (:data:`DEFAULT_TOOL_MODEL`), its
  :meth:`ToolMask.detect` on a whole X-ray at any size.

>>> import torch
>>> net = tool_segmenter(width=8)
>>> net(torch.zeros(2, 2, 64, 48)).shape
torch.Size([2, 1, 64, 48])
"""

from __future__ import annotations

import math
from dataclasses import asdict as dataclasses_asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from learn.batched import BatchedPairs, tool_arrangements, tool_looks
from learn.online import MAX_BATCH
from learn.torch_file import read_plain_torch_file
from sim.core.atomic import atomic_path, read_toml, sha256_file, write_toml
from sim.core.errors import InputError
from sim.distractors import mu_line
from sim.physics.two_basis import TOOL_CHANNELS
from sim.campaign.config import load_campaign
from sim.randomize import DomainRandomization, ToolBank, draw_tensors

__all__ = ["ToolMaskError", "ToolFrames", "ToolSegmenter", "tool_segmenter", "segmenter_input", "ToolMask",
           "TOOL_LINE_INTEGRAL", "METAL_CHANNELS", "SEGMENTER_SIDE", "DEFAULT_TOOL_MODEL", "metal_weights",
           "ToolTrainSettings", "train_tool_mask", "tool_frame_sources", "TOOL_TRAIN_FILES", "TOOL_CARD",
           "TOOL_WEIGHTS",
           "export_tool_mask", "confident_pieces"]

#: A pixel is a tool's where the metal's line integral on its ray is at least this (1, ``mu x mm`` at
#: 60 keV, summed over the metals): about 0.15 mm of stainless steel or 0.4 mm of titanium.
TOOL_LINE_INTEGRAL = 0.05
#: The tool materials (:data:`sim.physics.two_basis.TOOL_CHANNELS` names) whose pixels are labelled.
METAL_CHANNELS = ("titanium", "stainless_steel", "copper")
#: A metal pixel is labelled where it moves the displayed value by at least this share of the field's
#: 1-99 % range (the same frame rendered without its metal, the same noise draws): metal a display
#: clips at its extreme, or hides in a window's saturated part, is invisible and harmless.
VISIBLE = 0.02
#: The longer side (px) of the images the segmenter sees: a 2 mm K-wire spans 2-3 px of a 30 cm detector.
SEGMENTER_SIDE = 256
#: The shipped segmenter's folder (``card.toml`` and ``weights.pt``).
DEFAULT_TOOL_MODEL = Path(__file__).resolve().parents[1] / "models" / "tool_mask"
#: Percentiles of the field's pixels mapped to 0 and 1 by :func:`segmenter_input`, and the clip.
_LOW_PCT, _HIGH_PCT, _CLIP = 1.0, 99.0, (-1.0, 2.0)


class ToolMaskError(InputError):
    """A tool segmenter's input, settings or files are unusable; the message names the problem."""


def metal_weights(names: tuple[str, ...] = TOOL_CHANNELS) -> np.ndarray:
    """``(len(names),)`` float32: the line integral (1) per g/cm^2 of each tool channel at 60 keV for
    the :data:`METAL_CHANNELS`, 0 for the others (``sum_c w_c x density_c`` is the metal's line integral)."""
    # mu_line(m, rho) is mu (1/mm) at density rho (g/cm^3): per g/cm^2 of density integral, 10 mm/cm / rho
    return np.array([10.0 * mu_line(m, 1.0) if m in METAL_CHANNELS else 0.0 for m in names], np.float32)


def segmenter_input(image: torch.Tensor, field: torch.Tensor) -> torch.Tensor:
    """The segmenter's input ``(B, 2, H, W)`` float32 of displayed images ``(B, H, W)`` (any real
    values, either polarity) and their fields ``(B, H, W)`` bool: channel 0 the image with its
    field's 1st / 99th percentiles at 0 / 1 (clipped to [-1, 2]), 0 outside the field; channel 1
    the field. An image whose field is constant (or empty) gets 0 everywhere."""
    if image.ndim != 3 or field.shape != image.shape or field.dtype != torch.bool:
        raise ToolMaskError(f"segmenter_input: images (B, H, W) and bool fields of their shape, got "
                            f"{tuple(image.shape)} and {field.dtype} {tuple(field.shape)}")
    x = image.to(torch.float32)
    out = torch.zeros((len(x), 2) + tuple(x.shape[1:]), dtype=torch.float32, device=x.device)
    for b in range(len(x)):
        values = x[b][field[b]]
        if values.numel() < 2:
            continue
        if values.numel() > 65536:  # the percentiles of a regular subsample (torch.quantile's size limit)
            values = values[:: math.ceil(values.numel() / 65536)]
        lo, hi = torch.quantile(values, torch.tensor([_LOW_PCT / 100, _HIGH_PCT / 100], device=x.device))
        if not bool(hi > lo):
            continue
        out[b, 0] = torch.where(field[b], ((x[b] - lo) / (hi - lo)).clamp(*_CLIP), 0.0)
    out[:, 1] = field.to(torch.float32)
    return out


class _Double(nn.Sequential):
    """Two 3 x 3 convolutions, each with BatchNorm and ReLU. (GroupNorm in its place learned
    nothing in 60 steps on one batch where BatchNorm found 97 % of the tool pixels.)"""

    def __init__(self, cin: int, cout: int):
        super().__init__(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class ToolSegmenter(nn.Module):
    """A U-Net: ``(B, 2, H, W)`` (:func:`segmenter_input`) -> tool logits ``(B, 1, H, W)``.

    Four scales (``H``, ``H / 2``, ``H / 4``, ``H / 8``; any ``H, W``: padded to multiples of 8 and
    cropped back), ``width``, ``2 width``, ``4 width``, ``8 width`` channels; skip connections by
    concatenation; bilinear upsampling. Build it with :func:`tool_segmenter`.
    """

    def __init__(self, width: int):
        super().__init__()
        w = int(width)
        self.width = w
        self.enc = nn.ModuleList([_Double(2, w), _Double(w, 2 * w), _Double(2 * w, 4 * w), _Double(4 * w, 8 * w)])
        self.dec = nn.ModuleList([_Double(8 * w + 4 * w, 4 * w), _Double(4 * w + 2 * w, 2 * w), _Double(2 * w + w, w)])
        self.head = nn.Conv2d(w, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        ph, pw = (-h) % 8, (-w) % 8
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph))
        skips = []
        for i, block in enumerate(self.enc):
            x = block(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        for block, skip in zip(self.dec, reversed(skips[:-1])):
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], 1))
        return self.head(x)[..., :h, :w]


def tool_segmenter(*, width: int = 16) -> ToolSegmenter:
    """A :class:`ToolSegmenter` of ``width`` (an integer in [4, 64]) channels at full scale."""
    if isinstance(width, bool) or not isinstance(width, int) or not 4 <= width <= 64:
        raise ToolMaskError(f"tool_segmenter: width must be an integer in [4, 64], got {width!r}")
    return ToolSegmenter(width)


class ToolFrames(BatchedPairs):
    """Realistic displayed frames with their tool labels (module doc), batched in torch.

    Args:
        cfg: a :class:`sim.campaign.config.CampaignConfig` whose scene size is the frames' size.
        split: the campaign split of the subjects.
        randomization: a :class:`sim.randomize.DomainRandomization` (its ``tools`` probability
            sets how many frames carry tools; ``ideal`` draws are shown as realistic ones).
        seed: the draws' seed (poses, settings, noise).
        banks: how many :class:`sim.randomize.ToolBank` s (16 arrangements each, seeds
            ``seed * 1000 + j``) the tools are picked from (integer >= 1, default 4).
        device, tables, subjects_per_batch: as :class:`learn.batched.BatchedPairs`.

    ``frames(k, n)`` -> ``image (n, H, W)`` float32 display values, ``field (n, H, W)`` bool and
    ``tools (n, H, W)`` bool, on ``device``.
    """

    def __init__(self, cfg, split: str, *, randomization, seed: int = 0, banks: int = 4, device="cpu", tables=None,
                 subjects_per_batch: int | None = None):
        if isinstance(banks, bool) or not isinstance(banks, int) or banks < 1:
            raise ToolMaskError(f"ToolFrames: banks must be an integer >= 1, got {banks!r}")
        self.banks = banks
        super().__init__(cfg, split, randomization=randomization, seed=seed, device=device, tables=tables,
                         subjects_per_batch=subjects_per_batch)
        self._weights = torch.from_numpy(metal_weights()).to(self.device)

    def _tool_bank(self) -> torch.Tensor:
        h, w = self.geometry.height, self.geometry.width
        looks = []
        for j in range(self.banks):
            bank_seed = self.seed * 1000 + j
            path = None if self.tables is None else self.tables / f"tool_bank_seed{bank_seed}_{h}x{w}.npz"
            if path is not None and path.exists():
                with np.load(path, allow_pickle=False) as z:
                    arrangements = np.asarray(z["density"], np.float32)
            else:
                arrangements = tool_arrangements(ToolBank(bank_seed, self.geometry, scene=self.cfg.scene.name),
                                                 TOOL_CHANNELS)
                if path is not None:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    with atomic_path(path) as tmp:
                        with open(tmp, "wb") as f:
                            np.savez_compressed(f, density=arrangements)
            looks.append(tool_looks(arrangements))
        return torch.cat(looks)

    def frames(self, k: int, n: int):
        if not 1 <= n <= MAX_BATCH:
            raise ToolMaskError(f"ToolFrames.frames: n must be in [1, {MAX_BATCH}], got {n}")
        self.prepare()
        subject, t_a, _ = self.draw(k, n)
        index = int(k) * MAX_BATCH + np.arange(n)
        draws = [self.randomization.draw(self.seed, int(i)) for i in index]
        p = draw_tensors(draws, device=self.device, dtype=torch.float32)
        tools = self.drawn_tools(p)
        basis = self._volumes.line_integrals(subject, t_a, (1, 2)) / 10.0  # g/cm^2, as _realistic's
        image, field = self._realistic(subject, t_a, index, p, draws, tools=tools, basis=basis)
        line = torch.einsum("bchw,c->bhw", tools.to(self._weights.dtype), self._weights)
        metal = (line >= TOOL_LINE_INTEGRAL) & field
        has = metal.flatten(1).any(1)
        if bool(has.any()):  # the same frames without their metal (same noise draws): what the metal changed
            rows = torch.nonzero(has).flatten()
            bare = tools[rows] * (self._weights == 0).to(tools.dtype)[None, :, None, None]
            q = {key: v[rows] for key, v in p.items()}
            r = rows.cpu().numpy()
            without, _ = self._realistic(subject[r], t_a[r], index[r], q, [draws[i] for i in r], tools=bare,
                                         basis=basis[rows])
            for j, b in enumerate(r):
                values = image[b][field[b]]
                lo, hi = torch.quantile(values.float()[:: max(1, values.numel() // 65536)],
                                        torch.tensor([0.01, 0.99], device=values.device))
                seen = (image[b] - without[j]).abs() >= VISIBLE * max(float(hi - lo), 1e-12)
                metal[b] &= seen
        return image.to(torch.float32), field, metal


def confident_pieces(p: np.ndarray, threshold: float, low: float, min_px: float) -> np.ndarray:
    """``(H, W)`` bool: the 8-connected pieces of ``p >= low`` (``p`` ``(H, W)`` probabilities) that
    hold at least ``min_px`` pixels at or above ``threshold`` (hysteresis)."""
    from scipy import ndimage

    hit = p >= low
    if not hit.any():
        return hit
    labels, n = ndimage.label(hit, structure=np.ones((3, 3), bool))
    core = np.bincount(labels.ravel(), weights=(p >= threshold).ravel().astype(float), minlength=n + 1)
    keep = core >= max(min_px, 1)
    keep[0] = False
    return keep[labels]


#: The card of a tool-mask folder (TOML) and its weights (a state dict, read as tensors only).
TOOL_CARD, TOOL_WEIGHTS = "card.toml", "weights.pt"


class ToolMask:
    """A trained :class:`ToolSegmenter` from a model folder, applied to whole X-rays.

    The folder holds :data:`TOOL_CARD` (``[model]``: ``file``, ``sha256``, ``width``, ``threshold``
    and ``low`` (probabilities of :meth:`detect`'s hysteresis), ``min_px`` (px at
    :data:`SEGMENTER_SIDE`), ``dilate_px`` (px of the image); the
    training and its measured numbers in ``[training]`` / ``[accuracy]``) and its weights, read as
    tensors only (never unpickled objects).

    Args:
        folder: the model folder (default :data:`DEFAULT_TOOL_MODEL`).

    >>> import numpy as np
    >>> mask = ToolMask()                               # doctest: +SKIP
    >>> tools = mask.detect(np.random.rand(512, 512), np.ones((512, 512), bool))  # doctest: +SKIP
    >>> tools.shape, tools.dtype                        # doctest: +SKIP
    ((512, 512), dtype('bool'))
    """

    _shared: dict[str, "ToolMask"] = {}

    def __init__(self, folder: str | Path = DEFAULT_TOOL_MODEL):
        folder = Path(folder)
        card_path = folder / TOOL_CARD
        if not card_path.is_file():
            raise ToolMaskError(f"tool mask {folder}: no {TOOL_CARD} (a tool-mask model is a folder with "
                                f"{TOOL_CARD} and {TOOL_WEIGHTS})")
        card = read_toml(card_path, ToolMaskError, "tool mask card")
        model = card.get("model")
        need = {"file": str, "sha256": str, "width": int, "threshold": float, "low": float, "min_px": int,
                "dilate_px": int}
        if not isinstance(model, dict):
            raise ToolMaskError(f"tool mask card {card_path}: no [model] table")
        for key, kind in need.items():
            v = model.get(key)
            if isinstance(v, bool) or not isinstance(v, (int, float) if kind is float else kind):
                raise ToolMaskError(f"tool mask card {card_path}: model.{key} must be a {kind.__name__}, got {v!r}")
        if not (0.0 < float(model["low"]) <= float(model["threshold"]) < 1.0) or model["min_px"] < 0 \
                or model["dilate_px"] < 0:
            raise ToolMaskError(f"tool mask card {card_path}: 0 < low <= threshold < 1, min_px and dilate_px >= 0")
        weights = folder / model["file"]
        if not weights.is_file():
            raise ToolMaskError(f"tool mask card {card_path}: model.file {model['file']!r} not found in {folder}")
        if sha256_file(weights) != model["sha256"]:
            raise ToolMaskError(f"tool mask card {card_path}: model.sha256 does not match {weights} (the weights "
                                f"changed after the card)")
        state = read_plain_torch_file(weights, "tool mask weights", error=ToolMaskError)
        self.net = tool_segmenter(width=int(model["width"]))
        try:
            self.net.load_state_dict(state)
        except (RuntimeError, TypeError, AttributeError) as e:
            raise ToolMaskError(f"tool mask weights {weights} do not fit a width-{model['width']} segmenter "
                                f"({str(e).splitlines()[0][:200]})") from None
        self.net.eval()
        self.folder = folder
        self.card = card
        self.threshold = float(model["threshold"])
        self.low = float(model["low"])
        self.min_px = int(model["min_px"])
        self.dilate_px = int(model["dilate_px"])

    @classmethod
    def shared(cls, folder: str | Path = DEFAULT_TOOL_MODEL) -> "ToolMask":
        """One loaded segmenter per folder for the process (read once)."""
        key = str(Path(folder).resolve())
        if key not in cls._shared:
            cls._shared[key] = cls(folder)
        return cls._shared[key]

    @torch.no_grad()
    def probabilities(self, image: np.ndarray, field: np.ndarray) -> np.ndarray:
        """``(H, W)`` float32 tool probabilities of ``image`` ``(H, W)`` (a displayed X-ray's stored
        values, either polarity) inside ``field`` ``(H, W)`` bool (0 outside): the image is resampled
        so that its longer side is :data:`SEGMENTER_SIDE` px (area mean; the field's median outside it
        first, so no outside value leaks in), the probabilities bilinearly back."""
        image = np.asarray(image)
        field = np.asarray(field)
        if image.ndim != 2 or field.shape != image.shape or field.dtype != bool:
            raise ToolMaskError(f"tool mask: an image (H, W) and a bool field of its shape, got {image.shape} and "
                                f"{field.dtype} {field.shape}")
        if not np.isfinite(image).all():
            raise ToolMaskError("tool mask: the image holds NaN or inf")
        h, w = image.shape
        if not field.any():
            return np.zeros((h, w), np.float32)
        fill = float(np.median(image[field]))
        x = torch.from_numpy(np.where(field, image, fill).astype(np.float32))[None, None]
        f = torch.from_numpy(field.astype(np.float32))[None, None]
        scale = SEGMENTER_SIDE / max(h, w)
        size = (max(8, round(h * scale)), max(8, round(w * scale)))
        mode = "area" if scale < 1 else "bilinear"
        kw = {} if mode == "area" else {"align_corners": False}
        xs = F.interpolate(x, size=size, mode=mode, **kw)[:, 0]
        fs = F.interpolate(f, size=size, mode=mode, **kw)[:, 0] > 0.5
        logits = self.net(segmenter_input(xs, fs))
        p = torch.sigmoid(F.interpolate(logits, size=(h, w), mode="bilinear", align_corners=False))[0, 0]
        return np.where(field, p.numpy(), 0.0).astype(np.float32)

    def detect(self, image: np.ndarray, field: np.ndarray) -> np.ndarray:
        """``(H, W)`` bool: the tool pixels of ``image`` inside ``field``: :meth:`probabilities` at or
        above the card's ``low`` in 8-connected pieces holding at least ``min_px`` px (at the
        segmenter's size) at or above its ``threshold`` (hysteresis: a confident core, grown over
        its less certain rim), grown by ``dilate_px`` px (the blur of a tool's edge); never outside
        ``field``."""
        from scipy import ndimage

        p = self.probabilities(image, field)
        hit = confident_pieces(p, self.threshold, self.low, self.min_px * (max(p.shape) / SEGMENTER_SIDE) ** 2)
        if self.dilate_px and hit.any():
            hit = ndimage.binary_dilation(hit, iterations=self.dilate_px)
        return hit & np.asarray(field, bool)


# -- training ----------------------------------------------------------------------------------------

#: The shipped pose network whose card's randomization the frames use (its ``tools`` and ``ideal``
#: probabilities replaced: :attr:`ToolTrainSettings.tools_probability`, every frame realistic).
RANDOMIZATION_FROM = Path(__file__).resolve().parents[1] / "models" / "pelvis_xray"
#: The subjects: the base network's (the training pelvis, its virtual patients and seeded phantoms;
#: never the validation pelvis), shown at :data:`SEGMENTER_SIDE` px.
TOOL_CAMPAIGN = Path(__file__).resolve().parents[1] / "campaigns" / "pelvis_base.toml"
#: What :func:`train_tool_mask` writes into its output folder.
TOOL_TRAIN_FILES = ("checkpoint.pt", "log.csv")


@dataclass(frozen=True)
class ToolTrainSettings:
    """Settings of :func:`train_tool_mask` (unit, default).

    Attributes:
        minutes: min, 30. Training time; the learning rate follows a cosine over it (resumable).
        width: channels, 12. :func:`tool_segmenter`'s width.
        crop: px, 128. Side of the square crops trained on (two per frame, each zoomed by a factor
            in [0.75, 1.33] drawn per crop: tools of other magnifications and pixel sizes).
        frames: 12. Frames rendered per step (a batch of ``2 x frames`` crops).
        lr: 3e-3. AdamW's peak learning rate (a 2 % linear warm-up, then the cosine to 0).
        tools_probability: 0.7. Share of the frames with tools.
        banks: 8. Tool banks (16 arrangements each, in 8 looks) the tools come from.
        pos_weight: 10.0. Weight of the tool pixels in the binary cross-entropy (a soft Dice term
            beside it).
        val_frames: 96. Whole frames of the campaign's validation subjects, judged every
            ``val_every_s``.
        val_every_s: s, 120.
        seed: 0.
        low_res: 0.0. Share of the frames shown at a lower resolution (reduced by a factor in
            [1.5, 4], log-uniform, area mean, then bilinearly back): X-rays of 64-170 px across
            the detector, as the segmenter sees a small image resampled to its side; the labels
            stay at full resolution.
        max_transmission: 0.1. The collimator's blades pass up to this share of the signal (the
            pose network's randomization's 0.1).

    (A run of 30 more minutes from the shipped weights with ``low_res = 0.5`` and
    ``max_transmission = 0.3`` left out more of the study frames without tools, not less:
    resume/tool_mask/log_run2_lowres.csv, docs/training.md.)
    """

    minutes: float = 30.0
    width: int = 12
    crop: int = 128
    frames: int = 12
    lr: float = 3e-3
    tools_probability: float = 0.7
    banks: int = 8
    pos_weight: float = 10.0
    val_frames: int = 96
    val_every_s: float = 120.0
    seed: int = 0
    low_res: float = 0.0
    max_transmission: float = 0.1

    def __post_init__(self):
        checks = {"minutes": (0.05, 10000.0), "crop": (32, SEGMENTER_SIDE), "frames": (1, 64), "lr": (1e-6, 1.0),
                  "tools_probability": (0.0, 1.0), "banks": (1, 64), "pos_weight": (0.1, 100.0),
                  "val_frames": (1, 4096), "val_every_s": (1.0, 1e5), "seed": (0, 2 ** 31), "low_res": (0.0, 1.0),
                  "max_transmission": (0.005, 1.0)}
        for name, (lo, hi) in checks.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (lo <= v <= hi):
                raise ToolMaskError(f"ToolTrainSettings.{name}: must be a number in [{lo}, {hi}], got {v!r}")
        tool_segmenter(width=self.width)


def tool_frame_sources(settings: ToolTrainSettings, device, tables: Path, campaign: Path = TOOL_CAMPAIGN):
    """The training's and the validation's :class:`ToolFrames` (``(train, val)``): ``campaign``'s
    ``train`` subjects under ``settings.seed`` (4 subjects a batch), its ``val`` subjects under
    ``seed + 1``, at :data:`SEGMENTER_SIDE` px, with the randomization of :data:`RANDOMIZATION_FROM`'s
    card (tools on ``settings.tools_probability`` of the frames, every frame realistic, blades passing
    up to ``settings.max_transmission``); spectral
    table and tool banks cached in ``tables``."""
    import dataclasses
    import tomllib

    with open(RANDOMIZATION_FROM / "model.toml", "rb") as f:
        table = dict(tomllib.load(f)["model"]["physics"]["randomize"])
    table.update(tools=float(settings.tools_probability), ideal=0.0,
                 field_transmission=[0.005, float(settings.max_transmission)])
    randomization = DomainRandomization.from_table(table)
    cfg = load_campaign(campaign)
    cfg = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, size=(SEGMENTER_SIDE, SEGMENTER_SIDE)))
    kw = dict(randomization=randomization, banks=settings.banks, device=device, tables=tables)
    subjects = sum(1 for s in cfg.subjects() if s.split == "train")
    train = ToolFrames(cfg, "train", seed=settings.seed, subjects_per_batch=min(4, max(subjects, 1)), **kw)
    val = ToolFrames(cfg, "val", seed=settings.seed + 1, **kw)
    return train, val


def _crops(x: torch.Tensor, y: torch.Tensor, side: int, gen: torch.Generator):
    """Two random crops per frame of ``x`` ``(B, 2, H, W)`` and ``y`` ``(B, 1, H, W)``, each of a side
    ``side x zoom`` (zoom in [0.75, 1.33], log-uniform) resampled to ``side``: ``(2 B, ...)``."""
    xs, ys = [], []
    H, W = x.shape[-2:]
    for b in range(len(x)):
        for _ in range(2):
            zoom = math.exp(float(torch.empty(1).uniform_(math.log(0.75), math.log(1.333), generator=gen)))
            s = min(int(round(side * zoom)), H, W)
            r = int(torch.randint(0, H - s + 1, (1,), generator=gen))
            c = int(torch.randint(0, W - s + 1, (1,), generator=gen))
            xc, yc = x[b:b + 1, :, r:r + s, c:c + s], y[b:b + 1, :, r:r + s, c:c + s].float()
            if s != side:
                xc = F.interpolate(xc, size=(side, side), mode="bilinear", align_corners=False)
                yc = F.interpolate(yc, size=(side, side), mode="bilinear", align_corners=False)
            xs.append(xc)
            ys.append(yc)
    return torch.cat(xs), torch.cat(ys)


def _low_res(image: torch.Tensor, field: torch.Tensor, share: float, gen: torch.Generator):
    """``share`` of the frames ``(B, H, W)`` (and their fields) reduced by a factor in [1.5, 4]
    (log-uniform; area mean, the field by the majority) and bilinearly back to ``(H, W)``."""
    image, field = image.clone(), field.clone()
    h, w = image.shape[-2:]
    for b in range(len(image)):
        if float(torch.rand(1, generator=gen)) >= share:
            continue
        f = math.exp(float(torch.empty(1).uniform_(math.log(1.5), math.log(4.0), generator=gen)))
        size = (max(8, round(h / f)), max(8, round(w / f)))
        small = F.interpolate(image[b][None, None], size=size, mode="area")
        image[b] = F.interpolate(small, size=(h, w), mode="bilinear", align_corners=False)[0, 0]
        fs = F.interpolate(field[b][None, None].float(), size=size, mode="area")
        field[b] = F.interpolate(fs, size=(h, w), mode="bilinear", align_corners=False)[0, 0] > 0.5
    return image, field


def _loss(logits: torch.Tensor, target: torch.Tensor, pos_weight: float) -> torch.Tensor:
    bce = F.binary_cross_entropy_with_logits(logits, target, pos_weight=torch.tensor(pos_weight, device=logits.device))
    p = torch.sigmoid(logits)
    inter = (p * target).sum()
    dice = 1 - (2 * inter + 1) / (p.sum() + target.sum() + 1)
    return bce + 0.5 * dice


@torch.no_grad()
def _validate(net, val_batches, pos_weight: float) -> dict:
    net.eval()
    tp = fp = fn = 0
    loss, clean, flagged = 0.0, 0, 0
    for x, y in val_batches:
        logits = net(x)
        loss += float(_loss(logits, y.float(), pos_weight)) * len(x)
        hit = logits > 0
        tp += int((hit & y).sum())
        fp += int((hit & ~y).sum())
        fn += int((~hit & y).sum())
        free = ~y.flatten(1).any(1)
        clean += int(free.sum())
        flagged += int((hit.flatten(1).any(1) & free).sum())
    net.train()
    n = sum(len(x) for x, _ in val_batches)
    return {"val_loss": loss / n, "recall": tp / max(tp + fn, 1), "precision": tp / max(tp + fp, 1),
            "tool_free": clean, "tool_free_flagged": flagged}


def train_tool_mask(out: str | Path, settings: ToolTrainSettings = ToolTrainSettings(), *, resume: bool = False,
                    device: str = "cpu", campaign: str | Path = TOOL_CAMPAIGN, init_from: str | Path | None = None,
                    log=print) -> Path:
    """Train a :class:`ToolSegmenter` on :class:`ToolFrames` for ``settings.minutes`` and write
    ``out/checkpoint.pt`` (weights, optimiser, time spent, the log; every validation and at the end,
    atomically) and ``out/log.csv`` (minutes, frames, train loss, validation loss, recall, precision,
    tool-free validation frames with any pixel flagged). ``resume`` continues a run from its checkpoint
    (its settings must match). Ctrl-C / SIGTERM stop with a checkpoint. ``campaign``: the subjects
    (a campaign file with ``train`` and ``val`` splits; its scene size is replaced by
    :data:`SEGMENTER_SIDE`). ``init_from``: a start from another run's checkpoint's weights (a new
    optimiser and schedule; not with ``resume``). Returns the checkpoint's path."""
    import csv
    import signal
    import time

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    torch.manual_seed(settings.seed)
    net = tool_segmenter(width=settings.width).to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=settings.lr, weight_decay=1e-4)
    elapsed, frames_seen, step, rows = 0.0, 0, 0, []
    if resume:
        state = read_plain_torch_file(ckpt_path, "tool-mask checkpoint", error=ToolMaskError)
        saved = {**dataclasses_asdict(ToolTrainSettings()), **state.get("settings", {})}  # older runs lack new keys
        if saved != dataclasses_asdict(settings):
            raise ToolMaskError(f"--resume: {ckpt_path} was trained with {state.get('settings')}, not "
                                f"{dataclasses_asdict(settings)}")
        net.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        elapsed, frames_seen, step, rows = state["elapsed_s"], state["frames"], state["step"], list(state["log"])
    elif ckpt_path.exists():
        raise ToolMaskError(f"{ckpt_path} exists: resume it (--resume) or choose another folder")
    elif init_from is not None:
        start = read_plain_torch_file(init_from, "tool-mask checkpoint", error=ToolMaskError)
        try:
            net.load_state_dict(start["model"])
        except (RuntimeError, KeyError, TypeError) as e:
            raise ToolMaskError(f"init_from {init_from}: not the weights of a width-{settings.width} segmenter "
                                f"({str(e).splitlines()[0][:200]})") from None
    train, val = tool_frame_sources(settings, device, out / "tables", Path(campaign))
    log(f"tool mask: preparing {len(train.subjects)} training and {len(val.subjects)} validation subjects at "
        f"{SEGMENTER_SIDE} px")
    val_batches = []
    for k in range(math.ceil(settings.val_frames / 32)):
        n = min(32, settings.val_frames - 32 * k)
        image, field, tools = val.frames(k, n)
        val_batches.append((segmenter_input(image, field), tools[:, None]))
    train.prepare()
    gen = torch.Generator().manual_seed(settings.seed * 7919 + step)
    total = settings.minutes * 60.0
    stop = {"now": False}

    def _stop(signum, frame):
        stop["now"] = True

    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}

    def _save():
        state = {"model": net.state_dict(), "optimizer": opt.state_dict(), "elapsed_s": elapsed, "frames": frames_seen,
                 "step": step, "log": rows, "settings": dataclasses_asdict(settings),
                 "init_from": None if init_from is None else str(init_from)}
        with atomic_path(ckpt_path) as tmp:
            torch.save(state, tmp)
        with atomic_path(out / "log.csv") as tmp:
            with open(tmp, "w", newline="") as f:
                w = csv.writer(f)
                w.writerow(["minutes", "frames", "train_loss", "val_loss", "recall", "precision", "tool_free",
                            "tool_free_flagged"])
                w.writerows(rows)

    try:
        last_val, running, t_mark = elapsed, [], time.perf_counter()
        net.train()
        while elapsed < total and not stop["now"]:
            frac = elapsed / total
            lr = settings.lr * min(1.0, frac / 0.02 + 0.05) * 0.5 * (1 + math.cos(math.pi * frac))
            for g in opt.param_groups:
                g["lr"] = lr
            image, field, tools = train.frames(step, settings.frames)
            image, shown = _low_res(image, field, settings.low_res, gen)
            x, y = _crops(segmenter_input(image, shown), (tools & shown)[:, None], settings.crop, gen)
            loss = _loss(net(x), y, settings.pos_weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            running.append(float(loss.detach()))
            step += 1
            frames_seen += settings.frames
            now = time.perf_counter()
            elapsed += now - t_mark
            t_mark = now
            if elapsed - last_val >= settings.val_every_s or elapsed >= total or stop["now"]:
                v = _validate(net, val_batches, settings.pos_weight)
                rows.append([round(elapsed / 60, 2), frames_seen, round(float(np.mean(running)), 4),
                             round(v["val_loss"], 4), round(v["recall"], 4), round(v["precision"], 4), v["tool_free"],
                             v["tool_free_flagged"]])
                running, last_val = [], elapsed
                _save()
                rate = frames_seen / max(elapsed, 1e-9)
                log(f"tool mask: {elapsed / 60:.1f}/{settings.minutes:g} min, {frames_seen} frames "
                    f"({rate:.1f}/s), ETA {max(total - elapsed, 0) / 60:.1f} min: loss {rows[-1][2]:.3f}, "
                    f"validation {v['val_loss']:.3f}, recall {v['recall']:.3f}, precision {v['precision']:.3f}, "
                    f"{v['tool_free_flagged']}/{v['tool_free']} tool-free frames flagged")
                t_mark = time.perf_counter()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    return ckpt_path


def export_tool_mask(checkpoint: str | Path, folder: str | Path, *, threshold: float = 0.9, low: float = 0.5,
                     min_px: int = 4, dilate_px: int = 1, accuracy: dict | None = None) -> Path:
    """Write a :class:`ToolMask` folder from a :func:`train_tool_mask` checkpoint: :data:`TOOL_WEIGHTS`
    (the state dict alone) and :data:`TOOL_CARD` (``[model]``: the file, its sha256, width and the
    detection's ``threshold`` and ``low`` (probabilities), ``min_px`` (px at :data:`SEGMENTER_SIDE`) and
    ``dilate_px`` (px of the image); ``[training]``: the settings, frames, minutes and the learning
    curve; ``[accuracy]``: ``accuracy`` where given). Returns ``folder``."""
    state = read_plain_torch_file(checkpoint, "tool-mask checkpoint", error=ToolMaskError)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / TOOL_WEIGHTS) as tmp:
        torch.save(state["model"], tmp)
    settings = state["settings"]
    curve = [list(r) for r in state["log"]]
    card = {"model": {"name": "tool_mask", "summary": "U-Net segmenter of metal tools (screws, K-wires, plates, "
                      "retractors, cables) in displayed X-rays; registration leaves its pixels out",
                      "file": TOOL_WEIGHTS, "sha256": sha256_file(folder / TOOL_WEIGHTS),
                      "width": int(settings["width"]),
                      "side_px": SEGMENTER_SIDE, "threshold": float(threshold), "low": float(low), "min_px": int(min_px),
                      "dilate_px": int(dilate_px)},
            "training": {"command": "ctxreg train-tools --out DIR --minutes M", "settings": settings,
                         "frames": int(state["frames"]), "steps": int(state["step"]),
                         "init_from": state.get("init_from") or "random weights",
                         "minutes": round(float(state["elapsed_s"]) / 60, 2),
                         "label": f"metal (titanium, steel, copper) line integral >= {TOOL_LINE_INTEGRAL} at 60 keV "
                                  f"and "
                                  f"visible (moves the display by >= {VISIBLE:.0%} of the field's 1-99 % range)",
                         "subjects": str(TOOL_CAMPAIGN.relative_to(TOOL_CAMPAIGN.parents[1])) + " (train split; "
                                     "never the validation pelvis)",
                         "randomization": f"{RANDOMIZATION_FROM.name}'s card, tools on "
                                          f"{settings['tools_probability']:.0%} of the frames",
                         "curve_columns": ["minutes", "frames", "train_loss", "val_loss", "recall", "precision",
                                           "tool_free", "tool_free_flagged"],
                         "curve": curve}}
    if state.get("init_from"):  # the run it started from: its curve too (the whole history)
        try:
            before = read_plain_torch_file(state["init_from"], "tool-mask checkpoint", error=ToolMaskError)
            card["training"]["before_curve"] = [list(r) for r in before["log"]]
            card["training"]["before_minutes"] = round(float(before["elapsed_s"]) / 60, 2)
            card["training"]["before_frames"] = int(before["frames"])
        except ToolMaskError:
            card["training"]["before_curve"] = []
    if accuracy:
        card["accuracy"] = accuracy
    write_toml(folder / TOOL_CARD, card)
    return folder
