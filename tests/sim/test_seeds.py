"""Every random stream is named in sim/core/seeds.py and equals, bit for bit, the literal construction
it replaced (so datasets, virtual patients, phantoms and training pairs stay the same)."""

from __future__ import annotations

import ast

import numpy as np
import pytest

from sim.core import seeds
from tests.conftest import REPO


def _gen(ss: np.random.SeedSequence) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(ss))


def _same(a: np.random.Generator, b: np.random.Generator) -> bool:
    return np.array_equal(a.integers(0, 2**63, 16), b.integers(0, 2**63, 16)) and a.random() == b.random()


#: name -> (the literal number it had in the code, the spawn-key indices after it in that code)
KEYED = {
    "KIND_POSES": (0, (7,)),                    # sim/campaign/runner.py: (KIND_POSES, subject)
    "KIND_VIRTUAL_PATIENT": (1, (2, 5)),        # runner: (1, ct, vp)
    "KIND_SPLIT": (3, ()),                      # sim/campaign/config.py: KIND_SPLIT = 3
    "KIND_NOISE": (4, (3, 1, 0)),               # runner: (4, subject, shard, entry)
    "KIND_EVALUATE_CASES": (10, ()),            # register/evaluation/evaluate.py
    "KIND_POLARITY_POSES": (13, ()),            # register/xray/prepare.py
    "KIND_EPOCH_PAIRS": (20, (4,)),             # learn/data.py: (20, epoch)
    "KIND_ACCURACY_PAIRS": (30, (1, 2)),        # learn/commands.py: (30, ki, si)
    "KIND_BATCH": (40, (9,)),                   # learn/online.py
    "KIND_BATCH_NOISE": (41, (9, 2, 1)),        # learn/online.py
    "KIND_RANDOMIZE": (50, (9, 0)),             # sim/randomize.py: (50, index, 0 settings / 1 noise)
    "KIND_VP_FIELD": (0, ()),                   # sim/ct/patients.py: _STREAM_FIELD = 0
    "KIND_VP_NOISE": (1, ()),                   # sim/ct/patients.py: _STREAM_NOISE = 1
}
TAGS = {"TAG_PELVIS_SHAPE": 0x5E1F15, "TAG_PHANTOM_TEXTURE": 0x7E47, "TAG_SCATTER_CHUNKS": 0x5CA7}


@pytest.mark.parametrize("name", KEYED)
def test_each_keyed_stream_equals_its_literal_construction(name):
    literal, indices = KEYED[name]
    assert getattr(seeds, name) == literal
    for seed in (0, 5, 2**63 - 1):
        old = _gen(np.random.SeedSequence(entropy=seed, spawn_key=(literal, *indices)))
        assert _same(seeds.rng_for(seed, getattr(seeds, name), *indices), old)
        # the positional form (learn/data.py, learn/commands.py wrote SeedSequence(seed, spawn_key=...))
        assert _same(_gen(seeds.seed_sequence(seed, getattr(seeds, name), *indices)),
                     _gen(np.random.SeedSequence(seed, spawn_key=(literal, *indices))))


@pytest.mark.parametrize("name", TAGS)
def test_each_tagged_stream_equals_its_literal_construction(name):
    tag = getattr(seeds, name)
    assert tag == TAGS[name]
    for seed in (0, 3, 12345):
        assert _same(seeds.tagged_rng(seed, tag), np.random.default_rng(np.random.SeedSequence([seed, TAGS[name]])))
        new = [int(c.generate_state(1, np.uint64)[0]) for c in seeds.tagged(seed, tag).spawn(3)]
        old = [int(c.generate_state(1, np.uint64)[0]) for c in np.random.SeedSequence([seed, TAGS[name]]).spawn(3)]
        assert new == old


def test_pose_seeds_and_image_noise_equal_their_literal_construction():
    for seed in (0, 7, 2**40):
        for b in (0, 1, 5):
            assert seeds.pose_seed(seed, b) == int(np.random.SeedSequence([seed, b]).generate_state(1)[0])
        assert _same(seeds.image_noise_rng(seed), np.random.default_rng(seed))


def test_keyed_streams_of_different_purposes_differ():
    """The campaign's kinds are distinct numbers, so no two purposes share a stream."""
    campaign = [seeds.KIND_POSES, seeds.KIND_VIRTUAL_PATIENT, seeds.KIND_SPLIT, seeds.KIND_NOISE,
                seeds.KIND_EVALUATE_CASES, seeds.KIND_POLARITY_POSES, seeds.KIND_EPOCH_PAIRS,
                seeds.KIND_ACCURACY_PAIRS, seeds.KIND_BATCH, seeds.KIND_BATCH_NOISE, seeds.KIND_RANDOMIZE]
    assert len(set(campaign)) == len(campaign)
    assert not _same(seeds.rng_for(1, seeds.KIND_POSES, 0), seeds.rng_for(1, seeds.KIND_VIRTUAL_PATIENT, 0))


def test_the_users_take_their_streams_from_sim_seeds():
    """The campaign runner and config use the named kinds, and the split permutation is the
    literal kind-3 stream's."""
    from sim.campaign import config, runner

    assert runner.rng_for is seeds.rng_for
    assert (runner.KIND_POSES, runner.KIND_VIRTUAL_PATIENT, runner.KIND_NOISE) == (0, 1, 4)
    assert config.KIND_SPLIT == 3
    got = config.assign_splits(12, {"train": 0.5, "val": 0.25, "test": 0.25}, [None] * 12, seed=9)
    perm = _gen(np.random.SeedSequence(entropy=9, spawn_key=(3,))).permutation(12)
    expect = [None] * 12
    for k, split in zip(perm, ["train"] * 6 + ["val"] * 3 + ["test"] * 3):
        expect[k] = split
    assert got == expect


#: Files that still build their SeedSequence themselves (owned elsewhere; their kinds are named
#: in sim/core/seeds.py already and can switch to it).
NOT_YET: set[str] = set()


def test_no_other_module_builds_a_keyed_or_tagged_stream():
    """No ``SeedSequence(...)`` call and no stream tag outside sim/core/seeds.py (docstrings may cite them)."""
    tags = set(TAGS.values())
    offenders = []
    for pkg in ("sim", "learn", "register"):
        for path in sorted((REPO / pkg).rglob("*.py")):
            rel = path.relative_to(REPO).as_posix()
            if rel == "sim/core/seeds.py" or rel in NOT_YET:
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                called = isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None))
                if called == "SeedSequence" or (isinstance(node, ast.Constant) and node.value in tags
                                                and not isinstance(node.value, bool)):
                    offenders.append(f"{rel}:{node.lineno}")
    assert offenders == []
