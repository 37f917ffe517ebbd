"""Campaign runs: determinism, resume after kill -9, parts of the work, splits, the reader."""

from __future__ import annotations

import json
import os
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
    from sim.phantom import write_phantom_nifti

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
        _, err = proc.communicate(timeout=300)
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
    from sim.ct_io import load_ct
    from sim.geometry import pose_from_params, project_points
    from sim.render import DRRRenderer, RenderSettings

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
