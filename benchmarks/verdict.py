"""The verdict on registrations (register/verdict.py) against the truth: false accepts and the share
of good registrations accepted, per condition; and the calibration of its thresholds.

Rows: registrations of known truth written by ``benchmarks/search.py --rows FILE`` (each with
result.json's ``verdict_evidence``), and rows of X-rays that no pose can register (``mtre_mm``
null: every pose counts as off, e.g. the paediatric radiographs against an adult CT, written by
``benchmarks/verdict.py --unmatched``). The verdict is judged again from each row's evidence with
the current :class:`register.verdict.VerdictSettings` (or the calibrated ones with
``--calibrate``) and the runner-up found again from the search's record by the current rule of
distinct poses, so a change of thresholds or of that rule needs no registration again; a change of
the evidence, or of a step after the pipeline's winner, needs none either: ``--rejudge OUT`` makes
each row's X-ray again and finishes it from its recorded pose (``register.api.RegistrationRequest.finish``:
the rescue by local similarity where the pose's is low, then the verdict), about 3 s a row on 2
cores, 10-12 s more for a row the rescue searches again::

    .venv/bin/python benchmarks/verdict.py benchmarks/verdict_rows/calib.jsonl --rejudge runs/verdict/calib.jsonl

The rows of docs/results.md's tables are committed, compacted (``--compact OUT``: only what the
tables read), in ``benchmarks/verdict_rows/`` (``calib.jsonl``, ``calib_off.jsonl``: the calibration pelvis
registered without the grid, ``heldout.jsonl``, ``unmatched.jsonl``,
``heldout_chains.jsonl``: six more display chains; ``heldout5.jsonl``: three more, new poses, a
512 px detector; ``heldout6.jsonl``: metal tools behind two more chains and two chains without,
384 px; each registered again with the tool segmenter as ``*_detect.jsonl``; ``heldout20_detect.jsonl``:
twenty frames of the four held-out conditions the verdict accepted least on ten; docs/results.md)::

    .venv/bin/python benchmarks/verdict.py benchmarks/verdict_rows/calib.jsonl benchmarks/verdict_rows/calib_off.jsonl --calibrate
    .venv/bin/python benchmarks/verdict.py benchmarks/verdict_rows/heldout.jsonl benchmarks/verdict_rows/unmatched.jsonl

They were made so (docs/results.md, "Whether to trust a registration")::

    B=".venv/bin/python benchmarks/search.py --cases 10 --methods network always"
    $B --study studies/domain_gap.toml --target fluoro-65kV --out runs/verdict/frames --rows runs/verdict/calib.jsonl
    $B --study studies/heldout.toml --target all --out runs/verdict/frames --rows runs/verdict/calib.jsonl
    $B --study studies/metal.toml --target all --out runs/verdict/frames --rows runs/verdict/calib.jsonl
    .venv/bin/python benchmarks/verdict.py runs/verdict/calib.jsonl --calibrate

and the held-out check: the validation pelvis adapted for 10 minutes (``ctxreg adapt --ct
../shared/data/ct/pelvis_chiconasa_2mm.nii.gz --out runs/adapt_chiconasa --minutes 10``), its
frames of four conditions, new conditions on the training pelvis, and the paediatric radiographs::

    $B --ct ../shared/data/ct/pelvis_chiconasa_2mm.nii.gz --model runs/adapt_chiconasa \\
       --study studies/domain_gap.toml studies/heldout.toml studies/metal.toml --target all ... --rows runs/verdict/heldout.jsonl
    $B --study studies/heldout2.toml --target all --out runs/verdict/frames --rows runs/verdict/heldout.jsonl
    .venv/bin/python benchmarks/verdict.py --unmatched ../shared/data/xray/paediatric_ap_pelvis/dicoms \\
       --ct ../shared/data/ct/pelvis_abdomen_3mm.nii.gz runs/verdict/unmatched.jsonl
    .venv/bin/python benchmarks/verdict.py runs/verdict/heldout.jsonl runs/verdict/unmatched.jsonl
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from register.engines.search import GlobalSearchSettings  # noqa: E402
from register.verdict import DECISION_MARGIN, VerdictSettings, checks, failure, judge, runner_up  # noqa: E402
from register.xray.field import TOOL_OPTIONS, TOOLS_DEFAULT  # noqa: E402

#: A registration within this mTRE (mm) is good: the issue's bar, and the study's success.
WITHIN_MM = 10.0

#: The thresholds ``--calibrate`` tries (every combination; the others stay at their defaults).
#: One the pipeline acts on too, ``min_local_similarity`` (``local_below``: the search again below
#: it), holds the pipeline's value alone (:class:`register.verdict.VerdictSettings` takes it): the
#: rows were registered with it, and another would judge poses the pipeline treats otherwise.
#: ``sure_similarity`` (a floor for methods without the search) decides no calibration row: its
#: strictest value, the pipeline's own ``refined_above``, is kept.
GRID = {"min_similarity": (0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.6),
        "min_tone_fit": (0.0, 0.2, 0.3, 0.4, 0.5, 0.6),
        "min_margin": (0.0, 0.02, 0.03, 0.05, 0.07, 0.1, 0.15),
        "min_joint_margin": (None, -0.05, -0.02, 0.0, 0.02, 0.05),
        "sure_similarity": (None, 0.5, 0.7, GlobalSearchSettings.refined_above),
        "min_depth_drop": (0.0, 0.03, 0.05, 0.07),
        "min_profile_drop": (None, 0.02, 0.04, 0.06, 0.08),
        "max_rival_gain": (None, 0.2, 0.1, 0.07, 0.05, 0.03),
        "min_local_similarity": (GlobalSearchSettings.local_below,)}

#: A registration this far off (mTRE, mm; 1.5 times :data:`WITHIN_MM`) is clearly wrong: the
#: thresholds must reject it with a margin (:data:`MARGIN`), not only just.
CLEARLY_OFF_MM = 15.0

#: The margin, a share of each threshold's value: a clearly wrong registration must still be
#: rejected with every threshold this much looser (lower bounds lowered by it, ``max_rival_gain``
#: raised), so that no threshold rests on the exact value of a wrong pose's evidence (a calibration
#: without it put the similarity's floor at 0.25 against a frame 24.6 mm off that scored 0.248).
MARGIN = DECISION_MARGIN

#: The check (:func:`register.verdict.checks`, by the setting it is named for) each threshold of
#: :data:`GRID` sets.
CHECK_OF = {name: name for name in GRID}

#: The evidence each threshold of :data:`GRID` that may be None judges (rows registered before it
#: was gathered lack it; where no row has it, the threshold stays None).
EVIDENCE_OF = {"min_profile_drop": "depth_profile", "max_rival_gain": "rival", "min_joint_margin": "refined_tones",
               "min_local_similarity": "local_similarity"}


def _strictness_of(name: str, value) -> float:
    """One threshold's part of :func:`strictness`."""
    if name == "max_rival_gain":
        return -(2.0 if value is None else value)
    return -2.0 if value is None else value


