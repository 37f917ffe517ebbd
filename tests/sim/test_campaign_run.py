"""Campaign runs: determinism, resume after kill -9, parts of the work, splits, the reader; and the
refusals before any work (output path, another campaign, a busy folder, a CT out of view), workers
that die with their parent, and shards checked before they are read."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sim.campaign import dataset as ds
from tests.conftest import REPO

CAMPAIGN = """
[campaign]
name = "{name}"
seed = 7
images_per_ct = {n}
shard_size = {shard}

[scene]
name = "cios_fusion"
size = [48, 48]

[[physics]]
name = "line"
level = "line"

[[physics]]
name = "line_trilinear"
level = "line"
ray_model = "trilinear"

[split]
train = 0.5
val = 0.0
test = 0.5

[[cts]]
path = "{ct0}"

[[cts]]
path = "{ct1}"
virtual_patients = {vp}

[outputs]
bone_mask = true
projected_center = true
"""


@pytest.fixture(scope="module")
def small_cts(tmp_path_factory):
    """Two phantoms at 4 mm as NIfTI (fast to load in every worker)."""
    from sim.ct.phantom import write_phantom_nifti

    d = tmp_path_factory.mktemp("cts")
    paths = []
    for seed in (1, 2):
        p = d / f"phantom{seed}.nii.gz"
        write_phantom_nifti(p, seed, spacing_mm=4.0)
        paths.append(p)
    return paths


def write_campaign(folder: Path, cts, *, name="t", n=6, shard=2, vp=1) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.toml"
    path.write_text(CAMPAIGN.format(name=name, n=n, shard=shard, ct0=cts[0], ct1=cts[1], vp=vp))
    return path


def load(path):
    from sim.campaign.config import load_campaign

    return load_campaign(path)


def checksums(folder: Path) -> dict[str, str]:
    return {k: v["sha256"] for k, v in ds.read_manifest(folder)["shards"].items()}


@pytest.fixture(scope="module")
def reference(small_cts, tmp_path_factory):
    """One uninterrupted single-process run: the truth the other runs must equal."""
    from sim.campaign.runner import run_campaign

    base = tmp_path_factory.mktemp("ref")
    cfg = load(write_campaign(base, small_cts))
    manifest = run_campaign(cfg, base / "out", progress=False)
    return cfg, base / "out", manifest


def run_cli(*args, **kw):
    return subprocess.run([sys.executable, "-m", "register.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=REPO, **kw)


def test_reference_run_is_complete_with_exact_counts(reference):
    cfg, out, manifest = reference
    n_subjects = len(cfg.subjects())
    assert n_subjects == 3  # two CTs and one virtual patient
    assert manifest["complete"]
    assert manifest["counts"]["images"] == manifest["counts"]["expected"] == 3 * 6
    assert len(manifest["shards"]) == 3 * 3
    with ds.open_dataset(out, verify=True) as data:
        assert len(data) == 18
        keys = [(data[i]["subject"], int(data[i]["image_index"])) for i in range(len(data))]
        assert len(set(keys)) == len(keys)  # none duplicated
        assert sorted(keys) == [(s, i) for s in range(3) for i in range(6)]


def test_same_campaign_gives_bit_identical_shards(reference, small_cts, tmp_path):
    from sim.campaign.runner import run_campaign

    cfg, out, _ = reference
    again = load(write_campaign(tmp_path, small_cts))
    run_campaign(again, tmp_path / "out", progress=False)
    assert checksums(tmp_path / "out") == checksums(out)


def test_two_workers_give_the_same_bytes(reference, small_cts, tmp_path):
    cfg, out, _ = reference
    camp = write_campaign(tmp_path, small_cts)
    r = run_cli("simulate", camp, "--out", tmp_path / "out", "--workers", 2, timeout=600)
    assert r.returncode == 0, r.stderr
    assert checksums(tmp_path / "out") == checksums(out)


def _children(pid: int) -> list[int]:
    kids = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            kids += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return kids


@pytest.mark.slow
@pytest.mark.parametrize("victim, delay_s", [("all", 0.3), ("all", None), ("worker", None)])
def test_resume_after_kill_finishes_exactly(reference, small_cts, tmp_path, victim, delay_s):
    """kill -9 the whole run (or one worker) at a random point, then --resume."""
    _, ref_out, _ = reference
    camp = write_campaign(tmp_path, small_cts)
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "register.cli", "simulate", str(camp), "--out", str(out),
                             "--workers", "2"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    rng = np.random.default_rng(abs(hash((victim, delay_s))) % 2**32)
    if delay_s is None:  # wait until some shards exist, then a random extra moment
        t0 = time.monotonic()
        while not list((out / ds.SHARD_DIR).glob("*.sha256")) and time.monotonic() - t0 < 120:
            time.sleep(0.05)
        delay_s = float(rng.uniform(0.0, 0.5))
    time.sleep(delay_s)
    if victim == "all":
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
    else:
        kids = [k for k in _children(proc.pid) if Path(f"/proc/{k}/cmdline").read_bytes().count(b"spawn")]
        if not kids or proc.poll() is not None:
            os.killpg(proc.pid, signal.SIGKILL)
            pytest.skip("the run finished before a worker could be killed")
        os.kill(kids[0], signal.SIGKILL)
        _, err = proc.communicate(timeout=600)  # as the runs above: 300 s ran out once on a slow, loaded 2-core machine
        if proc.returncode != 0:  # the parent reports the dead worker in one line
            assert "worker process died" in err.decode() and "--resume" in err.decode(), err.decode()
            assert "Traceback" not in err.decode()
        os.killpg(proc.pid, signal.SIGKILL) if proc.poll() is None else None
    r = run_cli("simulate", camp, "--out", out, "--resume", timeout=600)
    assert r.returncode == 0, r.stderr
    assert checksums(out) == checksums(ref_out)
    with ds.open_dataset(out, verify=True) as data:
        assert len(data) == 18
    leftovers = [p.name for p in (out / ds.SHARD_DIR).iterdir() if ".tmp" in p.name]
    assert not leftovers


def test_parts_of_the_work_merge_by_resume(reference, small_cts, tmp_path):
    from sim.campaign.runner import run_campaign

    _, ref_out, _ = reference
    cfg = load(write_campaign(tmp_path, small_cts))
    out = tmp_path / "out"
    m1 = run_campaign(cfg, out, shard=(1, 2), progress=False)
    assert not m1["complete"] and (out / "manifest.part1-of-2.json").is_file()
    run_campaign(cfg, out, shard=(2, 2), resume=True, progress=False)
    mtimes = {p.name: p.stat().st_mtime_ns for p in (out / ds.SHARD_DIR).iterdir()}
    merged = run_campaign(cfg, out, resume=True, progress=False)
    assert merged["complete"]
    assert {p.name: p.stat().st_mtime_ns for p in (out / ds.SHARD_DIR).iterdir()} == mtimes  # nothing redone
    assert checksums(out) == checksums(ref_out)


def test_corrupt_shard_is_rendered_again_on_resume(reference, small_cts, tmp_path):
    import shutil

    from sim.campaign.runner import run_campaign

    _, ref_out, _ = reference
    out = tmp_path / "out"
    shutil.copytree(ref_out, out)
    victim = sorted((out / ds.SHARD_DIR).glob("*.h5"))[3]
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    with pytest.raises(ds.DatasetError, match="checksum"):
        ds.open_dataset(out, verify=True)
    cfg = load(write_campaign(tmp_path, small_cts))
    run_campaign(cfg, out, resume=True, progress=False)
    assert checksums(out) == checksums(ref_out)
    ds.open_dataset(out, verify=True).close()


def test_splits_are_per_ct_and_virtual_patients_follow_their_ct(reference):
    cfg, out, manifest = reference
    subjects = {s["index"]: s for s in manifest["subjects"]}
    vp = [s for s in subjects.values() if s["vp_index"] is not None]
    assert len(vp) == 1
    parent = next(s for s in subjects.values() if s["ct_index"] == vp[0]["ct_index"] and s["vp_index"] is None)
    assert vp[0]["split"] == parent["split"]
    assert vp[0]["virtual_patient"]["seed"] is not None  # recorded so it can be regenerated
    with ds.open_dataset(out) as data:
        seen: dict[int, set[str]] = {}
        for i in range(len(data)):
            item = data[i]
            seen.setdefault(item["subject"], set()).add(item["split"])
        assert all(len(v) == 1 for v in seen.values())
        per_split = {k: len(data.indices(k)) for k in data.splits}
    assert per_split == manifest["counts"]["images_per_split"]


def test_poses_stay_in_their_ranges_and_the_histogram_is_written(reference):
    cfg, out, _ = reference
    with ds.open_dataset(out) as data:
        params = data.arrays("params")
    bounds = cfg.poses.bounds()
    assert params.shape == (18, 6)
    assert np.all(params >= bounds[:, 0]) and np.all(params <= bounds[:, 1])
    assert (out / "pose_histogram.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_reader_round_trip_against_a_direct_render(reference, small_cts):
    from sim.ct.io import load_ct
    from sim.projection.geometry import pose_from_params, project_points
    from sim.projection.drr import DRRRenderer, RenderSettings

    cfg, out, manifest = reference
    with ds.open_dataset(out) as data:
        item = data[len(data) - 1 - 6]  # an image of subject 1 (the second CT, not the virtual patient)
        assert item["subject"] == 1
        meta = data.subjects[1]
    vol = load_ct(small_cts[1])
    r = DRRRenderer(vol, RenderSettings(size=(48, 48)), center_lps=meta["anatomy_center_lps_mm"])
    pose = pose_from_params(item["params"], r.geometry.sod_mm)
    np.testing.assert_allclose(item["pose"], pose, atol=1e-12)
    np.testing.assert_array_equal(item["images"]["line"], r.render(pose)[0])
    np.testing.assert_allclose(item["projection"], r.projection_matrix(pose), atol=1e-9)
    c = np.asarray(meta["anatomy_center_lps_mm"])[None]
    np.testing.assert_allclose(item["projected_center"], project_points(item["projection"], c)[0], atol=1e-9)
    assert set(item["images"]) == {"line", "line_trilinear"}
    rel = np.linalg.norm(item["images"]["line"] - item["images"]["line_trilinear"]) / np.linalg.norm(item["images"]["line"])
    assert rel < 0.05  # same pose, two ray models
    assert item["bone_mask"].dtype == np.uint8 and 0 < item["bone_mask"].mean() < 1


def test_refusals_name_the_problem(reference, small_cts, tmp_path):
    from sim.campaign.runner import CampaignError, run_campaign

    cfg, out, _ = reference
    with pytest.raises(CampaignError, match="not empty"):
        run_campaign(cfg, out, progress=False)
    other = load(write_campaign(tmp_path, small_cts, n=5))
    with pytest.raises(CampaignError, match="different campaign"):
        run_campaign(other, out, resume=True, progress=False)
    r = run_cli("simulate", tmp_path / "missing.toml")
    assert r.returncode == 2 and "missing.toml" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("simulate", write_campaign(tmp_path, small_cts), "--shard", "3/2", "--out", tmp_path / "x")
    assert r.returncode == 2 and "K <= N" in r.stderr
    partial = tmp_path / "partial"
    run_campaign(other, partial, shard=(1, 3), progress=False)
    with pytest.raises(ds.DatasetError, match="no manifest.json"):
        ds.open_dataset(partial)


def test_one_process_running_two_campaigns_does_not_mix_them(reference, small_cts, tmp_path):
    """A worker's cached subject belongs to one campaign: a second campaign re-prepares it."""
    from sim.campaign.runner import run_campaign

    _, ref_out, _ = reference
    # part 1 of 3 of a 2-image campaign renders subject 0 only, so subject 0 is cached last
    run_campaign(load(write_campaign(tmp_path / "a", small_cts, n=2)), tmp_path / "a" / "out",
                 shard=(1, 3), progress=False)
    run_campaign(load(write_campaign(tmp_path / "b", small_cts)), tmp_path / "b" / "out", progress=False)
    assert checksums(tmp_path / "b" / "out") == checksums(ref_out)


