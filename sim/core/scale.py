"""Work past one machine: a Dask cluster for the units of work ctxreg already has (campaign shards).

``--scheduler local:N`` starts a :class:`distributed.LocalCluster` of ``N`` worker processes (one
thread each) for the run; ``--scheduler ADDRESS`` (``tcp://host:8786``, or a scheduler file
``*.json``) joins a running scheduler, e.g. one that dask-jobqueue started on a SLURM or PBS cluster
(docs/scale.md). The workers must see the same paths (CTs, the output folder) as this process:
a shared file system.

The unit of work stays the one the local runner has (:func:`sim.campaign.runner.render_unit`: one
shard, its seeds from the campaign and its index, written atomically with its checksum), so a run
on Dask writes the same bytes as a local one. A worker lost mid-shard is retried by Dask on
another worker (the scheduler's ``allowed-failures``, 3 by default): the retried shard overwrites
nothing that was complete, its half-written temporary file is removed at the end of the run.

Example::

    from sim.core.scale import dask_client, parse_scheduler

    with dask_client(parse_scheduler("local:2")) as client:
        run_campaign(cfg, "out/run", client=client)
"""

from __future__ import annotations

import contextlib
import json
import re
from typing import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from sim.core.errors import InputError

__all__ = ["SchedulerError", "WorkerLost", "Scheduler", "parse_scheduler", "dask_client", "worker_count", "each_result",
           "CONNECT_TIMEOUT_S", "MAX_LOCAL_WORKERS"]

#: Seconds to reach a scheduler before the run is refused (nothing is written before).
CONNECT_TIMEOUT_S = 10.0
#: The most worker processes ``local:N`` starts.
MAX_LOCAL_WORKERS = 256


class SchedulerError(InputError):
    """``--scheduler`` cannot be used: a malformed value, an unreachable scheduler, Dask missing."""


class WorkerLost(RuntimeError):
    """A task's worker died on every try the scheduler allowed (:class:`distributed.KilledWorker`);
    ``key`` names the task as :func:`each_result` was given it."""

    def __init__(self, key, message: str):
        super().__init__(message)
        self.key = key


@dataclass(frozen=True)
class Scheduler:
    """A parsed ``--scheduler``: ``local`` workers to start, or the ``address`` (or scheduler file) to join."""

    text: str
    local: int | None = None
    address: str | None = None
    scheduler_file: str | None = None

    def describe(self) -> str:
        if self.local is not None:
            return f"a local Dask cluster of {self.local} worker process{'es' if self.local > 1 else ''}"
        return f"the Dask scheduler {self.address or self.scheduler_file}"


_ADDRESS = re.compile(r"^(tcp|tls|inproc|ucx|ws|wss)://\S+$|^[A-Za-z0-9_.\-]+:\d{1,5}$")


def parse_scheduler(text: str) -> Scheduler:
    """``local:N`` (1 <= N <= :data:`MAX_LOCAL_WORKERS`), a scheduler address (``tcp://host:port`` or
    ``host:port``) or a scheduler file (``*.json``, as ``dask scheduler --scheduler-file`` writes it).
    Raises :class:`SchedulerError` naming the value."""
    t = str(text).strip()
    if t.startswith("local:"):
        n = t[len("local:"):]
        if not n.isdigit() or not 1 <= int(n) <= MAX_LOCAL_WORKERS:
            raise SchedulerError(f"--scheduler {text}: local:N needs N worker processes, 1 to {MAX_LOCAL_WORKERS}")
        return Scheduler(t, local=int(n))
    if t.endswith(".json"):
        _check_scheduler_file(Path(t), text)
        return Scheduler(t, scheduler_file=t)
    if _ADDRESS.match(t):
        address = t if "://" in t else f"tcp://{t}"
        if address.startswith("tcp://"):
            host, colon, port = address[len("tcp://"):].rpartition(":")
            if not colon or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
                raise SchedulerError(f"--scheduler {text}: a TCP address needs a host and a port 1-65535 "
                                     "(tcp://host:8786)")
        return Scheduler(t, address=address)
    raise SchedulerError(f"--scheduler {text}: give local:N, a scheduler address (tcp://host:8786) or a "
                         "scheduler file (*.json)")


