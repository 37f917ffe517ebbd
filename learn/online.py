"""Training pairs rendered on the fly from a campaign file: unlimited pairs, near pairs included.

A campaign folder (:mod:`learn.data`) holds a fixed set of images, so its pairs are drawn from
one pose distribution: two independent poses of the original protocol are on average ~45 deg
and ~120 mm apart, and pairs closer than a few degrees, the ones that decide where the
registration iteration comes to rest, are rare. Rendering is cheap here (a 128 x 128 DRR of the
3 mm pelvis CT takes about 1 ms in a batch), so :class:`OnlinePairs` renders every batch
from the campaign *file* instead: the same subjects (CTs and their virtual patients, the same
seeds, so the same anatomies as ``ctxreg simulate``), the same scene and image size, the first
physics entry (or the named ones: targets and currents may differ), and pairs drawn as follows (all angles in degrees, lengths in mm):

* target pose ``T_A``: from the campaign's pose distribution ``[poses]``;
* current pose ``T_B``: with probability ``1 - near.fraction`` an independent draw from the
  same distribution (far pairs, as in the original); otherwise a *near* pair
  ``T_B = T_A o Exp(delta)`` (:func:`learn.labels.apply_update`, rotation about the anatomy
  centre) whose rotation part has a uniformly random axis and an angle log-uniform in
  ``near.rot_deg``, and whose translation part has a uniformly random direction and a length
  log-uniform in ``near.trans_mm``.

Every draw of batch ``k`` comes from ``SeedSequence(seed, spawn_key=(40, k))``: a batch is a
function of the seed and its index only, so a resumed training run takes the same steps.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np
import torch

from learn.labels import LabelNormalizer, apply_update, geodesic_label
from sim.errors import InputError
from sim.seeds import KIND_BATCH, KIND_BATCH_NOISE  # batch k: (KIND_BATCH, k); its noise: (KIND_BATCH_NOISE, k, u[, 1])


class OnlinePairsError(InputError):
    """Online pairs cannot be drawn; the message names the setting and the problem."""


def _range(value, name: str, unit: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise OnlinePairsError(f"{name} must be [low, high] in {unit}, got {value!r}") from None
    if not (0 < lo <= hi and math.isfinite(hi)):
        raise OnlinePairsError(f"{name} must satisfy 0 < low <= high ({unit}), got [{lo}, {hi}]")
    return lo, hi


@dataclass(frozen=True)
class NearPairs:
    """How often and how near the current pose is drawn around the target (see the module doc).

    Attributes:
        fraction: share of near pairs in [0, 1] (0: the original's independent pairs only).
        rot_deg: ``(low, high)`` deg, the log-uniform range of the rotation offset's angle.
        trans_mm: ``(low, high)`` mm, the log-uniform range of the translation offset's length.
    """

    fraction: float = 0.5
    rot_deg: tuple[float, float] = (0.5, 20.0)
    trans_mm: tuple[float, float] = (1.0, 40.0)

    def __post_init__(self) -> None:
        if not (isinstance(self.fraction, numbers.Real) and 0.0 <= self.fraction <= 1.0):
            raise OnlinePairsError(f"near fraction must be in [0, 1], got {self.fraction!r}")
        object.__setattr__(self, "rot_deg", _range(self.rot_deg, "near rot_deg", "deg"))
        object.__setattr__(self, "trans_mm", _range(self.trans_mm, "near trans_mm", "mm"))

    def offsets(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n, 6)`` offsets ``delta`` (rad, mm) with the module doc's distribution."""
        def directions():
            v = rng.standard_normal((n, 3))
            return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)

        def log_uniform(lo, hi):
            return np.exp(rng.uniform(math.log(lo), math.log(hi), n))

        rot = directions() * np.radians(log_uniform(*self.rot_deg))[:, None]
        trans = directions() * log_uniform(*self.trans_mm)[:, None]
        return np.concatenate([rot, trans], axis=1)


