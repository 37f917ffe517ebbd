"""A DeepFluoro-layout file made from a CT: frames rendered by ctxreg at known poses.

The real file cannot be downloaded here, so the reader and ``ctxreg evaluate --deepfluoro`` are tested
on a file of the same layout (:mod:`register.datasets.deepfluoro`) whose truth is known by
construction: ctxreg poses, written through :func:`register.convert.to_deepfluoro` and a C-arm world
frame of our choosing, and frames rendered at DeepFluoro's geometry (SDD 1020 mm, a 298 mm detector
of 1536 px at 0.194 mm, optionally binned) with realistic physics (spectrum, detector, quantum
noise), a collimator border and raw intensities scaled to the real frames' flat field (65487).

Example::

    from sim import load_ct
    from register.datasets.deepfluoro_synthetic import SyntheticSettings, synthesize_deepfluoro

    ct = load_ct("pelvis.nii.gz")
    synthesize_deepfluoro("synthetic.h5", ct, [[0, 0, 0, 0, 0, 0], [10, 5, 0, 20, 0, 30]],
                          settings=SyntheticSettings(binning=8))
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from register.convert import to_deepfluoro
from register.datasets.deepfluoro import (I0_RAW, LANDMARK_NAMES, LABEL_NAMES, DeepFluoroError, ProjectionData,
                                          SpecimenData, projection_params_for, write_deepfluoro)
from sim.ct.anatomy import anatomy_center, bone_mask
from sim.projection.geometry import CArmGeometry, pose_from_params
from sim.physics.display import Collimator
from sim.physics.settings import PhysicsSettings
from sim.ct.volume import CTVolume
from sim.physics.imaging import XRayImager

__all__ = ["SyntheticSettings", "synthesize_deepfluoro", "canonical_lps", "synthetic_landmarks", "hemipelvis_labels",
           "DEEPFLUORO_WORLD_FROM_CAMERA"]

#: The synthetic file's ``proj-params/extrinsic`` (C-arm world -> camera): the world's origin half way
#: between source and detector on the principal ray, its axes turned 90 deg about the camera's y, so
#: that a reader that skipped the extrinsic would be off by metres and a right angle.
DEEPFLUORO_WORLD_FROM_CAMERA = np.array([[0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, -510.0],
                                         [0.0, 0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class SyntheticSettings:
    """How the frames are made.

    Attributes:
        binning (int, default 8): detector pixels per side of one synthetic pixel: 1536 / binning px at
            0.194 x binning mm (1 = DeepFluoro's full resolution; 8 = 192 px, for tests).
        physics (PhysicsSettings): the frames' physics (default: poly at 90 kV, 2 mAs, quantum noise).
        collimator (Collimator): the field; outside it the signal is the blades' transmission (default:
            a square field leaving a 50 px border at full resolution, as DiffPose crops).
        rot_180_every (int, default 0): flag every n-th frame ``rot-180-for-up`` (its image stored
            turned, as the file's documentation says); 0: none.
        sdd_mm (float, default 1020), sod_mm (float, default 700): the C-arm (Cios Fusion).
        landmarks (int, default 14): 3-D landmarks, named as DeepFluoro's.
        seed (int, default 0): noise and landmark choice.
    """

    binning: int = 8
    physics: PhysicsSettings = field(default_factory=lambda: PhysicsSettings(level="poly", kvp=90.0, mas=2.0,
                                                                              noise=True))
    collimator: Collimator = field(default_factory=lambda: Collimator(shape="rectangle",
                                                                      half_size=(0.5 - 50 / 1536, 0.5 - 50 / 1536)))
    rot_180_every: int = 0
    sdd_mm: float = 1020.0
    sod_mm: float = 700.0
    landmarks: int = 14
    seed: int = 0

    def __post_init__(self) -> None:
        if not (isinstance(self.binning, int) and self.binning >= 1 and 1536 % self.binning == 0
                and 1536 // self.binning >= 32):
            raise DeepFluoroError(f"binning must be a divisor of 1536 leaving at least 32 px, got {self.binning!r}")
        if self.rot_180_every < 0:
            raise DeepFluoroError(f"rot_180_every must be >= 0, got {self.rot_180_every}")
        if not 1 <= self.landmarks <= len(LANDMARK_NAMES):
            raise DeepFluoroError(f"landmarks must be 1..{len(LANDMARK_NAMES)}, got {self.landmarks}")

    def geometry(self) -> CArmGeometry:
        n = 1536 // self.binning
        return CArmGeometry(sdd_mm=self.sdd_mm, sod_mm=self.sod_mm, height=n, width=n,
                            pixel_spacing_mm=0.194 * self.binning)


def canonical_lps(volume: CTVolume) -> CTVolume:
    """The same CT with the identity as its direction (DeepFluoro's ``dir-mat``): axes permuted and
    flipped so that index ``i, j, k`` run along L, P, S. Only for axis-aligned CTs (the direction a
    signed permutation); the voxels and their LPS positions are unchanged."""
    A = volume.affine
    spacing = np.linalg.norm(A[:3, :3], axis=0)
    D = A[:3, :3] / spacing
    P = np.round(D)
    if np.abs(D - P).max() > 1e-6 or sorted(np.abs(P).sum(axis=0)) != [1, 1, 1]:
        raise DeepFluoroError(f"{volume.source}: an oblique CT (direction {np.round(D, 4).tolist()}); resample it "
                              "axis-aligned first")
    hu, labels = volume.hu, volume.labels
    index = np.zeros(3)  # voxel index (old) of the new origin
    for axis in range(3):
        lps = int(np.argmax(np.abs(P[:, axis])))
        if P[lps, axis] < 0:
            hu = np.flip(hu, axis)
            labels = None if labels is None else np.flip(labels, axis)
            index[axis] = volume.shape[axis] - 1
    order = [int(np.argmax(np.abs(P[:, axis]))) for axis in range(3)]  # LPS axis of each index axis
    perm = [order.index(k) for k in range(3)]
    hu = np.ascontiguousarray(np.transpose(hu, perm))
    labels = None if labels is None else np.ascontiguousarray(np.transpose(labels, perm))
    new = np.eye(4)
    new[:3, :3] = np.diag(spacing[perm])
    new[:3, 3] = (A @ np.r_[index, 1.0])[:3]
    return CTVolume(hu=hu, affine=new, source=volume.source, labels=labels)


def hemipelvis_labels(volume: CTVolume, center_lps) -> np.ndarray:
    """``(I, J, K)`` int32 labels of the bone: 1 (left-hemipelvis) where LPS x > the centre's, 2
    (right-hemipelvis) elsewhere: a stand-in for DeepFluoro's segmentation whose centroid is the bone's."""
    bone = bone_mask(volume)
    i = np.arange(volume.shape[0], dtype=np.float64)
    x = volume.affine[0, 0] * i + volume.affine[0, 3]  # canonical grid: x depends on i only
    left = (x > float(center_lps[0]))[:, None, None]
    return np.where(bone, np.where(left, 1, 2), 0).astype(np.int32)


def synthetic_landmarks(volume: CTVolume, center_lps, count: int = 14, seed: int = 0,
                        radius_mm: float = 90.0) -> dict[str, np.ndarray]:
    """``{name: (3,) LPS mm}``: ``count`` bone voxel centres within ``radius_mm`` of ``center_lps``
    (the pelvis, where DeepFluoro's landmarks lie), spread by farthest-point sampling from a seeded
    start, named as DeepFluoro's landmarks (the names only: they are not those anatomical points)."""
    ijk = np.argwhere(bone_mask(volume))
    rng = np.random.default_rng(seed)
    pts = volume.voxel_to_lps(ijk.astype(np.float64))
    pts = pts[np.linalg.norm(pts - np.asarray(center_lps, np.float64), axis=1) <= radius_mm]
    if len(pts) < count:
        raise DeepFluoroError(f"{volume.source}: fewer than {count} bone voxels within {radius_mm:g} mm of the centre")
    if len(pts) > 20000:
        pts = pts[rng.choice(len(pts), 20000, replace=False)]
    chosen = [int(rng.integers(len(pts)))]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(pts - pts[chosen[-1]], axis=1))
    return {name: pts[k].copy() for name, k in zip(LANDMARK_NAMES, chosen)}


def synthesize_deepfluoro(path: str | os.PathLike, volume: CTVolume, params: Sequence[Sequence[float]], *,
                          specimen_id: str = "17-1882", settings: SyntheticSettings | None = None,
                          extrinsic: np.ndarray = DEEPFLUORO_WORLD_FROM_CAMERA,
                          log: Callable[[str], None] | None = None) -> dict:
    """Write a one-specimen DeepFluoro-layout file of ``volume`` with a frame at each pose.

    Args:
        path: the HDF5 file to write (atomically).
        volume: the CT (axis-aligned; written with the identity direction, :func:`canonical_lps`).
        params: ``(N, 6)`` ctxreg pose parameters (deg, mm; :func:`sim.projection.geometry.pose_from_params` at
            ``settings.sod_mm``) about the bone centroid.
        specimen_id: the specimen group's name.
        settings: :class:`SyntheticSettings`.
        extrinsic: ``(4, 4)`` the file's C-arm world -> camera.

    Returns ``{"path", "center_lps" (3,), "poses" (N, 4, 4) ctxreg truth, "geometry", "landmarks_lps"}``.
    """

    s = settings or SyntheticSettings()
    log = log or (lambda line: None)
    params = np.asarray(params, np.float64).reshape(-1, 6)
    vol = canonical_lps(volume)
    center = anatomy_center(vol)
    vol = replace(vol, labels=hemipelvis_labels(vol, center))
    landmarks = synthetic_landmarks(vol, center, s.landmarks, s.seed)
    g = s.geometry()
    imager = XRayImager(vol, replace(s.physics, seed=s.seed), geometry=g, center_lps=center)
    names = list(landmarks)
    X = np.array([landmarks[n] for n in names])
    frames, poses = [], pose_from_params(params, g.sod_mm).reshape(-1, 4, 4)
    for i, T in enumerate(poses):
        rot = bool(s.rot_180_every) and i % s.rot_180_every == s.rot_180_every - 1
        raw = imager.render(T, seed=s.seed * 100_003 + i)["raw"][0].astype(np.float64)
        intensity = s.collimator.apply(raw / imager.flat * I0_RAW)
        stored = intensity[::-1, :] if rot else intensity[:, ::-1]
        E_lps, K = to_deepfluoro(T, g, center, rot_180_for_up=rot)
        h = np.c_[X, np.ones(len(X))] @ (K @ E_lps[:3]).T
        uv = h[:, :2] / h[:, 2:]
        cam_to_vol = np.linalg.inv(E_lps) @ extrinsic
        frames.append(ProjectionData(pixels=stored.astype(np.float32), cam_to_pelvis_vol=cam_to_vol,
                                     landmarks_px=dict(zip(names, uv)), rot_180_for_up=rot))
        log(f"frame {i + 1}/{len(poses)} rendered")
    spec = SpecimenData(id=specimen_id, volume=vol, landmarks_lps=landmarks, projections=frames,
                        labels_def=dict(LABEL_NAMES))
    write_deepfluoro(path, projection_params_for(g, extrinsic=extrinsic), [spec])
    return {"path": Path(path), "center_lps": center, "poses": poses, "geometry": g, "landmarks_lps": landmarks}
