"""Composable, recorded preprocessing of network input images (PyTorch).

Every step is a :class:`TensorStep`: the project's one step protocol (:class:`sim.prepare.Step`,
which registration's steps follow too) as a small :class:`torch.nn.Module` taking and returning a float tensor
``(B, 1, H, W)`` (``B`` images, one channel, ``H`` rows, ``W`` columns, indexed ``[row, col]``).
``(B, C, H, W)`` with ``C > 1`` is also accepted: every step then works on each image and channel
independently (``Sobel(mode="xy")`` returns ``2 C`` channels). Each step has ``to_dict()``, a
JSON-serialisable record ``{"name": ..., parameters...}``; :class:`Compose` chains steps and
``record()`` lists the records; :func:`build` makes a :class:`Compose` from names or records.

Input kinds: ``"intensity"`` images (detected X-ray intensities, ``I = I0 exp(-L)``, > 0) and
``"line_integral"`` images (DRRs as rendered by :mod:`sim`: ``L = sum mu ds``, unit-free,
>= 0). :class:`LogCorrect` turns intensities into line integrals (identity for line integrals);
all other steps accept any real-valued image.

Errors: :class:`LearnPreprocessError` (a ``ValueError``) naming the input and the problem.
"""

from __future__ import annotations

import hashlib
import math
import numbers
from typing import Any, ClassVar, Iterable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from sim.core.errors import InputError
from sim import prepare
from sim.prepare import Step  # the one step protocol, which TensorStep is

__all__ = [
    "LearnPreprocessError",
    "TensorStep",
    "LogCorrect",
    "Normalize",
    "Median",
    "Sobel",
    "Gaussian",
    "LocalContrast",
    "RandomConvolution",
    "HistogramMatch",
    "Compose",
    "STEPS",
    "build",
]

#: Guard against division by zero (constant images, zero intensities).
_EPS = 1e-12


class LearnPreprocessError(InputError):
    """An input to :mod:`learn.preprocess` cannot be used; the message names it and the problem."""


def _check_images(x: Any, name: str = "x") -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise LearnPreprocessError(
            f"{name}: expected a torch tensor of shape (B, 1, H, W), got {type(x).__name__}"
        )
    if x.ndim != 4:
        raise LearnPreprocessError(
            f"{name}: expected shape (B, 1, H, W) (batch, channel, rows, columns), "
            f"got {tuple(x.shape)}"
        )
    if not torch.is_floating_point(x):
        raise LearnPreprocessError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    if min(x.shape) < 1:
        raise LearnPreprocessError(f"{name}: empty tensor of shape {tuple(x.shape)}")
    return x


def _flat(x: torch.Tensor) -> torch.Tensor:
    """``(B, C, H, W) -> (B * C, 1, H, W)``: every image and channel on its own."""
    b, c, h, w = x.shape
    return x.reshape(b * c, 1, h, w)


def _positive(value: Any, name: str, *, allow_zero: bool = False) -> float:
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise LearnPreprocessError(f"{name}: expected a finite number {bound}, got {value!r}")
    return float(value)


