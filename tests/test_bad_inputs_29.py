"""Issue 29's bad inputs, table-driven like tests/test_bad_inputs.py (its harness and inputs): each
is refused before any work, in one line naming the option, with exit status 2 and nothing written."""

from __future__ import annotations

import ast
import functools
import importlib

import pytest

from pathlib import Path

from tests.test_bad_inputs import _run, assert_refused, inputs  # noqa: F401  (the module's fixture, reused)

ROOT = Path(__file__).resolve().parents[1]

#: (command line after ``ctxreg``, words the error line must hold, words it must not hold)
BAD = {
    "register size 8": ("register --ct phantom --xray {xray} --size 8 8 --out reg", ["--size 8 8", "at least 32"]),
    "register size 16": ("register --ct phantom --xray {xray} --size 16 16 --out reg", ["--size 16 16", "at least 32"]),
    "register size 24 x 64": ("register --ct phantom --xray {xray} --size 24 64 --out reg",
                              ["--size 24 64", "at least 32"]),
    "demo size 8": ("demo --ct phantom --size 8 8 --out demo", ["--size 8 8", "at least 32"]),
    "demo size off the aspect": ("demo --ct phantom --size 64 32 --out demo", ["--size 64 32", "aspect"]),
    "demo pose behind the detector": ("demo --ct phantom --size 32 32 --pose 0 0 0 0 0 5000 --out demo",
                                      ["--pose 0 0 0 0 0 5000", "between the source and the detector"]),
    "demo pose at the source": ("demo --ct phantom --size 32 32 --pose 0 0 0 0 0 -700 --out demo",
                                ["--pose", "TZ -700"]),
    "demo pose off the detector": ("demo --ct phantom --size 32 32 --pose 0 0 0 900 0 0 --out demo",
                                   ["--pose", "off the detector"]),
    "register a stack of 3 images in one TIFF": ("register --ct phantom --xray {planes} --size 32 32 --out reg",
                                                 ["3 separate planes", "a stack of 3 images"]),
    "register 3 TIFF pages": ("register --ct phantom --xray {pages} --size 32 32 --out reg", ["3 frames/pages"]),
    "render a folder of two series": ("render --ct {twoseries} --size 16 16 --out x.npy",
                                      ["2 DICOM series", "give a folder holding one series"]),
    "train --resume without a checkpoint": ("train {config} --resume", ["--resume", "no checkpoint.pt",
                                                                      "run without --resume"]),
    "register model folder without a card": ("register --ct phantom --xray {xray} --model {emptydir} --out reg",
                                             ["--model", "without model.toml"]),
    "register model.pt changed after its card": ("register --ct phantom --xray {xray} --model {tampered} --out reg",
                                                 ["model.sha256 does not match"]),
    "demo model.pt changed after its card": ("demo --ct phantom --model {tampered} --out demo",
                                             ["model.sha256 does not match"]),
}

#: The rows refused by reading the CT (the rest before it is read).
READ_THE_CT = {"render a folder of two series"}


@pytest.fixture(scope="module")
def inputs29(inputs, tmp_path_factory):  # noqa: F811
    """The inputs of tests/test_bad_inputs.py and this issue's: a TIFF holding a (3, H, W) stack as
    tifffile writes it (three planes, 'RGB'), a 3-page TIFF, a folder of two DICOM series, a train
    config whose out holds no checkpoint, an empty folder, a model folder whose model.pt changed."""
    import shutil

    import numpy as np
    from PIL import Image

    from tests.sim.test_ct_io import write_series

    d = tmp_path_factory.mktemp("inputs29")
    rng = np.random.default_rng(0)
    stack = (rng.random((3, 40, 40)) * 4000).astype(np.uint16)
    tifffile = pytest.importorskip("tifffile")
    tifffile.imwrite(d / "planes.tif", stack, photometric="rgb", planarconfig="separate")  # as it wrote (3, H, W)
    pages = [Image.fromarray(p) for p in stack]
    pages[0].save(d / "pages.tif", save_all=True, append_images=pages[1:])
    for sub, seed in (("a", 1), ("b", 2)):
        write_series(d / "two" / sub, n=4, seed=seed)
        for f in (d / "two" / sub).iterdir():
            f.rename(d / "two" / f"{sub}_{f.name}")
    (d / "config.toml").write_text(f'[train]\ndataset = "{ROOT / "campaigns" / "smoke.toml"}"\niterations = 2\n'
                                   f'out = "{d / "never_trained"}"\n')
    (d / "empty").mkdir()
    shutil.copytree(ROOT / "models" / "pelvis_line", d / "tampered")
    with open(d / "tampered" / "model.pt", "ab") as f:
        f.write(b"\0")
    return {**inputs, "planes": str(d / "planes.tif"), "pages": str(d / "pages.tif"), "twoseries": str(d / "two"),
            "config": str(d / "config.toml"), "emptydir": str(d / "empty"),
            "tampered": str(d / "tampered" / "model.pt")}


