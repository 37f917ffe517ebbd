"""Realistic C-arm frames simulated at a known pose: detector signal, collimator, display chain, DICOM.

The one simulator of the frames that the demo (:mod:`register.evaluation.demo`), the study's
``xray`` targets (:mod:`register.evaluation.study`) and the collimated-against-open study
(:mod:`register.evaluation.xray_study`) register: an :class:`sim.physics.imaging.XRayImager`'s
detector signal (full physics: spectrum, materials, CsI detector, scatter, noise), a
:class:`sim.physics.display.Collimator` (or an open field) and a
:class:`sim.physics.display.DisplayChain`, written as DICOM with its geometry tags
(``DistanceSourceToDetector``, ``DistanceSourceToPatient``, ``ImagerPixelSpacing``), Modality RF and
the chain's bits: a frame as a C-arm delivers it. After the imager, a frame goes through the imaging
chain every realistic image of the project goes through (:func:`sim.physics.chain.apply_chain`:
collimation and display; its scatter and noise are the imager's own). With ``tools`` each frame also shows metal tools
fixed to the patient (:func:`sim.distractors.implanted_tools`: screws, K-wires, plates,
retractors around the anatomy centre), a new arrangement per frame seed.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from register.xray.io import write_xray_dicom
from sim.distractors import implanted_tools
from sim.distractors import imager_with_distractors

__all__ = ["FrameSimulator"]

#: The random stream of a frame's tools (beside its noise and Monte Carlo, which use the seed itself).
_TOOLS_STREAM = 7
#: Bumped when :func:`sim.distractors.implanted_tools` draws differently (cached frames are redone).
_TOOLS_VERSION = 1


class FrameSimulator:
    """Frames of one imager through one display chain, collimated by ``collimator`` (None: open).

    ``imager``: the :class:`sim.physics.imaging.XRayImager`; ``chain``: the
    :class:`sim.physics.display.DisplayChain`; ``geometry``: the geometry written into the DICOM
    tags (default the imager's); ``tools``: ``(low, high)`` metal tools fixed to the patient in
    every frame (None: none; :func:`sim.distractors.implanted_tools`), their kinds, sizes, places
    and orientations drawn from the frame's seed."""

    def __init__(self, imager, chain, collimator=None, *, geometry=None, tools: tuple[int, int] | None = None):
        self.imager = imager
        self.chain = chain
        self.collimator = collimator
        self.geometry = imager.geometry if geometry is None else geometry
        self.tools = None if tools is None else (int(tools[0]), int(tools[1]))

    def implants(self, seed: int) -> list:
        """The :class:`sim.distractors.Distractor` s of the frame of ``seed`` (empty without ``tools``)."""
        if self.tools is None:
            return []

        rng = np.random.default_rng([int(seed), _TOOLS_STREAM])
        return implanted_tools(rng, self.imager.renderer.center_lps, tools=self.tools)

    def raw(self, pose: np.ndarray, seed: int) -> np.ndarray:
        """The detector signal ``(H, W)`` float64 at ``pose`` ``(4, 4)``, its noise and Monte Carlo
        drawn from ``seed`` (and its tools, with ``tools``)."""
        imager = self.imager
        if self.tools is not None:
            imager = imager_with_distractors(imager, self.implants(seed))
        return imager.render(pose, seed=seed)["raw"][0].astype(np.float64)

    def display(self, raw: np.ndarray, *, collimated: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """The displayed frame ``(H, W)`` uint16 of ``raw`` ``(H, W)`` and its field mask (None: open):
        through the collimator (unless ``collimated`` is False or there is none), then the display
        chain, by the imaging chain (:func:`sim.physics.chain.apply_chain`, a batch of one in float64;
        no scatter or electronic noise of its own: the imager's signal holds them)."""
        import torch  # slow to import: only where frames are simulated

        from sim.physics.chain import apply_chain  # loads torch (above)

        collimator = self.collimator if collimated else None
        h, w = raw.shape
        field = None if collimator is None else collimator.mask(h, w)
        p = {**self.chain.tensors(1, dtype=torch.float64), "scatter": torch.zeros(1, dtype=torch.int64),
             "field_transmission": torch.full((1,), 1.0 if collimator is None else collimator.transmission,
                                              dtype=torch.float64)}
        mask = np.ones((h, w), bool) if field is None else field
        pixels, _ = apply_chain(torch.from_numpy(np.asarray(raw, np.float64))[None], float(self.imager.flat), p,
                                field=torch.from_numpy(mask)[None])
        return pixels[0].numpy().astype(np.uint16), field

    def write(self, path: str | Path, pixels: np.ndarray) -> Path:
        """``pixels`` as DICOM at ``path`` (RF, the chain's bits, the geometry's tags)."""
        g = self.geometry
        return write_xray_dicom(path, pixels, pixel_spacing_mm=g.pixel_spacing_mm, sdd_mm=g.sdd_mm, sod_mm=g.sod_mm,
                                bits_stored=min(16, max(8, self.chain.bits)), modality="RF")

    def simulate(self, path: str | Path, pose: np.ndarray, seed: int) -> Path:
        """Render, display and write one frame at ``pose`` (``(4, 4)``) to ``path``; returns the path."""
        pixels, _ = self.display(self.raw(pose, seed))
        return self.write(path, pixels)

    def fingerprint(self, pose: np.ndarray, seed: int) -> str:
        """A hex digest of everything that makes the frame at ``pose`` ``(4, 4)`` (mm) and ``seed``:
        the imager's physics and Monte Carlo settings, the display chain, the collimator, the
        geometry, the pose and the seed."""
        mc = self.imager.scatter
        what = {"physics": self.imager.record(), "monte_carlo": None if mc is None else repr(mc.settings),
                "chain": repr(self.chain), "collimator": repr(self.collimator), "geometry": repr(self.geometry),
                **({"tools": list(self.tools), "tools_version": _TOOLS_VERSION} if self.tools is not None else {}),
                "pose": np.asarray(pose, dtype=np.float64).round(9).tolist(), "seed": int(seed)}
        return hashlib.sha256(json.dumps(what, sort_keys=True, default=repr).encode()).hexdigest()

    def cached(self, path: str | Path, pose: np.ndarray, seed: int) -> Path:
        """The frame at ``path``, simulated (:meth:`simulate`) unless ``path`` holds this very frame:
        its stamp ``path + ".sim"`` records the :meth:`fingerprint` it was made with, so a frame
        cached before a change of the simulator, the settings or the pose is made again."""
        path = Path(path)
        stamp = path.with_name(path.name + ".sim")
        key = self.fingerprint(pose, seed)
        if path.exists() and stamp.exists() and stamp.read_text().strip() == key:
            return path
        self.simulate(path, pose, seed)
        tmp = stamp.with_name(stamp.name + ".tmp")
        tmp.write_text(key + "\n")
        tmp.replace(stamp)
        return path
