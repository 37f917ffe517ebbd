"""One preparation protocol (issue 54): a single class named ``Step`` in sim, learn and register,
and every preprocessing step of registration and of training one of its kind."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]


def test_there_is_one_class_named_step():
    homes = []
    for package in ("sim", "learn", "register"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ClassDef) and node.name == "Step":
                    homes.append(str(path.relative_to(ROOT)))
    assert homes == ["sim/prepare.py"]


def test_every_step_of_registration_and_training_follows_it():
    """Both registries' steps are sim.prepare.Step; each takes (image, mask) and gives (image, mask,
    measured) on its own kind of array, and its record names it."""
    from learn.preprocess import STEPS as LEARN_STEPS
    from register.xray.preprocess import STEPS as REGISTER_STEPS
    from sim.prepare import Step

    assert all(issubclass(cls, Step) for cls in (*LEARN_STEPS.values(), *REGISTER_STEPS.values()))
    image = np.linspace(1.0, 2.0, 64 * 64).reshape(64, 64)
    for name in ("median", "log", "normalize", "invert", "crop"):
        out, mask, measured = REGISTER_STEPS[name]().apply(image, None)
        assert out.shape[0] > 0 and isinstance(measured, dict)
        assert REGISTER_STEPS[name]().to_dict()["name"] == name
    batch = torch.from_numpy(image)[None, None].float()
    mask = torch.ones_like(batch, dtype=torch.bool)
    for name in ("log_correct", "normalize", "median", "sobel", "gaussian", "local_contrast"):
        step = LEARN_STEPS[name]()
        out, kept, measured = step.apply(batch, mask)
        assert torch.equal(out, step(batch)) and kept is mask and measured == {}
        assert step.to_dict()["name"] == name
