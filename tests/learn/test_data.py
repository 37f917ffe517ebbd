"""Training pairs from a campaign: same subject, exact labels, no leakage between splits."""

from __future__ import annotations

import numpy as np
import pytest
import torch

def test_pairs_come_from_one_subject_of_the_split_with_exact_labels(campaign):
    from learn.data import PairDataset
    from learn.labels import geodesic_label

    ds = PairDataset(campaign, "train", pairs=20, seed=1)
    train_subjects = set(campaign.splits["train"])
    for k in range(len(ds)):
        a, b = (int(i) for i in ds.pairs[k])
        ia, ib = campaign[a], campaign[b]
        assert ia["subject"] == ib["subject"] and ia["subject"] in train_subjects
        target, current, label = ds[k]
        assert target.shape == current.shape == (1, 32, 32) and label.shape == (6,)
        np.testing.assert_array_equal(target[0].numpy(), ia["images"]["line"])
        expected = ds.normalizer.normalize(geodesic_label(torch.from_numpy(ia["pose"]), torch.from_numpy(ib["pose"])))
        torch.testing.assert_close(label, expected.to(torch.float32))


def test_epochs_are_seeded(campaign):
    from learn.data import PairDataset

    a = PairDataset(campaign, "test", pairs=10, seed=7)
    b = PairDataset(campaign, "test", pairs=10, seed=7)
    np.testing.assert_array_equal(a.pairs, b.pairs)
    first = a.pairs.copy()
    a.set_epoch(1)
    assert not np.array_equal(first, a.pairs)


def test_bad_requests_are_named(campaign):
    from learn.data import PairDataset, PairDatasetError

    with pytest.raises(PairDatasetError, match="val"):
        PairDataset(campaign, "val", pairs=4)
    with pytest.raises(PairDatasetError, match="physics 'poly'"):
        PairDataset(campaign, "train", pairs=4, physics="poly")
