"""Training pairs rendered on the fly from a campaign file: unlimited pairs, near pairs included.

A campaign folder (:mod:`learn.data`) holds a fixed set of images, so its pairs are drawn from
one pose distribution: two independent poses of the original protocol are on average ~45 deg
and ~120 mm apart, and pairs closer than a few degrees, the ones that decide where the
registration iteration comes to rest, are rare. Rendering is cheap here (a 128 x 128 DRR of the
3 mm pelvis CT takes about 1 ms in a batch), so :class:`OnlinePairs` renders every batch
from the campaign *file* instead: the same subjects (CTs and their virtual patients, the same
seeds, so the same anatomies as ``ctxreg simulate``), the same scene and image size, the first
physics entry (or the named ones: targets and currents may differ), and pairs drawn as follows (all angles in degrees, lengths in mm):

* target pose ``T_A``: from the campaign's pose distribution ``[poses]``;
* current pose ``T_B``: with probability ``1 - near.fraction`` an independent draw from the
  same distribution (far pairs, as in the original); otherwise a *near* pair
  ``T_B = T_A o Exp(delta)`` (:func:`learn.labels.apply_update`, rotation about the anatomy
  centre) whose rotation part has a uniformly random axis and an angle log-uniform in
  ``near.rot_deg``, and whose translation part has a uniformly random direction and a length
  log-uniform in ``near.trans_mm``.

Every draw of batch ``k`` comes from ``SeedSequence(seed, spawn_key=(40, k))``: a batch is a
function of the seed and its index only, so a resumed training run takes the same steps.

**Realistic targets** (``randomization=``, :class:`RealisticTargets`): each pair's target is an
X-ray as a C-arm would deliver it, drawn per pair by :mod:`sim.randomize` (tube, filtration,
exposure, blur, kernel scatter, tools, collimator, display chain, bit depth), then made ready
as registration makes a user's X-ray ready (:func:`prepare_like_registration`): bone bright,
cropped to the collimated field (the current image with it, as registration renders its moving
images for the cropped detector), normalised over the field, the outside filled neutrally. A
draw with ``ideal`` true gets the plain line DRR of the current images' physics as its target.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np
import torch

from learn.labels import LabelNormalizer, apply_update, geodesic_label
from sim.core.errors import InputError
from sim.randomize import DomainRandomization
from sim.physics.display import TONES, apply_tone, quantile_curve
from sim.prepare import crop_to_field, i0_percentile, invert, log_correct, masked_fill, normalize, percentile_bounds
from sim.core.seeds import KIND_BATCH, KIND_BATCH_NOISE  # batch k: (KIND_BATCH, k); its noise: (KIND_BATCH_NOISE, k, u[, 1])
from sim.core.seeds import rng_for
from sim.distractors import add_to_density_integrals
from sim.physics.materials import TISSUE_DECOMPOSITION
from sim.physics.poly import Detector, Polychromatic
from sim.physics.settings import PhysicsSettings
from sim.physics.spectrum import filtered_tube_spectrum
from sim.projection.geometry import pose_from_params
from sim.projection.scene import load_scene
from sim.randomize import ToolBank, apply_image, image_rng
from sim.campaign.runner import SubjectContext
from sim.projection.drr import DRRRenderer, RenderSettings


class OnlinePairsError(InputError):
    """Online pairs cannot be drawn; the message names the setting and the problem."""


def _range(value, name: str, unit: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise OnlinePairsError(f"{name} must be [low, high] in {unit}, got {value!r}") from None
    if not (0 < lo <= hi and math.isfinite(hi)):
        raise OnlinePairsError(f"{name} must satisfy 0 < low <= high ({unit}), got [{lo}, {hi}]")
    return lo, hi


@dataclass(frozen=True)
class NearPairs:
    """How often and how near the current pose is drawn around the target (see the module doc).

    Attributes:
        fraction: share of near pairs in [0, 1] (0: the original's independent pairs only).
        rot_deg: ``(low, high)`` deg, the log-uniform range of the rotation offset's angle.
        trans_mm: ``(low, high)`` mm, the log-uniform range of the translation offset's length.
    """

    fraction: float = 0.5
    rot_deg: tuple[float, float] = (0.5, 20.0)
    trans_mm: tuple[float, float] = (1.0, 40.0)

    def __post_init__(self) -> None:
        if not (isinstance(self.fraction, numbers.Real) and 0.0 <= self.fraction <= 1.0):
            raise OnlinePairsError(f"near fraction must be in [0, 1], got {self.fraction!r}")
        object.__setattr__(self, "rot_deg", _range(self.rot_deg, "near rot_deg", "deg"))
        object.__setattr__(self, "trans_mm", _range(self.trans_mm, "near trans_mm", "mm"))

    def offsets(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n, 6)`` offsets ``delta`` (rad, mm) with the module doc's distribution."""
        def directions():
            v = rng.standard_normal((n, 3))
            return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)

        def log_uniform(lo, hi):
            return np.exp(rng.uniform(math.log(lo), math.log(hi), n))

        rot = directions() * np.radians(log_uniform(*self.rot_deg))[:, None]
        trans = directions() * log_uniform(*self.trans_mm)[:, None]
        return np.concatenate([rot, trans], axis=1)


