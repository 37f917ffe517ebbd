"""Where the network's first step from AP goes wrong: a study's frames against the training's own pairs at the same poses.

    .venv/bin/python benchmarks/network_first_step.py [--model pelvis_batched_small] [--cases 20] [--draws 4]
        [--study studies/domain_gap.toml] [--target fluoro-65kV] [--out runs/bench_search]
        [--rows frame frame-pixels frame-pixels-poly frame-pixels-sks frame-pixels-sks-texture training
                training-vp line]

Registration from AP starts with a far pair, and there the network's prediction on the study's
frames is far worse than on the training's far validation pairs (docs/benchmarks.md, "The network
on realistic frames"). Three things differ between the two: the target image (a study frame,
12-bit DICOM through registration's preparation, against a target of the training's randomized
two-basis pipeline), the CT (the real pelvis CT against held-out virtual patients) and the poses
(the study's protocol against the training's draws). This script holds the poses fixed (each
frame's true pose, current at registration's AP start, ``register.api.parse_init("ap")``) and
changes one thing per row (``--rows``, default all; ``frame`` registers every frame with the
network alone, the slow one):

* ``frame``: the study's frame through ``register_xray(method="contextual")`` (its first
  prediction; the frames cached in ``--out`` as ``benchmarks/search.py`` makes them);
* ``frame-pixels``: the same frames' displayed pixels (made again from their seeds), area-averaged
  to the training's image size, through the training's preparation with their true field and
  polarity (:meth:`learn.batched.BatchedPairs.displayed_pairs`): the frame's appearance without
  registration's preparation (field detection, polarity and intensity decisions, filters);
* ``frame-pixels-poly``: the same, the frames rendered again at physics level ``poly`` (no Monte
  Carlo scatter, no grid; the same spectrum, exposure, noise seed, collimator and display): what
  the frames' scatter costs;
* ``frame-pixels-sks``: the ``poly`` frames with the scatter-kernel model's scatter added in its
  place (:func:`sim.physics.scatter_kernel.default_table` at the frames' kV and grid, the
  frames' air gap, of the exposure before the collimator as the frames' Monte Carlo is, with its
  quantum noise): whether the training's ``sks`` scatter does to the network what the frames'
  Monte Carlo scatter does;
* ``frame-pixels-sks-texture``: the same with the ``sks`` texture of :data:`FRAME_TEXTURE`
  (:func:`sim.randomize.sks_texture`), about the relative structure of the frames' Monte Carlo
  scatter (its estimate's noise at 10^6 histories);
* ``training`` (training pairs, real CT): targets of the training's own pipeline
  (:meth:`learn.batched.BatchedPairs.pairs`, the checkpoint's ``[train.randomize]`` with every
  target realistic, ``--draws`` draws per pose) on the real CT (a training subject);
* ``training-vp`` (training pairs, held-out VP): the same on the first validation virtual patient;
* ``line`` (line DRR targets, real CT): the ideal line-DRR target (no appearance gap at all).

Columns (mean over frames and draws): rotation error ``|g_rot - g_rot,true|`` (deg) and
translation error (mm) as the training's validation computes them, their size relative to the true
label, and the cosine between the predicted and the true rotation (translation) part: the
iteration moves along ``-g``, so a cosine near 1 is a step in the right direction whatever its
length. The true first label is printed for scale (``|g|`` is twice the pose distance).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository first: benchmarks/learn.py and register.py are not the packages
from network_on_frames import FrameTargetError, study_frame_files  # noqa: E402  (benchmarks/)
from timing import add_frame_arguments, input_problem  # noqa: E402  (benchmarks/timing.py)

#: Pair numbers of the synthetic rows start here: far beyond any training batch's
#: (``k * MAX_BATCH + i`` for k below 10^6), so their draws are not the training's.
INDEX_BASE = 1 << 40

#: ``(strength, sigma as a fraction of the shorter side)`` of the row ``frame-pixels-sks-texture``:
#: a 65 kV frame's Monte Carlo scatter (128 x 128, 10^6 histories) deviates from an 8 px Gaussian
#: of itself by 7-10 % (mean 8.4 % over 4 frames), with the power spectrum of this texture at sigma
#: 0.03 (3.8 px) and strength 0.12 (whose own such deviation is 8-9 %): benchmarks/scatter_structure.py,
#: docs/journal/training.md "The frames' Monte Carlo structure".
FRAME_TEXTURE = (0.12, 0.03)

#: The rows, in order (module doc).
ROWS = ("frame", "frame-pixels", "frame-pixels-poly", "frame-pixels-sks", "frame-pixels-sks-texture", "training",
        "training-vp", "line")


def _scores(g_pred: np.ndarray, g_true: np.ndarray) -> np.ndarray:
    """``(K, 6)`` rad/mm each -> ``(K, 6)``: rotation error deg, translation error mm, their
    relative sizes, the rotation and translation cosines."""
    out = []
    for part in (slice(0, 3), slice(3, 6)):
        err = np.linalg.norm(g_pred[:, part] - g_true[:, part], axis=1)
        size = np.linalg.norm(g_true[:, part], axis=1)
        cos = (g_pred[:, part] * g_true[:, part]).sum(1) / np.maximum(
            np.linalg.norm(g_pred[:, part], axis=1) * size, 1e-12)
        out.append((err, err / np.maximum(size, 1e-12), cos))
    (er, rr, cr), (et, rt, ct) = out
    return np.stack([np.degrees(er), et, rr, rt, cr, ct], 1)


def _training_pairs(model, randomize: dict, subject_split: str, ideal: float, seed: int):
    """A :class:`learn.batched.BatchedPairs` of the pelvis campaign drawing as ``model``'s run
    drew (its randomization with ``ideal`` set), untransformed (the predictor normalises),
    restricted to the split's first subject (the real CT in ``train``, a held-out virtual
    patient in ``val``)."""
    from learn.batched import BatchedPairs
    from learn.online import NearPairs
    from sim.campaign.config import load_campaign
    from sim.randomize import DomainRandomization

    cfg = model.checkpoint.config or {}
    campaign = load_campaign(ROOT / "campaigns" / "pelvis_vp.toml")
    randomization = DomainRandomization.from_table({**randomize, "ideal": ideal}, "train.randomize")
    pairs = BatchedPairs(campaign, subject_split, near=NearPairs(), seed=seed, randomization=randomization,
                         current_field=cfg.get("current_field", "masked"), framing=cfg.get("framing", "field"),
                         tables=ROOT / "runs" / "bench_pairs_tables")
    pairs.subjects = pairs.subjects[:1]  # only this subject's volume is built
    return pairs


def _poly_frames(study_path, target: str, volume, center):
    """The frame simulator of a study's ``xray`` target at physics level ``poly``: its settings
    without the Monte Carlo scatter and grid (the settings that mean something only at ``full``)."""
    from dataclasses import replace

    from register.evaluation.study import load_study, study_frames
    from sim.physics.settings import SETTINGS

    study = load_study(study_path)
    t = next(t for t in study.targets if t.name == target)
    physics = {k: v for k, v in t.physics.items() if k == "level" or "poly" in SETTINGS[k].levels}
    return study_frames(study, replace(t, physics={**physics, "level": "poly"}), volume, center)


def _with_sks(raw, simulator, physics, pose, seed: int, texture=None):
    """``raw`` ``(H, W)`` (a ``poly`` frame, before its collimator) with the default scatter-kernel
    table's scatter at ``physics``' kV and grid ratio and ``pose``'s air gap added, with its
    quantum noise (a normal draw of ``seed``) and, given ``(strength, sigma fraction)``, a texture
    (:func:`sim.randomize.sks_texture` of another draw)."""
    from sim.physics.scatter_kernel import default_table, detector_gap_mm
    from sim.randomize import sks_texture

    g = simulator.imager.geometry
    model = default_table().model_for(float(physics.kvp), float(physics.grid_ratio))
    flat = float(simulator.imager.flat)
    tau = -np.log(np.maximum(raw, 1e-12 * flat) / flat)
    sc = model.predict(tau, g, flat_signal=flat, gap_mm=float(detector_gap_mm(pose, g)[0]))
    rng = np.random.default_rng([seed, 28])
    noise = rng.standard_normal(raw.shape)
    if texture is not None:
        sc = sc * sks_texture(rng.standard_normal(raw.shape), texture[0], texture[1] * min(raw.shape))
    return raw + sc + np.sqrt(sc * model.signal_per_photon) * noise


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_frame_arguments(ap, cases=20)
    ap.add_argument("--model", default="pelvis_batched_small",
                    help="a shipped model's name or a checkpoint trained with [train.randomize] and pairs = "
                         "'batched' (default pelvis_batched_small)")
    ap.add_argument("--draws", type=int, default=4, help="randomization draws per pose for the synthetic rows (default 4)")
    ap.add_argument("--study", default=str(ROOT / "studies" / "domain_gap.toml"))
    ap.add_argument("--target", default="fluoro-65kV", help="an xray target of --study (default fluoro-65kV)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_search"), help="frame cache (frames in OUT/TARGET)")
    ap.add_argument("--rows", nargs="+", choices=ROWS, default=list(ROWS), help="the rows (module doc; default all)")
    a = ap.parse_args()
    problem = input_problem("network_first_step", a.ct, a.cases)
    if problem or a.draws < 1:
        print(problem or "network_first_step: --draws must be >= 1", file=sys.stderr)
        return 2

    from learn.labels import geodesic_label
    from learn.predict import NetworkPredictor
    from register.api import parse_init, register_xray
    from register.evaluation.study import frame_refusals
    from sim.projection.geometry import pose_from_params

    model = NetworkPredictor(a.model)
    randomize = (model.checkpoint.config or {}).get("randomize")
    if randomize is None or (model.checkpoint.config or {}).get("pairs") != "batched":
        print(f"network_first_step: {a.model} was not trained on batched randomized pairs ([train.randomize], "
              f"pairs = 'batched'): there are no training pairs to compare with", file=sys.stderr)
        return 2
    try:
        volume, center, sod, cases, frames = study_frame_files(a.study, a.target, a.ct, a.cases, a.out)
    except FrameTargetError as e:
        print(f"network_first_step: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    start = pose_from_params(parse_init("ap"), sod)  # registration's start (init="ap")
    t_true = np.stack([T for _, T, _ in cases])
    n = len(t_true)
    g_frames = np.asarray(geodesic_label(t_true, np.broadcast_to(start, t_true.shape)), np.float64)
    rows = []
    if "frame" in a.rows:
        scores = []
        for (i, T_true, path), g_true in zip(cases, g_frames):
            try:
                res = register_xray(volume, path, center=center, method="contextual", model=model)
            except frame_refusals():
                continue
            traj = res.result.trajectory
            if not np.allclose(pose_from_params(np.asarray(traj["params"])[0], sod), start, atol=1e-9):
                print(f"network_first_step: frame {i} did not start at AP", file=sys.stderr)
                return 1
            scores.append(_scores(np.asarray(traj["g"], np.float64)[:1], g_true[None])[0])
            print(f"network_first_step: frame {i} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        rows.append(("frame (registration's preparation)", np.mean(scores, 0), len(scores)))
    seed = int((model.checkpoint.config or {}).get("seed", 0))
    for key, name in (("frame-pixels", "frame pixels, training's preparation (true field, polarity)"),
                      ("frame-pixels-poly", "the same, frames without scatter (poly)"),
                      ("frame-pixels-sks", "the same, poly frames + the kernel model's scatter (sks)"),
                      ("frame-pixels-sks-texture", "the same, sks with a texture")):
        if key not in a.rows:
            continue
        import torch
        import torch.nn.functional as F

        simulator = frames if key == "frame-pixels" else _poly_frames(a.study, a.target, volume, center)
        pairs = _training_pairs(model, randomize, "train", 0.0, seed)
        h, w = pairs.geometry.height, pairs.geometry.width
        shown = []
        for i, T_true, _ in cases:
            raw = simulator.raw(T_true, frames.seeds[i])
            if key.startswith("frame-pixels-sks"):
                raw = _with_sks(raw, simulator, frames.imager.physics, T_true, frames.seeds[i],
                                FRAME_TEXTURE if key.endswith("texture") else None)
            pixels, _ = simulator.display(raw)
            shown.append(F.interpolate(torch.from_numpy(np.asarray(pixels, np.float64))[None, None], size=(h, w),
                                       mode="area")[0, 0])
        field = simulator.collimator.mask(h, w) if simulator.collimator is not None else np.ones((h, w), bool)
        target, current, _ = pairs.displayed_pairs(
            torch.stack(shown), torch.from_numpy(np.repeat(field[None], n, 0)), np.zeros(n, np.int64), t_true,
            np.repeat(start[None], n, 0), log_display=bool(simulator.chain.log),
            bone_dark=simulator.chain.polarity == "bone-dark")
        pred = model.predict(target[:, 0].numpy(), current[:, 0].numpy()).g
        rows.append((name, _scores(pred, g_frames).mean(0), n))
        print(f"network_first_step: {name} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    T_a = np.repeat(t_true, a.draws, 0)
    T_b = np.repeat(start[None], len(T_a), 0)
    g_true = np.repeat(g_frames, a.draws, 0)
    for key, name, split, ideal in (("training", "training pairs, real CT", "train", 0.0),
                                    ("training-vp", "training pairs, held-out VP", "val", 0.0),
                                    ("line", "line DRR targets, real CT", "train", 1.0)):
        if key not in a.rows:
            continue
        pairs = _training_pairs(model, randomize, split, ideal, seed)
        target, current, _ = pairs.pairs(np.zeros(len(T_a), np.int64), T_a, T_b, INDEX_BASE + np.arange(len(T_a)))
        pred = model.predict(target[:, 0].numpy(), current[:, 0].numpy()).g
        rows.append((name, _scores(pred, g_true).mean(0), len(T_a)))
        print(f"network_first_step: {name} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    size = np.array([np.degrees(np.linalg.norm(g_frames[:, :3], axis=1)).mean(),
                     np.linalg.norm(g_frames[:, 3:], axis=1).mean()])
    print(f"\n{a.target}: the network's first prediction from AP, {n} frames' true poses, model {a.model} "
          f"(true first label {size[0]:.1f} deg / {size[1]:.1f} mm on average; {time.strftime('%Y-%m-%d %H:%M')})\n")
    print("| target | pairs | rotation error deg (relative) | translation error mm (relative) | cosine rotation "
          "| cosine translation |")
    print("|---|---|---|---|---|---|")
    for name, sc, count in rows:
        print(f"| {name} | {count} | {sc[0]:.1f} ({sc[2]:.2f}) | {sc[1]:.1f} ({sc[3]:.2f}) | {sc[4]:.2f} | {sc[5]:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
