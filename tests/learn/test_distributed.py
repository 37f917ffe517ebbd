"""``ctxreg train`` under ``torchrun`` (learn/distributed.py): two CPU processes (gloo) with the global
batch split between them train the same weights as one process on the whole batch.

Truth: the single-process run of the same configuration. With the backbone frozen (eval mode, so
BatchNorm's statistics do not depend on the batch) DDP's averaged gradient is the mean over the
whole batch; only the order of floating-point sums differs. Adam moves every weight by up to the
learning rate (1e-3) per step whatever its gradient's size, and divides by the root of the second
moment, which turns the last bits of a near-zero gradient into a visible part of a step: after 4
steps the weights agree within 2e-5 (2 % of one step; measured 8e-6). A wrong share (both ranks on
the first half of the batch) fails it (checked). Rank 0 alone writes the checkpoint and
the log, and ``--resume`` continues a two-process run.
"""

from __future__ import annotations

import csv
import os
import re
import subprocess
from dataclasses import asdict, replace
from pathlib import Path

import pytest
import torch

from tests.conftest import REPO
from tests.learn.test_train import config

TORCHRUN = REPO / ".venv" / "bin" / "torchrun"


def _write_config(cfg, path: Path) -> Path:
    from sim.core.atomic import toml_text

    table = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items() if v is not None}
    path.write_text(toml_text({"train": table}))
    return path


def _torchrun(config_path: Path, *extra: str):
    if not TORCHRUN.exists():
        pytest.skip("torchrun not found in .venv")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([str(TORCHRUN), "--standalone", "--nproc-per-node", "2", "-m", "register.cli", "train",
                           str(config_path), *extra], capture_output=True, text=True, cwd=REPO, env=env, timeout=900)


def test_two_processes_train_the_weights_of_one(campaign, tmp_path):
    import learn.train as tr
    from learn.checkpoint import load_checkpoint

    one = config(campaign, tmp_path / "one", iterations=4, val_every=2, checkpoint_every=2, freeze_backbone=True)
    torch.set_num_threads(1)
    tr.train(one, log=lambda *_: None)
    ref = load_checkpoint(tmp_path / "one" / "checkpoint.pt")

    two = replace(one, out=str(tmp_path / "two"))
    r = _torchrun(_write_config(two, tmp_path / "two.toml"))
    assert r.returncode == 0, r.stderr[-3000:]
    got = load_checkpoint(tmp_path / "two" / "checkpoint.pt")
    assert got.iteration == 4
    for key, value in ref.model_state.items():
        torch.testing.assert_close(got.model_state[key], value, rtol=0, atol=2e-5, msg=key)
    rows = list(csv.DictReader(open(tmp_path / "two" / "log.csv")))
    assert [int(r["iteration"]) for r in rows] == [2, 4]  # one log, rank 0's

    # a two-process run of 2 iterations, resumed by two processes to 4
    first = replace(one, out=str(tmp_path / "resumed"), iterations=2)
    r = _torchrun(_write_config(first, tmp_path / "first.toml"))
    assert r.returncode == 0, r.stderr[-3000:]
    r = _ctxreg_train(_write_config(replace(first, iterations=4), tmp_path / "resumed.toml"), "--resume",
                      "--procs", "2")  # resumed by ctxreg train's own launcher
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    again = load_checkpoint(tmp_path / "resumed" / "checkpoint.pt")
    assert again.iteration == 4
    for key, value in ref.model_state.items():
        torch.testing.assert_close(again.model_state[key], value, rtol=0, atol=2e-5, msg=key)


def _ctxreg_train(config_path: Path, *extra: str):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([str(REPO / ".venv" / "bin" / "python"), "-m", "register.cli", "train", str(config_path),
                           *extra], capture_output=True, text=True, cwd=REPO, env=env, timeout=900)


def test_a_batch_that_does_not_divide_is_refused_once(campaign, tmp_path):
    """Under torchrun every rank refuses, rank 0 alone prints it; ctxreg train --procs refuses it
    before any process starts: one line, exit 2, no traceback."""
    cfg = config(campaign, tmp_path / "odd", batch_size=3, iterations=2)
    path = _write_config(cfg, tmp_path / "odd.toml")
    r = _torchrun(path)
    assert r.returncode != 0
    assert r.stderr.count("does not divide among 2 processes") == 1, r.stderr[-3000:]
    r = _ctxreg_train(path, "--procs", "2")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == ["ctxreg train: error: train.batch_size 3 does not divide among 2 processes "
                                             "(--procs or torchrun --nproc-per-node): give a multiple of 2"]


def test_a_refusal_inside_the_ranks_is_printed_once_and_ends_in_one_line(campaign, tmp_path):
    """A dataset that only the ranks open (not a campaign folder): rank 0 names it once, the
    launcher's failure is one line with the ranks and exit code, no traceback."""
    empty = tmp_path / "not_a_campaign"
    empty.mkdir()
    cfg = replace(config(campaign, tmp_path / "run", iterations=2), dataset=str(empty))
    r = _ctxreg_train(_write_config(cfg, tmp_path / "bad.toml"), "--procs", "2")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-3000:]
    errors = [line for line in r.stderr.splitlines() if line.startswith("ctxreg train: error:")]
    assert len(errors) == 2 and str(empty) in errors[0], r.stderr[-3000:]
    # both ranks refuse; where one exits first, the launcher stops the other (SIGTERM) before it does
    assert re.fullmatch(r"ctxreg train: error: 2 processes: (ranks 0, 1 ended with exit code 2|rank [01] ended with "
                        r"exit code 2; rank [01] stopped by the launcher) \(the message above says why\)",
                        errors[1]), errors[1]