#: Tool materials given a (zero) density channel in every realistic target, so that one
#: :class:`sim.physics.poly.Polychromatic` per spectrum serves images with and without tools.
TOOL_MATERIALS = ("titanium", "stainless_steel", "carbon", "copper", "pvc")

#: Pair ``i`` of batch ``k`` is randomization index ``k * MAX_BATCH + i``.
MAX_BATCH = 1 << 16

#: What the network sees of a pair's current image outside the target's collimated field:
#: ``"masked"`` (filled with the field's mean, as the target: the edge is the same in both images)
#: or ``"open"`` (the whole current image: the anatomy around the field gives the context a
#: partial view lacks). A checkpoint records it (``config.current_field``); registration follows it.
CURRENT_FIELDS = ("masked", "open")


#: How a pair is framed for the network: ``"field"`` (cropped to the target's collimated field and
#: resampled to the network's size: the image scale and the CoordConv coordinates follow the field)
#: or ``"detector"`` (the whole detector, the outside of the field filled: scale and coordinates are
#: the detector's whatever the field). Batched pairs only (``train.framing``); registration frames
#: the X-ray as the checkpoint records (``register.xray.network_view.network_view``).
FRAMINGS = ("field", "detector")


def current_field_problem(value) -> str | None:
    """What is wrong with a ``current_field`` value (None when it is one of :data:`CURRENT_FIELDS`)."""
    return None if value in CURRENT_FIELDS else f"must be one of {', '.join(CURRENT_FIELDS)}, got {value!r}"


