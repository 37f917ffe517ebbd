"""Realistic collimated fluoroscopy frames of the real pelvis CT through ``ctxreg register``
(default preprocessing and method), at a reduced size: the full study is
``benchmarks/xray_input.py`` (docs/results.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from register.evaluation.xray_study import run_xray_study, summarize_xray_study


@pytest.mark.slow
def test_collimated_frames_register_like_open_ones_from_a_local_start(pelvis_ct_path, tmp_path):
    rows = run_xray_study(str(pelvis_ct_path), tmp_path, cases=2, size=192, starts=("local",),
                     scatter_photons=200_000, progress=None)
    assert len(rows) == 4 and all(r["exit_code"] == 0 for r in rows)
    s = summarize_xray_study(rows)
    # from a local start (<= 5 deg, 10 mm away) collimated frames succeed (mTRE < 10 mm) within one case
    # of their open twins, and at least once (measured at this size: 1-2 of 2 each)
    assert s["collimated/local"]["successes"] >= max(s["open/local"]["successes"] - 1, 1), s
    for r in rows:
        assert r["intensity"] == "bone-dark" and r["scale"] == "display"
        if r["kind"] == "collimated":
            assert r["field_kind"] == "circle"
            # the field: the round field less its 2 px margin (a 77 px radius loses about 5 %)
            field = json.loads((tmp_path / f"case_{r['case']:03d}" / "collimated_local" / "result.json").read_text())[
                "xray_input"]["field"]
            assert 0.9 * r["truth_field_fraction"] < field["field_fraction"] <= r["truth_field_fraction"]
            # the valid pixels: the field less what it excludes (burned-in overlays, saturated
            # plateaus such as the air below the CT's last slice), pixel for pixel
            excluded = sum(field["excluded"].values()) / (192 * 192)
            assert r["field_valid_fraction"] == pytest.approx(field["field_fraction"] - excluded, abs=1e-5)
    result = json.loads((tmp_path / "case_000" / "collimated_local" / "result.json").read_text())
    src = result["xray_input"]["geometry_sources"]
    assert (src["sdd_source"], src["sod_source"], src["pixel_spacing_source"]) == (
        "DICOM DistanceSourceToDetector", "DICOM DistanceSourceToPatient", "DICOM ImagerPixelSpacing")
    assert result["xray_input"]["full_size"] == [192, 192]
    assert np.isfinite(result["similarity"])
