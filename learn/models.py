"""Shipped models: weights only, with a model card, under ``models/<name>/``.

A shipped model is a folder holding

* ``model.pt``: a :mod:`learn.checkpoint` file without training state (no optimiser, scheduler
  or random state: a few MB), read with ``weights_only=True`` like every checkpoint;
* ``model.toml``: its card: ``[model]`` (name, description, file, sha256 of ``model.pt``,
  backbone, head channels, image size (H, W) px, preprocessing, the physics entries of the
  training images), ``[training]`` (the config, the command, the campaign, the iterations, the
  duration and machine) and ``[accuracy]`` (what was measured, with the command that reproduces it).

:func:`export_model` makes such a folder from a ``ctxreg train`` checkpoint; :func:`load_card`
reads a card and checks it against its weights (the file's hash and what the checkpoint records);
:func:`shipped_models` lists the folders of ``models/``.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from learn.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from sim.atomic import read_toml, sha256_file

__all__ = ["MODELS_DIR", "DEFAULT_MODEL", "export_model", "load_card", "shipped_models", "resolve_model",
           "describe_models", "ModelCardError"]

#: The repository's folder of shipped models.
MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
CARD = "model.toml"
WEIGHTS = "model.pt"
#: The shipped model the contextual methods use when no ``--model`` is given.
DEFAULT_MODEL = "pelvis_line"


class ModelCardError(CheckpointError):
    """A model folder or its card cannot be used; the message names the file and the key."""


def export_model(checkpoint: str | Path, folder: str | Path, *, name: str, description: str,
                 training: dict[str, Any], accuracy: dict[str, Any]) -> Path:
    """Write ``folder/model.pt`` (the checkpoint's weights and what they need: architecture,
    image size, preprocessing, physics, config) and ``folder/model.toml`` (the card); returns the
    card's path. ``training`` and ``accuracy`` are the card's tables (plain data: the command,
    campaign, duration, what was measured and how)."""
    from sim.atomic import write_toml

    ckpt = load_checkpoint(checkpoint)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    weights = folder / WEIGHTS
    save_checkpoint(weights, replace(ckpt, optimizer=None, scheduler=None, rng=None, path=None))
    card = {
        "model": {"name": name, "description": description, "file": WEIGHTS, "sha256": sha256_file(weights),
                  "backbone": ckpt.backbone, "head_channels": ckpt.head_channels,
                  "image_size": list(ckpt.image_size) if ckpt.image_size else None,
                  "preprocess": list(ckpt.preprocess), "physics": ckpt.physics,
                  "current_physics": ckpt.current_physics,
                  "current_field": (ckpt.config or {}).get("current_field", "masked"), "iterations": ckpt.iteration},
        "training": training,
        "accuracy": accuracy,
    }
    write_toml(folder / CARD, card)
    return folder / CARD


def load_card(folder: str | Path) -> dict[str, Any]:
    """The card of the model in ``folder``, checked against its weights: the file exists, its
    sha256 matches, and the architecture, image size and preprocessing the card states are those
    the checkpoint records. Raises :class:`ModelCardError` naming the file and the key."""
    folder = Path(folder)
    path = folder / CARD
    if not path.is_file():
        raise ModelCardError(f"{folder}: no {CARD} (a shipped model is a folder with {WEIGHTS} and {CARD})")
    card = read_toml(path, ModelCardError, "model card")
    model = card.get("model")
    if not isinstance(model, dict) or not isinstance(model.get("file"), str):
        raise ModelCardError(f"{path}: needs a [model] table with file, sha256, backbone, image_size, preprocess")
    weights = folder / model["file"]
    if not weights.is_file():
        raise ModelCardError(f"{path}: model.file {model['file']!r} not found in {folder}")
    if sha256_file(weights) != model.get("sha256"):
        raise ModelCardError(f"{path}: model.sha256 does not match {weights} (the weights changed after the card)")
    ckpt = load_checkpoint(weights)
    recorded = {"backbone": ckpt.backbone, "head_channels": ckpt.head_channels,
                "image_size": list(ckpt.image_size) if ckpt.image_size else None,
                "preprocess": list(ckpt.preprocess)}
    for key, value in recorded.items():
        if model.get(key) != value:
            raise ModelCardError(f"{path}: model.{key} is {model.get(key)!r} but {weights} records {value!r}")
    return card


def shipped_models(root: str | Path = MODELS_DIR) -> dict[str, Path]:
    """``{name: folder}`` of the model folders (with a card) under ``root``."""
    root = Path(root)
    return {p.parent.name: p.parent for p in sorted(root.glob(f"*/{CARD}"))} if root.is_dir() else {}


def resolve_model(value: str | Path | None = None, root: str | Path = MODELS_DIR) -> Path:
    """The checkpoint file of ``--model VALUE``: an existing file as it is (a model folder's
    weights file after its card is checked against it), a model folder (its weights, card checked;
    or a ``ctxreg train`` output folder's ``checkpoint.pt``), or the name of a shipped model (its
    ``model.pt``, after its card is checked against it, :func:`load_card`);
    None: the default shipped model (:data:`DEFAULT_MODEL`). Raises :class:`ModelCardError`
    naming the value and the shipped names otherwise."""
    shipped = shipped_models(root)
    name = DEFAULT_MODEL if value is None else str(value)
    if value is not None and Path(name).is_dir():
        return _model_in_folder(Path(name))
    if value is not None and Path(name).is_file() and (Path(name).parent / CARD).is_file():
        return _checked_against_card(Path(name))
    if value is not None and (Path(name).is_file() or name not in shipped and ("/" in name or "\\" in name
                                                                             or name.endswith(".pt"))):
        return Path(name)  # a path: load_checkpoint names a missing or damaged file
    if name in shipped:
        card = load_card(shipped[name])
        return shipped[name] / card["model"]["file"]
    names = ", ".join(shipped) or "none"
    if value is None:
        raise ModelCardError(f"no --model given and the default model {DEFAULT_MODEL!r} is not in {root} "
                             f"(shipped: {names})")
    raise ModelCardError(f"--model {name}: neither a checkpoint file nor a shipped model (shipped: {names}; "
                         f"`ctxreg models` lists them)")


def _model_in_folder(folder: Path) -> Path:
    """``--model FOLDER``: a model folder's weights (its card checked, :func:`load_card`), or a
    ``ctxreg train`` output folder's ``checkpoint.pt``."""
    if (folder / CARD).is_file():
        return folder / load_card(folder)["model"]["file"]
    if (folder / "checkpoint.pt").is_file():
        return folder / "checkpoint.pt"
    raise ModelCardError(f"--model {folder}: a folder without {CARD} (a model folder, `ctxreg models`) or "
                         f"checkpoint.pt (a ctxreg train output folder)")