def _check_prepare_inputs(display, field, current, bone_dark, low_pct, high_pct, crop) -> tuple[float, float]:
    """:func:`prepare_like_registration`'s checks (:class:`OnlinePairsError`); the percentiles as floats."""
    where = "prepare_like_registration"
    batch = isinstance(display, torch.Tensor)
    want = "(B, H, W) tensor" if batch else "(H, W) array"
    for name, t in (("display", display), ("current", current)):
        kind = isinstance(t, torch.Tensor) if batch else isinstance(t, np.ndarray)
        ok = kind and t.ndim == (3 if batch else 2) and t.dtype != (torch.bool if batch else np.bool_) and (
            not t.is_complex() if batch else t.dtype.kind in "uif")
        if not ok:
            shape = tuple(t.shape) if hasattr(t, "shape") else type(t).__name__
            raise OnlinePairsError(f"{where}: {name} must be a real {want} (as display), got {shape}")
    if current.shape != display.shape:
        raise OnlinePairsError(f"{where}: current must have display's shape {tuple(display.shape)}, "
                               f"got {tuple(current.shape)}")
    fkind = isinstance(field, torch.Tensor) if batch else isinstance(field, np.ndarray)
    if not fkind or field.dtype != (torch.bool if batch else np.bool_) or field.shape != display.shape:
        got = f"{field.dtype} {tuple(field.shape)}" if hasattr(field, "shape") else type(field).__name__
        raise OnlinePairsError(f"{where}: field must be a bool {'tensor' if batch else 'array'} of display's shape "
                               f"{tuple(display.shape)}, got {got}")
    if batch and not isinstance(bone_dark, bool):
        b = display.shape[0]
        if not isinstance(bone_dark, torch.Tensor) or bone_dark.dtype != torch.bool or bone_dark.shape != (b,):
            got = (f"{bone_dark.dtype} {tuple(bone_dark.shape)}" if isinstance(bone_dark, torch.Tensor)
                   else type(bone_dark).__name__)
            raise OnlinePairsError(f"{where}: bone_dark must be a bool or a ({b},) bool tensor, got {got}")
    elif not batch and not isinstance(bone_dark, (bool, np.bool_)):
        raise OnlinePairsError(f"{where}: bone_dark must be a bool, got {bone_dark!r}")
    if not isinstance(crop, bool):
        raise OnlinePairsError(f"{where}: crop must be a bool, got {crop!r}")
    try:
        lo_q, hi_q = float(low_pct), float(high_pct)
    except (TypeError, ValueError):
        raise OnlinePairsError(f"{where}: low_pct and high_pct must be percentiles (%), got {low_pct!r}, "
                               f"{high_pct!r}") from None
    if not 0.0 <= lo_q < hi_q <= 100.0:
        raise OnlinePairsError(f"{where}: low_pct and high_pct must satisfy 0 <= low < high <= 100 (%), got "
                               f"{lo_q:g}, {hi_q:g}")
    holds = field.any(-1).any(-1)
    if not bool(holds.all()):
        if batch:
            empty = torch.nonzero(~holds).flatten().tolist()[:10]
            raise OnlinePairsError(f"{where}: the fields of pairs {empty} hold no pixel")
        raise OnlinePairsError(f"{where}: the field holds no pixel")
    return lo_q, hi_q


