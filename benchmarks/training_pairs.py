"""Training pairs per second: realistic randomized targets against line pairs (issue 15).

Usage (from the repository root, after set-up)::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/training_pairs.py [--batches 6] [--batch-size 32]

The CPU recipe's online pairs (``campaigns/pelvis_vp.toml``: the pelvis CT's 24 training
virtual patients, 64 x 64 px, 4 subjects per batch) of three kinds, measured in the same run:

* ``line``: target and current Siddon line-integral DRRs (the recipe of ``models/pelvis_line``);
* ``realistic``: the target drawn with domain randomization and prepared as registration does
  (``learn.online.RealisticTargets``: density integrals, tools, spectrum, noise, kernel scatter,
  collimator, display chain, bits), the current a line DRR;
* ``realistic, no tools``: the same with ``tools = false``;
* ``realistic, batched``: the same randomization through ``learn.batched.BatchedPairs``
  (``train.pairs = "batched"``): the two-basis model and every image stage batched in torch (on a
  CPU the ray march is Dr.Jit's Siddon kernel; with ``--device cuda`` everything runs on the GPU);
* ``realistic, batched, sks``: the batched pairs with the randomization of the long training's
  recipe (``configs/train_batched_small_sks.toml``'s ``[train.randomize]``, read from the file:
  the scatter-kernel model fitted to the Monte Carlo, with its texture, on most targets; a share
  of ideal line-DRR targets).

``--kinds`` picks the rows (default all five); ``--device`` runs the network (and the batched
pairs) there.

The kinds' batches are interleaved (batch 1 of every kind, then batch 2, ...), so that a drift
of the machine's speed (a shared 2-core VM drifts by tens of percent over a minute) hits every
row alike; the ratio column is the comparison to read.

Columns: median seconds per batch of rendering (``OnlinePairs.batch``), of one optimiser step
of the tiny network (forward, backward, Adam) and of both, pairs per second of both, and the
ratio of the line rate to each. Batches are new draws each time (batch indices 1..); every
one-off cost is paid before the timing (each subject's CT, virtual patient and renderers, and for
realistic pairs every spectrum model and tool arrangement: about a minute in all, which a
training run pays once, spread over its first few hundred batches). The pairs are the network's
input after the training preprocessing (``normalize``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


#: The rows of the table, in order.
KINDS = ("line", "realistic", "realistic, no tools", "realistic, batched", "realistic, batched, sks")

#: The config whose ``[train.randomize]`` table the ``realistic, batched, sks`` row draws from.
SKS_RECIPE = REPO / "configs" / "train_batched_small_sks.toml"


def _recipe_table(path: Path) -> dict:
    """The ``[train.randomize]`` table of a training config (TOML)."""
    import tomllib

    with open(path, "rb") as f:
        return dict(tomllib.load(f)["train"]["randomize"])


#: Full-size batches each kind draws before the timing (batch indices WARM_BASE ..), after its
#: one-off costs: the first few full batches run slower (allocations growing to their steady state).
WARM_BATCHES = 2
WARM_BASE = 100_000


def _source(kind: str, device="cpu"):
    from learn.online import NearPairs, OnlinePairs
    from learn.preprocess import build
    from sim.campaign.config import load_campaign
    from sim.randomize import DomainRandomization

    cfg = load_campaign(REPO / "campaigns" / "pelvis_vp.toml")
    if kind == "line":
        table = None
    elif kind == "realistic, batched, sks":
        table = _recipe_table(SKS_RECIPE)
    else:
        table = {"scatter": ["none", "kernel"], **({"tools": False} if "no tools" in kind else {})}
    randomization = None if table is None else DomainRandomization.from_table(table)
    if kind.startswith("realistic, batched"):
        from learn.batched import BatchedPairs

        return BatchedPairs(cfg, "train", near=NearPairs(), transform=build(["normalize"]), seed=0,
                            subjects_per_batch=4, randomization=randomization, device=device,
                            tables=REPO / "runs" / "bench_pairs_tables")
    return OnlinePairs(cfg, "train", near=NearPairs(), transform=build(["normalize"]), seed=0,
                       subjects_per_batch=4, randomization=randomization)


def _warm(source) -> None:
    """Pay every one-off cost before timing: each subject's CT, virtual patient and renderers, and
    for realistic pairs every spectrum model (kV x filtration) and tool arrangement."""
    import itertools

    from sim.randomize import TOOL_BANK_SIZE

    if hasattr(source, "prepare"):  # batched: volumes, table, tool bank, every subject's renderers
        source.prepare()
        for u in range(len(source.subjects)):
            for chans in ((0,), (1, 2)):
                if hasattr(source._volumes, "_renderer"):
                    source._volumes._renderer(u, chans)
        source.batch(0, 4)
        return
    for u in range(len(source.subjects)):
        source.context(u)
        if source.realistic is not None:
            source.density_renderer(u)
    rt = source.realistic
    if rt is not None:
        by = rt.randomization.by_name
        kvs = np.arange(by["kvp"].low, by["kvp"].high + 1e-9, by["kvp"].step)
        als = np.arange(by["al_mm"].low, by["al_mm"].high + 1e-9, by["al_mm"].step)
        for kv, al, cu in itertools.product(kvs, als, by["cu_mm"].choices):
            filters = (("Al", float(al)),) + ((("Cu", float(cu)),) if cu > 0 else ())
            rt._model(replace(rt.base, kvp=float(kv), filters=filters))
        for j in range(TOOL_BANK_SIZE):
            rt.bank.arrangement(j)
    source.batch(0, 4)


def main(argv=None) -> int:
    import torch

    from learn.model import pose_update_net

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batches", type=int, default=6, help="timed batches per kind (default 6)")
    ap.add_argument("--batch-size", type=int, default=32, help="pairs per batch (default 32, the recipe's)")
    ap.add_argument("--kinds", nargs="+", choices=KINDS, default=KINDS, help="rows, in this order (default all)")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"),
                    help="where the network steps and the batched pairs are made (default cpu)")
    args = ap.parse_args(argv)
    if args.batches < 1 or args.batch_size < 1:
        ap.error("--batches and --batch-size must be >= 1")
    torch.manual_seed(0)
    model = pose_update_net(backbone="tiny").to(args.device)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    sync = torch.cuda.synchronize if args.device == "cuda" else (lambda: None)
    sources = {}
    for kind in args.kinds:
        sources[kind] = _source(kind, args.device)
        _warm(sources[kind])
        for j in range(WARM_BATCHES):  # full-size batches: the allocator's and caches' steady state
            sources[kind].batch(WARM_BASE + j, args.batch_size)
    render = {kind: [] for kind in args.kinds}
    step = {kind: [] for kind in args.kinds}
    for k in range(1, args.batches + 1):
        for kind in args.kinds:  # interleaved: a drift of the machine's speed hits every row alike
            sync()
            t0 = time.perf_counter()
            a, b, y = (t.to(args.device) for t in sources[kind].batch(k, args.batch_size))
            sync()
            t1 = time.perf_counter()
            out = model(a, b)
            loss = model.loss(out, y)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sync()
            t2 = time.perf_counter()
            render[kind].append(t1 - t0)
            step[kind].append(t2 - t1)
    rows = []
    for kind in args.kinds:
        r, s = statistics.median(render[kind]), statistics.median(step[kind])
        rows.append((kind, r, s, r + s, args.batch_size / (r + s)))
        print(f"  {kind}: {args.batch_size / (r + s):.0f} pairs/s", file=sys.stderr)
    line_rate = rows[0][4] if rows[0][0] == "line" else float("nan")
    print(f"\n{args.batch_size} pairs per batch, median of {args.batches} batches, "
          f"torch threads {torch.get_num_threads()}, device {args.device}\n")
    print("| pairs | render s/batch | step s/batch | total s/batch | pairs/s | line / this |")
    print("|---|---|---|---|---|---|")
    for kind, r, s, t, rate in rows:
        print(f"| {kind} | {r:.3f} | {s:.3f} | {t:.3f} | {rate:.0f} | {line_rate / rate:.1f}x |")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    raise SystemExit(main())