def strictness(settings: VerdictSettings) -> float:
    """How strict ``settings`` are, for ties of :func:`calibrate`: the lower bounds of :data:`GRID`
    summed (None, not judged, counts as -2), less the upper bound ``max_rival_gain`` (None counts as 2)."""
    v = asdict(settings)
    return round(sum(_strictness_of(k, v[k]) for k in GRID), 9)


def load_rows(paths) -> list[dict]:
    """The judged rows of ``paths`` (JSON lines): ``condition``, ``mtre_mm`` (None: no pose is
    right), ``evidence``; rows without evidence (refused frames, older files) are counted and left out."""
    rows, skipped = [], 0
    for path in paths:
        for line in Path(path).read_text().splitlines():
            if not line.strip():
                continue
            r = json.loads(line)
            ev = (r.get("result") or {}).get("verdict_evidence")
            if ev is None:
                skipped += 1
                continue
            res = r["result"]
            if ev["search"] == "none" and "no grid" in str(r.get("method", "")):  # --search off, before the evidence said so
                ev = {**ev, "search": "off"}
            if ev["search"] == "ran":  # the runner-up again, by the current rule of distinct poses
                ev = {**ev, "runner_up": runner_up(res.get("search"), np.array(res["pose_4x4"]),
                                                   res["geometry"]["sod_mm"], ev.get("refined_tones"))}
            ct = Path(str(r.get("ct"))).name.split(".")[0]
            model = "adapted" if r.get("model") and "adapt" in str(r["model"]) else "shipped"
            method = str(r.get("method", ""))
            method = ("grid always" if "always" in method else "no grid" if "no grid" in method
                      else "network alone" if "alone" in method else "default")
            if row_tools(r) != "off":
                method += f", tools {row_tools(r)}"
            rows.append({"condition": f"{r['target']}, {ct}, {model}, {method}", "mtre_mm": r.get("mtre_mm"),
                         "evidence": ev})
    if skipped:
        print(f"verdict: {skipped} rows without the verdict's evidence left out", file=sys.stderr)
    return rows


