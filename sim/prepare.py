"""The preparation an X-ray image gets before the network or the similarity measure sees it (NumPy).

One home for the arithmetic that registration (``register.xray.preprocess``, ``register.xray.prepare``)
and training (``learn.online.prepare_like_registration``) both apply to an X-ray, so that a
training target is prepared exactly as registration prepares a user's frame. Each function is
one step over the *field* (the valid pixels, a ``(H, W)`` bool ``mask``; ``None``: every pixel):

* :func:`checked_image`: an image the steps can take (numeric, ``(H, W)``, finite) as float64;
* :func:`field_values`: the pixels the statistics of every step are taken over;
* :func:`invert`: ``max + min - x`` over the field's extremes (bone dark <-> bone bright);
* :func:`i0_percentile`, :func:`log_correct`: ``-ln(max(I, floor_frac I0) / I0)``, transmitted
  intensity -> line-integral-like values, ``I0`` a high percentile over the field;
* :func:`field_box`: the field's bounding box (the crop of the field);
* :func:`percentile_bounds`, :func:`normalize`: the ``low`` / ``high`` percentiles over the field
  to 0 / 1, clipped to ``[0, 1]``;
* :func:`masked_fill`: the pixels outside the field set to the mean over it.

:class:`Step` is the one protocol of every preprocessing step of the project: registration's
(:mod:`register.xray.preprocess`: one ``(H, W)`` NumPy image and its field) and training's
(:mod:`learn.preprocess`: ``(B, C, H, W)`` torch batches, the domain-gap study's steps among them).

Callers decide what a degenerate input means (registration raises, training substitutes), so the
functions return the measured values (extremes, percentiles) and leave that to them. The batched
torch twins (and the resampling of a field's crop) are :mod:`sim.prepare_batched`. The operations
(and their order, dtypes and ``np.percentile`` calls) are those the callers made before they
shared them: results are bit-identical.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import numpy as np

from sim.core.atomic import jsonable

__all__ = ["Step", "checked_image", "field_values", "invert", "i0_percentile", "log_correct", "field_box", "percentile_bounds",
           "normalize", "masked_fill"]


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
    """The pixels of ``image`` inside ``mask`` (all of them, flattened, without a mask)."""
    return image.ravel() if mask is None else image[mask]


def invert(image: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, float, float]:
    """``(max + min - image, min, max)`` with ``min`` / ``max`` over the field: the range is kept,
    reversed; inverting twice with the same field gives the image back."""
    v = field_values(image, mask)
    mn, mx = float(v.min()), float(v.max())
    return (mx + mn) - image, mn, mx


def i0_percentile(image: np.ndarray, mask: np.ndarray | None, percentile: float) -> float:
    """The unattenuated intensity ``I0`` of a transmission image: the ``percentile``-th percentile
    of the field (the brightest, least attenuated part stands for the direct beam)."""
    return float(np.percentile(field_values(image, mask), percentile))


def log_correct(image: np.ndarray, i0: float, floor_frac: float = 1e-6) -> np.ndarray:
    """``-ln(max(image, floor_frac * i0) / i0)``: transmitted intensity -> line-integral-like values
    (bone bright, the direct beam ~ 0; pixels above ``i0`` get small negative values)."""
    floor = floor_frac * i0
    return -np.log(np.maximum(image, floor) / i0)


def field_box(mask: np.ndarray, margin: int = 0) -> tuple[int, int, int, int]:
    """The bounding box ``(row0, row1, col0, col1)`` (half-open) of the ``True`` pixels of ``mask``
    (``(H, W)`` bool, at least one ``True``), ``margin`` pixels wider on each side, clipped to the image."""
    H, W = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    m = int(margin)
    return (max(0, int(rows[0]) - m), min(H, int(rows[-1]) + 1 + m),
            max(0, int(cols[0]) - m), min(W, int(cols[-1]) + 1 + m))


def percentile_bounds(image: np.ndarray, mask: np.ndarray | None, low_pct: float, high_pct: float) -> np.ndarray:
    """``(2,)``: the ``low_pct`` and ``high_pct`` percentiles (%) of the field (``np.percentile``, linear)."""
    return np.percentile(field_values(image, mask), [low_pct, high_pct])


def normalize(image: np.ndarray, lo, hi) -> np.ndarray:
    """``lo`` -> 0 and ``hi`` -> 1 linearly, clipped to ``[0, 1]`` (``hi > lo``: the caller checks)."""
    return np.clip((image - lo) / (hi - lo), 0.0, 1.0)


def masked_fill(image: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """``image`` (as float64) with the pixels outside ``mask`` set to the mean of the valid pixels.

    The neutral fill for a network's input: it adds no contrast of its own (the valid pixels'
    mean), does not move a min-max normalisation, and, applied with the same mask to both images
    of a pair, makes the field edge a feature they share rather than one that depends on the pose.
    An empty mask fills with 0; no mask returns the image.
    """
    if mask is None:
        return np.asarray(image, np.float64)
    img = np.asarray(image, np.float64)
    return np.where(mask, img, float(img[mask].mean()) if mask.any() else 0.0)
