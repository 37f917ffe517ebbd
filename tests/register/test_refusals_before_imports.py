"""Errors before the imports (issue 53): a missing X-ray or CT is named before the network (torch)
or the renderer (Mitsuba, Dr.Jit) loads, and ``ctxreg models`` lists the cards without reading
weights. Checked by what the process imported, not by seconds (the seconds are a benchmark row:
benchmarks/startup.py)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO

HEAVY = ("torch", "mitsuba", "drjit")

PROBE = """
import sys
from register.cli import main
status = main({argv!r})
print("STATUS", status, "LOADED", ",".join(m for m in {heavy!r} if m in sys.modules))
"""


def _probe(argv: list[str]) -> tuple[int, list[str], str]:
    r = subprocess.run([sys.executable, "-c", PROBE.format(argv=argv, heavy=HEAVY)], cwd=REPO, capture_output=True,
                       text=True, timeout=120)
    line = next(x for x in r.stdout.splitlines() if x.startswith("STATUS"))
    fields = line.split(" ")
    return int(fields[1]), [m for m in fields[3].split(",") if m] if len(fields) > 3 else [], r.stderr


@pytest.mark.parametrize("argv, words", [
    (["register", "--ct", "phantom", "--xray", "missing.dcm", "--out", "{out}"], "missing.dcm: file not found"),
    (["register", "--ct", "no_such_ct.nii.gz", "--xray", "{xray}", "--out", "{out}"],
     "no_such_ct.nii.gz: file or folder not found"),
])
def test_a_missing_file_is_named_before_torch_or_mitsuba_load(argv, words, tmp_path):
    import numpy as np

    from register.xray.io import write_xray_dicom

    xray = write_xray_dicom(tmp_path / "x.dcm", np.random.default_rng(0).uniform(0, 1, (64, 64)).astype(np.float32),
                            pixel_spacing_mm=1.0, sdd_mm=1020.0, sod_mm=700.0)
    argv = [a.format(xray=xray, out=tmp_path / "out") for a in argv]
    status, loaded, err = _probe(argv)
    assert status == 2 and words in err and "\n" not in err.strip(), err
    assert loaded == [], f"loaded before the refusal: {loaded}"


def test_models_lists_the_cards_without_reading_weights():
    status, loaded, err = _probe(["models"])
    assert status == 0, err
    assert loaded == [], f"loaded to list the cards: {loaded}"


def test_a_card_listed_without_its_weights_is_still_tied_to_them(tmp_path, monkeypatch):
    """The listing does not read the weights, but their sha256 still ties them to the card: a
    changed model.pt is refused in the listing too."""
    import shutil

    from learn.shipped import ModelCardError, describe_model, describe_models

    root = tmp_path / "models"
    shutil.copytree(REPO / "models" / "pelvis_line", root / "pelvis_line")
    assert "pelvis_line" in describe_models(root) and describe_model("pelvis_line", root)["model"]["name"]
    with open(root / "pelvis_line" / "model.pt", "ab") as f:
        f.write(b"\0")
    with pytest.raises(ModelCardError, match="model.sha256 does not match"):
        describe_models(root)