def _good(row) -> bool:
    return row["mtre_mm"] is not None and row["mtre_mm"] < WITHIN_MM


def rates(rows, settings: VerdictSettings) -> dict:
    """``within``, ``off``, ``accepted`` (share of the good ones called registered), ``false_accepts``
    (off ones called registered) and each verdict's count."""
    labels = [judge(r["evidence"], settings).label for r in rows]
    good = [lab for r, lab in zip(rows, labels) if _good(r)]
    off = [lab for r, lab in zip(rows, labels) if not _good(r)]
    return {"within": len(good), "off": len(off),
            "accepted": float(np.mean([lab == "registered" for lab in good])) if good else float("nan"),
            "false_accepts": sum(lab == "registered" for lab in off),
            "registered": labels.count("registered"), "doubtful": labels.count("doubtful"),
            "failed": labels.count("failed")}


def _passes(rows, check: str, values: dict, base: VerdictSettings) -> np.ndarray:
    """``(N,)`` bool: whether each row passes ``check`` with the thresholds ``values`` (a check not
    made on a row passes)."""
    s = replace(base, **values)
    return np.array([all(ok for n, ok, _ in checks(r["evidence"], s) if n == check) for r in rows], bool)


def _looser(name: str, value):
    """``value`` of the threshold ``name`` made :data:`MARGIN` looser (None stays None)."""
    if value is None:
        return None
    return value + (MARGIN if name == "max_rival_gain" else -MARGIN) * abs(value)


