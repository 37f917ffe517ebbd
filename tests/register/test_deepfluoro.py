"""The DeepFluoro reader and ``ctxreg evaluate --deepfluoro`` on files of the documented layout.

The real file cannot be downloaded here, so the files are written from known truth
(:mod:`register.datasets.deepfluoro_synthetic`): ctxreg poses through the converter and a non-trivial
C-arm world frame, frames rendered with realistic physics. Truth checks:

* the reader gives back the written CT (voxels and LPS affine exactly), label map, landmarks,
  intrinsics, extrinsic and ctxreg poses (1e-9: float64 round trips);
* the file's geometry (its landmarks projected with its intrinsics and ground-truth poses) meets its
  2-D landmarks to 1e-6 px, and an independent pinhole projection written here agrees;
* the frame handed to registration is oriented right: a DRR rendered at the truth correlates with
  its log (NCC > 0.9), the unflipped frame does not;
* ``ctxreg evaluate --deepfluoro`` from the truth reports a near-zero initial mTRE and a final one under
  2 mm (the binned 1.55 mm pixel); from AP it registers every frame (< 10 mm);
* bad files (another layout, the preprocessed file, a missing specimen, a truncated file, a text
  file, NaN in a pose, a positive focal length) are one line each.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from register.convert import to_deepfluoro
from register.datasets.deepfluoro import DeepFluoroError, DeepFluoroFile
from register.datasets.deepfluoro_synthetic import (DEEPFLUORO_WORLD_FROM_CAMERA, SyntheticSettings, canonical_lps,
                                                    synthesize_deepfluoro)
from register.engines.metrics import ncc
from sim.ct.volume import CTVolume

#: ctxreg pose parameters (deg, mm) of the synthetic frames: near AP, as a C-arm frame of the pelvis.
PARAMS = [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [10.0, 5.0, -5.0, 20.0, -10.0, 30.0], [-12.0, 3.0, 6.0, -15.0, 10.0, -25.0]]


def _small_ct() -> CTVolume:
    """A 3-D CT in an RAS-stored orientation (axes flipped in LPS) with a bone 'pelvis' of two blocks."""
    hu = np.full((40, 36, 32), -50.0, np.float32)
    hu[6:18, 8:28, 8:24] = 900.0
    hu[22:34, 8:28, 8:24] = 900.0
    hu[16:24, 14:22, 10:14] = 1100.0
    affine = np.diag([-4.0, -4.0, 4.0, 1.0])
    affine[:3, 3] = (80.0, 70.0, -60.0)
    return CTVolume(hu=hu, affine=affine, source="test:small")


@pytest.fixture(scope="module")
def small_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("df") / "small.h5"
    info = synthesize_deepfluoro(path, _small_ct(), PARAMS, settings=SyntheticSettings(binning=16, rot_180_every=2,
                                                                                        landmarks=8))
    return path, info


@pytest.fixture(scope="module")
def pelvis_file(tmp_path_factory, pelvis_ct_path):
    from sim import load_ct

    path = tmp_path_factory.mktemp("df") / "pelvis.h5"
    info = synthesize_deepfluoro(path, load_ct(pelvis_ct_path), PARAMS, settings=SyntheticSettings(binning=8,
                                                                                                   rot_180_every=2))
    return path, info


def test_canonical_lps_keeps_every_voxel_where_it_was():
    ct = _small_ct()
    can = canonical_lps(ct)
    assert np.allclose(can.affine[:3, :3], np.diag(np.abs(np.diag(ct.affine[:3, :3]))))
    rng = np.random.default_rng(0)
    ijk = np.stack([rng.integers(0, n, 50) for n in ct.shape], axis=1)
    lps = ct.voxel_to_lps(ijk.astype(float))
    back = np.rint(can.lps_to_voxel(lps)).astype(int)
    assert np.array_equal(can.hu[tuple(back.T)], ct.hu[tuple(ijk.T)])


def test_reader_gives_back_what_was_written(small_file):
    path, info = small_file
    g = info["geometry"]
    with DeepFluoroFile(path) as f:
        assert f.specimens == ["17-1882"]
        assert f.resolve(1) == f.resolve("17-1882") == "17-1882"
        _, K = to_deepfluoro(np.eye(4), g, np.zeros(3))
        assert np.array_equal(f.params.intrinsic, K) and np.array_equal(f.params.extrinsic, DEEPFLUORO_WORLD_FROM_CAMERA)
        assert (f.params.rows, f.params.cols) == (g.height, g.width)
        assert f.params.sdd_mm == pytest.approx(1020.0, rel=1e-12)
        spec = f.specimen("17-1882")
        written = canonical_lps(_small_ct())
        assert np.array_equal(spec.volume.hu, written.hu)
        assert np.allclose(spec.volume.affine, written.affine, atol=1e-12)
        assert set(np.unique(spec.volume.labels)) == {0, 1, 2}
        assert spec.labels_def[1] == "left-hemipelvis"
        assert np.allclose(spec.center_lps, info["center_lps"], atol=1e-9)
        assert spec.landmarks_lps.keys() == info["landmarks_lps"].keys()
        for name, p in info["landmarks_lps"].items():
            assert np.allclose(spec.landmarks_lps[name], p, atol=1e-12)
        assert len(spec) == len(PARAMS)
        for i, frame in enumerate(spec):
            assert frame.rot_180_for_up == (i % 2 == 1)
            T, geometry = frame.truth(spec.center_lps, sod_mm=700.0)
            assert np.allclose(T, info["poses"][i], atol=1e-9)
            assert geometry.sdd_mm == pytest.approx(1020.0) and geometry.pixel_spacing_mm == pytest.approx(0.194 * 16)
            x = frame.xray(sod_mm=700.0)
            assert not x.attenuation_bright and x.sdd_mm == pytest.approx(1020.0)
            flip = x.pixels[::-1, :] if frame.rot_180_for_up else x.pixels[:, ::-1]
            assert np.array_equal(flip, frame.pixels)
            assert set(frame.femurs) == {"left", "right"}


def test_geometry_check_and_an_independent_projection_agree(small_file):
    path, info = small_file
    with DeepFluoroFile(path) as f:
        spec = f.specimen(1)
        K, X = f.params.intrinsic, f.params.extrinsic
        f_px, cx, cy = -K[0, 0], K[0, 2], K[1, 2]
        for frame in spec:
            check = frame.reprojection_px(spec.landmarks_lps)
            assert check["count"] >= 3
            assert check["stored_max_px"] < 1e-6 and check["ctxreg_max_px"] < 1e-6
            # independent: world -> camera by hand, pinhole with the camera's +z toward the source
            cam_to_vol = frame.cam_to_pelvis_vol
            for name, p in spec.landmarks_lps.items():
                world = np.linalg.solve(cam_to_vol, np.r_[p, 1.0])
                x, y, z = (X @ world)[:3]
                assert z < 0  # in front of the source: the camera looks down -z
                uv = np.array([cx + f_px * x / -z, cy + f_px * y / -z])
                assert np.allclose(uv, frame.landmarks_px[name], atol=1e-6)


def test_frames_reach_registration_in_the_cts_view(pelvis_file):
    """The DRR at the true pose matches the frame as handed to registration, not the stored one."""
    from sim.projection.drr import DRRRenderer, RenderSettings

    path, _ = pelvis_file
    with DeepFluoroFile(path) as f:
        spec = f.specimen(1)
        assert len(spec) == len(PARAMS)  # the frames in the order written
        for k, frame in enumerate(spec):
            T, g = frame.truth(spec.center_lps, sod_mm=700.0)
            drr = DRRRenderer(spec.volume, RenderSettings(size=(g.height, g.width)), center_lps=spec.center_lps,
                              geometry=g).render(T)[0]
            inner = (slice(12, -12), slice(12, -12))  # inside the collimator's border
            ours = -np.log(frame.xray().pixels.astype(np.float64))
            stored = -np.log(frame.pixels.astype(np.float64))
            assert ncc(ours[inner], drr[inner]) > 0.9
            # the stored frame is mirrored (or turned): it must match worse. At AP the pelvis is
            # centred and nearly mirror-symmetric, so its mirror image still matches well (0.94
            # against 0.99); the oblique frames tell the two apart clearly
            if not any(PARAMS[k]):  # the AP frame
                assert ncc(stored[inner], drr[inner]) < ncc(ours[inner], drr[inner]) - 0.02
            else:
                assert ncc(stored[inner], drr[inner]) < 0.8


def _evaluate_here(capsys, *args) -> tuple[int, str]:
    """``ctxreg evaluate ARGS`` in this process (no interpreter start: the refusals come before any work):
    ``(exit status, stderr)``."""
    from register.cli import main

    capsys.readouterr()
    rc = main(["evaluate", *map(str, args)])
    return rc, capsys.readouterr().err


def _evaluate(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "register.cli", "evaluate", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=900)


def test_evaluate_from_the_truth_stays_there(pelvis_file, tmp_path):
    path, _ = pelvis_file
    out = tmp_path / "truth"
    r = _evaluate("--deepfluoro", path, "--start", "truth", "--method", "cmaes", "--out", out)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    check = next(i for i, line in enumerate(lines) if line.startswith("geometry check"))
    first = next(i for i, line in enumerate(lines) if " frame 000 " in line)
    assert check < first and "0.000 px" in lines[check]
    rows = (out / "cases.csv").read_text().splitlines()
    assert len(rows) == 1 + len(PARAMS)
    summary = json.loads((out / "summary.json").read_text())
    allf = summary["summary"]["cmaes"]["all"]
    assert allf["frames"] == len(PARAMS)
    assert allf["initial_mtre_mm"]["max"] < 1e-6
    assert allf["mtre_mm"]["max"] < 2.0 and allf["under_10mm"] == 1.0
    assert summary["reprojection_px"]["17-1882"]["stored_mean_px"] < 1e-6
    assert (out / "table.md").exists() and list((out / "worst").glob("*_estimate.png"))


@pytest.mark.slow
def test_evaluate_registers_the_frames_from_ap(pelvis_file, tmp_path):
    path, _ = pelvis_file
    out = tmp_path / "ap"
    r = _evaluate("--deepfluoro", path, "--specimen", "1", "--out", out)
    assert r.returncode == 0, r.stderr
    allf = json.loads((out / "summary.json").read_text())["summary"]["contextual+cmaes"]["all"]
    assert allf["initial_under_10mm"] < 1.0  # the starts are far
    assert allf["under_10mm"] == 1.0 and allf["mtre_mm"]["median"] < 2.0


# ---------------------------------------------------------------------------------------------- bad input


def _copy(src: Path, dst: Path, edit) -> Path:
    dst.write_bytes(src.read_bytes())
    with h5py.File(dst, "r+") as f:
        edit(f)
    return dst


@pytest.mark.parametrize("case, expect", [
    ("other_layout", "not the DeepFluoro full-resolution layout"),
    ("preprocessed", "a preprocessed DeepFluoro file"),
    ("missing_specimen", "no specimen '5'"),
    ("truncated", "truncated"),
    ("text_file", "not a readable HDF5 file"),
    ("nan_pose", "NaN"),
    ("positive_focal", "with f > 0"),
    ("missing_pose", "no '17-1882/projections/000/gt-poses/cam-to-pelvis-vol'"),
])
def test_bad_files_are_one_line(small_file, tmp_path, capsys, case, expect):
    src, _ = small_file
    bad = tmp_path / f"{case}.h5"
    args = []
    if case == "other_layout":
        with h5py.File(bad, "w") as f:
            f["volume"] = np.zeros((2, 2, 2))
    elif case == "preprocessed":
        with h5py.File(bad, "w") as f:
            f.create_group("land-names")["num-lands"] = 14
            f.create_group("01")["projs"] = np.zeros((1, 4, 4))
    elif case == "missing_specimen":
        bad = src
        args = ["--specimen", "5"]
    elif case == "truncated":
        data = src.read_bytes()
        bad.write_bytes(data[: len(data) // 3])
    elif case == "text_file":
        bad.write_text("not hdf5\n")
    elif case == "nan_pose":
        def edit(f):
            f["17-1882/projections/000/gt-poses/cam-to-pelvis-vol"][0, 0] = np.nan
        _copy(src, bad, edit)
    elif case == "positive_focal":
        def edit(f):
            f["proj-params/intrinsic"][0, 0] *= -1
        _copy(src, bad, edit)
    elif case == "missing_pose":
        def edit(f):
            del f["17-1882/projections/000/gt-poses/cam-to-pelvis-vol"]
        _copy(src, bad, edit)
    rc, stderr = _evaluate_here(capsys, "--deepfluoro", bad, *args, "--method", "cmaes", "--out", tmp_path / "out")
    assert rc == 2, stderr
    err = stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ctxreg evaluate: error:"), stderr
    assert expect in err[0], err[0]


def test_reader_errors_are_input_errors(tmp_path):
    """The reader's refusals are user errors (one line on the command line), not tracebacks."""
    from sim.core.errors import InputError

    assert issubclass(DeepFluoroError, InputError)
    with pytest.raises(DeepFluoroError, match="file not found"):
        DeepFluoroFile(tmp_path / "none.h5")
    with pytest.raises(DeepFluoroError, match="a folder"):
        DeepFluoroFile(tmp_path)


