"""``ctxreg train``: defaults (one dataclass) and the run."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from sim.cliargs import opt


@dataclass(frozen=True)
class TrainCommand:
    """Defaults of ``ctxreg train``."""

    config: str = field(metadata=opt("training config (TOML with a [train] table; see learn/train.py)",
                                     group="input", positional=True, metavar="CONFIG.toml"))
    resume: bool = field(default=False, metadata=opt(
        "continue from the output folder's checkpoint (same config)", group="run"))


def run_train(cmd: TrainCommand) -> list[Path]:
    from learn.train import load_train_config, train

    cfg = load_train_config(cmd.config)
    train(cfg, resume=cmd.resume)
    out = Path(cfg.out)
    return [out / "checkpoint.pt", out / "log.csv", out / "loss.png"]
