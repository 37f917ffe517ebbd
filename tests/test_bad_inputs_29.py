"""Issue 29's bad inputs, table-driven like tests/test_bad_inputs.py (its harness and inputs): each
is refused before any work, in one line naming the option, with exit status 2 and nothing written."""

from __future__ import annotations

import pytest

from tests.test_bad_inputs import _run, inputs  # noqa: F401  (the module's fixture, reused)

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
}


@pytest.mark.parametrize("name", list(BAD))
def test_a_bad_input_is_refused_before_the_work_naming_the_option(name, inputs, tmp_path, capsys,  # noqa: F811
                                                                  monkeypatch):
    import register.demo
    import sim.physics.imaging

    def no_work(*args, **kwargs):
        raise AssertionError("simulated or loaded before the refusal")

    monkeypatch.setattr(sim.physics.imaging, "XRayImager", no_work)  # the demo's simulation
    monkeypatch.setattr("sim.ct_io.load_ct_spec", no_work)  # the demo's CT
    monkeypatch.setattr("sim.load_ct", no_work)  # register's CT
    assert register.demo  # imported: its imports are made inside run_demo
    line, words = BAD[name]
    status, new = _run(line, inputs, tmp_path)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert status == 2 and "Traceback" not in err, err
    assert len(lines) == 1 and lines[0].startswith(f"ctxreg {line.split()[0]}: error: "), err
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert "mask: empty" not in lines[0] and "erosion" not in lines[0]
    assert not new, f"files written: {sorted(new)}"


@pytest.mark.parametrize("size", ["4096 4096", "1024 1024"])
def test_a_size_beyond_the_memory_is_refused_before_it_is_allocated(size, inputs, tmp_path, capsys,  # noqa: F811
                                                                    monkeypatch):
    """register --size 4096 4096 on a 64 x 64 X-ray asked for 27 GiB in the polarity check."""
    import register.prepare
    import sim.cliargs

    monkeypatch.setattr(sim.cliargs, "available_memory_bytes", lambda: 4 * 1024 ** 3)

    def no_work(*args, **kwargs):
        raise AssertionError("prepared before the memory check")

    monkeypatch.setattr(register.prepare, "prepare_xray", no_work)
    status, new = _run(f"register --ct phantom --xray {{xray}} --size {size} --out reg", inputs, tmp_path)
    err = capsys.readouterr().err.strip()
    assert status == 2 and "\n" not in err and "Traceback" not in err, err
    assert f"--size {size}" in err and "GiB" in err and "4.0 GiB of memory available" in err, err
    assert not new


def test_the_memory_estimate_is_the_grid_s_and_the_default_size_passes(inputs):  # noqa: F811
    from register.api import GRID_BYTES_PER_PX, check_registration_memory, grid_bytes
    from register.search import GlobalSearchSettings
    from register.xray_io import load_xray, resolve_geometry

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
    from register.preprocess import PreprocessError

    class Prepared:
        image = np.zeros((32, 12))
        mask = np.ones((32, 12), bool)

    with pytest.raises(PreprocessError, match=r"--size 32 32: the X-ray's field, fitted into it \(32 x 12 px\)"):
        _check_coarse_field(Prepared, (32, 32), need=16)
    Prepared.image, Prepared.mask = np.zeros((32, 32)), np.ones((32, 32), bool)
    _check_coarse_field(Prepared, (32, 32), need=16)  # 8 x 8 at 1/4, 6 x 6 after erosion


def test_a_study_size_below_the_registration_s_minimum_is_refused_with_xray_targets(tmp_path):
    from register.study import StudyError, load_study

    path = tmp_path / "s.toml"
    path.write_text('[study]\nct = "phantom"\nsize = [16, 16]\n[[variant]]\nname = "a"\nmodel = "pelvis_line"\n'
                    '[[target]]\nname = "f"\nkind = "xray"\nphysics = { level = "full" }\n')
    with pytest.raises(StudyError, match=r"study.size: \[16, 16\]: kind 'xray' targets"):
        load_study(path)
