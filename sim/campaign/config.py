"""Campaign files: a TOML description of a simulation campaign -> validated frozen dataclasses.

A campaign renders ``images_per_ct`` labelled X-rays of every subject (a CT or a virtual
patient derived from one) at random C-arm poses, once per ``[[physics]]`` entry. The file format
is documented key by key in ``docs/campaigns.md``; :func:`load_campaign` reads a file and
:func:`parse_campaign` checks an already parsed table (for example ``CampaignConfig.to_dict()``
read back from a dataset manifest).

Every error is a :class:`CampaignConfigError` whose message starts with the file and the dotted
key path (``poses.phi.dist``, ``cts[2].path``; list indices count from 0) and states the allowed
values or range. Unknown keys are rejected with the closest valid key suggested. CT files are
checked to exist but not loaded.

Units: mm, degrees, 1/mm (see ``docs/conventions.md``).
"""

from __future__ import annotations

import copy
import difflib
import hashlib
import json
import math
import os
import re
import tomllib
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from sim.campaign.poses import ORIGINAL_PROTOCOL, PoseDistribution, PoseDistributionError
from sim.core.errors import InputError
from sim.physics.materials import MU_WATER_60KEV_PER_MM
from sim.projection.drr import RAY_MODELS, STEP_FRACTION
from sim.physics import PhysicsError
from sim.physics.settings import (FORMER_NAMES, LEVELS, SETTINGS, PhysicsSettings, campaign_settings,
                                  with_campaign_settings)
from sim.projection.scene import DEFAULT_SCENE, SceneError, load_scene
from sim.core.seeds import KIND_SPLIT, rng_for
from sim.physics.materials import MaterialError, parse_label_materials

#: Split names, in the order used everywhere (tie-breaks, listings).
SPLIT_NAMES: tuple[str, ...] = ("train", "val", "test")
#: Default CT-level split fractions (used when the file has no ``[split]`` table).
DEFAULT_SPLIT: dict[str, float] = {"train": 0.8, "val": 0.1, "test": 0.1}
#: Physics levels that can be rendered now.
PHYSICS_LEVELS: tuple[str, ...] = LEVELS
#: Tolerance on the sum of the split fractions.
SPLIT_SUM_TOL = 1e-9

_TOP_KEYS = ("campaign", "scene", "physics", "poses", "split", "cts", "virtual_patients", "outputs")
_CAMPAIGN_KEYS = ("name", "seed", "images_per_ct", "shard_size")
_SCENE_KEYS = ("name", "size")
#: keys of [[physics]] entries: the render's own, then the physics settings (sim.physics.settings)
_PHYSICS_KEYS = ("name", "level", "ray_model", "step_fraction", "mu_water_per_mm") + tuple(
    s.name for s in campaign_settings())
_CT_KEYS = ("path", "label_map", "label_materials", "center", "split", "virtual_patients",
            "held_out_virtual_patients")
_OUTPUT_KEYS = ("bone_mask", "projected_center")
_PHYSICS_NAME = re.compile(r"[a-z0-9_]+")
_NIFTI_SUFFIXES = (".nii", ".nii.gz")

# Declared ranges of the numbers outside [physics] (a value outside is refused with its key,
# the value and the range; docs/campaigns.md lists them).
#: ``campaign.seed``: at most the largest int64 (it is stored in every shard).
MAX_SEED = 2**63 - 1
#: ``campaign.images_per_ct`` (a subject's poses are drawn at once: 48 MB at the maximum).
MAX_IMAGES_PER_CT = 1_000_000
#: ``campaign.shard_size``.
MAX_SHARD_SIZE = 100_000
#: Shard files of a campaign (subjects x shards per subject): the run plans them all at once.
MAX_SHARDS = 1_000_000
#: Bytes of one shard's images (float32 per physics entry, uint8 bone mask), held in memory.
MAX_SHARD_BYTES = 4 << 30
#: ``scene.size`` rows and columns.
MAX_IMAGE_SIDE = 4096
#: ``cts[i].virtual_patients``.
MAX_VIRTUAL_PATIENTS = 10_000
#: ``cts[i].center``: each coordinate within +-100 m (LPS mm).
MAX_CENTER_MM = 1e5


class CampaignConfigError(InputError):
    """An invalid campaign file; the message names the file, the key path and what is allowed."""


# --------------------------------------------------------------------------------------------
# dataclasses
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SceneConfig:
    """The C-arm scene and the render size.

    Attributes:
        name: a shipped scene name (``cios_fusion``) or the absolute path of a scene XML file.
        size: ``(rows, cols)`` of the rendered images in pixels (same aspect as the detector).
    """

    name: str = DEFAULT_SCENE
    size: tuple[int, int] = (128, 128)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "size": [int(self.size[0]), int(self.size[1])]}


