"""The network's own prediction error on a study's realistic frames, along its own iteration.

    .venv/bin/python benchmarks/network_on_frames.py [--models pelvis_line pelvis_batched ...] [--cases 20]
        [--study studies/domain_gap.toml] [--target fluoro-65kV] [--out runs/bench_search] [--mask network|valid|field]

The training's validation measures single predictions on virtual patients' pairs; registration
meets the real CT's frames and the poses its own iteration visits. This script measures the
second: each frame (the first ``--cases`` poses of a study's ``xray`` target, from AP, the frames
cached in ``--out`` as ``benchmarks/search.py`` makes them) is registered with
``method="contextual"`` (``register_xray``: the network alone), and at every pose ``T_k`` of its
trajectory the predicted gradient ``g_k`` is compared with the true label
``geodesic_label(T_true, T_k)`` (:mod:`learn.labels`): rotation error ``|g_rot - g_rot,true|``
(deg) and translation error ``|g_trans - g_trans,true|`` (mm), as the training's validation
computes them.

``--mask`` chooses what the network is shown (what registration does is the default,
``network``: the detected field minus drawn overlays, its clipped plateaus kept,
:attr:`register.xray.prepare.PreparedXRay.network_mask`). ``valid``: registration's valid pixels,
the field minus every exclusion of :func:`register.xray.field.detect_field` (saturated / empty
plateaus and overlays; what registration showed the network before 2026-11-26). ``field``: the
detected field alone for every stage of the registration (an experiment; training's targets are
masked by the true field only).

Prints one table: per model, the error of the first prediction (at AP, the far pair registration
starts from), the mean over every prediction of the iteration, the mean over the predictions made
within 10 deg of the truth (the near pairs), the size of the true first label (for scale), and the
network alone's final mean rotation / translation error.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository first: benchmarks/learn.py and register.py are not the packages
from timing import add_frame_arguments, input_problem  # noqa: E402  (benchmarks/timing.py)


def _errors(g_pred: np.ndarray, g_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(K, 6)`` rad/mm labels -> per-prediction rotation (deg) and translation (mm) errors."""
    rot = np.degrees(np.linalg.norm(g_pred[:, :3] - g_true[:, :3], axis=1))
    return rot, np.linalg.norm(g_pred[:, 3:] - g_true[:, 3:], axis=1)


class FrameTargetError(ValueError):
    """An unknown ``--target`` of the study (one line for the user)."""


def study_frame_files(study_path, target: str, ct, cases: int, out):
    """The first ``cases`` frames of a study's ``xray`` target from AP, simulated into
    ``out/target`` where missing or made by other settings
    (:meth:`register.evaluation.frames.FrameSimulator.cached`): ``(volume, centre (3,) mm, sod_mm,
    [(i, T_true (4, 4) mm, path)], simulator)`` (the
    :class:`register.evaluation.frames.FrameSimulator` and the frames' seeds as
    ``simulator.seeds``, ``{i: seed}``, to make a frame's pixels again).
    :class:`FrameTargetError` names an unknown target."""
    from register.evaluation.evaluate import EvaluationSettings, sample_cases
    from register.evaluation.study import frame_seed, load_study, study_frames
    from sim import load_ct
    from sim.ct.anatomy import anatomy_center
    from sim.projection.geometry import pose_from_params

    study = load_study(study_path)
    targets = {t.name: t for t in study.targets if t.kind == "xray"}
    if target not in targets:
        raise FrameTargetError(f"--target must be one of {sorted(targets)}")
    volume = load_ct(ct)
    center = anatomy_center(volume)
    frames = study_frames(study, targets[target], volume, center)
    sod = frames.imager.geometry.sod_mm
    poses, _ = sample_cases(EvaluationSettings(cases=cases, seed=study.seed, size=study.size, start="ap"))
    folder = Path(out) / target
    folder.mkdir(parents=True, exist_ok=True)
    found = []
    frames.seeds = {i: frame_seed(study, i) for i in range(len(poses))}
    for i, params in enumerate(poses):
        T_true = pose_from_params(params, sod)
        path = folder / f"case_{i:03d}.dcm"
        frames.cached(path, T_true, frames.seeds[i])
        found.append((i, T_true, path))
    return volume, center, sod, found, frames


def add_monte_carlo_frame_arguments(ap, *, cases: int) -> None:
    """The frame options of the scripts that read a ``full`` target's Monte Carlo scatter
    (``--ct``, ``--cases`` with its default ``cases``, ``--study``, ``--target``, ``--out``), for
    :func:`monte_carlo_frames`."""
    add_frame_arguments(ap, cases=cases)
    ap.add_argument("--study", default=str(ROOT / "studies" / "domain_gap.toml"),
                    help="a study file (default studies/domain_gap.toml)")
    ap.add_argument("--target", default="fluoro-65kV",
                    help="an xray target of --study at physics level full (default fluoro-65kV)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_search"), help="frame cache (frames in OUT/TARGET)")