def test_a_part_cleans_up_only_its_own_files(tmp_path):
    """Parts share a folder: one part's clean-up must not touch another part's files in flight."""
    shard_dir = tmp_path / ds.SHARD_DIR
    shard_dir.mkdir()
    mine, theirs = ds.shard_name(0, 0), ds.shard_name(0, 1)
    (shard_dir / f".{mine}.abc.tmp.h5").write_bytes(b"partial")
    (shard_dir / f".{theirs}.def.tmp.h5").write_bytes(b"partial")
    (shard_dir / theirs).write_bytes(b"renamed, checksum not written yet")
    assert ds.remove_partial_files(tmp_path, only={mine}) == 1
    assert sorted(p.name for p in shard_dir.iterdir()) == sorted([f".{theirs}.def.tmp.h5", theirs])
    assert ds.remove_partial_files(tmp_path) == 2  # a whole-campaign run cleans everything


# ----------------------------------------------------------------------------- robustness (issue 14)
def _alive(pid: int) -> bool:
    """A process exists and is not a zombie (a dead child waiting to be reaped)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _copy(ref_out: Path, dest: Path) -> Path:
    import shutil

    shutil.copytree(ref_out, dest)
    return dest


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc to find the workers")
@pytest.mark.parametrize("sig", ["SIGKILL", "SIGTERM"])
def test_workers_die_with_their_parent_and_resume_finishes_exactly(reference, small_cts, tmp_path, sig):
    """Kill only the parent of `simulate --workers 2`: no worker may survive and go on writing."""
    _, ref_out, _ = reference
    camp = write_campaign(tmp_path, small_cts)
    out = tmp_path / "out"
    err_file = tmp_path / "stderr.txt"
    with open(err_file, "w") as err:  # not a pipe: a surviving worker would hold it open
        proc = subprocess.Popen([sys.executable, "-m", "register.cli", "simulate", str(camp), "--out", str(out),
                                 "--workers", "2"], cwd=REPO, stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True)
    kids: list[int] = []
    try:
        t0 = time.monotonic()
        while not list((out / ds.SHARD_DIR).glob("*.sha256")) and time.monotonic() - t0 < 120:
            time.sleep(0.05)
        kids = _children(proc.pid)
        workers = [k for k in kids if b"spawn_main" in Path(f"/proc/{k}/cmdline").read_bytes()]
        if len(workers) < 2 or proc.poll() is not None:
            pytest.skip("the run finished before both workers could be seen")
        os.kill(proc.pid, getattr(signal, sig))
        proc.wait(timeout=60)
        t0 = time.monotonic()
        while any(_alive(k) for k in kids) and time.monotonic() - t0 < 5:
            time.sleep(0.05)
        assert not [k for k in kids if _alive(k)], "a worker outlived its parent"
        shards = sorted(p.name for p in (out / ds.SHARD_DIR).glob("*.sha256"))
        time.sleep(1.0)
        assert sorted(p.name for p in (out / ds.SHARD_DIR).glob("*.sha256")) == shards  # nobody writes on
        if sig == "SIGTERM":  # the parent stops the pool and says what to do, in one line
            text = err_file.read_text()
            assert proc.returncode == 2, text
            assert "stopped by SIGTERM" in text and "--resume" in text and "Traceback" not in text, text
    finally:
        for pid in [proc.pid, *kids]:  # clean up after a failure: only the processes this test started
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    r = run_cli("simulate", camp, "--out", out, "--resume", timeout=600)
    assert r.returncode == 0, r.stderr
    assert checksums(out) == checksums(ref_out)
    assert not [p.name for p in (out / ds.SHARD_DIR).iterdir() if ".tmp" in p.name]


def test_a_corrupt_or_truncated_shard_is_refused_when_first_used(reference, tmp_path):
    """No verify=True needed: the reader checks each shard before it uses its data, and says how to fix it."""
    cfg, ref_out, _ = reference
    out = _copy(ref_out, tmp_path / "out")
    shards = sorted((out / ds.SHARD_DIR).glob("*.h5"))
    data = bytearray(shards[3].read_bytes())
    data[len(data) // 2] ^= 0xFF
    shards[3].write_bytes(bytes(data))
    shards[5].write_bytes(shards[5].read_bytes()[:-100])
    with ds.open_dataset(out) as reader:  # opening reads only the manifest
        assert reader[0]["images"]["line"].shape == (48, 48)  # shard 0 is fine
        first = {ref.name: int(reader._offsets[k]) for k, ref in enumerate(reader._refs)}
        with pytest.raises(ds.DatasetError) as info:
            reader[first[shards[3].name]]
        msg = str(info.value)
        assert str(shards[3]) in msg and "checksum mismatch" in msg, msg
        assert f"ctxreg simulate {cfg.source} --out {out} --resume" in msg, msg
        with pytest.raises(ds.DatasetError, match=rf"{shards[5].name}: truncated \(\d+ bytes, the manifest says"):
            reader[first[shards[5].name] + 1]
        with pytest.raises(ds.DatasetError, match="checksum mismatch"):
            reader.arrays("params")  # every way in is checked


def test_each_shard_is_hashed_once_per_process(reference, tmp_path, monkeypatch):
    _, ref_out, _ = reference
    out = _copy(ref_out, tmp_path / "out")
    calls = []
    real = ds.sha256_file
    monkeypatch.setattr(ds, "sha256_file", lambda p, *a: calls.append(Path(p).name) or real(p, *a))
    for _ in range(2):  # two readers of one folder, every image read
        with ds.open_dataset(out) as reader:
            for i in range(len(reader)):
                reader[i]
    assert sorted(calls) == sorted(p.name for p in (out / ds.SHARD_DIR).glob("*.h5"))
    victim = sorted((out / ds.SHARD_DIR).glob("*.h5"))[0]
    victim.write_bytes(victim.read_bytes())  # rewritten: hashed again
    ds.open_dataset(out, verify=True).close()
    assert calls.count(victim.name) == 2


def test_resume_removes_stale_temporaries_and_re_renders_a_truncated_shard(reference, small_cts, tmp_path):
    import subprocess as sp

    from sim.core.atomic import _host
    from sim.campaign.runner import run_campaign

    _, ref_out, _ = reference
    out = _copy(ref_out, tmp_path / "out")
    p = sp.Popen([sys.executable, "-c", "pass"])
    p.wait()
    stale = [out / f".manifest.json.{p.pid}@{_host()}-abcd1234.tmp.json",
             out / ds.SHARD_DIR / f".s0000_00000.h5.{p.pid}@{_host()}-abcd1234.tmp.h5"]
    for f in stale:
        f.write_bytes(b"left by a killed run")
    victim = sorted((out / ds.SHARD_DIR).glob("*.h5"))[4]
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    run_campaign(load(write_campaign(tmp_path, small_cts)), out, resume=True, progress=False)
    assert not any(f.exists() for f in stale)
    assert checksums(out) == checksums(ref_out)
    ds.open_dataset(out, verify=True).close()


def test_resume_of_another_campaign_names_the_keys_that_changed(reference, small_cts, tmp_path):
    from sim.campaign.runner import CampaignError, run_campaign

    _, ref_out, _ = reference
    other = load(write_campaign(tmp_path, small_cts, n=5, shard=3))
    with pytest.raises(CampaignError) as info:
        run_campaign(other, ref_out, resume=True, progress=False)
    msg = str(info.value)
    assert "different campaign" in msg
    assert "campaign.images_per_ct: 6 -> 5" in msg and "campaign.shard_size: 2 -> 3" in msg, msg
    assert "source" not in msg.split("changed since that run:")[1]  # where the file lives is no change


def test_an_output_path_that_cannot_be_a_folder_is_refused_before_any_work(reference, tmp_path):
    from sim.campaign.runner import run_campaign
    from sim.core.errors import InputError

    cfg, _, _ = reference
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out, pattern in [(a_file, "is an existing file"), (a_file / "sub", "a_file is an existing file")]:
        with pytest.raises(InputError, match=pattern):
            run_campaign(cfg, out, progress=False)
    assert a_file.read_text() == "x"
    (tmp_path / "o" / ds.SHARD_DIR).parent.mkdir()
    (tmp_path / "o" / ds.SHARD_DIR).write_text("x")
    with pytest.raises(InputError, match="is a file where the folder of shard files goes"):
        run_campaign(cfg, tmp_path / "o", resume=True, progress=False)
    r = run_cli("simulate", cfg.source, "--out", a_file / "sub")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "a_file is an existing file" in r.stderr, r.stderr
    for bad in (0, 1000, True):
        with pytest.raises(InputError, match=r"--workers must be an integer in \[1, 256\]"):
            run_campaign(cfg, tmp_path / "w", workers=bad, progress=False)
    assert not (tmp_path / "w").exists()


OUT_OF_VIEW = {
    "offset": ('[poses]\ntx = { dist = "uniform", low = 1500.0, high = 2000.0 }\n', "",
               [r"pose 0 \(phi [-\d.]+, theta [-\d.]+, psi [-\d.]+ deg, tx 1[5-9]\d\d",
                r"\(6 of the subject's 6 poses show nothing\)",
                r"derived from the CT"]),
    "behind the source": ('[poses]\ntz = { dist = "fixed", value = -2000.0 }\n', "",
                          [r"tz -2000 mm", r"behind the source"]),
    "centre": ("", "center = [3000.0, 0.0, 0.0]", [r"cts\[0\]\.center = \[3000\.0, 0\.0, 0\.0\] mm"]),
}


@pytest.mark.parametrize("case", list(OUT_OF_VIEW), ids=list(OUT_OF_VIEW))
def test_a_ct_out_of_view_is_refused_before_any_work(small_cts, tmp_path, case):
    """Poses or a centre that put the CT out of the picture would render blank images: refused at once."""
    from sim.campaign.runner import CampaignError, run_campaign

    poses, center, patterns = OUT_OF_VIEW[case]
    text = CAMPAIGN.format(name="t", n=6, shard=2, ct0=small_cts[0], ct1=small_cts[1], vp=1)
    text = text.replace('[[cts]]\npath = "%s"\n' % small_cts[0], '[[cts]]\npath = "%s"\n%s\n' % (small_cts[0], center))
    path = tmp_path / "far.toml"
    path.write_text(text + poses)
    cfg = load(path)
    t0 = time.monotonic()
    with pytest.raises(CampaignError) as info:
        run_campaign(cfg, tmp_path / "out", progress=False)
    assert time.monotonic() - t0 < 5  # nothing loaded or rendered
    msg = str(info.value)
    assert msg.startswith(f"{path}: cts[0] ({small_cts[0]}), subject ct000_phantom1: pose 0 ("), msg
    for pat in patterns:
        assert re.search(pat, msg), (pat, msg)
    assert not (tmp_path / "out").exists()


def test_view_check_matches_the_renderer(small_cts):
    """visible_poses says 'nothing' exactly where a render is all zero (for these poses), and
    the header box equals the loaded CT's box."""
    from sim.campaign.runner import ct_box_from_header, visible_poses
    from sim.ct.io import load_ct
    from sim.projection.geometry import pose_from_params
    from sim.projection.drr import DRRRenderer, RenderSettings

    from sim.ct.phantom import make_pelvis_phantom

    np.testing.assert_allclose(ct_box_from_header("phantom:3"), make_pelvis_phantom(3).corners_lps(), atol=1e-9)
    assert ct_box_from_header("/data/ct_series_folder") is None  # DICOM: checked by the worker once loaded
    vol = load_ct(small_cts[0])
    np.testing.assert_allclose(ct_box_from_header(str(small_cts[0])), vol.corners_lps(), atol=1e-6)
    r = DRRRenderer(vol, RenderSettings(size=(48, 48)), center_lps=vol.center_of_box_lps())
    params = np.array([[0, 0, 0, 0, 0, 0], [0, 0, 0, 200, 0, 0], [0, 0, 0, 2000, 0, 0], [30, 0, 0, 0, -2500, 0],
                       [0, 0, 0, 0, 0, -900], [0, 0, 0, 0, 0, 3000], [0, 0, 0, 0, 0, -560], [0, 0, 0, 400, 0, 0]],
                      dtype=float)  # centre, box edge in view, far aside, behind the source, beyond the
    # detector (rays go on), box straddling the source plane, box just out of view
    seen = visible_poses(vol.corners_lps() - vol.center_of_box_lps(), params, r.geometry)
    blank = [not r.render(pose_from_params(p, r.geometry.sod_mm))[0].any() for p in params]
    assert seen.tolist() == [True, True, False, False, False, True, True, False]
    assert [not s for s in seen] == blank


