"""``ctxreg train``: defaults (one dataclass) and the run."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from sim.core.cliargs import Range, opt
from learn.shipped import DEFAULT_ADAPT_BASE, describe_model, describe_models, shipped_models
from sim.core.atomic import atomic_path, write_json
from sim.core.outputs import check_output_dir
from sim.core.seeds import KIND_ACCURACY_PAIRS, rng_for


@dataclass(frozen=True)
class TrainCommand:
    """Defaults of ``ctxreg train``."""

    config: str = field(metadata=opt("training config (TOML with a [train] table; see learn/train.py)",
                                     group="input", positional=True, metavar="CONFIG.toml"))
    resume: bool = field(default=False, metadata=opt(
        "continue from the output folder's checkpoint (same config); refused where the folder holds none (run "
        "without --resume to start)", group="run"))
    device: str = field(default="auto", metadata=opt(
        "where the network trains and batched pairs (train.pairs = 'batched') are made: auto (a CUDA GPU when "
        "torch sees one), cpu or cuda", group="run", choices=("auto", "cpu", "cuda")))
    stop_after: float | None = field(default=None, metadata=opt(
        "stop at the first iteration after this many seconds of training, with a checkpoint (then --resume); "
        "default: no limit, the run goes to train.iterations (Ctrl-C or SIGTERM also stops with a checkpoint at "
        "that step)",
        group="run", unit="s", metavar="S", bounds=Range(0.0, None, lo_open=True)))
    procs: int = field(default=1, metadata=opt(
        "train in N processes on this machine (data-parallel torch DDP, as torchrun --nproc-per-node N; the "
        "config is checked once before they start, a refusal printed once)", group="run",
        metavar="N", bounds=Range(1, 64)))


#: What ``ctxreg train`` writes into the config's ``out`` folder, and ``ctxreg accuracy`` into ``--out``.
TRAIN_FILES = ("checkpoint.pt", "log.csv", "loss.png")
ACCURACY_FILES = ("accuracy.md", "accuracy.json", "accuracy.png")


def run_train(cmd: TrainCommand) -> list[Path]:
    from learn.train import load_train_config, train  # loads torch: imported where first needed (start-up)

    from learn.train import resolve_device  # loads torch: imported where first needed (start-up)

    cfg = load_train_config(cmd.config)
    resolve_device(cmd.device)  # refused before any work
    out = check_output_dir(cfg.out, TRAIN_FILES, flag=f"{cmd.config}: [train] out")
    if cmd.resume and not (out / "checkpoint.pt").is_file():
        from learn.train import TrainConfigError  # loads torch: imported where first needed (start-up)

        raise TrainConfigError(f"--resume: {out} holds no checkpoint.pt to resume from (train.out of {cmd.config}); "
                               f"run without --resume to start the training")
    from learn.distributed import DistributedRun, launch, under_torchrun  # loads torch: imported where first needed (start-up)

    if cmd.procs > 1 and not under_torchrun():
        DistributedRun(world=cmd.procs).check_batch(cfg.batch_size)  # the ranks' checks, once, before they start
        if cfg.cache_features:
            from learn.train import TrainConfigError  # loads torch: imported where first needed (start-up)

            raise TrainConfigError("train.cache_features: not with --procs (the cached heads' forward would bypass "
                                   "DDP's gradient averaging); train in one process or without the cache")
        launch(cmd.procs, ["train", str(cmd.config), "--device", cmd.device, *(["--resume"] if cmd.resume else []),
                           *(["--stop-after", repr(cmd.stop_after)] if cmd.stop_after is not None else [])])
    else:
        train(cfg, resume=cmd.resume, device=cmd.device, stop_after_s=cmd.stop_after)
    return [out / name for name in TRAIN_FILES]


@dataclass(frozen=True)
class AdaptCommand:
    """Defaults of ``ctxreg adapt`` (:mod:`learn.adapt`)."""

    ct: str = field(metadata=opt("the CT to adapt the network to (NIfTI file or DICOM series folder; phantom[:SEED]: "
                                 "the built-in pelvis, written into --out first)", group="input",
                                 metavar="CT"))
    out: str = field(metadata=opt("the output folder: the adapted model (model.pt, model.toml, for register --model "
                                  "DIR), the training run (run/) and adapt.json", group="output", metavar="DIR"))
    minutes: float = field(default=10.0, metadata=opt(
        "training time; with --resume, minutes more", group="run", unit="min", metavar="M",
        bounds=Range(0.0, 24 * 60.0, lo_open=True)))
    from_model: str | None = field(default=None, metadata=opt(
        "the base network: a shipped model's name (ctxreg models), a model folder or a checkpoint (default: "
        f"{DEFAULT_ADAPT_BASE}, the shipped base made to be adapted)", group="input", flag="--from", metavar="MODEL"))
    device: str = field(default="auto", metadata=opt(
        "where the network trains and its pairs are made: auto (a CUDA GPU when torch sees one), cpu or cuda",
        group="run", choices=("auto", "cpu", "cuda")))
    resume: bool = field(default=False, metadata=opt(
        "continue the adaptation in --out (its checkpoint, optimiser and random state) for --minutes more",
        group="run"))


def run_adapt(cmd: AdaptCommand) -> list[Path]:
    from learn.adapt import ADAPT_FILES, adapt  # off the CLI's start-up: building the parser imports every command's module

    out = check_output_dir(cmd.out, ADAPT_FILES)
    adapt(cmd.ct, out, minutes=cmd.minutes, base=cmd.from_model, device=cmd.device, resume=cmd.resume)
    return [out / name for name in ADAPT_FILES]


@dataclass(frozen=True)
class TrainToolsCommand:
    """Defaults of ``ctxreg train-tools`` (:mod:`learn.tool_mask`)."""

    out: str = field(default="runs/tool_mask", metadata=opt(
        "the output folder: checkpoint.pt and log.csv of the run, model/ (card.toml and weights.pt, for "
        "models/tool_mask)", group="output", metavar="DIR"))
    minutes: float = field(default=45.0, metadata=opt(
        "training time (the learning rate's cosine runs over it); with --resume the same run continues",
        group="run", unit="min", metavar="M", bounds=Range(0.0, 24 * 60.0, lo_open=True)))
    device: str = field(default="auto", metadata=opt(
        "where the segmenter trains and its frames are made: auto (a CUDA GPU when torch sees one), cpu or cuda",
        group="run", choices=("auto", "cpu", "cuda")))
    resume: bool = field(default=False, metadata=opt(
        "continue the run in --out from its checkpoint (same settings)", group="run"))


def run_train_tools(cmd: TrainToolsCommand) -> list[Path]:
    from learn.tool_mask import TOOL_TRAIN_FILES, ToolTrainSettings, export_tool_mask, train_tool_mask  # torch
    from learn.train import resolve_device  # loads torch: imported where first needed (start-up)

    out = check_output_dir(cmd.out, TOOL_TRAIN_FILES)
    settings = ToolTrainSettings(minutes=cmd.minutes)
    device = resolve_device(cmd.device)
    checkpoint = train_tool_mask(out, settings, resume=cmd.resume, device=device)
    folder = export_tool_mask(checkpoint, out / "model")
    return [out / name for name in TOOL_TRAIN_FILES] + [folder]


@dataclass(frozen=True)
class AccuracyCommand:
    """Defaults of ``ctxreg accuracy``."""

    model: str = field(metadata=opt("the network: a shipped model's name (ctxreg models), a model folder or a ctxreg "
                                    "train checkpoint",
                                    group="input", metavar="NAME|CKPT"))
    ct: str | None = field(default=None, metadata=opt(
        "CT to evaluate on (NIfTI, DICOM folder or phantom[:SEED]); or use --campaign", group="input",
        metavar="PATH|phantom"))
    campaign: str | None = field(default=None, metadata=opt(
        "campaign file whose --split subjects (e.g. held-out virtual patients) to evaluate on", group="input",
        metavar="FILE.toml"))
    split: str = field(default="val", metadata=opt("split of --campaign", group="input",
                                                   choices=("train", "val", "test")))
    entry: str | None = field(default=None, metadata=opt(
        "name of the [[physics]] entry of --campaign that renders the target images (default: its first)",
        group="input", metavar="NAME"))
    current_entry: str | None = field(default=None, metadata=opt(
        "name of the [[physics]] entry of --campaign that renders the current images, e.g. noise-free poly "
        "beside full targets (default: as --entry)", group="input", metavar="NAME"))
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

    from learn.accuracy import (AccuracyError, accuracy_figure, finite_or_none, format_accuracy_table, merge_errors,  # loads torch: imported where first needed (start-up)
                                prediction_errors, sample_eval_pairs, summarize_errors)
    from learn.predict import NetworkPredictor  # off the CLI's start-up: building the parser imports every command's module

    out = check_output_dir(cmd.out, ACCURACY_FILES)
    if (cmd.ct is None) == (cmd.campaign is None):
        raise AccuracyError("give exactly one of --ct and --campaign")
    if cmd.pairs < 1:
        raise AccuracyError(f"--pairs must be >= 1, got {cmd.pairs}")
    predictor = NetworkPredictor(cmd.model)
    if predictor.size is None:
        raise AccuracyError(f"{cmd.model} does not record its image size (trained before it was stored)")
    renderers, names, current_settings = _accuracy_renderers(cmd, predictor.size)
    note = predictor.physics_mismatch(current_settings, advice="pick a matching --current-entry")
    if note:
        print(f"note: {note}")

    errors, results = {}, {}
    for ki, kind in enumerate(cmd.kind):
        parts = []
        counts = np.diff(np.linspace(0, cmd.pairs, len(renderers) + 1).round().astype(int))
        for si, ((target, current), n) in enumerate(zip(renderers, counts)):
            if n == 0:
                continue
            rng = rng_for(cmd.seed, KIND_ACCURACY_PAIRS, ki, si)
            T_a, T_b = sample_eval_pairs(kind, rng, int(n), target.geometry.sod_mm)
            parts.append(prediction_errors(predictor, target, T_a, T_b, current_renderer=current))
        errors[kind] = merge_errors(parts)
        results[kind] = summarize_errors(errors[kind])
    out.mkdir(parents=True, exist_ok=True)
    source = cmd.ct or f"{cmd.campaign} [{cmd.split}]"
    images = f"targets {names[0]}, current images {names[1]}"
    table = format_accuracy_table(results)
    print(f"{cmd.model} on {source} ({len(renderers)} subject(s); {images})\n{table}")
    with atomic_path(out / "accuracy.md") as tmp:
        tmp.write_text(f"Model: `{cmd.model}`; subjects: `{source}` ({len(renderers)}); {images}; "
                       f"{cmd.pairs} pairs per kind, seed {cmd.seed}.\n\n{table}")
    # JSON keys "physics" / "current_physics": the entry names (as train.physics in a config)
    write_json(out / "accuracy.json", finite_or_none({
        "model": cmd.model, "source": source, "subjects": len(renderers), "physics": names[0],
        "current_physics": names[1], "note": note, "pairs": cmd.pairs, "seed": cmd.seed, "results": results}))
    accuracy_figure(errors, out / "accuracy.png", title=f"single-prediction errors: {Path(source).name}")
    return [out / name for name in ACCURACY_FILES]


def _accuracy_renderers(cmd: AccuracyCommand, size) -> tuple[list, tuple[str, str], object]:
    """Per subject ``(target renderer, current renderer)``; the two images' physics names; the
    current images' :class:`~sim.physics.imaging.PhysicsSettings` (None for line DRRs)."""
    from learn.accuracy import AccuracyError  # loads torch: imported where first needed (start-up)
    from sim.campaign.config import load_campaign  # off the CLI's start-up: building the parser imports every command's module
    from sim.campaign.runner import SubjectContext  # off the CLI's start-up: building the parser imports every command's module
    from sim.projection.drr import DRRRenderer, RenderSettings  # off the CLI's start-up: building the parser imports every command's module

    if cmd.ct is not None:
        from sim.ct.anatomy import anatomy_center  # loads SciPy: imported where first needed (start-up)
        from sim.ct.io import load_ct_spec  # loads SciPy: imported where first needed (start-up)

        if cmd.entry is not None or cmd.current_entry is not None:
            raise AccuracyError("--entry and --current-entry name [[physics]] entries of --campaign; "
                                "with --ct both images are line DRRs")
        volume = load_ct_spec(cmd.ct)
        drr = DRRRenderer(volume, RenderSettings(size=tuple(size)), center_lps=anatomy_center(volume))
        return [(drr, drr)], ("line DRRs", "line DRRs"), None
    from dataclasses import replace

    campaign = load_campaign(cmd.campaign)
    campaign = replace(campaign, scene=replace(campaign.scene, size=tuple(size)))
    subjects = [s for s in campaign.subjects() if s.split == cmd.split]
    if not subjects:
        raise AccuracyError(f"{cmd.campaign} has no subject in split {cmd.split!r}")
    entries = {p.name: p for p in campaign.physics}
    for option, name in (("--entry", cmd.entry), ("--current-entry", cmd.current_entry)):
        if name is not None and name not in entries:
            raise AccuracyError(f"{option} {name!r} is not a [[physics]] entry of {cmd.campaign} "
                                f"(it has {list(entries)})")
    target = cmd.entry if cmd.entry is not None else campaign.physics[0].name
    current = cmd.current_entry if cmd.current_entry is not None else target
    contexts = [SubjectContext(campaign, s) for s in subjects]
    entry = entries[current]
    settings = entry.settings() if entry.level in ("poly", "full") else None
    return [(c.renderers[target], c.renderers[current]) for c in contexts], (target, current), settings


@dataclass(frozen=True)
class ModelsCommand:
    """Defaults of ``ctxreg models``."""

    name: str | None = field(default=None, metadata=opt(
        "a shipped model: print its whole card (JSON); without it, a short block per model", group="output",
        positional=True, nargs="?", metavar="NAME"))
    json: bool = field(default=False, metadata=opt("print every shipped model's whole card as one JSON object "
                                                   "(name -> card)", group="output"))


def run_models(cmd: ModelsCommand) -> list[Path]:
    """Print the shipped models (``models/<name>/``, each checked against its card)."""
    import json

    if cmd.name is not None:
        print(json.dumps(describe_model(cmd.name), indent=2))
    elif cmd.json:
        print(json.dumps({name: describe_model(name) for name in shipped_models()}, indent=2))
    else:
        print(describe_models())
    return []