def prepare_like_registration(display, field, current, *, log_display, bone_dark, raw_intensity: bool = False,
                              low_pct: float = 1.0, high_pct: float = 99.0, i0_pct: float = 99.5,
                              mask_current: bool = True, tone: bool = False, crop: bool = True):
    """Displayed X-rays and the pairs' current images as the network meets them in registration.

    One pair in NumPy, or a batch of pairs in torch on the device of its inputs (each pair with its
    own field, log / linear and polarity, no Python loop over pairs): the steps are
    :mod:`sim.prepare`'s, written once for both.

    Args:
        display: ``(H, W)`` NumPy or ``(B, H, W)`` torch, the display chain's integers (any real
            dtype: :func:`sim.randomize.apply_image`'s or
            :func:`sim.physics.chain.apply_chain`'s image).
        field: bool of ``display``'s shape and kind, the collimated field (each pair's holding a pixel).
        current: the moving images (line integrals), ``display``'s shape and kind.
        log_display: the display chain's log (a bool, or ``(B,)`` bool for a batch), kept for the
            record and for ``raw_intensity``.
        bone_dark: the display shows bone dark (a bool, or ``(B,)`` bool for a batch).
        raw_intensity, tone: one NumPy pair only (below).
        low_pct, high_pct: the normalisation percentiles (%) over the field, ``0 <= low < high <= 100``.
        mask_current: fill the current images' pixels outside the field with their mean over it
            too (``current_field = "masked"``), as the targets'.
        crop: step 2 (crop to the field's box and resample, as registration does); False keeps the
            whole detector, the field masked (``train.framing = "detector"``): the image scale and
            CoordConv coordinates then stay the detector's whatever the field.

    Returns:
        ``(target, current)`` float32, ``display``'s shape and kind (a batch on its device).

    The steps are those of ``register.xray.prepare.prepare_xray`` and ``register.engines.contextual``
    with registration's decisions taken from the truth (the field, log or linear, the polarity):

    1. bone bright: a display shown bone dark is inverted (``max + min - x`` over the field), log
       or linear alike. Registration's intensity step decides the same for display-processed
       frames: it inverts a bone-dark frame and does not log-correct a windowed linear display
       (measured on 12-bit DICOM frames of the pelvis, 110 kV, gamma 1.2: steps ``[]`` for
       linear bone-bright, ``["invert"]`` for linear bone-dark). A NumPy pair with
       ``raw_intensity=True`` and a linear display is transmitted intensity instead:
       ``-ln(max(x, 1e-6 I0) / I0)`` with ``I0`` the ``i0_pct`` percentile over the field, as
       ``register.xray.preprocess.LogCorrect``;
    2. both images cropped to the field's bounding box and resampled to the image's size
       (:func:`sim.prepare.crop_to_field`; registration crops the X-ray to its field and renders
       the moving images for the cropped detector; the predictor resamples both to the network's size);
    3. the target normalised: the ``low_pct`` / ``high_pct`` percentiles over the field to 0 / 1,
       clipped (``register.xray.preprocess.Normalize``; all 0 where they are equal);
    4. the target's pixels outside the field set to the mean over the field
       (:func:`sim.prepare.masked_fill`), and the current image's too unless ``mask_current`` is
       False (a network trained with ``current_field = "open"`` sees the whole current image:
       the anatomy around the target's field, :data:`CURRENT_FIELDS`).

    With ``tone`` (``train.tone = "ct"``, a NumPy pair), between steps 1 and 2 a target that
    registration would read as a display image (everything but ``raw_intensity``) is mapped by
    rank onto the current image's line integrals inside the field
    (:func:`sim.physics.display.apply_tone`), as registration makes the toned version of a display
    image on the CT's DRRs around its start pose (``register.xray.intensity.tone_curve``; a network
    trained so is shown that version): the current image plays the reference, a view of the same
    CT at another pose. A batch refuses ``raw_intensity`` and ``tone``: a raw-intensity target is
    not a display image, and the tone maps each pair by rank (a per-pair sort and interpolation).

    A NumPy pair runs in float64; a batch in float64 where ``display`` or ``current`` is float64,
    else in float32. A cropped image is resampled in float32 (as ``F.interpolate``).
    """
    batch = isinstance(display, torch.Tensor)
    lo_q, hi_q = _check_prepare_inputs(display, field, current, bone_dark, low_pct, high_pct, crop)
    if batch:
        if raw_intensity or tone:
            raise OnlinePairsError("prepare_like_registration: a batch takes display images without the CT tone "
                                   "(raw_intensity=False, tone=False); prepare such pairs one at a time in NumPy")
        work = torch.float64 if torch.float64 in (display.dtype, current.dtype) else torch.float32
        x, cur, m = display.to(work), current.to(device=display.device, dtype=work), field.to(display.device)
    else:
        x, cur, m = np.asarray(display, np.float64), current, field
    if raw_intensity and not log_display:  # transmitted intensity (bone dark): log-correct, bone bright
        if not bone_dark:
            x = invert(x, m)[0]
        i0 = i0_percentile(x, m, i0_pct)
        x = log_correct(x, i0 if i0 > 0 else 1.0)
    else:
        x = invert(x, m, bone_dark)[0]
    if tone and not raw_intensity:
        x = apply_tone(x, m, quantile_curve(np.asarray(current, np.float64)[m]))
    x, cur, m = crop_to_field((x, cur), m, crop=crop)
    x = masked_fill(normalize(x, *percentile_bounds(x, m, lo_q, hi_q)), m)
    if mask_current:
        cur = masked_fill(cur, m)
    return (x.to(torch.float32), cur.to(torch.float32)) if batch else (x.astype(np.float32), cur.astype(np.float32))


