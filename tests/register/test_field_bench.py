"""benchmarks/field.py --against REV: the field detection of another git revision, loaded from git
and timed beside the current one on the same frames."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
import field as bench  # noqa: E402  (benchmarks/field.py, not a package)

from register.xray import field  # noqa: E402


def test_a_revisions_field_detection_is_loaded_from_git_and_timed():
    """HEAD's register/xray/field.py, loaded as a module of its own, finds the same field as the
    code imported here wherever the working tree holds HEAD's file (a fresh clone); a refusal
    (too little field) is timed, not raised; an unknown revision is an error naming git's."""
    if bench.subprocess.run(["git", "-C", str(REPO), "diff", "--quiet", "HEAD", "--", "register/xray/field.py"]
                            ).returncode != 0:
        pytest.skip("register/xray/field.py differs from HEAD's in this tree")
    peer = bench._field_at("HEAD")
    assert peer is not field and peer.detect_field is not field.detect_field
    yy, xx = np.mgrid[:128, :128]
    inside = (yy - 64) ** 2 + (xx - 60) ** 2 < 45 ** 2
    img = np.where(inside, 2000 + 500 * np.sin(xx / 5.0) * np.cos(yy / 7.0), 0).astype(np.uint16)
    a, b = field.detect_field(img), peer.detect_field(img)
    assert a.kind == b.kind == "circle" and np.array_equal(a.mask, b.mask)
    empty = np.zeros((64, 64), np.uint16)
    empty[0, 0] = 1
    refusals = (field.FieldError, peer.FieldError)
    assert bench._seconds(peer.detect_field, empty, refusals) > 0
    with pytest.raises(bench.subprocess.CalledProcessError):
        bench._field_at("no-such-revision")
