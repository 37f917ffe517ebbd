"""Registration with realistic moving images: ``--physics poly|full`` in CMA-ES, the contextual
iteration, ``ctxreg register`` and ``ctxreg evaluate``; the shared physics options."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from register.engines.cmaes import CMAESRegistration, CMAESSettings
from sim.physics import PhysicsError
from sim.physics.imaging import LogImageRenderer, PhysicsSettings, XRayImager, moving_renderer
from tests.conftest import REPO

SMALL = CMAESSettings(levels=(2, 1), size=(64, 64), popsize=12, generations=(25, 15), polish_evals=120)


@pytest.fixture(scope="module")
def phantom():
    from sim.ct.anatomy import anatomy_center
    from sim.ct.phantom import make_pelvis_phantom

    vol = make_pelvis_phantom(0, spacing_mm=4.0)
    return vol, anatomy_center(vol)


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "register.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=REPO, timeout=600)


def test_moving_renderer_levels(phantom):
    """line: the plain DRR renderer; poly: the imager's noise-free log image, whatever the noise
    setting given; label materials are refused for line DRRs."""
    from sim.projection.geometry import pose_from_params
    from sim.projection.drr import DRRRenderer

    vol, c = phantom
    assert isinstance(moving_renderer(vol, None, size=(32, 32), center_lps=c), DRRRenderer)
    assert isinstance(moving_renderer(vol, PhysicsSettings(level="line"), size=(32, 32), center_lps=c), DRRRenderer)
    noisy = PhysicsSettings(level="poly", noise=True, mas=0.1)
    r = moving_renderer(vol, noisy, size=(32, 32), center_lps=c)
    assert isinstance(r, LogImageRenderer) and r.imager.physics.noise is False
    T = pose_from_params(np.array([5.0, -3.0, 2.0, 4.0, -6.0, 10.0]), r.geometry.sod_mm)
    expected = XRayImager(vol, PhysicsSettings(level="poly", noise=False), size=(32, 32), center_lps=c).render(T)
    np.testing.assert_array_equal(r.render(T), expected["log"])
    np.testing.assert_array_equal(r.render(T), r.render(T))  # no noise: the same image every time
    with pytest.raises(PhysicsError, match="poly or full"):
        moving_renderer(vol, None, size=(32, 32), center_lps=c, label_materials={1: "titanium"})


def test_full_moving_images_use_common_random_numbers(phantom):
    """With a fixed scatter seed a pose's image does not depend on its place in the batch (so an
    optimiser sees a deterministic objective); a dataset's imager draws each pose apart."""
    from sim.projection.geometry import pose_from_params

    vol, c = phantom
    physics = PhysicsSettings(level="full", scatter_photons=20_000, noise=False)
    r = moving_renderer(vol, physics, size=(32, 32), center_lps=c)
    T = pose_from_params(np.array([[0.0, 0, 0, 0, 0, 0], [4.0, 2.0, 0, 5.0, 0, 0]]), r.geometry.sod_mm)
    both = r.render(np.stack([T[1], T[0]]))
    np.testing.assert_array_equal(both[1], r.render(T[0])[0])
    np.testing.assert_array_equal(both[0], r.render(T[1])[0])
    dataset = XRayImager(vol, physics, size=(32, 32), center_lps=c).render(np.stack([T[0], T[0]]))["scatter"]
    assert not np.array_equal(dataset[0], dataset[1])  # independent streams per pose


