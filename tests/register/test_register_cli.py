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