def calibrate(rows) -> tuple[VerdictSettings, dict]:
    """The settings of :data:`GRID` with no false accept on ``rows`` that accept the most good
    registrations (ties: the stricter, :func:`strictness`; then the first in the grid's order), and
    that still reject every registration :data:`CLEARLY_OFF_MM` off or more (and every unmatched
    X-ray) with each threshold :data:`MARGIN` looser (:func:`_looser`). Each
    check (:func:`register.verdict.checks`) depends on its own thresholds (:data:`CHECK_OF`), so each
    check's passes are found once per combination of them, and a combination of all is registered
    where every check passes; the last two checks' combinations are tried at once, as arrays. A
    threshold of :data:`EVIDENCE_OF` whose evidence no row has stays None (not judged on evidence
    never seen)."""
    base = VerdictSettings()
    grid = {name: (None,) if name in EVIDENCE_OF and not any(r["evidence"].get(EVIDENCE_OF[name]) for r in rows)
            else values for name, values in GRID.items()}
    groups: dict[str, list[str]] = {}
    for name in grid:
        groups.setdefault(CHECK_OF[name], []).append(name)
    good = np.array([_good(r) for r in rows], bool)
    clearly_off = np.array([r["mtre_mm"] is None or r["mtre_mm"] >= CLEARLY_OFF_MM for r in rows], bool)
    fixed = np.array([failure(r["evidence"], base) is None and all(ok for n, ok, _ in checks(r["evidence"], base)
                                                                     if n not in groups) for r in rows], bool)
    options = {check: [dict(zip(names, vals)) for vals in itertools.product(*(grid[n] for n in names))]
               for check, names in groups.items()}
    passes = {check: np.array([_passes(rows, check, o, base) for o in opts]) for check, opts in options.items()}
    loose = {check: np.array([_passes(rows, check, {k: _looser(k, v) for k, v in o.items()}, base) for o in opts])
             for check, opts in options.items()}
    part = {check: np.array([sum(_strictness_of(k, v) for k, v in o.items()) for o in opts])
            for check, opts in options.items()}
    *outer, a, b = options  # the last two checks as arrays: (A, B, rows)
    inner = passes[a][:, None, :] & passes[b][None, :, :]
    inner_loose = loose[a][:, None, :] & loose[b][None, :, :]
    inner_part = part[a][:, None] + part[b][None, :]
    best, best_key = None, None
    for idx in itertools.product(*(range(len(options[c])) for c in outer)):
        reg, reg_loose = fixed.copy(), fixed & clearly_off
        for check, i in zip(outer, idx):
            reg &= passes[check][i]
            reg_loose &= loose[check][i]
        joint = reg & inner  # (A, B, rows)
        allowed = ~(joint & ~good).any(axis=2) & ~(reg_loose & inner_loose).any(axis=2)
        if not allowed.any():
            continue
        accepted = np.where(allowed, joint[..., good].sum(axis=2), -1)
        strict = np.round(sum(part[c][i] for c, i in zip(outer, idx)) + inner_part, 9)
        top = accepted == accepted.max()
        k = int(np.argmax(np.where(top, strict, -np.inf)))  # the first of the strictest among the most accepted
        ia, ib = np.unravel_index(k, allowed.shape)
        key = (int(accepted[ia, ib]), float(strict[ia, ib]))
        if best_key is None or key > best_key:
            chosen = [options[c][i] for c, i in zip(outer, idx)] + [options[a][ia], options[b][ib]]
            best, best_key = replace(base, **{k: v for o in chosen for k, v in o.items()}), key
    if best is None:
        raise SystemExit("verdict: no thresholds of the grid avoid every false accept on these rows")
    return best, rates(rows, best)


def table(rows, settings: VerdictSettings) -> str:
    lines = ["| condition (target, CT, network, search) | registrations | within 10 mm | called registered of "
             "those | further off | called registered of those (false accepts) | registered / doubtful / failed |",
             "|---|---|---|---|---|---|---|"]
    groups = {}
    for r in rows:
        groups.setdefault(r["condition"], []).append(r)
    for name, rs in [*groups.items(), ("all", rows)]:
        x = rates(rs, settings)
        acc = "-" if not x["within"] else f"{100 * x['accepted']:.0f} %"
        lines.append(f"| {name} | {len(rs)} | {x['within']} | {acc} | {x['off']} | {x['false_accepts']} | "
                     f"{x['registered']} / {x['doubtful']} / {x['failed']} |")
    return "\n".join(lines)


def unmatched(a) -> int:
    """Register every X-ray of a folder against a CT it cannot match (``mtre_mm`` null) into ``--rows``."""
    from register.api import register_xray
    from sim import load_ct
    from sim.core.errors import CtxregError

    files = sorted(p for p in Path(a.unmatched).iterdir() if p.suffix.lower() in (".dcm", ".png", ".jpg", ".tif"))
    if not files:
        print(f"verdict: --unmatched {a.unmatched}: no X-ray files", file=sys.stderr)
        return 2
    volume = load_ct(a.ct)
    t0 = time.perf_counter()
    for i, f in enumerate(files):
        try:
            res = register_xray(volume, f, model=a.model, tools=a.tools)
            row = {"target": a.label, "ct": a.ct, "model": a.model, "tools": a.tools, "xray": str(f), "mtre_mm": None,
                   "result": res.to_dict()}
            said = res.verdict.line()
        except CtxregError as e:
            row, said = {"target": a.label, "ct": a.ct, "model": a.model, "xray": str(f), "refused": str(e)}, str(e)
        with open(a.rows, "a") as out:
            out.write(json.dumps(row, default=lambda v: v.tolist() if hasattr(v, "tolist") else repr(v)) + "\n")
        rate = (i + 1) / (time.perf_counter() - t0)
        print(f"verdict: {f.name}: {said} ({i + 1}/{len(files)}, {rate:.2f}/s, ETA {(len(files) - i - 1) / rate:.0f} s)",
              file=sys.stderr, flush=True)
    return 0


