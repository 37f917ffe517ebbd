"""``ctxreg register`` end to end on a synthetic X-ray written as DICOM, and its bad inputs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.conftest import REPO


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "register.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=REPO, timeout=600)


def _assert_exit_says_the_verdict(r, out) -> dict:
    """The run wrote every output and exited with its verdict's status (0 registered, 3 otherwise),
    the verdict its last printed line; returns result.json."""
    from register.verdict import EXIT_STATUS

    result = json.loads((out / "result.json").read_text())
    assert r.returncode == EXIT_STATUS[result["verdict"]], r.stderr
    assert r.stdout.strip().splitlines()[-1].startswith(f"verdict: {result['verdict']} (")
    return result


def _assert_recovered(out, truth) -> dict:
    """result.json of a run whose pose is within 1 deg, 3 mm in-plane and 15 mm in depth (the
    weakly observed direction) of ``truth``; returns the result."""
    result = json.loads((out / "result.json").read_text())
    est = np.array([result["params"][k] for k in ("phi", "theta", "psi", "tx", "ty", "tz")])
    assert np.abs(est[:3] - truth[:3]).max() < 1.0, est
    assert np.abs(est[3:5] - truth[3:5]).max() < 3.0, est
    assert abs(est[5] - truth[5]) < 15.0, est
    return result


@pytest.fixture(scope="module")
def synthetic_case(tmp_path_factory):
    """A phantom CT (NIfTI) and its DRR at a known pose, stored as a DX DICOM with geometry tags."""
    from register.xray.io import write_xray_dicom
    from sim.ct.anatomy import anatomy_center
    from sim.ct.io import save_nifti
    from sim.ct.phantom import make_pelvis_phantom
    from sim.projection.drr import DRRRenderer, RenderSettings

    d = tmp_path_factory.mktemp("reg")
    vol = make_pelvis_phantom(3, spacing_mm=3.0)
    ct = d / "ct.nii.gz"
    save_nifti(vol, ct)
    center = anatomy_center(vol)
    truth = np.array([8.0, -5.0, 4.0, 10.0, -8.0, 20.0])
    r = DRRRenderer(vol, RenderSettings(size=(192, 192)), center_lps=center)
    image = r.render_params(truth)[0]
    g = r.geometry
    xray = d / "xray.dcm"
    write_xray_dicom(xray, image, pixel_spacing_mm=g.pixel_spacing_mm, sdd_mm=g.sdd_mm, sod_mm=g.sod_mm)
    return ct, xray, truth, center


def test_register_recovers_the_pose_of_a_synthetic_dicom(synthetic_case, tmp_path):
    ct, xray, truth, center = synthetic_case
    start = truth + np.array([4.0, 3.0, -3.0, -8.0, 6.0, 15.0])
    out = tmp_path / "out"
    r = run_cli("register", "--ct", ct, "--xray", xray, "--init", *start, "--size", 96, 96,
                "--center", *center, "--out", out, "--verbose")
    assert r.returncode == 0, r.stderr
    # geometry from the DICOM tags, image resampled 192 -> 96 px; the DRRs match the target up
    # to the 16-bit storage and the resampling, so the pose comes back within a degree / few mm
    result = _assert_recovered(out, truth)
    assert result["geometry"]["sdd_mm"] == pytest.approx(1020.0)
    # the centre used and how it was found: the one given
    assert result["anatomy_center_lps_mm"] == pytest.approx(list(center))
    assert result["anatomy_center_how"] == "given: stated by the user (LPS mm)"
    assert "anatomy centre LPS" in r.stdout + r.stderr and "given: stated by the user" in r.stdout + r.stderr
    assert [s["step"] for s in result["preprocessing"]] == ["field", "median", "intensity", "normalize", "crop",
                                                           "polarity_check"]
    assert result["xray_input"]["polarity_check"]["inverted"] is False  # a bone-bright DRR stays so
    assert result["xray_input"]["geometry_sources"]["sdd_source"] == "DICOM DistanceSourceToDetector"
    assert "geometry: SDD 1020 mm (DICOM DistanceSourceToDetector)" in r.stdout
    for name in ("overlay.png", "checkerboard.png", "convergence.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG"
    # the X-ray's own pixels, each a 3 x 3 block (a 192 px X-ray is enlarged to >= 512 px), with the
    # verdict above and the legend below
    h, w, _ = np.asarray(Image.open(out / "overlay.png")).shape
    assert w == 3 * 192 and h > 3 * 192
    # a right pose of a clean DRR: registered, said last, exit 0
    assert result["verdict"] == "registered" and r.stdout.strip().splitlines()[-1].startswith("verdict: registered")
    assert set(result["verdict_evidence"]) >= {"similarity", "tone_fit", "runner_up", "search", "network_gap",
                                               "field_fraction"}
    # where the seconds went: every stage of the call (the default method: the network, the search),
    # in order, each >= 0, printed with --verbose; the registration's own split stays in stage_seconds
    timings = result["timings_s"]
    assert list(timings) == ["startup", "xray", "model", "ct", "prepare", "search_setup", "engine_setup", "register",
                             "polarity", "verdict", "write"]
    assert all(v >= 0 for v in timings.values()) and timings["startup"] > 0
    assert sum(result["stage_seconds"].values()) <= timings["register"] + 1e-3
    said = r.stderr[r.stderr.index("where the seconds went"):]
    assert all(f"  {k}: " in said for k in timings) and "total since the process started" in said


@pytest.fixture(scope="module")
def fluoro_case(synthetic_case, tmp_path_factory):
    """The synthetic case as a C-arm shows it: Poisson noise, round collimator black outside,
    fluoroscopy display (log, bone dark, gamma 0.8, edge enhancement), 12-bit RF DICOM."""
    from register.xray.io import load_xray, write_xray_dicom
    from sim.physics.display import Collimator, DisplayChain

    ct, xray, truth, center = synthetic_case
    x = load_xray(xray)
    L = x.pixels.astype(np.float64)
    raw = np.random.default_rng(0).poisson(2e4 * np.exp(-L / max(L.max(), 1e-9) * 4.0)).astype(np.float64)
    col = Collimator(shape="circle", center=(0.52, 0.47), radius=0.42)
    chain = DisplayChain(polarity="bone-dark", gamma=0.8, unsharp_sigma_px=2.0, unsharp_amount=0.5, bits=12)
    frame = chain.apply(col.apply(raw), 2e4, col.mask(*raw.shape))
    d = tmp_path_factory.mktemp("fluoro")
    path = write_xray_dicom(d / "fluoro.dcm", frame, pixel_spacing_mm=x.pixel_spacing_mm, sdd_mm=x.sdd_mm,
                            sod_mm=x.sod_mm, bits_stored=12, modality="RF")
    return ct, path, truth, center, col.mask(*raw.shape)


def test_register_handles_a_collimated_fluoroscopy_frame_by_default(fluoro_case, tmp_path):
    ct, xray, truth, center, field = fluoro_case
    start = truth + np.array([3.0, -2.0, 2.0, 6.0, -5.0, 10.0])
    out = tmp_path / "out"
    r = run_cli("register", "--ct", ct, "--xray", xray, "--init", *start, "--size", 96, 96,
                "--center", *center, "--out", out)
    assert r.returncode == 0, r.stderr
    result = _assert_recovered(out, truth)
    inp = result["xray_input"]
    assert inp["field"]["kind"] == "circle" and inp["field"]["outside"] == "black"
    assert inp["intensity"]["polarity"] == "bone-dark" and inp["intensity"]["steps"] == ["invert"]
    assert "field: circle, black outside" in r.stdout and "intensity: display" in r.stdout
    o = np.asarray(Image.open(out / "overlay.png"))
    cyan = (o[..., 0] < 80) & (o[..., 1] > 180) & (o[..., 2] > 200)
    assert cyan.sum() > 300  # the field's outline


def test_register_says_which_geometry_it_assumed(synthetic_case, tmp_path):
    from register.xray.io import load_xray

    ct, xray, truth, center = synthetic_case
    png = tmp_path / "plain.png"
    px = load_xray(xray).pixels
    Image.fromarray((255 * (px - px.min()) / np.ptp(px)).astype(np.uint8)).save(png)
    r = run_cli("register", "--ct", ct, "--xray", png, "--init", *truth, "--size", 64, 64, "--center", *center,
                "--sdd", 1000, "--out", tmp_path / "o")
    assert r.returncode == 0, r.stderr
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("geometry:")]
    assert len(line) == 1 and "SDD 1000 mm (flag --sdd)" in line[0] and "(assumed)" in line[0], r.stdout


@pytest.mark.parametrize("make, words", [
    (lambda: np.full((64, 64), 700, np.uint16), "constant"),
    (lambda: np.where(np.hypot(*(np.indices((128, 128)) - 64)) < 15,
                      np.random.default_rng(0).integers(500, 900, (128, 128)), 0).astype(np.uint16), "%"),
])
def test_register_refuses_a_flat_image_or_a_tiny_field(synthetic_case, tmp_path, make, words):
    from register.xray.io import write_xray_dicom

    ct, *_ = synthetic_case
    path = write_xray_dicom(tmp_path / "bad.dcm", make(), pixel_spacing_mm=1.0, sdd_mm=1020.0, sod_mm=700.0)
    r = run_cli("register", "--ct", ct, "--xray", path, "--out", tmp_path / "o")
    assert r.returncode == 2 and "Traceback" not in r.stderr and words in r.stderr, r.stderr


@pytest.mark.parametrize("extra, words", [
    (["--init", "1", "2"], "six finite numbers"),
    (["--preprocess", "sharpen"], "sharpen"),
])
def test_bad_register_arguments_are_one_line_errors(synthetic_case, tmp_path, extra, words):
    ct, xray, *_ = synthetic_case
    r = run_cli("register", "--ct", ct, "--xray", xray, "--out", tmp_path, *extra)
    assert r.returncode == 2 and "Traceback" not in r.stderr and words in r.stderr, r.stderr


def test_register_rejects_a_missing_or_colour_xray(synthetic_case, tmp_path):
    from PIL import Image

    ct, *_ = synthetic_case
    r = run_cli("register", "--ct", ct, "--xray", tmp_path / "none.dcm")
    assert r.returncode == 2 and "none.dcm" in r.stderr and "Traceback" not in r.stderr
    rgb = np.zeros((32, 32, 3), np.uint8)
    rgb[..., 0] = 200
    Image.fromarray(rgb).save(tmp_path / "colour.png")
    r = run_cli("register", "--ct", ct, "--xray", tmp_path / "colour.png")
    assert r.returncode == 2 and "grey" in r.stderr and "Traceback" not in r.stderr


def test_contextual_register_saves_a_consistent_trajectory(synthetic_case, tmp_path):
    """With any network (here an untrained tiny one) the saved trajectory is the iteration it ran:
    it starts at --init, and each pose is the previous one moved by 0.15 of its predicted gradient."""
    import torch

    from learn.labels import apply_update
    from learn.model import pose_update_net
    from sim.projection.geometry import pose_from_params

    torch.manual_seed(0)
    ckpt = tmp_path / "tiny.pt"
    torch.save({"model": pose_update_net(backbone="tiny").state_dict(), "image_size": [32, 32],
                "config": {"backbone": "tiny", "preprocess": ["normalize"], "head_channels": 64}}, ckpt)
    ct, xray, truth, center = synthetic_case
    start = np.array([1.0, 2.0, -1.0, 5.0, -5.0, 10.0])
    out = tmp_path / "ctx"
    r = run_cli("register", "--ct", ct, "--xray", xray, "--init", *start, "--size", 64, 64, "--center", *center,
                "--method", "contextual", "--model", ckpt, "--out", out)
    # an untrained network ends anywhere: its pose is not trusted, yet every output is written
    assert _assert_exit_says_the_verdict(r, out)["verdict"] != "registered"
    t = np.load(out / "trajectory.npz")
    params, g, drrs = t["params_deg_mm"], t["g_rad_mm"], t["drrs"]
    k = len(g)
    assert params.shape == (k + 1, 6) and drrs.shape == (k, 64, 64) and t["xray"].shape == (64, 64)
    np.testing.assert_allclose(params[0], start, atol=1e-9)
    sod = json.loads((out / "result.json").read_text())["geometry"]["sod_mm"]
    for i in range(k - 1):
        expect = apply_update(pose_from_params(params[i], sod), g[i], 0.15)
        np.testing.assert_allclose(pose_from_params(params[i + 1], sod), expect, atol=1e-6)
    assert (out / "trajectory.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("size, expect", [((128, 128), (64, 128)), ((64, 64), (32, 64)), ((128, 32), (16, 32)),
                                          ((40, 200), (40, 80)), (96, (48, 96))])
def test_size_is_the_box_the_optimisers_image_fits_inside(size, expect):
    """``--size H W`` (and ``size=`` of prepare_xray / register_xray): a 100 x 200 X-ray keeps its
    aspect and becomes the largest image inside H x W with sides multiples of 4; the detector's
    extent is kept (spacing x width). The default 128 x 128 is the former longer side 128."""
    from register.xray.prepare import prepare_xray
    from register.xray.io import XRayImage

    pixels = np.random.default_rng(0).random((100, 200)).astype(np.float32)
    x = XRayImage(pixels, pixel_spacing_mm=0.3, sdd_mm=1000.0, sod_mm=600.0, source="wide")
    p = prepare_xray(x, steps=["normalize"], size=size)
    assert p.image.shape == expect and (p.geometry.height, p.geometry.width) == expect
    assert p.geometry.pixel_spacing_mm * p.geometry.width == pytest.approx(0.3 * 200, rel=0.02)
    assert p.summary()["optimiser_size"] == list(expect)


@pytest.mark.parametrize("size", [(0, 0), (4, 128), (128, 5000), (1, 2, 3)])
def test_sizes_outside_the_declared_range_are_refused(size):
    from register.xray.prepare import prepare_xray
    from register.xray.preprocess import PreprocessError
    from register.xray.io import XRayImage

    x = XRayImage(np.ones((16, 16), np.float32), pixel_spacing_mm=0.3, sdd_mm=1000.0, sod_mm=600.0, source="x")
    with pytest.raises(PreprocessError, match=r"\[8, 4096\]"):
        prepare_xray(x, steps=["normalize"], size=size)


def test_orientations_are_pillows_transposes_and_keep_the_geometry():
    """Each --orient name turns the pixels as Pillow's transpose of the same name does, keeps the
    geometry values, records itself, and swaps an anisotropic (row, column) spacing on a quarter turn."""
    from register.xray.io import ORIENTATIONS, XRayImage, XRayInputError

    a = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    x = XRayImage(a.astype(np.float32), pixel_spacing_mm=0.3, sdd_mm=1000.0, sod_mm=600.0, source="a",
                  meta={"pixel_spacing_rc_mm": [0.3, 0.31]})
    for name in ORIENTATIONS:
        turned = x.reoriented(name)
        if name == "none":
            assert turned is x
            continue
        want = np.asarray(Image.fromarray(a).transpose(getattr(Image.Transpose, name.upper().replace("-", "_"))))
        np.testing.assert_array_equal(turned.pixels, want.astype(np.float32))
        assert (turned.pixel_spacing_mm, turned.sdd_mm, turned.sod_mm) == (0.3, 1000.0, 600.0)
        assert turned.meta["orientation"] == name
        quarter = name in ("rotate-90", "rotate-270", "transpose", "transverse")
        assert turned.meta["pixel_spacing_rc_mm"] == ([0.31, 0.3] if quarter else [0.3, 0.31])
    with pytest.raises(XRayInputError, match="--orient must be one of"):
        x.reoriented("mirror")


def test_register_undoes_a_stored_mirror_or_rotation_with_orient(synthetic_case, tmp_path):
    """The synthetic DRR stored mirrored (left-right) and rotated a quarter turn: --orient undoes
    each and the pose comes back as from the unturned file; the mirrored file registered as it is
    ends elsewhere (so the option is what does it)."""
    from register.xray.io import load_xray, write_xray_dicom

    ct, xray, truth, center = synthetic_case
    x = load_xray(xray)
    start = truth + np.array([4.0, 3.0, -3.0, -8.0, 6.0, 15.0])
    for stored, orient in ((x.pixels[:, ::-1], "flip-left-right"), (np.rot90(x.pixels, 1), "rotate-270")):
        path = write_xray_dicom(tmp_path / f"{orient}.dcm", np.ascontiguousarray(stored),
                                pixel_spacing_mm=x.pixel_spacing_mm, sdd_mm=x.sdd_mm, sod_mm=x.sod_mm)
        out = tmp_path / orient
        r = run_cli("register", "--ct", ct, "--xray", path, "--init", *start, "--size", 96, 96, "--center",
                    *center, "--method", "cmaes", "--orient", orient, "--out", out)
        _assert_exit_says_the_verdict(r, out)
        assert f"orientation: {orient} (--orient)" in r.stdout
        result = _assert_recovered(out, truth)
        assert result["xray_input"]["orientation"] == orient
    out = tmp_path / "as-stored"
    r = run_cli("register", "--ct", ct, "--xray", tmp_path / "flip-left-right.dcm", "--init", *start, "--size", 96,
                96, "--center", *center, "--method", "cmaes", "--out", out)
    _assert_exit_says_the_verdict(r, out)
    est = np.array([json.loads((out / "result.json").read_text())["params"][k]
                    for k in ("phi", "theta", "psi", "tx", "ty", "tz")])
    assert np.abs(est[:3] - truth[:3]).max() > 2.0 or np.abs(est[3:5] - truth[3:5]).max() > 5.0, est


def test_a_huge_frame_is_binned_at_once_and_registers_as_the_original(synthetic_case, tmp_path):
    """The 192 px DRR blown up 11 x to 2112 px (pitch / 11): over MAX_XRAY_SIDE_PX, so binned 2 x 2
    to 1056 px (pitch x 2) when read, said in one line; the pose comes back as from the original."""
    from register.api import MAX_XRAY_SIDE_PX
    from register.xray.io import load_xray, write_xray_dicom

    ct, xray, truth, center = synthetic_case
    x = load_xray(xray)
    big = np.repeat(np.repeat(x.pixels, 11, axis=0), 11, axis=1)
    assert MAX_XRAY_SIDE_PX < big.shape[0] <= 2 * MAX_XRAY_SIDE_PX
    path = write_xray_dicom(tmp_path / "big.dcm", big, pixel_spacing_mm=x.pixel_spacing_mm / 11, sdd_mm=x.sdd_mm,
                            sod_mm=x.sod_mm)
    start = truth + np.array([4.0, 3.0, -3.0, -8.0, 6.0, 15.0])
    out = tmp_path / "out"
    r = run_cli("register", "--ct", ct, "--xray", path, "--init", *start, "--size", 96, 96, "--center", *center,
                "--method", "cmaes", "--out", out)
    _assert_exit_says_the_verdict(r, out)
    assert "2112 x 2112 px binned 2 x 2 to 1056 x 1056 px" in r.stdout + r.stderr
    result = _assert_recovered(out, truth)
    assert result["geometry"]["sdd_mm"] == pytest.approx(1020.0)


def test_serve_registers_each_frame_of_a_case_in_one_process(synthetic_case, tmp_path):
    """Paths on stdin, one JSON line per frame: the pose of each (the same frame twice gets its own
    folders, the second _2), a refused frame named with its error while the next goes on; then a
    watched folder, stopped after --frames."""
    ct, xray, truth, center = synthetic_case
    start = truth + np.array([4.0, 3.0, -3.0, -8.0, 6.0, 15.0])
    common = ("--ct", ct, "--init", *start, "--size", 64, 64, "--center", *center, "--method", "cmaes")
    out = tmp_path / "serve"
    r = subprocess.run([sys.executable, "-m", "register.cli", "serve", *map(str, common), "--out", str(out)],
                       input=f"{xray}\n{tmp_path / 'missing.dcm'}\n\n{xray}\n", capture_output=True, text=True,
                       cwd=REPO, timeout=600)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stdout.splitlines() if line.startswith("{")]
    assert [line.get("out") for line in lines] == [str(out / "xray"), None, str(out / "xray_2")]
    assert "missing.dcm" in lines[1]["xray"] and "not found" in lines[1]["error"]
    for line in (lines[0], lines[2]):
        _assert_recovered(Path(line["out"]), truth)
        assert line["seconds"] > 0 and line["search_status"].startswith("none")
        assert line["verdict"] == json.loads((Path(line["out"]) / "result.json").read_text())["verdict"]
        assert line["verdict_reasons"]
    assert r.stderr.count("ready; frames from stdin") == 1  # the CT and method loaded once
    folder = tmp_path / "incoming"
    folder.mkdir()
    (folder / "frame1.dcm").write_bytes(Path(xray).read_bytes())
    (folder / "notes.txt").write_text("not an X-ray")
    r = run_cli("serve", *common, "--xray", folder, "--frames", 1, "--out", tmp_path / "watched")
    assert r.returncode == 0, r.stderr
    (line,) = [json.loads(x) for x in r.stdout.splitlines() if x.startswith("{")]
    assert line["out"] == str(tmp_path / "watched" / "frame1")
    _assert_recovered(tmp_path / "watched" / "frame1", truth)
    bad = run_cli("serve", *common, "--xray", tmp_path / "nowhere")
    assert bad.returncode == 2 and "not a folder to watch" in bad.stderr
    # every frame refused: no "wrote", exit 2, the count said
    r = subprocess.run([sys.executable, "-m", "register.cli", "serve", *map(str, common), "--out", str(tmp_path / "none")],
                       input=f"{tmp_path / 'missing.dcm'}\n", capture_output=True, text=True, cwd=REPO, timeout=600)
    assert r.returncode == 2 and "no frame was registered (1 refused)" in r.stderr and "wrote" not in r.stdout
