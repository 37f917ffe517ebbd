"""Bad inputs of ``ctxreg render``, ``register``, ``evaluate`` and ``demo``, table-driven.

Each row runs ``register.cli.main`` in-process (fast) with one bad input and expects exit status
2, exactly one line on stderr starting ``ctxreg <cmd>: error:`` that names the problem, no
traceback, and no file written. A few valid inputs must succeed. Inputs are made once per module
(the phantom's DRR as a DICOM, broken variants of it, a CT slice, a tiny network checkpoint, a CT
with a singular affine); ``{name}`` in a row is replaced by that input's path.
"""

from __future__ import annotations

import os

import numpy as np
import pydicom
import pytest

from register.cli import main

#: (command line after ``ctxreg``, words the error line must hold)
BAD = {
    # ---------------------------------------------------------------- render
    "render size zero": ("render --ct phantom --size 0 16 --out x.npy", ["--size 0 16", "[8, 4096]"]),
    "render size huge": ("render --ct phantom --size 100000 100000 --out x.npy", ["--size", "[8, 4096]"]),
    "render step tiny": ("render --ct phantom --ray-model trilinear --step-fraction 1e-9 --out x.npy",
                         ["--step-fraction", "[0.05, 1]"]),
    "render step with siddon": ("render --ct phantom --step-fraction 0.25 --out x.npy",
                                ["--step-fraction", "--ray-model trilinear"]),
    "render step with poly": ("render --ct phantom --ray-model trilinear --step-fraction 0.25 --physics poly "
                              "--out x.npy", ["--step-fraction", "--physics line"]),
    "render CT behind the source": ("render --ct phantom --size 16 16 --pose 0 0 0 0 0 -2000 --out x.npy",
                                    ["not in the view", "--pose"]),
    "render centre far away": ("render --ct phantom --size 16 16 --center 1e6 1e6 1e6 --out x.npy",
                               ["not in the view", "--center"]),
    "render only air in view": ("render --ct phantom --size 16 16 --pose 0 0 0 300 0 0 --out x.npy",
                                ["only air"]),
    "render centre nan": ("render --ct phantom --center nan 0 0 --out x.npy", ["--center", "finite"]),
    "render mu inf": ("render --ct phantom --mu-water inf --out x.npy", ["--mu-water", "finite"]),
    "render out is a folder": ("render --ct phantom --out {dir_png}", ["existing folder"]),
    "render sidecar is a folder": ("render --ct phantom --out {sidecar}.npy", ["existing folder", ".json"]),
    "render parent is a file": ("render --ct phantom --out {file}/x.npy", ["existing file, not a folder"]),
    "render singular affine": ("render --ct {singular} --size 16 16 --out x.npy", ["singular", "singular.nii.gz"]),
    "render pose matrix not rigid": ("render --ct phantom --pose-matrix {shear} --out x.npy", ["rigid"]),
    "render kvp with line": ("render --ct phantom --kvp 100 --out x.npy", ["--kvp", "--physics poly or full"]),
    "render label map with centre": ("render --ct {ctnii} --label-map {ctnii} --center 0 0 0 --out x.npy",
                                     ["--label-map", "--center"]),
    # ---------------------------------------------------------------- register
    "register size zero": ("register --ct phantom --xray {xray} --size 0 0 --out reg", ["--size 0 0", "[8, 4096]"]),
    "register size huge": ("register --ct phantom --xray {xray} --size 100000 128 --out reg", ["--size"]),
    "register out is a file": ("register --ct phantom --xray {xray} --out {file}", ["existing file", "--out"]),
    "register output name is a folder": ("register --ct phantom --xray {xray} --out {taken}",
                                         ["result.json", "existing folder"]),
    "register broken geometry tags": ("register --ct phantom --xray {badgeom} --size 32 32 --out reg",
                                      ["DistanceSourceToDetector = -5", "ImagerPixelSpacing", "--sdd", "--pixel-spacing"]),
    "register broken tag, one flag": ("register --ct phantom --xray {badgeom} --size 32 32 --sdd 1020 --out reg",
                                      ["ImagerPixelSpacing", "--pixel-spacing"]),
    "register CT slice": ("register --ct phantom --xray {ctslice} --size 32 32 --out reg", ["a CT slice"]),
    "register CT slice by its tags": ("register --ct phantom --xray {slicetags} --size 32 32 --out reg",
                                      ["a CT slice", "ImagePositionPatient"]),
    "register NIfTI as X-ray": ("register --ct phantom --xray {singular} --out reg", ["NIfTI", "--ct"]),
    "register folder as X-ray": ("register --ct phantom --xray {dir_png} --out reg", ["a folder"]),
    "register model with cmaes": ("register --ct phantom --xray {xray} --method cmaes --model {tiny} --out reg",
                                  ["--model", "contextual methods only"]),
    "register unknown model name": ("register --ct phantom --xray {xray} --method contextual --model pelvis_nonexistent "
                                    "--out reg", ["--model pelvis_nonexistent", "neither a checkpoint file nor a "
                                                  "shipped model", "pelvis_line"]),
    "register missing model": ("register --ct phantom --xray {xray} --method contextual --model none.pt --out reg",
                               ["none.pt", "not found"]),
    "register restarts with contextual": ("register --ct phantom --xray {xray} --method contextual --model {tiny} "
                                          "--restarts 1 --out reg", ["--restarts", "--method cmaes only"]),
    "register polarity without intensity": ("register --ct phantom --xray {xray} --preprocess normalize "
                                            "--polarity bone-dark --out reg", ["--polarity", "'intensity'"]),
    "register unknown step": ("register --ct phantom --xray {xray} --preprocess sharpen --out reg", ["sharpen"]),
    "register centre far away": ("register --ct phantom --xray {xray} --size 32 32 --center 1e6 1e6 1e6 --out reg",
                                 ["not in the view", "--init"]),
    "register start behind the source": ("register --ct phantom --xray {xray} --size 32 32 "
                                         "--init 0 0 0 0 0 -2000 --out reg", ["not in the view"]),
    "register init short": ("register --ct phantom --xray {xray} --init 1 2 --out reg", ["six finite numbers"]),
    "register sdd negative": ("register --ct phantom --xray {xray} --sdd -1 --out reg", ["--sdd -1", "> 0"]),
    "register restarts many": ("register --ct phantom --xray {xray} --restarts 11 --out reg", ["--restarts 11"]),
    # ---------------------------------------------------------------- evaluate
    "evaluate local rot inf": ("evaluate --ct phantom --start local --local-rot inf --out ev", ["--local-rot", "finite"]),
    "evaluate local trans inf": ("evaluate --ct phantom --start local --local-trans inf --out ev",
                                 ["--local-trans", "finite"]),
    "evaluate local rot huge": ("evaluate --ct phantom --start local --local-rot 1000 --out ev",
                                ["--local-rot", "(0, 90]"]),
    "evaluate local rot with ap": ("evaluate --ct phantom --local-rot 10 --out ev", ["--local-rot", "--start local"]),
    "evaluate out is a file": ("evaluate --ct phantom --out {file}", ["existing file"]),
    "evaluate cases zero": ("evaluate --ct phantom --cases 0 --out ev", ["--cases 0"]),
    "evaluate seed negative": ("evaluate --ct phantom --seed -1 --out ev", ["--seed -1"]),
    "evaluate size zero": ("evaluate --ct phantom --size 0 0 --out ev", ["--size 0 0"]),
    "evaluate method twice": ("evaluate --ct phantom --method cmaes cmaes --out ev", ["twice"]),
    "evaluate model with cmaes": ("evaluate --ct phantom --model {tiny} --out ev", ["--model", "contextual"]),
    "evaluate label map with centre": ("evaluate --ct {ctnii} --label-map {ctnii} --center 0 0 0 --out ev",
                                       ["--label-map", "--center"]),
    "evaluate mas with line targets": ("evaluate --ct phantom --target-mas 5 --out ev", ["--target-mas"]),
    # ---------------------------------------------------------------- demo
    "demo out is a file": ("demo --out {file}", ["existing file"]),
    "demo output name is a folder": ("demo --size 16 16 --out {demo_taken}", ["xray.dcm", "existing folder"]),
    "demo unknown model": ("demo --ct phantom --model pelvis_nonesuch --out demo", ["--model pelvis_nonesuch",
                                                                                   "shipped model"]),
    "demo size huge": ("demo --size 5000 16 --out demo", ["--size 5000 16"]),
    "demo seed negative": ("demo --seed -1 --out demo", ["--seed -1"]),
}