def test_evaluate_refuses_the_simulated_protocols_options(small_file, tmp_path, capsys):
    path, _ = small_file
    rc, err = _evaluate_here(capsys, "--deepfluoro", path, "--cases", "3", "--out", tmp_path / "o")
    assert rc == 2 and "--cases" in err and "--deepfluoro" in err
    rc, err = _evaluate_here(capsys, "--cases", "3", "--specimen", "1", "--out", tmp_path / "o")
    assert rc == 2 and "--specimen" in err and "--deepfluoro only" in err
    rc, err = _evaluate_here(capsys, "--cases", "3", "--out", tmp_path / "o")
    assert rc == 2 and "--ct: required" in err


def test_optional_datasets_and_the_border_cut(small_file, tmp_path):
    """dir-mat (the identity throughout the data set) and rot-180-for-up may be absent; the border cut
    is symmetric, so the principal point stays the centre."""
    src, info = small_file

    def edit(f):
        del f["17-1882/vol/dir-mat"]
        del f["17-1882/projections/000/rot-180-for-up"]
        del f["17-1882/projections/000/image/dir-mat"]

    bare = _copy(src, tmp_path / "bare.h5", edit)
    with DeepFluoroFile(bare) as f:
        spec = f.specimen(1)
        assert np.allclose(spec.volume.affine, canonical_lps(_small_ct()).affine)
        frame = spec.projection(0)
        assert not frame.rot_180_for_up
        T, _ = frame.truth(spec.center_lps, sod_mm=700.0)
        assert np.allclose(T, info["poses"][0], atol=1e-9)
        whole, cut = frame.xray().pixels, frame.xray(border_px=5).pixels
        assert cut.shape == (whole.shape[0] - 10, whole.shape[1] - 10)
        assert np.array_equal(cut, whole[5:-5, 5:-5])
        with pytest.raises(DeepFluoroError, match="leaves less than 32 px"):
            frame.xray(border_px=whole.shape[0] // 2)


def test_an_interrupted_run_resumes_where_it_stopped(small_file, tmp_path):
    path, _ = small_file
    out = tmp_path / "run"
    common = ["--deepfluoro", path, "--start", "truth", "--method", "cmaes", "--size", "64", "64", "--out", out]
    r = _evaluate(*common)
    assert r.returncode == 0, r.stderr
    full = json.loads((out / "progress.json").read_text())
    assert len(full["rows"]) == len(PARAMS)
    # an interruption after the first frame: progress.json holds one row
    (out / "progress.json").write_text(json.dumps({**full, "rows": full["rows"][:1]}))
    r = _evaluate(*common, "--resume")
    assert r.returncode == 0, r.stderr
    assert f"resuming: 1 of {len(PARAMS)} registrations done" in r.stdout
    assert " frame 000 " not in r.stdout and " frame 001 " in r.stdout
    again = json.loads((out / "progress.json").read_text())["rows"]
    assert again[0] == full["rows"][0] and len(again) == len(PARAMS)
    assert len((out / "cases.csv").read_text().splitlines()) == 1 + len(PARAMS)
    # another protocol cannot continue it
    r = _evaluate(*common[:-2], "--start", "ap", "--out", out, "--resume")
    assert r.returncode == 2 and "settings.start" in r.stderr, r.stderr


def test_a_damaged_or_changed_progress_is_refused_and_a_specimen_named_twice_runs_once(small_file, tmp_path, capsys):
    """--resume with a progress.json whose rows are damaged ends in one line naming the file; a
    file changed in place at the same size is another run (its content hash, not its size); the
    same specimen by number and by name is registered once."""
    import shutil

    path, _ = small_file
    copy = tmp_path / "copy.h5"
    shutil.copy(path, copy)
    with DeepFluoroFile(copy) as f:
        name = f.specimens[0]
    out = tmp_path / "run"
    common = ["--deepfluoro", copy, "--start", "truth", "--method", "cmaes", "--size", "64", "64", "--out", out,
              "--specimen", "1", name]
    rc, err = _evaluate_here(capsys, *common)
    assert rc == 0, err
    full = json.loads((out / "progress.json").read_text())
    assert len(full["rows"]) == len(PARAMS)  # each frame once, not once per naming
    row = full["rows"][0]
    for rows, words in (("abc", "its rows are str, not a list"),
                        ([{k: v for k, v in row.items() if k != "specimen"}], "row 0 has no specimen"),
                        ([{**row, "frame": "0"}], "row 0 has no frame of type int"),
                        ([row, 7], "row 1 is int, not a table")):
        (out / "progress.json").write_text(json.dumps({**full, "rows": rows}))
        rc, err = _evaluate_here(capsys, *common, "--resume")
        assert rc == 2 and "is damaged" in err and words in err and err.count("\n") == 1, err
    (out / "progress.json").write_text(json.dumps({**full, "rows": full["rows"][:1]}))
    size = copy.stat().st_size
    with h5py.File(copy, "r+") as h:  # one value changed in place: the same size, other content
        found = []
        h.visititems(lambda k, v: found.append(k) if isinstance(v, h5py.Dataset) and v.dtype.kind == "f"
                     and v.size > 0 and not found else None)
        data = h[found[0]]
        flat = data[()].reshape(-1)
        flat[0] += 1.0
        data[()] = flat.reshape(data.shape)
    assert copy.stat().st_size == size
    rc, err = _evaluate_here(capsys, *common, "--resume")
    assert rc == 2 and "file_sha256" in err, err


def test_start_params_of_every_start_mode():
    """The starts both protocols share (register.evaluation.evaluate.start_params)."""
    from register.evaluation.evaluate import start_params

    targets = np.random.default_rng(1).uniform(-30, 30, (200, 6))
    rng = np.random.default_rng(0)
    assert np.array_equal(start_params("ap", targets, rng), np.zeros_like(targets))
    assert np.array_equal(start_params("truth", targets, rng), targets)
    init = (180.0, 0, 0, 1, 2, 3)
    assert np.array_equal(start_params("pose", targets, rng, init=init), np.tile(init, (200, 1)))
    local = start_params("local", targets, rng, local_rot_deg=6.0, local_trans_mm=12.0) - targets
    rot, trans = np.linalg.norm(local[:, :3], axis=1), np.linalg.norm(local[:, 3:], axis=1)
    assert rot.max() <= 6.0 / np.sqrt(3) + 1e-12 and trans.max() <= 12.0 + 1e-12
    assert rot.max() > 0.8 * 6.0 / np.sqrt(3) and trans.max() > 0.8 * 12.0  # the bounds are reached, not shrunk


def test_frames_on_a_local_dask_cluster_give_the_sequential_rows(small_file, tmp_path):
    """``--scheduler local:2``: every frame registered on a worker (the file opened there), the rows in
    the sequential run's order and equal to them but for the seconds."""
    import csv

    path, _ = small_file
    common = ["--deepfluoro", path, "--start", "truth", "--method", "cmaes", "--size", "64", "64"]
    here = _evaluate(*common, "--out", tmp_path / "here")
    assert here.returncode == 0, here.stderr
    dask = _evaluate(*common, "--scheduler", "local:2", "--out", tmp_path / "dask")
    assert dask.returncode == 0, dask.stderr
    assert "on a local Dask cluster of 2 worker processes" in dask.stderr

    def rows(folder):
        with open(folder / "cases.csv") as f:
            return [{k: v for k, v in r.items() if k != "time_s"} for r in csv.DictReader(f)]

    assert len(rows(tmp_path / "here")) == len(PARAMS) and rows(tmp_path / "here") == rows(tmp_path / "dask")
