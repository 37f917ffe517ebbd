"""The ``ctxreg`` command line.

Each command's defaults live in one dataclass (:mod:`sim.cli`, and later :mod:`register` and
:mod:`learn`); the options and their grouped help are generated from it. Errors in the user's
input (:class:`sim.core.errors.CtxregError`, or a path that is missing or not writable) print one
line and exit with status 2; set ``CTXREG_DEBUG=1`` for the traceback. Any other exception is a
bug: it keeps its traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from sim.core.cliargs import HelpFormatter, add_options, from_namespace
from learn.commands import AccuracyCommand, AdaptCommand, ModelsCommand, TrainCommand, TrainToolsCommand
from register.commands import EvaluateCommand, RegisterCommand, ServeCommand, StudyCommand
from register.evaluation.demo import DemoCommand
from register.verdict import EXIT_STATUS
from sim.cli import RenderCommand, SimulateCommand
from sim.core.errors import CtxregError, USER_OS_ERRORS

COMMANDS = {
    "render": (RenderCommand, "render a DRR of a CT at one pose", "sim.cli:run_render"),
    "simulate": (SimulateCommand, "render a synthetic data campaign (sharded HDF5 dataset)",
                 "sim.cli:run_simulate"),
    "register": (RegisterCommand, "register an X-ray to a CT (pose, overlay, convergence plot)",
                 "register.commands:run_register"),
    "serve": (ServeCommand, "register a case's frames as they arrive, in one process", "register.commands:run_serve"),
    "evaluate": (EvaluateCommand, "evaluate registration methods on sampled target poses of a CT",
                 "register.commands:run_evaluate"),
    "train": (TrainCommand, "train the contextual pose-update network on a campaign",
              "learn.commands:run_train"),
    "adapt": (AdaptCommand, "fine-tune the network to one CT in minutes (a patient it has never seen)",
              "learn.commands:run_adapt"),
    "train-tools": (TrainToolsCommand, "train the metal-tool segmenter on simulated frames with the simulator's truth",
                    "learn.commands:run_train_tools"),
    "accuracy": (AccuracyCommand, "single-prediction accuracy of a trained network (per depth, vs zero)",
                 "learn.commands:run_accuracy"),
    "models": (ModelsCommand, "list the shipped models (models/<name>: card, preprocessing, accuracy)",
               "learn.commands:run_models"),
    "study": (StudyCommand, "train network variants and evaluate each on several target domains (resumable)",
              "register.commands:run_study"),
    "demo": (DemoCommand, "register a simulated realistic X-ray of the pelvis from AP; show the error",
             "register.evaluation.demo:run_demo"),
}


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, like every other ctxreg error."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="ctxreg", formatter_class=HelpFormatter,
        description="ctxreg: X-ray simulation from CT and 2D/3D registration. "
                    "Units: mm, degrees, 1/mm. Conventions: docs/conventions.md.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (cls, summary, _) in COMMANDS.items():
        p = sub.add_parser(name, help=summary, description=summary, formatter_class=HelpFormatter,
                           argument_default=argparse.SUPPRESS)
        add_options(p, cls)
    return parser


def _user_errors() -> tuple[type[BaseException], ...]:
    """Exception types a user can act on (:mod:`sim.core.errors`): one line, no traceback. Anything
    else is a bug and keeps its traceback."""

    return (CtxregError, *USER_OS_ERRORS)


#: Seconds a torchrun rank other than 0 waits, on an input error, for torchrun to stop it after rank 0
#: said the same error (see :func:`main`).
RANK_ERROR_WAIT_S = 10.0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    cls, _, target = COMMANDS[args.command]
    module, func = target.split(":")
    try:
        cmd = from_namespace(cls, args)
        run = getattr(__import__(module, fromlist=[func]), func)
        result = run(cmd)
    except KeyboardInterrupt:
        print(f"ctxreg {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of the output left (`ctxreg models | head`): nothing more to say
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        except (OSError, ValueError, AttributeError):
            pass
        return 0
    except _user_errors() as e:
        if os.environ.get("CTXREG_DEBUG"):
            raise
        if os.environ.get("RANK", "0") != "0" and "WORLD_SIZE" in os.environ:
            # Under torchrun every rank meets the same error and rank 0 says it: a rank that ended
            # first would have torchrun stop rank 0 before it printed, so the others wait for that
            # stop. An error of this rank alone is said after the wait.
            time.sleep(RANK_ERROR_WAIT_S)
        print(f"ctxreg {args.command}: error: {e}", file=sys.stderr)
        return 2
    for path in result if isinstance(result, list) else [result]:
        print(f"wrote {path}")
    if getattr(result, "last_line", None):  # sim.core.outputs.Written: e.g. register's verdict, printed last
        print(result.last_line)
    return getattr(result, "exit_status", 0)


#: ``ctxreg register``'s exit status where the registration is doubtful or failed, every output
#: written (:data:`register.verdict.EXIT_STATUS`).
DOUBTFUL_EXIT = EXIT_STATUS["doubtful"]

#: Commands after which :func:`entry` ends the process at once: every output written atomically and
#: flushed, nothing left for the interpreter's teardown to do.
FAST_EXIT_COMMANDS = ("register", "serve", "render")


def entry() -> None:
    """The ``ctxreg`` program: :func:`main`, then the exit. After ``register``, ``serve`` and ``render``
    (:data:`FAST_EXIT_COMMANDS`) the process ends without the interpreter's teardown, which after a
    registration takes about 1.2 s on 2 cores (Dr.Jit's JIT state, torch's thread pools and every
    module freed one by one) while the user waits; their outputs are written atomically and the
    streams are flushed first. The other commands (training, campaigns, studies, with their workers
    and logs) exit normally."""
    code = main()
    argv = sys.argv[1:]
    if code in (0, DOUBTFUL_EXIT) and argv and argv[0] in FAST_EXIT_COMMANDS:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        except (OSError, ValueError):  # a closed or broken stream: exit normally, as main() would
            sys.exit(code)
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    entry()
