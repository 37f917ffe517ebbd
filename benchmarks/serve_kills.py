"""``ctxreg serve`` killed at random moments: are its frame folders whole or absent, and does a restart
register exactly the frames that were not done? (issue 52)

Usage (from the repository root, after set-up; about 25 s a trial on 2 cores)::

    .venv/bin/python benchmarks/serve_kills.py [--trials 20] [--seed 0]

A synthetic case: the built-in phantom (3 mm) as a NIfTI CT and 8 DRRs of it at known poses as
DICOM frames in a watched folder. Each trial starts ``ctxreg serve --xray FOLDER --frames 8`` (the
real command: CT, kernels, CMA-ES at 64 px; a whole run takes 6-8 s here), kills it after a random
1-8 s with SIGKILL or SIGTERM
(alternating), then checks every visible frame folder (``result.json``, ``frame.json`` and the
figures all there) and restarts the same command, which must register exactly the frames with no
folder and skip the others. Prints one row per trial and a summary line; exit status 1 if any
trial broke a rule. The unit tests (tests/register/test_serve.py) check the same rules on serve's
machinery with a stand-in registration, in CI.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

POSES = [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [6.0, -4.0, 3.0, 8.0, -6.0, 15.0], [-5.0, 3.0, -4.0, -6.0, 5.0, -10.0],
         [4.0, 5.0, 2.0, 5.0, 8.0, 20.0], [-3.0, -6.0, 5.0, -8.0, -4.0, 10.0], [7.0, 2.0, -2.0, 3.0, -9.0, -15.0],
         [-6.0, 4.0, 4.0, 9.0, 3.0, 5.0], [2.0, -3.0, -5.0, -4.0, 7.0, -20.0]]
N = len(POSES)


def _case(folder: Path) -> tuple[Path, Path, np.ndarray]:
    from register.xray.io import write_xray_dicom
    from sim.ct.anatomy import anatomy_center
    from sim.ct.io import save_nifti
    from sim.projection.drr import DRRRenderer, RenderSettings
    from sim.ct.phantom import make_pelvis_phantom

    vol = make_pelvis_phantom(3, spacing_mm=3.0)
    ct = folder / "ct.nii.gz"
    save_nifti(vol, ct)
    center = anatomy_center(vol)
    r = DRRRenderer(vol, RenderSettings(size=(128, 128)), center_lps=center)
    incoming = folder / "incoming"
    incoming.mkdir()
    for k, pose in enumerate(POSES):
        g = r.geometry
        write_xray_dicom(incoming / f"frame{k}.dcm", r.render_params(np.array(pose))[0],
                         pixel_spacing_mm=g.pixel_spacing_mm, sdd_mm=g.sdd_mm, sod_mm=g.sod_mm)
    return ct, incoming, center


def _folders(out: Path) -> tuple[list[str], list[str], list[str]]:
    """(whole frame folders, broken ones, hidden leftovers) of ``out``."""
    whole, broken, hidden = [], [], []
    if not out.exists():
        return whole, broken, hidden
    for p in sorted(out.iterdir()):
        if p.name.startswith("."):
            if p.name != ".ctxreg.lock":
                hidden.append(p.name)
        elif p.is_dir():
            names = {x.name for x in p.iterdir()}
            (whole if {"result.json", "frame.json", "overlay.png", "convergence.png"} <= names else broken).append(p.name)
    return whole, broken, hidden


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rng = random.Random(a.seed)
    ctxreg = str(Path(sys.executable).parent / "ctxreg")
    bad = 0
    with tempfile.TemporaryDirectory() as tmp:
        ct, incoming, center = _case(Path(tmp))
        command = [ctxreg, "serve", "--ct", str(ct), "--xray", str(incoming), "--frames", str(N), "--method", "cmaes",
                   "--size", "64", "64", "--center", *map(str, center), "--ct-cache", "off"]
        print("| trial | signal | after s | whole folders | broken | hidden leftovers | restart registered | "
              "restart skipped | rules kept |")
        print("|---|---|---|---|---|---|---|---|---|")
        for trial in range(a.trials):
            out = Path(tmp) / f"out{trial}"
            sig = signal.SIGKILL if trial % 2 == 0 else signal.SIGTERM
            after = rng.uniform(1.0, 8.0)  # a whole run takes about 6-8 s here: kills land in it
            p = subprocess.Popen([*command, "--out", str(out)], cwd=REPO, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
            try:
                p.wait(timeout=after)
            except subprocess.TimeoutExpired:
                p.send_signal(sig)
                p.communicate(timeout=120)
            whole, broken, _ = _folders(out)
            r = subprocess.run([*command, "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=600)
            lines = [json.loads(x) for x in r.stdout.splitlines() if x.startswith("{")]
            registered = [Path(x["xray"]).stem for x in lines if "out" in x]
            skipped = r.stderr.count("already registered in")
            after_whole, after_broken, after_hidden = _folders(out)
            done_before = {w.split("_")[0] for w in whole}
            ok = (not broken and not after_broken and not after_hidden and r.returncode == 0
                  and sorted(after_whole) == [f"frame{k}" for k in range(N)]
                  and sorted(registered) == sorted({f"frame{k}" for k in range(N)} - done_before)
                  and skipped == len(done_before))
            bad += not ok
            print(f"| {trial} | {signal.Signals(sig).name} | {after:.1f} | {len(whole)} | {len(broken)} | "
                  f"{len(after_hidden)} | {len(registered)} | {skipped} | {'yes' if ok else 'NO'} |", flush=True)
    print(f"\n{a.trials - bad} of {a.trials} trials kept every rule ({time.strftime('%Y-%m-%d %H:%M')}, 2-core CPU)")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