@dataclass(frozen=True)
@with_campaign_settings
class PhysicsConfig:
    """One render setting; every image is rendered once per entry, at the same pose.

    Attributes:
        name: unique key ``[a-z0-9_]+`` (the dataset name ``images/<name>``).
        level: ``"line"`` (line-integral DRR) or ``"poly"`` (``-log(I/I0)`` of the spectral
            polychromatic model with CsI detector and noise, :mod:`sim.physics.imaging`) or ``"full"``
            (``poly`` + Monte Carlo scatter, :mod:`sim.physics.scatter`).
        ray_model: ``"siddon"`` (exact voxel traversal) or ``"trilinear"``.
        step_fraction: trilinear step as a fraction of the smallest voxel spacing, in
            :data:`sim.projection.drr.STEP_FRACTION` ([0.05, 1]).
        mu_water_per_mm: attenuation of water in 1/mm (HU -> mu; line level).
        kvp, anode_angle_deg, filters, bins, mas, detector_mm, detector_mode, noise, blur_mm,
            electronic_noise, scatter_photons, scatter_voxel_mm, grid_ratio: the physics settings
            (poly and full; the last three full only), one field each with the name, default and
            range of :class:`sim.physics.settings.PhysicsSettings`, added by
            :func:`~sim.physics.settings.with_campaign_settings` (the noise is seeded per shard
            from the campaign seed).
    """

    name: str = "line"
    level: str = "line"
    ray_model: str = "siddon"
    step_fraction: float = 0.5
    mu_water_per_mm: float = MU_WATER_60KEV_PER_MM

    def to_dict(self) -> dict[str, Any]:
        """The entry as the file writes it. A line entry has no physics settings; a poly or full
        entry has the settings of its level, those with ``recorded_always`` always and the others
        only when they differ from their defaults (so the config hash of campaigns from before
        they existed is unchanged)."""
        out = {"name": self.name, "level": self.level, "ray_model": self.ray_model,
               "step_fraction": float(self.step_fraction), "mu_water_per_mm": float(self.mu_water_per_mm)}
        if self.level in ("poly", "full"):  # line entries keep their old form (and config hash)
            for s in campaign_settings():
                value = getattr(self, s.name)
                if self.level in s.levels and (s.recorded_always or value != s.default):
                    out[s.name] = s.text(value)
        return out

    def settings(self):
        """The :class:`sim.physics.settings.PhysicsSettings` of a poly or full entry (noise seeds
        are the runner's)."""
        return PhysicsSettings(level=self.level, **{s.name: getattr(self, s.name) for s in campaign_settings()})


@dataclass(frozen=True)
class SplitConfig:
    """CT-level split fractions (each in [0, 1], summing to 1 within 1e-9)."""

    train: float = 0.8
    val: float = 0.1
    test: float = 0.1

    def as_dict(self) -> dict[str, float]:
        """``{"train": ..., "val": ..., "test": ...}`` in :data:`SPLIT_NAMES` order."""
        return {name: float(getattr(self, name)) for name in SPLIT_NAMES}

    def to_dict(self) -> dict[str, float]:
        return self.as_dict()


@dataclass(frozen=True)
class CTEntry:
    """One ``[[cts]]`` entry.

    Attributes:
        path: absolute path of a NIfTI file or DICOM-series folder, or ``"phantom:SEED"``.
        label_map: absolute path of a label volume on the CT's grid, or None.
        center: anatomy centre ``(x, y, z)`` in LPS mm, or None (the runner derives one).
        split: explicit split (``train`` / ``val`` / ``test``) or None (assigned by fractions).
        virtual_patients: number of virtual patients derived from this CT (they share its split,
            except the held-out ones).
        held_out: ``((split, count), ...)``: the last virtual patients of this CT go to these
            splits instead (in this order), e.g. ``(("val", 4),)``. They are deformed,
            re-textured copies of a CT whose other copies may be in training, so they measure
            generalisation to such changes, not to new patients.
        label_materials: ``((label, material), ...)``: in the poly and full images, voxels of
            these labels (of ``label_map``, or the phantom's own labels) take this material
            (:class:`sim.physics.materials.LabelOverride`), e.g. ``((3, "titanium"),)`` for an
            implant. Virtual patients carry the labels along with the anatomy.
    """

    path: str
    label_map: str | None = None
    center: tuple[float, float, float] | None = None
    split: str | None = None
    virtual_patients: int = 0
    held_out: tuple[tuple[str, int], ...] = ()
    label_materials: tuple[tuple[int, str], ...] = ()

    def vp_split(self, vp_index: int, ct_split: str) -> str:
        """The split of virtual patient ``vp_index`` (0-based) of this CT, whose split is ``ct_split``."""
        first = self.virtual_patients - sum(n for _, n in self.held_out)
        if vp_index < first:
            return ct_split
        for split, n in self.held_out:
            if vp_index < first + n:
                return split
            first += n
        raise IndexError(f"virtual patient {vp_index} of {self.virtual_patients}")

    @property
    def is_phantom(self) -> bool:
        return self.path.startswith("phantom:")

    @property
    def stem(self) -> str:
        """A short name: ``phantom3``, the file name without ``.nii[.gz]``, or the folder name."""
        if self.is_phantom:
            return "phantom" + self.path.partition(":")[2]
        name = Path(self.path).name
        for sfx in (".nii.gz", ".nii"):
            if name.lower().endswith(sfx):
                name = name[: -len(sfx)]
                break
        return re.sub(r"[^A-Za-z0-9_.-]+", "_", name) or "ct"

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"path": self.path}
        if self.label_map is not None:
            out["label_map"] = self.label_map
        if self.label_materials:  # absent when empty: older campaigns keep their config hash
            out["label_materials"] = {str(k): v for k, v in self.label_materials}
        if self.center is not None:
            out["center"] = [float(c) for c in self.center]
        if self.split is not None:
            out["split"] = self.split
        out["virtual_patients"] = int(self.virtual_patients)
        if self.held_out:
            out["held_out_virtual_patients"] = {k: int(n) for k, n in self.held_out}
        return out


