"""Shared helpers of the benchmark scripts (importable because Python puts a script's folder on
``sys.path``): timing, and the input checks of the scripts that register the shared CT's frames."""

from __future__ import annotations

import statistics
import time
from pathlib import Path


def timed(fn, repeats: int) -> float:
    """Median wall time (s) of ``repeats`` calls of ``fn`` after one untimed warm-up call."""
    fn()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


#: The frame benchmarks' default CT: the training pelvis of ../shared/data (its README).
DEFAULT_CT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"


def add_frame_arguments(ap, *, cases: int) -> None:
    """The two options of every benchmark that simulates a CT's frames: ``--ct`` (default
    :data:`DEFAULT_CT`) and ``--cases`` (frames per condition, the protocol's first N poses;
    default ``cases``), both checked by :func:`input_problem`."""
    ap.add_argument("--ct", default=str(DEFAULT_CT), help="the CT (NIfTI; default ../shared/data/ct/pelvis_abdomen_3mm.nii.gz)")
    ap.add_argument("--cases", type=int, default=cases,
                    help=f"frames per condition: the protocol's first N poses (default {cases})")


def input_problem(script: str, ct, cases: int) -> str | None:
    """One line naming what is wrong with a frame benchmark's ``--ct`` (missing) or ``--cases``
    (below 1), prefixed by the ``script``'s name; None when both are fine."""
    if not Path(ct).exists():
        return f"{script}: CT {ct} not found (see ../shared/data/README.md)"
    if cases < 1:
        return f"{script}: --cases must be >= 1, got {cases}"
    return None
