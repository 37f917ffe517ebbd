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

Target kinds:

* ``"drr"`` (default): targets rendered with ``physics`` (a :class:`sim.physics.imaging.PhysicsSettings`
  table; ``-log(I/I0)`` for poly / full) and registered directly
  (:func:`register.evaluate.evaluate`), as ``ctxreg evaluate`` does;
* ``"xray"``: full-physics detector signal, then a :class:`sim.physics.display.Collimator` and a
  :class:`sim.physics.display.DisplayChain`, written as 12-bit DICOM with geometry tags and
  registered through :func:`register.api.register_xray` with its default preprocessing, as
  ``ctxreg register`` would. A frame whose content registration refuses (a field, preprocessing
  or intensity error, e.g. no valid pixel left after the field detection) is a failed case, scored at its start pose,
  with the message in ``cases.csv`` (column ``refused``).

Outputs in ``--out``: ``variants/<name>/`` (the training run: ``train.toml``, ``checkpoint.pt``,
``log.csv``), ``results/<variant>/<target>/summary.json`` (and ``cases.csv``), ``table.md``,
``results.json``, ``study.png`` and ``commands.sh``. **Resumable**: a run continues where the
last one stopped: finished trainings (their checkpoint reached ``iterations``) and finished
evaluations (their ``summary.json``) are kept, an interrupted training resumes from its
checkpoint (``ctxreg train --resume``). ``study.json`` records the study; a changed study file is
refused, naming the keys that changed, unless the changes only add variants or targets.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sim.errors import InputError

__all__ = ["StudyError", "Variant", "Target", "Study", "load_study", "run_study", "format_study_table",
           "STUDY_FILES"]

