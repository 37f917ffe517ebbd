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


def input_problem(script: str, ct, cases: int) -> str | None:
    """One line naming what is wrong with a frame benchmark's ``--ct`` (missing) or ``--cases``
    (below 1), prefixed by the ``script``'s name; None when both are fine."""
    if not Path(ct).exists():
        return f"{script}: CT {ct} not found (see ../shared/data/README.md)"
    if cases < 1:
        return f"{script}: --cases must be >= 1, got {cases}"
    return None
