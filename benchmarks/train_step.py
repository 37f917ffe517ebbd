"""One training step of the pose-update network by memory layout and precision.

Usage (from the repository root, after set-up)::

    .venv/bin/python benchmarks/train_step.py [--backbones tiny small] [--size 64] [--batch 256] [--steps 3]

A step is what ``ctxreg train`` does per batch after the pairs are made: forward, the relative
loss, backward and Adam. Rows per backbone:

* ``plain fp32``: the maps in PyTorch's default NCHW layout, float32 (the network before
  2026-11-26);
* ``channels-last fp32``: the network's layout now (:class:`learn.model.PoseUpdateNet`), float32;
* ``channels-last bf16``: the same under ``torch.autocast`` bfloat16, ``train.precision = "bf16"``
  (the heads stay in float32).

The variants' steps are interleaved (step 1 of every variant, then step 2, ...) so that a drift
of a shared machine's speed hits every row alike: read the ratio column. Random images stand in
for pairs (timing does not depend on content); two untimed warm-up steps each (oneDNN builds its
kernels on the first). Columns: median ms per step, pairs per second, speed-up over plain fp32.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: The rows of each backbone: (name, channels last, bfloat16).
VARIANTS = (("plain fp32", False, False), ("channels-last fp32", True, False), ("channels-last bf16", True, True))


def _step_fn(backbone: str, channels_last: bool, bf16: bool, batch, device: str):
    import torch

    from learn.model import pose_update_net
    from learn.train import TrainConfig, _loss

    torch.manual_seed(0)
    model = pose_update_net(backbone=backbone).to(device)
    if not channels_last:
        model.to(memory_format=torch.contiguous_format)
        model.backbone.memory_format = torch.contiguous_format
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    cfg = TrainConfig(dataset="x.toml", loss="relative", relative_eps=0.1)
    a, b, y = batch

    def step():
        with torch.autocast(device, dtype=torch.bfloat16, enabled=bf16):
            out = model(a, b)
        loss = _loss(type(out)(*(t.float() for t in out)), y, cfg)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if device == "cuda":
            torch.cuda.synchronize()

    return step


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backbones", nargs="+", default=["tiny", "small"], choices=("tiny", "small", "densenet121"),
                    help="backbones (default: tiny small)")
    ap.add_argument("--size", type=int, default=64, help="image side in px (default 64, the training size)")
    ap.add_argument("--batch", type=int, default=256, help="pairs per step (default 256, the batched recipe's)")
    ap.add_argument("--steps", type=int, default=3, help="timed steps per row (default 3)")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    args = ap.parse_args(argv)
    if args.size < 32 or args.batch < 1 or args.steps < 1:
        ap.error("--size must be >= 32, --batch and --steps >= 1")
    sys.path.insert(0, str(REPO))
    import torch

    torch.manual_seed(0)
    n, s = args.batch, args.size
    batch = tuple(t.to(args.device) for t in (torch.randn(n, 1, s, s), torch.randn(n, 1, s, s),
                                                torch.randn(n, 6) * 0.3))
    rows = [(bb, name, _step_fn(bb, cl, bf, batch, args.device)) for bb in args.backbones for name, cl, bf in VARIANTS]
    for _, name, fn in rows:  # warm-up: oneDNN / cuDNN choose and build their kernels
        fn()
        fn()
    times = {(bb, name): [] for bb, name, _ in rows}
    for _ in range(args.steps):
        for bb, name, fn in rows:
            t0 = time.perf_counter()
            fn()
            times[(bb, name)].append(time.perf_counter() - t0)
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, torch {torch.__version__}, device {args.device}, "
          f"{torch.get_num_threads()} threads, {s}x{s} px, batch {n}, median of {args.steps} interleaved steps\n")
    print("| backbone | variant | ms/step | pairs/s | plain fp32 / this |")
    print("|---|---|---|---|---|")
    for bb in args.backbones:
        base = statistics.median(times[(bb, VARIANTS[0][0])])
        for name, _, _ in VARIANTS:
            t = statistics.median(times[(bb, name)])
            print(f"| {bb} | {name} | {t * 1e3:.0f} | {n / t:.0f} | {base / t:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