def monte_carlo_frames(study_path, target: str, ct, cases: int, out):
    """:func:`study_frame_files`'s ``[(i, T_true, path)]`` and simulator for a target at physics level
    ``full``; :class:`FrameTargetError` names an unknown target or one without Monte Carlo scatter."""
    _, _, _, found, frames = study_frame_files(study_path, target, ct, cases, out)
    im = frames.imager
    if im.scatter is None:
        raise FrameTargetError(f"target {target} has no Monte Carlo scatter (physics level "
                               f"{im.physics.level!r}, not 'full')")
    return found, frames


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_frame_arguments(ap, cases=20)
    ap.add_argument("--models", nargs="+", default=["pelvis_line"],
                    help="shipped model names or checkpoints (default pelvis_line)")
    ap.add_argument("--study", default=str(ROOT / "studies" / "domain_gap.toml"))
    ap.add_argument("--target", default="fluoro-65kV", help="an xray target of --study (default fluoro-65kV)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_search"), help="frame cache (frames in OUT/TARGET)")
    ap.add_argument("--mask", choices=("network", "valid", "field"), default="network",
                    help="what the network is shown: registration's network mask (default: the field minus "
                         "overlays), its valid pixels (minus plateaus too) or the field alone everywhere")
    a = ap.parse_args()
    problem = input_problem("network_on_frames", a.ct, a.cases)
    if problem:
        print(problem, file=sys.stderr)
        return 2

    from learn.labels import geodesic_label
    from register.api import register_xray
    from register.evaluation.errors import bone_points, pose_errors
    from register.evaluation.study import frame_refusals
    from sim.projection.geometry import pose_from_params

    if a.mask == "valid":  # the network shown what CMA-ES is: the valid pixels
        import register.api as api

        api.network_view = lambda predictor, prepared: None
    if a.mask == "field":  # the experiment: the detected field's mask without the exclusions inside it
        import dataclasses

        import register.xray.prepare as prepare
        import register.xray.preprocess as preprocess

        detect = preprocess.detect_field

        def field_alone(image, settings=None):
            found = detect(image, settings)
            return dataclasses.replace(found, mask=found.field_mask.copy(), overlay=np.zeros_like(found.field_mask))

        preprocess.detect_field = prepare.detect_field = field_alone
    try:
        volume, center, sod, cases, _ = study_frame_files(a.study, a.target, a.ct, a.cases, a.out)
    except FrameTargetError as e:
        print(f"network_on_frames: {e}", file=sys.stderr)
        return 2
    points = bone_points(volume, 2000, 0)
    rows = []
    t0 = time.perf_counter()
    for model in a.models:
        first, every, near, size0, final, refused = [], [], [], [], [], 0
        for i, T_true, path in cases:
            try:
                res = register_xray(volume, path, center=center, method="contextual", model=model)
            except frame_refusals():
                refused += 1
                continue
            traj = res.result.trajectory
            g_pred = np.asarray(traj["g"], np.float64)
            T_k = np.stack([pose_from_params(p, sod) for p in np.asarray(traj["params"])[:len(g_pred)]])
            g_true = np.asarray(geodesic_label(np.broadcast_to(T_true, T_k.shape), T_k), np.float64)
            rot, trans = _errors(g_pred, g_true)
            first.append((rot[0], trans[0]))
            every.append(np.stack([rot, trans], 1))
            close = np.degrees(np.linalg.norm(g_true[:, :3], axis=1)) / 2 < 10  # |log| = |g| / 2 within 10 deg
            if close.any():
                near.append(np.stack([rot[close], trans[close]], 1))
            size0.append((np.degrees(np.linalg.norm(g_true[0, :3])), np.linalg.norm(g_true[0, 3:])))
            e = pose_errors(res.pose, T_true, points, center, np.eye(3, 4), np.eye(3, 4), 1.0)
            final.append((e["rot_err_deg"], e["trans_err_mm"]))
            print(f"network_on_frames: {model} frame {i}: first prediction {rot[0]:.1f} deg / {trans[0]:.1f} mm "
                  f"(true {size0[-1][0]:.1f} deg / {size0[-1][1]:.1f} mm), {len(rot)} predictions, final "
                  f"{e['rot_err_deg']:.1f} deg / {e['trans_err_mm']:.1f} mm ({time.perf_counter() - t0:.0f} s)",
                  file=sys.stderr, flush=True)
        f, s0, fin = np.array(first), np.array(size0), np.array(final)
        ev = np.concatenate(every) if every else np.full((1, 2), np.nan)
        nr = np.concatenate(near) if near else np.full((1, 2), np.nan)
        rows.append((model, len(first), refused, f.mean(0), ev.mean(0), len(ev), nr.mean(0), len(nr), s0.mean(0),
                     fin.mean(0)))
    print(f"\n{a.target}: the first {a.cases} frames from AP, the network alone (method contextual, mask {a.mask}); "
          f"errors of the "
          f"predicted gradient against the true label, mean rotation deg / translation mm "
          f"({time.strftime('%Y-%m-%d %H:%M')})\n")
    print("| model | frames (refused) | first prediction (at AP) | every prediction (n) | within 10 deg of the truth (n) "
          "| true first label | final pose error |")
    print("|---|---|---|---|---|---|---|")
    for model, n, ref, f, ev, nev, nr, nnr, s0, fin in rows:
        print(f"| {model} | {n} ({ref}) | {f[0]:.1f} / {f[1]:.1f} | {ev[0]:.1f} / {ev[1]:.1f} ({nev}) | "
              f"{nr[0]:.1f} / {nr[1]:.1f} ({nnr}) | {s0[0]:.1f} / {s0[1]:.1f} | {fin[0]:.1f} / {fin[1]:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