def test_the_worker_checks_the_view_of_a_ct_it_loads(reference, tmp_path, monkeypatch):
    """A CT whose box the parent cannot read from a header (a DICOM folder) is checked when loaded."""
    from sim.campaign import runner

    cfg, _, _ = reference
    far = cfg.poses.__class__.from_dict({"ty": {"dist": "fixed", "value": 3000.0}})
    monkeypatch.setattr(runner, "ct_box_from_header", lambda path: None)
    import dataclasses

    cfg_far = dataclasses.replace(cfg, poses=far)
    with pytest.raises(runner.CampaignError, match=r"subject ct000_phantom1: pose 0 \(.*ty 3000, tz"):
        runner.run_campaign(cfg_far, tmp_path / "out", progress=False)
    assert not list((tmp_path / "out" / ds.SHARD_DIR).glob("*.h5"))


def test_a_shard_of_blank_images_is_refused(reference, tmp_path, monkeypatch):
    """The last guard: images that are all zero are never written as a dataset."""
    import dataclasses

    from sim.campaign import runner

    cfg, _, _ = reference
    cfg_far = dataclasses.replace(cfg, poses=cfg.poses.__class__.from_dict({"tx": {"dist": "fixed", "value": 3000.0}}))
    monkeypatch.setattr(runner, "check_view", lambda cfg, subjects: None)
    monkeypatch.setattr(runner, "visible_poses", lambda box, params, geometry: np.ones(len(params), bool))
    with pytest.raises(runner.CampaignError, match=r"all 2 images of shard s0000_00000\.h5 .* are zero"):
        runner.run_campaign(cfg_far, tmp_path / "out", progress=False)
    assert not list((tmp_path / "out" / ds.SHARD_DIR).glob("*.h5"))


