"""``ctxreg register`` end to end on a synthetic X-ray written as DICOM, and its bad inputs."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import REPO


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "register.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=REPO, timeout=600)


@pytest.fixture(scope="module")
def synthetic_case(tmp_path_factory):
    """A phantom CT (NIfTI) and its DRR at a known pose, stored as a DX DICOM with geometry tags."""
    from register.xray_io import write_xray_dicom
    from sim.anatomy import anatomy_center
    from sim.ct_io import save_nifti
    from sim.phantom import make_pelvis_phantom
    from sim.render import DRRRenderer, RenderSettings

    d = tmp_path_factory.mktemp("reg")
    vol = make_pelvis_phantom(3, spacing_mm=3.0)
    ct = d / "ct.nii.gz"
    save_nifti(vol, ct)
    center = anatomy_center(vol)
    truth = np.array([8.0, -5.0, 4.0, 10.0, -8.0, 20.0])
    r = DRRRenderer(vol, RenderSettings(size=(192, 192)), center_lps=center)
    image = r.render_params(truth)[0]
    g = r.geometry
    xray = d / "xray.dcm"
    write_xray_dicom(xray, image, pixel_spacing_mm=g.pixel_spacing_mm, sdd_mm=g.sdd_mm, sod_mm=g.sod_mm)
    return ct, xray, truth, center


def test_register_recovers_the_pose_of_a_synthetic_dicom(synthetic_case, tmp_path):
    ct, xray, truth, center = synthetic_case
    start = truth + np.array([4.0, 3.0, -3.0, -8.0, 6.0, 15.0])
    out = tmp_path / "out"
    r = run_cli("register", "--ct", ct, "--xray", xray, "--init", *start, "--size", 96,
                "--center", *center, "--out", out)
    assert r.returncode == 0, r.stderr
    result = json.loads((out / "result.json").read_text())
    est = np.array([result["params"][k] for k in ("phi", "theta", "psi", "tx", "ty", "tz")])
    # geometry from the DICOM tags, image resampled 192 -> 96 px; the DRRs match the target up
    # to the 16-bit storage and the resampling, so the pose comes back within a degree / few mm
    assert np.abs(est[:3] - truth[:3]).max() < 1.0, est
    assert np.abs(est[3:5] - truth[3:5]).max() < 3.0, est
    assert abs(est[5] - truth[5]) < 15.0, est  # depth is the weakly observed direction
    assert result["geometry"]["sdd_mm"] == pytest.approx(1020.0)
    assert [s["step"] for s in result["preprocessing"]] == ["crop", "median", "normalize"]
    for name in ("overlay.png", "convergence.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("extra, words", [
    (["--init", "1", "2"], "six finite numbers"),
    (["--preprocess", "sharpen"], "sharpen"),
])
def test_bad_register_arguments_are_one_line_errors(synthetic_case, tmp_path, extra, words):
    ct, xray, *_ = synthetic_case
    r = run_cli("register", "--ct", ct, "--xray", xray, "--out", tmp_path, *extra)
    assert r.returncode == 2 and "Traceback" not in r.stderr and words in r.stderr, r.stderr


def test_register_rejects_a_missing_or_colour_xray(synthetic_case, tmp_path):
    from PIL import Image

    ct, *_ = synthetic_case
    r = run_cli("register", "--ct", ct, "--xray", tmp_path / "none.dcm")
    assert r.returncode == 2 and "none.dcm" in r.stderr and "Traceback" not in r.stderr
    rgb = np.zeros((32, 32, 3), np.uint8)
    rgb[..., 0] = 200
    Image.fromarray(rgb).save(tmp_path / "colour.png")
    r = run_cli("register", "--ct", ct, "--xray", tmp_path / "colour.png")
    assert r.returncode == 2 and "grey" in r.stderr and "Traceback" not in r.stderr


def test_contextual_register_saves_a_consistent_trajectory(synthetic_case, tmp_path):
    """With any network (here an untrained tiny one) the saved trajectory is the iteration it ran:
    it starts at --init, and each pose is the previous one moved by 0.15 of its predicted gradient."""
    import torch

    from learn.labels import apply_update
    from learn.model import pose_update_net
    from sim.geometry import pose_from_params

    torch.manual_seed(0)
    ckpt = tmp_path / "tiny.pt"
    torch.save({"model": pose_update_net(backbone="tiny").state_dict(), "image_size": [32, 32],
                "config": {"backbone": "tiny", "preprocess": ["normalize"], "head_channels": 64}}, ckpt)
    ct, xray, truth, center = synthetic_case
    start = np.array([1.0, 2.0, -1.0, 5.0, -5.0, 10.0])
    out = tmp_path / "ctx"
    r = run_cli("register", "--ct", ct, "--xray", xray, "--init", *start, "--size", 64, "--center", *center,
                "--method", "contextual", "--model", ckpt, "--out", out)
    assert r.returncode == 0, r.stderr
    t = np.load(out / "trajectory.npz")
    params, g, drrs = t["params_deg_mm"], t["g_rad_mm"], t["drrs"]
    k = len(g)
    assert params.shape == (k + 1, 6) and drrs.shape == (k, 64, 64) and t["xray"].shape == (64, 64)
    np.testing.assert_allclose(params[0], start, atol=1e-9)
    sod = json.loads((out / "result.json").read_text())["geometry"]["sod_mm"]
    for i in range(k - 1):
        expect = apply_update(pose_from_params(params[i], sod), g[i], 0.15)
        np.testing.assert_allclose(pose_from_params(params[i + 1], sod), expect, atol=1e-6)
    assert (out / "trajectory.png").read_bytes()[:4] == b"\x89PNG"
