"""Metal tools in the registration's mask, what they cost the verdict's evidence at the true pose, and
what the tool segmenter (``--tools detect``, :class:`learn.tool_mask.ToolMask`) finds and takes.

    .venv/bin/python benchmarks/tools.py [--ct CT] [--cases 10] [--study studies/metal.toml ...] [--target all]

Frames: the first ``--cases`` poses of every ``xray`` target of the ``--study`` files (default
``studies/metal.toml``: 2 to 5 screws, K-wires, plates and retractors fixed to the patient per
frame), simulated where the cache (``--out``, shared with benchmarks/search.py) lacks them. The
truth: the simulator's own chords through the frame's tools (:class:`sim.distractors.DistractorField`
with the frame's :meth:`register.evaluation.frames.FrameSimulator.implants`, the renderer's rays at
the true pose); a pixel is a tool's where the tools' line integral (``mu(60 keV) x chord``, summed
over materials) is at least :data:`TOOL_LINE_INTEGRAL` (about 0.15 mm of steel or 0.4 mm of
titanium on the ray). Each frame is prepared as ``ctxreg register`` prepares it
(:func:`register.xray.prepare.prepare_xray` with the CT: field, intensity, tone), with ``tools="off"``
and ``"detect"`` (the default), its polarity taken as the true pose confirms it. Per condition with
tools:

* ``tools in field``: the share of the collimator's true field that is tool (median over frames);
* ``left out by the field``: the share of the tool pixels inside the true field that the field
  detection already excludes (:func:`register.xray.field.detect_field`'s empty or saturated
  plateaus: tools a display clips at black or white), pooled over frames;
* ``tools in the mask``: the share of the registration's mask, at the optimiser's size, that tools
  touch (any blur weight from a tool pixel above :data:`TOUCH`), median over frames;
* the verdict's intensity evidence at the **true pose**: the tone fit (:func:`register.engines.metrics.ncc`
  of the toned X-ray with the line DRR) and the local similarity (window-by-window gradient NCC),
  over the mask as registered and over the mask less the tools' pixels (the truth's, a ceiling for
  any tool detector), medians; and the frames whose tone fit at the truth is under the verdict's
  ``min_tone_fit`` either way: right poses that tools alone would make doubtful; each ``off ->
  detect`` and, in brackets, the truth's ceiling;
* the detector's recall and precision (:func:`detection_scores`) of the tool pixels the field kept.

Per condition without tools: the frames where the detector leaves pixels out, and their share of
the field (median, largest). Prints one row per condition and, with ``--frames``, one per frame;
then what detection costs: the seconds of ``prepare_xray`` with ``tools="off"`` and ``"detect"``
on each frame, one after the other in the same process (the segmenter loaded before the first),
medians per condition and their ratio.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from network_on_frames import study_frame_files  # noqa: E402  (benchmarks/network_on_frames.py)
from timing import add_frame_arguments, input_problem  # noqa: E402  (benchmarks/timing.py)

from learn.tool_mask import TOOL_LINE_INTEGRAL  # noqa: E402  (the segmenter's label: one definition)
#: An optimiser pixel is touched by tools where at least this share of its blur weight
#: (:func:`register.xray.prepare.fit_to_size`) falls on tool pixels.
TOUCH = 0.1


def tool_shares(tools: np.ndarray, field: np.ndarray, mask: np.ndarray) -> dict:
    """The tool pixels of one frame against its true field and the registration's mask.

    Args:
        tools: ``(H, W)`` bool the true tool pixels (full resolution).
        field: ``(H, W)`` bool the collimator's true field (all True where open).
        mask: ``(H, W)`` bool the registration's valid pixels at full resolution
            (:attr:`register.xray.prepare.PreparedXRay.full_mask`).

    Returns ``{"field_px", "tool_px", "left_out_px"}``: the true field's pixels, the tool pixels
    inside it, and those the mask excludes.
    """
    tools, field, mask = (np.asarray(a, bool) for a in (tools, field, mask))
    if not tools.shape == field.shape == mask.shape:
        raise ValueError(f"tools {tools.shape}, field {field.shape} and mask {mask.shape} must have one shape")
    inside = tools & field
    return {"field_px": int(field.sum()), "tool_px": int(inside.sum()), "left_out_px": int((inside & ~mask).sum())}


def tools_at_optimiser(tools: np.ndarray, prepared) -> np.ndarray:
    """``(h, w)`` bool: the optimiser pixels of ``prepared`` (a :class:`register.xray.prepare.PreparedXRay`)
    that the full-resolution ``tools`` ``(H, W)`` bool touch (blur weight above :data:`TOUCH`),
    through the same crop and resampling as the image (:func:`register.xray.prepare.fit_to_size`)."""
    from register.xray.prepare import fit_to_size
    from register.xray.preprocess import crop_box, cropped_geometry

    r0, r1, c0, c1 = crop_box(prepared.record, tools.shape)
    crop_geometry = cropped_geometry(prepared.full_geometry, prepared.record)
    box = (prepared.geometry.height, prepared.geometry.width)
    small, _, _ = fit_to_size(np.asarray(tools, float)[r0:r1, c0:c1], None, crop_geometry, box)
    if small.shape != box:
        raise ValueError(f"tools resampled to {small.shape}, the prepared image is {box}")
    return small > TOUCH


def detection_scores(detected: np.ndarray, tools: np.ndarray, kept: np.ndarray, reach_px: int) -> dict:
    """A detector's pixels against the truth, one frame (all ``(H, W)`` bool at full resolution).

    Args:
        detected: the detector's tool pixels.
        tools: the true tool pixels inside the true field.
        kept: the pixels the field detection keeps (:attr:`register.xray.field.Field.mask`).
        reach_px: a detected pixel within this distance (px) of a true one counts as right (the
            detector grows its pixels by ``dilate_px``: the blur of a tool's edge).

    Returns ``{"tool_px", "found_px", "detected_px", "right_px"}``: the true tool pixels the field
    kept, those the detector found, the detector's pixels inside ``kept``, and those within
    ``reach_px`` of a true tool pixel.
    """
    from scipy import ndimage

    detected, tools, kept = (np.asarray(a, bool) for a in (detected, tools, kept))
    if not detected.shape == tools.shape == kept.shape:
        raise ValueError(f"detected {detected.shape}, tools {tools.shape} and kept {kept.shape} must have one shape")
    near = ndimage.binary_dilation(tools, iterations=reach_px) if reach_px > 0 and tools.any() else tools
    mine = detected & kept
    return {"tool_px": int((tools & kept).sum()), "found_px": int((tools & kept & detected).sum()),
            "detected_px": int(mine.sum()), "right_px": int((mine & near).sum())}


def _at_truth(prepared, volume, center, T_true):
    """The tone fit and local similarity at the true pose over ``prepared``'s mask, the image and mask
    (polarity as the true pose confirms it), the toned image and the line DRR."""
    from register.engines.metrics import gradient_ncc, local_gradient_ncc, ncc
    from register.xray.prepare import recorded_tone_curve, toned_image
    from sim.prepare import invert
    from sim.projection.drr import DRRRenderer, RenderSettings

    g = prepared.geometry
    drr = DRRRenderer(volume, RenderSettings(size=(g.height, g.width)), center_lps=center, geometry=g).render(T_true)[0]
    image, mask, toned = prepared.image, prepared.mask, prepared.toned
    if gradient_ncc(image, drr, mask=mask)[0] < 0:  # the polarity as the true pose confirms it
        image = invert(image, mask)[0]
        toned = toned_image(image, mask, recorded_tone_curve(prepared.record))
    tones = image if toned is None else toned
    valid = np.ones(image.shape, bool) if mask is None else mask
    return image, valid, tones, drr, ncc, local_gradient_ncc


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_frame_arguments(ap, cases=10)
    ap.add_argument("--study", nargs="+", default=[str(ROOT / "studies" / "metal.toml")],
                    help="study files whose xray targets give the frames (default studies/metal.toml); targets "
                         "without tools give the detector's false exclusions")
    ap.add_argument("--target", default="all", help="one xray target, or 'all' (default)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_search"),
                    help="frame cache folder, shared with benchmarks/search.py (default runs/bench_search)")
    ap.add_argument("--frames", action="store_true", help="also print one row per frame")
    a = ap.parse_args()
    problem = input_problem("tools", a.ct, a.cases)
    if problem:
        print(problem, file=sys.stderr)
        return 2
    for study in a.study:
        if not Path(study).exists():
            print(f"tools: study file {study} not found", file=sys.stderr)
            return 2
    from register.evaluation.study import StudyError, load_study

    try:
        targets = [(study, t.name, bool(t.tools)) for study in a.study for t in load_study(study).targets
                   if t.kind == "xray"]
    except StudyError as exc:
        print(f"tools: {exc}", file=sys.stderr)
        return 2
    chosen = [t for t in targets if a.target in ("all", t[1])]
    if not chosen:
        print(f"tools: --target must be 'all' or one of {[t[1] for t in targets]} (the xray targets of "
              f"{' '.join(a.study)}), got {a.target!r}", file=sys.stderr)
        return 2

    from learn.tool_mask import ToolMask
    from register.verdict import VerdictSettings
    from register.xray.prepare import prepare_xray
    from register.xray.io import load_xray
    from sim.distractors import DistractorField, mu_line

    segmenter = ToolMask.shared()
    floor = VerdictSettings().min_tone_fit
    rows, free_rows, frame_rows, seconds = [], [], [], []
    t0, done, total = time.perf_counter(), 0, len(chosen) * a.cases
    for study, name, has_tools in chosen:
        volume, center, _, found, frames = study_frame_files(study, name, a.ct, a.cases, a.out)
        shares, scores, per, free = [], [], [], []
        for i, T_true, path in found:
            xray = load_xray(path)
            h, w = xray.shape
            field = np.ones((h, w), bool) if frames.collimator is None else frames.collimator.mask(h, w)
            t_off = time.perf_counter()
            off = prepare_xray(xray, volume=volume, center_lps=center, tools="off")
            t_on = time.perf_counter()
            on = prepare_xray(xray, volume=volume, center_lps=center, tools="detect")
            seconds.append((name, t_on - t_off, time.perf_counter() - t_on))
            detected = on.tools
            if not has_tools:
                free.append((i, float(detected.sum() / max(off.full_mask.sum(), 1))))
            else:
                field_tools = DistractorField(frames.implants(frames.seeds[i]), frames.imager.geometry, center)
                chords = field_tools.chords(T_true)[0]
                line = sum(mu_line(m, rho) * chords[k] for k, (m, rho) in enumerate(field_tools.channels))
                tools = np.asarray(line) >= TOOL_LINE_INTEGRAL
                s = tool_shares(tools, field, off.full_mask)
                shares.append(s)
                scores.append(detection_scores(detected, tools & field, off.full_mask, segmenter.dilate_px + 1))
                values = []
                for prepared in (off, on):
                    image, valid, tones, drr, ncc, local = _at_truth(prepared, volume, center, T_true)
                    small = tools_at_optimiser(tools, prepared)
                    without = valid & ~small
                    values += [float(small[valid].mean()), float(ncc(tones, drr, mask=valid)[0]),
                               float(local(image, drr, mask=valid)[0]), float(ncc(tones, drr, mask=without)[0]),
                               float(local(image, drr, mask=without)[0])]
                # off: in mask, tone, local, tone truth-out, local truth-out; on: the same
                per.append((i, s["tool_px"] / max(s["field_px"], 1), *values))
            done += 1
            rate = done / (time.perf_counter() - t0)
            print(f"tools: {done}/{total} frames, {rate * 60:.1f} per min, ETA {(total - done) / rate:.0f} s",
                  file=sys.stderr, flush=True)
        if not has_tools:
            f = np.array([v for _, v in free])
            free_rows.append((name, len(free), int(np.sum(f > 0)), float(np.median(f)), float(f.max()),
                              [i for i, v in free if v > 0]))
            continue
        p = np.array([r[1:] for r in per])
        tool_px = sum(s["tool_px"] for s in shares)
        left = sum(s["left_out_px"] for s in shares) / max(tool_px, 1)
        recall = sum(s["found_px"] for s in scores) / max(sum(s["tool_px"] for s in scores), 1)
        precision = sum(s["right_px"] for s in scores) / max(sum(s["detected_px"] for s in scores), 1)
        med = np.median(p, axis=0)
        rows.append((name, len(per), med[0], left, recall, precision, med[1], med[6], med[2], med[7], med[4],
                     med[3], med[8], int(np.sum(p[:, 2] < floor)), int(np.sum(p[:, 7] < floor)),
                     int(np.sum(p[:, 4] < floor))))
        frame_rows += [(name, *r) for r in per]
    stamp = time.strftime('%Y-%m-%d %H:%M')
    print(f"\nMetal tools against the registration's mask, {a.cases} frames per condition of {Path(a.ct).name}, "
          f"at the true pose ({stamp}); 'off' -> 'detect': prepare_xray(tools='off' / 'detect'), 'truth': the "
          f"simulator's tool pixels also left out\n")
    if rows:
        print("| condition | frames | tools in field | left out by the field | detector: recall of the rest | "
              "precision | tools in the mask: off -> detect | tone fit: off -> detect (truth) | local similarity: "
              f"off -> detect (truth) | tone fit < {floor:.2f}: off -> detect (truth) |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for (name, n, share, left, recall, precision, in_off, in_on, tone, tone_on, tone_t, loc, loc_on, low,
             low_on, low_t) in [(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8], r[9], r[10], r[11], r[12],
                                 r[13], r[14], r[15]) for r in rows]:
            print(f"| `{name}` | {n} | {100 * share:.1f} % | {100 * left:.0f} % | {100 * recall:.0f} % | "
                  f"{100 * precision:.0f} % | {100 * in_off:.1f} % -> {100 * in_on:.1f} % | {tone:.2f} -> "
                  f"{tone_on:.2f} ({tone_t:.2f}) | {loc:.2f} -> {loc_on:.2f} | {low} -> {low_on} ({low_t}) |")
    if free_rows:
        print("\n| condition without tools | frames | frames with pixels left out as tools | share of the field: "
              "median | largest | those frames |")
        print("|---|---|---|---|---|---|")
        for name, n, k, med, worst, which in free_rows:
            print(f"| `{name}` | {n} | {k} | {100 * med:.2f} % | {100 * worst:.2f} % | {which} |")
    if seconds:  # the segmenter loaded before the first frame: both columns warm
        print("\n| condition | frames | prepare_xray s, off: median | detect: median | detect / off |")
        print("|---|---|---|---|---|")
        for name in dict.fromkeys(n for n, _, _ in seconds):
            s_off = np.median([u for n, u, _ in seconds if n == name])
            s_on = np.median([v for n, _, v in seconds if n == name])
            print(f"| `{name}` | {sum(n == name for n, _, _ in seconds)} | {s_off:.2f} | {s_on:.2f} | {s_on / s_off:.2f} |")
        s_off, s_on = np.median([u for _, u, _ in seconds]), np.median([v for _, _, v in seconds])
        print(f"| all | {len(seconds)} | {s_off:.2f} | {s_on:.2f} | {s_on / s_off:.2f} |")
    if a.frames and frame_rows:
        print("\n| condition | frame | tools in field | tools in the mask: off -> detect | tone fit: off -> detect | "
              "local similarity: off -> detect |")
        print("|---|---|---|---|---|---|")
        for name, i, share, in_off, tone, loc, _, _, in_on, tone_on, loc_on, _, _ in frame_rows:
            print(f"| `{name}` | {i} | {100 * share:.1f} % | {100 * in_off:.1f} % -> {100 * in_on:.1f} % | "
                  f"{tone:.2f} -> {tone_on:.2f} | {loc:.2f} -> {loc_on:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
