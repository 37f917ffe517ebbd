"""A small campaign shared by the learning tests (two 5 mm phantoms, 6 images each, 32 x 32)."""

from __future__ import annotations

import pytest

CAMPAIGN = """
[campaign]
name = "pairs"
seed = 3
images_per_ct = 6
shard_size = 3
[scene]
size = [32, 32]
[split]
train = 0.5
val = 0.0
test = 0.5
[[cts]]
path = "{ct0}"
split = "train"
[[cts]]
path = "{ct1}"
split = "test"
"""


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    from sim.campaign import load_campaign, open_dataset, run_campaign
    from sim.ct.phantom import write_phantom_nifti

    d = tmp_path_factory.mktemp("pairs")
    cts = []
    for seed in (4, 5):
        p = d / f"p{seed}.nii.gz"
        write_phantom_nifti(p, seed, spacing_mm=5.0)
        cts.append(p)
    (d / "c.toml").write_text(CAMPAIGN.format(ct0=cts[0], ct1=cts[1]))
    run_campaign(load_campaign(d / "c.toml"), d / "out", progress=False)
    data = open_dataset(d / "out")
    yield data
    data.close()


def train_killed_after_first_checkpoint(cfg, monkeypatch) -> None:
    """Run ``learn.train.train(cfg)`` and kill it (KeyboardInterrupt) right after its first checkpoint."""
    import learn.train as tr

    real_save = tr._save_checkpoint

    def save_then_die(path, payload):
        real_save(path, payload)
        raise KeyboardInterrupt

    monkeypatch.setattr(tr, "_save_checkpoint", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        tr.train(cfg, log=lambda *_: None)
    monkeypatch.setattr(tr, "_save_checkpoint", real_save)


def log_rows(path, *, times: bool = False) -> list[dict]:
    """The rows of a training's ``log.csv`` (``path``: the file or its run folder), without the
    ``elapsed_s`` column (wall seconds differ between runs that take the same steps) unless
    ``times``."""
    import csv
    from pathlib import Path

    path = Path(path)
    with open(path / "log.csv" if path.is_dir() else path) as f:
        rows = list(csv.DictReader(f))
    return rows if times else [{k: v for k, v in r.items() if k != "elapsed_s"} for r in rows]
