"""Where a `ctxreg register` call's seconds go: cold processes, a warm one, and the import floor (issue 31).

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/startup.py [--runs 3] [--frames 1 3] [--target fluoro-65kV]

Rows, each timed as whole processes (wall seconds: minimum, median, maximum of ``--runs``), in
one run so that they share the machine's speed:

* ``import floor``: ``python -c "import torch, mitsuba"``, what any registration in Python pays;
* ``refused typo``: ``ctxreg register --xray missing.dcm``, refused before torch or Mitsuba load;
* ``ctxreg models``: the shipped cards listed (their weights' sha256 checked, not read);
* ``cold register, frame N``: one ``ctxreg register`` process per call on frame N of the study's
  target (``studies/domain_gap.toml``'s ``fluoro-65kV`` by default: frame 1's network pose is
  right and the grid is skipped, frame 3's is lost and the grid runs), with the median of each
  stage of ``result.json``'s ``timings_s`` (``startup`` is the interpreter and the imports);
* ``warm register, frame N``: the same frame registered a second time in one process
  (``register_xray`` and ``write``), as ``ctxreg serve``-like use would: the CT, the network
  and Dr.Jit's kernels loaded once.

The frames are the study's own (made and cached under ``runs/bench_search/TARGET`` as
``benchmarks/search.py`` makes them). Nothing else should run meanwhile (a 2-core machine).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CT = REPO.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"

#: The warm process: registers the frame twice and prints the second call's seconds and stages.
WARM = """
import json, sys, time
from register.api import register_xray
ct, frame, out = sys.argv[1:4]
for k in range(2):
    t0 = time.perf_counter()
    res = register_xray(ct, frame)
    res.write(f"{out}/{k}")
    seconds = time.perf_counter() - t0
print(json.dumps({"seconds": seconds, "timings": res.timings, "search_ran": bool(res.search_ran)}))
"""


def _frames(target: str, indices: list[int]) -> list[Path]:
    """The study's frames ``indices`` of ``target`` (made and cached where missing)."""
    from register.evaluation.evaluate import EvaluationSettings, sample_cases
    from register.evaluation.study import frame_seed, load_study, study_frames
    from sim import load_ct
    from sim.ct.anatomy import anatomy_center
    from sim.projection.geometry import pose_from_params

    study = load_study(REPO / "studies" / "domain_gap.toml")
    chosen = [t for t in study.targets if t.kind == "xray" and t.name == target]
    if not chosen:
        raise SystemExit(f"startup: no xray target {target!r} in studies/domain_gap.toml")
    volume = load_ct(str(CT))
    frames = study_frames(study, chosen[0], volume, anatomy_center(volume))
    poses, _ = sample_cases(EvaluationSettings(cases=max(indices) + 1, seed=study.seed, size=study.size, start="ap"))
    folder = REPO / "runs" / "bench_search" / target
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in indices:
        path = folder / f"case_{i:03d}.dcm"
        frames.cached(path, pose_from_params(poses[i], frames.imager.geometry.sod_mm), frame_seed(study, i))
        paths.append(path)
    return paths


def _wall(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def _wall_any(cmd: list[str]) -> float:
    """Wall seconds of a command whatever its exit status (a refusal's)."""
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def _row(name: str, seconds: list[float], floor: float | None, stages: dict | None = None) -> str:
    lo, med, hi = min(seconds), statistics.median(seconds), max(seconds)
    above = "-" if floor is None else f"{med - floor:+.1f}"
    split = "-" if not stages else ", ".join(f"{k} {v:.2f}" for k, v in stages.items())
    return f"| {name} | {lo:.1f} | {med:.1f} | {hi:.1f} | {above} | {split} |"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=3, help="processes per row (default 3)")
    ap.add_argument("--frames", type=int, nargs="+", default=[1, 3], help="frames of the target (default 1 3)")
    ap.add_argument("--target", default="fluoro-65kV", help="xray target of studies/domain_gap.toml")
    a = ap.parse_args(argv)
    if a.runs < 1 or min(a.frames) < 0:
        ap.error("--runs must be >= 1 and --frames non-negative")
    if not CT.exists():
        print(f"startup: the pelvis CT is missing ({CT}): see ../shared/data/README", file=sys.stderr)
        return 2
    frames = _frames(a.target, a.frames)
    py = sys.executable
    ctxreg = str(Path(py).parent / "ctxreg")
    rows = []
    floor = [_wall([py, "-c", "import torch, mitsuba"]) for _ in range(a.runs)]
    med_floor = statistics.median(floor)
    rows.append(_row("import floor (`import torch, mitsuba`)", floor, None))
    # the refusals that need no torch or Mitsuba: a typo answers before the imports
    typo = [_wall_any([ctxreg, "register", "--ct", str(CT), "--xray", "missing.dcm", "--out", "unused"])
            for _ in range(a.runs)]
    rows.append(_row("refused typo (`register --xray missing.dcm`)", typo, None))
    listing = [_wall([ctxreg, "models"]) for _ in range(a.runs)]
    rows.append(_row("`ctxreg models` (cards, no weights read)", listing, None))
    with tempfile.TemporaryDirectory() as tmp:
        for i, frame in zip(a.frames, frames):
            seconds, stages, ran = [], [], None
            for r in range(a.runs):
                out = Path(tmp) / f"cold{i}_{r}"
                seconds.append(_wall([ctxreg, "register", "--ct", str(CT), "--xray", str(frame), "--out", str(out)]))
                saved = json.loads((out / "result.json").read_text())
                stages.append(saved["timings_s"])
                ran = saved["search_ran"]
            split = {k: statistics.median(s[k] for s in stages) for k in stages[0]}
            rows.append(_row(f"cold register, {a.target} frame {i} (grid {'ran' if ran else 'skipped'})", seconds,
                             med_floor, split))
            print(f"startup: frame {i} cold done", file=sys.stderr, flush=True)
            warm, wstages = [], []
            for r in range(a.runs):
                done = subprocess.run([py, "-c", WARM, str(CT), str(frame), str(Path(tmp) / f"warm{i}_{r}")],
                                      check=True, cwd=REPO, capture_output=True, text=True)
                got = json.loads(done.stdout.strip().splitlines()[-1])
                warm.append(got["seconds"])
                wstages.append(got["timings"])
            split = {k: statistics.median(s[k] for s in wstages) for k in wstages[0]}
            rows.append(_row(f"warm register (second in one process), frame {i}", warm, None, split))
            print(f"startup: frame {i} warm done", file=sys.stderr, flush=True)
    print(f"\n{a.runs} processes per row, wall seconds, {time.strftime('%Y-%m-%d %H:%M')}; 'above floor' is the "
          f"median minus the import floor's median\n")
    print("| call | min s | median s | max s | above floor | median stages s |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(row)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    raise SystemExit(main())
