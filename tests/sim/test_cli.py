"""The simulator's commands (``ctxreg render`` and ``ctxreg demo``, :mod:`sim.cli`) end to end:
outputs and their geometry sidecars, the generated help, and one-line errors for bad input. The
dispatcher itself (:mod:`register.cli`) is tested in ``tests/register/test_cli.py``; ``ctxreg
simulate`` in ``test_campaign_run.py``."""

from __future__ import annotations

import json
import subprocess
import sys

import nibabel as nib
import numpy as np
import pytest

from tests.conftest import REPO


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "register.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd or REPO, timeout=300)


@pytest.fixture(scope="module")
def bead_nifti(tmp_path_factory):
    """A NIfTI CT (RAS affine) with one dense bead at a known LPS point and a bone block."""
    d = tmp_path_factory.mktemp("ct")
    hu = np.full((40, 40, 40), -1000.0, np.float32)
    hu[2:14, 25:38, 2:14] = 0.0  # soft tissue, away from the bead
    hu[5:9, 28:32, 5:9] = 800.0  # bone block
    hu[29:32, 11:14, 24:27] = 30000.0  # bead: 3 voxels wide, centred on voxel (30, 12, 25)
    ras = np.diag([-2.0, -2.0, 2.0, 1.0])  # i to patient right, j to anterior: LPS = index * 2
    path = d / "bead.nii.gz"
    nib.save(nib.Nifti1Image(hu, ras), path)
    bead_lps = np.array([30, 12, 25]) * 2.0
    return path, bead_lps


def test_render_writes_npy_and_sidecar_whose_projection_finds_the_bead(bead_nifti, tmp_path):
    path, bead_lps = bead_nifti
    out = tmp_path / "drr.npy"
    r = run_cli("render", "--ct", path, "--size", 128, 128, "--pose", 10, -5, 20, 4, -3, 30,
                "--center", 30, 40, 40, "--out", out)
    assert r.returncode == 0, r.stderr
    img = np.load(out)
    assert img.dtype == np.float32 and img.shape == (128, 128)
    meta = json.loads(out.with_suffix(".json").read_text())
    for key in ("K", "pose_4x4", "projection_3x4_lps_to_pixels", "sdd_mm", "sod_mm", "pixel_spacing_mm",
                "image_size_hw", "anatomy_center_lps_mm", "quantity", "mu_water_per_mm"):
        assert key in meta
    assert meta["anatomy_center_lps_mm"] == [30.0, 40.0, 40.0]
    assert meta["anatomy_center_how"] == "given: stated by the user (LPS mm)"
    P = np.array(meta["projection_3x4_lps_to_pixels"])
    uvw = P @ np.append(bead_lps, 1.0)
    u, v = uvw[:2] / uvw[2]
    i, j = np.unravel_index(np.argmax(img), img.shape)
    win = img[i - 5:i + 6, j - 5:j + 6]
    rows, cols = np.mgrid[i - 5:i + 6, j - 5:j + 6]
    # the bead's shadow centroid against the sidecar's projection of its centre (0.5 px, as for
    # the renderer's own bead test)
    assert abs((win * cols).sum() / win.sum() - u) < 0.5
    assert abs((win * rows).sum() / win.sum() - v) < 0.5


def test_pose_matrix_from_a_sidecar_reproduces_the_image(bead_nifti, tmp_path):
    path, _ = bead_nifti
    a = tmp_path / "a.npy"
    assert run_cli("render", "--ct", path, "--size", 64, 64, "--pose", 5, 5, 5, 1, 2, 3, "--out", a).returncode == 0
    b = tmp_path / "b.npy"
    r = run_cli("render", "--ct", path, "--size", 64, 64, "--pose-matrix", a.with_suffix(".json"), "--out", b)
    assert r.returncode == 0, r.stderr
    np.testing.assert_array_equal(np.load(a), np.load(b))


def test_png_output_is_a_display_image(bead_nifti, tmp_path):
    from PIL import Image

    path, _ = bead_nifti
    out = tmp_path / "drr.png"
    assert run_cli("render", "--ct", path, "--size", 64, 64, "--out", out).returncode == 0
    img = np.asarray(Image.open(out))
    assert img.dtype == np.uint8 and img.shape == (64, 64) and img.max() == 255


@pytest.mark.parametrize("args, words", [
    (["render", "--ct", "missing.nii.gz"], "missing.nii.gz"),
    (["render", "--ct", "phantom:abc"], "seed"),
    (["render", "--ct", "phantom", "--scene", "no_such_scene"], "no_such_scene"),
    (["render", "--ct", "phantom", "--size", "100", "50"], "aspect"),
    (["render", "--ct", "phantom", "--out", "x.tif"], ".npy or .png"),
    (["render", "--ct", "phantom", "--mu-water", "-1"], "mu_water"),
    (["render", "--ct", "phantom", "--pose", "nan", "0", "0", "0", "0", "0"], "finite"),
])
def test_bad_input_gives_one_line_error_and_exit_2(args, words, tmp_path):
    r = run_cli(*args, cwd=tmp_path)
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.strip().splitlines() if ln]
    assert len(lines) == 1 and words in lines[0], r.stderr


def test_bad_files_give_one_line_errors(tmp_path):
    bogus = tmp_path / "bogus.nii.gz"
    bogus.write_text("not an image")
    r = run_cli("render", "--ct", bogus)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "bogus.nii.gz" in r.stderr
    mat = tmp_path / "m.txt"
    np.savetxt(mat, np.eye(3))
    r = run_cli("render", "--ct", "phantom", "--pose-matrix", mat)
    assert r.returncode == 2 and "4x4" in r.stderr


def test_help_shows_units_and_defaults():
    r = run_cli("render", "--help")
    assert r.returncode == 0, r.stderr
    text = r.stdout
    for piece in ("[1/mm]", "(default: 0.020587)", "[deg deg deg mm mm mm]", "(default: 256 256)",
                  "geometry:", "pose:", "physics:", "output:"):
        assert piece in text, piece


@pytest.mark.parametrize("kind, words", [
    ("2d", "2-D"),
    ("nan", "NaN"),
    ("normalised", "HU"),
])
def test_bad_ct_contents_give_one_line_errors(kind, words, tmp_path):
    if kind == "2d":
        data = np.zeros((32, 32), np.float32)
    elif kind == "nan":
        data = np.full((16, 16, 16), -1000.0, np.float32)
        data[8:, :, :] = 40.0
        data[3, 4, 5] = np.nan
    else:
        data = np.random.default_rng(0).random((16, 16, 16)).astype(np.float32)
    path = tmp_path / f"{kind}.nii.gz"
    nib.save(nib.Nifti1Image(data, np.eye(4)), path)
    r = run_cli("render", "--ct", path, "--size", 16, 16, "--out", tmp_path / "x.npy")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert words in r.stderr and path.name in r.stderr, r.stderr
    assert not (tmp_path / "x.npy").exists()


def test_dicom_series_renders(tmp_path):
    from tests.conftest import shared_file

    series = shared_file("ct/abdomen_dicom_series")
    out = tmp_path / "dicom.npy"
    r = run_cli("render", "--ct", series, "--size", 64, 64, "--out", out)
    assert r.returncode == 0, r.stderr
    img = np.load(out)
    assert img.shape == (64, 64) and np.isfinite(img).all() and img.max() > 1.0