class OnlinePairs:
    """Batches of (target, current, label) rendered from a campaign's subjects of one split.

    Args:
        cfg: a :class:`sim.campaign.config.CampaignConfig` (``load_campaign(path)``).
        split: ``"train"``, ``"val"`` or ``"test"``; only that split's subjects are used.
        near: :class:`NearPairs` (default: half near pairs).
        transform: a callable on ``(2 B, 1, H, W)`` float32 tensors (targets then currents).
        normalizer: label scaling (default :class:`LabelNormalizer()`).
        seed: batch ``k`` draws from ``SeedSequence(seed, spawn_key=(40, k))``.
        physics: name of the campaign's ``[[physics]]`` entry of the target images (default: the
            first entry).
        current_physics: name of the entry of the current images (default: as the targets). With
            two entries, e.g. ``full`` targets (scatter, noise) and noise-free ``poly`` currents,
            the pairs look like a registration's: a realistic X-ray against moving images.
        subjects_per_batch: draw each batch's pairs from this many distinct subjects (uniformly
            among them) instead of a subject per pair (default None). Rendering costs a fixed
            amount per subject and batch, a lot for ``full`` images (one Monte Carlo run per
            subject): 4 subjects instead of ~16 makes a 32-pair batch about 3x cheaper.

    ``batch(k, n)`` returns ``target (n, 1, H, W)``, ``current (n, 1, H, W)`` float32 and the
    normalised label ``(n, 6)`` float32. Subjects are loaded (and virtual patients built) on first
    use and kept: about 6 MB of voxels per subject for the 3 mm pelvis CT.
    """

    def __init__(self, cfg, split: str, *, near: NearPairs | None = None, transform=None,
                 normalizer: LabelNormalizer | None = None, seed: int = 0, physics: str | None = None,
                 current_physics: str | None = None, subjects_per_batch: int | None = None):
        self.cfg = cfg
        entries = {p.name: p for p in cfg.physics}
        for key, name in (("physics", physics), ("current_physics", current_physics)):
            if name is not None and name not in entries:
                raise OnlinePairsError(f"{key} {name!r} is not a physics entry of campaign {cfg.name!r} "
                                       f"(it has {sorted(entries)})")
        #: the campaign physics entries of the target and of the current images
        self.target_entry = entries[physics] if physics is not None else cfg.physics[0]
        self.current_entry = entries[current_physics] if current_physics is not None else self.target_entry
        self.split = split
        self.subjects = [s for s in cfg.subjects() if s.split == split]
        if not self.subjects:
            splits = sorted({s.split for s in cfg.subjects()})
            raise OnlinePairsError(f"campaign {cfg.name!r} has no subject in split {split!r} (it has {splits})")
        self.near = near if near is not None else NearPairs()
        if subjects_per_batch is not None and (isinstance(subjects_per_batch, bool)
                                               or not isinstance(subjects_per_batch, numbers.Integral)
                                               or not 1 <= subjects_per_batch <= len(self.subjects)):
            raise OnlinePairsError(f"subjects_per_batch must be an integer in [1, {len(self.subjects)}] (the "
                                   f"{split} subjects), got {subjects_per_batch!r}")
        self.subjects_per_batch = subjects_per_batch
        self.transform = transform
        self.normalizer = normalizer or LabelNormalizer()
        self.seed = int(seed)
        self._contexts: dict[int, object] = {}

    def context(self, k: int):
        """The :class:`sim.campaign.runner.SubjectContext` of this split's subject ``k`` (cached)."""
        if k not in self._contexts:
            from sim.campaign.runner import SubjectContext

            self._contexts[k] = SubjectContext(self.cfg, self.subjects[k])
        return self._contexts[k]

    def draw(self, k: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Batch ``k``'s draws: subject per pair ``(n,)``, ``T_A`` and ``T_B`` ``(n, 4, 4)`` (mm)."""
        from sim.seeds import rng_for
        from sim.geometry import pose_from_params

        if n < 1:
            raise OnlinePairsError(f"batch size must be >= 1, got {n}")
        rng = rng_for(self.seed, KIND_BATCH, int(k))
        if self.subjects_per_batch is None:
            subject = rng.integers(0, len(self.subjects), n)
        else:
            chosen = rng.choice(len(self.subjects), self.subjects_per_batch, replace=False)
            subject = chosen[rng.integers(0, len(chosen), n)]
        sod = self.context(0).renderers[self.target_entry.name].geometry.sod_mm
        T_a = pose_from_params(self.cfg.poses.sample(rng, n), sod)
        T_b = pose_from_params(self.cfg.poses.sample(rng, n), sod)
        near = rng.random(n) < self.near.fraction
        delta = self.near.offsets(rng, n)
        if near.any():
            # T_B = T_A o Exp(delta): apply_update moves along -g, so pass g = -delta with step 1
            T_b[near] = apply_update(T_a[near], -delta[near], 1.0)
        return subject, T_a, T_b

    def batch(self, k: int, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Render batch ``k`` of ``n`` pairs; see the class doc for the shapes."""
        subject, T_a, T_b = self.draw(k, n)
        from sim.seeds import rng_for

        h, w = self.cfg.scene.size
        images = np.empty((2, n, h, w), np.float32)

        def render(entry, u, poses, stream):
            renderer = self.context(int(u)).renderers[entry.name]
            if entry.level in ("poly", "full"):  # fresh noise every batch, reproducible from (seed, k, u)
                key = (KIND_BATCH_NOISE, int(k), int(u)) + stream
                return renderer.render(poses, seed=int(rng_for(self.seed, *key).integers(2**63)))
            return renderer.render(poses)

        for u in np.unique(subject):
            rows = np.flatnonzero(subject == u)
            if self.current_entry is self.target_entry:  # one launch for both images of the pairs
                out = render(self.target_entry, u, np.concatenate([T_a[rows], T_b[rows]]), ())
                images[0, rows], images[1, rows] = out[:len(rows)], out[len(rows):]
            else:
                images[0, rows] = render(self.target_entry, u, T_a[rows], ())
                images[1, rows] = render(self.current_entry, u, T_b[rows], (1,))
        x = torch.from_numpy(images.reshape(2 * n, 1, h, w))
        if self.transform is not None:
            x = self.transform(x)
        label = self.normalizer.normalize(geodesic_label(torch.from_numpy(T_a), torch.from_numpy(T_b)))
        return x[:n], x[n:], label.to(torch.float32)
