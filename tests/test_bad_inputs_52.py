"""Issue 52's sweep over the commands and options added since the last one (adapt, train --procs,
serve's folder, study tools, scheduler files), table-driven like tests/test_bad_inputs.py (its
harness and inputs): each is refused before any work, in one line naming the problem, with exit
status 2 and nothing written."""

from __future__ import annotations

import pytest

from tests.test_bad_inputs import _run, assert_refused, inputs  # noqa: F401  (the module's fixture, reused)

#: (command line after ``ctxreg``, words the error line must hold)
BAD = {
    "adapt a phantom of no seed": ("adapt --ct phantom:x --out ad", ["--ct phantom:x", "seed must be a whole number"]),
    "adapt into a file": ("adapt --ct phantom --out {file}", ["--out", "is an existing file"]),
    "adapt zero minutes": ("adapt --ct phantom --out ad --minutes 0", ["--minutes 0"]),
    "train in no process": ("train {config} --procs 0", ["--procs 0", "[1, 64]"]),
    "train in too many": ("train {config} --procs 65", ["--procs 65"]),
    "train odd batch over 2": ("train {oddconfig} --procs 2", ["batch_size 3 does not divide among 2 processes"]),
    "serve into a file": ("serve --ct phantom --xray {emptydir} --out {file}", ["--out", "a file, not a folder"]),
    "serve a missing folder": ("serve --ct phantom --xray {emptydir}/nope --out sv", ["not a folder to watch"]),
    "evaluate an empty scheduler file": ("evaluate --ct phantom --scheduler {schedempty} --out ev",
                                         ["scheduler file is empty"]),
    "evaluate a scheduler file of no address": ("evaluate --ct phantom --scheduler {schednoaddr} --out ev",
                                                ["holds no scheduler address"]),
    "evaluate a folder as scheduler file": ("evaluate --ct phantom --scheduler {scheddir} --out ev",
                                            ["a folder, not a scheduler file"]),
    "evaluate a TCP address of no port": ("evaluate --ct phantom --scheduler tcp://bogus --out ev",
                                          ["a TCP address needs a host and a port"]),
    "study tools on a DRR target": ("study {toolstudy} --out st", ["tools apply to kind 'xray' only"]),
    "study a missing dataset": ("study {nodatastudy} --out st", ["(v).train.dataset", "not found"]),
}


@pytest.fixture(scope="module")
def inputs52(inputs, tmp_path_factory):  # noqa: F811
    d = tmp_path_factory.mktemp("inputs52")
    from tests.conftest import REPO

    smoke = REPO / "campaigns" / "smoke.toml"
    (d / "config.toml").write_text(f'[train]\ndataset = "{smoke}"\niterations = 2\nout = "{d / "never"}"\n')
    (d / "odd.toml").write_text(f'[train]\ndataset = "{smoke}"\niterations = 2\nbatch_size = 3\n'
                                f'out = "{d / "odd_never"}"\n')
    (d / "empty").mkdir()
    (d / "sched_empty.json").write_text("")
    (d / "sched_noaddr.json").write_text('{"type": "Scheduler"}')
    (d / "sched_dir.json").mkdir()
    head = '[study]\nct = "phantom"\ncases = 2\nmethods = ["contextual"]\nsize = [64, 64]\n'
    (d / "tools.toml").write_text(head + '[[variant]]\nname = "v"\nmodel = "pelvis_line"\n'
                                         '[[target]]\nname = "line"\ntools = [1, 2]\n')
    (d / "nodata.toml").write_text(head + f'[[variant]]\nname = "v"\n[variant.train]\ndataset = "{d / "nope.toml"}"\n'
                                          '[[target]]\nname = "line"\n')
    return {**inputs, "config": str(d / "config.toml"), "oddconfig": str(d / "odd.toml"), "emptydir": str(d / "empty"),
            "schedempty": str(d / "sched_empty.json"), "schednoaddr": str(d / "sched_noaddr.json"),
            "scheddir": str(d / "sched_dir.json"), "toolstudy": str(d / "tools.toml"),
            "nodatastudy": str(d / "nodata.toml")}


@pytest.mark.parametrize("name", list(BAD))
def test_a_bad_input_is_refused_in_one_line_and_writes_nothing(name, inputs52, tmp_path, capsys, monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("loaded or trained before the refusal")

    monkeypatch.setattr("sim.load_ct", no_work)
    monkeypatch.setattr("learn.train.train", no_work)
    monkeypatch.setattr("learn.distributed.launch", no_work)
    line, words = BAD[name]
    status, new = _run(line, inputs52, tmp_path)
    assert_refused(status, capsys.readouterr().err, new, line, words)
