"""Campaigns on a Dask cluster (sim.core.scale, ``ctxreg simulate --scheduler``): the same bytes as a local
run, a worker killed mid-shard retried with no loss and no duplicate, and the refusals before any
work (a malformed value, an unreachable scheduler, --workers beside --scheduler)."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest

from sim.campaign import dataset as ds
from sim.core.scale import SchedulerError, parse_scheduler
# the campaign tests' phantoms and their single-process run: the truth here too
from tests.sim.test_campaign_run import checksums, reference, run_cli, small_cts, write_campaign  # noqa: F401


def test_parse_scheduler():
    assert parse_scheduler("local:2").local == 2
    assert parse_scheduler("tcp://10.0.0.1:8786").address == "tcp://10.0.0.1:8786"
    assert parse_scheduler("node7:8786").address == "tcp://node7:8786"
    for bad in ("local:0", "local:x", "local:999", "8786", "http//x", "missing.json"):
        with pytest.raises(SchedulerError, match="--scheduler"):
            parse_scheduler(bad)


@pytest.mark.parametrize("content, words", [
    ("", "the scheduler file is empty"),
    ('{"address": "tcp://10.0.0.1:87', "the scheduler file is not valid JSON"),
    ('{"id": "Scheduler-1", "type": "Scheduler"}', "holds no scheduler address"),
    ('["tcp://10.0.0.1:8786"]', "holds no scheduler address"),
    ('{"address": 8786}', "holds no scheduler address"),
    (None, "a folder, not a scheduler file"),
])
def test_bad_scheduler_files_and_addresses_are_named_in_one_line(tmp_path, content, words):
    """A truncated, empty or address-less scheduler file (or a folder named *.json) is refused when
    parsed, before any work, in one line naming the file (Dask's own client ended in an
    AssertionError)."""
    path = tmp_path / "sched.json"
    if content is None:
        path.mkdir()
    else:
        path.write_text(content)
    with pytest.raises(SchedulerError) as e:
        parse_scheduler(str(path))
    assert words in str(e.value) and str(path) in str(e.value) and "\n" not in str(e.value)
    good = tmp_path / "good.json"
    good.write_text('{"type": "Scheduler", "address": "tcp://10.0.0.1:8786"}')
    assert parse_scheduler(str(good)).scheduler_file == str(good)
    for bad in ("tcp://bogus", "tcp://:8786", "tcp://host:99999"):
        with pytest.raises(SchedulerError, match="a TCP address needs a host and a port"):
            parse_scheduler(bad)


def test_a_local_cluster_writes_the_same_bytes_and_survives_a_killed_worker(reference, small_cts, tmp_path):
    """Two worker processes; the first worker seen rendering a shard is killed (SIGKILL) mid-shard. The
    nanny restarts it, the scheduler retries the shard: every checksum equals the single-process run's,
    no shard is missing or doubled, no temporary file is left."""
    from distributed import Client, LocalCluster

    from sim.campaign.runner import run_campaign

    cfg, ref, _ = reference
    out = tmp_path / "out"
    killed: list[int] = []
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=50) as cluster, Client(cluster) as client:
        pids = client.run(os.getpid)

        def killer():
            t0 = time.monotonic()
            while time.monotonic() - t0 < 120 and not killed:
                busy = [w for w, keys in client.processing().items() if keys]
                if busy:
                    time.sleep(0.3)  # inside the shard: its subject's CT and kernels take seconds
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed.append(pids[busy[0]])
                time.sleep(0.02)

        thread = threading.Thread(target=killer, daemon=True)
        thread.start()
        manifest = run_campaign(cfg, out, progress=False, client=client)
        thread.join(5)
    assert killed, "no worker was seen rendering"
    assert manifest["complete"]
    assert checksums(out) == checksums(ref)
    shards = sorted(p.name for p in (out / ds.SHARD_DIR).iterdir())
    assert not [n for n in shards if ".tmp" in n]
    assert len([n for n in shards if n.endswith(".h5")]) == len(checksums(ref))


def test_cli_on_a_local_cluster(reference, small_cts, tmp_path):
    _, ref, _ = reference
    camp = write_campaign(tmp_path, small_cts)
    r = run_cli("simulate", camp, "--out", tmp_path / "out", "--scheduler", "local:2", timeout=600)
    assert r.returncode == 0, r.stderr
    assert "a local Dask cluster of 2 worker processes" in r.stderr
    assert checksums(tmp_path / "out") == checksums(ref)


@pytest.mark.parametrize("args, expect", [
    (["--scheduler", "tcp://127.0.0.1:9"], "no Dask scheduler answered"),
    (["--scheduler", "local:2", "--workers", "2"], "--workers and --scheduler"),
    (["--scheduler", "local:0"], "local:N needs N worker processes"),
])
def test_bad_schedulers_are_one_line_before_any_work(small_cts, tmp_path, args, expect):
    camp = write_campaign(tmp_path, small_cts)
    out = tmp_path / "out"
    r = run_cli("simulate", camp, "--out", out, *args, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ctxreg simulate: error:") and expect in lines[0], r.stderr
    assert not out.exists()


def test_evaluate_on_a_local_cluster_returns_the_sequential_rows(tmp_path):
    """``ctxreg evaluate --scheduler local:2``: the same cases.csv as the run here, row for row, in the
    same order (only the seconds differ)."""
    import csv

    common = ["evaluate", "--ct", "phantom", "--cases", "3", "--size", "32", "32", "--method", "cmaes"]
    here = run_cli(*common, "--out", tmp_path / "here", timeout=900)
    assert here.returncode == 0, here.stderr
    dask = run_cli(*common, "--scheduler", "local:2", "--out", tmp_path / "dask", timeout=900)
    assert dask.returncode == 0, dask.stderr
    assert "a local Dask cluster of 2 worker processes" in dask.stderr

    def rows(folder):
        with open(folder / "cases.csv") as f:
            return [{k: v for k, v in r.items() if k != "time_s"} for r in csv.DictReader(f)]

    a, b = rows(tmp_path / "here"), rows(tmp_path / "dask")
    assert len(a) == 3 and a == b


def test_evaluate_refuses_an_unreachable_scheduler_before_any_work(tmp_path):
    r = run_cli("evaluate", "--ct", "phantom", "--cases", "2", "--scheduler", "tcp://127.0.0.1:9", "--out",
                tmp_path / "o", timeout=120)
    assert r.returncode == 2 and "no Dask scheduler answered" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_study_on_a_local_cluster_gives_the_sequential_results(tmp_path):
    """``ctxreg study --scheduler local:2`` on the tiny study's first variant (a DRR and a realistic-frame
    target, the contextual method): every evaluation's cases.csv equals the run here but for the seconds."""
    import csv

    from tests.register.test_study import TINY

    study = tmp_path / "s.toml"
    study.write_text(TINY.replace("cases = 2", "cases = 1", 1))  # one case per target: the fan-out, not the statistics
    here = run_cli("study", study, "--only", "tiny", "--out", tmp_path / "here", timeout=1200)
    assert here.returncode == 0, here.stderr[-3000:]
    dask = run_cli("study", study, "--only", "tiny", "--scheduler", "local:2", "--out", tmp_path / "dask", timeout=1200)
    assert dask.returncode == 0, dask.stderr[-3000:]

    def rows(path):
        with open(path) as f:
            return [{k: v for k, v in r.items() if k != "time_s"} for r in csv.DictReader(f)]

    for target in ("line", "fluoro"):
        a = rows(tmp_path / "here" / "results" / "tiny" / target / "cases.csv")
        b = rows(tmp_path / "dask" / "results" / "tiny" / target / "cases.csv")
        assert len(a) == 1 and a == b, target