def row_tools(row) -> str:
    """The ``tools`` a row was registered with: its ``tools`` key, else its method's name (``",
    tools detect"``, benchmarks/search.py), else ``"off"`` (rows made before either was recorded,
    or before tools could be detected), whatever the default is now."""
    if row.get("tools") is not None:
        return row["tools"]
    return "detect" if "tools detect" in str(row.get("method") or "") else "off"


def _ct_path(row) -> Path:
    """The CT of ``row``: its recorded path, or where that is not here (rows made on another
    machine), the file of that name under ``../shared/data/ct`` beside the repository."""
    recorded = Path(row["ct"])
    here = ROOT.parent / "shared" / "data" / "ct" / recorded.name
    return recorded if recorded.exists() or not here.exists() else here


def _ct(row, cache: dict, what: str) -> tuple[str, object, np.ndarray]:
    """The CT of ``row`` (:func:`_ct_path`), loaded once per ``cache``, and its anatomy centre:
    ``(path, volume, centre)``; a CT that is not here ends ``what`` with its name."""
    from sim import load_ct
    from sim.ct.anatomy import anatomy_center

    ct = str(_ct_path(row))
    if not Path(ct).exists():
        print(f"verdict: {what}: the CT of a row ({row.get('target')}, case {row.get('case')}) is not here: {ct} "
              "(run from the repository root with ../shared beside it)", file=sys.stderr)
        raise SystemExit(2)
    if ct not in cache:
        volume = load_ct(ct)
        cache[ct] = (volume, anatomy_center(volume))
    return (ct, *cache[ct])


def _frame(row, frames_dir: Path, cache: dict) -> tuple[Path, object, np.ndarray]:
    """The X-ray of ``row`` (its file for an unmatched one; else its study's frame, simulated again
    into ``frames_dir/<CT>/<target>/case_###.dcm`` as ``benchmarks/search.py`` made it), its CT and
    the CT's anatomy centre; ``cache`` keeps the CTs and the frame simulators."""
    from register.evaluation.evaluate import EvaluationSettings, sample_cases
    from register.evaluation.study import frame_seed, load_study, study_frames
    from sim.projection.geometry import pose_from_params

    what, path = ("X-ray", Path(row["xray"])) if row.get("xray") else ("study", ROOT / row["study"])
    if not path.exists():
        print(f"verdict: --rejudge: the {what} of a row ({row.get('target')}, case {row.get('case')}) is not here: "
              f"{path} (run from the repository root with ../shared beside it)", file=sys.stderr)
        raise SystemExit(2)
    ct, volume, center = _ct(row, cache, "--rejudge")
    if row.get("xray"):
        return Path(row["xray"]), volume, center
    key = (ct, row["study"], row["target"])
    if key not in cache:
        study = load_study(ROOT / row["study"])
        target = next(t for t in study.targets if t.name == row["target"])
        cache[key] = (study, study_frames(study, target, volume, center))
    study, frames = cache[key]
    case = int(row["case"])
    poses, _ = sample_cases(EvaluationSettings(cases=case + 1, seed=study.seed, size=study.size, start="ap"))
    path = frames_dir / Path(ct).name.split(".")[0] / row["target"] / f"case_{case:03d}.dcm"
    path.parent.mkdir(parents=True, exist_ok=True)
    frames.cached(path, pose_from_params(poses[case], frames.imager.geometry.sod_mm), frame_seed(study, case))
    return path, volume, center


