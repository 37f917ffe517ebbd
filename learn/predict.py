"""The trained network as a predictor of the geodesic gradient: the one place that turns image
pairs into ``g`` (rad, mm).

:class:`NetworkPredictor` loads a ``ctxreg train`` checkpoint (:mod:`learn.checkpoint`) and
predicts ``g = -2 log_{T_current}(T_target)`` (:func:`learn.labels.geodesic_label`: rotation in
rad first, then translation in mm) for one pair (``predictor(fixed, drr)``, the registration's
iteration, :mod:`register.engines.contextual`) or for many (:meth:`NetworkPredictor.predict`, batched;
``ctxreg accuracy``, :mod:`learn.accuracy`). Images of another size than the training images are
area-averaged to it first, then preprocessed as in training.
"""

from __future__ import annotations

import hashlib
from typing import NamedTuple

import numpy as np
from sim.physics.display import TONES
from learn.shipped import resolve_model
from sim.physics.filters import parse_filters

__all__ = ["NetworkPredictor", "Prediction"]


class Prediction(NamedTuple):
    """Predicted gradients of ``N`` pairs, float64, rad and mm, order ``(w, v)``."""

    g: np.ndarray  #: (N, 6) the weighted sum of the depths
    g_levels: np.ndarray  #: (N, 3, 6) each depth's estimate


