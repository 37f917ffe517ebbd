"""Single-prediction accuracy of a trained network on fresh pairs (the original's Figure 3.1 form).

For a subject (a CT or a virtual patient), ``pairs`` (target, current) pose pairs are drawn
(seeded), both DRRs rendered, and the network's predicted gradient compared with the true label
``g = -2 log_{T_current}(T_target)``: rotation error = ``|g_rot,pred - g_rot,true|`` (degrees),
translation error = ``|g_trans,pred - g_trans,true|`` (mm), for each depth's prediction and for
the weighted sum. The zero predictor's errors (``|g_true|``) are the baseline a network must beat.

Pair kinds (:data:`PAIR_KINDS`):

* ``far``: target and current drawn independently from the pose distribution (the original's pairs);
* ``ap``: target from the distribution, current at AP (all parameters 0): the first step of a
  registration from AP;
* ``near``: current = target o Exp(delta) with :class:`learn.online.NearPairs` offsets: the steps
  that decide where the registration comes to rest.

``ctxreg accuracy --model CKPT --ct SPEC`` or ``--campaign FILE --split val`` runs it and writes a table,
a JSON file and a box-plot figure (:mod:`learn.commands`).
"""

from __future__ import annotations

import math

from sim.core.errors import InputError

import numpy as np
import torch
from learn.labels import apply_update, geodesic_label
from learn.online import NearPairs
from learn.predict import NetworkPredictor
from sim.campaign.poses import ORIGINAL_PROTOCOL
from sim.core.atomic import save_figure
from sim.core.seeds import KIND_ACCURACY_PAIRS, rng_for
from sim.projection.drr import DRRRenderer, RenderSettings
from sim.projection.geometry import pose_from_params

#: Kinds of evaluation pairs (see the module doc).
PAIR_KINDS = ("far", "ap", "near")

#: Output names in a result, in table order.
OUTPUTS = ("weighted_sum", "depth1", "depth2", "depth3", "zero_baseline")


class AccuracyError(InputError):
    """An accuracy evaluation cannot run; the message says why."""


def sample_eval_pairs(kind: str, rng: np.random.Generator, n: int, sod_mm: float, distribution=None,
                      near=None) -> tuple[np.ndarray, np.ndarray]:
    """``(T_target, T_current)``, each ``(n, 4, 4)`` (mm), of the given pair kind."""

    if kind not in PAIR_KINDS:
        raise AccuracyError(f"pair kind must be one of {PAIR_KINDS}, got {kind!r}")
    dist = distribution or ORIGINAL_PROTOCOL
    T_a = pose_from_params(dist.sample(rng, n), sod_mm)
    if kind == "far":
        T_b = pose_from_params(dist.sample(rng, n), sod_mm)
    elif kind == "ap":
        T_b = pose_from_params(np.zeros((n, 6)), sod_mm)
    else:
        delta = (near or NearPairs()).offsets(rng, n)
        T_b = apply_update(T_a, -delta, 1.0)
    return T_a, T_b


def prediction_errors(predictor, renderer, T_a: np.ndarray, T_b: np.ndarray, *,
                      current_renderer=None) -> dict[str, np.ndarray]:
    """Per-pair errors ``{output: (rot_deg (n,), trans_mm (n,))}`` of a
    :class:`learn.predict.NetworkPredictor` on target images at ``T_a`` ``(n, 4, 4)`` from
    ``renderer`` and current images at ``T_b`` from ``current_renderer`` (default: the same).

    Raises:
        AccuracyError: the network's predictions are not finite (NaN or infinite) for some pair.
    """

    ia = renderer.render(T_a)
    ib = (renderer if current_renderer is None else current_renderer).render(T_b)
    true = geodesic_label(torch.from_numpy(T_a), torch.from_numpy(T_b)).numpy()
    preds, levels = predictor.predict(ia, ib)  # (n, 6), (n, 3, 6)
    bad = int((~(np.isfinite(preds).all(axis=1) & np.isfinite(levels).all(axis=(1, 2)))).sum())
    if bad:
        raise AccuracyError(f"the network's prediction is NaN or infinite for {bad} of {len(preds)} pairs")

    def errs(p):
        return (np.degrees(np.linalg.norm(p[..., :3] - true[..., :3], axis=-1)),
                np.linalg.norm(p[..., 3:] - true[..., 3:], axis=-1))

    out = {"weighted_sum": errs(preds)}
    for i in range(levels.shape[1]):
        out[f"depth{i + 1}"] = errs(levels[:, i])
    out["zero_baseline"] = errs(np.zeros_like(true))
    return out


