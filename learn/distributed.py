"""``ctxreg train`` under ``torchrun``: data-parallel training (torch DDP) over processes and machines.

``torchrun --nproc-per-node N -m register.cli train CONFIG.toml`` starts N processes; each reads
``RANK`` / ``WORLD_SIZE`` / ``LOCAL_RANK`` from the environment torchrun sets
(:meth:`DistributedRun.from_env`), joins the process group (gloo on a CPU, NCCL on GPUs) and trains
one model wrapped in :class:`torch.nn.parallel.DistributedDataParallel`:

* every rank draws the same global batch from the seed and the iteration (the sources are
  functions of those alone) and trains on its contiguous share of ``batch_size / WORLD_SIZE`` rows
  (:meth:`DistributedRun.share`); DDP averages the gradients, so a step equals the single-process
  step on the whole batch (the loss is a mean over rows), up to the order of floating-point sums;
* rank 0 alone validates (on the unwrapped model: no collective), logs, shows progress and writes
  the checkpoint (the unwrapped model's state, so a checkpoint resumes in one process or in N);
* a stop (a signal, ``--stop-after``) is agreed by all ranks each iteration, so none waits alone.

BatchNorm: the DenseNet backbone's statistics are each rank's share's in training mode (GPUs use
SyncBatchNorm instead); with ``freeze_backbone`` (the backbone in eval mode) the step is the
single-process step exactly, which ``tests/learn/test_distributed.py`` checks.
"""

from __future__ import annotations

import os
import signal
from dataclasses import dataclass

import torch

from sim.core.errors import InputError

__all__ = ["DistributedRun", "DistributedError", "launch", "under_torchrun"]


def under_torchrun() -> bool:
    """Whether this process is a rank that torchrun started (its ``RANK`` is set)."""
    return "RANK" in os.environ and "WORLD_SIZE" in os.environ


def launch(procs: int, argv: list[str]) -> None:
    """Run ``python -m register.cli ARGV`` in ``procs`` processes on this machine, as
    ``torchrun --standalone --nproc-per-node PROCS`` does (torch's own launcher, in this process).
    Each rank prints its refusals only where it is rank 0 (``register.cli``); a rank that fails
    raises :class:`DistributedError` here in one line (the rank and its exit code; its own
    message is above), instead of the launcher's traceback. ``OMP_NUM_THREADS`` defaults to the
    cores shared among the processes."""
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import parse_args, run

    before = os.environ.get("OMP_NUM_THREADS")
    if before is None:  # for the ranks only: restored below, so that nothing after the run inherits it
        os.environ["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // procs))
    try:
        run(parse_args(["--standalone", "--nproc-per-node", str(procs), "-m", "register.cli", *argv]))
    except ChildFailedError as e:
        # where one rank fails, the launcher stops the others (SIGTERM): they did not fail of their own
        own = {r: f.exitcode for r, f in e.failures.items() if f.exitcode != -signal.SIGTERM} or {
            r: f.exitcode for r, f in e.failures.items()}
        stopped = sorted(set(e.failures) - set(own))
        ranks, codes = sorted(own), sorted(set(own.values()))
        line = (f"{procs} processes: rank{'s' if len(ranks) > 1 else ''} {', '.join(map(str, ranks))} ended with "
                f"exit code {', '.join(map(str, codes))}")
        if stopped:
            line += f"; rank{'s' if len(stopped) > 1 else ''} {', '.join(map(str, stopped))} stopped by the launcher"
        raise DistributedError(line + " (the message above says why)") from None
    finally:
        if before is None:
            os.environ.pop("OMP_NUM_THREADS", None)


class DistributedError(InputError):
    """The distributed run cannot start as configured (a batch that does not divide)."""


@dataclass(frozen=True)
class DistributedRun:
    """This process's place in a ``torchrun`` job: ``rank`` of ``world`` processes (``world == 1``:
    a plain single-process run, every method a no-op)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @classmethod
    def from_env(cls) -> "DistributedRun":
        """From torchrun's ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` (absent: a single process)."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        return cls(rank=int(os.environ.get("RANK", "0")), world=world, local_rank=int(os.environ.get("LOCAL_RANK", "0")))

    @property
    def active(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        """Whether this process logs, validates and writes checkpoints (rank 0)."""
        return self.rank == 0

    def start(self, device: torch.device) -> torch.device:
        """Join the process group (gloo on a CPU, NCCL on CUDA); the device of this rank."""
        if not self.active:
            return device
        import torch.distributed as dist

        if device.type == "cuda":
            device = torch.device("cuda", self.local_rank)
            torch.cuda.set_device(device)
        if not dist.is_initialized():
            dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
        return device

    def check_batch(self, batch_size: int) -> None:
        if self.active and batch_size % self.world:
            raise DistributedError(f"train.batch_size {batch_size} does not divide among {self.world} processes "
                                   f"(--procs or torchrun --nproc-per-node): give a multiple of {self.world}")

    def wrap(self, model: torch.nn.Module, device: torch.device) -> torch.nn.Module:
        """``model`` in DDP (SyncBatchNorm on CUDA), or itself in a single process."""
        if not self.active:
            return model
        from torch.nn.parallel import DistributedDataParallel

        if device.type == "cuda":
            model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
            return DistributedDataParallel(model, device_ids=[device.index])
        return DistributedDataParallel(model)

    def share(self, batch: tuple) -> tuple:
        """This rank's contiguous rows of every tensor of ``batch`` (each ``(B, ...)``)."""
        if not self.active:
            return batch
        n = batch[0].shape[0] // self.world
        return tuple(t[self.rank * n:(self.rank + 1) * n] for t in batch)

    def any(self, flag: bool) -> bool:
        """Whether ``flag`` is set on any rank (every rank calls it at the same point)."""
        if not self.active:
            return flag
        import torch.distributed as dist

        t = torch.tensor([1.0 if flag else 0.0])
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return bool(t.item() > 0)

    def finish(self) -> None:
        if self.active:
            import torch.distributed as dist

            if dist.is_initialized():
                dist.barrier()
                dist.destroy_process_group()


def unwrap(model: torch.nn.Module) -> torch.nn.Module:
    """The model inside a DDP wrapper (the model itself otherwise)."""
    return getattr(model, "module", model)