@functools.lru_cache(maxsize=None)
def users_of(name: str, packages=("sim", "learn", "register")) -> tuple[str, ...]:
    """The project's modules that bind ``name`` by a module-level ``from ... import``: a patch of the
    name's own module does not reach them, and one of them first imported under the patch would keep
    the patched object after the test (a later test then meets it: found by a shuffled run)."""
    found = []
    for package in packages:
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text())
            if any(isinstance(node, ast.ImportFrom) and any(a.name == name and a.asname is None for a in node.names)
                   for node in tree.body):
                parts = list(path.relative_to(ROOT).with_suffix("").parts)
                found.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return tuple(found)


def patch_where_used(monkeypatch, source: str, name: str, replacement) -> None:
    """``source.name`` and every module's own binding of it (:func:`users_of`) replaced for one test,
    each module imported before the patch so that none binds the replacement at its import."""
    users = [importlib.import_module(m) for m in users_of(name)]
    real = getattr(importlib.import_module(source), name)
    monkeypatch.setattr(importlib.import_module(source), name, replacement)
    for module in users:
        if getattr(module, name, None) is real:
            monkeypatch.setattr(module, name, replacement)


def test_a_patch_where_used_reaches_every_binding_and_leaves_none(monkeypatch):
    import sim.render

    assert "sim.render" in users_of("XRayImager") and "register.evaluation.demo" in users_of("XRayImager")
    real = sim.render.XRayImager
    with monkeypatch.context() as m:
        patch_where_used(m, "sim.physics.imaging", "XRayImager", None)
        assert sim.render.XRayImager is None and importlib.import_module("sim.physics.imaging").XRayImager is None
    assert sim.render.XRayImager is real


