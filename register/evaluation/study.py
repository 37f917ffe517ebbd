"""``ctxreg study STUDY.toml``: train network variants and evaluate each on several target domains.

The domain-gap study of issue 15: for each **variant** (a training domain x a preprocessing, as a
``[train]`` table of :class:`learn.train.TrainConfig`), train or fine-tune the network, then
register every **target domain** with the variant's network and score it, and write a table of
variants x domains, a plot and the commands that reproduce it. A study file::

    [study]
    ct = "../shared/data/ct/pelvis_abdomen_3mm.nii.gz"   # the evaluation CT ("phantom" works)
    cases = 20                 # target poses per domain (the evaluation protocol's, seeded; a
                               # [[target]] may set its own cases)
    start = "ap"               # or "local"
    seed = 0
    methods = ["contextual", "contextual+cmaes"]
    size = [128, 128]          # the registration image (H, W), px

    [[variant]]
    name = "base"              # an existing network, evaluated as it is
    model = "pelvis_line"      # a shipped model's name (ctxreg models), or a checkpoint file

    [[variant]]
    name = "line-normalize"
    [variant.train]            # a [train] table; `out` is set by the study
    dataset = "../campaigns/pelvis_vp.toml"
    preprocess = ["normalize"]
    iterations = 2000

    [[target]]
    name = "line"              # line-integral DRRs (physics = { level = "line" })
    [[target]]
    name = "full-70kV-fluoro"
    kind = "xray"              # a realistic frame registered as a user would (register_xray)
    physics = { level = "full", kvp = 70, mas = 1.0, grid_ratio = 0 }
    collimator = { shape = "circle", radius = 0.45, transmission = 0.02 }
    display = { log = true, polarity = "bone-dark", gamma = 0.7, bits = 12, shutter = "black" }
    tools = [2, 5]             # optional (xray only): 2 to 5 metal tools fixed to the patient

Target kinds:

* ``"drr"`` (default): targets rendered with ``physics`` (a :class:`sim.physics.imaging.PhysicsSettings`
  table; ``-log(I/I0)`` for poly / full) and registered directly
  (:func:`register.evaluation.evaluate.evaluate`), as ``ctxreg evaluate`` does;
* ``"xray"``: full-physics detector signal, then a :class:`sim.physics.display.Collimator` and a
  :class:`sim.physics.display.DisplayChain`, written as 12-bit DICOM with geometry tags and
  registered through :func:`register.api.register_xray` with its default preprocessing, as
  ``ctxreg register`` would. A frame whose content registration refuses (a field, preprocessing
  or intensity error, e.g. no valid pixel left after the field detection) is a failed case, scored at its start pose,
  with the message in ``cases.csv`` (column ``refused``). ``tools = [low, high]`` puts that many
  metal tools (screws, K-wires, plates, retractors) fixed to the patient around the anatomy centre
  into every frame, a new arrangement per frame (:func:`sim.distractors.implanted_tools`).

Outputs in ``--out``: ``variants/<name>/`` (the training run: ``train.toml``, ``checkpoint.pt``,
``log.csv``), ``results/<variant>/<target>/summary.json`` (and ``cases.csv``), ``table.md``,
``results.json``, ``study.png`` and ``commands.sh``. **Resumable**: a run continues where the
last one stopped: finished trainings (their checkpoint reached ``iterations``) and finished
evaluations (their ``summary.json``) are kept **when they were made with the settings the study
now asks for** (``variants/<name>/settings.json``: :func:`training_settings`; ``summary.json``'s
``study_settings``: :func:`evaluation_settings`), an interrupted training resumes from its
checkpoint (``ctxreg train --resume``). A part made with other settings is redone, the changed
keys named, the old one moved to ``replaced/`` (docs/domain_gap.md). A damaged state file stops
the run in one line ("remove it to redo that evaluation"). ``study.json`` records the study; a
changed study file is refused, naming the keys that changed, unless the changes only add variants
or targets.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

import register.api as api
from register.engines.methods import METHOD_NAMES, build_method, needs_model
from register.evaluation.errors import bone_points, pose_errors
from register.evaluation.evaluate import (START_MODES, EvaluationSettings, MethodSpec, evaluate, sample_cases,
                                          summarize)
from register.evaluation.frames import FrameSimulator
from register.xray.preprocess import PreprocessError
from register.xray.field import FieldError
from register.xray.intensity import IntensityError
from sim.ct.anatomy import anatomy_center
from sim.core.atomic import (atomic_path, read_toml, save_figure, sha256_file, toml_text, write_csv, write_json,
                        write_toml)
from sim.core.cliargs import IMAGE_SIDE_PX
from sim.ct.io import load_ct_spec
from sim.core.errors import InputError
from sim.projection.geometry import pose_from_params
from sim.core.outputs import check_output_dir
from sim.physics.display import Collimator, DisplayChain
from sim.physics.imaging import LogImageRenderer, PhysicsSettings, XRayImager
from sim.core.progress import Progress
from sim.core.scale import each_result
from sim.projection.drr import DRRRenderer, RenderSettings
from sim.projection.scene import SceneError, load_scene
from learn.predict import NetworkPredictor
from sim.campaign import DatasetError, load_campaign, open_dataset
from sim.campaign.config import CampaignConfigError
from learn.shipped import ModelCardError, resolve_model, shipped_models

__all__ = ["StudyError", "Variant", "Target", "Study", "load_study", "run_domain_study", "format_study_table",
           "STUDY_FILES"]

#: Files ``ctxreg study`` writes at the top of its output folder.
STUDY_FILES = ("study.json", "table.md", "results.json", "study.png", "commands.sh")
TARGET_KINDS = ("drr", "xray")
_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-_.+")

#: The starts a study may use: those of :data:`START_MODES` that need no pose of their own.
STUDY_STARTS = tuple(m for m in START_MODES if m != "pose")


class StudyError(InputError):
    """A study file or its output folder cannot be used; the message names the key."""


@dataclass(frozen=True)
class Variant:
    """A network variant: ``name`` and either its ``[train]`` table (``out`` is set by the study)
    or ``model``, an existing checkpoint or shipped ``model.pt`` evaluated as it is (a
    reference, e.g. the network the others are fine-tuned from)."""

    name: str
    train: dict[str, Any] | None = None
    model: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model} if self.model is not None else dict(self.train)


@dataclass(frozen=True)
class Target:
    """A target domain: ``kind`` (:data:`TARGET_KINDS`), the targets' ``physics`` (keyword
    arguments of :class:`sim.physics.imaging.PhysicsSettings`, with ``level``), and for
    ``kind = "xray"`` the ``collimator`` and ``display`` records (``None``: open field / the
    fluoroscopy default) and ``tools``, ``(low, high)`` metal tools fixed to the patient per
    frame (``None``: none)."""

    name: str
    kind: str = "drr"
    physics: dict[str, Any] = field(default_factory=lambda: {"level": "line"})
    collimator: dict[str, Any] | None = None
    display: dict[str, Any] | None = None
    cases: int | None = None  #: this domain's case count (default the study's ``cases``)
    tools: tuple[int, int] | None = None


@dataclass(frozen=True)
class Study:
    """A parsed study file (:func:`load_study`). Units: px, deg, mm."""

    ct: str
    variants: tuple[Variant, ...]
    targets: tuple[Target, ...]
    cases: int = 20
    start: str = "ap"
    seed: int = 0
    methods: tuple[str, ...] = ("contextual", "contextual+cmaes")
    size: tuple[int, int] = (128, 128)
    moving_physics: str = "line"
    source: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"ct": self.ct, "cases": self.cases, "start": self.start, "seed": self.seed,
                "methods": list(self.methods), "size": list(self.size), "moving_physics": self.moving_physics,
                "variants": {v.name: v.to_dict() for v in self.variants},
                "targets": {t.name: {"kind": t.kind, "physics": t.physics, "collimator": t.collimator,
                                     "display": t.display, **({"cases": t.cases} if t.cases else {}),
                                     **({"tools": list(t.tools)} if t.tools else {})}
                            for t in self.targets}}

    def cases_of(self, target: "Target") -> int:
        """The number of cases of ``target`` (its own ``cases``, else the study's)."""
        return target.cases or self.cases


def _check_training_inputs(table: dict, where: str, earlier: list[str]) -> None:
    """The files a variant's training reads, checked when the study is read (so that a missing
    dataset of the last variant is named before the first one trains): the dataset (a campaign
    file, read and checked with its CTs, or a campaign folder, opened), ``init_from`` (an
    existing file, or ``.../variants/<an earlier variant>/checkpoint.pt``: what the study trains
    first) and ``weights_path``."""

    dataset = str(table["dataset"])
    try:
        if dataset.endswith(".toml"):
            load_campaign(dataset)
        elif not Path(dataset).is_dir():
            raise StudyError(f"{where}.dataset: {dataset} not found (a campaign .toml file or a campaign folder)")
        else:
            open_dataset(dataset)
    except (CampaignConfigError, DatasetError) as e:
        raise StudyError(f"{where}.dataset: {e}") from None
    for key in ("init_from", "weights_path"):
        value = table.get(key)
        if not isinstance(value, str) or Path(value).is_file():
            continue
        parts = Path(value).parts
        if key == "init_from" and parts[-3:-2] == ("variants",) and parts[-1] == "checkpoint.pt" and parts[-2] in earlier:
            continue  # the checkpoint of a variant this study trains before
        raise StudyError(f"{where}.{key}: {value} not found" + (" (nor the checkpoint of an earlier variant, "
                                                                ".../variants/<name>/checkpoint.pt)"
                                                                if key == "init_from" else ""))


#: The most metal tools a study frame may hold (``tools = [low, high]``).
MAX_TOOLS = 20


def _is_count(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _name(value: Any, key: str) -> str:
    if not isinstance(value, str) or not value or not set(value) <= _NAME_CHARS:
        raise StudyError(f"{key}: a name of letters, digits and - _ . + (it becomes a folder), got {value!r}")
    return value


def _int(table: dict, key: str, default: int, lo: int, hi: int, where: str) -> int:
    v = table.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise StudyError(f"{where}.{key}: an integer in [{lo}, {hi}], got {v!r}")
    return v


def load_study(path: str | Path) -> Study:
    """Read and check a study file; relative paths in it are relative to the file."""
    from learn.train import TrainConfig  # loads torch: imported where first needed (start-up)

    path = Path(path)
    data = read_toml(path, StudyError, "study file")
    unknown = set(data) - {"study", "variant", "target"}
    if unknown:
        raise StudyError(f"{path}: unknown table(s) {sorted(unknown)}; expected [study], [[variant]], [[target]]")
    head = data.get("study")
    if not isinstance(head, dict):
        raise StudyError(f"{path}: needs a [study] table (ct, cases, start, methods, ...)")
    known = {"ct", "cases", "start", "seed", "methods", "size", "moving_physics"}
    if set(head) - known:
        raise StudyError(f"{path}: [study] has unknown key(s) {sorted(set(head) - known)}; known: {sorted(known)}")
    base = path.resolve().parent

    def resolve(v: str) -> str:
        return v if v.startswith("phantom") or Path(v).is_absolute() else str((base / v).resolve())

    ct = head.get("ct")
    if not isinstance(ct, str) or not ct:
        raise StudyError(f"{path}: study.ct: the evaluation CT (a NIfTI file, DICOM folder or 'phantom'), got {ct!r}")
    start = head.get("start", "ap")
    if start not in STUDY_STARTS:
        raise StudyError(f"{path}: study.start: one of {', '.join(STUDY_STARTS)}, got {start!r}")
    methods = head.get("methods", ["contextual", "contextual+cmaes"])
    if (not isinstance(methods, list) or not methods or len(set(map(str, methods))) < len(methods)
            or any(m not in METHOD_NAMES or not needs_model(m) for m in methods)):
        raise StudyError(f"{path}: study.methods: distinct contextual methods from "
                         f"{[m for m in METHOD_NAMES if needs_model(m)]}, got {methods!r}")
    size = head.get("size", [128, 128])
    if (not isinstance(size, list) or len(size) != 2
            or any(isinstance(s, bool) or not isinstance(s, int) or s not in IMAGE_SIDE_PX for s in size)):
        raise StudyError(f"{path}: study.size: [H, W] in {IMAGE_SIDE_PX} px, got {size!r}")
    _check_aspect(size, f"{path}: study.size")
    moving = head.get("moving_physics", "line")
    if moving not in ("line", "poly"):
        raise StudyError(f"{path}: study.moving_physics: 'line' or 'poly', got {moving!r}")
    where = f"{path}: study"
    study_kw = dict(ct=resolve(ct), cases=_int(head, "cases", 20, 1, 10000, where),
                    seed=_int(head, "seed", 0, 0, 2**32 - 1, where), start=start, methods=tuple(methods),
                    size=(size[0], size[1]), moving_physics=moving, source=str(path))

    variants = []
    rows = data.get("variant", [])
    if not isinstance(rows, list) or not rows:
        raise StudyError(f"{path}: needs at least one [[variant]] with a name and a [variant.train] table")
    for i, row in enumerate(rows):
        where = f"{path}: variant[{i}]"
        if not isinstance(row, dict) or set(row) - {"name", "train", "model"} \
                or ("model" in row) == ("train" in row):
            raise StudyError(f"{where}: expected keys name and either train (a [variant.train] table) or model "
                             f"(a checkpoint to evaluate as it is), got {row!r}")
        name = _name(row.get("name"), f"{where}.name")
        if "model" in row:
            model = row["model"]
            if isinstance(model, str) and model:
                try:  # a shipped model's name, a model folder or its model.pt: the card checked
                    model = str(resolve_model(model if model in shipped_models() else resolve(model)))
                except ModelCardError as e:
                    raise StudyError(f"{where}.model: {e}") from None
            if not isinstance(model, str) or not Path(model).is_file():
                raise StudyError(f"{where}.model: an existing checkpoint file or a shipped model's name, got "
                                 f"{row['model']!r}")
            variants.append(Variant(name, model=model))
            continue
        if not isinstance(row.get("train"), dict):
            raise StudyError(f"{where}.train: a [variant.train] table, got {row.get('train')!r}")
        table = dict(row["train"])
        if "out" in table:
            raise StudyError(f"{where}.train.out: set by the study (<out>/variants/{name}); remove it")
        for key in ("dataset", "weights_path", "init_from"):
            if isinstance(table.get(key), str):
                table[key] = resolve(table[key])
        _checked(TrainConfig, {**table, "out": "-"}, f"{where}.train")  # as ctxreg train checks it
        _check_training_inputs(table, f"{where} ({name}).train", [v.name for v in variants])  # before any trains
        variants.append(Variant(name, table))

    targets = []
    rows = data.get("target", [])
    if not isinstance(rows, list) or not rows:
        raise StudyError(f"{path}: needs at least one [[target]] (name, kind, physics)")
    for i, row in enumerate(rows):
        where = f"{path}: target[{i}]"
        if not isinstance(row, dict) or set(row) - {"name", "kind", "physics", "collimator", "display", "cases",
                                                    "tools"}:
            raise StudyError(f"{where}: keys are name, kind, physics, collimator, display, cases, tools; got {row!r}")
        name = _name(row.get("name"), f"{where}.name")
        kind = row.get("kind", "drr")
        if kind not in TARGET_KINDS:
            raise StudyError(f"{where}.kind: one of {', '.join(TARGET_KINDS)}, got {kind!r}")
        physics = row.get("physics", {"level": "line"})
        if not isinstance(physics, dict):
            raise StudyError(f"{where}.physics: a table of physics settings (level, kvp, mas, ...), got {physics!r}")
        physics = {"level": "line", **physics}
        if kind == "xray" and physics["level"] != "full":
            raise StudyError(f"{where}.physics.level: kind 'xray' renders a detector signal with scatter: 'full'")
        _checked(PhysicsSettings, physics, f"{where}.physics")
        coll, disp = row.get("collimator"), row.get("display")
        if kind != "xray" and (coll is not None or disp is not None):
            raise StudyError(f"{where}: collimator and display apply to kind 'xray' only")
        for key, value, cls in (("collimator", coll, Collimator), ("display", disp, DisplayChain)):
            if value is None:
                continue
            if not isinstance(value, dict):
                raise StudyError(f"{where}.{key}: a table, got {value!r}")
            _checked(cls.from_dict, value, f"{where}.{key}", unpack=False)
        cases = _int(row, "cases", 0, 1, 10000, where) if "cases" in row else None
        tools = row.get("tools")
        if tools is not None:
            if kind != "xray":
                raise StudyError(f"{where}.tools: tools apply to kind 'xray' only")
            if not (isinstance(tools, list) and len(tools) == 2 and all(_is_count(v) for v in tools)
                    and tools[0] <= tools[1] <= MAX_TOOLS):
                raise StudyError(f"{where}.tools: [low, high], whole numbers with 0 <= low <= high <= {MAX_TOOLS} "
                                 f"(metal tools per frame), got {tools!r}")
            tools = (int(tools[0]), int(tools[1]))
        targets.append(Target(name, kind, physics, coll, disp, cases, tools))

    if any(t.kind == "xray" for t in targets) and min(study_kw["size"]) < api.REGISTER_MIN_SIDE_PX:
        raise StudyError(f"{path}: study.size: {list(study_kw['size'])}: kind 'xray' targets are registered as "
                         f"ctxreg register does, which needs at least {api.REGISTER_MIN_SIDE_PX} px per side")
    for what, items in (("variant", variants), ("target", targets)):
        names = [x.name for x in items]
        if len(set(names)) < len(names):
            raise StudyError(f"{path}: two {what}s are named alike: {sorted(n for n in names if names.count(n) > 1)}")
    return Study(variants=tuple(variants), targets=tuple(targets), **study_kw)


def _check_aspect(size, where: str, scene: str = "cios_fusion") -> None:
    """Refuse a registration size that does not keep the scene detector's aspect (square pixels):
    every target and DRR of the study is rendered at it, so this is refused before any training."""
    try:
        load_scene(scene).geometry_at(int(size[0]), int(size[1]))
    except (SceneError, ValueError) as e:
        g = load_scene(scene).geometry
        raise StudyError(f"{where}: {list(size)} does not keep the {scene} detector's aspect {g.height} x {g.width} "
                         f"(square pixels), e.g. {[size[0], round(size[0] * g.width / g.height)]}") from None


def _checked(build, args: dict, where: str, *, unpack: bool = True):
    """``build(**args)`` (or ``build(args)``), its refusal (a wrong key or value) as one StudyError
    line naming ``where``."""
    try:
        return build(**args) if unpack else build(args)
    except (TypeError, InputError) as e:
        raise StudyError(f"{where}: {e}") from None


def _changes(old: dict, new: dict) -> list[str]:
    """``key: old -> new`` for each setting that differs; variants and targets compared by name."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        pairs = ([(f"{key}.{k}", a.get(k), b.get(k)) for k in sorted(set(a) | set(b))]
                 if key in ("variants", "targets") else [(key, a, b)])
        out += [f"{name}: {json.dumps(x)} -> {json.dumps(y)}" for name, x, y in pairs if x != y]
    return out


def _check_record(out: Path, study: Study) -> None:
    """Refuse to continue a study whose settings changed (added variants / targets are fine)."""
    record = out / "study.json"
    new = study.to_dict()
    if record.is_file():
        try:
            old = json.loads(record.read_text())["study"]
        except (json.JSONDecodeError, KeyError, TypeError):
            raise StudyError(f"{record} is damaged: remove it to start the study afresh") from None
        kept = {**old, "variants": {k: v for k, v in old["variants"].items() if k in new["variants"]},
                "targets": {k: v for k, v in old["targets"].items() if k in new["targets"]}}
        changed = _changes(kept, {**new, "variants": {k: v for k, v in new["variants"].items() if k in old["variants"]},
                                  "targets": {k: v for k, v in new["targets"].items() if k in old["targets"]}})
        if changed:
            raise StudyError(f"{out} holds a study with other settings ({'; '.join(changed)}): use another "
                             f"--out, or remove the changed parts from it")
    write_json(record, {"study": new, "source": study.source})


def variant_config(variant: Variant, folder: Path) -> Path:
    """Write (if changed) and return the ``train.toml`` of a variant trained in ``folder``: the
    file ``ctxreg train`` runs alone (for a variant trained in another process)."""
    folder.mkdir(parents=True, exist_ok=True)
    config = folder / "train.toml"
    tables = {"train": {**variant.train, "out": str(folder.resolve())}}
    if not config.is_file() or config.read_text() != toml_text(tables):
        write_toml(config, tables)
    return config


#: The record of a variant's training settings in its folder (:func:`training_settings`).
TRAINING_RECORD = "settings.json"
#: Where a training or an evaluation made with other settings is moved before it is redone.
REPLACED = "replaced"


def _fingerprint(value: str) -> str:
    """What identifies an input file's content: a file's sha256; a campaign folder's
    ``manifest.json``'s (it holds every shard's sha256); another folder's file names and sizes."""
    path = Path(value)
    if path.is_file():
        return "sha256:" + sha256_file(path)
    if (path / "manifest.json").is_file():
        return "manifest sha256:" + sha256_file(path / "manifest.json")
    if path.is_dir():
        listing = sorted((str(p.relative_to(path)), p.stat().st_size) for p in path.rglob("*") if p.is_file())
        return "listing sha256:" + hashlib.sha256(json.dumps(listing).encode()).hexdigest()
    return "missing"


def _plain(obj: Any) -> Any:
    """``obj`` as JSON gives it back (tuples as lists): what a record compares against."""
    return json.loads(json.dumps(obj, sort_keys=True, default=str))


def _digest(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()


def training_settings(variant: Variant) -> dict:
    """The settings a variant's training is made with: its ``[variant.train]`` table (paths
    resolved) and its inputs' content (``dataset``, ``init_from``, ``weights_path``:
    :func:`_fingerprint`); for a ``model`` variant the model file's sha256."""
    if variant.model is not None:
        return _plain({"model": variant.model, "inputs": {"model": _fingerprint(variant.model)}})
    inputs = {key: _fingerprint(variant.train[key]) for key in ("dataset", "init_from", "weights_path")
              if isinstance(variant.train.get(key), str)}
    return _plain({"train": dict(variant.train), "inputs": inputs})


def evaluation_settings(study: Study, target: Target, network: dict) -> dict:
    """The settings an evaluation of one variant on one target is made with: the network's
    (``{"training_sha256": ...}``: the digest of :func:`training_settings`), the target's (kind,
    physics, collimator, display, cases: its frames) and the study's protocol (CT, start, seed,
    methods, size, moving physics)."""
    return _plain({"network": network,
                   "target": {"kind": target.kind, "physics": target.physics, "collimator": target.collimator,
                              "display": target.display, "cases": study.cases_of(target),
                              **({"tools": list(target.tools)} if target.tools else {})},
                   "protocol": {"ct": study.ct, "start": study.start, "seed": study.seed,
                                "methods": list(study.methods), "size": list(study.size),
                                "moving_physics": study.moving_physics}})


def _diff(old: Any, new: Any, key: str = "") -> list[str]:
    """``key: old -> new`` for every leaf that differs (dicts compared key by key); an input
    file's fingerprint as ``key: its content changed``."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new), key=str):
            out += _diff(old.get(k), new.get(k), f"{key}.{k}" if key else str(k))
        return out
    if old == new:
        return []
    if key.startswith("inputs.") and old is not None and new is not None:
        return [f"{key}: its content changed"]
    if key.startswith("network."):
        return [f"{key}: the variant's network changed"]
    return [f"{key}: {json.dumps(old, default=str)} -> {json.dumps(new, default=str)}"]


def _damaged(path: Path, why: str, what: str = "that part") -> StudyError:
    return StudyError(f"{path} is damaged ({why}): remove it to redo {what}")


def _read_json(path: Path, what: str) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise _damaged(path, f"not JSON: {str(e).splitlines()[0] if str(e) else type(e).__name__}", what) from None
    if not isinstance(data, dict):
        raise _damaged(path, f"a JSON {type(data).__name__}, not an object", what)
    return data


def _replace(out: Path, folder: Path, kind: str, old_digest: str | None) -> Path:
    """Move ``folder`` (a training or an evaluation made with other settings) to
    ``out/replaced/<kind>/<relative path>-<old digest>`` and return where it went."""
    rel = folder.relative_to(out / kind)
    dest = out / REPLACED / kind / f"{rel}-{(old_digest or 'unrecorded')[:12]}"
    n = 1
    while dest.exists():
        n += 1
        dest = dest.with_name(f"{dest.name.rsplit('~', 1)[0]}~{n}")
    dest.parent.mkdir(parents=True, exist_ok=True)
    os.replace(folder, dest)
    return dest


def _train_variant(variant: Variant, folder: Path, log, out: Path | None = None) -> Path:
    """Train (or resume) one variant; returns its checkpoint. A finished training is kept only if
    it was made with the variant's settings (:data:`TRAINING_RECORD`, :func:`training_settings`);
    one made with other settings is moved to ``out/replaced/variants/`` and redone, the changed
    keys named. A ``model`` variant is its model."""
    from learn.checkpoint import CheckpointError, load_checkpoint  # loads torch: imported where first needed (start-up)
    from learn.train import load_train_config, train  # loads torch: imported where first needed (start-up)

    if variant.model is not None:
        log(f"variant {variant.name}: the model {variant.model}, as it is")
        return Path(variant.model)
    out = folder.parent.parent if out is None else out
    settings = training_settings(variant)
    digest = _digest(settings)
    record = folder / TRAINING_RECORD
    ckpt = folder / "checkpoint.pt"
    if ckpt.is_file():
        changes: list[str] = []
        old_digest = None
        if record.is_file():
            old = _read_json(record, "that training's check (the checkpoint is then checked against its config)")
            if not isinstance(old.get("settings"), dict) or not isinstance(old.get("sha256"), str):
                raise _damaged(record, "no settings and sha256", "that training's check")
            old_digest = old["sha256"]
            if old_digest != digest:
                changes = _diff(old["settings"], settings) or ["(the recorded settings' digest)"]
        else:  # a training from before the record: its checkpoint's config is the record
            from learn.train import TrainConfig, _config_changes  # loads torch: imported where first needed (start-up)

            try:
                state = load_checkpoint(ckpt)
            except CheckpointError as e:
                raise _damaged(ckpt, str(e).splitlines()[0], "that training") from None
            stored = state.config if isinstance(state.config, dict) else {}
            out_now = stored.get("out", str(folder.resolve()))  # a study folder moved as a whole is the same
            changes = _config_changes(stored, TrainConfig(**{**variant.train, "out": out_now}))
        if changes:
            moved = _replace(out, folder, "variants", old_digest)
            log(f"variant {variant.name}: trained with other settings ({'; '.join(changes)}): training again "
                f"(the old training moved to {moved})")
    folder.mkdir(parents=True, exist_ok=True)
    cfg = load_train_config(variant_config(variant, folder))
    write_json(record, {"settings": settings, "sha256": digest})
    if ckpt.is_file():
        try:
            done = load_checkpoint(ckpt).iteration or 0
        except CheckpointError as e:
            raise _damaged(ckpt, str(e).splitlines()[0], "that training") from None
        if done >= cfg.iterations:
            log(f"variant {variant.name}: trained ({done} iterations), kept")
            return ckpt
        log(f"variant {variant.name}: resuming at iteration {done} of {cfg.iterations}")
    else:
        log(f"variant {variant.name}: training {cfg.iterations} iterations")
    train(cfg, resume=ckpt.is_file(), log=lambda s: log(f"  {variant.name}: {s}"))
    return ckpt


#: What each method's summary must hold for the table (a summary.json without it is damaged).
_SUMMARY_KEYS = ("cases", "success", "rot_err_deg", "trans_err_mm", "mtre_mm", "time_s")


def _finished_evaluation(path: Path, study: Study, settings: dict) -> tuple[dict | None, list[str]]:
    """``(summary, [])`` of a finished evaluation made with ``settings``; ``(None, changes)`` for
    one made with other settings (``changes``: the keys; one line where it predates the record);
    ``(None, [])`` where there is none. A damaged ``summary.json`` is refused in one line."""
    if not path.is_file():
        return None, []
    data = _read_json(path, "that evaluation")
    summary = data.get("summary")
    if not isinstance(summary, dict):
        raise _damaged(path, "no 'summary' table", "that evaluation")
    for method in study.methods:
        stats = summary.get(method)
        if stats is None and data.get("study_settings") != settings:
            continue  # another method list: a change, named below
        if not isinstance(stats, dict) or any(k not in stats for k in _SUMMARY_KEYS) or any(
                not isinstance(stats[k], dict) or not {"mean", "median"} <= set(stats[k])
                for k in _SUMMARY_KEYS if k not in ("cases", "success")):
            raise _damaged(path, f"summary.{method} lacks its statistics", "that evaluation")
    if "study_settings" not in data:
        return None, ["made before the study recorded each evaluation's settings"]
    if data.get("study_settings") != settings:
        old = data["study_settings"]
        return None, _diff(old, settings) if isinstance(old, dict) else ["study_settings: not a table"]
    return summary, []


def _evaluate_drr(study: Study, target: Target, volume, center, predictor, folder: Path, log,
                  stamp: dict | None = None, *, client=None, model: str | None = None) -> dict:
    """A ``drr`` target's evaluation (:func:`register.evaluation.evaluate.evaluate`); with a Dask
    ``client`` its cases are registered on the workers, which build the methods with the checkpoint
    ``model``."""
    settings = EvaluationSettings(cases=study.cases_of(target), seed=study.seed, size=study.size, start=study.start)
    physics = PhysicsSettings(**{**target.physics, "seed": study.seed})
    if physics.level == "line":
        renderer = DRRRenderer(volume, RenderSettings(size=study.size), center_lps=center)
    else:
        renderer = LogImageRenderer(volume, physics, size=study.size, center_lps=center)
    moving = _moving(study)
    common = dict(center_lps=center, geometry=renderer.geometry, target_renderer=renderer, log=lambda s: log(f"  {s}"),
                  record={"target_physics": asdict(physics), **(stamp or {})})
    if client is None:
        methods = {m: build_method(m, volume, center_lps=center, size=study.size, model=predictor, physics=moving)
                   for m in study.methods}
        result = evaluate(volume, methods, settings, folder, **common)
    else:
        spec = MethodSpec(ct=study.ct, label_map=None, center_lps=tuple(float(v) for v in center), size=study.size,
                          scene="cios_fusion", methods=tuple(study.methods), model=model, physics=moving)
        result = evaluate(volume, {}, settings, folder, client=client, spec=spec, **common)
    return result["summary"]


def _moving(study: Study):
    return None if study.moving_physics == "line" else PhysicsSettings(
        level=study.moving_physics, noise=False, scatter_photons=api.REGISTER_SCATTER_PHOTONS)


def frame_refusals() -> tuple[type, ...]:
    """The errors a frame's own content can make registration raise (no valid pixel left, no
    intensity decision): a failed case of a study, not a stop. Anything else (a bad setting, a bug)
    stops the study as it should."""
    return FieldError, PreprocessError, IntensityError


def study_frames(study: Study, target: Target, volume, center) -> FrameSimulator:
    """The realistic frames of a study's ``xray`` target (:class:`register.evaluation.frames.FrameSimulator`):
    full physics with noise (the target's ``physics``, the study's seed), its collimator and display
    chain (default: log, bone dark, 12 bits, black shutter) and its tools; frame ``case`` is drawn
    from :func:`frame_seed`."""
    physics = PhysicsSettings(**{**target.physics, "noise": True, "seed": study.seed})
    imager = XRayImager(volume, physics, size=study.size, center_lps=center)
    chain = DisplayChain.from_dict(target.display or {"log": True, "polarity": "bone-dark", "bits": 12,
                                                       "shutter": "black"})
    collimator = None if target.collimator is None else Collimator.from_dict(target.collimator)
    return FrameSimulator(imager, chain, collimator, tools=target.tools)


def frame_seed(study: Study, case: int) -> int:
    """The noise and Monte Carlo seed of frame ``case`` of a study's ``xray`` target."""
    return study.seed * 100003 + case


def _xray_case(study: Study, method_model, volume, center, frame: FrameSimulator, settings: EvaluationSettings,
               points, i: int, target_params, start, frames: Path) -> list[dict]:
    """Case ``i`` of an ``xray`` target: its frame simulated (seeded by :func:`frame_seed`) and
    registered by each of the study's methods, as rows (a frame refused by its content: a failed case)."""
    g = frame.imager.geometry
    T_true = pose_from_params(target_params, g.sod_mm)
    path = frame.simulate(frames / f"case_{i:03d}.dcm", T_true, frame_seed(study, i))
    rows = []
    for method in study.methods:
        t0 = time.perf_counter()
        try:
            res = api.register_xray(volume, path, method=method, model=method_model, init=start, center=center,
                                    size=study.size, physics=_moving(study) or "line")
            pose, similarity, refused, verdict = res.pose, res.similarity, "", res.verdict.label
        except frame_refusals() as e:  # the frame's content refused (e.g. no valid pixel left): a failed case
            pose = pose_from_params(np.asarray(start, float), g.sod_mm)  # the user keeps the start pose
            similarity, refused, verdict = float("nan"), str(e), "failed"
        elapsed = time.perf_counter() - t0
        err = pose_errors(pose, T_true, points, center, g)  # the frame's geometry: both poses projected
        rows.append({"case": i, "method": method, "start": study.start, **err,
                     "success": not refused and err["mtre_mm"] < settings.success_mtre_mm
                     and err["rot_err_deg"] < settings.success_rot_deg,
                     "time_s": elapsed, "similarity": similarity, "refused": refused, "verdict": verdict})
    return rows


_WORKER_STUDY: dict = {}  # a Dask worker's CT, frame simulator and network of the study it serves


def _dask_xray_case(study: Study, target: Target, model: str, settings: EvaluationSettings, i: int, target_params,
                    start, frames: str) -> list[dict]:
    """:func:`_xray_case` on a Dask worker: the CT, its centre and bone points, the target's frame
    simulator and the network built once per process."""

    key = (study.ct, target.name, repr(target), settings.max_points, settings.seed)
    if _WORKER_STUDY.get("key") != key:
        volume = load_ct_spec(study.ct)
        center = anatomy_center(volume)
        _WORKER_STUDY.clear()
        _WORKER_STUDY.update(key=key, volume=volume, center=center, frame=study_frames(study, target, volume, center),
                             points=bone_points(volume, settings.max_points, settings.seed))
    if _WORKER_STUDY.get("model") != model:
        _WORKER_STUDY.update(model=model, predictor=NetworkPredictor(model))
    w = _WORKER_STUDY
    return _xray_case(study, w["predictor"], w["volume"], w["center"], w["frame"], settings, w["points"], i,
                      target_params, start, Path(frames))


def _evaluate_xray(study: Study, target: Target, volume, center, predictor, folder: Path, log,
                   stamp: dict | None = None, *, client=None, model: str | None = None) -> dict:
    """Realistic frames through :func:`register.api.register_xray`, scored like the evaluation; with a
    Dask ``client`` each case (its frame and its registrations) is a task, the network the checkpoint
    ``model``."""
    settings = EvaluationSettings(cases=study.cases_of(target), seed=study.seed, size=study.size, start=study.start)
    targets, starts = sample_cases(settings)
    frames = folder / "frames"
    per_case: dict[int, list[dict]] = {}
    bar = Progress(settings.cases * len(study.methods), 0, f"{target.name}", "registrations", rate_unit="reg/s")

    def done(i: int, rows: list[dict]) -> None:
        per_case[i] = rows
        for row in rows:
            log(f"  case {i + 1}/{settings.cases} {row['method']}: " + (
                f"refused ({row['refused']})" if row["refused"] else
                f"rotation {row['rot_err_deg']:.2f} deg, mTRE {row['mtre_mm']:.1f} mm") + f", {row['time_s']:.1f} s")
        bar.update(len(rows))

    if client is None:
        frame = study_frames(study, target, volume, center)
        points = bone_points(volume, settings.max_points, settings.seed)
        for i, (target_params, start) in enumerate(zip(targets, starts)):
            done(i, _xray_case(study, predictor, volume, center, frame, settings, points, i, target_params, start,
                               frames))
    else:
        each_result(client, {i: (_dask_xray_case, study, target, model, settings, i, targets[i], starts[i], str(frames))
                             for i in range(len(targets))}, done)
    rows = [r for i in sorted(per_case) for r in per_case[i]]
    summary = summarize(rows, settings)
    write_csv(folder / "cases.csv", rows)
    write_json(folder / "summary.json", {"summary": summary, "target": target.name, **(stamp or {})})
    return summary


def run_domain_study(study: Study, out: str | Path, *, log: Callable[[str], None] = print,
              only: tuple[str, ...] | None = None, targets: tuple[str, ...] | None = None, client=None) -> dict:
    """Run (or continue) ``study`` into ``out``; returns ``{variant: {target: summary}}``.

    ``only``: variant names to train and evaluate (default all); the others contribute the
    evaluations they have finished (a summary on disk) and are not trained or evaluated, so
    processes with disjoint ``only`` can share one output folder. ``targets``: the same for target
    domains (the others' finished evaluations are kept, unfinished ones skipped). ``client``: a
    :class:`distributed.Client` (:func:`sim.core.scale.dask_client`): each evaluation's cases run on its
    workers (the variants still train here, one after another)."""

    names = [v.name for v in study.variants]
    unknown = sorted(set(only or ()) - set(names))
    if unknown:
        raise StudyError(f"--only {' '.join(unknown)}: not a variant of the study (it has {', '.join(names)})")
    target_names = [t.name for t in study.targets]
    unknown = sorted(set(targets or ()) - set(target_names))
    if unknown:
        raise StudyError(f"--targets {' '.join(unknown)}: not a target of the study (it has {', '.join(target_names)})")
    out = check_output_dir(out, STUDY_FILES)
    out.mkdir(parents=True, exist_ok=True)
    _check_record(out, study)
    volume = load_ct_spec(study.ct)
    center = anatomy_center(volume)
    results: dict[str, dict[str, dict]] = {}
    t_start = time.perf_counter()
    chosen = [v for v in study.variants if only is None or v.name in only]
    parts = len(chosen) * (1 + len(study.targets))
    done = 0
    for variant in study.variants:
        network = {"training_sha256": _digest(training_settings(variant))}
        if variant not in chosen:  # another process's: its finished evaluations (made with these settings) only
            for target in study.targets:
                summary_file = out / "results" / variant.name / target.name / "summary.json"
                expected = evaluation_settings(study, target, network)
                summary, changes = _finished_evaluation(summary_file, study, expected)
                if summary is not None:
                    results.setdefault(variant.name, {})[target.name] = summary
                elif changes:
                    log(f"{variant.name} on {target.name}: made with other settings ({'; '.join(changes)}), left "
                        f"out (--only {variant.name} redoes it)")
            continue
        ckpt = _train_variant(variant, out / "variants" / variant.name, log, out)
        done += 1
        predictor = None
        results[variant.name] = {}
        for target in study.targets:
            folder = out / "results" / variant.name / target.name
            settings = evaluation_settings(study, target, network)
            summary, changes = _finished_evaluation(folder / "summary.json", study, settings)
            if summary is not None:
                results[variant.name][target.name] = summary
                log(f"{variant.name} on {target.name}: evaluated, kept")
            elif targets is not None and target.name not in targets:
                log(f"{variant.name} on {target.name}: not in --targets, skipped"
                    + (f" (its evaluation was made with other settings: {'; '.join(changes)})" if changes else ""))
            else:
                if changes:
                    old = _read_json(folder / "summary.json", "that evaluation").get("study_settings_sha256")
                    moved = _replace(out, folder, "results", old if isinstance(old, str) else None)
                    log(f"{variant.name} on {target.name}: evaluated with other settings ({'; '.join(changes)}): "
                        f"evaluating again (the old evaluation moved to {moved})")
                predictor = predictor or NetworkPredictor(ckpt)
                log(f"{variant.name} on {target.name}: {study.cases_of(target)} cases ({target.kind})")
                evaluate = _evaluate_drr if target.kind == "drr" else _evaluate_xray
                stamp = {"study_settings": settings, "study_settings_sha256": _digest(settings)}
                results[variant.name][target.name] = evaluate(study, target, volume, center, predictor, folder, log,
                                                              stamp=stamp, client=client, model=str(ckpt))
            done += 1
            rate = done / max(time.perf_counter() - t_start, 1e-9)
            log(f"study: {done}/{parts} parts, ETA {(parts - done) / rate:.0f} s")
    table = format_study_table(study, results)
    with atomic_path(out / "table.md") as tmp:
        tmp.write_text(table + "\n")
    write_json(out / "results.json", {"study": study.to_dict(), "results": results})
    _plot(study, results, out / "study.png")
    commands = ["# reproduce this study (it resumes where it stopped)",
                f"ctxreg study {study.source} --out {out}"]
    commands += [f"# variant {v.name} alone:\nctxreg train {out / 'variants' / v.name / 'train.toml'}"
                 for v in study.variants if v.model is None]
    with atomic_path(out / "commands.sh") as tmp:
        tmp.write_text("\n".join(commands) + "\n")
    log(table)
    return results


def format_study_table(study: Study, results: dict) -> str:
    """Markdown: one row per variant, target and method: success (mTRE < 10 mm and rotation < 1
    deg), mean / median rotation (deg), translation (mm) and mTRE (mm), seconds per case."""
    lines = ["| variant | target | method | cases | success | mean rot (deg) | mean trans (mm) | median mTRE (mm) | "
             "mean mTRE (mm) | s / case |", "|---|---|---|---|---|---|---|---|---|---|"]
    for variant in study.variants:
        for target in study.targets:
            summary = results.get(variant.name, {}).get(target.name)
            if summary is None:
                continue
            for method in study.methods:
                s = summary[method]
                lines.append(f"| {variant.name} | {target.name} | {method} | {s['cases']} | {100 * s['success']:.0f} % | "
                             f"{s['rot_err_deg']['mean']:.2f} | {s['trans_err_mm']['mean']:.1f} | "
                             f"{s['mtre_mm']['median']:.1f} | {s['mtre_mm']['mean']:.1f} | "
                             f"{s['time_s']['median']:.1f} |")
    return "\n".join(lines)


def _plot(study: Study, results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(study.methods), figsize=(4 + 2.5 * len(study.targets), 3.8), squeeze=False)
    width = 0.8 / max(len(study.variants), 1)
    x = np.arange(len(study.targets))
    for ax, method in zip(axes[0], study.methods):
        for k, variant in enumerate(study.variants):
            ys = [100 * results[variant.name][t.name][method]["success"] if t.name in results.get(variant.name, {})
                  else np.nan for t in study.targets]  # another process's evaluation not finished yet
            ax.bar(x + (k - (len(study.variants) - 1) / 2) * width, ys, width, label=variant.name)
        ax.set_xticks(x, [t.name for t in study.targets], rotation=20, ha="right")
        ax.set_ylim(0, 100)
        ax.set_ylabel("success (%)")
        ax.set_title(method)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