def test_cmaes_with_poly_moving_images_recovers_a_noisy_poly_target(phantom):
    """A noisy 120 kVp image as the X-ray and noise-free poly moving images: the pose comes back
    as with line DRRs on line targets (tests/register/test_cmaes.py, same bounds and settings)."""
    from sim.projection.geometry import pose_from_params
    from sim.projection.se3 import rotation_error_deg, translation_error_mm

    vol, c = phantom
    truth = np.array([6.0, -4.0, 3.0, 8.0, -6.0, 15.0])
    target_imager = LogImageRenderer(vol, PhysicsSettings(level="poly", mas=2.5, seed=3), size=(64, 64),
                                     center_lps=c)
    T = pose_from_params(truth, target_imager.geometry.sod_mm)
    target = target_imager.render(T)[0]
    engine = CMAESRegistration(vol, SMALL, center_lps=c, physics=PhysicsSettings(level="poly"))
    assert all(isinstance(r, LogImageRenderer) for _, r in engine.renderers)
    result = engine.register(target, truth + np.array([3.0, -3.0, 2.0, 5.0, 5.0, -10.0]))
    assert rotation_error_deg(result.pose, T) < 0.5
    assert translation_error_mm(result.pose, T) < 2.0


def test_a_checkpoint_reports_a_physics_mismatch(tmp_path):
    import torch

    from learn.model import pose_update_net
    from learn.predict import NetworkPredictor

    base = {"model": pose_update_net(backbone="tiny").state_dict(), "image_size": [32, 32],
            "config": {"backbone": "tiny", "preprocess": ["normalize"], "head_channels": 64}}
    torch.save(base, tmp_path / "old.pt")
    assert NetworkPredictor(str(tmp_path / "old.pt")).physics_mismatch(None) is None  # not recorded
    torch.save({**base, "physics": {"name": "poly", "level": "poly", "kvp": 120.0, "filters": ["Al:2.5"]}},
               tmp_path / "poly.pt")
    p = NetworkPredictor(str(tmp_path / "poly.pt"))
    assert p.physics_mismatch(PhysicsSettings(level="poly")) is None
    for moving, words in ((PhysicsSettings(level="full"), "rendered with full physics"),(None, "trained on poly at 120 kVp current images"), (PhysicsSettings(level="line"), "with line physics"),
                          (PhysicsSettings(level="poly", kvp=80.0), "at 80 kVp"),
                          (PhysicsSettings(level="poly", filters=(("Al", 2.5), ("Cu", 0.1))), "poly")):
        msg = p.physics_mismatch(moving)
        assert msg is not None and words in msg and "--physics" in msg, (moving, msg)


@pytest.fixture(scope="module")
def poly_case(tmp_path_factory):
    """A phantom CT and a noisy 120 kVp image of it at a known pose, stored as a DICOM with geometry tags."""
    from register.xray.io import write_xray_dicom
    from sim.ct.io import save_nifti
    from sim.projection.geometry import pose_from_params
    from sim.ct.anatomy import anatomy_center
    from sim.ct.phantom import make_pelvis_phantom

    d = tmp_path_factory.mktemp("polyreg")
    vol = make_pelvis_phantom(3, spacing_mm=3.0)
    save_nifti(vol, d / "ct.nii.gz")
    center = anatomy_center(vol)
    truth = np.array([8.0, -5.0, 4.0, 10.0, -8.0, 20.0])
    r = LogImageRenderer(vol, PhysicsSettings(level="poly", mas=2.5, seed=1), size=(192, 192), center_lps=center)
    image = r.render(pose_from_params(truth, r.geometry.sod_mm))[0]
    g = r.geometry
    write_xray_dicom(d / "xray.dcm", image, pixel_spacing_mm=g.pixel_spacing_mm, sdd_mm=g.sdd_mm, sod_mm=g.sod_mm)
    return d / "ct.nii.gz", d / "xray.dcm", truth, center


