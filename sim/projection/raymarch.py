"""Line integrals of many CT volumes at many poses in one torch call (CPU or CUDA).

The Dr.Jit renderer (:mod:`sim.projection.drr`) is the reference and registration's renderer; this is
its batched twin for training pairs, where thousands of images per second of several subjects
must come from the device that trains the network. :class:`TorchVolumes` holds the channels of
several subjects (e.g. ``mu`` and the two basis densities of :mod:`sim.physics.two_basis`) on one
device, stacked along the first voxel axis with empty slabs between them, so one
``grid_sample`` serves a batch whose pairs come from any subjects.

On a CPU, ``grid_sample`` over a 3-D volume is about 80x slower than the Dr.Jit renderer's compiled
Siddon kernel, so :func:`volumes_for` gives :class:`DrJitVolumes` there (the same interface over
:class:`sim.projection.drr.DRRRenderer`) and :class:`TorchVolumes` on a GPU.

Rays (``docs/conventions.md``): the source is the camera origin, pixel ``(i, j)``'s centre is
``((j - cx) s, (i - cy) s, SDD)``; a camera point ``X`` is the patient point
``R^T (X - t) + c`` (pose ``T = (R, t)``, anatomy centre ``c``, LPS mm), then voxel indices by the
inverse affine. Each ray is clipped to the volume's box (voxel ``n`` covers ``[n - 0.5, n + 0.5]``
on each axis, as Siddon's traversal counts it) and sampled at ``S`` midpoints of equal segments,
trilinearly (values beyond the outer voxel centres fall linearly to 0 over the outer half voxel
and to the empty slab); ``S`` is the longest box diagonal of the subjects divided by
``step_fraction`` times the smallest spacing, the same for every ray and batch, so an image does
not depend on the batch it is rendered in. The midpoint rule's error falls as the step squared
(``tests/sim/test_raymarch.py`` states the agreement with the Siddon renderer).
"""

from __future__ import annotations

import math

import numpy as np

from sim.core.errors import InputError
from sim.ct.volume import CTVolume
from sim.projection.geometry import CArmGeometry
from sim.projection.drr import DRRRenderer, RenderSettings

__all__ = ["RaymarchError", "TorchVolumes", "DrJitVolumes", "volumes_for"]

#: Empty voxels between two stacked subjects (trilinear samples never mix them).
GAP_VOXELS = 2
#: Samples per ``grid_sample`` call (memory: 3 coordinates and the channels per sample).
CHUNK_SAMPLES = 1 << 24


class RaymarchError(InputError):
    """Volumes, poses or settings of the batched ray marcher cannot be used; the message names them."""


