"""The CI-sized fixed set of outputs (scripts/same_outputs.py small) is the committed one: bit for bit
on the machine it was made on, within the last bits on another CPU.

A refactoring must not change what the project computes: renders of the built-in phantom (line and
poly), the imaging chain (per-pair draws of every scatter kind, a fixed display chain), the
preparation of training targets (a NumPy pair and a torch batch), a CMA-ES registration and a
training step. ``tests/data/same_outputs_small.npz`` holds them as this code made them (the full
set, with the demo, an evaluation and two trainings, is ``scripts/same_outputs.py make`` /
``compare``). A change that alters outputs on purpose writes the set again
(``.venv/bin/python scripts/same_outputs.py small --write``) and says why in its commit.

Tolerance: none on the machine the set was made on (it records it: the CPU and its vector
instructions, Dr.Jit's and NumPy's versions). Each output is made in a fresh process with one thread
(``OMP_NUM_THREADS=1`` whatever the caller's environment: the renders' last bits follow the thread
count, and an earlier test of the session may have set it) and one torch thread, from fixed seeds, without the Mitsuba-traced tool bank (whose chords differ from one process
to the next in their last bits); the set was made three times in separate processes, beside a
training run, and was the same each time, and twice more at once on another machine. On another
CPU, Dr.Jit's LLVM backend compiles the renders for other vector instructions, which round a few
values differently (2 of 2304 render values, 4.8e-7; a display value one count off downstream; the
32 px CMA-ES registration 0.1-0.57 deg / 0.8-1.2 mm apart): there the set is compared within those last bits
(``small_differences``' rules), and a change of what the code computes still shows.
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
        outputs = {k: ref[k].copy() for k in ref.files if k not in module.SMALL_META}
    assert module.small_differences(outputs, exact=True) == []
    outputs["chain_fixed"][3, 4] += 1
    outputs["registration_pose"] = outputs["registration_pose"] + 1e-12
    del outputs["render_poly"]
    outputs["extra"] = np.zeros(2)
    lines = module.small_differences(outputs, exact=True)
    assert lines == ["extra: only in this run", "render_poly: only in the committed set",
                     "chain_fixed: 1 of 2304 values differ, at most 1",
                     "registration_pose: 16 of 16 values differ, at most 1.02e-12"]


def test_on_another_cpu_the_last_bits_may_differ_and_a_real_change_still_shows():
    module = _script()
    with np.load(module.SMALL) as ref:
        outputs = {k: ref[k].copy() for k in ref.files if k not in module.SMALL_META}
    outputs["render_line"][5, 7] = np.nextafter(outputs["render_line"][5, 7], np.float32(np.inf))  # one ulp
    outputs["chain_fixed"][3, 4] += 1  # one count, one value
    outputs["registration_pose"][2, 3] += 1.2  # mm in depth: CMA-ES's other path
    outputs["train_step_sha256"][0] ^= 1
    assert module.small_differences(outputs, exact=False) == []
    outputs["render_line"] = outputs["render_line"] * np.float32(1.01)  # a change of what is computed
    outputs["registration_pose"][0, 3] += 5.0
    assert [line.split(":")[0] for line in module.small_differences(outputs, exact=False)] == [
        "registration_pose", "render_line"]
