"""Issue 29: one function scores every pose (register.evaluation.errors.pose_errors), checked against an
independent computation (scipy's rotations, an explicit pinhole, a loop over the points) on known
poses, each metric non-zero where it must be; and every command scores with it, the study's
realistic-frame (xray) targets included, whose mPD was always 0.

Tolerances: everything is float64 arithmetic on a few hundred points: 1e-9 relative."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from register.evaluation.errors import pose_errors
from sim.projection.geometry import CArmGeometry, pose_from_params

GEOMETRY = CArmGeometry(sdd_mm=1000.0, sod_mm=600.0, height=48, width=64, pixel_spacing_mm=0.8, cx=30.0, cy=22.5)
CENTER = np.array([3.0, -7.0, 11.0])


def _points(n: int = 300, seed: int = 5) -> np.ndarray:
    return CENTER + np.random.default_rng(seed).uniform(-80, 80, size=(n, 3))


def _independent(T_est, T_true, points, geometry, center) -> dict:
    """The errors computed without sim.projection.se3 / sim.projection.geometry: scipy's rotation angle, a loop over the
    points, a pinhole camera written out (u = f x / z + cx, f = SDD / spacing)."""
    rot = np.degrees(Rotation.from_matrix(T_est[:3, :3].T @ T_true[:3, :3]).magnitude())
    trans = float(np.sqrt(sum((T_est[i, 3] - T_true[i, 3]) ** 2 for i in range(3))))
    f = geometry.sdd_mm / geometry.pixel_spacing_mm
    cx, cy = (geometry.width - 1) / 2 if geometry.cx is None else geometry.cx, \
        (geometry.height - 1) / 2 if geometry.cy is None else geometry.cy
    tre, pd = [], []
    for p in points:
        a = T_est[:3, :3] @ (p - center) + T_est[:3, 3]
        b = T_true[:3, :3] @ (p - center) + T_true[:3, 3]
        tre.append(np.sqrt(((a - b) ** 2).sum()))
        ua = np.array([f * a[0] / a[2] + cx, f * a[1] / a[2] + cy])
        ub = np.array([f * b[0] / b[2] + cx, f * b[1] / b[2] + cy])
        pd.append(np.sqrt(((ua - ub) ** 2).sum()) * geometry.pixel_spacing_mm)
    # the anatomy centre in each camera frame (its offset from itself is 0): its depth is its z
    zero = np.zeros(3)
    centre_est, centre_true = T_est[:3, :3] @ zero + T_est[:3, 3], T_true[:3, :3] @ zero + T_true[:3, 3]
    return {"rot_err_deg": rot, "trans_err_mm": trans, "depth_err_mm": float(abs(centre_est[2] - centre_true[2])),
            "mtre_mm": float(np.mean(tre)), "mpd_mm": float(np.mean(pd))}


#: known wrong poses (parameters of the estimate; the truth is TRUE) and the metrics that must
#: not be zero for each.
TRUE = np.array([10.0, -5.0, 3.0, 4.0, -6.0, 8.0])
CASES = {
    "rotation only": ([25.0, -5.0, 3.0, 4.0, -6.0, 8.0], ("rot_err_deg", "mtre_mm", "mpd_mm")),
    "in-plane shift only": ([10.0, -5.0, 3.0, 19.0, -6.0, 8.0], ("trans_err_mm", "mtre_mm", "mpd_mm")),
    "depth only": ([10.0, -5.0, 3.0, 4.0, -6.0, 58.0], ("trans_err_mm", "depth_err_mm", "mtre_mm", "mpd_mm")),
    "140 deg away": ([150.0, 30.0, -20.0, -10.0, 12.0, -40.0],
                     ("rot_err_deg", "trans_err_mm", "depth_err_mm", "mtre_mm", "mpd_mm")),
    "exact": (list(TRUE), ()),
}


@pytest.mark.parametrize("case", list(CASES))
def test_pose_errors_match_an_independent_computation(case):
    params, nonzero = CASES[case]
    T_est = pose_from_params(np.array(params), GEOMETRY.sod_mm)
    T_true = pose_from_params(TRUE, GEOMETRY.sod_mm)
    points = _points()
    got = pose_errors(T_est, T_true, points, CENTER, GEOMETRY)
    want = _independent(T_est, T_true, points, GEOMETRY, CENTER)
    assert set(got) == set(want)
    for key in want:
        assert got[key] == pytest.approx(want[key], rel=1e-9, abs=1e-9), key
        if key in nonzero:
            assert got[key] > 0.1, (key, got[key])
        else:
            assert got[key] == pytest.approx(0.0, abs=1e-9), (key, got[key])


def test_the_older_call_is_the_same_arithmetic():
    from sim.projection.geometry import projection_matrix

    T_est = pose_from_params(np.array(CASES["140 deg away"][0]), GEOMETRY.sod_mm)
    T_true = pose_from_params(TRUE, GEOMETRY.sod_mm)
    points = _points()
    new = pose_errors(T_est, T_true, points, CENTER, GEOMETRY)
    old = pose_errors(T_est, T_true, points, CENTER, projection_matrix(GEOMETRY, T_est, CENTER),
                      projection_matrix(GEOMETRY, T_true, CENTER), GEOMETRY.pixel_spacing_mm)
    assert new == pytest.approx(old, rel=1e-12)
    with pytest.raises(TypeError):
        pose_errors(T_est, T_true, points, CENTER)


def test_every_command_scores_with_the_one_function():
    """No module computes a pose's errors by its own arithmetic: each calls pose_errors with a geometry."""
    root = Path(__file__).resolve().parents[2]
    for name in ("register/evaluation/study.py", "register/evaluation/xray_study.py", "register/evaluation/demo.py", "register/evaluation/evaluate.py"):
        text = (root / name).read_text()
        calls = [line for line in text.splitlines() if "pose_errors(" in line and "def pose_errors" not in line
                 and "import" not in line and "``" not in line]
        assert calls, name
        for line in calls:
            assert "P_true, P_true" not in line and "P, P," not in line, (name, line)