def check_trainable(randomization) -> None:
    """Refuse (:class:`OnlinePairsError`) what online training cannot draw per pair: anything but a
    :class:`sim.randomize.DomainRandomization`, and a ``scatter`` that may be ``monte-carlo``."""
    if not isinstance(randomization, DomainRandomization):
        raise OnlinePairsError(f"randomization must be a DomainRandomization, got {type(randomization).__name__}")
    sc = randomization.by_name["scatter"]
    if dict(zip(sc.choices, sc.probs)).get("monte-carlo", 0.0) > 0:
        raise OnlinePairsError("randomize.scatter: online training cannot run a Monte Carlo transport per pair; "
                               "allow 'none', 'kernel' and 'sks' only (e.g. scatter = [\"none\", \"sks\"]): the "
                               "scatter-kernel model fitted to the Monte Carlo stands in for it")


class RealisticTargets:
    """Realistic target images of online pairs: domain randomization per pair (module doc).

    Args:
        randomization: the :class:`sim.randomize.DomainRandomization` (its ``scatter`` may not
            be ``monte-carlo``: a transport per pair is far too slow for training; the kernel
            scatter stands in for it).
        seed: the randomization seed (pair ``i`` of batch ``k`` is index ``k * MAX_BATCH + i``).
        geometry: the :class:`sim.projection.geometry.CArmGeometry` of the images; scene: its C-arm scene.

    ``image(L, index, gap_mm=None)``: density integrals ``(M, H, W)`` g/cm^2 of one pose over
    :data:`sim.physics.materials.TISSUE_DECOMPOSITION` -> ``(display (H, W) uint16, field (H, W) bool,
    draw)``: tools added where drawn (:class:`sim.randomize.ToolBank`), the drawn spectrum and
    detector (quantum noise, blur) applied, then the post-render stages
    (:func:`sim.randomize.apply_image`). spekpy runs once per kV (about 1 s each, 15 on the 5 kV
    grid); each filtration is applied to it by Beer-Lambert
    (:func:`sim.physics.spectrum.filtered_tube_spectrum`) and the model kept per (kV, filtration).
    """

    def __init__(self, randomization: DomainRandomization, seed: int, geometry, *, scene: str = "cios_fusion"):
        check_trainable(randomization)
        self.randomization = randomization
        self.seed = int(seed)
        self.geometry = geometry
        self.base = PhysicsSettings(level="poly", noise=True)
        self.names = tuple(TISSUE_DECOMPOSITION.names) + TOOL_MATERIALS
        self.bank = ToolBank(self.seed, geometry, scene=scene)
        self._models: dict[tuple, object] = {}

    def _model(self, physics):
        import copy

        key = (physics.kvp, tuple(physics.filters))
        if key not in self._models:
            spectrum = filtered_tube_spectrum(physics.kvp, anode_angle_deg=physics.anode_angle_deg, filters=physics.filters,
                                     bins=physics.bins)
            self._models[key] = Polychromatic(spectrum, Detector(physics.detector_mm, physics.detector_mode,
                                                                 physics.electronic_noise, 0.0), self.names)
        model = copy.copy(self._models[key])
        model.detector = Detector(physics.detector_mm, physics.detector_mode, physics.electronic_noise,
                                  physics.blur_mm)
        return model

    def image(self, L: np.ndarray, index: int, gap_mm: float | None = None):
        draw = self.randomization.draw(self.seed, index)
        physics = draw.physics_settings(self.base)
        m = len(self.names) - len(TOOL_MATERIALS)
        if L.ndim != 3 or L.shape[0] != m:
            raise OnlinePairsError(f"density integrals must be (M={m}, H, W), got {L.shape}")
        dens = np.zeros((1, len(self.names), *L.shape[1:]), np.float64)
        dens[0, :m] = L
        for bone in ("cancellous_bone", "cortical_bone"):  # randomize.bone_scale: bone's attenuation
            dens[0, self.names.index(bone)] *= float(draw["bone_scale"])
        tools = self.bank.for_draw(draw)
        if tools is not None:
            chords, channels = tools
            dens, names = add_to_density_integrals(dens, self.names, chords[None], channels)
            if names != self.names:  # a tool material outside TOOL_MATERIALS: a bug of the bank
                raise OnlinePairsError(f"tool materials {names[len(self.names):]} are not in TOOL_MATERIALS")
        model = self._model(physics)
        g = self.geometry
        exposure = dict(mas=physics.mas, sdd_mm=g.sdd_mm, pixel_area_mm2=g.pixel_spacing_mm ** 2)
        rng = image_rng(self.seed, index)
        raw = model.noisy(dens, rng, pixel_spacing_mm=g.pixel_spacing_mm, **exposure)[0]
        display, field = apply_image(raw, model.flat_field(**exposure), draw, rng, geometry=g, gap_mm=gap_mm)
        return display, field, draw