@dataclass(frozen=True)
class OutputConfig:
    """Optional per-image labels besides the images, poses and projection matrices.

    Attributes:
        bone_mask: per-pixel projected bone mask.
        projected_center: the anatomy centre projected to pixels ``(u, v)``.
    """

    bone_mask: bool = False
    projected_center: bool = True

    def to_dict(self) -> dict[str, bool]:
        return {"bone_mask": bool(self.bone_mask), "projected_center": bool(self.projected_center)}


@dataclass(frozen=True)
class Subject:
    """One subject of a campaign: a CT (``vp_index`` None) or one of its virtual patients.

    Attributes:
        index: position in :meth:`CampaignConfig.subjects` (0-based).
        ct_index: index of the ``[[cts]]`` entry (0-based).
        vp_index: None for the CT itself, else the virtual patient's number 0..n-1 of this CT.
        split: ``train``, ``val`` or ``test`` (a virtual patient has its CT's split).
        name: unique readable name, ``ct001_pelvis`` / ``ct001_pelvis_vp02``.
    """

    index: int
    ct_index: int
    vp_index: int | None
    split: str
    name: str


@dataclass(frozen=True)
class CampaignConfig:
    """A validated campaign. Build with :func:`load_campaign` or :func:`parse_campaign`.

    Attributes:
        name: campaign name.
        seed: campaign seed (int >= 0); every random draw derives from it.
        images_per_ct: images per subject (a CT or a virtual patient).
        shard_size: images per shard file.
        scene, physics, poses, split, cts, outputs: the tables of the file.
        virtual_patients: the ``[virtual_patients]`` table as given (validated by
            ``sim.ct.patients.VirtualPatientRanges.from_dict``); empty = default ranges.
        source: the campaign file (absolute path) or a description of where the table came from.
    """

    name: str
    seed: int
    images_per_ct: int
    shard_size: int
    scene: SceneConfig
    physics: tuple[PhysicsConfig, ...]
    poses: PoseDistribution
    split: SplitConfig
    cts: tuple[CTEntry, ...]
    virtual_patients: dict = field(default_factory=dict)
    outputs: OutputConfig = OutputConfig()
    source: str = "<dict>"

    def to_dict(self) -> dict[str, Any]:
        """Normalised, JSON-serialisable form with the file's layout and absolute paths.

        Numbers are normalised (floats for real values), every default is written out, and
        ``source`` is added at the top level. :func:`parse_campaign` reads it back to an equal
        config.
        """
        return {
            "campaign": {"name": self.name, "seed": int(self.seed), "images_per_ct": int(self.images_per_ct),
                         "shard_size": int(self.shard_size)},
            "scene": self.scene.to_dict(),
            "physics": [p.to_dict() for p in self.physics],
            "poses": self.poses.to_dict(),
            "split": self.split.to_dict(),
            "cts": [c.to_dict() for c in self.cts],
            "virtual_patients": copy.deepcopy(self.virtual_patients),
            "outputs": self.outputs.to_dict(),
            "source": self.source,
        }

    def config_hash(self) -> str:
        """SHA-256 (hex) of the canonical JSON of :meth:`to_dict` without ``source``.

        Canonical JSON: sorted keys, no spaces, ASCII. Because paths are absolute and ``source``
        is left out, the same campaign file moved or copied to another folder hashes the same as
        long as its CT (and scene, label-map) paths resolve to the same absolute paths; any
        change of a value (seed, a range, a CT, a default written out or not aside) changes it.
        """
        d = self.to_dict()
        d.pop("source")
        text = json.dumps(d, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
        return hashlib.sha256(text.encode("ascii")).hexdigest()

    def ct_splits(self) -> tuple[str, ...]:
        """The split of every ``[[cts]]`` entry (see :func:`assign_splits`)."""
        return tuple(self._ct_splits)

    @cached_property
    def _ct_splits(self) -> tuple[str, ...]:
        return tuple(assign_splits(len(self.cts), self.split.as_dict(), [c.split for c in self.cts], self.seed))

    def subjects(self) -> tuple[Subject, ...]:
        """All subjects in a fixed order: CT 0, its virtual patients 0..n-1, CT 1, ...

        A virtual patient has its CT's split (no anatomy appears in two splits) unless the CT's
        ``held_out_virtual_patients`` sends it elsewhere on purpose (:class:`CTEntry`).
        """
        return self._subjects

    @cached_property
    def _subjects(self) -> tuple[Subject, ...]:
        out: list[Subject] = []
        for ci, (ct, split) in enumerate(zip(self.cts, self._ct_splits)):
            base = f"ct{ci:03d}_{ct.stem}"
            out.append(Subject(len(out), ci, None, split, base))
            for vi in range(ct.virtual_patients):
                out.append(Subject(len(out), ci, vi, ct.vp_split(vi, split), f"{base}_vp{vi:02d}"))
        return tuple(out)

    def total_images(self) -> int:
        """Images in the campaign per physics entry: subjects x ``images_per_ct``."""
        return len(self.subjects()) * self.images_per_ct


# --------------------------------------------------------------------------------------------
# splits
# --------------------------------------------------------------------------------------------


def assign_splits(n_cts: int, fractions: Mapping[str, float] | SplitConfig,
                  explicit: Sequence[str | None], seed: int) -> list[str]:
    """Assign every CT to a split; deterministic for a seed.

    Rule:

    1. CTs with an explicit split keep it.
    2. The other ``m`` CTs are shared out by the largest-remainder method so that the total
       count of each split ``s`` comes as close as possible to ``fractions[s] * n_cts``: each
       split's shortfall ``max(0, fractions[s] * n_cts - explicit_count[s])`` gets the share
       ``m * shortfall / sum(shortfalls)`` (if no split falls short: ``m * fractions[s]``), rounded
       down, and the CTs left over go to the largest remainders (ties: larger fraction, then the
       order train, val, test).
    3. Every split with a positive fraction and no CT then takes one free CT, while possible,
       from the split with the most freely assigned CTs among those holding more than one CT
       (receivers in order of decreasing fraction, then train, val, test).
    4. Which free CT goes to which split is a random permutation from
       ``SeedSequence(entropy=seed, spawn_key=(3,))`` (:data:`sim.core.seeds.KIND_SPLIT`).

    For example 10 CTs at 0.8/0.1/0.1 give 8/1/1, and 3 CTs give 1/1/1.

    Args:
        n_cts: number of CTs (>= 0).
        fractions: split name -> fraction (``train``, ``val``, ``test``; sum 1 within 1e-9), or
            a :class:`SplitConfig`.
        explicit: ``n_cts`` entries, each a split name or None.
        seed: campaign seed (int >= 0).

    Returns:
        ``n_cts`` split names.

    Raises:
        CampaignConfigError: invalid arguments, naming the argument.
    """
    if isinstance(fractions, SplitConfig):
        fractions = fractions.as_dict()
    if isinstance(n_cts, bool) or not isinstance(n_cts, (int, np.integer)) or n_cts < 0:
        raise CampaignConfigError(f"n_cts: expected an integer >= 0, got {n_cts!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise CampaignConfigError(f"seed: expected an integer >= 0, got {seed!r}")
    fr = {}
    for k, v in dict(fractions).items():
        if k not in SPLIT_NAMES:
            raise CampaignConfigError(f"fractions: unknown split {k!r}; allowed: {', '.join(SPLIT_NAMES)}")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0.0 <= v <= 1.0):
            raise CampaignConfigError(f"fractions.{k}: expected a number in [0, 1], got {v!r}")
        fr[k] = float(v)
    fr = {s: fr.get(s, 0.0) for s in SPLIT_NAMES}
    if abs(sum(fr.values()) - 1.0) > SPLIT_SUM_TOL:
        raise CampaignConfigError(f"fractions: must sum to 1 (within {SPLIT_SUM_TOL:g}), got {sum(fr.values())!r}")
    explicit = list(explicit)
    if len(explicit) != n_cts:
        raise CampaignConfigError(f"explicit: expected {n_cts} entries (one per CT), got {len(explicit)}")
    for i, e in enumerate(explicit):
        if e is not None and e not in SPLIT_NAMES:
            raise CampaignConfigError(f"explicit[{i}]: unknown split {e!r}; allowed: {', '.join(SPLIT_NAMES)}")

    n = int(n_cts)
    free = [i for i, e in enumerate(explicit) if e is None]
    m = len(free)
    fixed_count = {s: sum(1 for e in explicit if e == s) for s in SPLIT_NAMES}
    order = sorted(SPLIT_NAMES, key=lambda s: (-fr[s], SPLIT_NAMES.index(s)))

    shortfall = {s: max(0.0, fr[s] * n - fixed_count[s]) for s in SPLIT_NAMES}
    weights = shortfall if sum(shortfall.values()) > 0 else fr
    total_w = sum(weights.values())
    quota = {s: m * weights[s] / total_w for s in SPLIT_NAMES}
    alloc = {s: int(math.floor(quota[s] + 1e-12)) for s in SPLIT_NAMES}
    left = m - sum(alloc.values())
    by_remainder = sorted(SPLIT_NAMES, key=lambda s: (-(quota[s] - alloc[s]), -fr[s], SPLIT_NAMES.index(s)))
    for s in by_remainder[:max(left, 0)]:
        alloc[s] += 1

    # every split with a positive fraction gets a CT when the free CTs allow it
    for s in order:
        if fr[s] <= 0 or fixed_count[s] + alloc[s] > 0:
            continue
        donors = [d for d in order if alloc[d] > 0 and fixed_count[d] + alloc[d] > 1]
        if not donors:
            break
        donor = max(donors, key=lambda d: (alloc[d], -order.index(d)))
        alloc[donor] -= 1
        alloc[s] += 1

    rng = rng_for(int(seed), KIND_SPLIT)
    perm = [free[k] for k in rng.permutation(m)]
    out = list(explicit)
    pos = 0
    for s in SPLIT_NAMES:
        for i in perm[pos:pos + alloc[s]]:
            out[i] = s
        pos += alloc[s]
    return out  # type: ignore[return-value]


# --------------------------------------------------------------------------------------------
# loading and validation
# --------------------------------------------------------------------------------------------


def load_campaign(path: str | os.PathLike) -> CampaignConfig:
    """Read and validate a campaign TOML file.

    Relative paths in the file (CTs, label maps, scene XML) are taken against the file's folder.

    Raises:
        CampaignConfigError: the file is missing or unreadable, has a TOML syntax error (file and
            line), or any value is invalid (file, key path, allowed values).
    """
    p = Path(os.path.abspath(Path(path).expanduser()))
    if not p.exists():
        raise CampaignConfigError(f"campaign file {p} not found")
    if not p.is_file():
        raise CampaignConfigError(f"campaign file {p} is not a file")
    try:
        text = p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise CampaignConfigError(f"{p}: not UTF-8 text ({e})") from None
    except OSError as e:
        raise CampaignConfigError(f"{p}: cannot read the campaign file ({e})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        m = re.search(r"line (\d+)", str(e))
        where = f"line {m.group(1)}: " if m else ""
        raise CampaignConfigError(f"{p}: {where}TOML syntax error: {e}") from None
    if "source" in data:
        raise CampaignConfigError(f"{p}: source: not a campaign key (the loader sets it); "
                                  f"allowed top-level keys: {', '.join(_TOP_KEYS)}")
    return parse_campaign(data, base_dir=p.parent, source=str(p))


def parse_campaign(data: Mapping[str, Any], *, base_dir: str | os.PathLike, source: str | None = None,
                   check_files: bool = True) -> CampaignConfig:
    """Validate a parsed campaign table (the TOML file's layout, or :meth:`CampaignConfig.to_dict`).

    Args:
        data: the table. A top-level ``source`` string (as written by ``to_dict``) is accepted.
        base_dir: folder that relative paths are taken against (the campaign file's folder).
        source: the name used in error messages and stored as ``CampaignConfig.source``;
            default: ``data["source"]`` if present, else ``"<dict>"``.
        check_files: check that the CT, label-map and scene files exist (turn off to read the
            config of a dataset made on another machine).

    Raises:
        CampaignConfigError: naming ``source``, the key path and what is allowed.
    """
    if source is None:
        source = data.get("source") if isinstance(data, Mapping) and isinstance(data.get("source"), str) else "<dict>"
    return _Parser(str(source), Path(os.path.abspath(Path(base_dir).expanduser())), check_files).campaign(data)


class _Parser:
    def __init__(self, source: str, base_dir: Path, check_files: bool) -> None:
        self.source = source
        self.base = base_dir
        self.check_files = check_files

    # -- errors and primitive checks ----------------------------------------------------------

    def err(self, key: str, msg: str) -> CampaignConfigError:
        return CampaignConfigError(f"{self.source}: {key}: {msg}")

    def table(self, value: Any, key: str, example: str) -> Mapping[str, Any]:
        if not isinstance(value, Mapping):
            raise self.err(key, f"expected a table ({example}), got {type(value).__name__} {value!r}")
        return value

    def keys(self, table: Mapping[str, Any], allowed: Sequence[str], prefix: str) -> None:
        for k in table:
            if k not in allowed:
                close = difflib.get_close_matches(str(k), list(allowed), n=1, cutoff=0.6)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                where = f"{prefix}.{k}" if prefix else str(k)
                scope = ("at the top level" if not prefix else f"in {prefix}" if "[" in prefix
                         else f"in [{prefix}]")
                raise self.err(where, f"unknown key {scope}; allowed: {', '.join(allowed)}{hint}")

    def int_(self, value: Any, key: str, minimum: int, maximum: int | None = None) -> int:
        allowed = f">= {minimum}" if maximum is None else f"in [{minimum}, {maximum}]"
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise self.err(key, f"expected an integer {allowed}, got {value!r}")
        if value < minimum or (maximum is not None and value > maximum):
            raise self.err(key, f"must be an integer {allowed}, got {value}")
        return int(value)

    def float_(self, value: Any, key: str, lo: float, hi: float, *, lo_open: bool, hi_open: bool,
               unit: str = "") -> float:
        rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.err(key, f"expected a number in {rng}{unit}, got {value!r}")
        v = float(value)
        ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
        if not ok:
            raise self.err(key, f"must be in {rng}{unit}, got {value!r}")
        return v

    def bool_(self, value: Any, key: str) -> bool:
        if not isinstance(value, bool):
            raise self.err(key, f"expected true or false, got {value!r}")
        return value

    def str_(self, value: Any, key: str) -> str:
        if not isinstance(value, str) or not value.strip():
            raise self.err(key, f"expected a non-empty string, got {value!r}")
        return value

    def path(self, value: Any, key: str) -> Path:
        text = self.str_(value, key)
        p = Path(text).expanduser()
        return Path(os.path.normpath(p if p.is_absolute() else self.base / p))

    def array_of_tables(self, value: Any, key: str, example: str) -> list[Mapping[str, Any]]:
        if isinstance(value, Mapping) or not isinstance(value, (list, tuple)):
            raise self.err(key, f"expected an array of tables ({example}), got {type(value).__name__}")
        if not value:
            raise self.err(key, f"needs at least one entry ({example})")
        return [self.table(v, f"{key}[{i}]", example) for i, v in enumerate(value)]

    # -- tables -------------------------------------------------------------------------------

    def campaign(self, data: Any) -> CampaignConfig:
        data = self.table(data, "(top level)", "a campaign file")
        allowed = _TOP_KEYS + (("source",) if isinstance(data.get("source"), str) else ())
        self.keys(data, allowed, "")
        if "campaign" not in data:
            raise self.err("campaign", "missing [campaign] table (name, images_per_ct required)")
        c = self.table(data["campaign"], "campaign", "[campaign] with name, images_per_ct")
        self.keys(c, _CAMPAIGN_KEYS, "campaign")
        for req in ("name", "images_per_ct"):
            if req not in c:
                raise self.err(f"campaign.{req}", "required key is missing")
        name = self.str_(c["name"], "campaign.name")
        if "/" in name or "\\" in name:
            raise self.err("campaign.name", f"must not contain path separators, got {name!r}")
        seed = self.int_(c.get("seed", 0), "campaign.seed", 0, MAX_SEED)
        images = self.int_(c["images_per_ct"], "campaign.images_per_ct", 1, MAX_IMAGES_PER_CT)
        shard = self.int_(c.get("shard_size", 256), "campaign.shard_size", 1, MAX_SHARD_SIZE)

        scene = self.scene(data.get("scene", {}))
        physics = self.physics(data.get("physics", [{"name": "line", "level": "line"}]))
        try:
            poses = PoseDistribution.from_dict(self.table(data.get("poses", {}), "poses", "[poses]"), "poses",
                                               ORIGINAL_PROTOCOL)
        except PoseDistributionError as e:
            raise CampaignConfigError(f"{self.source}: {e}") from None
        split = self.split(data.get("split"))
        if "cts" not in data:
            raise self.err("cts", "at least one [[cts]] entry with a path is required")
        cts = self.cts(data["cts"])
        if any(e.label_materials for e in cts) and not any(p.level in ("poly", "full") for p in physics):
            i = next(i for i, e in enumerate(cts) if e.label_materials)
            raise self.err(f"cts[{i}].label_materials", "only poly and full physics entries use materials; "
                                                       "this campaign has none")
        vp = self.virtual_patients(data.get("virtual_patients", {}))
        outputs = self.outputs(data.get("outputs", {}))
        self.work_limits(images, shard, scene.size, len(physics), cts, outputs)
        return CampaignConfig(name=name, seed=seed, images_per_ct=images, shard_size=shard, scene=scene,
                              physics=physics, poses=poses, split=split, cts=cts, virtual_patients=vp,
                              outputs=outputs, source=self.source)

    def work_limits(self, images: int, shard: int, size: tuple[int, int], n_physics: int,
                    cts: Sequence[CTEntry], outputs: OutputConfig) -> None:
        """Refuse a campaign whose shard count or shard size would exhaust memory."""
        subjects = sum(1 + c.virtual_patients for c in cts)
        n_shards = subjects * math.ceil(images / shard)
        if n_shards > MAX_SHARDS:
            raise self.err("campaign.shard_size", f"{subjects} subjects x {math.ceil(images / shard)} shards each "
                                                  f"= {n_shards} shard files, more than {MAX_SHARDS}; raise shard_size")
        per_image = size[0] * size[1] * (4 * n_physics + (1 if outputs.bone_mask else 0))
        nbytes = min(shard, images) * per_image
        if nbytes > MAX_SHARD_BYTES:
            raise self.err("campaign.shard_size", f"a shard of {min(shard, images)} images of {size[0]} x {size[1]} "
                                                  f"pixels x {n_physics} physics entries holds {nbytes / 2**30:.1f} GiB; "
                                                  f"at most {MAX_SHARD_BYTES / 2**30:g} GiB: lower shard_size to at "
                                                  f"most {MAX_SHARD_BYTES // per_image}")

    def scene(self, value: Any) -> SceneConfig:
        t = self.table(value, "scene", "[scene] with name, size")
        self.keys(t, _SCENE_KEYS, "scene")
        raw = self.str_(t.get("name", DEFAULT_SCENE), "scene.name")
        size_raw = t.get("size", [128, 128])
        if isinstance(size_raw, (str, bytes, Mapping)) or not isinstance(size_raw, (list, tuple)) or len(size_raw) != 2:
            raise self.err("scene.size", f"expected [rows, cols] (2 integers >= 1), got {size_raw!r}")
        size = (self.int_(size_raw[0], "scene.size[0]", 1, MAX_IMAGE_SIDE),
                self.int_(size_raw[1], "scene.size[1]", 1, MAX_IMAGE_SIDE))
        from scenes import available

        if raw.lower().endswith(".xml") or "/" in raw or "\\" in raw:
            p = self.path(raw, "scene.name")
            name = str(p)
            if not p.is_file():
                if self.check_files:
                    raise self.err("scene.name", f"scene file {p} not found (a shipped scene name or an XML "
                                                 f"path; shipped: {', '.join(available())})")
                return SceneConfig(name, size)
        else:
            name = raw
            if raw not in available():
                close = difflib.get_close_matches(raw, available(), n=1, cutoff=0.6)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise self.err("scene.name", f"unknown scene {raw!r}; shipped scenes: {', '.join(available())} "
                                             f"(or the path of a scene .xml file){hint}")
        try:
            sc = load_scene(name)
        except SceneError as e:
            raise self.err("scene.name", str(e)) from None
        try:
            sc.geometry_at(*size)
        except (SceneError, ValueError) as e:
            raise self.err("scene.size", str(e)) from None
        return SceneConfig(name, size)

    def physics(self, value: Any) -> tuple[PhysicsConfig, ...]:
        entries = self.array_of_tables(value, "physics", "[[physics]] with name, level")
        out: list[PhysicsConfig] = []
        seen: dict[str, int] = {}
        for i, t in enumerate(entries):
            key = f"physics[{i}]"
            for k in t:
                if k in FORMER_NAMES:
                    new = SETTINGS[FORMER_NAMES[k]]
                    raise self.err(f"{key}.{k}", f"unknown key: the setting is spelled {new.name!r} (one name "
                                                 f"for the campaign key, PhysicsSettings.{new.name} and {new.flag})")
            self.keys(t, _PHYSICS_KEYS, key)
            level = t.get("level", "line")
            if level not in PHYSICS_LEVELS:
                raise self.err(f"{key}.level", f"unknown level {level!r}; allowed: {', '.join(PHYSICS_LEVELS)}")
            name = t.get("name", level)
            if not isinstance(name, str) or not _PHYSICS_NAME.fullmatch(name):
                raise self.err(f"{key}.name", f"expected lower-case letters, digits and '_' ([a-z0-9_]+), got {name!r}")
            if name in seen:
                raise self.err(f"{key}.name", f"duplicate physics name {name!r} (also physics[{seen[name]}]); "
                                              "names must be unique (they key the image datasets)")
            seen[name] = i
            ray = t.get("ray_model", "siddon")
            if ray not in RAY_MODELS:
                raise self.err(f"{key}.ray_model", f"unknown ray model {ray!r}; allowed: {', '.join(RAY_MODELS)}")
            step = self.float_(t.get("step_fraction", 0.5), f"{key}.step_fraction", STEP_FRACTION.lo,
                               STEP_FRACTION.hi, lo_open=False, hi_open=False)
            mu = self.float_(t.get("mu_water_per_mm", MU_WATER_60KEV_PER_MM), f"{key}.mu_water_per_mm", 0.0,
                             math.inf, lo_open=True, hi_open=True, unit=" 1/mm")
            outside = sorted(s.name for s in campaign_settings() if s.name in t and level not in s.levels)
            if outside:
                levels = " or ".join(f'"{lv}"' for lv in SETTINGS[outside[0]].levels)
                raise self.err(f"{key}.{outside[0]}", f"only for level = {levels} (this entry is {level!r})")
            extra = {}
            for s in campaign_settings():
                if s.name in t:
                    try:
                        extra[s.name] = s.check(t[s.name], f"{key}.{s.name}")
                    except PhysicsError as e:
                        raise CampaignConfigError(f"{self.source}: {e}") from None
            entry = PhysicsConfig(name, level, ray, step, mu, **extra)
            if level in ("poly", "full"):
                try:
                    entry.settings()  # the physics' own checks (e.g. bins <= 1000, scatter settings)
                except PhysicsError as e:
                    raise self.err(key, str(e)) from None
            out.append(entry)
        return tuple(out)

    def split(self, value: Any) -> SplitConfig:
        if value is None:
            return SplitConfig(**DEFAULT_SPLIT)
        t = self.table(value, "split", "[split] with train, val, test")
        self.keys(t, SPLIT_NAMES, "split")
        fr = {s: self.float_(t.get(s, 0.0), f"split.{s}", 0.0, 1.0, lo_open=False, hi_open=False)
              for s in SPLIT_NAMES}
        total = sum(fr.values())
        if abs(total - 1.0) > SPLIT_SUM_TOL:
            given = ", ".join(f"{s} = {fr[s]:g}" for s in SPLIT_NAMES)
            raise self.err("split", f"fractions must sum to 1 (within {SPLIT_SUM_TOL:g}), got {given} "
                                    f"(sum {total!r}); a missing fraction counts as 0")
        return SplitConfig(**fr)

    def cts(self, value: Any) -> tuple[CTEntry, ...]:
        entries = self.array_of_tables(value, "cts", "[[cts]] with path")
        out: list[CTEntry] = []
        seen: dict[str, int] = {}
        for i, t in enumerate(entries):
            key = f"cts[{i}]"
            self.keys(t, _CT_KEYS, key)
            if "path" not in t:
                raise self.err(f"{key}.path", "required key is missing (a NIfTI file, a DICOM folder or "
                                              "'phantom:SEED')")
            raw = self.str_(t["path"], f"{key}.path")
            phantom = raw == "phantom" or raw.startswith("phantom:")
            if phantom:
                seed_text = raw.partition(":")[2] or "0"
                if not re.fullmatch(r"\d+", seed_text.strip()):
                    raise self.err(f"{key}.path", f"{raw!r}: the phantom seed must be an integer >= 0 "
                                                  "('phantom:SEED')")
                path = f"phantom:{int(seed_text)}"
            else:
                p = self.path(raw, f"{key}.path")
                path = str(p)
                if self.check_files:
                    if not p.exists():
                        raise self.err(f"{key}.path", f"CT not found: {p} (from {raw!r}; relative paths are "
                                                      f"taken against {self.base})")
                    if p.is_file() and not p.name.lower().endswith(_NIFTI_SUFFIXES):
                        raise self.err(f"{key}.path", f"{p}: expected a NIfTI file (.nii, .nii.gz), a DICOM "
                                                      "series folder or 'phantom:SEED'")
            if path in seen:
                raise self.err(f"{key}.path", f"{path} is also cts[{seen[path]}]; each CT may appear once "
                                              "(else it could land in two splits)")
            seen[path] = i
            label_map = None
            if t.get("label_map") is not None:
                if phantom:
                    raise self.err(f"{key}.label_map", "the built-in phantom has its own labels; remove label_map")
                lp = self.path(t["label_map"], f"{key}.label_map")
                if self.check_files and not lp.exists():
                    raise self.err(f"{key}.label_map", f"label map not found: {lp} (from {t['label_map']!r})")
                label_map = str(lp)
            label_materials: tuple[tuple[int, str], ...] = ()
            if t.get("label_materials") is not None:
                lk = f"{key}.label_materials"
                lm = self.table(t["label_materials"], lk, '{ 3 = "titanium" }')
                if label_map is None and not phantom:
                    raise self.err(lk, "needs a label_map (the labels it refers to)")

                try:
                    parsed = parse_label_materials([f"{k}:{v}" for k, v in lm.items()])
                except MaterialError as e:
                    raise self.err(lk, str(e)) from None
                label_materials = tuple(sorted(parsed.items()))
            center = None
            if t.get("center") is not None:
                c = t["center"]
                if isinstance(c, (str, bytes, Mapping)) or not isinstance(c, (list, tuple)) or len(c) != 3:
                    raise self.err(f"{key}.center", f"expected [x, y, z] in LPS mm (3 numbers), got {c!r}")
                center = tuple(self.float_(v, f"{key}.center[{k}]", -MAX_CENTER_MM, MAX_CENTER_MM, lo_open=False,
                                           hi_open=False, unit=" mm") for k, v in enumerate(c))
            split = t.get("split")
            if split is not None and split not in SPLIT_NAMES:
                close = difflib.get_close_matches(str(split), SPLIT_NAMES, n=1, cutoff=0.6)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise self.err(f"{key}.split", f"unknown split {split!r}; allowed: {', '.join(SPLIT_NAMES)}{hint}")
            vp = self.int_(t.get("virtual_patients", 0), f"{key}.virtual_patients", 0, MAX_VIRTUAL_PATIENTS)
            held: list[tuple[str, int]] = []
            if t.get("held_out_virtual_patients") is not None:
                hk = f"{key}.held_out_virtual_patients"
                h = self.table(t["held_out_virtual_patients"], hk, "{ val = 4 }")
                for name in h:
                    if name not in SPLIT_NAMES:
                        raise self.err(f"{hk}.{name}", f"unknown split; allowed: {', '.join(SPLIT_NAMES)}")
                    held.append((name, self.int_(h[name], f"{hk}.{name}", 1)))
                if sum(n for _, n in held) > vp:
                    raise self.err(hk, f"holds out {sum(n for _, n in held)} virtual patients but the CT has "
                                       f"virtual_patients = {vp}")
            out.append(CTEntry(path, label_map, center, split, vp, tuple(held), label_materials))
        return tuple(out)

    def virtual_patients(self, value: Any) -> dict:
        t = self.table(value, "virtual_patients", "[virtual_patients] with sampling ranges")
        try:
            raw = json.loads(json.dumps(t, allow_nan=False))
        except (TypeError, ValueError) as e:
            raise self.err("virtual_patients",
                           f"values must be numbers, strings, booleans, arrays or tables ({e})") from None
        if raw:
            try:
                from sim.ct.patients import VirtualPatientRanges  # guarded: the ranges are checked where the module imports
            except ImportError as e:
                raise self.err("virtual_patients",
                               f"cannot check the ranges: sim.ct.patients is not importable ({e})") from None
            self.keys(raw, [f.name for f in fields(VirtualPatientRanges)], "virtual_patients")
            try:
                VirtualPatientRanges.from_dict(copy.deepcopy(raw))
            except (ValueError, TypeError, KeyError) as e:
                raise self.err("virtual_patients", str(e)) from None
        return raw

    def outputs(self, value: Any) -> OutputConfig:
        t = self.table(value, "outputs", "[outputs] with bone_mask, projected_center")
        self.keys(t, _OUTPUT_KEYS, "outputs")
        return OutputConfig(
            bone_mask=self.bool_(t.get("bone_mask", False), "outputs.bone_mask"),
            projected_center=self.bool_(t.get("projected_center", True), "outputs.projected_center"),
        )