def _check_scheduler_file(path: Path, text: str) -> None:
    """A scheduler file as ``dask scheduler --scheduler-file`` writes it: a JSON object whose
    ``address`` is a scheduler address; anything else is refused in one line naming the file."""
    if path.is_dir():
        raise SchedulerError(f"--scheduler {text}: a folder, not a scheduler file")
    if not path.is_file():
        raise SchedulerError(f"--scheduler {text}: scheduler file not found")
    try:
        info = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise SchedulerError(f"--scheduler {text}: cannot read the scheduler file ({e})") from None
    except json.JSONDecodeError as e:
        why = "empty" if not path.read_bytes().strip() else f"not valid JSON ({e.msg} at line {e.lineno})"
        raise SchedulerError(f"--scheduler {text}: the scheduler file is {why}; is the scheduler still starting, "
                             "or was the file cut short?") from None
    address = info.get("address") if isinstance(info, dict) else None
    if not isinstance(address, str) or not _ADDRESS.match(address.strip()):
        raise SchedulerError(f"--scheduler {text}: the scheduler file holds no scheduler address (its \"address\" "
                             f"is {address!r}); give the file the scheduler wrote (dask scheduler --scheduler-file)")


@contextlib.contextmanager
def dask_client(scheduler: Scheduler, *, timeout_s: float = CONNECT_TIMEOUT_S) -> Iterator:
    """A :class:`distributed.Client` of ``scheduler`` for the ``with`` block (a local cluster is
    started for it and closed after). An address that does not answer within ``timeout_s`` raises
    :class:`SchedulerError` before any work."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as exc:  # a broken install: the dependency is pinned in pyproject.toml
        raise SchedulerError(f"--scheduler needs dask[distributed] ({exc}); run scripts/setup.sh") from None
    if scheduler.local is not None:
        # One task at a time per worker process, as a local worker process renders one shard. The
        # workers keep this process's environment: Dask's nanny would set OMP / MKL / OpenBLAS to one
        # thread, and the thread count changes the order of floating-point sums (and so a result's
        # last digits, which an optimiser then follows elsewhere): a case registered on a worker must
        # give the row it gives here.
        # (For the cluster's whole life: a worker the nanny restarts is spawned with it too.)
        with dask.config.set({"distributed.nanny.pre-spawn-environ": {"MALLOC_TRIM_THRESHOLD_": 65536}}):
            cluster = LocalCluster(n_workers=scheduler.local, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=40)
            try:
                with Client(cluster) as client:
                    yield client
            finally:
                cluster.close()
        return
    if scheduler.address is not None and scheduler.address.startswith("tcp://"):
        _check_reachable(scheduler, timeout_s)
    try:
        if scheduler.scheduler_file is not None:
            client = Client(scheduler_file=scheduler.scheduler_file, timeout=timeout_s)
        else:
            client = Client(scheduler.address, timeout=timeout_s)
    except (OSError, TimeoutError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SchedulerError(f"--scheduler {scheduler.text}: no Dask scheduler answered within {timeout_s:g} s "
                             f"({first})") from None
    try:
        yield client
    finally:
        client.close()


def worker_count(client) -> int:
    """The workers the scheduler has now (at least 1, for a progress line's sake)."""
    return max(1, len(client.scheduler_info().get("workers", {})))


def _check_reachable(scheduler: Scheduler, timeout_s: float) -> None:
    """A TCP scheduler that refuses the connection is refused at once (Dask's client would retry for
    ``timeout_s``); one that answers is left to the client."""
    import socket

    host, _, port = scheduler.address[len("tcp://"):].rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except (OSError, ValueError) as exc:
        raise SchedulerError(f"--scheduler {scheduler.text}: no Dask scheduler answered ({exc})") from None


def each_result(client, tasks: dict, on_result: Callable[[object, object], None]) -> None:
    """Submit ``tasks`` (``{key: (function, *args)}``, each a top-level function and picklable
    arguments) to ``client`` and call ``on_result(key, result)`` as each finishes, in the order they
    finish. A task that raised re-raises here; one whose workers kept dying raises :class:`WorkerLost`.
    On any error (or Ctrl-C) the tasks not yet done are cancelled, so no worker goes on writing."""
    from distributed import as_completed
    from distributed.scheduler import KilledWorker

    futures = {client.submit(fn, *args, pure=False): key for key, (fn, *args) in tasks.items()}
    try:
        for fut in as_completed(list(futures)):
            try:
                result = fut.result()
            except KilledWorker as exc:
                raise WorkerLost(futures[fut], f"its Dask worker died on every try ({exc})") from None
            on_result(futures[fut], result)
    except BaseException:
        client.cancel(list(futures))
        raise
