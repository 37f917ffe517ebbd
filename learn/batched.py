"""Realistic training pairs batched in torch: every stage of a pair on the training device.

:class:`learn.online.OnlinePairs` with realistic targets renders each pair's target through the
9-material density render and per-pair numpy post-processing: 19 pairs/s per core, and a GPU
waits for the CPU. :class:`BatchedPairs` draws the same kind of pairs (the campaign's subjects,
its pose distribution, near pairs, :mod:`sim.randomize`'s settings drawn per pair from
``(seed, index)``) with every image stage batched over the pairs in torch, on the CPU or CUDA:

1. the ray march of the targets and currents of every pair of every subject
   (:func:`sim.projection.raymarch.volumes_for`: Dr.Jit's Siddon kernel on a CPU, ``grid_sample`` on a GPU):
   ``mu`` for the currents and ideal targets (the line DRR registration renders), the water and
   bone basis densities of :mod:`sim.physics.two_basis` for the realistic targets;
2. the targets' polychromatic signal from the two basis line integrals and the tools' density
   integrals (:class:`sim.physics.two_basis.TorchImager`: the drawn spectrum, filtration,
   exposure and bone factor), the quantum noise of its variance in one normal draw, the
   detector's blur (:func:`sim.physics.chain.gaussian_reflect`);
3. collimator, scatter (the Gaussian ``kernel`` or the fitted scatter-kernel superposition
   ``sks`` of :mod:`sim.physics.scatter_kernel` at the pair's kV, grid and air gap, with its
   quantum noise), electronic noise and display chain
   (:func:`sim.physics.chain.apply_chain`, the imaging chain every realistic image goes through);
4. made ready as registration makes a user's X-ray ready
   (:func:`learn.online.prepare_like_registration`, batched).

``ideal`` draws take the line DRR of the target pose as their target, collimated as drawn; they
skip stages 1-3's realistic work (basis march, signal, noise, display), the rest of the batch
goes through it as one batch. The
currents are line DRRs of ``mu`` (the campaign's first physics entry must be a line entry, as
registration's moving images). Each pair's noise comes from a generator of its own
(:func:`sim.core.seeds.pair_normals`), so a pair is a function of ``(seed, batch, index)`` only: the same
in a batch of 1 or 256 (tested); a CPU and a GPU draw different noise of the same distribution.

What the two-basis model leaves out, against the per-pair path: nothing of the randomization
but the Monte Carlo scatter (refused there too); the physics error of the two bases is in
``docs/physics.md``. The ray march is trilinear (the per-pair path renders Siddon): the two
agree to the tolerance stated in ``tests/sim/test_raymarch.py``; on a CPU the Siddon kernel runs.
"""

from __future__ import annotations

import dataclasses
import zipfile
from pathlib import Path

import numpy as np
import torch

from learn.labels import LabelNormalizer, geodesic_label
from learn.online import FRAMINGS, MAX_BATCH, NearPairs, OnlinePairs, OnlinePairsError, check_trainable
from learn.online import prepare_like_registration
from sim.campaign.runner import subject_volume
from sim.core.seeds import pair_normals
from sim.physics.chain import apply_chain, field_masks, gaussian_reflect
from sim.physics.materials import mu_from_hu
from sim.physics.settings import SETTINGS
from sim.physics.two_basis import BasisDecomposition, SpectralTable, TOOL_CHANNELS, TorchImager
from sim.projection.geometry import pose_from_params
from sim.projection.raymarch import TorchVolumes, volumes_for
from sim.projection.scene import load_scene
from sim.randomize import TOOL_BANK_SIZE, ToolBank, draw_tensors
from sim.core.atomic import atomic_path
from sim.core.build_cache import cached
from sim.physics import PhysicsError
from sim.physics.scatter_kernel import detector_gap_mm

__all__ = ["BatchedPairs", "NOISE_STREAM_QUANTUM", "NOISE_STREAM_ELECTRONIC", "NOISE_STREAM_SCATTER", "tool_arrangements", "tool_looks"]

#: :func:`sim.core.seeds.pair_normals` streams of a pair's noise (the seed is the randomization seed).
NOISE_STREAM_QUANTUM = 1
NOISE_STREAM_ELECTRONIC = 2
NOISE_STREAM_SCATTER = 3