class _Outcome:
    def __init__(self, pose):
        from register.verdict import Verdict

        self.pose, self.similarity = pose, 0.5
        self.verdict = Verdict("doubtful", ("similarity 0.50",))


WRONG = np.array([30.0, 8.0, -4.0, 15.0, -10.0, 25.0])  # start + this: the known wrong estimate


@pytest.mark.parametrize("kind", ["drr", "xray"])
def test_a_study_scores_a_known_wrong_pose_right_for_every_target_kind(tmp_path, monkeypatch, kind):
    """Each target kind's cases.csv: the four errors of a registration that returns a known wrong
    pose are those of the independent computation, mPD non-zero (it was 0 for xray targets)."""
    import register.api
    from register.evaluation import study as S
    from register.evaluation.errors import bone_points
    from register.evaluation.evaluate import EvaluationSettings, sample_cases
    from sim.ct.anatomy import anatomy_center
    from sim.ct.io import load_ct_spec

    study = S.Study(ct="phantom:0", variants=(S.Variant("v", model="x.pt"),), cases=2, size=(32, 32),
                    methods=("contextual",), targets=())
    volume = load_ct_spec("phantom:0")
    center = anatomy_center(volume)
    settings = EvaluationSettings(cases=2, seed=0, size=(32, 32), start="ap")
    truths, _ = sample_cases(settings)
    from sim.projection.scene import load_scene

    g = load_scene().geometry_at(32, 32)
    estimates = [pose_from_params(t + WRONG, g.sod_mm) for t in truths]
    calls = iter(estimates)

    if kind == "xray":
        target = S.Target("fluoro", "xray", {"level": "full", "kvp": 80, "mas": 1.0, "scatter_photons": 2000})
        monkeypatch.setattr(register.api, "register_xray", lambda *a, **k: _Outcome(next(calls)))
        S._evaluate_xray(study, target, volume, center, object(), tmp_path, lambda s: None)
    else:
        target = S.Target("line")
        class Fake:
            name = "contextual"

            def register(self, fixed, init_params, **kw):
                pose = next(calls)
                from types import SimpleNamespace

                from sim.projection.geometry import params_from_pose

                return SimpleNamespace(pose=pose, params=params_from_pose(pose, g.sod_mm), renders=0,
                                       similarity=0.5, trajectory=None, search=None)

        monkeypatch.setattr(S, "build_method", lambda *a, **k: Fake())
        S._evaluate_drr(study, target, volume, center, object(), tmp_path, lambda s: None)
    with open(tmp_path / "cases.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2
    points = bone_points(volume, settings.max_points, settings.seed)
    for row, t, T_est in zip(rows, truths, estimates):
        want = _independent(T_est, pose_from_params(t, g.sod_mm), points, g, center)
        for key, value in want.items():
            assert float(row[key]) == pytest.approx(value, rel=1e-6), (kind, key)
            assert float(row[key]) > 0.5, (kind, key)
    summary = json.loads((tmp_path / "summary.json").read_text())["summary"]["contextual"]
    assert summary["mpd_mm"]["min"] > 0.5