def test_a_second_run_into_a_busy_folder_is_refused(reference, small_cts, tmp_path):
    """A run of the whole campaign locks its folder; parts share it with each other only."""
    import fcntl

    from sim.campaign.runner import LOCK_FILE, CampaignError, run_campaign

    _, ref_out, _ = reference
    out = _copy(ref_out, tmp_path / "out")
    cfg = load(write_campaign(tmp_path, small_cts))
    with open(out / LOCK_FILE, "w") as f:
        fcntl.flock(f, fcntl.LOCK_SH)  # a part is running
        with pytest.raises(CampaignError, match="another `ctxreg simulate` is writing into this folder"):
            run_campaign(cfg, out, resume=True, progress=False)
        assert run_campaign(cfg, out, resume=True, shard=(1, 3), progress=False)["counts"]["shards"] == 9
        fcntl.flock(f, fcntl.LOCK_EX)  # a whole run is running
        with pytest.raises(CampaignError, match="another `ctxreg simulate`"):
            run_campaign(cfg, out, resume=True, shard=(1, 3), progress=False)
    assert run_campaign(cfg, out, resume=True, progress=False)["complete"]


def test_the_workers_option_declares_the_runner_limit():
    from dataclasses import fields

    from sim.campaign.runner import MAX_WORKERS
    from sim.cli import SimulateCommand

    bounds = {f.name: f for f in fields(SimulateCommand)}["workers"].metadata["bounds"]
    assert (bounds.lo, bounds.hi) == (1, MAX_WORKERS)