class TensorStep(Step, torch.nn.Module):
    """Base of training's preprocessing steps: a :class:`sim.prepare.Step` that is a torch module.

    ``forward(x)`` (the module's call, a transform of ``(B, C, H, W)`` batches) checks the input and
    applies the step; :meth:`apply` is the step protocol's form of it: the mask passes through
    unchanged (these steps work on every pixel) and nothing is measured."""

    name: ClassVar[str] = "step"

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D401
        return self._apply(_check_images(x))

    def apply(self, image: torch.Tensor, mask):
        """``(image (B, C, H, W), mask) -> (forward(image), mask, {})``: :class:`sim.prepare.Step`."""
        return self.forward(image), mask, {}

    def _apply(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable record ``{"name": ..., **parameters}``; ``build([d])`` rebuilds it."""
        return {"name": self.name, **self.params()}

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.params().items())


class LogCorrect(TensorStep):
    """``-log(I / I0)``: intensity images -> line integrals (unit-free), per image and channel.

    ``input_kind="intensity"`` (default) expects ``I > 0``; ``I0`` is the image's
    ``percentile``-th percentile (an estimate of the unattenuated beam), values are clamped to
    ``>= 1e-12 I0`` before the log: :func:`sim.prepare.i0_percentile` and
    :func:`sim.prepare.log_correct`, registration's arithmetic. ``input_kind="line_integral"`` (DRRs rendered by :mod:`sim`,
    already ``-log`` of a transmission) makes the step the identity.
    """

    name = "log_correct"

    def __init__(self, percentile: float = 99.5, input_kind: str = "intensity") -> None:
        super().__init__()
        p = _positive(percentile, "percentile")
        if p > 100:
            raise LearnPreprocessError(f"percentile: expected a value in (0, 100], got {percentile!r}")
        if input_kind not in ("intensity", "line_integral"):
            raise LearnPreprocessError(
                f"input_kind: expected 'intensity' or 'line_integral', got {input_kind!r}"
            )
        self.percentile = p
        self.input_kind = input_kind

    def params(self) -> dict[str, Any]:
        return {"percentile": self.percentile, "input_kind": self.input_kind}

    def _apply(self, x: torch.Tensor) -> torch.Tensor:
        if self.input_kind == "line_integral":
            return x
        b, c, h, w = x.shape
        images = x.reshape(b * c, h, w)
        i0 = prepare.i0_percentile(images, None, self.percentile)
        if bool((i0 <= 0).any()):
            raise LearnPreprocessError(
                "x: LogCorrect(input_kind='intensity') needs positive intensities; an image has "
                "its high percentile <= 0 (pass input_kind='line_integral' for DRRs)"
            )
        return prepare.log_correct(images, i0, _EPS).reshape(b, c, h, w)


class Normalize(TensorStep):
    """Per-image (and channel) intensity normalisation.

    ``mode="minmax"`` (the original method): ``[min, max] -> [-1, 1]`` linearly (a constant image
    maps to 0). ``mode="zscore"``: zero mean, unit (population) standard deviation (constant -> 0).
    """

    name = "normalize"

    def __init__(self, mode: str = "minmax") -> None:
        super().__init__()
        if mode not in ("minmax", "zscore"):
            raise LearnPreprocessError(f"mode: expected 'minmax' or 'zscore', got {mode!r}")
        self.mode = mode

    def params(self) -> dict[str, Any]:
        return {"mode": self.mode}

    def _apply(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.flatten(2)
        if self.mode == "minmax":
            lo = flat.amin(-1)[..., None, None]
            hi = flat.amax(-1)[..., None, None]
            span = hi - lo
            safe = torch.where(span > 0, span, torch.ones_like(span))
            return torch.where(span > 0, 2.0 * (x - lo) / safe - 1.0, torch.zeros_like(x))
        mean = flat.mean(-1)[..., None, None]
        std = flat.std(-1, unbiased=False)[..., None, None]
        safe = torch.where(std > 0, std, torch.ones_like(std))
        return torch.where(std > 0, (x - mean) / safe, torch.zeros_like(x))


class Median(TensorStep):
    """Median filter over a ``size x size`` pixel window (odd ``size``), replicate padding.

    :func:`sim.prepare.median_filter` (``unfold``: memory ``size^2`` times the image), registration's
    median.
    """

    name = "median"

    def __init__(self, size: int = 3) -> None:
        super().__init__()
        if isinstance(size, bool) or not isinstance(size, numbers.Integral) or size < 1 or size % 2 == 0:
            raise LearnPreprocessError(f"size: expected an odd integer >= 1 (pixels), got {size!r}")
        self.size = int(size)

    def params(self) -> dict[str, Any]:
        return {"size": self.size}

    def _apply(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        return prepare.median_filter(x.reshape(b * c, h, w), self.size).reshape(b, c, h, w)


class Sobel(TensorStep):
    """Sobel image gradient, replicate padding, normalised to intensity per pixel.

    The kernels are divided by 8, so a ramp ``I = a col + b row`` gives exactly ``d/dcol = a``
    and ``d/drow = b`` (away from the border, where replicate padding halves them).
    ``mode="magnitude"`` (default): one channel ``sqrt(gx^2 + gy^2)``; ``mode="xy"``: two
    channels per input channel, ``[d/dcol, d/drow]`` (x = columns, y = rows).
    """

    name = "sobel"

    def __init__(self, mode: str = "magnitude") -> None:
        super().__init__()
        if mode not in ("magnitude", "xy"):
            raise LearnPreprocessError(f"mode: expected 'magnitude' or 'xy', got {mode!r}")
        self.mode = mode

    def params(self) -> dict[str, Any]:
        return {"mode": self.mode}

    def _apply(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        kx = torch.tensor(
            [[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=x.dtype, device=x.device
        ) / 8.0
        weight = torch.stack([kx, kx.T])[:, None]  # (2, 1, 3, 3): d/dcol, d/drow (correlation)
        padded = F.pad(_flat(x), (1, 1, 1, 1), mode="replicate")
        g = F.conv2d(padded, weight)  # (B C, 2, H, W)
        if self.mode == "xy":
            return g.reshape(b, 2 * c, h, w)
        return torch.sqrt((g * g).sum(1)).reshape(b, c, h, w)


def gaussian_kernel_1d(sigma_px: float, dtype=torch.float64, device=None) -> torch.Tensor:
    """Sampled Gaussian ``exp(-k^2 / (2 sigma^2))``, ``k = -r..r``, ``r = ceil(3 sigma)``, sum 1."""
    r = max(int(math.ceil(3.0 * sigma_px)), 1)
    k = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-(k * k) / (2.0 * sigma_px * sigma_px))
    return (g / g.sum()).to(dtype=dtype, device=device)


class Gaussian(TensorStep):
    """Separable Gaussian blur, ``sigma_px`` in pixels (0: identity).

    Kernel radius ``ceil(3 sigma_px)`` px, sampled and normalised to sum 1 (so constants are
    kept, and the image sum is kept when the content is further than the radius from the
    border), replicate padding.
    """

    name = "gaussian"

    def __init__(self, sigma_px: float = 1.0) -> None:
        super().__init__()
        self.sigma_px = _positive(sigma_px, "sigma_px", allow_zero=True)

    def params(self) -> dict[str, Any]:
        return {"sigma_px": self.sigma_px}

    def _apply(self, x: torch.Tensor) -> torch.Tensor:
        if self.sigma_px == 0:
            return x
        b, c, h, w = x.shape
        k = gaussian_kernel_1d(self.sigma_px, dtype=x.dtype, device=x.device)
        r = (k.numel() - 1) // 2
        y = F.pad(_flat(x), (r, r, r, r), mode="replicate")
        y = F.conv2d(y, k.reshape(1, 1, 1, -1))
        y = F.conv2d(y, k.reshape(1, 1, -1, 1))
        return y.reshape(b, c, h, w)


class LocalContrast(TensorStep):
    """Local contrast normalisation: ``(x - m) / sqrt(v + eps^2)`` with ``m`` and ``v`` the
    Gaussian-weighted local mean and variance (window ``sigma_px`` pixels; Pinto et al. 2008,
    the "LCN" of the original work's proposed remedies).

    It removes slowly varying intensity (scatter's low-frequency veil, a heel effect, a display
    window) and equalises local contrast, keeping edges: the output is invariant to
    ``a x + b`` (``a > 0``) wherever the local standard deviation is well above ``eps``. ``eps`` is
    relative: ``eps_rel`` times the image's global standard deviation (per image and channel),
    so flat regions stay near 0 instead of amplifying noise. Output: ``(B, C, H, W)``,
    dimensionless, roughly in [-3, 3]. Replicate padding, as :class:`Gaussian`.
    """

    name = "local_contrast"

    def __init__(self, sigma_px: float = 8.0, eps_rel: float = 0.1) -> None:
        super().__init__()
        self.sigma_px = _positive(sigma_px, "sigma_px")
        self.eps_rel = _positive(eps_rel, "eps_rel")

    def params(self) -> dict[str, Any]:
        return {"sigma_px": self.sigma_px, "eps_rel": self.eps_rel}

    def _apply(self, x: torch.Tensor) -> torch.Tensor:
        blur = Gaussian(self.sigma_px)
        m = blur(x)
        v = (blur(x * x) - m * m).clamp_min(0.0)
        b, c = x.shape[:2]
        eps = self.eps_rel * x.reshape(b, c, -1).std(dim=-1).reshape(b, c, 1, 1)
        return (x - m) / torch.sqrt(v + eps * eps + _EPS)


class RandomConvolution(TensorStep):
    """Random convolutions (Xu et al., ICLR 2021), a training-time appearance randomisation.

    Per call (one draw for the whole batch): with probability ``p`` pick a kernel size ``k`` from
    ``kernel_sizes`` (odd, px), draw a ``k x k`` kernel with entries ``N(0, 1/k^2)``, convolve
    every image (replicate padding) and rescale each output image linearly to its input image's
    ``[min, max]`` (a constant output keeps the input). Otherwise, and in ``eval()`` mode, the
    identity. Randomness comes from the ``generator`` passed to ``forward``, else from an own
    generator seeded with ``seed``, else from torch's global generator; with a generator of a
    given state the result is deterministic.
    """

    name = "random_convolution"

    def __init__(
        self, kernel_sizes: Sequence[int] = (1, 3, 5, 7), p: float = 0.5, seed: int | None = None
    ) -> None:
        super().__init__()
        sizes = tuple(kernel_sizes) if isinstance(kernel_sizes, (list, tuple)) else None
        if not sizes or any(
            isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 1 or k % 2 == 0
            for k in sizes
        ):
            raise LearnPreprocessError(
                f"kernel_sizes: expected a non-empty sequence of odd integers >= 1 (px), got {kernel_sizes!r}"
            )
        p = _positive(p, "p", allow_zero=True)
        if p > 1:
            raise LearnPreprocessError(f"p: expected a probability in [0, 1], got {p!r}")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, numbers.Integral)):
            raise LearnPreprocessError(f"seed: expected an integer or None, got {seed!r}")
        self.kernel_sizes = tuple(int(k) for k in sizes)
        self.p = p
        self.seed = None if seed is None else int(seed)
        self._generator = None if seed is None else torch.Generator().manual_seed(int(seed))

    def params(self) -> dict[str, Any]:
        return {"kernel_sizes": list(self.kernel_sizes), "p": self.p, "seed": self.seed}

    def forward(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        x = _check_images(x)
        if generator is not None and not isinstance(generator, torch.Generator):
            raise LearnPreprocessError(
                f"generator: expected a torch.Generator or None, got {type(generator).__name__}"
            )
        if not self.training or self.p == 0:
            return x
        gen = generator if generator is not None else self._generator
        if float(torch.rand((), generator=gen, dtype=torch.float64)) >= self.p:
            return x
        k = self.kernel_sizes[int(torch.randint(len(self.kernel_sizes), (), generator=gen))]
        weight = torch.randn(k, k, generator=gen, dtype=torch.float64) / k  # std 1/k
        weight = weight.to(dtype=x.dtype, device=x.device)[None, None]
        b, c, h, w = x.shape
        r = k // 2
        y = F.conv2d(F.pad(_flat(x), (r, r, r, r), mode="replicate"), weight).reshape(b, c, h, w)
        # Re-normalise each output image to its input's [min, max].
        lo_x, hi_x = x.flatten(2).amin(-1)[..., None, None], x.flatten(2).amax(-1)[..., None, None]
        lo_y, hi_y = y.flatten(2).amin(-1)[..., None, None], y.flatten(2).amax(-1)[..., None, None]
        span = hi_y - lo_y
        safe = torch.where(span > 0, span, torch.ones_like(span))
        out = lo_x + (y - lo_y) / safe * (hi_x - lo_x)
        return torch.where(span > 0, out, x)


class HistogramMatch(TensorStep):
    """Match each image's intensity histogram to a reference image's (quantile mapping).

    A pixel of mid-rank ``r`` among the image's ``N`` pixels (ties share their mean rank) gets
    the reference's quantile ``q = r / (N - 1)`` (linear interpolation between the sorted
    reference values). For an image that is a strictly increasing function of the reference (same
    pixel count) the output is exactly the reference. ``reference``: any-shaped real array
    (NumPy or torch), finite, at least 2 values.
    """

    name = "histogram_match"

    def __init__(self, reference: np.ndarray | torch.Tensor) -> None:
        super().__init__()
        if isinstance(reference, torch.Tensor):
            ref = reference.detach().to("cpu", torch.float64).flatten()
        elif isinstance(reference, (np.ndarray, list, tuple)):
            arr = np.asarray(reference)
            if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
                raise LearnPreprocessError(f"reference: expected a real array, got dtype {arr.dtype}")
            ref = torch.from_numpy(arr.astype(np.float64).ravel())
        else:
            raise LearnPreprocessError(
                f"reference: expected a numpy array or torch tensor, got {type(reference).__name__}"
            )
        if ref.numel() < 2 or not bool(torch.isfinite(ref).all()):
            raise LearnPreprocessError("reference: expected at least 2 finite values")
        self.register_buffer("sorted_reference", torch.sort(ref).values)

    def params(self) -> dict[str, Any]:
        ref = self.sorted_reference
        digest = hashlib.sha256(ref.cpu().numpy().tobytes()).hexdigest()[:16]
        return {
            "reference_summary": {
                "n": int(ref.numel()),
                "min": float(ref[0]),
                "median": float(ref[(ref.numel() - 1) // 2]),
                "max": float(ref[-1]),
                "sha256_16": digest,
            }
        }

    def _apply(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        n = h * w
        if n < 2:
            raise LearnPreprocessError(f"x: histogram matching needs at least 2 pixels, got {h}x{w}")
        flat = x.reshape(b * c, n).to(torch.float64)
        srt = torch.sort(flat, dim=1).values
        left = torch.searchsorted(srt, flat, right=False)
        right = torch.searchsorted(srt, flat, right=True) - 1
        q = (left + right).to(torch.float64) / (2.0 * (n - 1))
        ref = self.sorted_reference.to(flat.device)
        m = ref.numel()
        pos = q * (m - 1)
        lo = pos.floor().clamp(0, m - 1).long()
        hi = (lo + 1).clamp(max=m - 1)
        frac = pos - lo.to(torch.float64)
        out = ref[lo] * (1.0 - frac) + ref[hi] * frac
        return out.to(x.dtype).reshape(b, c, h, w)


class Compose(torch.nn.Module):
    """Apply ``steps`` in order; ``record()`` is the JSON-serialisable list of their records."""

    def __init__(self, steps: Iterable[TensorStep]) -> None:
        super().__init__()
        steps = list(steps)
        for k, s in enumerate(steps):
            if not isinstance(s, TensorStep):
                raise LearnPreprocessError(
                    f"steps[{k}]: expected a learn.preprocess step, got {type(s).__name__}"
                )
        self.steps = torch.nn.ModuleList(steps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = _check_images(x)
        for s in self.steps:
            x = s(x)
        return x

    def record(self) -> list[dict[str, Any]]:
        """``[step.to_dict() for step in steps]``: names and parameters, JSON-serialisable."""
        return [s.to_dict() for s in self.steps]

    def to_dict(self) -> dict[str, Any]:
        return {"name": "compose", "steps": self.record()}


#: Registry of step names for :func:`build`.
STEPS: dict[str, type[TensorStep]] = {
    cls.name: cls
    for cls in (LogCorrect, Normalize, Median, Sobel, Gaussian, LocalContrast, RandomConvolution, HistogramMatch)
}


def build(names_or_dicts: Iterable[str | dict[str, Any] | TensorStep]) -> Compose:
    """A :class:`Compose` from step names (defaults), records ``{"name": ..., **params}`` or steps.

    Valid names: ``log_correct``, ``normalize``, ``median``, ``sobel``, ``gaussian``,
    ``local_contrast``, ``random_convolution``, ``histogram_match`` (the latter needs ``"reference"``: an array).
    Unknown names or parameters raise :class:`LearnPreprocessError` listing the valid ones.
    """
    if isinstance(names_or_dicts, (str, dict)):
        names_or_dicts = [names_or_dicts]
    steps: list[TensorStep] = []
    for k, item in enumerate(names_or_dicts):
        if isinstance(item, TensorStep):
            steps.append(item)
            continue
        if isinstance(item, str):
            name, kwargs = item, {}
        elif isinstance(item, dict):
            if "name" not in item:
                raise LearnPreprocessError(f"steps[{k}]: a step record needs a 'name' key, got {item!r}")
            name = item["name"]
            kwargs = {key: v for key, v in item.items() if key != "name"}
        else:
            raise LearnPreprocessError(
                f"steps[{k}]: expected a step name, a dict with 'name', or a step, got {type(item).__name__}"
            )
        if name not in STEPS:
            raise LearnPreprocessError(
                f"steps[{k}]: unknown preprocessing step {name!r}; valid: {', '.join(sorted(STEPS))}"
            )
        cls = STEPS[name]
        if cls is HistogramMatch:
            kwargs.pop("reference_summary", None)
            if "reference" not in kwargs:
                raise LearnPreprocessError(
                    f"steps[{k}]: 'histogram_match' needs a 'reference' image (array)"
                )
        try:
            steps.append(cls(**kwargs))
        except TypeError as exc:
            raise LearnPreprocessError(f"steps[{k}] ({name}): bad parameters {sorted(kwargs)}: {exc}") from exc
    return Compose(steps)
