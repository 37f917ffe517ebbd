"""Shipped models: weights only, with a model card, under ``models/<name>/``.

A shipped model is a folder holding

* ``model.pt``: a :mod:`learn.checkpoint` file without training state (no optimiser, scheduler
  or random state: a few MB), read with ``weights_only=True`` like every checkpoint;
* ``model.toml``: its card, in one schema (:data:`CARD_SCHEMA`, checked by :func:`check_card`):

  - ``[model]``, what the model is: name, a one-phrase summary, the weights file and its sha256,
    backbone, head channels, image size (H, W) px, preprocessing, the physics entries of the
    training images and current images, the current images' field, the iterations;
  - ``[training]``, how it was trained: data, images, physics, randomization, initial weights,
    config, command, iterations, batch size, pairs seen, seed, duration (s) and machine;
  - ``[accuracy]``, how well the network does on its own (no global search, no refinement):
    ``protocol`` (what "on its own" means for this card), ``headline`` (the tables
    ``ctxreg models`` shows) and one table per measurement, ``[accuracy.<name>]`` with ``what``,
    ``command``, ``measured`` and the numbers (``success`` a fraction in [0, 1]; errors named
    with their unit, ``_deg`` or ``_mm``; counts ``cases``, ``frames`` or ``pairs``).

  Results of a whole pipeline (the network with the CMA-ES refinement or the global search) are
  not the network's and live in docs/results.md.

:func:`export_model` makes such a folder from a ``ctxreg train`` checkpoint; :func:`load_card`
reads a card and checks it against its schema and its weights (the file's hash and what the
checkpoint records); :func:`shipped_models` lists the folders of ``models/``;
:func:`describe_models` and :func:`describe_model` are what ``ctxreg models`` prints.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from learn.errors import CheckpointError
from sim.core.atomic import read_toml, sha256_file
from sim.core.atomic import write_toml

__all__ = ["MODELS_DIR", "DEFAULT_MODEL", "DEFAULT_ADAPT_BASE", "CARD_SCHEMA", "export_model", "load_card", "check_card",
           "shipped_models", "resolve_model", "describe_models", "describe_model", "ModelCardError"]

#: The repository's folder of shipped models.
MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
CARD = "model.toml"
WEIGHTS = "model.pt"
#: The shipped model the contextual methods use when no ``--model`` is given.
DEFAULT_MODEL = "pelvis_xray"
#: The shipped model ``ctxreg adapt`` starts from when no ``--from`` is given: the base made to be
#: adapted (the default network continued on pelves of varied shape; docs/training.md, "A base
#: network made to be adapted").
DEFAULT_ADAPT_BASE = "pelvis_base"


class ModelCardError(CheckpointError):
    """A model folder or its card cannot be used; the message names the file and the key."""


_STR, _INT, _NUM, _LIST, _DICT = str, int, (int, float), list, dict
#: The card's schema: section -> (required keys -> type, optional keys -> type). ``[accuracy]``'s
#: measurement tables are checked by :func:`_check_measurement`.
CARD_SCHEMA: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "model": ({"name": _STR, "summary": _STR, "file": _STR, "sha256": _STR, "backbone": _STR,
               "head_channels": _INT, "image_size": _LIST, "preprocess": _LIST, "physics": _DICT,
               "current_physics": _DICT, "current_field": _STR, "iterations": _INT}, {}),
    "training": ({"trained_on": _STR, "data": _STR, "images": _STR, "physics": _STR, "randomization": _STR,
                  "init_from": _STR, "config": _STR, "command": _STR, "iterations": _INT, "batch_size": _INT,
                  "pairs_seen": _INT, "seed": _INT, "duration_s": _NUM, "machine": _STR},
                 {"lr": _STR, "note": _STR, "resume_state": _STR}),
    "accuracy": ({"protocol": _STR, "headline": _LIST}, {}),
    # a model adapted to one CT (``ctxreg adapt``, :mod:`learn.adapt`); other models have none
    "adaptation": ({"base": _STR, "ct": _STR, "ct_hash": _STR, "pairs_seen": _INT, "minutes": _NUM,
                    "device": _STR, "curve": _LIST, "curve_columns": _LIST}, {"note": _STR}),
}
#: Sections a card may leave out.
OPTIONAL_SECTIONS = ("adaptation",)
#: Keys of a measurement table ``[accuracy.<name>]``: required text, and text it may hold.
_MEASUREMENT_TEXT = ("what", "command", "measured")
_MEASUREMENT_NOTES = ("success_definition", "compared_with", "note", "groups_unit")
_COUNTS = ("cases", "frames", "pairs")
_METRIC_SUFFIXES = ("_deg", "_mm", "_deg_mean", "_mm_mean", "_mm_median", "_deg_median")


def _typename(t) -> str:
    return " or ".join(x.__name__ for x in t) if isinstance(t, tuple) else t.__name__


def _check_measurement(where: str, table: Any) -> None:
    if not isinstance(table, dict):
        raise ModelCardError(f"{where}: must be a table (what, command, measured and the numbers)")
    for key in _MEASUREMENT_TEXT:
        if not isinstance(table.get(key), str) or not table[key]:
            raise ModelCardError(f"{where}.{key}: missing (a measurement states what, command and measured)")
    numbers = 0
    for key, value in table.items():
        if key in _MEASUREMENT_TEXT or key in _MEASUREMENT_NOTES:
            if not isinstance(value, str):
                raise ModelCardError(f"{where}.{key}: must be text")
        elif key in _COUNTS:
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ModelCardError(f"{where}.{key}: must be a count >= 1, got {value!r}")
        elif key == "success":
            if not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise ModelCardError(f"{where}.success: must be a fraction in [0, 1], got {value!r}")
            numbers += 1
        elif key == "groups":  # {group: [rotation deg, translation mm]}
            if not isinstance(value, dict) or not all(
                    isinstance(v, list) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v)
                    for v in value.values()):
                raise ModelCardError(f"{where}.groups: must map each group to [rotation deg, translation mm]")
        elif key.endswith(_METRIC_SUFFIXES):
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not value == value or value < 0:
                raise ModelCardError(f"{where}.{key}: must be a number >= 0, got {value!r}")
            numbers += 1
        else:
            raise ModelCardError(f"{where}.{key}: not a key of a measurement (text: {', '.join(_MEASUREMENT_TEXT)}, "
                                 f"{', '.join(_MEASUREMENT_NOTES)}; counts: {', '.join(_COUNTS)}; success; "
                                 f"errors ending {', '.join(_METRIC_SUFFIXES)}; groups)")
    if not numbers:
        raise ModelCardError(f"{where}: holds no measured number")


def check_card(card: Any, where: str = "model card") -> None:
    """Check a card (the parsed ``model.toml``) against :data:`CARD_SCHEMA`: every section and
    required key present with its type, no key the schema does not know, the summary free of
    issue numbers (it says what the model is), every ``[accuracy.<name>]`` a measurement and
    every ``headline`` entry one of them. Raises :class:`ModelCardError` naming the key."""
    if not isinstance(card, dict):
        raise ModelCardError(f"{where}: not a table")
    extra = set(card) - set(CARD_SCHEMA)
    if extra:
        raise ModelCardError(f"{where}: unknown section(s) {sorted(extra)} (a card has {list(CARD_SCHEMA)})")
    for section, (required, optional) in CARD_SCHEMA.items():
        table = card.get(section)
        if table is None and section in OPTIONAL_SECTIONS:
            continue
        if not isinstance(table, dict):
            raise ModelCardError(f"{where}: needs a [{section}] table")
        for key, kind in required.items():
            if key not in table:
                raise ModelCardError(f"{where}: {section}.{key} is missing")
        for key, value in table.items():
            kind = required.get(key, optional.get(key))
            if section == "accuracy" and kind is None:
                _check_measurement(f"{where}: accuracy.{key}", value)
                continue
            if kind is None:
                raise ModelCardError(f"{where}: {section}.{key} is not a key of the card's schema "
                                     f"({', '.join([*required, *optional])})")
            if not isinstance(value, kind) or isinstance(value, bool):
                raise ModelCardError(f"{where}: {section}.{key} must be {_typename(kind)}, got {value!r}")
    if "issue" in card["model"]["summary"].lower():
        raise ModelCardError(f"{where}: model.summary says what the model is, without issue numbers")
    for name in card["accuracy"]["headline"]:
        if not isinstance(card["accuracy"].get(name), dict):
            raise ModelCardError(f"{where}: accuracy.headline names {name!r}, which is not an [accuracy.{name}] table")


def export_model(checkpoint: str | Path, folder: str | Path, *, name: str, summary: str,
                 training: dict[str, Any], accuracy: dict[str, Any], adaptation: dict[str, Any] | None = None) -> Path:
    """Write ``folder/model.pt`` (the checkpoint's weights and what they need: architecture,
    image size, preprocessing, physics, config) and ``folder/model.toml`` (the card); returns the
    card's path. ``training``, ``accuracy`` and (a model adapted to one CT) ``adaptation`` are
    the card's tables in :data:`CARD_SCHEMA` (checked before anything is written)."""
    from learn.checkpoint import load_checkpoint, save_checkpoint  # torch: only where weights are read or written

    ckpt = load_checkpoint(checkpoint)
    model = {"name": name, "summary": summary, "file": WEIGHTS, "sha256": "", "backbone": ckpt.backbone,
             "head_channels": ckpt.head_channels, "image_size": list(ckpt.image_size) if ckpt.image_size else [],
             "preprocess": list(ckpt.preprocess), "physics": ckpt.physics or {},
             "current_physics": ckpt.current_physics or {},
             "current_field": (ckpt.config or {}).get("current_field", "masked"), "iterations": ckpt.iteration}
    card = {"model": model, "training": training, "accuracy": accuracy}
    if adaptation is not None:
        card["adaptation"] = adaptation
    check_card(card, f"the card of {name}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    weights = folder / WEIGHTS
    save_checkpoint(weights, replace(ckpt, optimizer=None, scheduler=None, rng=None, path=None))
    model["sha256"] = sha256_file(weights)
    write_toml(folder / CARD, card)
    return folder / CARD


def load_card(folder: str | Path, *, read_weights: bool = True) -> dict[str, Any]:
    """The card of the model in ``folder``, checked against its schema (:func:`check_card`) and its
    weights: the file exists, its sha256 matches, and (``read_weights``) the architecture, image
    size and preprocessing the card states are those the checkpoint records. Listing the cards
    (``ctxreg models``) passes ``read_weights=False``: the sha256 still ties the card to its
    weights, and torch is not imported. Raises :class:`ModelCardError` naming the file and the
    key."""
    folder = Path(folder)
    path = folder / CARD
    if not path.is_file():
        raise ModelCardError(f"{folder}: no {CARD} (a shipped model is a folder with {WEIGHTS} and {CARD})")
    card = read_toml(path, ModelCardError, "model card")
    check_card(card, str(path))
    model = card["model"]
    weights = folder / model["file"]
    if not weights.is_file():
        raise ModelCardError(f"{path}: model.file {model['file']!r} not found in {folder}")
    if sha256_file(weights) != model.get("sha256"):
        raise ModelCardError(f"{path}: model.sha256 does not match {weights} (the weights changed after the card)")
    if not read_weights:
        return card
    from learn.checkpoint import load_checkpoint  # torch: only where weights are read

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


def resolve_model(value: str | Path | None = None, root: str | Path = MODELS_DIR, *, flag: str = "--model") -> Path:
    """The checkpoint file of ``--model VALUE`` (``flag``: the option a refusal names): an existing file as it is (a model folder's
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
        raise ModelCardError(f"no {flag} given and the default model {DEFAULT_MODEL!r} is not in {root} "
                             f"(shipped: {names})")
    raise ModelCardError(f"{flag} {name}: neither a checkpoint file nor a shipped model (shipped: {names}; "
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


def _headline(table: dict[str, Any]) -> str:
    """One measurement in a phrase: ``what: S % with <success definition>, R deg / T mm mean``."""
    parts = []
    if "success" in table:
        parts.append(f"{100 * table['success']:.0f} % with {table.get('success_definition', 'success')}")
    rot, trans = table.get("rotation_deg_mean"), table.get("translation_mm_mean")
    if rot is not None and trans is not None:
        parts.append(f"{rot:.2f} deg / {trans:.1f} mm mean")
    return f"{table['what']}: {', '.join(parts) or 'see the card'}"


def describe_models(root: str | Path = MODELS_DIR, width: int = 100) -> str:
    """The shipped models as ``ctxreg models`` prints them, a short block each, lines at most
    ``width`` characters: name (and whether it is the default, or ``ctxreg adapt``'s), image size, preprocessing and
    backbone, what it was trained on in a phrase, and the network's own headline accuracy."""
    import textwrap

    blocks = []
    for name, folder in shipped_models(root).items():
        card = load_card(folder, read_weights=False)
        m, t, acc = card["model"], card["training"], card["accuracy"]
        size = " x ".join(str(v) for v in m["image_size"])
        pre = ", ".join(p if isinstance(p, str) else str(p.get("name")) for p in m["preprocess"]) or "none"
        role = {DEFAULT_MODEL: "  (default)", DEFAULT_ADAPT_BASE: "  (ctxreg adapt's default base)"}.get(name, "")
        lines = [f"{name}{role}: {m['summary']}",
                 f"image {size} px, preprocessing {pre}, backbone {m['backbone']}",
                 f"trained on {t['trained_on']}"]
        lines += [f"alone: {_headline(acc[h])}" for h in acc["headline"]]
        wrapped = [textwrap.fill(line, width, initial_indent="  " if k else "", subsequent_indent="      ")
                   for k, line in enumerate(lines)]
        blocks.append("\n".join(wrapped))
    if not blocks:
        return f"no shipped models in {root}"
    note = (f"'alone': the network on its own (no global search, no refinement). The whole card: ctxreg models "
            f"NAME (--json: every card). Folder: {root}")
    return "\n\n".join(blocks) + "\n\n" + textwrap.fill(note, width)


def describe_model(name: str, root: str | Path = MODELS_DIR) -> dict[str, Any]:
    """The whole card of shipped model ``name`` (checked against its weights' sha256,
    :func:`load_card`, without reading them). Raises
    :class:`ModelCardError` naming the shipped models when ``name`` is not one."""
    shipped = shipped_models(root)
    if name not in shipped:
        raise ModelCardError(f"no shipped model {name!r} (shipped: {', '.join(shipped) or 'none'})")
    return load_card(shipped[name], read_weights=False)