def _checked_against_card(path: Path) -> Path:
    """``--model .../model.pt`` inside a model folder: the file its card names is checked against
    the card (sha256, architecture, :func:`load_card`) as the folder or the name would be; another
    file of that folder is taken as it is."""
    card = load_card(path.parent) if path.name == _card_file(path.parent) else None
    return path if card is None else path.parent / card["model"]["file"]


def _card_file(folder: Path) -> str | None:
    """The weights file the card of ``folder`` names (None where the card does not say)."""
    try:
        model = read_toml(folder / CARD, ModelCardError, "model card").get("model")
    except ModelCardError:
        return WEIGHTS  # a damaged card: load_card names it
    return model.get("file") if isinstance(model, dict) and isinstance(model.get("file"), str) else WEIGHTS


def describe_models(root: str | Path = MODELS_DIR) -> str:
    """A table of the shipped models for ``ctxreg models``: name (``*`` the default), image size,
    preprocessing, training images, measured accuracy and description."""
    rows = ["| model | image (H x W px) | preprocess | trained on | accuracy | description |",
            "|---|---|---|---|---|---|"]
    for name, folder in shipped_models(root).items():
        card = load_card(folder)
        m, acc = card["model"], card.get("accuracy", {})
        trained = card.get("training", {}).get("images") or (m.get("physics") or {}).get("name", "?")
        summary = "; ".join(f"{k} = {v:g}" if isinstance(v, float) else f"{k} = {v}"
                            for k, v in acc.items() if k.endswith("success"))
        size = " x ".join(str(v) for v in m.get("image_size") or ["?"])
        pre = " ".join(p if isinstance(p, str) else str(p.get("name")) for p in m.get("preprocess", []))
        rows.append(f"| {name}{' *' if name == DEFAULT_MODEL else ''} | {size} | {pre} | {trained} | "
                    f"{summary or '-'} | {m.get('description', '')} |")
    if len(rows) == 2:
        return f"no shipped models in {root}"
    return "\n".join(rows) + f"\n\n* the default of --model (the contextual methods); models folder: {root}"
