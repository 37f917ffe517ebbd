"""Learning benchmark: training pairs per second and inference ms per pair for each recipe.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/learn.py [--size 128] [--batch 16] [--steps 5]

Recipes (``learn.model.pose_update_net``): the tiny DenseNet (CPU recipe candidate),
DenseNet-121 and DenseNet-161 trained end to end, and DenseNet-161 with a frozen backbone
whose features are cached (the heads alone are trained: ``heads_forward`` on stored features,
so a training step costs only the heads; the one-off feature extraction is timed separately).
Random images stand in for DRRs (timing does not depend on content). Median of ``--steps``
timed steps after one warm-up step; torch uses all cores.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def timed(fn, steps: int) -> float:
    fn()
    out = []
    for _ in range(steps):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


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
    return 0


if __name__ == "__main__":
    sys.exit(main())
