"""Single-prediction accuracy of a trained network on fresh pairs (the original's Figure 3.1 form).

For a CT, ``pairs`` (target, current) pose pairs are drawn (seeded) from a pose distribution,
both DRRs rendered, and the network's predicted gradient compared with the true label
``g = -2 log_{T_current}(T_target)``: rotation error = ``|g_rot,pred - g_rot,true|`` (degrees),
translation error = ``|g_trans,pred - g_trans,true|`` (mm), for each depth's prediction and for
the weighted sum. The zero predictor's errors (``|g_true|``) are the baseline a network must beat.
"""

from __future__ import annotations

import numpy as np
import torch


def single_prediction_errors(checkpoint: str, volume, *, pairs: int = 200, size=(64, 64), seed: int = 0,
                             center_lps=None, distribution=None) -> dict:
    """Errors of the weighted sum, of each depth, and of the zero baseline (median and mean)."""
    from learn.labels import geodesic_label
    from register.contextual import NetworkPredictor
    from sim.anatomy import anatomy_center
    from sim.campaign.poses import ORIGINAL_PROTOCOL
    from sim.geometry import pose_from_params
    from sim.render import DRRRenderer, RenderSettings

    predictor = NetworkPredictor(checkpoint)
    center = anatomy_center(volume) if center_lps is None else np.asarray(center_lps, float)
    renderer = DRRRenderer(volume, RenderSettings(size=tuple(size)), center_lps=center)
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=(30,))))
    dist = distribution or ORIGINAL_PROTOCOL
    pa, pb = dist.sample(rng, pairs), dist.sample(rng, pairs)
    Ta, Tb = pose_from_params(pa, renderer.geometry.sod_mm), pose_from_params(pb, renderer.geometry.sod_mm)
    ia, ib = renderer.render(Ta), renderer.render(Tb)
    true = geodesic_label(torch.from_numpy(Ta), torch.from_numpy(Tb)).numpy()
    preds, levels = [], []
    model, norm = predictor.model, predictor.normalizer
    with torch.no_grad():
        for k in range(pairs):
            x = predictor.transform(torch.from_numpy(np.stack([ia[k], ib[k]]).astype(np.float32))[:, None])
            out = model(x[:1], x[1:2])
            preds.append(norm.denormalize(out.g[0].double()).numpy())
            levels.append(norm.denormalize(out.g_levels[0].double()).numpy())
    preds, levels = np.array(preds), np.array(levels)  # (N, 6), (N, 3, 6)

    def errs(p):
        rot = np.degrees(np.linalg.norm(p[..., :3] - true[..., :3], axis=-1))
        trans = np.linalg.norm(p[..., 3:] - true[..., 3:], axis=-1)
        return {"rot_deg_median": float(np.median(rot)), "rot_deg_mean": float(rot.mean()),
                "trans_mm_median": float(np.median(trans)), "trans_mm_mean": float(trans.mean())}

    out = {"weighted_sum": errs(preds), "zero_baseline": errs(np.zeros_like(true))}
    for i in range(levels.shape[1]):
        out[f"depth{i + 1}"] = errs(levels[:, i])
    return out