#: The evidence :func:`rejudge` must find again as recorded (it is made the same way): a check that
#: the X-ray was prepared as it was registered.
SAME_EVIDENCE = ("tone_fit", "depth_drop")


#: A pose's six parameters, in result.json's order (deg, mm).
PARAM_KEYS = ("phi", "theta", "psi", "tx", "ty", "tz")


def _errors(row, pose, volume, center, cache) -> dict:
    """``mtre_mm``, ``rot_err_deg``, ``trans_err_mm`` of ``pose`` ``(4, 4)`` against the row's truth,
    as ``benchmarks/search.py`` measures them (2000 bone points of the CT, cached)."""
    from register.evaluation.errors import bone_points, pose_errors
    from sim.projection.geometry import pose_from_params

    key = ("points", row["ct"])
    if key not in cache:
        cache[key] = bone_points(volume, 2000, 0)
    T_true = pose_from_params(np.asarray(row["true_params"], float), row["result"]["geometry"]["sod_mm"])
    e = pose_errors(np.asarray(pose, float), T_true, cache[key], center, np.eye(3, 4), np.eye(3, 4), 1.0)
    return {k: float(e[k]) for k in ("mtre_mm", "rot_err_deg", "trans_err_mm")}


def rejudge(src: Path, dst: Path, frames_dir: Path) -> int:
    """Finish the registrations of ``src`` again with the current steps after the pipeline's winner
    and write them to ``dst`` (atomically): each X-ray made again (:func:`_frame`) and finished from
    its recorded pose (:meth:`register.api.RegistrationRequest.finish`: no registration; the rescue by
    local similarity for the contextual+cmaes rows, then the verdict), the network's gap carried over
    (None where the rescue moved the pose: the compact rows keep no network pose). A rescued row gets
    the new pose, its errors against the truth and the rescue's search record. Rows without a result
    (refused frames) are copied. Prints how many were rescued and how far the evidence made the
    same way (:data:`SAME_EVIDENCE`) moved elsewhere: 0 where each X-ray was prepared as it was
    registered."""
    from register.api import RegistrationRequest

    rows = [json.loads(line) for line in Path(src).read_text().splitlines() if line.strip()]
    cache: dict = {}
    out, moved, rescued = [], {k: 0.0 for k in SAME_EVIDENCE}, 0
    t0 = time.perf_counter()
    for i, row in enumerate(rows):
        res = row.get("result")
        if res is not None and res.get("verdict_evidence") is not None:
            path, volume, center = _frame(row, frames_dir, cache)
            request = RegistrationRequest(search="always" if "always" in str(row.get("method", "")) else "auto",
                                          center=center, tools=row_tools(row))
            params = [res["params"][k] for k in PARAM_KEYS]
            result, verdict = request.finish(volume, path, params, similarity=res["similarity"], search=res.get("search"))
            old = res["verdict_evidence"]
            new = {**verdict.evidence, "network_gap": old.get("network_gap")}
            rescue = (result.search or {}).get("rescue")
            if rescue is not None and rescue["kept"] == "rescued":  # another pose: its errors, no network gap known
                rescued += 1
                new["network_gap"] = None
                res = {**res, "params": dict(zip(PARAM_KEYS, np.asarray(result.params, float).tolist())),
                       "pose_4x4": np.asarray(result.pose).tolist(), "similarity": float(result.similarity)}
                if row.get("mtre_mm") is not None:
                    row = {**row, **_errors(row, result.pose, volume, center, cache)}
            else:
                for k in SAME_EVIDENCE:
                    if old.get(k) is not None and new.get(k) is not None:
                        moved[k] = max(moved[k], abs(old[k] - new[k]))
            row = {**row, "result": {**res, "search": result.search, "verdict": verdict.label,
                                     "verdict_reasons": list(verdict.reasons), "verdict_evidence": new}}
        out.append(json.dumps(row, default=lambda v: v.tolist() if hasattr(v, "tolist") else repr(v)))
        rate = (i + 1) / (time.perf_counter() - t0)
        print(f"verdict: rejudged {i + 1}/{len(rows)} ({rate:.2f} rows/s, ETA {(len(rows) - i - 1) / rate:.0f} s)",
              file=sys.stderr, flush=True)
    tmp = Path(dst).with_suffix(".tmp")
    tmp.write_text("\n".join(out) + "\n")
    tmp.replace(dst)
    print(f"verdict: {len(out)} rows -> {dst} ({rescued} rescued: another pose); the evidence made as recorded "
          "moved by at most " + ", ".join(f"{k} {v:.2g}" for k, v in moved.items()))
    return len(out)


