"""``ctxreg adapt``: a network fine-tuned to one CT in minutes, for a patient it has never seen.

Every user registers X-rays to their own CT. The shipped network learnt one pelvis; on another
person's it is lost. :func:`adapt` continues a base network (``--from``, default the shipped
base made to be adapted, ``pelvis_base``) on realistic randomized pairs of the user's CT: the batched pairs
(:class:`learn.batched.BatchedPairs`) with the randomization the base model recorded (tube,
filtration, dose, scatter, collimators, display chains, tools: all of it), rendered from the CT
and from virtual patients of it (:mod:`sim.ct.patients`: shape and intensity variation around this
anatomy), for the time given. It validates, as it goes, on poses of this CT that training never
draws (the CT itself as the ``val`` subject, its own seed), and prints the error as it falls.

The output folder holds

* ``campaign.toml``: the subjects (the CT and its virtual patients) and the scene, and
  ``heldout_poses_<CT>``: a link to the CT, its validation subject;
* ``run/``: the ``ctxreg train`` run (``checkpoint.pt`` with the optimiser, ``log.csv``,
  ``loss.png``): Ctrl-C or SIGTERM stops with a checkpoint, ``--resume`` continues it;
* ``model.pt`` and ``model.toml``: the adapted model, a model folder like the shipped ones
  (``ctxreg register --model DIR``), its card recording the base model, the CT's content hash,
  the pairs seen, the minutes and device, and the validation curve (``[adaptation]``);
* ``adapt.json``: the same record as JSON, and ``curve.png``: the validation curve (rotation
  and translation error of single predictions against minutes).

``ctxreg register --model DIR`` with a CT other than the one adapted to prints a one-line
warning naming both (:func:`adapted_ct_warning`).

Example (about 10 minutes on 2 CPU cores)::

    ctxreg adapt --ct patient.nii.gz --out models_local/patient --minutes 10
    ctxreg register --ct patient.nii.gz --xray frame.dcm --model models_local/patient --out out/reg
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.core.errors import InputError
from learn.shipped import DEFAULT_ADAPT_BASE, ModelCardError, export_model, resolve_model
from sim.core.atomic import atomic_path, folder_lock, read_toml, save_figure, write_json
from sim.core.outputs import check_output_dir
from sim.projection.scene import DEFAULT_SCENE

__all__ = ["AdaptSettings", "ADAPT", "AdaptError", "adapt", "adapted_ct_warning", "ADAPT_FILES"]


class AdaptError(InputError):
    """``ctxreg adapt`` cannot start or continue; the message names the input and the problem."""


@dataclass(frozen=True)
class AdaptSettings:
    """How an adaptation trains (every value a default of :func:`adapt`).

    Attributes:
        virtual_patients: virtual patients of the CT in the training subjects (besides the CT).
        batch_size: pairs per step. xvr adapts with 116 DRRs a step; 32 keeps a step near a
            second on 2 CPU cores, so the validation curve has points within minutes.
        lr: Adam's peak learning rate, chosen on the built-in phantom (seed 5; never the
            validation pelvis) among 1e-4, 3e-4, 1e-3 and 3e-3 for 10 minutes on 2 cores
            (docs/training.md, "Adapting to one CT").
        lr_schedule / lr_warmup: the rate's schedule over the minutes given
            (:class:`learn.train.TrainConfig`): ``"cosine"`` warms up linearly over the first
            ``lr_warmup`` of the time, then falls as a half cosine to 0 when the time is up, so
            the last minutes average out the noise of single batches; ``"step"`` is a constant
            ``lr``. A ``--resume`` with more minutes stretches the cosine to the new end.
        val_pairs: held-out validation pairs (poses of the CT itself, never trained on).
        val_every: steps between validations (and checkpoints).
        near_fraction: the share of near pairs (the base models' 0.5).
        train_backbone_from / backbone_lr_scale: for a base whose backbone is frozen (an ImageNet
            one, trained in its heads only): the stage from which on its weights train in the
            adaptation too, at that share of the rate (:class:`learn.train.TrainConfig`); None:
            the heads only. A base that trained its whole backbone adapts it whole.
        seed: every random draw.
    """

    virtual_patients: int = 8
    batch_size: int = 32
    lr: float = 1e-3
    lr_schedule: str = "cosine"
    lr_warmup: float = 0.05
    val_pairs: int = 128
    val_every: int = 40
    near_fraction: float = 0.5
    train_backbone_from: str | None = None
    backbone_lr_scale: float = 0.1
    seed: int = 11


#: The defaults of ``ctxreg adapt``.
ADAPT = AdaptSettings()

#: What ``ctxreg adapt`` writes into ``--out`` (besides ``run/``).
ADAPT_FILES = ("campaign.toml", "model.pt", "model.toml", "adapt.json", "curve.png")
#: Iterations a run is declared for: a time budget ends it first.
_OPEN_ENDED = 10_000_000


def _campaign_text(ct: Path, val_link: Path, size, settings: AdaptSettings, scene: str) -> str:
    return f"""# ctxreg adapt: the subjects of one CT's adaptation (learn/adapt.py). The CT and its virtual
# patients train; the CT itself, at poses of its own seed, validates.
[campaign]
name = "adapt"
seed = {settings.seed}
images_per_ct = 256
shard_size = 256

[scene]
name = "{scene}"
size = [{int(size[0])}, {int(size[1])}]

[[physics]]
name = "line"
level = "line"
ray_model = "siddon"

[[cts]]
path = {json.dumps(str(ct))}
split = "train"
virtual_patients = {int(settings.virtual_patients)}

[[cts]]  # the same CT under a link of its own name (a campaign lists each path once)
path = {json.dumps(str(val_link))}
split = "val"
"""


def _train_config(out: Path, base_path: Path, base, settings: AdaptSettings):
    from learn.train import TrainConfig  # loads torch: imported where first needed (start-up)

    physics = base.physics or {}
    if physics.get("level") != "randomized" or not isinstance(physics.get("randomize"), dict):
        raise AdaptError(f"--from {base_path}: the base network was not trained on randomized realistic pairs "
                         f"(its physics is {physics.get('name', 'not recorded')!r}); adapt a realistic model such as "
                         "the default")
    config = base.config or {}
    frozen = bool(config.get("freeze_backbone", False))
    return TrainConfig(
        dataset=str(out / "campaign.toml"), out=str(out / "run"), init_from=str(base_path),
        backbone=base.backbone, head_channels=int(base.head_channels), preprocess=tuple(base.preprocess),
        freeze_backbone=frozen,  # a frozen (ImageNet) backbone stays frozen, but for the stages trained
        train_backbone_from=settings.train_backbone_from if frozen else None,
        backbone_lr_scale=settings.backbone_lr_scale,
        pairs="batched", randomize=physics["randomize"], current_field=config.get("current_field", "masked"),
        framing=config.get("framing", "field"), batch_size=settings.batch_size, iterations=_OPEN_ENDED,
        lr=settings.lr, lr_step=_OPEN_ENDED, lr_decay=1.0, lr_schedule=settings.lr_schedule,
        lr_warmup=settings.lr_warmup if settings.lr_schedule == "cosine" else 0.0, val_pairs=settings.val_pairs,
        val_every=settings.val_every, checkpoint_every=settings.val_every, near_fraction=settings.near_fraction,
        loss="relative", relative_eps=float(config.get("relative_eps", 0.1)), seed=settings.seed,
        precision="auto")


#: The columns of the card's validation curve.
CURVE_COLUMNS = ["minutes", "pairs", "rotation_deg", "translation_mm"]


def _curve(log_csv: Path, batch_size: int, before: dict | None) -> list[list[float]]:
    """``[[minutes, pairs, rotation deg, translation mm], ...]``: the base network's validation
    (0 minutes) and the run's (``log.csv``'s ``elapsed_s``)."""
    out = [[0.0, 0, round(before["rotation_deg"], 3), round(before["translation_mm"], 2)]] if before else []
    if log_csv.is_file():
        with open(log_csv) as f:
            for r in csv.DictReader(f):
                if r.get("val_rot_err_deg") and r.get("elapsed_s"):
                    out.append([round(float(r["elapsed_s"]) / 60.0, 2), int(r["iteration"]) * batch_size,
                                round(float(r["val_rot_err_deg"]), 3), round(float(r["val_trans_err_mm"]), 2)])
    return out


def adapt(ct: str | os.PathLike, out: str | os.PathLike, *, minutes: float = 10.0, base: str | None = None,
          device: str = "auto", resume: bool = False, settings: AdaptSettings = ADAPT, log=print) -> Path:
    """Fine-tune ``base`` to ``ct`` for ``minutes`` of training; returns the model folder ``out``.

    Args:
        ct: the CT (NIfTI file or DICOM folder), or ``phantom[:SEED]``: the built-in phantom,
            written as ``out/phantom_SEED.nii.gz`` and adapted to as a file.
        out: the output folder (module doc); an existing adaptation there is refused unless
            ``resume``.
        minutes: training time (min, > 0); with ``resume``, more minutes on top of what the run
            has done.
        base: the network to start from: a shipped model's name, a model folder or a checkpoint
            (default: :data:`learn.shipped.DEFAULT_ADAPT_BASE`, the shipped base made to be adapted).
        device: ``auto`` (a CUDA GPU when torch sees one), ``cpu`` or ``cuda``.
        resume: continue the run in ``out/run`` (its checkpoint, optimiser and random state).
        settings: :class:`AdaptSettings`.

    Raises :class:`AdaptError` (and the CT's, model's and config's own errors) naming the problem,
    before any training.
    """
    from learn.checkpoint import load_checkpoint  # loads torch: imported where first needed (start-up)
    from learn.train import resolve_device, train  # loads torch: imported where first needed (start-up)
    from sim.ct.cache import ct_hash  # loads SciPy: imported where first needed (start-up)
    from sim.ct.io import is_phantom_spec, load_ct  # loads SciPy: imported where first needed (start-up)
    from sim.ct.phantom import write_phantom_nifti  # loads SciPy: imported where first needed (start-up)

    if not (isinstance(minutes, (int, float)) and not isinstance(minutes, bool) and math.isfinite(minutes)
            and minutes > 0):
        raise AdaptError(f"--minutes must be a positive number of minutes, got {minutes!r}")
    out = check_output_dir(Path(out).expanduser().resolve(), ADAPT_FILES, flag="--out")
    if is_phantom_spec(str(ct)):  # the built-in phantom: adapted as a NIfTI file of it in --out
        seed_text = str(ct).partition(":")[2] or "0"
        if not seed_text.isdigit():
            raise AdaptError(f"--ct {ct}: the phantom seed must be a whole number")
        written = out / f"phantom_{int(seed_text)}.nii.gz"
        if not written.is_file():
            out.mkdir(parents=True, exist_ok=True)
            write_phantom_nifti(written, int(seed_text))
            log(f"adapt: the built-in phantom {ct} written to {written}")
        ct = written
    ct = Path(ct).expanduser().resolve()
    run = out / "run"
    load_ct(ct)  # a missing or damaged CT is refused here, before any work
    dev = resolve_device(device)
    record_path = out / "adapt.json"
    if resume:
        if not (run / "checkpoint.pt").is_file() or not record_path.is_file():
            raise AdaptError(f"--resume: {out} holds no adaptation to continue (run/checkpoint.pt and adapt.json); "
                             "run without --resume to start one")
        try:
            record = json.loads(record_path.read_text())
            base_path = Path(record["base_checkpoint"])
            if record["ct_hash"] != ct_hash(ct):
                raise AdaptError(f"--resume: {out} adapts {record['ct']} (content hash {record['ct_hash'][:12]}), "
                                 f"not {ct}; give that CT or another --out")
        except (json.JSONDecodeError, KeyError, TypeError) as e:
            raise AdaptError(f"--resume: {record_path} is damaged ({type(e).__name__}: {e}); start again in another "
                             "--out") from None
    else:
        if (run / "checkpoint.pt").exists() or record_path.exists():
            raise AdaptError(f"--out {out} already holds an adaptation: --resume continues it, or give another --out")
        base = DEFAULT_ADAPT_BASE if base is None else base
        base_path = resolve_model(base, flag="--from").resolve()
        record = {"ct": str(ct), "ct_hash": ct_hash(ct), "base": base,
                  "base_checkpoint": str(base_path), "sessions": [], "before": None}
    base_ckpt = load_checkpoint(base_path)
    if base_ckpt.image_size is None:
        raise AdaptError(f"--from {base_path}: the checkpoint does not record its image size")
    out.mkdir(parents=True, exist_ok=True)
    with folder_lock(out, "ctxreg adapt"):  # one run per folder at a time: a second is refused at once

        val_link = out / f"heldout_poses_{ct.name}"
        if val_link.is_symlink() or val_link.exists():
            val_link.unlink()
        try:
            val_link.symlink_to(ct, target_is_directory=ct.is_dir())
        except OSError as e:
            raise AdaptError(f"--out {out}: cannot link the validation CT there ({e.strerror or e})") from None
        with atomic_path(out / "campaign.toml") as tmp:
            tmp.write_text(_campaign_text(ct, val_link, base_ckpt.image_size, settings, DEFAULT_SCENE))
        cfg = _train_config(out, base_path, base_ckpt, settings)
        from learn.train import validate_checkpoint  # loads torch: imported where first needed (start-up)

        if record.get("before") is None:  # the base network on this CT's held-out poses: the curve's start
            log(f"adapt: the base network {record['base']} on {settings.val_pairs} held-out poses of {ct.name} ...")
            row = validate_checkpoint(cfg, base_path, device=str(dev), log=lambda line: log(f"adapt: {line}"))
            record["before"] = {"rotation_deg": float(row["val_rot_err_deg"]), "translation_mm": float(row["val_trans_err_mm"])}
            log(f"adapt: before adaptation: rotation {row['val_rot_err_deg']:.2f} deg, translation "
                f"{row['val_trans_err_mm']:.1f} mm (single predictions)")
            write_json(record_path, record)
        started = time.perf_counter()
        when = time.strftime("%Y-%m-%d %H:%M", time.localtime())
        log(f"adapt: {ct.name} from {record['base']} for {minutes:g} min on {dev} (Ctrl-C or SIGTERM stops with a "
            "checkpoint; --resume continues)")
        last = train(cfg, resume=resume, device=str(dev), stop_after_s=60.0 * minutes, log=log)
        spent = (time.perf_counter() - started) / 60.0
        record["sessions"].append({"started": when, "minutes": round(spent, 2), "device": _device_name(dev),
                                   "iteration": int(last.get("iteration", 0))})
        write_json(record_path, record)
        return _export(out, record, settings, log)


def _device_name(dev) -> str:
    import torch

    if dev.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(dev)})"
    return f"cpu ({os.cpu_count()} cores)"


def _export(out: Path, record: dict, settings: AdaptSettings, log) -> Path:
    """The adapted model folder: ``model.pt`` and its card, from the run's checkpoint."""
    from learn.checkpoint import load_checkpoint  # loads torch: imported where first needed (start-up)

    ckpt_path = out / "run" / "checkpoint.pt"
    ckpt = load_checkpoint(ckpt_path)
    iterations = int(ckpt.iteration or 0)
    pairs = iterations * settings.batch_size
    minutes = sum(s["minutes"] for s in record["sessions"])
    devices = sorted({s["device"] for s in record["sessions"]})
    curve = _curve(out / "run" / "log.csv", settings.batch_size, record.get("before"))
    last = curve[-1] if curve else None
    ct_name = Path(record["ct"]).name
    name = "adapted_" + "".join(c if c.isalnum() else "_" for c in ct_name.split(".")[0])
    training = {
        "trained_on": f"{pairs} batched realistic pairs of {ct_name} and {settings.virtual_patients} virtual patients of it",
        "data": f"{out / 'campaign.toml'}: the CT and its virtual patients train; the CT itself, at poses of its own "
                "seed, validates",
        "images": "batched realistic pairs (learn/batched.py) with the base model's randomization, line-DRR currents",
        "physics": "two-basis polychromatic targets, as the base model's training",
        "randomization": "the base model's recorded randomization (its card's model.physics.randomize)",
        "init_from": f"{record['base']} ({record['base_checkpoint']})",
        "config": str(out / "run"),
        "command": f"ctxreg adapt --ct {record['ct']} --out {out}",
        "iterations": iterations, "batch_size": settings.batch_size, "pairs_seen": pairs, "seed": settings.seed,
        "duration_s": round(60.0 * minutes, 1), "machine": ", ".join(devices), "lr": (f"{settings.lr:g}, a linear warm-up over {settings.lr_warmup:.0%} of the minutes, then a half "
                                    "cosine to 0 at their end" if settings.lr_schedule == "cosine"
                                    else f"{settings.lr:g}, constant")}
    accuracy = {"protocol": "the network alone: single predictions on held-out poses of the adapted CT (realistic "
                            "randomized targets), no iteration, no search, no refinement",
                "headline": ["held_out_poses"]}
    if last is not None:
        accuracy["held_out_poses"] = {
            "what": f"single predictions on {settings.val_pairs} realistic pairs of held-out poses of {ct_name}",
            "command": f"ctxreg adapt --ct {record['ct']} --out {out} (run/log.csv, the last validation)",
            "measured": time.strftime("%Y-%m-%d %H:%M", time.localtime()), "pairs": settings.val_pairs,
            "rotation_deg_mean": float(last[2]), "translation_mm_mean": float(last[3]),
            "compared_with": (f"the base network on the same pairs: {record['before']['rotation_deg']:.2f} deg / "
                              f"{record['before']['translation_mm']:.1f} mm" if record.get("before") else "")}
    adaptation = {"base": record["base"], "ct": record["ct"], "ct_hash": record["ct_hash"], "pairs_seen": pairs,
                  "minutes": round(minutes, 2), "device": ", ".join(devices), "curve": curve,
                  "curve_columns": CURVE_COLUMNS}
    try:
        _plot_curve(curve, out / "curve.png", ct_name, record["base"])
    except ImportError as e:  # a bare GPU machine: the card and adapt.json hold the curve
        log(f"adapt: curve.png not written ({e})")
    card = export_model(ckpt_path, out, name=name,
                        summary=f"The base network {record['base']} adapted to the CT {ct_name}",
                        training=training, accuracy=accuracy, adaptation=adaptation)
    log(f"adapt: wrote {card.parent} ({pairs} pairs in {minutes:.1f} min; held-out poses "
        + (f"{curve[0][2]:.2f} deg / {curve[0][3]:.1f} mm -> {last[2]:.2f} deg / {last[3]:.1f} mm" if last else "n/a")
        + "); use it with ctxreg register --model " + str(card.parent))
    return out


def _plot_curve(curve: list[list[float]], path: Path, ct_name: str, base: str) -> None:
    """The validation curve: rotation (deg) and translation (mm) error against minutes."""
    if not curve:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = np.asarray(curve, float)
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    for a, col, unit in ((ax[0], 2, "rotation error (deg)"), (ax[1], 3, "translation error (mm)")):
        a.plot(c[:, 0], c[:, col], "o-", ms=2)
        a.set_xlabel("minutes of adaptation")
        a.set_ylabel(unit)
        a.set_ylim(bottom=0)
        a.grid(alpha=0.3)
    fig.suptitle(f"{base} adapted to {ct_name}: single predictions on held-out poses", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)


def adapted_ct_warning(model: str | os.PathLike | None, ct: str | os.PathLike) -> str | None:
    """One line when ``model`` is a folder adapted to another CT than ``ct`` (by content hash),
    naming both; None otherwise (a shipped model, the same CT, a CT given as an array)."""
    if model is None:
        return None
    folder = Path(model)
    folder = folder.parent if folder.is_file() else folder
    card_path = folder / "model.toml"
    if not card_path.is_file() or not isinstance(ct, (str, os.PathLike)) or not Path(ct).exists():
        return None
    from sim.ct.cache import ct_hash  # loads SciPy: imported where first needed (start-up)

    try:
        adaptation = read_toml(card_path, ModelCardError, "model card").get("adaptation")
    except ModelCardError:
        return None  # the card's own check names its problem
    if not isinstance(adaptation, dict) or not isinstance(adaptation.get("ct_hash"), str):
        return None
    if adaptation["ct_hash"] == ct_hash(ct):
        return None
    return (f"warning: the model {folder} was adapted to the CT {adaptation.get('ct')} "
            f"(content hash {adaptation['ct_hash'][:12]}), not to {ct}: its accuracy here is not that of its card; "
            f"adapt one to this CT (ctxreg adapt --ct {ct})")