def test_the_pose_histogram_of_a_huge_campaign_draws_the_first_poses_of_each_subject(reference, monkeypatch):
    from sim.campaign import runner

    cfg, _, _ = reference
    seen = {}
    monkeypatch.setattr(runner, "pose_histogram", lambda params, dist, path: seen.setdefault("params", params))
    runner._pose_histogram(cfg, Path("unused"))  # small: every pose
    np.testing.assert_array_equal(seen.pop("params"),
                                  np.concatenate([runner.subject_poses(cfg, s.index) for s in cfg.subjects()]))
    monkeypatch.setattr(runner, "HISTOGRAM_POSES", 7)  # 3 subjects: the first 2 poses of each
    runner._pose_histogram(cfg, Path("unused"))
    np.testing.assert_array_equal(seen["params"],
                                  np.concatenate([runner.subject_poses(cfg, s.index)[:2] for s in cfg.subjects()]))


def test_a_corrupt_manifest_says_how_to_rebuild_it(reference, small_cts, tmp_path):
    from sim.campaign.runner import run_campaign

    _, ref_out, _ = reference
    out = _copy(ref_out, tmp_path / "out")
    (out / ds.MANIFEST).write_text('{"format": "ctxreg-campaign", ')
    with pytest.raises(ds.DatasetError, match=r"corrupt JSON .* delete it and run `ctxreg simulate .* --resume`"):
        ds.open_dataset(out)
    (out / ds.MANIFEST).unlink()  # as the message says
    assert run_campaign(load(write_campaign(tmp_path, small_cts)), out, resume=True, progress=False)["complete"]
    assert checksums(out) == checksums(ref_out)
