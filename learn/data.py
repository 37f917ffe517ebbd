"""Training pairs from campaign datasets: (target image, current image, geodesic label).

A pair takes two images of the same subject (CT or virtual patient) from a campaign folder
written by ``ctxreg simulate`` (:mod:`sim.campaign.dataset`): image A is the target, image B the
DRR at the "current" pose, and the label is ``g = -2 log_{T_B}(T_A)`` (:func:`learn.labels.geodesic_label`)
in normalised units (:class:`learn.labels.LabelNormalizer`). Pairs never cross subjects, and a
split's pairs come from that split's subjects only, so no CT leaks between splits.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from learn.labels import LabelNormalizer, geodesic_label, sample_pairs
from sim.core.errors import InputError
from sim.core.seeds import KIND_EPOCH_PAIRS, rng_for


class PairDatasetError(InputError):
    """A campaign split cannot provide pairs; the message says why."""


class PairDataset(Dataset):
    """Pairs of one split of a campaign, resampled every epoch from a seed.

    Args:
        data: an open :class:`sim.campaign.dataset.CampaignDataset`.
        split: ``"train"``, ``"val"`` or ``"test"``.
        pairs: pairs per epoch.
        physics: which ``images/<physics>`` to use for the target (default: the first); the
            current image always uses ``current_physics`` (default: the same), so a domain-gap
            study can pair a realistic target with a simple DRR.
        transform: a callable on ``(2, 1, H, W)`` float32 tensors (e.g. :class:`learn.preprocess.Compose`).
        normalizer: label scaling (default :class:`LabelNormalizer()`).
        seed: the pairs of epoch ``e`` come from ``SeedSequence(seed, spawn_key=(20, e))``.

    Items: ``(target (1, H, W), current (1, H, W), label (6,))`` float32 tensors.
    """

    def __init__(self, data, split: str, *, pairs: int, physics: str | None = None,
                 current_physics: str | None = None, transform=None, normalizer: LabelNormalizer | None = None,
                 seed: int = 0):
        self.data = data
        self.indices = np.asarray(data.indices(split), dtype=np.int64)
        if len(self.indices) < 2:
            raise PairDatasetError(f"split {split!r} has {len(self.indices)} images; pairs need at least 2 "
                                   f"(splits here: {sorted(data.splits)})")
        names = data.physics
        self.physics = physics or names[0]
        self.current_physics = current_physics or self.physics
        for p in (self.physics, self.current_physics):
            if p not in names:
                raise PairDatasetError(f"physics {p!r} is not in the campaign (it has {names})")
        self.split = split
        self.n_pairs = int(pairs)
        if self.n_pairs < 1:
            raise PairDatasetError(f"pairs must be >= 1, got {pairs}")
        self.transform = transform
        self.normalizer = normalizer or LabelNormalizer()
        self.seed = seed
        self.subjects = np.array([data[int(i)]["subject"] for i in self.indices])
        self.set_epoch(0)

    def set_epoch(self, epoch: int) -> None:
        """Draw this epoch's pairs (deterministic for ``seed`` and ``epoch``)."""

        rng = rng_for(self.seed, KIND_EPOCH_PAIRS, epoch)
        local = sample_pairs(len(self.indices), self.n_pairs, rng, groups=self.subjects)
        self.pairs = self.indices[local]

    def __len__(self) -> int:
        return self.n_pairs

    def __getitem__(self, k: int):
        a_idx, b_idx = (int(v) for v in self.pairs[k])
        a, b = self.data[a_idx], self.data[b_idx]
        images = torch.from_numpy(np.stack([a["images"][self.physics], b["images"][self.current_physics]])
                                  .astype(np.float32))[:, None]  # (2, 1, H, W)
        if self.transform is not None:
            images = self.transform(images)
        g = geodesic_label(torch.from_numpy(a["pose"]), torch.from_numpy(b["pose"]))
        label = self.normalizer.normalize(g).to(torch.float32)
        return images[0], images[1], label