class OnlinePairs:
    """Batches of (target, current, label) rendered from a campaign's subjects of one split.

    Args:
        cfg: a :class:`sim.campaign.config.CampaignConfig` (``load_campaign(path)``).
        split: ``"train"``, ``"val"`` or ``"test"``; only that split's subjects are used.
        near: :class:`NearPairs` (default: half near pairs).
        transform: a callable on ``(2 B, 1, H, W)`` float32 tensors (targets then currents).
        normalizer: label scaling (default :class:`LabelNormalizer()`).
        seed: batch ``k`` draws from ``SeedSequence(seed, spawn_key=(40, k))``.
        physics: name of the campaign's ``[[physics]]`` entry of the target images (default: the
            first entry).
        current_physics: name of the entry of the current images (default: as the targets). With
            two entries, e.g. ``full`` targets (scatter, noise) and noise-free ``poly`` currents,
            the pairs look like a registration's: a realistic X-ray against moving images.
        subjects_per_batch: draw each batch's pairs from this many distinct subjects (uniformly
            among them) instead of a subject per pair (default None). Rendering costs a fixed
            amount per subject and batch, a lot for ``full`` images (one Monte Carlo run per
            subject): 4 subjects instead of ~16 makes a 32-pair batch about 3x cheaper.
        randomization: a :class:`sim.randomize.DomainRandomization`: realistic targets
            (:class:`RealisticTargets`, module doc) drawn under ``seed``; the target physics entry
            is then unused (each pair draws its own), the currents are rendered with
            ``current_physics`` (default: the first entry). ``ideal`` draws are line DRRs of the
            target pose collimated as drawn (the field is geometry, not appearance).
        current_field: with ``randomization``: ``"masked"`` (default) or ``"open"``
            (:data:`CURRENT_FIELDS`): whether the current image is filled outside the target's
            field as the target is.
        tone: with ``randomization``: ``"ct"`` tones every target onto its current image's line
            integrals in the field (:func:`prepare_like_registration`), ``"off"`` (default) not.

    ``batch(k, n)`` returns ``target (n, 1, H, W)``, ``current (n, 1, H, W)`` float32 and the
    normalised label ``(n, 6)`` float32. Subjects are loaded (and virtual patients built) on first
    use and kept: about 6 MB of voxels per subject for the 3 mm pelvis CT.
    """

    def __init__(self, cfg, split: str, *, near: NearPairs | None = None, transform=None,
                 normalizer: LabelNormalizer | None = None, seed: int = 0, physics: str | None = None,
                 current_physics: str | None = None, subjects_per_batch: int | None = None,
                 randomization: DomainRandomization | None = None, current_field: str = "masked",
                 tone: str = "off"):
        if current_field_problem(current_field):
            raise OnlinePairsError(f"current_field {current_field_problem(current_field)}")
        if tone not in TONES:
            raise OnlinePairsError(f"tone must be one of {', '.join(TONES)}, got {tone!r}")
        self.current_field = current_field
        self.tone = tone
        self.cfg = cfg
        entries = {p.name: p for p in cfg.physics}
        for key, name in (("physics", physics), ("current_physics", current_physics)):
            if name is not None and name not in entries:
                raise OnlinePairsError(f"{key} {name!r} is not a physics entry of campaign {cfg.name!r} "
                                       f"(it has {sorted(entries)})")
        #: the campaign physics entries of the target and of the current images
        self.target_entry = entries[physics] if physics is not None else cfg.physics[0]
        self.current_entry = entries[current_physics] if current_physics is not None else self.target_entry
        self.split = split
        self.subjects = [s for s in cfg.subjects() if s.split == split]
        if not self.subjects:
            splits = sorted({s.split for s in cfg.subjects()})
            raise OnlinePairsError(f"campaign {cfg.name!r} has no subject in split {split!r} (it has {splits})")
        self.near = near if near is not None else NearPairs()
        if subjects_per_batch is not None and (isinstance(subjects_per_batch, bool)
                                               or not isinstance(subjects_per_batch, numbers.Integral)
                                               or not 1 <= subjects_per_batch <= len(self.subjects)):
            raise OnlinePairsError(f"subjects_per_batch must be an integer in [1, {len(self.subjects)}] (the "
                                   f"{split} subjects), got {subjects_per_batch!r}")
        self.subjects_per_batch = subjects_per_batch
        self.transform = transform
        self.normalizer = normalizer or LabelNormalizer()
        self.seed = int(seed)
        self._contexts: dict[int, object] = {}
        self.realistic = None
        self._density: dict[int, object] = {}
        if randomization is not None:
            h, w = cfg.scene.size
            self.realistic = RealisticTargets(randomization, self.seed, load_scene(cfg.scene.name).geometry_at(h, w),
                                              scene=cfg.scene.name)

    def context(self, k: int):
        """The :class:`sim.campaign.runner.SubjectContext` of this split's subject ``k`` (cached)."""
        if k not in self._contexts:
            self._contexts[k] = SubjectContext(self.cfg, self.subjects[k])
        return self._contexts[k]

    def density_renderer(self, k: int):
        """Density-integral renderer (:data:`sim.physics.materials.TISSUE_DECOMPOSITION`) of subject ``k`` (cached)."""
        if k not in self._density:
            ctx = self.context(k)
            self._density[k] = DRRRenderer(ctx.volume, RenderSettings(scene=self.cfg.scene.name,
                                                                      size=tuple(self.cfg.scene.size),
                                                                      quantity="density"),
                                           center_lps=ctx.center, materials=TISSUE_DECOMPOSITION)
        return self._density[k]

    def draw(self, k: int, n: int, *, near_flags: bool = False):
        """Batch ``k``'s draws: subject per pair ``(n,)``, ``T_A`` and ``T_B`` ``(n, 4, 4)`` (mm); with
        ``near_flags`` also which pairs are near pairs ``(n,)`` bool."""

        if n < 1:
            raise OnlinePairsError(f"batch size must be >= 1, got {n}")
        rng = rng_for(self.seed, KIND_BATCH, int(k))
        if self.subjects_per_batch is None:
            subject = rng.integers(0, len(self.subjects), n)
        else:
            chosen = rng.choice(len(self.subjects), self.subjects_per_batch, replace=False)
            subject = chosen[rng.integers(0, len(chosen), n)]

        sod = load_scene(self.cfg.scene.name).geometry.sod_mm  # the renderers' too (geometry_at keeps it)
        T_a = pose_from_params(self.cfg.poses.sample(rng, n), sod)
        T_b = pose_from_params(self.cfg.poses.sample(rng, n), sod)
        near = rng.random(n) < self.near.fraction
        delta = self.near.offsets(rng, n)
        if near.any():
            # T_B = T_A o Exp(delta): apply_update moves along -g, so pass g = -delta with step 1
            T_b[near] = apply_update(T_a[near], -delta[near], 1.0)
        return (subject, T_a, T_b, near) if near_flags else (subject, T_a, T_b)

    def batch(self, k: int, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Render batch ``k`` of ``n`` pairs; see the class doc for the shapes."""
        subject, T_a, T_b = self.draw(k, n)

        h, w = self.cfg.scene.size
        images = np.empty((2, n, h, w), np.float32)

        def render(entry, u, poses, stream):
            renderer = self.context(int(u)).renderers[entry.name]
            if entry.level in ("poly", "full"):  # fresh noise every batch, reproducible from (seed, k, u)
                key = (KIND_BATCH_NOISE, int(k), int(u)) + stream
                return renderer.render(poses, seed=int(rng_for(self.seed, *key).integers(2**63)))
            return renderer.render(poses)

        if self.realistic is not None:
            if n > MAX_BATCH:
                raise OnlinePairsError(f"batch size must be <= {MAX_BATCH} with realistic targets, got {n}")
            mask_current = self.current_field == "masked"
            toned = self.tone == "ct"
            for u in np.unique(subject):
                rows = np.flatnonzero(subject == u)
                draws = [self.realistic.randomization.draw(self.seed, int(k) * MAX_BATCH + int(i)) for i in rows]
                # density integrals for the realistic targets, line DRRs for the ideal ones; at[j]: the
                # row of pair j in its own stack
                real = [j for j, d in enumerate(draws) if not d["ideal"]]
                ideal_rows = [j for j, d in enumerate(draws) if d["ideal"]]
                at = {j: r for group in (real, ideal_rows) for r, j in enumerate(group)}
                L = self.density_renderer(int(u)).render(T_a[rows[real]]) if real else None
                ideal = render(self.current_entry, u, T_a[rows[ideal_rows]], (2,)) if ideal_rows else None
                current = render(self.current_entry, u, T_b[rows], (1,))
                for j, (i, draw) in enumerate(zip(rows, draws)):
                    if draw["ideal"]:  # a line DRR, collimated as drawn: the field is geometry, not appearance
                        col = draw.collimator(h, w)
                        field = np.ones((h, w), bool) if col is None else col.mask(h, w)
                        images[0, i], images[1, i] = prepare_like_registration(
                            ideal[at[j]], field, current[j], log_display=True, bone_dark=False,
                            mask_current=mask_current, tone=toned)
                        continue
                    gap = float(self.realistic.geometry.sdd_mm - T_a[i][2, 3])  # detector_gap_mm of the target
                    display, field, _ = self.realistic.image(L[at[j]], int(k) * MAX_BATCH + int(i), gap)
                    if draw["field_missed"] and draw["field"] != "none":  # shown as a field read as none
                        field = np.ones_like(field)
                    images[0, i], images[1, i] = prepare_like_registration(
                        display, field, current[j], log_display=bool(draw["log"]),
                        bone_dark=draw["polarity"] == "bone-dark", mask_current=mask_current, tone=toned)
        for u in () if self.realistic is not None else np.unique(subject):
            rows = np.flatnonzero(subject == u)
            if self.current_entry is self.target_entry:  # one launch for both images of the pairs
                out = render(self.target_entry, u, np.concatenate([T_a[rows], T_b[rows]]), ())
                images[0, rows], images[1, rows] = out[:len(rows)], out[len(rows):]
            else:
                images[0, rows] = render(self.target_entry, u, T_a[rows], ())
                images[1, rows] = render(self.current_entry, u, T_b[rows], (1,))
        x = torch.from_numpy(images.reshape(2 * n, 1, h, w))
        if self.transform is not None:
            x = self.transform(x)
        label = self.normalizer.normalize(geodesic_label(torch.from_numpy(T_a), torch.from_numpy(T_b)))
        return x[:n], x[n:], label.to(torch.float32)
