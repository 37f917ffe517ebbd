"""``ctxreg train``: defaults (one dataclass) and the run."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from sim.cliargs import opt


@dataclass(frozen=True)
class TrainCommand:
    """Defaults of ``ctxreg train``."""

    config: str = field(metadata=opt("training config (TOML with a [train] table; see learn/train.py)",
                                     group="input", positional=True, metavar="CONFIG.toml"))
    resume: bool = field(default=False, metadata=opt(
        "continue from the output folder's checkpoint (same config)", group="run"))


def run_train(cmd: TrainCommand) -> list[Path]:
    from learn.train import load_train_config, train

    cfg = load_train_config(cmd.config)
    train(cfg, resume=cmd.resume)
    out = Path(cfg.out)
    return [out / "checkpoint.pt", out / "log.csv", out / "loss.png"]


@dataclass(frozen=True)
class AccuracyCommand:
    """Defaults of ``ctxreg accuracy``."""

    model: str = field(metadata=opt("trained network checkpoint (ctxreg train)", group="input", positional=True,
                                    metavar="CKPT"))
    ct: str | None = field(default=None, metadata=opt(
        "CT to evaluate on (NIfTI, DICOM folder or phantom[:SEED]); or use --campaign", group="input",
        metavar="PATH|phantom"))
    campaign: str | None = field(default=None, metadata=opt(
        "campaign file whose --split subjects (e.g. held-out virtual patients) to evaluate on", group="input",
        metavar="FILE.toml"))
    split: str = field(default="val", metadata=opt("split of --campaign", group="input",
                                                   choices=("train", "val", "test")))
    kind: tuple[str, ...] = field(default=("far", "ap", "near"), metadata=opt(
        "pair kinds: far (independent poses), ap (current at AP), near (current close to the target)",
        group="protocol", nargs="+", choices=("far", "ap", "near")))
    pairs: int = field(default=200, metadata=opt("pairs per kind (spread over the subjects)", group="protocol",
                                                 metavar="N"))
    seed: int = field(default=0, metadata=opt("seed of the pairs", group="protocol"))
    out: str = field(default="out/accuracy", metadata=opt(
        "folder for accuracy.md, accuracy.json, accuracy.png", group="output", metavar="DIR"))


def run_accuracy(cmd: AccuracyCommand) -> list[Path]:
    import numpy as np

    from learn.evaluate import (AccuracyError, accuracy_figure, format_accuracy_table, merge_errors,
                                prediction_errors, sample_eval_pairs, summarize_errors)
    from register.contextual import NetworkPredictor
    from sim.atomic import atomic_path, write_json

    if (cmd.ct is None) == (cmd.campaign is None):
        raise AccuracyError("give exactly one of --ct and --campaign")
    if cmd.pairs < 1:
        raise AccuracyError(f"--pairs must be >= 1, got {cmd.pairs}")
    predictor = NetworkPredictor(cmd.model)
    if predictor.size is None:
        raise AccuracyError(f"{cmd.model} does not record its image size (trained before it was stored)")
    renderers = _accuracy_renderers(cmd, predictor.size)
    errors, results = {}, {}
    for ki, kind in enumerate(cmd.kind):
        parts = []
        counts = np.diff(np.linspace(0, cmd.pairs, len(renderers) + 1).round().astype(int))
        for si, (renderer, n) in enumerate(zip(renderers, counts)):
            if n == 0:
                continue
            rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(cmd.seed, spawn_key=(30, ki, si))))
            T_a, T_b = sample_eval_pairs(kind, rng, int(n), renderer.geometry.sod_mm)
            parts.append(prediction_errors(predictor, renderer, T_a, T_b))
        errors[kind] = merge_errors(parts)
        results[kind] = summarize_errors(errors[kind])
    out = Path(cmd.out)
    out.mkdir(parents=True, exist_ok=True)
    source = cmd.ct or f"{cmd.campaign} [{cmd.split}]"
    table = format_accuracy_table(results)
    print(f"{cmd.model} on {source} ({len(renderers)} subject(s))\n{table}")
    with atomic_path(out / "accuracy.md") as tmp:
        tmp.write_text(f"Model: `{cmd.model}`; subjects: `{source}` ({len(renderers)}); "
                       f"{cmd.pairs} pairs per kind, seed {cmd.seed}.\n\n{table}")
    write_json(out / "accuracy.json", {"model": cmd.model, "source": source, "subjects": len(renderers),
                                       "pairs": cmd.pairs, "seed": cmd.seed, "results": results})
    accuracy_figure(errors, out / "accuracy.png", title=f"single-prediction errors: {Path(source).name}")
    return [out / "accuracy.md", out / "accuracy.json", out / "accuracy.png"]


def _accuracy_renderers(cmd: AccuracyCommand, size) -> list:
    from learn.evaluate import AccuracyError
    from sim.render import DRRRenderer, RenderSettings

    if cmd.ct is not None:
        from sim.anatomy import anatomy_center
        from sim.ct_io import load_ct_spec

        volume = load_ct_spec(cmd.ct)
        return [DRRRenderer(volume, RenderSettings(size=tuple(size)), center_lps=anatomy_center(volume))]
    from dataclasses import replace

    from sim.campaign.config import load_campaign
    from sim.campaign.runner import SubjectContext

    campaign = load_campaign(cmd.campaign)
    campaign = replace(campaign, scene=replace(campaign.scene, size=tuple(size)))
    subjects = [s for s in campaign.subjects() if s.split == cmd.split]
    if not subjects:
        raise AccuracyError(f"{cmd.campaign} has no subject in split {cmd.split!r}")
    return [next(iter(SubjectContext(campaign, s).renderers.values())) for s in subjects]
