"""Metal tools in the registration's mask, and what they cost the verdict's evidence at the true pose.

    .venv/bin/python benchmarks/tools.py [--ct CT] [--cases 10] [--study studies/metal.toml] [--target all]

Frames: the first ``--cases`` poses of every ``xray`` target with ``tools`` of ``--study`` (default
``studies/metal.toml``: 2 to 5 screws, K-wires, plates and retractors fixed to the patient per
frame), simulated where the cache (``--out``, shared with benchmarks/search.py) lacks them. The
truth: the simulator's own chords through the frame's tools (:class:`sim.distractors.DistractorField`
with the frame's :meth:`register.evaluation.frames.FrameSimulator.implants`, the renderer's rays at
the true pose); a pixel is a tool's where the tools' line integral (``mu(60 keV) x chord``, summed
over materials) is at least :data:`TOOL_LINE_INTEGRAL` (about 0.15 mm of steel or 0.4 mm of
titanium on the ray). Each frame is prepared as ``ctxreg register`` prepares it
(:func:`register.xray.prepare.prepare_xray` with the CT: field, intensity, tone), its polarity taken
as the true pose confirms it. Per condition:

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
  ``min_tone_fit`` either way: right poses that tools alone would make doubtful.

Prints one row per condition and, with ``--frames``, one per frame.
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

#: A pixel is a tool's where the tools' line integral on its ray is at least this (mu x mm at 60 keV,
#: summed over the tools' materials): about 0.15 mm of stainless steel, 0.4 mm of titanium.
TOOL_LINE_INTEGRAL = 0.05
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_frame_arguments(ap, cases=10)
    ap.add_argument("--study", default=str(ROOT / "studies" / "metal.toml"),
                    help="a study file whose xray targets with tools give the frames (default studies/metal.toml)")
    ap.add_argument("--target", default="all", help="one xray target with tools, or 'all' (default)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_search"),
                    help="frame cache folder, shared with benchmarks/search.py (default runs/bench_search)")
    ap.add_argument("--frames", action="store_true", help="also print one row per frame")
    a = ap.parse_args()
    problem = input_problem("tools", a.ct, a.cases)
    if problem:
        print(problem, file=sys.stderr)
        return 2
    if not Path(a.study).exists():
        print(f"tools: study file {a.study} not found", file=sys.stderr)
        return 2
    from register.evaluation.study import StudyError, load_study

    try:
        targets = [t.name for t in load_study(a.study).targets if t.kind == "xray" and t.tools]
    except StudyError as exc:
        print(f"tools: {exc}", file=sys.stderr)
        return 2
    chosen = [t for t in targets if a.target in ("all", t)]
    if not chosen:
        print(f"tools: --target must be 'all' or one of {targets} (the xray targets with tools of {a.study}), "
              f"got {a.target!r}", file=sys.stderr)
        return 2

    from register.engines.metrics import gradient_ncc, local_gradient_ncc, ncc
    from register.verdict import VerdictSettings
    from register.xray.prepare import prepare_xray, recorded_tone_curve, toned_image
    from register.xray.io import load_xray
    from sim.distractors import DistractorField, mu_line
    from sim.prepare import invert
    from sim.projection.drr import DRRRenderer, RenderSettings

    floor = VerdictSettings().min_tone_fit
    rows, frame_rows = [], []
    t0, done, total = time.perf_counter(), 0, len(chosen) * a.cases
    for name in chosen:
        volume, center, _, found, frames = study_frame_files(a.study, name, a.ct, a.cases, a.out)
        shares, per = [], []
        for i, T_true, path in found:
            field_tools = DistractorField(frames.implants(frames.seeds[i]), frames.imager.geometry, center)
            chords = field_tools.chords(T_true)[0]
            line = sum(mu_line(m, rho) * chords[k] for k, (m, rho) in enumerate(field_tools.channels))
            tools = np.asarray(line) >= TOOL_LINE_INTEGRAL
            xray = load_xray(path)
            h, w = xray.shape
            field = np.ones((h, w), bool) if frames.collimator is None else frames.collimator.mask(h, w)
            prepared = prepare_xray(xray, volume=volume, center_lps=center)
            g = prepared.geometry
            drr = DRRRenderer(volume, RenderSettings(size=(g.height, g.width)), center_lps=center,
                              geometry=g).render(T_true)[0]
            image, mask = prepared.image, prepared.mask
            toned = prepared.toned
            if gradient_ncc(image, drr, mask=mask)[0] < 0:  # the polarity as the true pose confirms it
                image = invert(image, mask)[0]
                toned = toned_image(image, mask, recorded_tone_curve(prepared.record))
            tones = image if toned is None else toned
            small = tools_at_optimiser(tools, prepared)
            valid = np.ones(image.shape, bool) if mask is None else mask
            without = valid & ~small
            s = tool_shares(tools, field, prepared.full_mask)
            shares.append(s)
            per.append((i, s["tool_px"] / max(s["field_px"], 1), float(small[valid].mean()),
                        float(ncc(tones, drr, mask=valid)[0]), float(ncc(tones, drr, mask=without)[0]),
                        float(local_gradient_ncc(image, drr, mask=valid)[0]),
                        float(local_gradient_ncc(image, drr, mask=without)[0])))
            done += 1
            rate = done / (time.perf_counter() - t0)
            print(f"tools: {done}/{total} frames, {rate * 60:.1f} per min, ETA {(total - done) / rate:.0f} s",
                  file=sys.stderr, flush=True)
        p = np.array([r[1:] for r in per])
        tool_px = sum(s["tool_px"] for s in shares)
        left = sum(s["left_out_px"] for s in shares) / max(tool_px, 1)
        rows.append((name, len(per), np.median(p[:, 0]), left, np.median(p[:, 1]), np.median(p[:, 2]),
                     np.median(p[:, 3]), np.median(p[:, 4]), np.median(p[:, 5]), int(np.sum(p[:, 2] < floor)),
                     int(np.sum(p[:, 3] < floor))))
        frame_rows += [(name, *r) for r in per]
    print(f"\nMetal tools against the registration's mask, {a.cases} frames per condition of {Path(a.ct).name}, "
          f"at the true pose ({time.strftime('%Y-%m-%d %H:%M')})\n")
    print("| condition | frames | tools in field | left out by the field | tools in the mask | tone fit: as "
          "registered -> tools left out | local similarity: as registered -> tools left out | "
          f"tone fit < {floor:.2f}: as registered -> tools left out |")
    print("|---|---|---|---|---|---|---|---|")
    for name, n, share, left, in_mask, tone, tone_w, loc, loc_w, low, low_w in rows:
        print(f"| `{name}` | {n} | {100 * share:.1f} % | {100 * left:.0f} % | {100 * in_mask:.1f} % | "
              f"{tone:.2f} -> {tone_w:.2f} | {loc:.2f} -> {loc_w:.2f} | {low} -> {low_w} |")
    if a.frames:
        print("\n| condition | frame | tools in field | tools in the mask | tone fit | tools left out | "
              "local similarity | tools left out |")
        print("|---|---|---|---|---|---|---|---|")
        for name, i, share, in_mask, tone, tone_w, loc, loc_w in frame_rows:
            print(f"| `{name}` | {i} | {100 * share:.1f} % | {100 * in_mask:.1f} % | {tone:.2f} | {tone_w:.2f} | "
                  f"{loc:.2f} | {loc_w:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