@pytest.mark.parametrize("name", list(BAD))
def test_a_bad_input_is_refused_before_the_work_naming_the_option(name, inputs29, tmp_path, capsys, monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("simulated or loaded before the refusal")

    patch_where_used(monkeypatch, "sim.physics.imaging", "XRayImager", no_work)  # a simulation
    if name not in READ_THE_CT:
        patch_where_used(monkeypatch, "sim.ct.io", "load_ct_spec", no_work)  # the demo's CT
        patch_where_used(monkeypatch, "sim", "load_ct", no_work)  # register's CT
    line, words = BAD[name]
    status, new = _run(line, inputs29, tmp_path)
    said = assert_refused(status, capsys.readouterr().err, new, line, words)
    assert "mask: empty" not in said and "erosion" not in said and "a colour image (RGB" not in said
    assert "pick one with series_uid=" not in said


@pytest.mark.parametrize("size", ["4096 4096", "1024 1024"])
def test_a_size_beyond_the_memory_is_refused_before_it_is_allocated(size, inputs, tmp_path, capsys,  # noqa: F811
                                                                    monkeypatch):
    """register --size 4096 4096 on a 64 x 64 X-ray asked for 27 GiB in the polarity check."""
    import register.api
    import sim.core.cliargs

    monkeypatch.setattr(sim.core.cliargs, "available_memory_bytes", lambda: 4 * 1024 ** 3)

    def no_work(*args, **kwargs):
        raise AssertionError("prepared before the memory check")

    monkeypatch.setattr(register.api, "prepare_xray", no_work)
    monkeypatch.setattr("sim.load_ct", no_work)  # the X-ray and its geometry suffice
    status, new = _run(f"register --ct phantom --xray {{xray}} --size {size} --out reg", inputs, tmp_path)
    err = capsys.readouterr().err.strip()
    assert status == 2 and "\n" not in err and "Traceback" not in err, err
    assert f"--size {size}" in err and "GiB" in err and "4.0 GiB of memory available" in err, err
    assert not new


def test_the_memory_estimate_is_the_grid_s_and_the_default_size_passes(inputs):  # noqa: F811
    from register.api import GRID_BYTES_PER_PX, check_registration_memory, grid_bytes
    from register.engines.search import GlobalSearchSettings
    from register.xray.geometry import resolve_geometry
    from register.xray.io import load_xray

    xray = load_xray(inputs["xray"])
    g, _ = resolve_geometry(xray, "cios_fusion")
    small = grid_bytes((128, 128), (64, 64), g)
    big = grid_bytes((4096, 4096), (64, 64), g)
    poses = len(GlobalSearchSettings().grid_offsets())
    assert big / small > 500  # the grid's area grows with the square of the size
    assert big >= poses * 1024 * 1024 * GRID_BYTES_PER_PX  # at least the unpadded grid
    check_registration_memory((128, 128), (64, 64), g, available=1024 ** 3)  # 1 GiB is enough for the default
    with pytest.raises(Exception, match="--size 4096 4096"):
        check_registration_memory((4096, 4096), (64, 64), g, available=64 * 1024 ** 3)


def test_a_field_too_small_at_the_coarsest_level_names_size():
    """An X-ray whose field, fitted into --size, keeps too few pixels at 1/4: refused naming --size
    (it failed deep inside with "mask: empty after erosion" or "too few to search")."""
    import numpy as np

    from register.api import _check_coarse_field
    from register.xray.preprocess import PreprocessError

    class Prepared:
        image = np.zeros((32, 12))
        mask = np.ones((32, 12), bool)

    with pytest.raises(PreprocessError, match=r"--size 32 32: the X-ray's field, fitted into it \(32 x 12 px\)"):
        _check_coarse_field(Prepared, (32, 32), need=16)
    Prepared.image, Prepared.mask = np.zeros((32, 32)), np.ones((32, 32), bool)
    _check_coarse_field(Prepared, (32, 32), need=16)  # 8 x 8 at 1/4, 6 x 6 after erosion


def test_a_study_size_below_the_registration_s_minimum_is_refused_with_xray_targets(tmp_path):
    from register.evaluation.study import StudyError, load_study

    path = tmp_path / "s.toml"
    path.write_text('[study]\nct = "phantom"\nsize = [16, 16]\n[[variant]]\nname = "a"\nmodel = "pelvis_line"\n'
                    '[[target]]\nname = "f"\nkind = "xray"\nphysics = { level = "full" }\n')
    with pytest.raises(StudyError, match=r"study.size: \[16, 16\]: kind 'xray' targets"):
        load_study(path)


def _model_folder(tmp_path) -> Path:
    import shutil

    folder = tmp_path / "my_model"
    shutil.copytree(ROOT / "models" / "pelvis_line", folder)
    return folder


def test_model_takes_a_model_folder_and_checks_a_model_pt_against_its_card(tmp_path):
    from learn.shipped import ModelCardError, resolve_model

    folder = _model_folder(tmp_path)
    assert resolve_model(str(folder)) == folder / "model.pt"  # the folder: it holds the card
    assert resolve_model(str(folder / "model.pt")) == folder / "model.pt"  # checked, unchanged
    (folder / "model.pt").write_bytes((folder / "model.pt").read_bytes() + b"\0")
    for value in (folder, folder / "model.pt"):
        with pytest.raises(ModelCardError, match="model.sha256 does not match"):
            resolve_model(str(value))
    train_out = tmp_path / "run"
    train_out.mkdir()
    (train_out / "checkpoint.pt").write_bytes(b"")
    assert resolve_model(str(train_out)) == train_out / "checkpoint.pt"  # a ctxreg train output folder
    loose = tmp_path / "loose.pt"
    loose.write_bytes(b"")
    assert resolve_model(str(loose)) == loose  # a checkpoint outside a model folder: as it is


def test_a_model_folder_runs_where_a_model_name_does(tmp_path):
    from learn.predict import NetworkPredictor

    folder = _model_folder(tmp_path)
    assert NetworkPredictor(str(folder)).size == NetworkPredictor("pelvis_line").size


def test_a_study_variant_s_model_may_be_a_folder_and_its_card_is_checked(tmp_path):
    from register.evaluation.study import StudyError, load_study

    folder = _model_folder(tmp_path)
    text = ('[study]\nct = "phantom"\nsize = [32, 32]\n[[variant]]\nname = "a"\nmodel = "{m}"\n'
            '[[target]]\nname = "line"\n')
    path = tmp_path / "s.toml"
    path.write_text(text.format(m="my_model"))  # relative to the study file
    assert load_study(path).variants[0].model == str(folder / "model.pt")
    (folder / "model.pt").write_bytes((folder / "model.pt").read_bytes() + b"\0")
    path.write_text(text.format(m="my_model/model.pt"))
    with pytest.raises(StudyError, match="variant\\[0\\].model: .*model.sha256 does not match"):
        load_study(path)
