"""The preparation an X-ray image gets before the network or the similarity measure sees it.

One home for the arithmetic that registration (``register.xray.preprocess``, ``register.xray.prepare``)
and training (``learn.online.prepare_like_registration``: one pair in NumPy, or a batch of pairs in
torch on the device that rendered them) apply to an X-ray, so that a training target is prepared
exactly as registration prepares a user's frame. Each step is written once, for either kind of array
(as :mod:`sim.projection.se3`):

* a NumPy image ``(H, W)`` with its field ``mask`` ``(H, W)`` bool or ``None`` (every pixel): the
  measured values (extremes, percentiles, box) are Python / NumPy scalars;
* a torch batch ``(B, H, W)`` with one field per image, ``mask`` ``(B, H, W)`` bool (each holding a
  pixel) or ``None``: the measured values are ``(B,)`` tensors, and no Python loop runs over the batch.

The steps:

* :func:`checked_image`: an image the steps can take (numeric, ``(H, W)``, finite) as float64;
* :func:`field_values`: the pixels the statistics of a NumPy image's steps are taken over;
* :func:`invert`: ``max + min - x`` over the field's extremes (bone dark <-> bone bright);
* :func:`i0_percentile`, :func:`log_correct`: ``-ln(max(I, floor_frac I0) / I0)``, transmitted
  intensity -> line-integral-like values, ``I0`` a high percentile over the field;
* :func:`median_filter`: the ``size x size`` median, the edges repeated;
* :func:`field_box`: the field's bounding box (the crop of the field);
* :func:`crop_to_field`: images and their field cropped to the box and resampled to the whole
  image (bilinear, ``align_corners=False``, for images; nearest for the field), as ``F.interpolate``;
* :func:`percentile_bounds`, :func:`normalize`: the ``low`` / ``high`` percentiles over the field
  to 0 / 1, clipped to ``[0, 1]`` (an image whose percentiles are equal becomes 0);
* :func:`masked_fill`: the pixels outside the field set to the mean over it.

Three operations have one implementation per kind, behind the step that uses them: the percentiles
(``np.percentile``; :func:`sim.physics.chain.masked_percentile`, which computes them as NumPy
does), the median (scipy's; ``unfold``'s: the same numbers) and the box resampling (``F.interpolate`` on the crop; for a batch of different boxes, one
gather with ``F.interpolate``'s own source indices and weights, equal to it up to float32 rounding,
the field exactly). The field mean is NumPy's pairwise sum for an image and torch's sum for a batch.

:class:`Step` is the one protocol of every preprocessing step of the project: registration's
(:mod:`register.xray.preprocess`: one ``(H, W)`` NumPy image and its field) and training's
(:mod:`learn.preprocess`: ``(B, C, H, W)`` torch batches, the domain-gap study's steps among them).

Callers decide what a degenerate input means (registration raises, training substitutes), so the
functions return the measured values (extremes, percentiles) and leave that to them. The operations
(and their order, dtypes and ``np.percentile`` calls) are those the callers made before they
shared them: results are bit-identical (``scripts/same_outputs.py``). Torch is imported only where a
step is given a torch tensor or resamples a NumPy crop, so registration's NumPy path never pays for it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import numpy as np

from sim.core.atomic import jsonable

__all__ = ["Step", "checked_image", "field_values", "invert", "i0_percentile", "log_correct", "median_filter",
           "field_box",
           "crop_to_field", "resize_boxes", "bilinear_source", "nearest_source", "gather2d", "percentile_bounds",
           "normalize", "masked_fill"]

Array = Any  # numpy.ndarray (one image) or torch.Tensor (a batch)


class Step:
    """A preprocessing step: a ``name`` (class attribute, the key a list of names builds it by) and
    parameters, applied to an image and its field.

    ``apply(image, mask) -> (image, mask, measured)``: ``image`` an ``(H, W)`` NumPy array
    (registration's steps) or a ``(B, C, H, W)`` torch tensor (training's); ``mask`` the valid
    pixels, bool, of the image's layout, or None (every pixel); ``measured`` a dict of what the
    step found (the chosen ``I0``, the percentiles, the crop box), ``{}`` where it finds nothing.
    ``params()`` is the step's parameters, JSON-serialisable (a dataclass step's fields by
    default), and ``to_dict()`` its record ``{"name": ..., **params()}``, from which the step's
    package builds it again. Subclasses: :class:`register.xray.preprocess.Field` ... (NumPy, frozen
    dataclasses), :class:`learn.preprocess.TensorStep` (torch modules).

    Example::

        >>> @dataclasses.dataclass(frozen=True)
        ... class Scale(Step):
        ...     name: ClassVar[str] = "scale"
        ...     factor: float = 2.0
        ...     def apply(self, image, mask):
        ...         return image * self.factor, mask, {}
        >>> Scale(3.0).to_dict()
        {'name': 'scale', 'factor': 3.0}
        >>> Scale().apply(np.ones((2, 2)), None)[0].tolist()
        [[2.0, 2.0], [2.0, 2.0]]
    """

    name: ClassVar[str] = ""

    def params(self) -> dict[str, Any]:
        """The step's parameters, JSON-serialisable: a dataclass step's fields, else none."""
        return jsonable(dataclasses.asdict(self)) if dataclasses.is_dataclass(self) else {}

    def to_dict(self) -> dict[str, Any]:
        """The step's record ``{"name": ..., **params()}``."""
        return {"name": self.name, **self.params()}

    def apply(self, image, mask):
        """``(image, mask) -> (image, mask, measured)`` (class doc)."""
        raise NotImplementedError


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _per_image(v, like: Array):
    """A measured value ready to broadcast against ``like``: a ``(B,)`` tensor as ``(B, 1, 1)``; a
    scalar of a NumPy image as it is."""
    return v[:, None, None] if _is_torch(like) else v