class NetworkPredictor:
    """A trained pose-update network (``ctxreg train`` checkpoint) as a predictor of g (rad, mm).

    ``NetworkPredictor(path)`` reads the checkpoint (``path``: a file, or the name of a shipped
    model, :func:`learn.shipped.resolve_model`) (:func:`learn.checkpoint.load_checkpoint`:
    refused in one line if it is missing, damaged, foreign, pickles objects or holds NaN
    weights). ``predictor(fixed, drr)``: one pair ``(H, W)`` each -> ``g`` ``(6,)``;
    :meth:`predict`: ``(N, H, W)`` each -> :class:`Prediction`, in batches of :attr:`batch_size`
    pairs. The preprocessing and the backbone treat each image on its own (eval mode), so the
    target images' maps are kept from one call to the next while they do not change (the
    registration's iteration: one X-ray, a new DRR each step).

    Attributes:
        model: the :class:`learn.model.PoseUpdateNet`, eval mode.
        transform: the training preprocessing (:func:`learn.preprocess.build`).
        normalizer: :class:`learn.labels.LabelNormalizer` (network units -> rad, mm).
        size: ``(H, W)`` pixels of the training images, or None (checkpoints that do not record it).
        physics: the campaign physics entry of the training target images (``{"name", "level",
            "kvp", ...}``), or None when not recorded.
        current_physics: the entry of the training pairs' *current* images (the registration's
            moving images): ``physics`` unless the run set ``train.current_physics``.
        current_field: ``"masked"`` or ``"open"``: whether the current image is filled outside the
            X-ray's collimated field before it meets the network (``train.current_field``).
        tone: ``"ct"`` or ``"off"`` (``train.tone``; ``"off"`` when not recorded): whether the
            training targets were toned onto line integrals, so that registration shows the network
            the X-ray's toned version.
        framing: ``"field"`` or ``"detector"`` (``train.framing``; ``"field"`` when not recorded).
        checkpoint: the loaded :class:`learn.checkpoint.Checkpoint`.
    """

    #: Pairs per forward pass in :meth:`predict`.
    batch_size = 32
    #: The last batch of targets and their backbone maps (``(key, maps)``): the registration's
    #: iteration shows the network one X-ray with a new DRR each step, and the model in eval mode
    #: maps each image on its own, so the X-ray's maps are computed once (half the backbone's work).
    _targets = None

    def __init__(self, checkpoint):
        from learn.checkpoint import Checkpoint, load_checkpoint  # loads torch: imported where first needed (start-up)
        from learn.labels import LabelNormalizer  # loads torch: imported where first needed (start-up)
        from learn.preprocess import build  # loads torch: imported where first needed (start-up)

        if not isinstance(checkpoint, Checkpoint):
            checkpoint = resolve_model(checkpoint)  # a file, or a shipped model's name
        ckpt = checkpoint if isinstance(checkpoint, Checkpoint) else load_checkpoint(checkpoint)
        self.checkpoint = ckpt
        self.model = ckpt.build_model()
        self.model.eval()
        self.transform = build(list(ckpt.preprocess))
        self.normalizer = LabelNormalizer()
        self.size = ckpt.image_size
        self.physics = ckpt.physics
        self.current_physics = ckpt.current_physics or ckpt.physics
        from learn.online import current_field_problem  # loads torch: imported where first needed (start-up)

        field = (ckpt.config or {}).get("current_field", "masked")
        if current_field_problem(field):
            from learn.checkpoint import CheckpointError  # loads torch: imported where first needed (start-up)

            raise CheckpointError(f"{ckpt.name}: config.current_field {current_field_problem(field)}")
        #: what the network sees of the current image outside the X-ray's field (``"masked"``:
        #: filled as the X-ray, ``"open"``: all of it), as it was trained (:data:`learn.online.CURRENT_FIELDS`)
        self.current_field = field

        tone = (ckpt.config or {}).get("tone", "off")
        if tone not in TONES:
            from learn.checkpoint import CheckpointError  # loads torch: imported where first needed (start-up)

            raise CheckpointError(f"{ckpt.name}: config.tone must be one of {', '.join(TONES)}, got {tone!r}")
        #: whether the network was trained on targets toned onto line integrals (``train.tone``):
        #: registration then shows it the X-ray's toned version
        self.tone = tone
        from learn.online import FRAMINGS  # loads torch: imported where first needed (start-up)

        framing = (ckpt.config or {}).get("framing", "field")
        if framing not in FRAMINGS:
            from learn.checkpoint import CheckpointError  # loads torch: imported where first needed (start-up)

            raise CheckpointError(f"{ckpt.name}: config.framing must be one of {', '.join(FRAMINGS)}, got {framing!r}")
        #: how the network's pairs were framed (``train.framing``): ``"field"`` (cropped to the
        #: X-ray's field, as registration crops it) or ``"detector"`` (the whole detector with the
        #: field masked: registration shows it :func:`register.xray.network_view.network_view`)
        self.framing = framing

    def physics_mismatch(self, physics, *, advice: str = "set --physics to match") -> str | None:
        """A sentence when the moving images' :class:`~sim.physics.imaging.PhysicsSettings` (None =
        line) differ from the physics of the training pairs' current images (level, and kVp and
        filtration for poly and full), ending in ``advice``; None when they agree or the checkpoint
        does not record its physics."""
        ref = self.current_physics
        if ref is None:
            return None
        level = "line" if physics is None else physics.level
        trained = ref.get("level", "line")
        differ = level != trained
        if not differ and level in ("poly", "full"):
            filters = parse_filters(ref.get("filters", ()))  # stored as "SYMBOL:MM" strings
            differ = (abs(float(ref.get("kvp", physics.kvp)) - physics.kvp) > 1e-9
                      or filters != tuple((s, float(t)) for s, t in physics.filters))
        if not differ:
            return None
        spec = f"{trained}" + (f" at {ref.get('kvp'):g} kVp" if trained in ("poly", "full") else "")
        return (f"the network was trained on {spec} current images (campaign physics {ref.get('name')!r}) but "
                f"the current images are rendered with {level} physics"
                + (f" at {physics.kvp:g} kVp" if level in ("poly", "full") else "")
                + f": its predictions may be off (the domain gap); {advice}")

    def predict(self, fixed: np.ndarray, drr: np.ndarray) -> Prediction:
        """``fixed`` (target) and ``drr`` (current) images ``(N, H, W)`` -> :class:`Prediction`
        (rad, mm). Images of another size than the training images are resampled to it first
        (area averaging, as a coarser detector would)."""
        import torch
        import torch.nn.functional as F

        fixed, drr = np.asarray(fixed), np.asarray(drr)
        if fixed.ndim != 3 or fixed.shape != drr.shape:
            from learn.model import PoseInputError  # loads torch: imported where first needed (start-up)

            raise PoseInputError(f"fixed and drr must be (N, H, W) of one shape, got {fixed.shape} and {drr.shape}")
        if len(fixed) == 0:
            return Prediction(np.zeros((0, 6)), np.zeros((0, 3, 6)))
        def prepared(images):  # (b, H, W) -> (b, 1, h, w) at the training size, preprocessed
            x = torch.from_numpy(np.asarray(images, np.float32))[:, None]
            if self.size is not None and tuple(x.shape[-2:]) != self.size:
                x = F.interpolate(x, size=self.size, mode="area")
            return self.transform(x)

        g, levels = [], []
        with torch.no_grad():
            for start in range(0, len(fixed), self.batch_size):
                stop = min(start + self.batch_size, len(fixed))
                targets = fixed[start:stop]
                key = (targets.shape, targets.dtype.str, hashlib.blake2b(targets.tobytes(), digest_size=16).digest())
                if self._targets is None or self._targets[0] != key:
                    self._targets = (key, self.model.backbone.taps(prepared(targets)))
                current = self.model.backbone.taps(prepared(drr[start:stop]))
                out = self.model.heads_forward([torch.cat((t, c), dim=1) for t, c in zip(self._targets[1], current)])
                g.append(self.normalizer.denormalize(out.g.double()).numpy())
                levels.append(self.normalizer.denormalize(out.g_levels.double()).numpy())
        return Prediction(np.concatenate(g), np.concatenate(levels))

    def __call__(self, fixed: np.ndarray, drr: np.ndarray) -> np.ndarray:
        """``fixed``, ``drr`` ``(H, W)`` -> g ``(6,)`` (rad, mm); see :meth:`predict`."""
        return self.predict(np.asarray(fixed)[None], np.asarray(drr)[None]).g[0]