def test_register_with_poly_moving_images(poly_case, tmp_path):
    ct, xray, truth, center = poly_case
    start = truth + np.array([4.0, 3.0, -3.0, -8.0, 6.0, 15.0])
    out = tmp_path / "out"
    r = run_cli("register", "--ct", ct, "--xray", xray, "--init", *start, "--size", 96, 96, "--center", *center,
                "--physics", "poly", "--out", out)
    assert r.returncode == 0, r.stderr
    result = json.loads((out / "result.json").read_text())
    est = np.array([result["params"][k] for k in ("phi", "theta", "psi", "tx", "ty", "tz")])
    # the bounds of the line-DRR case (test_register_cli.py); here the X-ray also has quantum noise
    assert np.abs(est[:3] - truth[:3]).max() < 1.0, est
    assert np.abs(est[3:5] - truth[3:5]).max() < 3.0, est
    assert abs(est[5] - truth[5]) < 15.0, est
    assert result["moving_physics"]["level"] == "poly" and result["moving_physics"]["noise"] is False


@pytest.mark.parametrize("extra, words", [
    (["--kvp", "90"], "--kvp: meaningful with --physics poly or full only; this run is --physics line"),
    (["--physics", "poly", "--scatter-photons", "5000"], "--scatter-photons: meaningful with --physics full only"),
    (["--physics", "poly", "--label-material", "3:titanium"], "needs a CT with a label map"),
    (["--physics", "poly", "--label-material", "0:titanium"], "integer label > 0"),
    (["--physics", "poly", "--label-material", "3:steel"], "'steel' is not one of"),
    (["--physics", "poly", "--filter", "Xx:1"], "SYMBOL:MM"),
])
def test_bad_physics_options_of_register_are_one_line_errors(poly_case, tmp_path, extra, words):
    ct, xray, *_ = poly_case
    r = run_cli("register", "--ct", ct, "--xray", xray, "--method", "cmaes", "--out", tmp_path, *extra)
    assert r.returncode == 2 and words in r.stderr and r.stderr.count("\n") == 1, r.stderr


def test_evaluate_records_the_physics_of_targets_and_moving_images(tmp_path):
    """`ctxreg evaluate --target-physics poly --physics poly`: the same physics on both sides, the
    pose comes back from a local start, and summary.json says which physics each side had."""
    import csv

    from register.commands import EvaluateCommand, run_evaluate

    run_evaluate(EvaluateCommand(ct="phantom", cases=1, start="local", size=(64, 64), target_physics="poly",
                                 target_mas=5.0, physics="poly", out=str(tmp_path)))
    rows = list(csv.DictReader(open(tmp_path / "cases.csv")))
    assert len(rows) == 1 and float(rows[0]["rot_err_deg"]) < 2.0 and float(rows[0]["mtre_mm"]) < 10.0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["target_physics"]["level"] == "poly" and summary["target_physics"]["mas"] == 5.0
    assert summary["moving_physics"]["level"] == "poly" and summary["moving_physics"]["noise"] is False


def test_physics_options_are_declared_once_for_every_command():
    """render, register and evaluate take their physics options from sim/physics/options.py: the
    same help, unit and choices, the levels in the help; only register's scatter default differs."""
    from dataclasses import fields

    from register.commands import REGISTER_SCATTER_PHOTONS, EvaluateCommand, RegisterCommand
    from sim.cli import RenderCommand
    from sim.physics.options import physics_option

    render = {f.name: f for f in fields(RenderCommand)}
    register = {f.name: f for f in fields(RegisterCommand)}
    shared = sorted(set(render) & set(register) - {"ct", "label_map", "center", "scene", "size", "out", "physics"})
    assert shared == ["anode_angle_deg", "bins", "detector_mm", "detector_mode", "filters", "grid_ratio", "kvp",
                      "label_material", "scatter_photons", "scatter_voxel_mm"]
    for name in shared:
        assert render[name].metadata == register[name].metadata, name
        assert "(poly or full)" in render[name].metadata["help"] or "(full)" in render[name].metadata["help"]
    assert register["scatter_photons"].default == REGISTER_SCATTER_PHOTONS != render["scatter_photons"].default
    assert {f.name for f in fields(EvaluateCommand)} >= {"physics", "target_physics"}
    with pytest.raises(KeyError, match="unknown physics option 'kv'"):
        physics_option("kv")