def rescues(paths) -> str:
    """What the search again by local similarity (the pipeline's step 6) did in the rows of
    ``paths``: on how many registrations it ran and how long (s), how many poses it moved, how far
    off they were before (mTRE of the recorded first winner against the truth, mm) and after, and
    how many of those it moved to within :data:`WITHIN_MM` the verdict calls registered."""
    from sim.projection.geometry import pose_from_params

    cache: dict = {}
    ran, moved = [], []
    total = 0
    for path in paths:
        for n, line in enumerate(Path(path).read_text().splitlines(), 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError as e:
                print(f"verdict: --rescues: {path} line {n} is not a JSON row ({e.msg})", file=sys.stderr)
                raise SystemExit(2) from None
            if row.get("result") is None:
                continue
            total += 1
            rescue = (row["result"].get("search") or {}).get("rescue")
            if rescue is None:
                continue
            ran.append(rescue["seconds"])
            if rescue["kept"] != "rescued" or row.get("mtre_mm") is None:
                continue
            _, volume, center = _ct(row, cache, "--rescues")
            first = pose_from_params(np.asarray(rescue["first_params"], float), row["result"]["geometry"]["sod_mm"])
            before = _errors(row, first, volume, center, cache)["mtre_mm"]
            label = judge(row["result"]["verdict_evidence"], VerdictSettings()).label
            moved.append((before, row["mtre_mm"], label, f"{row['target']} case {row.get('case')}"))
    if not ran:
        return f"the search again by local similarity ran on none of {total} registrations"
    good = [m for m in moved if m[1] < WITHIN_MM]
    out = [f"the search again by local similarity ran on {len(ran)} of {total} registrations (median "
           f"{np.median(ran):.1f} s, {min(ran):.1f}-{max(ran):.1f} s) and moved {len(moved)} poses"]
    if moved:
        out.append(f"  before: {min(m[0] for m in moved):.1f}-{max(m[0] for m in moved):.1f} mm off; after: "
                   f"{len(good)} within {WITHIN_MM:g} mm ({sum(m[2] == 'registered' for m in good)} called registered), "
                   f"{len(moved) - len(good)} not")
        out += [f"  not within: {m[3]}: {m[0]:.1f} -> {m[1]:.1f} mm ({m[2]})" for m in moved if m[1] >= WITHIN_MM]
        out += [f"  moved off: {m[3]}: {m[0]:.1f} -> {m[1]:.1f} mm" for m in moved if m[0] < WITHIN_MM]
    return "\n".join(out)


#: What :func:`compact` keeps of a row's ``result`` (everything :func:`load_rows` and the tables read,
#: and the stage times).
COMPACT_RESULT_KEYS = ("geometry", "params", "pose_4x4", "search", "search_status", "similarity", "verdict",
                       "verdict_evidence", "timings_s")


def compact(src: Path, dst: Path) -> int:
    """Write the rows of ``src`` to ``dst`` with only :data:`COMPACT_RESULT_KEYS` of each result (the
    committed rows, ``benchmarks/verdict_rows/``); returns the rows written."""
    out = []
    for line in Path(src).read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            if "result" in r:
                r["result"] = {k: r["result"][k] for k in COMPACT_RESULT_KEYS if k in r["result"]}
            out.append(json.dumps(r))
    tmp = Path(dst).with_suffix(".tmp")
    tmp.write_text("\n".join(out) + "\n")
    tmp.replace(dst)
    return len(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rows", nargs="*", help="JSON-lines files of registrations (benchmarks/search.py --rows)")
    ap.add_argument("--calibrate", action="store_true",
                    help="choose the thresholds of GRID with no false accept (and every registration "
                         f"{CLEARLY_OFF_MM:g} mm off or more still rejected with each threshold {100 * MARGIN:g} %% "
                         "looser) that accept the most good registrations")
    ap.add_argument("--unmatched", default=None, metavar="DIR",
                    help="register the X-rays of DIR against --ct (no pose can be right) into --rows")
    ap.add_argument("--ct", default=None, help="with --unmatched: the CT")
    ap.add_argument("--model", default=None, help="with --unmatched: the network (default: the shipped default)")
    ap.add_argument("--label", default="unmatched X-ray", help="with --unmatched: the condition's name")
    ap.add_argument("--tools", choices=TOOL_OPTIONS, default=TOOLS_DEFAULT,
                    help=f"with --unmatched: register_xray's tools (default {TOOLS_DEFAULT}, the pipeline's)")
    ap.add_argument("--rejudge", default=None, metavar="OUT",
                    help="finish the one ROWS file's registrations again from their recorded poses with the current "
                         "steps after the pipeline's winner (the rescue by local similarity, the verdict; each X-ray "
                         "made again, no registration) into OUT")
    ap.add_argument("--frames", default="runs/verdict/rejudge_frames",
                    help="with --rejudge: where the study frames are simulated again, cached (default: %(default)s)")
    ap.add_argument("--rescues", action="store_true",
                    help="summarise what the search again by local similarity did in the ROWS files")
    ap.add_argument("--compact", default=None, metavar="OUT",
                    help="write the one ROWS file to OUT with only what the tables read of each result")
    a = ap.parse_args()
    if a.rejudge is not None:
        if len(a.rows) != 1 or not Path(a.rows[0]).is_file():
            print("verdict: --rejudge needs one existing ROWS file", file=sys.stderr)
            return 2
        rejudge(Path(a.rows[0]), Path(a.rejudge), Path(a.frames))
        return 0
    if a.compact is not None:
        if len(a.rows) != 1 or not Path(a.rows[0]).is_file():
            print("verdict: --compact needs one existing ROWS file", file=sys.stderr)
            return 2
        print(f"verdict: {compact(Path(a.rows[0]), Path(a.compact))} rows -> {a.compact}")
        return 0
    if a.rescues:
        missing = [p for p in a.rows if not Path(p).is_file()]
        if not a.rows or missing:
            print(f"verdict: --rescues: rows file(s) not found: {missing or 'none given'}", file=sys.stderr)
            return 2
        print(rescues(a.rows))
        return 0
    if a.unmatched is not None:
        if a.ct is None or not a.rows or len(a.rows) != 1:
            print("verdict: --unmatched needs --ct and one ROWS file to append to", file=sys.stderr)
            return 2
        a.rows = a.rows[0]
        return unmatched(a)
    missing = [p for p in a.rows if not Path(p).is_file()]
    if not a.rows or missing:
        print(f"verdict: rows file(s) not found: {missing or 'none given'}", file=sys.stderr)
        return 2
    rows = load_rows(a.rows)
    if not rows:
        print("verdict: no judged rows", file=sys.stderr)
        return 2
    settings = VerdictSettings()
    if a.calibrate:
        settings, r = calibrate(rows)
        print(f"calibrated on {len(rows)} registrations: {asdict(settings)}\n")
    print(f"{len(rows)} registrations, VerdictSettings {asdict(settings)}; good: mTRE < {WITHIN_MM:g} mm "
          f"({time.strftime('%Y-%m-%d %H:%M')})\n")
    print(table(rows, settings))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
