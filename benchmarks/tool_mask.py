"""The metal-tool segmenter alone (learn/tool_mask.py) on simulated frames of subjects it never trained on.

    .venv/bin/python benchmarks/tool_mask.py [--model models/tool_mask] [--frames 256] [--seed 101]

Frames: :class:`learn.tool_mask.ToolFrames` of the segmenter's campaign's ``val`` subjects (held-out
virtual patients and phantoms), drawn under ``--seed`` (not the training's seeds), whole
:data:`learn.tool_mask.SEGMENTER_SIDE` px frames, tools on 70 % of them; the truth is the
simulator's visible metal (the label the segmenter trained on). For each probability threshold:
the pixel recall and precision over every frame (a detected pixel within 1 px of a true one is
right: the tool's blurred edge; before the card's dilation), the frames with tools where it finds
at least half of their tool pixels, and the tool-free frames with any pixel left out, each with
the card's hysteresis (:func:`learn.tool_mask.confident_pieces`: pieces over its ``low`` holding
``min_px`` px at the threshold). The card's threshold is marked.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

THRESHOLDS = (0.3, 0.5, 0.7, 0.8, 0.9, 0.95)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=None, help="a tool-mask folder (default models/tool_mask)")
    ap.add_argument("--frames", type=int, default=256, help="frames (default 256)")
    ap.add_argument("--seed", type=int, default=101, help="the frames' seed (default 101; training used 0 and 1)")
    ap.add_argument("--curve", default=None, metavar="PNG",
                    help="only draw the card's learning curve (validation loss, recall and precision at 0.5 against "
                         "minutes) into PNG")
    a = ap.parse_args()
    if not 1 <= a.frames <= 4096:
        print(f"tool_mask: --frames must be in [1, 4096], got {a.frames}", file=sys.stderr)
        return 2
    import torch
    from scipy import ndimage

    from learn.tool_mask import (DEFAULT_TOOL_MODEL, TOOL_CAMPAIGN, ToolMask, ToolMaskError, ToolTrainSettings,
                                 confident_pieces, segmenter_input, tool_frame_sources)

    try:
        mask = ToolMask(a.model or DEFAULT_TOOL_MODEL)
    except ToolMaskError as e:
        print(f"tool_mask: {e}", file=sys.stderr)
        return 2
    if a.curve:
        _plot_curve(mask.card["training"], Path(a.curve))
        return 0
    settings = ToolTrainSettings(seed=a.seed, banks=8)
    _, val = tool_frame_sources(settings, "cpu", ROOT / "runs" / "tool_mask_bench" / "tables", TOOL_CAMPAIGN)
    probs, truths = [], []
    t0 = time.perf_counter()
    with torch.no_grad():
        for k in range(0, a.frames, 32):
            n = min(32, a.frames - k)
            image, field, tools = val.frames(k // 32, n)
            p = torch.sigmoid(mask.net(segmenter_input(image, field)))[:, 0].numpy()
            probs.append(np.where(field.numpy(), p, 0.0))
            truths.append(tools.numpy())
            done = k + n
            rate = done / (time.perf_counter() - t0)
            print(f"tool_mask: {done}/{a.frames} frames, {rate:.1f}/s, ETA {(a.frames - done) / rate:.0f} s",
                  file=sys.stderr, flush=True)
    probs, truths = np.concatenate(probs), np.concatenate(truths)
    with_tools = truths.reshape(len(truths), -1).any(1)
    print(f"\nThe tool segmenter alone ({mask.folder}), {a.frames} frames of the validation subjects, seed {a.seed}, "
          f"{int(with_tools.sum())} with visible tools ({time.strftime('%Y-%m-%d %H:%M')})\n")
    print(f"| threshold (grown over >= {mask.low:.2f}) | pixel recall | precision (1 px) | frames with tools: half "
          f"found | tool-free frames with pixels left out (cores >= {mask.min_px} px) |")
    print("|---|---|---|---|---|")
    for th in sorted(set(THRESHOLDS) | {mask.threshold}):
        tp = fn = det = right = half = flagged = 0
        for p, t in zip(probs, truths):
            hit = confident_pieces(p, th, min(mask.low, th), mask.min_px)
            near = ndimage.binary_dilation(t, iterations=1) if t.any() else t
            tp += int((hit & t).sum())
            fn += int((~hit & t).sum())
            det += int(hit.sum())
            right += int((hit & near).sum())
            if t.any():
                half += int((hit & t).sum() >= 0.5 * t.sum())
            else:
                flagged += int(hit.any())
        mark = " (card)" if th == mask.threshold else ""
        print(f"| {th:.2f}{mark} | {100 * tp / max(tp + fn, 1):.0f} % | {100 * right / max(det, 1):.0f} % | "
              f"{half} of {int(with_tools.sum())} | {flagged} of {int((~with_tools).sum())} |")
    return 0


def _plot_curve(training: dict, path: Path) -> None:
    """The card's learning curve(s): its own run and, where it started from another, that run's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim.core.atomic import save_figure

    runs = [("this run", training["curve"])]
    if training.get("before_curve"):
        runs.insert(0, ("the run it started from", training["before_curve"]))
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    offset = 0.0
    for name, curve in runs:
        c = np.asarray(curve, float)
        t = c[:, 0] + offset
        ax[0].plot(t, c[:, 3], label=f"validation loss ({name})")
        ax[0].plot(t, c[:, 2], "--", alpha=0.6, label=f"training loss ({name})")
        ax[1].plot(t, c[:, 4], label=f"recall ({name})")
        ax[1].plot(t, c[:, 5], "--", label=f"precision ({name})")
        offset = t[-1]
    ax[0].set_xlabel("minutes of training (2 CPU cores)")
    ax[1].set_xlabel("minutes of training (2 CPU cores)")
    ax[1].set_ylabel("pixels at p >= 0.5, validation frames")
    ax[1].set_ylim(0, 1)
    for a_ in ax:
        a_.legend(fontsize=7)
        a_.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
