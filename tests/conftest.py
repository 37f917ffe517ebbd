"""Shared fixtures: the real data beside the project, skipped with a reason when absent."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = (REPO / ".." / "shared" / "data").resolve()


def pytest_addoption(parser):
    parser.addoption("--shuffle", type=int, default=None, metavar="SEED",
                     help="run the modules in a shuffled order, and the tests of each module shuffled too, from SEED "
                          "(a module's tests stay together, so its module-scoped fixtures are made once): finds tests "
                          "that pass only in the order they were written")


def pytest_collection_modifyitems(config, items):
    import random

    seed = config.getoption("--shuffle")
    if seed is None:
        return
    rng = random.Random(seed)
    modules: dict = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::")[0], []).append(item)
    order = list(modules)
    rng.shuffle(order)
    items[:] = [item for name in order for item in rng.sample(modules[name], len(modules[name]))]


def load_benchmark(name: str):
    """The script ``benchmarks/<name>.py`` as a module (benchmarks/ is no package, and putting it on
    sys.path would let its learn.py and register.py shadow the packages)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def shared_file(relative: str) -> Path:
    """A file under ../shared/data, or skip the test saying what is missing."""
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"real data {relative} not found under {SHARED_DATA} (see ../shared/data/README.md)")
    return path


def _private_folder(tmp_path_factory, variable: str, name: str):
    """Set the environment ``variable`` to a new folder ``name`` of the session (subprocesses
    inherit it) for the session, then put back what was there."""
    import os

    before = os.environ.get(variable)
    os.environ[variable] = str(tmp_path_factory.mktemp(name))
    yield Path(os.environ[variable])
    if before is None:
        os.environ.pop(variable, None)
    else:
        os.environ[variable] = before


@pytest.fixture(scope="session", autouse=True)
def private_ct_cache(tmp_path_factory):
    """The CT cache (sim.ct.cache) of the tests: a folder of their own, never the user's."""
    yield from _private_folder(tmp_path_factory, "CTXREG_CT_CACHE", "ct_cache")


@pytest.fixture(scope="session", autouse=True)
def private_build_cache(tmp_path_factory):
    """The build cache (sim.core.build_cache: spectral tables, tool banks) of the tests: one folder
    for the session, never the user's; tests of the cache itself give their own folder."""
    yield from _private_folder(tmp_path_factory, "CTXREG_BUILD_CACHE", "build_cache")


@pytest.fixture(scope="session")
def pelvis_ct_path() -> Path:
    return shared_file("ct/pelvis_abdomen_3mm.nii.gz")


@pytest.fixture(scope="session")
def chest_ct_path() -> Path:
    return shared_file("ct/chest_0p7x2p5mm.nii.gz")


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch CPU thread for a module (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``):
    small batches gain nothing from more, and lose much on a busy machine."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
