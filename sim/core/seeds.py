"""Every random stream of ctxreg, declared once: what it is for -> its entropy and spawn key.

A stream is a :class:`numpy.random.Generator` on PCG64 seeded by a
:class:`numpy.random.SeedSequence`. Two families:

* **Keyed streams**: ``SeedSequence(entropy=seed, spawn_key=(KIND, *indices))`` (:func:`rng_for`,
  :func:`seed_sequence`). ``seed`` is a user's seed (campaign, training, evaluation, ...), ``KIND``
  says what the stream is for and the indices which item (subject, shard, epoch, ...) it
  belongs to, so a draw never depends on the order in which items are processed.
* **Tagged streams**: ``SeedSequence([seed, TAG])`` (:func:`tagged`): entropy mixed with a fixed
  tag, for library functions that take one integer seed (phantom, Monte Carlo).

Keyed streams (the spawn key's first element; the rest of the key after it):

=====================================  ====  ==========================  ================================================
name                                   kind  entropy                     purpose (rest of the spawn key) -- user
=====================================  ====  ==========================  ================================================
:data:`KIND_POSES`                     0     campaign seed               a subject's poses ``(subject)`` -- sim.campaign.runner
:data:`KIND_VIRTUAL_PATIENT`           1     campaign seed               a virtual patient's parameters ``(ct, vp)`` -- runner
(2: never used)
:data:`KIND_SPLIT`                     3     campaign seed               CT-level split permutation ``()`` -- sim.campaign.config
:data:`KIND_NOISE`                     4     campaign seed               noise and Monte Carlo seed of a shard's poly/full images
                                                                         ``(subject, shard, physics entry)`` -- runner
:data:`KIND_EVALUATE_CASES`            10    evaluation seed             ``ctxreg evaluate`` targets and starts ``()``
                                                                         -- register.evaluation.evaluate
:data:`KIND_POLARITY_POSES`            13    polarity seed               poses of the polarity reference DRRs ``()``
                                                                         -- register.xray.prepare
:data:`KIND_EPOCH_PAIRS`               20    training seed               the pairs of an epoch ``(epoch)`` -- learn.data
:data:`KIND_ACCURACY_PAIRS`            30    accuracy seed               evaluation pairs ``(kind, subject)`` -- learn.commands;
                                                                         ``()`` -- learn.accuracy
:data:`KIND_BATCH`                     40    training seed               an online batch's draws ``(batch)`` -- learn.online
:data:`KIND_BATCH_NOISE`               41    training seed               noise / Monte Carlo of an online batch's images
                                                                         ``(batch, subject[, 1])`` -- learn.online
:data:`KIND_RANDOMIZE`                 50    randomization seed          domain randomization of pair ``index``: its
                                                                         settings ``(index, 0)``, its post-render noise
                                                                         ``(index, 1)``, tool bank arrangement ``(j, 2)``
                                                                         -- sim.randomize
:data:`KIND_VP_FIELD`                  0     a virtual patient's seed    its deformation field ``()`` -- sim.ct.patients
:data:`KIND_VP_NOISE`                  1     a virtual patient's seed    its added CT noise ``()`` -- sim.ct.patients
=====================================  ====  ==========================  ================================================

The last two are keyed by a virtual patient's own seed (drawn from its
:data:`KIND_VIRTUAL_PATIENT` stream), never by the campaign seed: they cannot meet the kinds 0
and 1 of the campaign. New kinds take a number not in this table.

Tagged streams and plain seeds:

=================================  ===========================================  ==========================================
name                               construction                                 purpose -- user
=================================  ===========================================  ==========================================
:data:`TAG_PELVIS_SHAPE`           ``SeedSequence([seed, 0x5E1F15])``           the phantom's random shape -- sim.ct.phantom
:data:`TAG_PHANTOM_TEXTURE`        ``SeedSequence([seed, 0x7E47])``             the phantom's texture -- sim.ct.phantom
:data:`TAG_SCATTER_CHUNKS`         ``SeedSequence([pose seed, 0x5CA7])``        ``.spawn(n)``: one child per chunk of
                                                                                Monte Carlo histories -- sim.physics.scatter
:func:`pose_seed`                  ``SeedSequence([seed, b]).generate_state``   Monte Carlo seed of pose ``b`` of a batch
                                                                                (``b = 0`` for all: common random
                                                                                numbers) -- sim.physics.imaging
:func:`image_noise_rng`            ``default_rng(seed)``                        quantum / electronic noise of an image
                                                                                batch -- sim.physics.imaging
=================================  ===========================================  ==========================================

``tests/sim/test_seeds.py`` checks that every name gives the same numbers as the literal
construction it replaced: the streams are bit-identical to those of earlier datasets.
"""

from __future__ import annotations

import numpy as np