class TorchVolumes:
    """Several subjects' volume channels on one torch device, for batched line integrals.

    Args:
        channels: one ``(C, I, J, K)`` float array per subject (the same ``C``; values per mm of
            path: 1/mm for ``mu``, g/cm^3 for densities; the result multiplies by the path in mm).
        affines: one ``(4, 4)`` voxel-index-to-LPS-mm affine per subject.
        centers: one ``(3,)`` anatomy centre (LPS mm) per subject.
        geometry: the :class:`sim.projection.geometry.CArmGeometry` of the images.
        device: torch device; dtype: torch dtype of the volumes and samples (default float32).
        step_fraction: the sampling step as a fraction of the smallest voxel spacing, in
            [0.05, 1] (default 0.5).
        scene: unused (the rays come from ``geometry``); :class:`DrJitVolumes` takes the same arguments.

    ``line_integrals(subject (B,), poses (B, 4, 4) mm) -> (B, C, H, W)``: each channel's integral
    along each pixel's ray, in the channel's unit times mm.

    Example::

        >>> vols = TorchVolumes([mu[None]], [ct.affine], [center], geometry)   # doctest: +SKIP
        >>> drr = vols.line_integrals(torch.zeros(2, dtype=torch.long), poses)  # (2, 1, H, W)
    """

    def __init__(self, channels, affines, centers, geometry, *, device="cpu", dtype=None, step_fraction: float = 0.5,
                 scene: str = "cios_fusion"):
        import torch

        if not isinstance(geometry, CArmGeometry):
            raise RaymarchError(f"geometry must be a CArmGeometry, got {type(geometry).__name__}")
        if not (isinstance(step_fraction, (int, float)) and 0.05 <= step_fraction <= 1.0):
            raise RaymarchError(f"step_fraction must be a number in [0.05, 1], got {step_fraction!r}")
        if not (len(channels) == len(affines) == len(centers) >= 1):
            raise RaymarchError(f"one affine and one centre per volume: got {len(channels)} volumes, "
                                f"{len(affines)} affines, {len(centers)} centres")
        arrays = [np.asarray(c) for c in channels]
        nc = arrays[0].shape[0] if arrays[0].ndim == 4 else None
        for n, a in enumerate(arrays):
            if a.ndim != 4 or a.shape[0] != nc or min(a.shape) < 1 or not np.all(np.isfinite(a)):
                raise RaymarchError(f"volume {n}: expected a finite (C={nc}, I, J, K) array, got shape {a.shape}")
        self.device = torch.device(device)
        self.dtype = dtype or torch.float32
        self.geometry = geometry
        self.step_fraction = float(step_fraction)
        self.n_channels = nc
        self.shapes = np.array([a.shape[1:] for a in arrays])  # (N, 3)
        di, dj, dk = self.shapes.max(axis=0)
        # stacked along i with GAP_VOXELS empty voxels before each subject
        self.offsets = np.cumsum([0] + [int(s[0]) + GAP_VOXELS for s in self.shapes])[:-1] + GAP_VOXELS
        total = int(self.offsets[-1] + self.shapes[-1][0] + GAP_VOXELS)
        big = torch.zeros((1, nc, total, int(dj), int(dk)), dtype=self.dtype, device=self.device)
        for a, off in zip(arrays, self.offsets):
            big[0, :, off:off + a.shape[1], :a.shape[2], :a.shape[3]] = torch.as_tensor(a, dtype=self.dtype)
        self.volume = big
        self.size_ijk = np.array([total, dj, dk], dtype=np.float64)
        index_from_lps = []
        spacing = []
        for n, a in enumerate(affines):
            a = np.asarray(a, dtype=np.float64)
            if a.shape != (4, 4) or not np.all(np.isfinite(a)) or abs(np.linalg.det(a[:3, :3])) < 1e-12:
                raise RaymarchError(f"affine {n}: expected an invertible finite (4, 4) matrix, got shape {a.shape}")
            index_from_lps.append(np.linalg.inv(a))
            spacing.append(np.linalg.norm(a[:3, :3], axis=0))
        self.index_from_lps = np.stack(index_from_lps)  # (N, 4, 4)
        self.min_spacing_mm = float(np.min(spacing))
        self.centers = np.asarray(centers, dtype=np.float64).reshape(len(arrays), 3)
        # one sample count for every ray of every batch (the longest diagonal of any subject's box),
        # so an image does not depend on the batch it is rendered in
        diagonal = max(float(np.linalg.norm(np.asarray(a, np.float64)[:3, :3] @ s)) for a, s in zip(affines, self.shapes))
        self.samples_per_ray = max(1, int(math.ceil(diagonal / (self.step_fraction * self.min_spacing_mm))))
        pix = geometry.pixel_centers_camera().reshape(-1, 3)  # (P, 3) camera mm
        self._pixels = torch.as_tensor(pix, dtype=torch.float64, device=self.device)

    @property
    def n_subjects(self) -> int:
        return len(self.shapes)

    def line_integrals(self, subject, poses, channels=None):
        """See the class doc. ``subject`` ``(B,)`` integers, ``poses`` ``(B, 4, 4)`` (numpy or torch);
        ``channels``: the channel indices to integrate (default all) -> ``(B, len(channels), H, W)``.

        Differentiable in the poses: a torch ``poses`` that requires grad gives images whose
        gradient flows back to it (through the sample positions of the trilinear march and the
        rays' clipping to the box), e.g. for a loss on the image at a predicted pose
        (:mod:`learn.image_term`)."""
        import torch
        import torch.nn.functional as F

        pose_t = poses if isinstance(poses, torch.Tensor) and poses.requires_grad else None
        subject, poses = _checked(subject, poses, self.n_subjects)
        b = len(subject)
        h, w = self.geometry.height, self.geometry.width
        chans = _channels(channels, self.n_channels)
        volume = self.volume if len(chans) == self.n_channels else self.volume[:, list(chans)]
        nc = len(chans)
        if b == 0:
            return torch.zeros((0, nc, h, w), dtype=self.dtype, device=self.device)
        # index(lambda) = lambda * (M p) + e per ray, M = A^-1 R^T, e = A^-1 (c - R^T t) (+ offset in i)
        if pose_t is None:
            rot_t = np.swapaxes(poses[:, :3, :3], 1, 2)
            inv = self.index_from_lps[subject]  # (B, 4, 4)
            m = inv[:, :3, :3] @ rot_t  # (B, 3, 3)
            e = np.einsum("bij,bj->bi", inv[:, :3, :3], self.centers[subject] - np.einsum("bij,bj->bi", rot_t,
                                                                                         poses[:, :3, 3])) + inv[:, :3, 3]
            m_t = torch.as_tensor(m, dtype=torch.float64, device=self.device)
            e_t = torch.as_tensor(e, dtype=torch.float64, device=self.device)
        else:  # the same in torch, so the gradient reaches the poses
            pose_t = pose_t.to(device=self.device, dtype=torch.float64)
            rot_t = pose_t[:, :3, :3].transpose(1, 2)
            inv = torch.as_tensor(self.index_from_lps[subject], dtype=torch.float64, device=self.device)
            centers = torch.as_tensor(self.centers[subject], dtype=torch.float64, device=self.device)
            m_t = inv[:, :3, :3] @ rot_t
            e_t = torch.einsum("bij,bj->bi", inv[:, :3, :3],
                               centers - torch.einsum("bij,bj->bi", rot_t, pose_t[:, :3, 3])) + inv[:, :3, 3]
        d = torch.einsum("bij,pj->bpi", m_t, self._pixels)  # (B, P, 3) index units per unit lambda
        # slab clipping to [-0.5, n - 0.5] of each subject's own box
        hi = torch.as_tensor(self.shapes[subject] - 0.5, dtype=torch.float64, device=self.device)[:, None, :]
        lo = torch.full_like(hi, -0.5)
        safe = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        t0 = (lo - e_t[:, None, :]) / safe
        t1 = (hi - e_t[:, None, :]) / safe
        enter = torch.minimum(t0, t1).amax(dim=2).clamp(min=0.0)
        leave = torch.maximum(t0, t1).amin(dim=2)
        span = (leave - enter).clamp(min=0.0)  # (B, P) lambda
        ray_mm = torch.linalg.norm(self._pixels, dim=1)  # (P,) mm from the source to the pixel
        chord = span * ray_mm[None, :]
        n_s = self.samples_per_ray
        frac = (torch.arange(n_s, dtype=torch.float64, device=self.device) + 0.5) / n_s  # (S,)
        offset = torch.zeros_like(e_t)
        offset[:, 0] = torch.as_tensor(self.offsets[subject], dtype=torch.float64, device=self.device)
        e_t = e_t + offset
        # normalised grid coordinates (align_corners=True): x -> k, y -> j, z -> i (stacked)
        scale = torch.as_tensor(2.0 / (self.size_ijk - 1.0), dtype=torch.float64, device=self.device)
        out = []
        d, e_t, scale = d.to(self.dtype), e_t.to(self.dtype), scale.to(self.dtype)
        p = h * w
        per_chunk = max(1, CHUNK_SAMPLES // (p * n_s))
        for start in range(0, b, per_chunk):
            sl = slice(start, min(b, start + per_chunk))
            lam = (enter[sl, :, None] + span[sl, :, None] * frac[None, None, :]).to(self.dtype)  # (b', P, S)
            # normalised (x, y, z) = (k, j, i) of each sample, align_corners=True
            g = (d[sl, :, None, :] * lam[..., None] + e_t[sl, None, None, :]) * scale - 1.0  # (b', P, S, 3) i, j, k
            g = g.flip(-1)
            nb = g.shape[0]
            v = F.grid_sample(volume, g.reshape(1, nb * p, n_s, 1, 3), mode="bilinear", padding_mode="zeros",
                              align_corners=True)  # (1, C, nb * P, S, 1)
            v = v[0, :, :, :, 0].sum(dim=2).reshape(nc, nb, p).permute(1, 0, 2)
            out.append(v * (chord[sl] / n_s).to(self.dtype)[:, None, :])
        return torch.cat(out).reshape(b, nc, h, w)


def _checked(subject, poses, n_subjects: int) -> tuple[np.ndarray, np.ndarray]:
    """``subject`` ``(B,)`` int64 and ``poses`` ``(B, 4, 4)`` float64 as numpy (from numpy or torch),
    refused in one line when their shapes or the subject indices do not fit."""
    subject = np.asarray(subject.cpu() if hasattr(subject, "cpu") else subject).astype(np.int64).ravel()
    poses = np.asarray(poses.detach().cpu() if hasattr(poses, "cpu") else poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(subject):
        raise RaymarchError(f"poses must be (B, 4, 4) with B = {len(subject)} subjects, got {poses.shape}")
    if len(subject) and (subject.min() < 0 or subject.max() >= n_subjects):
        raise RaymarchError(f"subject indices must be in [0, {n_subjects}), got {subject.min()}..{subject.max()}")
    return subject, poses


def _channels(channels, n: int) -> tuple[int, ...]:
    if channels is None:
        return tuple(range(n))
    chans = tuple(int(c) for c in channels)
    if not chans or min(chans) < 0 or max(chans) >= n:
        raise RaymarchError(f"channels must be indices in [0, {n}), got {channels!r}")
    return chans


class _Channels:
    """A fixed channel stack as the Dr.Jit renderer's ``materials`` (``quantity="density"``)."""

    def __init__(self, array: np.ndarray):
        self.array = array
        self.names = tuple(f"c{i}" for i in range(array.shape[0]))

    def partial_densities(self, hu):
        return self.array


class DrJitVolumes:
    """:class:`TorchVolumes`'s interface on the Dr.Jit renderer (:class:`sim.projection.drr.DRRRenderer`,
    exact Siddon traversal, many poses per kernel launch): the fast path on a CPU, where
    ``grid_sample`` over 3-D volumes is about 80x slower than Dr.Jit's compiled kernel. Same
    arguments (``step_fraction`` unused: Siddon has no step) and results, returned as torch
    tensors on ``device``; one renderer per subject and channel group, made on first use. A
    group of two channels is stored as 16-bit fixed point (``RenderSettings.storage="fixed16"``:
    one gather per step for both, each voxel within half a code of its value)."""

    def __init__(self, channels, affines, centers, geometry, *, device="cpu", dtype=None, scene: str = "cios_fusion",
                 step_fraction: float = 0.5):
        import torch

        if not (len(channels) == len(affines) == len(centers) >= 1):
            raise RaymarchError(f"one affine and one centre per volume: got {len(channels)} volumes, "
                                f"{len(affines)} affines, {len(centers)} centres")
        self.arrays = [np.asarray(c, np.float32) for c in channels]
        nc = self.arrays[0].shape[0] if self.arrays[0].ndim == 4 else None
        for n, a in enumerate(self.arrays):
            if a.ndim != 4 or a.shape[0] != nc or not np.all(np.isfinite(a)):
                raise RaymarchError(f"volume {n}: expected a finite (C={nc}, I, J, K) array, got shape {a.shape}")
        self.n_channels = nc
        self.volumes = [CTVolume(np.zeros(a.shape[1:], np.float32), np.asarray(af, np.float64), source=f"subject {n}")
                        for n, (a, af) in enumerate(zip(self.arrays, affines))]
        self.centers = [np.asarray(c, np.float64) for c in centers]
        self.geometry = geometry
        self.scene = scene
        self.device = torch.device(device)
        self.dtype = dtype or torch.float32
        self._renderers: dict[tuple[int, tuple[int, ...]], object] = {}

    @property
    def n_subjects(self) -> int:
        return len(self.arrays)

    def _renderer(self, u: int, chans: tuple[int, ...]):
        key = (u, chans)
        if key not in self._renderers:
            h, w = self.geometry.height, self.geometry.width
            # the density quantity divides by 10 (g/cm^3 mm -> g/cm^2): channels go in x 10 so the
            # result is the plain integral (channel unit x mm), as TorchVolumes returns it
            # two channels (the basis pair) share one 16+16-bit word per voxel: one gather per step
            storage = "fixed16" if len(chans) == 2 else "float32"
            self._renderers[key] = DRRRenderer(self.volumes[u], RenderSettings(scene=self.scene, size=(h, w),
                                                                              quantity="density", storage=storage),
                                               center_lps=self.centers[u], geometry=self.geometry,
                                               materials=_Channels(self.arrays[u][list(chans)] * 10.0))
        return self._renderers[key]

    def line_integrals(self, subject, poses, channels=None):
        """See :meth:`TorchVolumes.line_integrals`."""
        import torch

        subject, poses = _checked(subject, poses, self.n_subjects)
        chans = _channels(channels, self.n_channels)
        h, w = self.geometry.height, self.geometry.width
        out = np.zeros((len(subject), len(chans), h, w), np.float32)
        for u in np.unique(subject):
            rows = np.flatnonzero(subject == u)
            out[rows] = self._renderer(int(u), chans).render(poses[rows])
        return torch.from_numpy(out).to(device=self.device, dtype=self.dtype)


def volumes_for(device, *args, **kwargs):
    """The ray marcher for a torch device: :class:`DrJitVolumes` on the CPU, :class:`TorchVolumes`
    elsewhere (CUDA), with the same arguments."""
    import torch

    return (DrJitVolumes if torch.device(device).type == "cpu" else TorchVolumes)(*args, device=device, **kwargs)
