"""Learning benchmark: training pairs per second and inference ms per pair for each recipe.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/learn.py [--size 128] [--batch 16] [--steps 5]

Recipes (``learn.model.pose_update_net``): the tiny DenseNet (CPU recipe candidate),
DenseNet-121 and DenseNet-161 trained end to end, and DenseNet-161 with a frozen backbone
whose features are cached (the heads alone are trained: ``heads_forward`` on stored features,
so a training step costs only the heads; the one-off feature extraction is timed separately).
Random images stand in for DRRs (timing does not depend on content). Median of ``--steps``
timed steps after one warm-up step; torch uses all cores.

The last row is the CPU recipe as it trains (docs/training.md): the tiny DenseNet on pairs
rendered on the fly (:mod:`learn.online`, ``campaigns/pelvis_vp.toml``, 64 x 64, batch 32): each
step renders its 64 DRRs, normalises them and trains; it needs the shared pelvis CT
(``../shared/data``) and is skipped without it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

from timing import timed  # noqa: E402  (benchmarks/timing.py)



def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=128, help="image side in pixels (default: 128)")
    ap.add_argument("--batch", type=int, default=16, help="pairs per training step (default: 16)")
    ap.add_argument("--steps", type=int, default=5, help="timed steps per recipe (default: 5)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import torch

    from learn.model import pose_update_net

    torch.manual_seed(0)
    b, s = args.batch, args.size
    a = torch.randn(b, 1, s, s)
    c = torch.randn(b, 1, s, s)
    y = torch.randn(b, 6)
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{s}x{s} images, batch {b}")
    print("| recipe | trainable params | train pairs/s | inference ms/pair | notes |")
    print("|---|---|---|---|---|")
    for backbone, frozen in (("tiny", False), ("densenet121", False), ("densenet161", False), ("densenet161", True)):
        model = pose_update_net(backbone=backbone, freeze_backbone=frozen)
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.Adam(params, lr=1e-4)
        n_params = sum(p.numel() for p in params)
        note = ""
        if frozen:
            with torch.no_grad():
                t0 = time.perf_counter()
                feats = model.extract_features(a, c)
                extract = time.perf_counter() - t0
            feats = [f.detach() for f in feats]

            def step():
                out = model.heads_forward(feats)
                loss = model.loss(out, y)
                opt.zero_grad()
                loss.backward()
                opt.step()

            note = f"features cached once: {extract / b * 1e3:.0f} ms/pair to extract"
        else:
            def step():
                out = model(a, c)
                loss = model.loss(out, y)
                opt.zero_grad()
                loss.backward()
                opt.step()

        t_step = timed(step, args.steps)
        model.eval()
        with torch.no_grad():
            t_inf = timed(lambda: model(a[:1], c[:1]), args.steps)
        print(f"| {backbone}{' frozen+cached' if frozen else ''} | {n_params / 1e6:.2f} M | {b / t_step:.1f} | "
              f"{t_inf * 1e3:.1f} | {note} |")
    recipe_row(args.steps)
    return 0


def recipe_row(steps: int) -> None:
    """The CPU recipe's full step: render a batch of online pairs, then train on it."""
    import torch

    from learn.model import pose_update_net
    from learn.online import NearPairs, OnlinePairs
    from learn.preprocess import build
    from sim.campaign.config import CampaignConfigError, load_campaign

    try:
        cfg = load_campaign(REPO / "campaigns" / "pelvis_vp.toml")
    except CampaignConfigError as e:
        print(f"| tiny, online pairs (the recipe) | | n/a | | skipped: {e} |")
        return
    batch = 32
    pairs = OnlinePairs(cfg, "train", near=NearPairs(0.5), transform=build(["normalize"]), seed=0)
    model = pose_update_net(backbone="tiny")
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    k = iter(range(10**9))
    for u in range(len(pairs.subjects)):  # build every subject once (virtual patients: ~0.5 s each)
        pairs.context(u)
    render = timed(lambda: pairs.batch(next(k), batch), steps)

    def step():
        target, current, label = pairs.batch(next(k), batch)
        loss = model.loss(model(target, current), label)
        opt.zero_grad()
        loss.backward()
        opt.step()

    t_step = timed(step, steps)
    h, w = cfg.scene.size
    print(f"| tiny, online pairs (the recipe, {h}x{w}, batch {batch}) | "
          f"{sum(p.numel() for p in model.parameters()) / 1e6:.2f} M | {batch / t_step:.1f} | | "
          f"rendering {render / batch * 1e3:.2f} ms/pair of it |")


if __name__ == "__main__":
    sys.exit(main())
