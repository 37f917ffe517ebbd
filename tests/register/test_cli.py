"""The ``ctxreg`` dispatcher (:mod:`register.cli`): every command reaches its runner, a user's
error is one line with exit status 2, anything else keeps its traceback. The commands' own
behaviour is tested beside them (``tests/sim/test_cli.py`` for render and demo,
``test_register_cli.py``, ``tests/learn``)."""

from __future__ import annotations

import pytest

import sim.cli
from register import cli
from sim.core.errors import InputError, SetupError


def test_every_command_is_listed_and_reaches_a_runner():
    help_text = cli.build_parser().format_help()
    for name, (cls, summary, target) in cli.COMMANDS.items():
        assert name in help_text and summary in help_text, name
        module, func = target.split(":")
        assert callable(getattr(__import__(module, fromlist=[func]), func)), target


@pytest.fixture
def render_raises(monkeypatch):
    """Make ``ctxreg render`` raise the given exception (or return the given paths)."""
    monkeypatch.delenv("CTXREG_DEBUG", raising=False)
    seen = {}

    def use(outcome):
        def fake(cmd):
            seen["cmd"] = cmd
            if isinstance(outcome, BaseException):
                raise outcome
            return outcome

        monkeypatch.setattr(sim.cli, "run_render", fake)
        return seen

    return use


@pytest.mark.parametrize("error", [
    InputError("--kvp: 20 is outside 40..150"),
    SetupError("no libLLVM >= 16 found"),
    FileNotFoundError(2, "No such file or directory", "ct.nii.gz"),
    PermissionError(13, "Permission denied", "out/x.png"),
])
def test_a_users_error_is_one_line_and_exit_2(render_raises, capsys, error):
    render_raises(error)
    assert cli.main(["render", "--ct", "phantom"]) == 2
    assert capsys.readouterr().err == f"ctxreg render: error: {error}\n"


@pytest.mark.parametrize("error", [ValueError("a bug"), ZeroDivisionError("a bug"), OSError(5, "I/O error")])
def test_any_other_exception_keeps_its_traceback(render_raises, error):
    render_raises(error)
    with pytest.raises(type(error)) as raised:
        cli.main(["render", "--ct", "phantom"])
    assert raised.value is error


def test_ctxreg_debug_shows_the_traceback_of_a_users_error(render_raises, monkeypatch):
    error = InputError("--size: must be positive")
    render_raises(error)
    monkeypatch.setenv("CTXREG_DEBUG", "1")
    with pytest.raises(InputError) as raised:
        cli.main(["render", "--ct", "phantom"])
    assert raised.value is error


def test_an_interrupt_exits_130(render_raises, capsys):
    render_raises(KeyboardInterrupt())
    assert cli.main(["render", "--ct", "phantom"]) == 130
    assert capsys.readouterr().err == "ctxreg render: interrupted\n"


@pytest.mark.parametrize("result, lines", [("a.png", ["wrote a.png"]),
                                           (["a.png", "b.json"], ["wrote a.png", "wrote b.json"])])
def test_the_written_files_are_listed_and_the_options_reach_the_runner(render_raises, capsys, result, lines):
    seen = render_raises(result)
    assert cli.main(["render", "--ct", "phantom:3", "--size", "48", "64"]) == 0
    assert capsys.readouterr().out.splitlines() == lines
    cmd = seen["cmd"]
    assert isinstance(cmd, sim.cli.RenderCommand)
    assert cmd.ct == "phantom:3" and tuple(cmd.size) == (48, 64)
    assert cmd.mu_water == sim.cli.RenderCommand(ct="x").mu_water  # left out: the dataclass default


@pytest.mark.parametrize("argv", [[], ["no-such-command"], ["render"]])
def test_a_missing_command_or_option_is_one_line_pointing_to_the_help(argv, capsys):
    with pytest.raises(SystemExit) as raised:
        cli.main(argv)
    err = capsys.readouterr().err
    assert raised.value.code == 2 and err.count("\n") == 1 and err.startswith("ctxreg")
    assert ": error: " in err and "--help)" in err


@pytest.mark.parametrize("argv, code, fast", [(["register", "--ct", "x"], 0, True), (["render"], 0, True),
                                              (["register"], 2, False), (["train", "c.toml"], 0, False)])
def test_the_program_skips_the_teardown_only_after_a_finished_register_or_render(monkeypatch, capsys, argv, code,
                                                                                  fast):
    """``entry`` flushes what was printed and ends the process with ``os._exit`` after a successful
    register or render; a failure and the other commands (workers, logs) exit normally."""
    exits = []

    def fake_main():
        print("wrote out/result.json")
        return code

    monkeypatch.setattr(cli, "main", fake_main)
    monkeypatch.setattr(cli.sys, "argv", ["ctxreg", *argv])
    def fake_exit(c):  # os._exit does not return
        exits.append(c)
        raise SystemExit(c)

    monkeypatch.setattr(cli.os, "_exit", fake_exit)
    with pytest.raises(SystemExit) as e:
        cli.entry()
    assert e.value.code == code and exits == ([code] if fast else [])
    assert capsys.readouterr().out == "wrote out/result.json\n"
