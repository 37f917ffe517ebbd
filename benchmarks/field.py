"""The detected field of view (register/xray/field.py) against the collimator's true field, on study frames.

    .venv/bin/python benchmarks/field.py [--cases 20] [--study studies/domain_gap.toml ...] [--target all]

Frames: the first ``--cases`` poses of every ``xray`` target of every ``--study`` (default the five
study files: 15 conditions of tube, collimator and display chain), simulated where the cache
(``--out``, shared with benchmarks/search.py) lacks them. For each frame :func:`register.xray.field.detect_field`
runs on the stored pixels as registration reads them, and its ``field_mask`` is compared with the
simulator's collimator mask (an open collimator: every pixel):

* ``precision``: the share of the valid pixels (the field less its exclusions, the mask registration
  uses) inside the true field (a field that takes the outside, or no field found where there is
  one, is low, unless the outside is excluded as an empty or saturated plateau);
* ``recall``: the share of the true field inside the detected one (the 2 px margin costs a few
  per cent on 128 px frames; a field that misses anatomy is low);
* ``wrong``: frames with precision or recall under 0.8; ``refused``: frames the detection refuses
  (registration counts them as failures); ``log views``: frames read in a logarithmic view (the
  fallback for linear displays, :data:`register.xray.field.LOG_VIEWS`).

Prints one row per condition (medians over its frames) and the frames that are wrong or refused;
with ``--against REV``, a table of detect_field's seconds against the code of git revision REV on
the same frames (docs/benchmarks.md, "Time of the detection").
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from network_on_frames import study_frame_files  # noqa: E402  (benchmarks/network_on_frames.py)
from timing import add_frame_arguments, input_problem  # noqa: E402  (benchmarks/timing.py)

STUDIES = ("domain_gap", "heldout", "heldout2", "heldout3", "heldout4")


def field_scores(detected: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """``(precision, recall)`` of a detected field ``(H, W)`` bool against the true one ``(H, W)``
    bool: the share of the detected pixels inside the truth, and of the truth inside the detected."""
    both = float(np.logical_and(detected, truth).sum())
    return both / max(float(detected.sum()), 1.0), both / max(float(truth.sum()), 1.0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_frame_arguments(ap, cases=20)
    ap.add_argument("--study", nargs="+", default=[str(ROOT / "studies" / f"{s}.toml") for s in STUDIES],
                    help="study files whose xray targets give the frames (default the five of studies/)")
    ap.add_argument("--target", default="all", help="one xray target, or 'all' (default)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_search"),
                    help="frame cache folder, shared with benchmarks/search.py (default runs/bench_search)")
    ap.add_argument("--against", default=None, metavar="REV",
                    help="also time detect_field against register/xray/field.py as it was at git revision REV, "
                         "in the same process on the same frames (median seconds per condition and their ratio)")
    a = ap.parse_args()
    problem = input_problem("field", a.ct, a.cases)
    if problem:
        print(problem, file=sys.stderr)
        return 2
    from register.evaluation.study import StudyError, load_study
    from register.xray.field import FieldError, detect_field
    from register.xray.io import load_xray

    studies = {}
    for path in a.study:
        if not Path(path).exists():
            print(f"field: study file {path} not found", file=sys.stderr)
            return 2
        try:
            studies[path] = load_study(path)
        except StudyError as exc:
            print(f"field: {exc}", file=sys.stderr)
            return 2
    chosen = [(path, t) for path, study in studies.items() for t in study.targets
              if t.kind == "xray" and a.target in ("all", t.name)]
    if not chosen:
        names = sorted({t.name for study in studies.values() for t in study.targets if t.kind == "xray"})
        print(f"field: --target must be 'all' or one of {names}, got {a.target!r}", file=sys.stderr)
        return 2
    peer = None
    if a.against is not None:
        try:
            peer = _field_at(a.against)
        except (subprocess.CalledProcessError, OSError) as exc:
            print(f"field: --against {a.against}: no register/xray/field.py there ({exc})", file=sys.stderr)
            return 2
    rows, notes, times = [], [], []
    t_all = time.perf_counter()
    for k, (path, target) in enumerate(chosen):
        _, _, _, found, frames = study_frame_files(path, target.name, a.ct, a.cases, a.out)
        scores, refused, logs, kinds = [], 0, 0, {}
        for i, _, frame in found:
            pixels = load_xray(frame).pixels
            h, w = pixels.shape
            truth = np.ones((h, w), bool) if frames.collimator is None else frames.collimator.mask(h, w)
            if peer is not None:
                refusals = (FieldError, peer.FieldError)
                times.append((target.name, _seconds(detect_field, pixels, refusals),
                              _seconds(peer.detect_field, pixels, refusals)))
            try:
                f = detect_field(pixels)
            except FieldError as exc:
                refused += 1
                notes.append(f"{target.name} frame {i}: refused ({exc})")
                continue
            p, _ = field_scores(f.mask, truth)
            _, r = field_scores(f.field_mask, truth)
            scores.append((p, r))
            logs += f.view != "display"
            kinds[f.kind] = kinds.get(f.kind, 0) + 1
            if p < 0.8 or r < 0.8:
                notes.append(f"{target.name} frame {i}: {f.kind} in the {f.view} view, precision {p:.2f}, "
                             f"recall {r:.2f}")
        s = np.array(scores).reshape(-1, 2)
        wrong = int(np.sum((s[:, 0] < 0.8) | (s[:, 1] < 0.8)))
        rows.append((target.name, len(found), refused, wrong, logs, kinds,
                     np.median(s[:, 0]) if len(s) else np.nan, np.median(s[:, 1]) if len(s) else np.nan))
        done = k + 1
        rate = done / (time.perf_counter() - t_all)
        print(f"field: {done}/{len(chosen)} conditions, {rate * 60:.1f} per min, ETA {(len(chosen) - done) / rate:.0f} s",
              file=sys.stderr, flush=True)
    print(f"\nThe detected field against the collimator's, {a.cases} frames per condition from AP "
          f"({time.strftime('%Y-%m-%d %H:%M')})\n")
    print("| condition | frames | refused | wrong (precision or recall < 0.8) | read in a log view | kinds | "
          "median precision | median recall |")
    print("|---|---|---|---|---|---|---|---|")
    for name, n, refused, wrong, logs, kinds, p, r in rows:
        kind = ", ".join(f"{k} {v}" for k, v in sorted(kinds.items()))
        print(f"| `{name}` | {n} | {refused} | {wrong} | {logs} | {kind} | {p:.2f} | {r:.2f} |")
    if notes:
        print("\n" + "\n".join(f"- {n}" for n in notes))
    if times:
        print(f"\nSeconds of detect_field, median over each condition's frames (each the median of "
              f"{TIMING_CALLS} calls), against {a.against} in the same process\n")
        print(f"| condition | {a.against} s | now s | ratio |")
        print("|---|---|---|---|")
        for name in dict.fromkeys(n for n, _, _ in times):
            now = float(np.median([t for n, t, _ in times if n == name]))
            before = float(np.median([t for n, _, t in times if n == name]))
            print(f"| `{name}` | {before:.3f} | {now:.3f} | {now / before:.2f}x |")
    return 0


#: Calls timed per frame and version (their median is the frame's seconds).
TIMING_CALLS = 3


def _seconds(detect, pixels, refusals: tuple) -> float:
    """The median seconds of ``detect(pixels)`` over :data:`TIMING_CALLS` calls (a refusal, one of
    ``refusals``, is timed like a result)."""
    out = []
    for _ in range(TIMING_CALLS):
        t0 = time.perf_counter()
        try:
            detect(pixels)
        except refusals:
            pass
        out.append(time.perf_counter() - t0)
    return float(np.median(out))


def _field_at(rev: str):
    """register/xray/field.py as it was at git revision ``rev``, loaded as a module of its own."""
    source = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:register/xray/field.py"], check=True,
                            capture_output=True, text=True).stdout
    module = types.ModuleType(f"field_at_{rev}")
    module.__file__ = f"{rev}:register/xray/field.py"
    sys.modules[module.__name__] = module  # dataclasses resolve their module by name
    exec(compile(source, module.__file__, "exec"), module.__dict__)
    return module


if __name__ == "__main__":
    raise SystemExit(main())
