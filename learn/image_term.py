"""An image-space term for training the pose-update network (xvr's choice): how unlike the line DRR
at the network's predicted target pose is to the line DRR at the true one.

The network regresses the normalised geodesic gradient ``y`` of a pair (target at ``T_A``, current
at ``T_B``; :mod:`learn.labels`). Its predicted target pose is the half step that lands on
``T_A`` for a perfect ``y``: ``T_pred = apply_update(T_B, denormalize(y), 0.5)``. The term is

``1 - NCC(DRR(T_pred), DRR(T_A))``, averaged over the pairs, in ``[0, 2]`` (0 for a perfect pose),

with NCC the zero-mean normalised cross-correlation over all pixels of the two ``size x size`` line
DRRs of ``mu``. ``DRR(T_pred)`` is differentiable in ``T_pred``
(:meth:`sim.projection.raymarch.TorchVolumes.line_integrals`), so the term's gradient reaches the
network's output. Unlike the geodesic loss it weighs a pose error by what it does to the image: a
depth error that barely changes the image counts little, an in-plane shift a lot.

Example::

    >>> term = ImageTerm(volumes, LabelNormalizer())                        # doctest: +SKIP
    >>> loss = geodesic_loss + 0.5 * term(subject, t_a, t_b, output.g[:16])  # doctest: +SKIP
"""

from __future__ import annotations

import numpy as np
import torch

from learn.labels import LabelNormalizer, apply_update
from sim.core.errors import InputError

__all__ = ["ImageTerm", "ImageTermError", "ncc"]

#: Added to each image's pixel variance in the NCC: a blank DRR (anatomy out of view) gives 0, not NaN.
_NCC_EPS = 1e-8


class ImageTermError(InputError):
    """The image term's inputs cannot be used; the message names them."""


def ncc(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Zero-mean normalised cross-correlation of image pairs: ``(B, ..., H, W)`` x 2 -> ``(B,)`` in [-1, 1]."""
    a = a.reshape(len(a), -1)
    b = b.reshape(len(b), -1)
    a = a - a.mean(dim=1, keepdim=True)
    b = b - b.mean(dim=1, keepdim=True)
    return (a * b).mean(dim=1) / torch.sqrt((a.square().mean(dim=1) + _NCC_EPS) * (b.square().mean(dim=1) + _NCC_EPS))


class ImageTerm:
    """``1 - NCC`` of the line DRRs at the predicted and the true target poses (module doc).

    Args:
        volumes: a :class:`sim.projection.raymarch.TorchVolumes` of the subjects' ``mu`` at the
            term's image size (:meth:`learn.batched.BatchedPairs.image_volumes`).
        normalizer: the labels' :class:`learn.labels.LabelNormalizer` (the network's units).

    ``term(subject (K,), t_a (K, 4, 4) mm, t_b (K, 4, 4) mm, y (K, 6) normalised)`` -> a scalar
    tensor, differentiable in ``y``.
    """

    def __init__(self, volumes, normalizer: LabelNormalizer) -> None:
        if not hasattr(volumes, "line_integrals"):
            raise ImageTermError(f"volumes must be a TorchVolumes, got {type(volumes).__name__}")
        self.volumes = volumes
        self.normalizer = normalizer

    def __call__(self, subject, t_a, t_b, y: torch.Tensor) -> torch.Tensor:
        k = len(y)
        subject = np.asarray(subject, np.int64)
        t_a = torch.as_tensor(np.asarray(t_a, np.float64))
        t_b = torch.as_tensor(np.asarray(t_b, np.float64))
        if y.ndim != 2 or y.shape[1] != 6 or subject.shape != (k,) or t_a.shape != (k, 4, 4) or t_b.shape != (k, 4, 4):
            raise ImageTermError(f"image term: subject (K,), t_a and t_b (K, 4, 4) and y (K, 6) for K = {k} pairs, "
                                 f"got {subject.shape}, {tuple(t_a.shape)}, {tuple(t_b.shape)}, {tuple(y.shape)}")
        device = self.volumes.device
        g = self.normalizer.denormalize(y.to(device=device, dtype=torch.float64))
        t_pred = apply_update(t_b.to(device), g, 0.5)
        with torch.no_grad():
            truth = self.volumes.line_integrals(subject, t_a)
        return (1.0 - ncc(self.volumes.line_integrals(subject, t_pred), truth)).mean()
