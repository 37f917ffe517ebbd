"""The CI-sized fixed set of outputs (scripts/same_outputs.py small) is bit for bit the committed one.

A refactoring must not change what the project computes: renders of the built-in phantom (line and
poly), the imaging chain (per-pair draws of every scatter kind, a fixed display chain), the
preparation of training targets (a NumPy pair and a torch batch), a CMA-ES registration and a
training step. ``tests/data/same_outputs_small.npz`` holds them as this code made them (the full
set, with the demo, an evaluation and two trainings, is ``scripts/same_outputs.py make`` /
``compare``). A change that alters outputs on purpose writes the set again
(``.venv/bin/python scripts/same_outputs.py small --write``) and says why in its commit.

Tolerance: none. Each output is made in a fresh process with one torch thread, from fixed seeds,
without the Mitsuba-traced tool bank (whose chords differ from one process to the next in their
last bits); the set was made three times in separate processes, beside a training run, and was
the same each time.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import numpy as np

from tests.conftest import REPO

SCRIPT = REPO / "scripts" / "same_outputs.py"


def _script():
    spec = importlib.util.spec_from_file_location("same_outputs", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_small_set_is_the_committed_one_bit_for_bit():
    r = subprocess.run([sys.executable, str(SCRIPT), "small"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]


def test_a_changed_value_is_named(tmp_path):
    module = _script()
    with np.load(module.SMALL) as ref:
        outputs = {k: ref[k].copy() for k in ref.files}
    assert module.small_differences(outputs) == []
    outputs["chain_fixed"][3, 4] += 1
    outputs["registration_pose"] = outputs["registration_pose"] + 1e-12
    del outputs["render_poly"]
    outputs["extra"] = np.zeros(2)
    lines = module.small_differences(outputs)
    assert lines == ["extra: only in this run", "render_poly: only in the committed set",
                     "chain_fixed: 1 of 2304 values differ, at most 1",
                     "registration_pose: 16 of 16 values differ, at most 1.02e-12"]