#: (command line, files it must write)
GOOD = {
    "render trilinear at the smallest step": ("render --ct phantom --size 16 16 --ray-model trilinear "
                                              "--step-fraction 0.05 --out x.npy", ["x.npy", "x.json"]),
    "render replaces an existing file": ("render --ct phantom --size 16 16 --out old.npy", ["old.json"]),
    "register": ("register --ct phantom --xray {xray} --method cmaes --size 32 32 --restarts 0 --out reg",
                 ["reg/result.json", "reg/overlay.png"]),
}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, str]:
    """The input files of the rows (outside the folder a row may write in)."""
    import nibabel as nib
    import torch

    from learn.model import pose_update_net
    from register.xray.io import write_xray_dicom
    from sim.ct.phantom import make_pelvis_phantom
    from sim.projection.drr import DRRRenderer, RenderSettings

    d = tmp_path_factory.mktemp("inputs")
    r = DRRRenderer(make_pelvis_phantom(0), RenderSettings(size=(64, 64)))
    g = r.geometry
    xray = write_xray_dicom(d / "xray.dcm", r.render_params(np.array([5.0, -3, 2, 4, -2, 10]))[0],
                            pixel_spacing_mm=g.pixel_spacing_mm, sdd_mm=g.sdd_mm, sod_mm=g.sod_mm)
    ds = pydicom.dcmread(xray)
    ds.DistanceSourceToDetector, ds.ImagerPixelSpacing = "-5", ["0", "0"]
    ds.save_as(d / "badgeom.dcm")
    ds = pydicom.dcmread(xray)
    ds.Modality, ds.SOPClassUID = "CT", "1.2.840.10008.5.1.4.1.1.2"
    ds.save_as(d / "ctslice.dcm")
    ds = pydicom.dcmread(xray)
    ds.Modality = "OT"
    ds.ImagePositionPatient, ds.ImageOrientationPatient = [0, 0, 0], [1, 0, 0, 0, 1, 0]
    ds.save_as(d / "slicetags.dcm")
    hu = np.full((16, 16, 16), -1000.0, np.float32)
    hu[4:12, 4:12, 4:12] = 400.0
    nib.save(nib.Nifti1Image(hu, np.diag([-1e-4, -1e-4, 1e-4, 1.0])), d / "singular.nii.gz")
    nib.save(nib.Nifti1Image(hu, np.diag([-2.0, -2.0, 2.0, 1.0])), d / "ctnii.nii.gz")
    np.savetxt(d / "shear.txt", np.array([[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
    torch.manual_seed(0)
    torch.save({"model": pose_update_net(backbone="tiny").state_dict(), "image_size": [32, 32],
                "config": {"backbone": "tiny", "preprocess": ["normalize"], "head_channels": 64}}, d / "tiny.pt")
    names = ("xray.dcm", "badgeom.dcm", "ctslice.dcm", "slicetags.dcm", "singular.nii.gz", "ctnii.nii.gz", "shear.txt",
             "tiny.pt")
    return {n.split(".")[0]: str(d / n) for n in names}


def _files(root) -> set[str]:
    return {os.path.relpath(os.path.join(a, f), root) for a, dirs, files in os.walk(root) for f in files + dirs}


def _run(line: str, inputs: dict, work) -> tuple[int, set[str]]:
    """Run a row in the folder ``work`` (where its outputs go, with an existing file, an existing
    folder, a folder holding a folder named like an output); returns the status and the new files."""
    (work / "file").write_text("not a folder")
    (work / "old.npy").write_text("an old output")
    (work / "folder.png").mkdir()
    (work / "sidecar.json").mkdir()
    (work / "taken" / "result.json").mkdir(parents=True)
    (work / "demo_taken" / "xray.dcm").mkdir(parents=True)
    paths = {**inputs, "file": str(work / "file"), "dir_png": str(work / "folder.png"),
             "sidecar": str(work / "sidecar"), "taken": str(work / "taken"), "demo_taken": str(work / "demo_taken")}
    argv = [a.format(**paths) for a in line.split()]
    before = _files(work)
    cwd = os.getcwd()
    os.chdir(work)
    try:
        status = main(argv)
    finally:
        os.chdir(cwd)
    return status, _files(work) - before


def assert_refused(status: int, err: str, new: set[str], line: str, words) -> str:
    """A row's run was refused: exit 2, one line ``ctxreg COMMAND: error: ...`` holding every one
    of ``words``, no traceback, no file written. Returns the line."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert status == 2 and "Traceback" not in err, (status, err)
    assert len(lines) == 1 and lines[0].startswith(f"ctxreg {line.split()[0]}: error: "), err
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert not new, f"files written: {sorted(new)}"
    return lines[0]


@pytest.mark.parametrize("name", list(BAD))
def test_a_bad_input_is_one_line_exit_2_and_writes_nothing(name, inputs, tmp_path, capsys):
    line, words = BAD[name]
    status, new = _run(line, inputs, tmp_path)
    assert_refused(status, capsys.readouterr().err, new, line, words)


@pytest.mark.parametrize("name", list(GOOD))
def test_a_valid_input_succeeds(name, inputs, tmp_path, capsys):
    line, expected = GOOD[name]
    status, new = _run(line, inputs, tmp_path)
    err = capsys.readouterr().err
    if name == "register":  # it ran to the end: exit 0 if registered, 3 if doubtful or failed (register/verdict.py)
        import json

        from register.verdict import EXIT_STATUS

        assert status == EXIT_STATUS[json.loads((tmp_path / "reg" / "result.json").read_text())["verdict"]], err
    else:
        assert status == 0, err
    assert set(expected) <= new, sorted(new)
    for out in (a for a in line.split() if a.endswith(".npy")):
        assert np.load(tmp_path / out).shape == (16, 16)  # written, or replaced when it existed
