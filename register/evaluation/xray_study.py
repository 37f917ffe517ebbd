"""Registering realistic C-arm frames as a user would: collimated against open, as ``ctxreg register`` does.

For a CT, :func:`run_xray_study` draws target poses (the evaluation protocol's distribution), renders
each with full physics (spectrum, seven materials, CsI detector, Monte Carlo scatter, quantum
noise) at one of several tube, grid and exposure settings (:data:`CONDITIONS`), and makes two
frames of it that differ only in the collimator:

* **collimated**: a round field (Cios Fusion style: radius and centre varied per case), the blades
  passing 2 % of the signal, black outside (the vendor's electronic shutter);
* **open**: the same detector signal without a collimator.

Both go through the same fluoroscopy display chain (log, bone dark, window over the field, a
gamma curve and edge enhancement of the condition, 12-bit) and are written as 12-bit DICOM with
geometry tags (``DistanceSourceToDetector``, ``DistanceSourceToPatient``, ``ImagerPixelSpacing``)
and Modality RF. Each file is registered as ``ctxreg register`` does (:func:`register.api.register_xray`,
default preprocessing, default method, its outputs written) from AP and from a local start, and the result is scored against
the known pose: rotation and translation error, mTRE over the CT's bone voxels (mm).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from register.api import OUTPUT_FILES, register_xray
from register.evaluation.errors import bone_points, pose_errors
from register.evaluation.evaluate import EvaluationSettings, sample_cases
from register.evaluation.frames import FrameSimulator
from sim.ct.anatomy import anatomy_center
from sim.core.atomic import jsonable
from sim.ct.io import load_ct_spec
from sim.core.errors import USER_OS_ERRORS, CtxregError
from sim.projection.geometry import pose_from_params
from sim.core.outputs import check_output_dir
from sim.physics.display import Collimator, DisplayChain
from sim.physics.imaging import PhysicsSettings, XRayImager

__all__ = ["Condition", "CONDITIONS", "run_xray_study", "summarize_xray_study", "format_xray_study"]


@dataclass(frozen=True)
class Condition:
    """One acquisition: tube (kV, filters), exposure (mAs), grid ratio, and display (gamma,
    unsharp-mask sigma in px and amount)."""

    name: str
    kvp: float
    filters: tuple[tuple[str, float], ...]
    mas: float
    grid_ratio: float
    gamma: float
    unsharp_sigma_px: float
    unsharp_amount: float


#: The acquisition settings cycled over the cases (kV 70-125, with and without a grid, 0.5-4 mAs).
CONDITIONS = (
    Condition("70kV-1mAs-nogrid", 70.0, (("Al", 2.5),), 1.0, 0.0, 0.7, 3.0, 0.8),
    Condition("90kV-4mAs-grid10", 90.0, (("Al", 2.5),), 4.0, 10.0, 1.0, 2.0, 0.5),
    Condition("110kV-0.5mAs-Cu", 110.0, (("Al", 2.5), ("Cu", 0.1)), 0.5, 0.0, 1.3, 4.0, 1.0),
    Condition("125kV-2mAs-grid10", 125.0, (("Al", 2.5),), 2.0, 10.0, 0.8, 0.0, 0.0),
)


def _frames(imager, pose, condition: Condition, seed: int, rng) -> tuple[FrameSimulator, dict, dict]:
    """The collimated and open 12-bit display frames of one pose, with their collimators, and the
    simulator that writes them."""
    chain = DisplayChain(log=True, polarity="bone-dark", window=(1.0, 99.5), gamma=condition.gamma,
                         unsharp_sigma_px=condition.unsharp_sigma_px, unsharp_amount=condition.unsharp_amount,
                         bits=12, shutter="black")
    circle = Collimator(shape="circle", center=tuple(0.5 + rng.uniform(-0.04, 0.04, 2)),
                        radius=float(rng.uniform(0.40, 0.48)), transmission=0.02)
    frames = FrameSimulator(imager, chain, circle)
    raw = frames.raw(pose, seed)
    H, W = raw.shape
    collimated, field = frames.display(raw)
    open_frame, _ = frames.display(raw, collimated=False)
    return (frames, {"pixels": collimated, "collimator": circle.to_dict(), "field_mask": field},
            {"pixels": open_frame, "collimator": None, "field_mask": np.ones((H, W), bool)})


def _register(ct: str, path: Path, out: Path, init: np.ndarray):
    """Register ``path`` as ``ctxreg register --ct CT --xray PATH --out OUT --init ...`` does (default
    method, preprocessing and size; the start as the command line would receive it, 6 decimals) and
    write its outputs into ``out``: ``(outcome, 0)``, or ``(None, 2)`` where it refuses the input
    (the command's exit status)."""
    try:
        check_output_dir(out, OUTPUT_FILES)
        outcome = register_xray(ct, path, init=[f"{v:.6f}" for v in init], log=print,
                                note=lambda text: print(f"ctxreg register: note: {text}", file=sys.stderr))
        outcome.write(out)
    except (CtxregError, *USER_OS_ERRORS) as e:
        print(f"ctxreg register: error: {e}", file=sys.stderr)
        return None, 2
    print(outcome.summary())
    return outcome, 0


def run_xray_study(ct: str, out: str | Path, *, cases: int = 10, size: int = 256, seed: int = 0,
                   starts: tuple[str, ...] = ("ap", "local"), scatter_photons: int = 1_000_000,
                   local_rot_deg: float = 5.0, local_trans_mm: float = 10.0, progress=print) -> list[dict]:
    """Render, write, register and score; returns one row per (case, frame kind, start).

    Files go to ``out/case_NNN/{collimated,open}.dcm`` and the registrations to
    ``out/case_NNN/<kind>_<start>/``. ``size``: detector pixels per side of the frames.
    """
    out = Path(out)
    volume = load_ct_spec(ct)
    center = anatomy_center(volume)
    points = bone_points(volume, 5000, seed=seed)
    targets, local = sample_cases(EvaluationSettings(cases=cases, seed=seed, start="local",
                                                     local_rot_deg=local_rot_deg, local_trans_mm=local_trans_mm))
    rng = np.random.default_rng(seed)
    imagers: dict[str, XRayImager] = {}
    rows: list[dict] = []
    t_start = time.perf_counter()
    for k in range(cases):
        cond = CONDITIONS[k % len(CONDITIONS)]
        if cond.name not in imagers:
            physics = PhysicsSettings(level="full", kvp=cond.kvp, filters=cond.filters, mas=cond.mas,
                                      grid_ratio=cond.grid_ratio, scatter_photons=scatter_photons, noise=True)
            imagers[cond.name] = XRayImager(volume, physics, size=(size, size), center_lps=center)
        imager = imagers[cond.name]
        g = imager.geometry
        T_true = pose_from_params(targets[k], g.sod_mm)
        simulator, *frames = _frames(imager, T_true, cond, seed=seed * 1000 + k, rng=rng)
        case_dir = out / f"case_{k:03d}"
        for kind, frame in zip(("collimated", "open"), frames):
            path = simulator.write(case_dir / f"{kind}.dcm", frame["pixels"])
            for start in starts:
                init = np.zeros(6) if start == "ap" else local[k]
                reg_dir = case_dir / f"{kind}_{start}"
                t0 = time.perf_counter()
                outcome, code = _register(ct, path, reg_dir, init)
                seconds = time.perf_counter() - t0
                row = {"case": k, "condition": cond.name, "kind": kind, "start": start, "exit_code": code,
                       "seconds": seconds, "target_params": targets[k].tolist(), "init_params": init.tolist(),
                       "collimator": frame["collimator"]}
                if code == 0:
                    err = pose_errors(outcome.pose, T_true, points, center, g)
                    truth_field = frame["field_mask"]
                    inp = jsonable(outcome.xray_input)
                    row.update({k2: err[k2] for k2 in ("rot_err_deg", "trans_err_mm", "mtre_mm")},
                               verdict=outcome.verdict.label,
                               intensity=(inp["polarity_check"] or inp["intensity"])["polarity"],
                               decided_polarity=inp["intensity"]["polarity"],
                               scale=inp["intensity"]["scale"],
                               field_kind=inp["field"]["kind"],
                               field_valid_fraction=inp["field"]["valid_fraction"],
                               truth_field_fraction=float(truth_field.mean()))
                rows.append(row)
        done = k + 1
        rate = done / (time.perf_counter() - t_start)
        if progress:
            progress(f"case {done}/{cases} ({cond.name}): {rate * 60:.1f} cases/min, "
                     f"ETA {(cases - done) / rate:.0f} s")
    return rows


def summarize_xray_study(rows: list[dict], success_mtre_mm: float = 10.0) -> dict:
    """Per (frame kind, start): cases, successes (mTRE < 10 mm), success rate, median / mean errors,
    failed runs, median seconds."""
    summary: dict = {}
    for kind in sorted({r["kind"] for r in rows}):
        for start in sorted({r["start"] for r in rows}):
            sel = [r for r in rows if r["kind"] == kind and r["start"] == start]
            if not sel:
                continue
            ok = [r for r in sel if r["exit_code"] == 0]
            mtre = np.array([r["mtre_mm"] for r in ok]) if ok else np.zeros(0)
            rot = np.array([r["rot_err_deg"] for r in ok]) if ok else np.zeros(0)
            summary[f"{kind}/{start}"] = {
                "cases": len(sel), "errors": len(sel) - len(ok),
                "successes": int(np.sum(mtre < success_mtre_mm)),
                "success_rate": float(np.sum(mtre < success_mtre_mm) / len(sel)),
                "median_rot_deg": float(np.median(rot)) if ok else None,
                "median_mtre_mm": float(np.median(mtre)) if ok else None,
                "mean_mtre_mm": float(np.mean(mtre)) if ok else None,
                "median_seconds": float(np.median([r["seconds"] for r in sel])),
                "bone_dark_decided": sum(r.get("intensity") == "bone-dark" for r in ok),
                "bone_dark_before_check": sum(r.get("decided_polarity") == "bone-dark" for r in ok),
            }
    return summary


def format_xray_study(summary: dict) -> str:
    """A Markdown table of :func:`summarize_xray_study`."""
    lines = ["| frames / start | cases | mTRE < 10 mm | median rot (deg) | median mTRE (mm) | mean mTRE (mm) "
             "| polarity right | s / registration |", "|---|---|---|---|---|---|---|---|"]
    for key, s in summary.items():
        def f(v, fmt):
            return "-" if v is None else format(v, fmt)
        lines.append(f"| {key} | {s['cases']} | {s['successes']} ({100 * s['success_rate']:.0f} %) | "
                     f"{f(s['median_rot_deg'], '.2f')} | {f(s['median_mtre_mm'], '.1f')} | "
                     f"{f(s['mean_mtre_mm'], '.1f')} | {s['bone_dark_decided']}/{s['cases'] - s['errors']} | "
                     f"{s['median_seconds']:.1f} |")
    return "\n".join(lines)