#: The code the spectral table and the tool bank are built by: part of their key in the build cache
#: (:mod:`sim.core.build_cache`), so that no run reads what older code built.
BUILT_BY = (str(Path(__file__).resolve().parents[1] / "sim"), str(Path(__file__).resolve().parent))


def tool_arrangements(bank, names: tuple[str, ...]) -> np.ndarray:
    """``(TOOL_BANK_SIZE, len(names), H, W)`` float32 density integrals (g/cm^2) of every
    arrangement of a :class:`sim.randomize.ToolBank`, one channel per material name (a tool
    material outside ``names`` is refused)."""

    out = []
    for j in range(TOOL_BANK_SIZE):
        chords, channels = bank.arrangement(j)  # (C, H, W) mm; ((material, g/cm^3), ...)
        dens = np.zeros((len(names),) + chords.shape[1:], np.float32)
        for c, (material, rho) in enumerate(channels):
            if material not in names:
                raise OnlinePairsError(f"tool material {material!r} has no channel (have {list(names)})")
            dens[names.index(material)] += chords[c] * float(rho) / 10.0  # mm x g/cm^3 -> g/cm^2
        out.append(dens)
    return np.stack(out)


def _write_tool_bank(arrangements: np.ndarray, path: Path) -> None:
    """Write :func:`tool_arrangements`'s array to ``path`` (compressed ``.npz``, atomically)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, density=arrangements)


def _read_tool_bank(path: Path, shape: tuple[int, int, int]) -> np.ndarray:
    """:func:`_write_tool_bank`'s array, refused in one line where damaged or of another ``shape``
    ``(channels, H, W)``."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrangements = np.asarray(z["density"], np.float32)
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise OnlinePairsError(f"tool bank {path} cannot be read ({e}): remove it to rebuild") from None
    if arrangements.ndim != 4 or arrangements.shape[1:] != tuple(shape):
        raise OnlinePairsError(f"tool bank {path} holds {arrangements.shape[1:]} (channels, rows, columns), this run "
                               f"needs {tuple(shape)}: remove it to rebuild")
    return arrangements


def tool_looks(arrangements: np.ndarray) -> torch.Tensor:
    """``(TOOL_BANK_SIZE * 8, K, H, W)``: each arrangement in its 8 looks, in the order of a draw's
    ``tools_pick`` (``int(pick * 16 * 8)``: arrangement ``// 8``, look ``% 8``; look bit 1 flips
    the rows, 2 the columns, 4 transposes a square image), as :meth:`sim.randomize.ToolBank.for_draw`."""
    looks = []
    for dens in arrangements:
        h, w = dens.shape[1:]
        for look in range(8):
            d = dens
            if look & 1:
                d = d[:, ::-1]
            if look & 2:
                d = d[:, :, ::-1]
            if look & 4 and h == w:
                d = d.transpose(0, 2, 1)
            looks.append(np.ascontiguousarray(d))
    return torch.from_numpy(np.stack(looks))


