"""The field of realistic study frames (``studies/metal.toml``'s linear display behind a leaky iris,
tools fixed to the patient): where no shape model fits the image as stored, its logarithmic view
is tried too. Needs ../shared/data (skips without it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from register.evaluation.evaluate import EvaluationSettings, sample_cases
from register.evaluation.study import frame_seed, load_study, study_frames
from register.xray.field import FieldSettings, _detect, _validated, detect_field
from sim import load_ct
from sim.ct.anatomy import anatomy_center
from sim.projection.geometry import pose_from_params
from tests.conftest import shared_file

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def metal_linear():
    ct = shared_file("ct/pelvis_chiconasa_2mm.nii.gz")
    study = load_study(ROOT / "studies" / "metal.toml")
    target = next(t for t in study.targets if t.name == "metal-linear-90kV")
    volume = load_ct(ct)
    frames = study_frames(study, target, volume, anatomy_center(volume))
    poses, _ = sample_cases(EvaluationSettings(cases=10, seed=study.seed, size=study.size, start="ap"))

    def frame(case: int):
        pose = pose_from_params(poses[case], frames.imager.geometry.sod_mm)
        return frames.display(frames.raw(pose, frame_seed(study, case)))

    return frame


@pytest.mark.parametrize("case", [0, 6])
def test_a_leaky_iris_of_a_linear_display_is_found_in_its_log_view(metal_linear, case):
    """Validation-pelvis frames 0 and 6 (10-bit linear display, iris passing 8 % of the beam, tools
    reaching black at the field's edge): the image as stored fits no model (kind ``"none"``, its
    shadowed outside kept as field), its log view fits the circle. Within 0.1 of the collimator's
    own mask by intersection over union: the 2 px margin on a 59 px radius loses 7 %."""
    pixels, truth = metal_linear(case)
    assert _detect(_validated(pixels), FieldSettings()).kind == "none"
    f = detect_field(pixels)
    assert f.kind == "circle" and f.view != "display", (f.kind, f.view)
    iou = (f.field_mask & truth).sum() / (f.field_mask | truth).sum()
    assert iou > 0.9, iou
    assert f.mask[~truth].mean() < 0.01  # the shadow is out
