"""``ctxreg adapt`` at a tiny size: the model folder and its card, resume, the refusals, and the
warning for a model adapted to another CT. The phantom CT (4 mm) stands for the user's CT; the
base network is the shipped default (a realistic model, as a user would adapt)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from learn.adapt import ADAPT, AdaptError, adapt, adapted_ct_warning
from learn.shipped import DEFAULT_ADAPT_BASE, load_card
from sim.ct.cache import ct_hash
from sim.ct.phantom import write_phantom_nifti

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: A tiny adaptation: 1 virtual patient, batches of 4, 8 validation pairs, a validation every 2 steps.
TINY = replace(ADAPT, virtual_patients=1, batch_size=4, val_pairs=8, val_every=2)
#: A few seconds of training (the first step takes longer: it builds the pair tables).
MINUTES = 0.05


@pytest.fixture(scope="module")
def cts(tmp_path_factory):
    folder = tmp_path_factory.mktemp("adapt_cts")
    a, b = folder / "patient_a.nii.gz", folder / "patient_b.nii.gz"
    write_phantom_nifti(a, 1, spacing_mm=4.0)
    write_phantom_nifti(b, 2, spacing_mm=4.0)
    return a, b


@pytest.fixture(scope="module")
def adapted(cts, tmp_path_factory):
    out = tmp_path_factory.mktemp("adapted") / "patient_a"
    lines = []
    adapt(cts[0], out, minutes=MINUTES, device="cpu", settings=TINY, log=lines.append)
    return out, lines


def test_the_model_folder_and_its_card(adapted, cts):
    out, lines = adapted
    card = load_card(out)  # checked against its schema and its weights
    a = card["adaptation"]
    assert a["ct_hash"] == ct_hash(cts[0]) and a["base"] == DEFAULT_ADAPT_BASE == "pelvis_base"
    assert a["pairs_seen"] == card["training"]["iterations"] * TINY.batch_size > 0
    assert a["curve_columns"] == ["minutes", "pairs", "rotation_deg", "translation_mm"]
    curve = a["curve"]
    assert curve[0][:2] == [0.0, 0] and len(curve) >= 2  # the base network first, then the run's validations
    assert all(later[0] >= earlier[0] and later[1] > earlier[1] for earlier, later in zip(curve, curve[1:]))
    held = card["accuracy"]["held_out_poses"]
    assert held["rotation_deg_mean"] == curve[-1][2] and held["pairs"] == TINY.val_pairs
    record = json.loads((out / "adapt.json").read_text())
    assert record["before"]["rotation_deg"] == pytest.approx(curve[0][2], abs=1e-3)
    assert any("before adaptation" in line for line in lines)
    assert any(line.startswith("adapt: wrote") for line in lines)
    assert (out / "curve.png").read_bytes()[:4] == b"\x89PNG"


def test_resume_continues_the_run(adapted, cts):
    out, _ = adapted
    before = load_card(out)["adaptation"]
    adapt(cts[0], out, minutes=MINUTES, device="cpu", settings=TINY, resume=True, log=lambda line: None)
    after = load_card(out)["adaptation"]
    assert after["pairs_seen"] > before["pairs_seen"]
    assert after["minutes"] > before["minutes"]
    assert after["curve"][: len(before["curve"])] == before["curve"]  # the earlier curve kept, points added
    assert len(json.loads((out / "adapt.json").read_text())["sessions"]) == 2


def test_refusals(adapted, cts, tmp_path):
    out, _ = adapted
    with pytest.raises(AdaptError, match="already holds an adaptation"):
        adapt(cts[0], out, minutes=MINUTES, device="cpu", settings=TINY)
    with pytest.raises(AdaptError, match="holds no adaptation to continue"):
        adapt(cts[0], tmp_path / "empty", minutes=MINUTES, device="cpu", settings=TINY, resume=True)
    with pytest.raises(AdaptError, match="not .*patient_b"):
        adapt(cts[1], out, minutes=MINUTES, device="cpu", settings=TINY, resume=True)
    for bad in (0, -1, float("nan"), True):
        with pytest.raises(AdaptError, match="--minutes"):
            adapt(cts[0], tmp_path / "x", minutes=bad, device="cpu", settings=TINY)
    with pytest.raises(AdaptError, match="not trained on randomized realistic pairs"):
        adapt(cts[0], tmp_path / "line", minutes=MINUTES, base="pelvis_line", device="cpu", settings=TINY)
    with pytest.raises(AdaptError, match="the phantom seed must be a whole number"):
        adapt("phantom:x", tmp_path / "ph", minutes=MINUTES, device="cpu", settings=TINY)
    lines = []
    with pytest.raises(AdaptError, match="not trained on randomized realistic pairs"):  # after the phantom's file
        adapt("phantom:2", tmp_path / "ph", minutes=MINUTES, base="pelvis_line", device="cpu", settings=TINY,
              log=lines.append)
    from sim.ct.io import load_ct
    from sim.ct.phantom import make_pelvis_phantom

    np.testing.assert_allclose(load_ct(tmp_path / "ph" / "phantom_2.nii.gz").hu, make_pelvis_phantom(2).hu, atol=1e-3)
    assert any("the built-in phantom phantom:2 written to" in line for line in lines)
    (tmp_path / "damaged" / "run").mkdir(parents=True)
    (tmp_path / "damaged" / "run" / "checkpoint.pt").write_bytes(b"x")
    (tmp_path / "damaged" / "adapt.json").write_text("{")
    with pytest.raises(AdaptError, match="adapt.json is damaged"):
        adapt(cts[0], tmp_path / "damaged", minutes=MINUTES, device="cpu", settings=TINY, resume=True)


def test_a_model_adapted_to_another_ct_is_named_in_a_warning(adapted, cts):
    out, _ = adapted
    assert adapted_ct_warning(out, cts[0]) is None  # its own CT
    line = adapted_ct_warning(out, cts[1])
    assert line.startswith("warning:") and "patient_a" in line and "patient_b" in line and "\n" not in line
    assert adapted_ct_warning(out / "model.pt", cts[1]) == line  # the weights file names the folder too
    assert adapted_ct_warning("pelvis_xray", cts[1]) is None  # a shipped model: adapted to no CT
    assert adapted_ct_warning(None, cts[1]) is None


def test_a_frozen_base_backbone_stays_frozen_in_the_adaptation(tmp_path):
    """A base trained with a frozen (ImageNet) backbone adapts its heads only: its config's
    ``freeze_backbone`` carries into the adaptation's training config; a trained one's stays trainable."""
    from types import SimpleNamespace

    from learn.adapt import _train_config

    randomized = {"level": "randomized", "randomize": {"kvp": [60.0, 130.0], "scatter": ["none", "sks"]}}
    for frozen in (True, False):
        fake = SimpleNamespace(physics=randomized, config={"freeze_backbone": frozen}, backbone="efficientnet-lite0",
                               head_channels=64, preprocess=("normalize",))
        cfg = _train_config(tmp_path, tmp_path / "base.pt", fake, ADAPT)
        assert cfg.freeze_backbone is frozen and cfg.train_backbone_from is None
        # stages of a frozen backbone trained again where the settings say so; a trained one adapts whole
        cfg = _train_config(tmp_path, tmp_path / "base.pt", fake, replace(ADAPT, train_backbone_from="block11",
                                                                          backbone_lr_scale=0.2))
        assert cfg.freeze_backbone is frozen and cfg.train_backbone_from == ("block11" if frozen else None)
        assert cfg.backbone_lr_scale == 0.2


def test_ctxreg_models_names_the_base_adapt_starts_from():
    from learn.shipped import DEFAULT_MODEL, describe_models

    text = describe_models()
    assert f"{DEFAULT_ADAPT_BASE}  (ctxreg adapt's default base):" in text and f"{DEFAULT_MODEL}  (default):" in text