class BatchedPairs(OnlinePairs):
    """Batches of realistic (target, current, label) pairs, every stage in torch (module doc).

    Args:
        cfg, split, near, transform, normalizer, seed, subjects_per_batch, current_field: as
            :class:`learn.online.OnlinePairs` (its draws of subjects and poses are reused).
        randomization: the :class:`sim.randomize.DomainRandomization` (required; no Monte Carlo
            scatter).
        device: torch device of the rendering and the returned tensors (default CPU).
        tables: a folder for the cached spectral table and tool bank (``pair_tables.npz``,
            ``tool_bank_seed<seed>_<H>x<W>.npz``): built once where spekpy, xraylib and Mitsuba are at hand, then
            read on a machine without them (a GPU machine). None: no copy of the run's own. Either way
            a build goes through the machine's build cache (:mod:`sim.core.build_cache`).
        framing: ``"field"`` (default: both images cropped to the target's field and resampled, as
            registration shows them to the network today) or ``"detector"`` (the whole detector,
            the field masked; :data:`learn.online.FRAMINGS`).
        step_fraction: the trilinear ray march's step on a GPU, a fraction of the smallest voxel
            spacing (default 1: against Siddon it does as well as 0.5, ``tests/sim/test_raymarch.py``).
        log: called with a line where the spectral table or the tool bank is built (seconds of
            work once per machine) or the build cache refuses an entry (default: silence).

    ``batch(k, n)`` -> ``target (n, 1, H, W)``, ``current (n, 1, H, W)`` float32 on ``device``
    and the normalised label ``(n, 6)`` float32 on ``device``.
    """

    def __init__(self, cfg, split: str, *, randomization, near: NearPairs | None = None, transform=None,
                 normalizer: LabelNormalizer | None = None, seed: int = 0, subjects_per_batch: int | None = None,
                 current_field: str = "masked", device="cpu", tables=None, step_fraction: float = 1.0,
                 framing: str = "field", log=None):
        super().__init__(cfg, split, near=near, transform=transform, normalizer=normalizer, seed=seed,
                         subjects_per_batch=subjects_per_batch, current_field=current_field)
        if randomization is None:
            raise OnlinePairsError("batched pairs need a randomization (train.randomize)")
        check_trainable(randomization)
        if self.current_entry.level != "line":
            raise OnlinePairsError(f"batched pairs render line DRRs as current images: the campaign's physics entry "
                                   f"{self.current_entry.name!r} is {self.current_entry.level!r}")

        if framing not in FRAMINGS:
            raise OnlinePairsError(f"framing must be one of {', '.join(FRAMINGS)}, got {framing!r}")
        self.framing = framing
        self.randomization = randomization
        self.device = torch.device(device)
        self.tables = None if tables is None else Path(tables)
        self.step_fraction = step_fraction
        self.log = log or (lambda line: None)  # a line where the spectral table or tool bank is built

        h, w = cfg.scene.size
        self.geometry = load_scene(cfg.scene.name).geometry_at(h, w)
        self._volumes = None
        self._imager = None
        self._tools = None

    # -- built on first use --------------------------------------------------------------------
    def _build(self):
        table = self._table()
        basis = BasisDecomposition(matrix=table.basis)
        channels, affines, centers = [], [], []
        mu_water = self.current_entry.mu_water_per_mm
        for s in self.subjects:
            volume, center, _ = subject_volume(self.cfg, s)
            channels.append(np.concatenate([mu_from_hu(volume.hu, mu_water)[None], basis.partial_densities(volume.hu)]))
            affines.append(volume.affine)
            centers.append(center)
        self._volumes = volumes_for(self.device, channels, affines, centers, self.geometry,
                                    step_fraction=self.step_fraction, scene=self.cfg.scene.name)
        self._subject_arrays = ([c[:1] for c in channels], affines, centers)  # mu, for image_volumes
        self._imager = TorchImager(table, self.device)
        self._tools = self._tool_bank().to(self.device)

    def _table(self):
        path = None if self.tables is None else self.tables / "pair_tables.npz"
        if path is not None and path.exists():  # a draw outside it is refused by SpectralTable.index, naming the setting
            return SpectralTable.load(path)
        grid = SpectralTable.grid_for(self.randomization)

        def build():
            n = len(grid["kvp"]) * len(grid["al_mm"]) * len(grid["cu_mm"])
            self.log(f"building the pairs' spectral table ({n} tube settings: spekpy, xraylib), once on this machine "
                     f"(then from the build cache)")
            return SpectralTable.for_randomization(self.randomization)
        table = cached("pair_tables", grid, build=build, save=lambda t, entry: t.save(entry), load=SpectralTable.load,
                       errors=(PhysicsError,), code=BUILT_BY, log=self.log)
        if path is not None:  # the run's own copy: what it trained with, for a machine without spekpy
            path.parent.mkdir(parents=True, exist_ok=True)
            table.save(path)
        return table

    def _tool_bank(self) -> torch.Tensor:
        h, w = self.geometry.height, self.geometry.width
        path = None
        if self.tables is not None:
            path = self.tables / f"tool_bank_seed{self.seed}_{h}x{w}.npz"
            if path.exists():
                return tool_looks(_read_tool_bank(path, (len(TOOL_CHANNELS), h, w)))
        settings = {"seed": self.seed, "scene": self.cfg.scene.name, "channels": list(TOOL_CHANNELS),
                    "geometry": dataclasses.asdict(self.geometry)}

        def build():
            self.log(f"tracing the tool bank ({TOOL_BANK_SIZE} arrangements of metal tools at {h} x {w} px, seed "
                     f"{self.seed}: Mitsuba), once on this machine (then from the build cache)")
            return tool_arrangements(ToolBank(self.seed, self.geometry, scene=self.cfg.scene.name), TOOL_CHANNELS)
        arrangements = cached("tool_bank", settings, build=build, save=_write_tool_bank,
                              load=lambda entry: _read_tool_bank(entry, (len(TOOL_CHANNELS), h, w)),
                              errors=(OnlinePairsError,), code=BUILT_BY, log=self.log)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            _write_tool_bank(arrangements, path)
        return tool_looks(arrangements)

    def cache_tables(self) -> None:
        """Build the spectral table and this seed's tool bank into ``tables`` now (where spekpy,
        xraylib and Mitsuba are at hand), so that a machine without them can train from the cache."""
        if self.tables is None:
            raise OnlinePairsError("cache_tables needs a tables folder (BatchedPairs(..., tables=FOLDER))")
        self._table()
        self._tool_bank()

    def image_volumes(self, size: int, *, step_fraction: float = 1.0) -> TorchVolumes:
        """The subjects' ``mu`` (1/mm) as a :class:`sim.projection.raymarch.TorchVolumes` of
        ``size x size`` px line DRRs (the scene's detector binned to that size): the trilinear
        march, differentiable in the poses, on this source's device (the CPU too, where the pairs
        themselves come from Dr.Jit), for a loss on the image at a predicted pose
        (:class:`learn.image_term.ImageTerm`). Subject ``i`` is :attr:`subjects` ``[i]``."""
        if not (isinstance(size, int) and size >= 8):
            raise OnlinePairsError(f"image_volumes: size must be an integer >= 8 px, got {size!r}")
        self.prepare()
        mu, affines, centers = self._subject_arrays
        geometry = load_scene(self.cfg.scene.name).geometry_at(size, size)
        return TorchVolumes(mu, affines, centers, geometry, device=self.device, step_fraction=step_fraction)

    def prepare(self):
        """Build the subjects' volumes, the spectral table and the tool bank now (else on the first batch)."""
        if self._volumes is None:
            self._build()
        return self

    # -- pairs ---------------------------------------------------------------------------------
    #: The pair groups of :meth:`groups` (validation errors are logged per group).
    GROUPS = ("near", "far", "ideal", "log", "linear", "field", "open")

    def groups(self, k: int, n: int) -> dict[str, np.ndarray]:
        """Which pairs of batch ``k`` belong to each of :data:`GROUPS`, ``(n,)`` bool each: near or
        far (independent) current pose; ideal (a line-DRR target) or a realistic target on a log or
        a linear display; a collimated field or an open one."""
        _, _, _, near = self.draw(k, n, near_flags=True)
        draws = [self.randomization.draw(self.seed, int(k) * MAX_BATCH + i) for i in range(n)]
        ideal = np.array([bool(d["ideal"]) for d in draws])
        log = np.array([bool(d["log"]) for d in draws])
        field = np.array([d["field"] != "none" for d in draws])
        return {"near": near, "far": ~near, "ideal": ideal, "log": log & ~ideal, "linear": ~log & ~ideal,
                "field": field, "open": ~field}

    def drawn_tools(self, p) -> torch.Tensor:
        """``(R, K, H, W)`` the tools' density integrals (g/cm^2, one channel per
        :data:`sim.physics.two_basis.TOOL_CHANNELS` material) of draws with :func:`draw_tensors`
        entries ``p``: each draw's arrangement and look of the bank (``tools_pick``), zero where it
        draws no tools."""
        self.prepare()
        tools = self._tools[(p["tools_pick"].clamp(max=1 - 1e-7) * self._tools.shape[0]).long()]
        return tools * p["tools"].to(tools.dtype)[:, None, None, None]

    def _realistic(self, subject, poses, index, p, draws, tools=None, basis=None):
        """The displayed realistic targets ``(R, H, W)`` and their fields ``(R, H, W)`` bool of the
        pairs ``index`` ``(R,)`` (their subjects, target poses ``(R, 4, 4)``, :func:`draw_tensors`
        entries ``p`` and draws): the module doc's stages 1-3. ``tools`` ``(R, K, H, W)``: other tool
        density integrals than the draws' (:meth:`drawn_tools`); ``basis`` ``(R, 2, H, W)``: the
        anatomy's basis integrals (g/cm^2) when already marched."""

        g = self.geometry
        h, w = g.height, g.width
        if basis is None:  # water and bone: g/cm^3 mm -> g/cm^2
            basis = self._volumes.line_integrals(subject, poses, (1, 2)) / 10.0
        tools = self.drawn_tools(p) if tools is None else tools
        dens = torch.cat([basis, tools.to(basis.dtype)], dim=1)  # (R, 7, H, W)
        combo = torch.as_tensor(self._imager.table.index(*([d[k] for d in draws] for k in ("kvp", "al_mm", "cu_mm"))),
                                device=self.device)
        mean, var, flat = self._imager.signal(dens, combo, p["mas"], p["bone_scale"],
                                              pixel_area_mm2=g.pixel_spacing_mm ** 2, sdd_mm=g.sdd_mm)
        e_det = float(SETTINGS["electronic_noise"].default)
        raw = mean + torch.sqrt(var + e_det ** 2) * pair_normals(self.seed, index, NOISE_STREAM_QUANTUM, (h, w),
                                                                     device=self.device, dtype=mean.dtype)
        raw = gaussian_reflect(raw, p["blur_mm"].to(raw.dtype) / g.pixel_spacing_mm)
        raw = raw.clamp(min=0.0)
        normals = pair_normals(self.seed, index, NOISE_STREAM_ELECTRONIC, (h, w), device=self.device,
                                  dtype=raw.dtype)
        sks = p["scatter"] == 3
        scatter_normals = gaps = None
        if bool(sks.any()):  # the scatter-kernel model's quantum noise, and the targets' air gaps

            scatter_normals = pair_normals(self.seed, index, NOISE_STREAM_SCATTER, (2, h, w), device=self.device,
                                           dtype=raw.dtype)
            gaps = detector_gap_mm(poses, g)
        return apply_chain(raw, flat, p, normals, geometry=g, gap_mm=gaps, scatter_normals=scatter_normals)

    def batch(self, k: int, n: int):
        if n > MAX_BATCH:
            raise OnlinePairsError(f"batch size must be <= {MAX_BATCH}, got {n}")
        subject, t_a, t_b = self.draw(k, n)
        return self.pairs(subject, t_a, t_b, int(k) * MAX_BATCH + np.arange(n))

    def ap_batch(self, k: int, n: int):
        """Batch ``k``'s targets (the same subjects, poses, draws and noise as :meth:`batch`) with
        every current image at registration's start from AP (pose parameters zero,
        ``register.api.parse_init("ap")``): the pair kind ``ap`` of :mod:`learn.accuracy`, the far
        pairs every registration from AP begins with. Shapes as :meth:`batch`."""

        if n > MAX_BATCH:
            raise OnlinePairsError(f"batch size must be <= {MAX_BATCH}, got {n}")
        subject, t_a, _ = self.draw(k, n)
        t_b = pose_from_params(np.zeros((n, 6)), load_scene(self.cfg.scene.name).geometry.sod_mm)
        return self.pairs(subject, t_a, t_b, int(k) * MAX_BATCH + np.arange(n))

    def _checked_poses(self, where: str, subject, t_a, t_b, n: int):
        subject = np.asarray(subject, np.int64)
        t_a, t_b = np.asarray(t_a, np.float64), np.asarray(t_b, np.float64)
        if subject.shape != (n,) or t_a.shape != (n, 4, 4) or t_b.shape != (n, 4, 4):
            raise OnlinePairsError(f"{where}: subject (n,), t_a and t_b (n, 4, 4) for {n} pair numbers, got "
                                   f"{subject.shape}, {t_a.shape} and {t_b.shape}")
        if n and not (0 <= subject.min() and subject.max() < len(self.subjects)):
            raise OnlinePairsError(f"{where}: subject indices must lie in [0, {len(self.subjects)})")
        self.prepare()
        return subject, t_a, t_b

    def pairs(self, subject, t_a, t_b, index):
        """The pairs of given subjects and poses: ``subject`` ``(n,)`` indices into
        :attr:`subjects`, target poses ``t_a`` and current poses ``t_b`` ``(n, 4, 4)`` (mm),
        ``index`` ``(n,)`` the pairs' numbers (the randomization's draw and noise streams of pair
        ``i``: :meth:`batch` ``k`` uses ``k * MAX_BATCH + arange(n)``) -> as :meth:`batch`. Used
        by :meth:`batch` and to render the training's own pairs at chosen poses (the benchmarks)."""

        index = np.asarray(index, np.int64)
        n = len(index)
        subject, t_a, t_b = self._checked_poses("pairs", subject, t_a, t_b, n)
        draws = [self.randomization.draw(self.seed, int(i)) for i in index]
        p = draw_tensors(draws, device=self.device, dtype=torch.float32)
        g = self.geometry
        h, w = g.height, g.width
        ideal = p["ideal"].bool()
        ideal_rows = np.flatnonzero(ideal.cpu().numpy())
        real_rows = np.flatnonzero(~ideal.cpu().numpy())
        march = self._volumes.line_integrals
        current = march(subject, t_b, (0,))[:, 0]  # line DRRs of mu, as registration's moving images
        display = torch.empty_like(current)
        field = torch.empty(current.shape, dtype=torch.bool, device=self.device)
        if len(ideal_rows):  # the line DRR of the target pose, collimated as drawn
            rows = torch.as_tensor(ideal_rows, device=self.device)
            display[rows] = march(subject[ideal_rows], t_a[ideal_rows], (0,))[:, 0].to(display.dtype)
            field[rows] = field_masks({k: v[rows] for k, v in p.items()}, h, w)
        if len(real_rows):  # the realistic stages for the other pairs only
            rows = torch.as_tensor(real_rows, device=self.device)
            q = {k: v[rows] for k, v in p.items()}
            display[rows], field[rows] = self._realistic(subject[real_rows], t_a[real_rows], index[real_rows], q,
                                                         [draws[i] for i in real_rows])
        # a field registration missed (field_missed): the whole detector shown, the shadow or shutter
        # outside the field included, as registration shows a field read as none
        missed = p["field_missed"].bool() & (p["field_code"] != 0) & ~ideal
        if bool(missed.any()):
            field[missed] = True
        log_display = p["log"].bool() | ideal
        bone_dark = (p["polarity"] == 0) & ~ideal  # choice 0: "bone-dark"
        return self._prepared(display, field, current, log_display, bone_dark, t_a, t_b)

    def displayed_pairs(self, display, field, subject, t_a, t_b, *, log_display, bone_dark):
        """Pairs of given displayed targets with the training's current images and preparation:
        ``display`` ``(n, H, W)`` displayed X-rays at the campaign's image size (a display
        chain's values, e.g. a study's frames resampled to it), ``field`` ``(n, H, W)`` bool their
        collimated fields, ``subject``, ``t_a`` (the targets' true poses) and ``t_b`` as
        :meth:`pairs`, ``log_display`` and ``bone_dark`` ``(n,)`` bool (or one bool) their display's
        log and polarity -> as :meth:`batch`. What training would make of those images (the
        benchmarks compare it with registration's preparation of the same frames)."""
        n = len(display)
        subject, t_a, t_b = self._checked_poses("displayed_pairs", subject, t_a, t_b, n)
        h, w = self.geometry.height, self.geometry.width
        display = torch.as_tensor(display, device=self.device)
        field = torch.as_tensor(field, device=self.device)
        if display.shape != (n, h, w) or field.shape != (n, h, w) or field.dtype != torch.bool:
            raise OnlinePairsError(f"displayed_pairs: display and a bool field of shape {(n, h, w)} (the campaign's "
                                   f"image size), got {tuple(display.shape)} and {field.dtype} {tuple(field.shape)}")
        current = self._volumes.line_integrals(subject, t_b, (0,))[:, 0]
        return self._prepared(display.to(current.dtype), field, current, log_display, bone_dark, t_a, t_b)

    def _prepared(self, display, field, current, log_display, bone_dark, t_a, t_b):
        """Registration's preparation of the displayed targets and currents (``(n, H, W)`` each),
        the transform and the labels of ``t_a`` from ``t_b``: the returns of :meth:`batch`."""

        n = len(display)
        target, cur = prepare_like_registration(display, field, current, log_display=log_display, bone_dark=bone_dark,
                                                mask_current=self.current_field == "masked",
                                                crop=self.framing == "field")
        x = torch.cat([target, cur])[:, None].to(torch.float32)
        if self.transform is not None:
            x = self.transform(x)
        label = self.normalizer.normalize(geodesic_label(torch.from_numpy(t_a), torch.from_numpy(t_b)))
        return x[:n], x[n:], label.to(device=self.device, dtype=torch.float32)