#: Files ``ctxreg study`` writes at the top of its output folder.
STUDY_FILES = ("study.json", "table.md", "results.json", "study.png", "commands.sh")
TARGET_KINDS = ("drr", "xray")
_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-_.+")


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
    fluoroscopy default)."""

    name: str
    kind: str = "drr"
    physics: dict[str, Any] = field(default_factory=lambda: {"level": "line"})
    collimator: dict[str, Any] | None = None
    display: dict[str, Any] | None = None
    cases: int | None = None  #: this domain's case count (default the study's ``cases``)


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
                                     "display": t.display, **({"cases": t.cases} if t.cases else {})}
                            for t in self.targets}}

    def cases_of(self, target: "Target") -> int:
        """The number of cases of ``target`` (its own ``cases``, else the study's)."""
        return target.cases or self.cases


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
    from learn.train import TrainConfig
    from register.evaluate import START_MODES
    from register.methods import METHOD_NAMES, needs_model
    from sim.cliargs import IMAGE_SIDE_PX
    from sim.physics.display import Collimator, DisplayChain
    from sim.physics.imaging import PhysicsSettings

    from sim.atomic import read_toml

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
    if start not in START_MODES:
        raise StudyError(f"{path}: study.start: one of {', '.join(START_MODES)}, got {start!r}")
    methods = head.get("methods", ["contextual", "contextual+cmaes"])
    if (not isinstance(methods, list) or not methods or len(set(map(str, methods))) < len(methods)
            or any(m not in METHOD_NAMES or not needs_model(m) for m in methods)):
        raise StudyError(f"{path}: study.methods: distinct contextual methods from "
                         f"{[m for m in METHOD_NAMES if needs_model(m)]}, got {methods!r}")
    size = head.get("size", [128, 128])
    if (not isinstance(size, list) or len(size) != 2
            or any(isinstance(s, bool) or not isinstance(s, int) or s not in IMAGE_SIDE_PX for s in size)):
        raise StudyError(f"{path}: study.size: [H, W] in {IMAGE_SIDE_PX} px, got {size!r}")
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
            from learn.models import ModelCardError, resolve_model, shipped_models

            model = row["model"]
            if isinstance(model, str) and model in shipped_models():
                try:
                    model = str(resolve_model(model))
                except ModelCardError as e:
                    raise StudyError(f"{where}.model: {e}") from None
            elif isinstance(model, str):
                model = resolve(model)
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
        variants.append(Variant(name, table))

    targets = []
    rows = data.get("target", [])
    if not isinstance(rows, list) or not rows:
        raise StudyError(f"{path}: needs at least one [[target]] (name, kind, physics)")
    for i, row in enumerate(rows):
        where = f"{path}: target[{i}]"
        if not isinstance(row, dict) or set(row) - {"name", "kind", "physics", "collimator", "display", "cases"}:
            raise StudyError(f"{where}: keys are name, kind, physics, collimator, display, cases; got {row!r}")
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
        targets.append(Target(name, kind, physics, coll, disp, cases))
    for what, items in (("variant", variants), ("target", targets)):
        names = [x.name for x in items]
        if len(set(names)) < len(names):
            raise StudyError(f"{path}: two {what}s are named alike: {sorted(n for n in names if names.count(n) > 1)}")
    return Study(variants=tuple(variants), targets=tuple(targets), **study_kw)


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
    from sim.atomic import write_json

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
    from sim.atomic import toml_text, write_toml

    folder.mkdir(parents=True, exist_ok=True)
    config = folder / "train.toml"
    tables = {"train": {**variant.train, "out": str(folder.resolve())}}
    if not config.is_file() or config.read_text() != toml_text(tables):
        write_toml(config, tables)
    return config


def _train_variant(variant: Variant, folder: Path, log) -> Path:
    """Train (or resume) one variant; returns its checkpoint. A finished training is kept; a
    ``model`` variant is its model."""
    from learn.checkpoint import load_checkpoint
    from learn.train import load_train_config, train

    if variant.model is not None:
        log(f"variant {variant.name}: the model {variant.model}, as it is")
        return Path(variant.model)
    folder.mkdir(parents=True, exist_ok=True)
    cfg = load_train_config(variant_config(variant, folder))
    ckpt = folder / "checkpoint.pt"
    if ckpt.is_file():
        done = load_checkpoint(ckpt).iteration or 0
        if done >= cfg.iterations:
            log(f"variant {variant.name}: trained ({done} iterations), kept")
            return ckpt
        log(f"variant {variant.name}: resuming at iteration {done} of {cfg.iterations}")
    else:
        log(f"variant {variant.name}: training {cfg.iterations} iterations")
    train(cfg, resume=ckpt.is_file(), log=lambda s: log(f"  {variant.name}: {s}"))
    return ckpt


def _evaluate_drr(study: Study, target: Target, volume, center, predictor, folder: Path, log) -> dict:
    from dataclasses import asdict

    from register.evaluate import EvaluationSettings, evaluate
    from register.methods import build_method
    from sim.physics.imaging import LogImageRenderer, PhysicsSettings
    from sim.render import DRRRenderer, RenderSettings

    settings = EvaluationSettings(cases=study.cases_of(target), seed=study.seed, size=study.size, start=study.start)
    physics = PhysicsSettings(**{**target.physics, "seed": study.seed})
    if physics.level == "line":
        renderer = DRRRenderer(volume, RenderSettings(size=study.size), center_lps=center)
    else:
        renderer = LogImageRenderer(volume, physics, size=study.size, center_lps=center)
    moving = _moving(study)
    methods = {m: build_method(m, volume, center_lps=center, size=study.size, model=predictor, physics=moving)
               for m in study.methods}
    result = evaluate(volume, methods, settings, folder, center_lps=center, geometry=renderer.geometry,
                      target_renderer=renderer, log=lambda s: log(f"  {s}"),
                      record={"target_physics": asdict(physics)})
    return result["summary"]


def _moving(study: Study):
    from register.commands import REGISTER_SCATTER_PHOTONS
    from sim.physics.imaging import PhysicsSettings

    return None if study.moving_physics == "line" else PhysicsSettings(
        level=study.moving_physics, noise=False, scatter_photons=REGISTER_SCATTER_PHOTONS)


def frame_refusals() -> tuple[type, ...]:
    """The errors a frame's own content can make registration raise (no valid pixel left, no
    intensity decision): a failed case of a study, not a stop. Anything else (a bad setting, a bug)
    stops the study as it should."""
    from register.field import FieldError
    from register.intensity import IntensityError
    from register.preprocess import PreprocessError

    return FieldError, PreprocessError, IntensityError


class XRayFrames:
    """The realistic frames of a study's ``xray`` target: full physics with noise (the target's
    ``physics``), its collimator and display chain, written as DICOM (RF, the chain's bits).

    ``write(path, T_true (4, 4), case) -> path``: frame ``case`` at the pose ``T_true``, its noise
    and Monte Carlo drawn from the study's seed and the case. ``imager``: the
    :class:`sim.physics.imaging.XRayImager` (its ``geometry`` is the frame's)."""

    def __init__(self, study: Study, target: Target, volume, center):
        from sim.physics.display import Collimator, DisplayChain
        from sim.physics.imaging import PhysicsSettings, XRayImager

        physics = PhysicsSettings(**{**target.physics, "noise": True, "seed": study.seed})
        self.seed = study.seed
        self.imager = XRayImager(volume, physics, size=study.size, center_lps=center)
        self.chain = DisplayChain.from_dict(target.display or {"log": True, "polarity": "bone-dark", "bits": 12,
                                                               "shutter": "black"})
        self.collimator = None if target.collimator is None else Collimator.from_dict(target.collimator)

    def write(self, path: Path, T_true: np.ndarray, case: int) -> Path:
        from register.xray_io import write_xray_dicom

        g = self.imager.geometry
        raw = self.imager.render(T_true, seed=self.seed * 100003 + case)["raw"][0].astype(np.float64)
        fld = None if self.collimator is None else self.collimator.mask(*raw.shape)
        pixels = self.chain.apply(raw if self.collimator is None else self.collimator.apply(raw), self.imager.flat,
                                  fld)
        return write_xray_dicom(path, pixels, pixel_spacing_mm=g.pixel_spacing_mm, sdd_mm=g.sdd_mm, sod_mm=g.sod_mm,
                                bits_stored=min(16, max(8, self.chain.bits)), modality="RF")


def _evaluate_xray(study: Study, target: Target, volume, center, predictor, folder: Path, log) -> dict:
    """Realistic frames through :func:`register.api.register_xray`, scored like the evaluation."""
    from register.api import register_xray
    from register.evaluate import EvaluationSettings, bone_points, pose_errors, sample_cases, summarize

    FRAME_REFUSALS = frame_refusals()
    from sim.atomic import write_csv, write_json
    from sim.geometry import pose_from_params

    settings = EvaluationSettings(cases=study.cases_of(target), seed=study.seed, size=study.size, start=study.start)
    frame = XRayFrames(study, target, volume, center)
    g = frame.imager.geometry
    targets, starts = sample_cases(settings)
    points = bone_points(volume, settings.max_points, settings.seed)
    rows = []
    frames = folder / "frames"
    from sim.progress import Progress

    bar = Progress(settings.cases * len(study.methods), 0, f"{target.name}", "registrations", rate_unit="reg/s")
    for i, (target_params, start) in enumerate(zip(targets, starts)):
        T_true = pose_from_params(target_params, g.sod_mm)
        path = frame.write(frames / f"case_{i:03d}.dcm", T_true, i)
        for method in study.methods:
            t0 = time.perf_counter()
            try:
                res = register_xray(volume, path, method=method, model=predictor, init=start, center=center,
                                    size=study.size, physics=_moving(study) or "line")
                pose, similarity, refused = res.pose, res.similarity, ""
            except FRAME_REFUSALS as e:  # the frame's content refused (e.g. no valid pixel left): a failed case
                pose = pose_from_params(np.asarray(start, float), g.sod_mm)  # the user keeps the start pose
                similarity, refused = float("nan"), str(e)
            elapsed = time.perf_counter() - t0
            err = pose_errors(pose, T_true, points, center, g)  # the frame's geometry: both poses projected
            rows.append({"case": i, "method": method, "start": study.start, **err,
                         "success": not refused and err["mtre_mm"] < settings.success_mtre_mm
                         and err["rot_err_deg"] < settings.success_rot_deg,
                         "time_s": elapsed, "similarity": similarity, "refused": refused})
            log(f"  case {i + 1}/{settings.cases} {method}: " + (f"refused ({refused})" if refused else
                f"rotation {err['rot_err_deg']:.2f} deg, mTRE {err['mtre_mm']:.1f} mm") + f", {elapsed:.1f} s")
            bar.update(1)
    summary = summarize(rows, settings)
    write_csv(folder / "cases.csv", rows)
    write_json(folder / "summary.json", {"summary": summary, "target": target.name})
    return summary


def run_study(study: Study, out: str | Path, *, log: Callable[[str], None] = print,
              only: tuple[str, ...] | None = None, targets: tuple[str, ...] | None = None) -> dict:
    """Run (or continue) ``study`` into ``out``; returns ``{variant: {target: summary}}``.

    ``only``: variant names to train and evaluate (default all); the others contribute the
    evaluations they have finished (a summary on disk) and are not trained or evaluated, so
    processes with disjoint ``only`` can share one output folder. ``targets``: the same for target
    domains (the others' finished evaluations are kept, unfinished ones skipped)."""
    from learn.predict import NetworkPredictor
    from sim.anatomy import anatomy_center
    from sim.atomic import atomic_path, write_json
    from sim.ct_io import load_ct_spec
    from sim.outputs import check_output_dir

    out = check_output_dir(out, STUDY_FILES)
    out.mkdir(parents=True, exist_ok=True)
    _check_record(out, study)
    names = [v.name for v in study.variants]
    unknown = sorted(set(only or ()) - set(names))
    if unknown:
        raise StudyError(f"--only {' '.join(unknown)}: not a variant of the study (it has {', '.join(names)})")
    target_names = [t.name for t in study.targets]
    unknown = sorted(set(targets or ()) - set(target_names))
    if unknown:
        raise StudyError(f"--targets {' '.join(unknown)}: not a target of the study (it has {', '.join(target_names)})")
    volume = load_ct_spec(study.ct)
    center = anatomy_center(volume)
    results: dict[str, dict[str, dict]] = {}
    t_start = time.perf_counter()
    chosen = [v for v in study.variants if only is None or v.name in only]
    parts = len(chosen) * (1 + len(study.targets))
    done = 0
    for variant in study.variants:
        if variant not in chosen:  # another process's: its finished evaluations only
            for target in study.targets:
                summary_file = out / "results" / variant.name / target.name / "summary.json"
                if summary_file.is_file():
                    results.setdefault(variant.name, {})[target.name] = json.loads(summary_file.read_text())["summary"]
            continue
        ckpt = _train_variant(variant, out / "variants" / variant.name, log)
        done += 1
        predictor = None
        results[variant.name] = {}
        for target in study.targets:
            folder = out / "results" / variant.name / target.name
            summary_file = folder / "summary.json"
            if summary_file.is_file():
                results[variant.name][target.name] = json.loads(summary_file.read_text())["summary"]
                log(f"{variant.name} on {target.name}: evaluated, kept")
            elif targets is not None and target.name not in targets:
                log(f"{variant.name} on {target.name}: not in --targets, skipped")
            else:
                predictor = predictor or NetworkPredictor(ckpt)
                log(f"{variant.name} on {target.name}: {study.cases_of(target)} cases ({target.kind})")
                evaluate = _evaluate_drr if target.kind == "drr" else _evaluate_xray
                results[variant.name][target.name] = evaluate(study, target, volume, center, predictor, folder, log)
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

    from sim.atomic import save_figure

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
