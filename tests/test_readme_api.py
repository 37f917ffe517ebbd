"""The README's "Python API" example runs as written and does what it says (so it cannot rot)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tests.conftest import REPO


def readme_api_block() -> str:
    """The first ```python block under the README heading "## Python API"."""
    text = (REPO / "README.md").read_text()
    section = text.split("## Python API", 1)
    assert len(section) == 2, "README.md has no '## Python API' section"
    block = re.search(r"```python\n(.*?)```", section[1], flags=re.S)
    assert block is not None, "the '## Python API' section has no ```python block"
    return block.group(1)


@pytest.mark.slow  # about 10 s: a poly image and a registration with its polarity check
def test_readme_api_example_runs_and_recovers_the_pose(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "readme_api"}
    exec(compile(readme_api_block(), "README.md (Python API)", "exec"), namespace)
    drr, result, truth, written = (namespace[k] for k in ("drr", "result", "truth", "written"))
    # render: the image the text promises, not a blank one
    assert drr.shape == (256, 256) and drr.dtype == np.float32
    assert np.isfinite(drr).all() and np.percentile(drr, 99) > 1.0
    # register_xray: the simulated X-ray's pose comes back (1 deg, 3 mm in-plane, 15 mm in depth)
    est = np.array([result.params[k] for k in ("phi", "theta", "psi", "tx", "ty", "tz")])
    assert np.abs(est[:3] - np.array(truth[:3])).max() < 1.0, est
    assert np.abs(est[3:5] - np.array(truth[3:5])).max() < 3.0, est
    assert abs(est[5] - truth[5]) < 15.0, est
    np.testing.assert_allclose(result.pose[:3, :3] @ result.pose[:3, :3].T, np.eye(3), atol=1e-9)
    assert result.similarity > 0.8
    # write: the files of ctxreg register, and result.json holds the same pose
    assert [p.name for p in written] == ["result.json", "overlay.png", "checkerboard.png", "convergence.png"]
    saved = json.loads(written[0].read_text())
    assert saved["params"] == pytest.approx(result.params) and saved["method"] == "cmaes"
    assert saved["xray_input"]["optimiser_size"] == [64, 64]