def _select(ok, a, b: float):
    """``a`` where ``ok`` else ``b`` (a number): ``torch.where`` for a tensor condition; for a scalar
    one, ``a`` or ``b`` (an array of ``a``'s shape and dtype filled with ``b`` where ``a`` is one)."""
    if _is_torch(ok):
        import torch  # only reached with a tensor: torch is loaded

        return torch.where(ok, a, b)
    if ok:
        return a
    return np.full_like(a, b) if isinstance(a, np.ndarray) else b


def _field_extremes(image: Array, mask) -> tuple[Any, Any]:
    """``(min, max)`` over the field: floats for a NumPy image, ``(B,)`` tensors for a batch."""
    if _is_torch(image):
        import torch  # only reached with a tensor: torch is loaded

        if mask is None:
            return image.amin(dim=(-2, -1)), image.amax(dim=(-2, -1))
        return (torch.where(mask, image, torch.inf).amin(dim=(-2, -1)),
                torch.where(mask, image, -torch.inf).amax(dim=(-2, -1)))
    v = field_values(image, mask)
    return float(v.min()), float(v.max())


def _field_mean(image: Array, mask) -> Any:
    """The mean over a non-None field (0 for an empty one): a float, or ``(B,)`` for a batch."""
    if _is_torch(image):
        import torch  # only reached with a tensor: torch is loaded

        count = mask.sum(dim=(-2, -1)).to(image.dtype)
        total = torch.where(mask, image, 0.0).sum(dim=(-2, -1))
        return torch.where(count > 0, total / torch.where(count > 0, count, 1.0), 0.0)
    return float(image[mask].mean()) if mask.any() else 0.0