# -- keyed streams: spawn_key=(KIND, *indices) ---------------------------------------------------
#: A subject's poses: ``(KIND_POSES, subject)``, campaign seed.
KIND_POSES = 0
#: A virtual patient's parameters: ``(KIND_VIRTUAL_PATIENT, ct, vp)``, campaign seed.
KIND_VIRTUAL_PATIENT = 1
#: The CT-level split permutation: ``(KIND_SPLIT,)``, campaign seed.
KIND_SPLIT = 3
#: Noise and Monte Carlo of a shard's poly / full images: ``(KIND_NOISE, subject, shard, entry)``.
KIND_NOISE = 4
#: ``ctxreg evaluate``'s target and start poses: ``(KIND_EVALUATE_CASES,)``, evaluation seed.
KIND_EVALUATE_CASES = 10
#: Poses of the polarity reference DRRs: ``(KIND_POLARITY_POSES,)``.
KIND_POLARITY_POSES = 13
#: The pairs of a training epoch: ``(KIND_EPOCH_PAIRS, epoch)``, training seed.
KIND_EPOCH_PAIRS = 20
#: Evaluation pairs of the accuracy command: ``(KIND_ACCURACY_PAIRS, kind, subject)`` (and
#: ``(KIND_ACCURACY_PAIRS,)`` in :mod:`learn.accuracy`).
KIND_ACCURACY_PAIRS = 30
#: An online training batch's draws: ``(KIND_BATCH, batch)``, training seed.
KIND_BATCH = 40
#: Noise / Monte Carlo of an online batch's images: ``(KIND_BATCH_NOISE, batch, subject[, 1])``.
KIND_BATCH_NOISE = 41
#: Domain randomization of pair ``index``: settings ``(KIND_RANDOMIZE, index, 0)``, post-render
#: noise ``(KIND_RANDOMIZE, index, 1)``, tool bank arrangement ``(KIND_RANDOMIZE, j, 2)`` (:mod:`sim.randomize`).
KIND_RANDOMIZE = 50
#: A virtual patient's deformation field: ``(KIND_VP_FIELD,)`` under the virtual patient's seed.
KIND_VP_FIELD = 0
#: A virtual patient's added CT noise: ``(KIND_VP_NOISE,)`` under the virtual patient's seed.
KIND_VP_NOISE = 1

# -- tagged streams: SeedSequence([seed, TAG]) ---------------------------------------------------
#: The phantom's random shape (:meth:`sim.ct.phantom.PelvisShape.sample`).
TAG_PELVIS_SHAPE = 0x5E1F15
#: The phantom's texture (:func:`sim.ct.phantom.make_pelvis_phantom`).
TAG_PHANTOM_TEXTURE = 0x7E47
#: The chunks of a pose's Monte Carlo histories (:class:`sim.physics.scatter.MonteCarloScatter`).
TAG_SCATTER_CHUNKS = 0x5CA7


def seed_sequence(seed: int, kind: int, *indices: int) -> np.random.SeedSequence:
    """``SeedSequence(entropy=seed, spawn_key=(kind, *indices))``: the keyed stream's seed."""
    return np.random.SeedSequence(entropy=seed, spawn_key=(kind, *indices))


def rng_for(seed: int, kind: int, *indices: int) -> np.random.Generator:
    """The keyed stream ``kind`` of item ``indices`` under ``seed`` (a ``KIND_*`` of this module)."""
    return np.random.Generator(np.random.PCG64(seed_sequence(seed, kind, *indices)))


def tagged(seed: int, tag: int) -> np.random.SeedSequence:
    """``SeedSequence([seed, tag])`` (a ``TAG_*`` of this module)."""
    return np.random.SeedSequence([seed, tag])


def tagged_rng(seed: int, tag: int) -> np.random.Generator:
    """The generator of :func:`tagged` (``np.random.default_rng(SeedSequence([seed, tag]))``)."""
    return np.random.default_rng(tagged(seed, tag))


def pose_seed(seed: int, pose: int) -> int:
    """The Monte Carlo seed of pose ``pose`` of a batch: ``SeedSequence([seed, pose]).generate_state(1)[0]``."""
    return int(np.random.SeedSequence([seed, pose]).generate_state(1)[0])


def image_noise_rng(seed: int) -> np.random.Generator:
    """The noise stream of one batch of images: ``np.random.default_rng(seed)``."""
    return np.random.default_rng(seed)


# --------------------------------------------------------------------------------------------
# per-pair noise for batched torch code
# --------------------------------------------------------------------------------------------


def pair_normals(seed: int, index, stream: int, shape: tuple[int, ...], *, device=None, dtype=None):
    """Standard normal numbers ``(B, *shape)``: row ``b`` from a torch generator of its own,
    seeded by ``SeedSequence([seed, stream, index[b]])``, so a pair's noise depends on
    ``(seed, index, stream)`` only, not on the batch it is drawn in or its place there.

    ``index`` ``(B,)`` non-negative integers (e.g. a pair's randomization index); ``stream`` a
    small integer naming what the noise is for. The numbers come from the generator of
    ``device`` (Mersenne Twister on a CPU, Philox on CUDA): the same pair draws different noise
    of the same distribution on the two kinds of device. One generator and one ``randn`` per
    pair (about 20 us each on a CPU core; a hash of element counters in int64 tensors was 20x slower).
    """
    import torch

    dtype = dtype or torch.float32
    device = torch.device(device if device is not None else "cpu")
    idx = np.asarray(index.cpu() if hasattr(index, "cpu") else index, dtype=np.int64).ravel()
    out = torch.empty((len(idx),) + tuple(shape), dtype=dtype, device=device)
    for b, i in enumerate(idx):
        g = torch.Generator(device=device)
        g.manual_seed(int(np.random.SeedSequence([int(seed), int(stream), int(i)]).generate_state(2, np.uint64)[0]
                          >> np.uint64(1)))
        out[b] = torch.randn(tuple(shape), generator=g, device=device, dtype=dtype)
    return out
