"""Where the contextual network loses a realistic frame: its appearance, or its collimated field.

For the first ``--cases`` poses of the evaluation protocol (seed 0, from AP) this renders the
study target ``--target`` of ``studies/domain_gap.toml`` (full physics, collimator, display chain,
12-bit DICOM; cached in ``--frames``), prepares each frame as ``ctxreg register`` does, and runs
the contextual iteration alone (no CMA-ES) of each ``--model`` on three targets of the same pose:

* ``frame``: the prepared realistic frame with its detected field (what registration sees: a
  network trained on toned targets is shown its toned version, as ``ctxreg register`` does);
* ``line+field``: the line DRR at the true pose on the same cropped detector, with the same field;
* ``line``: that line DRR without a field (the whole cropped detector).

``frame`` against ``line+field`` is the appearance gap, ``line+field`` against ``line`` the cost of
the partial view. Prints one row per model and target: mean rotation (deg) and translation (mm)
errors, median mTRE (mm) and the shares under 10 and 20 mm mTRE.

    .venv/bin/python studies/field_probe.py --model pelvis_line pelvis_realistic --cases 20
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", nargs="+", default=["pelvis_line"], help="shipped model names or checkpoints")
    ap.add_argument("--cases", type=int, default=20, help="poses of the protocol (default 20)")
    ap.add_argument("--target", default="fluoro-65kV", help="an xray target of studies/domain_gap.toml")
    ap.add_argument("--ct", default=str(ROOT.parent / "shared/data/ct/pelvis_abdomen_3mm.nii.gz"))
    ap.add_argument("--frames", default=str(ROOT / "runs/field_probe"), help="frame cache folder")
    args = ap.parse_args(argv)
    if not Path(args.ct).is_file():
        print(f"field_probe: no CT at {args.ct} (the shared data is absent)", file=sys.stderr)
        return 2

    from register.evaluation.errors import bone_points, pose_errors
    from register.evaluation.evaluate import EvaluationSettings, sample_cases
    from register.engines.methods import build_method, load_predictor
    from register.xray.prepare import prepare_xray
    from register.evaluation.study import frame_seed, load_study, study_frames
    from register.xray.io import load_xray
    from sim import load_ct
    from sim.ct.anatomy import anatomy_center
    from sim.projection.geometry import pose_from_params
    from sim.physics.imaging import moving_renderer

    study = load_study(ROOT / "studies" / "domain_gap.toml")
    targets = {t.name: t for t in study.targets if t.kind == "xray"}
    if args.target not in targets:
        print(f"field_probe: --target must be one of {sorted(targets)}", file=sys.stderr)
        return 2
    target = targets[args.target]
    volume = load_ct(args.ct)
    center = anatomy_center(volume)
    poses, _ = sample_cases(EvaluationSettings(cases=args.cases, seed=0, size=(128, 128), start="ap"))
    frames = study_frames(study, target, volume, center)  # the study's frames (its seed, 128 px)
    imager = frames.imager
    folder = Path(args.frames) / args.target
    folder.mkdir(parents=True, exist_ok=True)
    points = bone_points(volume, 2000, 0)
    cases = []  # (prepared, T_true, line DRR at the truth)
    for i, params in enumerate(poses):
        T_true = pose_from_params(params, imager.geometry.sod_mm)
        path = folder / f"case_{i:03d}.dcm"
        if not path.exists():
            frames.simulate(path, T_true, frame_seed(study, i))
        prep = prepare_xray(load_xray(path), volume=volume, center_lps=center, init_params=np.zeros(6),
                            size=(128, 128))
        g = prep.geometry
        line = moving_renderer(volume, None, size=(g.height, g.width), center_lps=center, geometry=g).render(T_true)[0]
        cases.append((prep, T_true, line))
    print(f"{args.target}: {args.cases} cases from AP, contextual alone")
    print(f"{'model':40s} {'target':11s} {'rot deg':>8s} {'trans mm':>9s} {'mTRE med':>9s} {'<10mm':>6s} {'<20mm':>6s}")
    for name in args.model:
        predictor = load_predictor(name)
        rows = {"frame": [], "line+field": [], "line": []}
        for prep, T_true, line in cases:
            g = prep.geometry
            engine = build_method("contextual", volume, center_lps=center, size=(g.height, g.width), geometry=g,
                                  model=predictor)
            for key, (image, mask) in {"frame": (prep.image, prep.mask), "line+field": (line, prep.mask),
                                       "line": (line, None)}.items():
                result = engine.register(image, np.zeros(6), mask=mask,
                                         toned=prep.toned if key == "frame" else None)
                e = pose_errors(result.pose, T_true, points, center, np.eye(3, 4), np.eye(3, 4), 1.0)
                rows[key].append((e["rot_err_deg"], e["trans_err_mm"], e["mtre_mm"]))
        for key, v in rows.items():
            v = np.asarray(v)
            print(f"{str(name)[-40:]:40s} {key:11s} {v[:, 0].mean():8.1f} {v[:, 1].mean():9.1f} "
                  f"{np.median(v[:, 2]):9.1f} {np.mean(v[:, 2] < 10):6.0%} {np.mean(v[:, 2] < 20):6.0%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