def summarize_errors(errors: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, dict[str, float]]:
    """Median and mean of each output's rotation (deg) and translation (mm) errors."""
    return {name: {"rot_deg_median": float(np.median(r)), "rot_deg_mean": float(np.mean(r)),
                   "trans_mm_median": float(np.median(t)), "trans_mm_mean": float(np.mean(t))}
            for name, (r, t) in errors.items()}


def merge_errors(parts: list[dict]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Concatenate per-subject error dicts."""
    return {k: (np.concatenate([p[k][0] for p in parts]), np.concatenate([p[k][1] for p in parts]))
            for k in parts[0]}


def single_prediction_errors(checkpoint: str, volume, *, pairs: int = 200, size=None, seed: int = 0,
                             center_lps=None, distribution=None, kind: str = "far", near=None) -> dict:
    """Errors of the weighted sum, of each depth, and of the zero baseline (median and mean)
    on ``pairs`` pairs of ``kind`` for one CT volume. ``size``: image size (default: the model's)."""
    from sim.ct.anatomy import anatomy_center  # loads SciPy: imported where first needed (start-up)

    predictor = NetworkPredictor(checkpoint)
    center = anatomy_center(volume) if center_lps is None else np.asarray(center_lps, float)
    renderer = DRRRenderer(volume, RenderSettings(size=tuple(size or predictor.size)), center_lps=center)

    rng = rng_for(seed, KIND_ACCURACY_PAIRS)
    T_a, T_b = sample_eval_pairs(kind, rng, pairs, renderer.geometry.sod_mm, distribution, near)
    return summarize_errors(prediction_errors(predictor, renderer, T_a, T_b))


def finite_or_none(obj):
    """``obj`` (dicts, lists, tuples of numbers and strings) with every NaN or infinite float
    replaced by None: JSON without bare ``NaN`` or ``Infinity``."""
    if isinstance(obj, dict):
        return {k: finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_none(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def format_accuracy_table(results: dict[str, dict[str, dict[str, float]]]) -> str:
    """Markdown table: one row per (pair kind, output)."""
    lines = ["| pairs | output | rotation median (deg) | rotation mean (deg) | translation median (mm) "
             "| translation mean (mm) |", "|---|---|---|---|---|---|"]
    for kind, res in results.items():
        for name in OUTPUTS:
            if name in res:
                r = res[name]
                lines.append(f"| {kind} | {name.replace('_', ' ')} | {r['rot_deg_median']:.2f} | "
                             f"{r['rot_deg_mean']:.2f} | {r['trans_mm_median']:.1f} | {r['trans_mm_mean']:.1f} |")
    return "\n".join(lines) + "\n"


def accuracy_figure(errors: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]], path, title: str = "") -> None:
    """Box plots of rotation and translation errors per output, one row per pair kind (Figure 3.1 form)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = list(errors)
    fig, axes = plt.subplots(len(kinds), 2, figsize=(10, 3.2 * len(kinds)), squeeze=False)
    for row, kind in enumerate(kinds):
        names = [n for n in OUTPUTS if n in errors[kind]]
        for col, (label, unit) in enumerate((("rotation error", "deg"), ("translation error", "mm"))):
            ax = axes[row, col]
            ax.boxplot([errors[kind][n][col] for n in names], showfliers=False)
            ax.set_xticks(range(1, len(names) + 1), [n.replace("_", "\n") for n in names], fontsize=8)
            ax.set_ylabel(f"{label} ({unit})")
            ax.set_title(f"{kind} pairs", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)
