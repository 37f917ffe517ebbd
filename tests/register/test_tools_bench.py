"""benchmarks/tools.py: the true tool pixels counted against the field and carried to the
optimiser's pixels as the image is (crop and resampling), so that each optimiser pixel a tool
touches sees the same ray as the tool's full-resolution pixels."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
import tools as bench  # noqa: E402  (benchmarks/tools.py, not a package)

from register.xray.io import XRayImage  # noqa: E402
from register.xray.prepare import prepare_xray  # noqa: E402


def test_tool_pixels_are_counted_inside_the_true_field_and_against_the_mask():
    tools = np.zeros((40, 50), bool)
    tools[10:20, 5:25] = True  # 200 px, 50 of them outside the field below
    field = np.ones((40, 50), bool)
    field[:, :10] = False
    mask = field.copy()
    mask[10:20, 20:30] = False  # the field's exclusions take 5 columns of the tool
    s = bench.tool_shares(tools, field, mask)
    assert s == {"field_px": 40 * 40, "tool_px": 150, "left_out_px": 50}
    with pytest.raises(ValueError, match="one shape"):
        bench.tool_shares(tools, field[:, :10], mask)


def test_tools_reach_the_optimiser_pixels_that_see_their_rays():
    """A 2:1 X-ray with a collimated rectangle (cropped) shrunk into 128 px: a tool bar's
    touched optimiser pixels have their centroid on the bar's rays (through both geometries'
    principal points and spacings) within half an optimiser pixel, and cover the bar."""
    rng = np.random.default_rng(0)
    h, w = 300, 600
    img = np.zeros((h, w))
    img[40:260, 60:560] = 1500 + 300 * rng.random((220, 500))  # the field; black outside
    xray = XRayImage(pixels=img.astype(np.float32), source="synthetic", pixel_spacing_mm=0.3)
    prepared = prepare_xray(xray, size=(128, 128), tone="off")
    tools = np.zeros((h, w), bool)
    tools[140:150, 200:400] = True
    small = bench.tools_at_optimiser(tools, prepared)
    assert small.shape == prepared.image.shape and small.any()
    fg, sg = prepared.full_geometry, prepared.geometry
    (fcx, fcy), (scx, scy) = fg.principal_point, sg.principal_point
    rows, cols = np.nonzero(small)
    # the same ray: (small px - small principal point) x small spacing = (full px - full pp) x full spacing
    to_full = sg.pixel_spacing_mm / fg.pixel_spacing_mm
    half = 0.5 * to_full
    assert abs((rows.mean() - scy) * to_full + fcy - 144.5) < half
    assert abs((cols.mean() - scx) * to_full + fcx - 299.5) < half
    # the bar is 200 full px long: the touched columns span it (blur may add a pixel each side)
    span = (cols.max() - cols.min() + 1) * to_full
    assert 200 - 2 * to_full <= span <= 200 + 4 * to_full


def test_the_script_names_a_missing_or_corrupt_study_and_a_target_without_tools(tmp_path):
    ct = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"
    if not ct.exists():
        pytest.skip(f"the shared CT {ct} is not here (../shared/data/README.md)")
    script = str(REPO / "benchmarks" / "tools.py")
    out = subprocess.run([sys.executable, script, "--study", "no-such.toml"], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 2 and "study file no-such.toml not found" in out.stderr
    out = subprocess.run([sys.executable, script, "--target", "fluoro-65kV"], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 2 and "metal-log-75kV" in out.stderr and "Traceback" not in out.stderr
    corrupt = tmp_path / "study.toml"
    corrupt.write_text("[study\nct = 1\n")
    out = subprocess.run([sys.executable, script, "--study", str(corrupt)], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 2 and "not valid TOML" in out.stderr and "Traceback" not in out.stderr


def test_a_detectors_pixels_are_scored_against_the_truth_the_field_kept():
    """Recall counts the true tool pixels the field kept that the detector found; precision the
    detector's kept pixels within ``reach_px`` of a true one (a detection grown by its dilation is
    not wrong at the tool's edge), and a detection far from any tool is wrong."""
    tools = np.zeros((30, 30), bool)
    tools[10:12, 5:25] = True  # a wire, 40 px
    kept = np.ones((30, 30), bool)
    kept[:, 20:] = False  # the field left out its last 5 columns (clipped): 30 px kept
    detected = np.zeros((30, 30), bool)
    detected[9:13, 5:15] = True  # 20 px of the wire found, grown 1 px (40 px)
    detected[25:27, 0:5] = True  # 10 px far from it
    s = bench.detection_scores(detected, tools, kept, 1)
    assert s == {"tool_px": 30, "found_px": 20, "detected_px": 50, "right_px": 40}
    assert bench.detection_scores(detected, tools, kept, 0)["right_px"] == 20
    with pytest.raises(ValueError, match="one shape"):
        bench.detection_scores(detected, tools[:5], kept, 1)