def checked_image(image, name: str, error: type[Exception]) -> np.ndarray:
    """``image`` as a float64 ``(H, W)`` array, or ``error`` naming ``name`` and what is wrong: not
    numeric (bool too), not two-dimensional, NaN or infinite values."""
    a = np.asarray(image)
    if a.dtype.kind not in "uif" or a.dtype == np.bool_:
        raise error(f"{name}: must be numeric, got dtype {a.dtype}")
    if a.ndim != 2:
        raise error(f"{name}: expected shape (H, W), got {a.shape}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise error(f"{name}: contains NaN or infinite values")
    return a


def field_values(image: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """The pixels of a NumPy ``image`` inside ``mask`` (all of them, flattened, without a mask)."""
    return image.ravel() if mask is None else image[mask]


def invert(image: Array, mask, which=True) -> tuple[Array, Any, Any]:
    """``(max + min - image, min, max)`` with ``min`` / ``max`` over the field: the range is kept,
    reversed; inverting twice with the same field gives the image back.

    ``which``: invert this image (a bool), or, for a batch, the images where a ``(B,)`` bool tensor
    is True (the others are returned unchanged; ``min`` / ``max`` are measured for every image).

    Example::

        >>> out, lo, hi = invert(np.array([[1.0, 4.0], [2.0, 0.0]]), np.array([[True, True], [True, False]]))
        >>> out.tolist(), lo, hi
        ([[4.0, 1.0], [3.0, 5.0]], 1.0, 4.0)
    """
    lo, hi = _field_extremes(image, mask)
    out = _per_image(hi + lo, image) - image
    if _is_torch(image):
        import torch  # only reached with a tensor: torch is loaded

        which = torch.as_tensor(which, dtype=torch.bool, device=image.device)
        return torch.where(which.reshape(-1, 1, 1) if which.ndim else which, out, image), lo, hi
    return (out if which else image), lo, hi


def i0_percentile(image: Array, mask, percentile: float):
    """The unattenuated intensity ``I0`` of a transmission image: the ``percentile``-th percentile
    of the field (the brightest, least attenuated part stands for the direct beam); a float for a
    NumPy image, ``(B,)`` for a batch."""
    if _is_torch(image):
        from sim.physics.chain import masked_percentile  # loads torch: only reached with a tensor

        return masked_percentile(image, mask, [percentile])[:, 0]
    return float(np.percentile(field_values(image, mask), percentile))


def log_correct(image: Array, i0, floor_frac: float = 1e-6) -> Array:
    """``-ln(max(image, floor_frac * i0) / i0)``: transmitted intensity -> line-integral-like values
    (bone bright, the direct beam ~ 0; pixels above ``i0`` get small negative values). ``i0``: a
    number for a NumPy image, ``(B,)`` for a batch (:func:`i0_percentile`)."""
    i0 = _per_image(i0, image)
    if _is_torch(image):
        import torch  # only reached with a tensor: torch is loaded

        return -torch.log(torch.maximum(image, floor_frac * i0) / i0)
    floor = floor_frac * i0
    return -np.log(np.maximum(image, floor) / i0)


def median_filter(image: Array, size: int) -> Array:
    """The ``size x size`` median (odd ``size``; the edges repeated, scipy's ``nearest``) of a NumPy
    image ``(H, W)`` (``scipy.ndimage.median_filter``) or of each image of a batch ``(B, H, W)``
    (the ``size^2`` neighbours by ``unfold``: memory ``size^2`` times the batch). The median of an
    odd count is one of the values: both give the same numbers."""
    if size == 1:
        return image
    if _is_torch(image):
        import torch.nn.functional as F  # only reached with a tensor: torch is loaded

        b, h, w = image.shape
        r = size // 2
        padded = F.pad(image[:, None], (r, r, r, r), mode="replicate")
        return F.unfold(padded, kernel_size=size).median(dim=1).values.reshape(b, h, w)
    from scipy import ndimage  # slow to import: only where a NumPy image is filtered

    return ndimage.median_filter(image, size=int(size), mode="nearest")


def field_box(mask: Array, margin: int = 0) -> tuple[Any, Any, Any, Any]:
    """The bounding box ``(row0, row1, col0, col1)`` (half-open) of the ``True`` pixels of ``mask``,
    ``margin`` pixels wider on each side, clipped to the image.

    ``mask``: ``(H, W)`` bool NumPy (at least one ``True``; the box is four ints) or ``(B, H, W)``
    bool torch (each image at least one ``True``; the box is four ``(B,)`` int64 tensors).
    """
    h, w = mask.shape[-2:]
    rows_any, cols_any = mask.any(-1), mask.any(-2)  # (..., H), (..., W)
    if _is_torch(mask):
        import torch  # only reached with a tensor: torch is loaded

        def first(a):  # the index of the first True along the last axis
            return a.to(torch.uint8).argmax(-1)

        def flip(a):
            return a.flip(-1)
    else:
        def first(a):
            return a.argmax(-1)

        def flip(a):
            return a[..., ::-1]
    m = int(margin)
    box = ((first(rows_any) - m).clip(0, h), (h - first(flip(rows_any)) + m).clip(0, h),
           (first(cols_any) - m).clip(0, w), (w - first(flip(cols_any)) + m).clip(0, w))
    return box if _is_torch(mask) else tuple(int(v) for v in box)


def _resample_crop(image: np.ndarray, box: tuple[int, int, int, int], shape: tuple[int, int], mode: str) -> np.ndarray:
    """``image[r0:r1, c0:c1]`` resampled to ``shape`` (``bilinear``, ``align_corners=False``, or
    ``nearest``) by ``F.interpolate`` in float32, as float64."""
    import torch  # slow to import: only training's per-pair targets resample a NumPy crop
    import torch.nn.functional as F

    r0, r1, c0, c1 = box
    x = torch.from_numpy(np.ascontiguousarray(image[r0:r1, c0:c1], np.float32))[None, None]
    kw = {"align_corners": False} if mode == "bilinear" else {}
    return F.interpolate(x, size=shape, mode=mode, **kw)[0, 0].double().numpy()


def bilinear_source(in_size, out_size: int):
    """``F.interpolate(..., mode="bilinear", align_corners=False)``'s source indices and weight
    along one axis: crop lengths ``in_size`` ``(B,)`` int tensor -> ``(i0, i1, lambda1)``
    ``(B, out_size)`` (output pixel ``o`` is ``(1 - lambda1) in[i0] + lambda1 in[i1]``), in float32 as torch."""
    import torch  # only reached with a tensor: torch is loaded

    scale = in_size.to(torch.float32) / torch.tensor(float(out_size), dtype=torch.float32, device=in_size.device)
    o = torch.arange(out_size, dtype=torch.float32, device=in_size.device)
    # scale (o + 0.5) - 0.5 rounded once, as torch's kernels compute it (a fused multiply-add;
    # the float32 product is exact in float64): without, lambda differs by up to ~1e-5
    src = (scale[:, None].double() * (o[None, :] + 0.5).double() - 0.5).float().clamp_min(0.0)
    last = (in_size - 1)[:, None]
    i0 = torch.minimum(torch.floor(src).to(torch.int64), last)
    lam = (src - i0.to(torch.float32)).clamp(0.0, 1.0)
    i1 = torch.where(i0 < last, i0 + 1, i0)
    return i0, i1, lam


def nearest_source(in_size, out_size: int):
    """``F.interpolate(..., mode="nearest")``'s source indices ``(B, out_size)`` for crop lengths
    ``in_size`` ``(B,)`` int tensor: ``min(floor(o * (float)in / out), in - 1)`` in float32, as torch."""
    import torch  # only reached with a tensor: torch is loaded

    scale = in_size.to(torch.float32) / torch.tensor(float(out_size), dtype=torch.float32, device=in_size.device)
    o = torch.arange(out_size, dtype=torch.float32, device=in_size.device)
    return torch.minimum(torch.floor(o[None, :] * scale[:, None]).to(torch.int64), (in_size - 1)[:, None])


def gather2d(x, rows, cols):
    """``x[b, rows[b, i], cols[b, j]]``: ``(B, H, W)`` from ``(B, Hin, Win)``, rows ``(B, H)``, cols ``(B, W)``."""
    b, _, win = x.shape
    r = x.gather(1, rows[:, :, None].expand(b, rows.shape[1], win))
    return r.gather(2, cols[:, None, :].expand(b, rows.shape[1], cols.shape[1]))


def resize_boxes(x, box, size: tuple[int, int]):
    """Each image's ``x[b, r0:r1, c0:c1]`` resampled bilinearly (``align_corners=False``) to
    ``size``, as ``F.interpolate`` in float32: ``(B, Hin, Win)`` -> ``(B, H, W)`` float32."""
    import torch  # only reached with a tensor: torch is loaded

    r0, r1, c0, c1 = box
    h0, h1, lh = bilinear_source(r1 - r0, size[0])
    w0, w1, lw = bilinear_source(c1 - c0, size[1])
    h0, h1, w0, w1 = h0 + r0[:, None], h1 + r0[:, None], w0 + c0[:, None], w1 + c0[:, None]
    x = x.to(torch.float32)
    lw1, lw0 = lw[:, None, :], (1.0 - lw)[:, None, :]
    lh1, lh0 = lh[:, :, None], (1.0 - lh)[:, :, None]
    top = gather2d(x, h0, w0) * lw0 + gather2d(x, h0, w1) * lw1
    bottom = gather2d(x, h1, w0) * lw0 + gather2d(x, h1, w1) * lw1
    return top * lh0 + bottom * lh1


def crop_to_field(images: tuple[Array, ...], mask: Array, box=None, *, crop: bool = True) -> tuple[Array, ...]:
    """Each of ``images`` and the field ``mask`` cropped to the field's bounding box and resampled
    to the whole image's size: ``(*images, mask)``.

    Args:
        images: NumPy ``(H, W)`` images (returned as float64) or torch ``(B, H, W)`` batches
            (returned in their own dtype), resampled bilinearly (``align_corners=False``) in float32,
            as ``F.interpolate`` does.
        mask: the field, ``(H, W)`` or ``(B, H, W)`` bool, every image's holding a pixel; resampled
            nearest (``F.interpolate``'s ``nearest``).
        box: :func:`field_box` of ``mask`` (computed when None).
        crop: False returns the images (as float64 for NumPy) and the field as they are.

    An image whose box is the whole image is not resampled. A resampled field that lost every
    pixel becomes the whole image.
    """
    box = field_box(mask) if box is None else box
    h, w = mask.shape[-2:]
    if _is_torch(mask):
        import torch  # only reached with a tensor: torch is loaded

        r0, r1, c0, c1 = box
        cropped = ((r0 != 0) | (r1 != h) | (c0 != 0) | (c1 != w))[:, None, None] & crop
        out = [torch.where(cropped, resize_boxes(x, box, (h, w)).to(x.dtype), x) for x in images]
        rows = nearest_source(r1 - r0, h) + r0[:, None]
        cols = nearest_source(c1 - c0, w) + c0[:, None]
        mask = torch.where(cropped, gather2d(mask, rows, cols), mask)
        return (*out, torch.where(mask.flatten(1).any(1)[:, None, None], mask, True))
    if not crop or tuple(box) == (0, h, 0, w):
        return (*(np.asarray(x, np.float64) for x in images), mask)
    out = [_resample_crop(x, box, (h, w), "bilinear") for x in images]
    mask = _resample_crop(mask.astype(np.float32), box, (h, w), "nearest") > 0.5
    return (*out, mask if mask.any() else np.ones((h, w), bool))


def percentile_bounds(image: Array, mask, low_pct: float, high_pct: float) -> tuple[Any, Any]:
    """``(low, high)``: the ``low_pct`` and ``high_pct`` percentiles (%) of the field (``np.percentile``,
    linear): NumPy scalars for a NumPy image, ``(B,)`` tensors for a batch."""
    if _is_torch(image):
        from sim.physics.chain import masked_percentile  # loads torch: only reached with a tensor

        lohi = masked_percentile(image, mask, [low_pct, high_pct])
        return lohi[:, 0], lohi[:, 1]
    lo, hi = np.percentile(field_values(image, mask), [low_pct, high_pct])
    return lo, hi


def normalize(image: Array, lo, hi) -> Array:
    """``lo`` -> 0 and ``hi`` -> 1 linearly, clipped to ``[0, 1]``; an image whose ``hi <= lo`` becomes
    0 (registration refuses such an image before: see ``register.xray.preprocess.Normalize``).
    ``lo``, ``hi``: scalars for a NumPy image, ``(B,)`` for a batch (:func:`percentile_bounds`)."""
    lo, hi = _per_image(lo, image), _per_image(hi, image)
    span = hi - lo
    ok = span > 0
    out = ((image - lo) / _select(ok, span, 1.0)).clip(0.0, 1.0)
    return _select(ok, out, 0.0)


def masked_fill(image: Array, mask) -> Array:
    """``image`` with the pixels outside ``mask`` set to the mean of the valid pixels (a NumPy image
    as float64, a batch in its dtype, each image its own mean).

    The neutral fill for a network's input: it adds no contrast of its own (the valid pixels'
    mean), does not move a min-max normalisation, and, applied with the same mask to both images
    of a pair, makes the field edge a feature they share rather than one that depends on the pose.
    An empty field fills with 0; no mask returns the image.
    """
    img = image if _is_torch(image) else np.asarray(image, np.float64)
    if mask is None:
        return img
    fill = _per_image(_field_mean(img, mask), img)
    if _is_torch(img):
        import torch  # only reached with a tensor: torch is loaded

        return torch.where(mask, img, fill)
    return np.where(mask, img, fill)
