"""``ctxreg study``: a tiny study end to end (train, evaluate on a DRR and a realistic-frame domain,
table, plot, commands), its resume after an interruption, and its bad study files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from register.evaluation.study import StudyError, load_study

ROOT = Path(__file__).resolve().parents[2]

_SMOKE = str(ROOT / "campaigns" / "smoke.toml")
TINY = f'''
[study]
ct = "phantom"
cases = 2
methods = ["contextual"]
size = [64, 64]

[[variant]]
name = "tiny"
[variant.train]
dataset = "{ROOT / 'campaigns' / 'smoke.toml'}"
iterations = 2
batch_size = 2
val_pairs = 2
val_every = 1
checkpoint_every = 1
pairs_per_epoch = 4
head_channels = 8

[[variant]]
name = "tiny-realistic"          # realistic randomized targets (learn.online.RealisticTargets)
[variant.train]
dataset = "{ROOT / 'campaigns' / 'smoke.toml'}"
iterations = 2
batch_size = 2
val_pairs = 2
val_every = 1
checkpoint_every = 1
head_channels = 8
[variant.train.randomize]
scatter = ["none", "kernel"]

[[target]]
name = "line"

[[target]]
name = "fluoro"
kind = "xray"
physics = {{ level = "full", kvp = 80, mas = 1.0, scatter_photons = 20000 }}
collimator = {{ shape = "circle", radius = 0.45, transmission = 0.02 }}
display = {{ log = true, polarity = "bone-dark", gamma = 0.8, bits = 12, shutter = "black" }}
'''


@pytest.mark.slow
def test_a_tiny_study_runs_end_to_end_and_resumes(tmp_path, capsys, monkeypatch):
    from register.cli import main

    study, out = tmp_path / "s.toml", tmp_path / "o"
    study.write_text(TINY)
    assert main(["study", str(study), "--out", str(out)]) == 0
    for name in ("study.json", "table.md", "results.json", "study.png", "commands.sh",
                 "variants/tiny/checkpoint.pt", "variants/tiny/train.toml", "variants/tiny-realistic/checkpoint.pt",
                 "results/tiny/line/summary.json", "results/tiny/fluoro/summary.json",
                 "results/tiny/fluoro/frames/case_000.dcm"):
        assert (out / name).is_file(), name
    table = (out / "table.md").read_text()
    assert "| tiny | line | contextual |" in table and "| tiny | fluoro | contextual |" in table
    first = json.loads((out / "results.json").read_text())["results"]
    assert first["tiny"]["line"]["contextual"]["cases"] == 2
    assert f"ctxreg study {study}" in (out / "commands.sh").read_text()
    capsys.readouterr()

    # a second run keeps everything; an evaluation lost in an interruption is redone, identically
    (out / "results" / "tiny" / "fluoro" / "summary.json").unlink()
    assert main(["study", str(study), "--out", str(out)]) == 0
    log = capsys.readouterr().out
    assert "variant tiny: trained (2 iterations), kept" in log and "tiny on line: evaluated, kept" in log
    assert "tiny on fluoro: 2 cases (xray)" in log
    again = json.loads((out / "results.json").read_text())["results"]
    for target in ("line", "fluoro"):
        for err in ("rot_err_deg", "mtre_mm"):
            assert again["tiny"][target]["contextual"][err]["mean"] == pytest.approx(
                first["tiny"][target]["contextual"][err]["mean"], rel=1e-9)

    # a frame the registration refuses (its one-line input error) is a failed case, not a failed study
    import register.api
    from register.xray.field import FieldError
    from sim.core.errors import InputError

    def refuse(*args, **kwargs):
        raise FieldError("the valid pixels cover only 0.0 % of the image")

    (out / "results" / "tiny" / "fluoro" / "summary.json").unlink()
    monkeypatch.setattr(register.api, "register_xray", refuse)
    assert main(["study", str(study), "--out", str(out), "--only", "tiny"]) == 0
    refused = json.loads((out / "results" / "tiny" / "fluoro" / "summary.json").read_text())["summary"]["contextual"]
    assert refused["refused"] == 2 and refused["success"] == 0.0
    assert "refused (the valid pixels cover only" in capsys.readouterr().out
    # any other error (a bad setting, not the frame) still stops the study with its one line
    (out / "results" / "tiny" / "fluoro" / "summary.json").unlink()

    def bad_setting(*args, **kwargs):
        raise InputError("--size: a bad setting")

    monkeypatch.setattr(register.api, "register_xray", bad_setting)
    assert main(["study", str(study), "--out", str(out), "--only", "tiny"]) == 2
    assert "--size: a bad setting" in capsys.readouterr().err
    monkeypatch.undo()
    assert main(["study", str(study), "--out", str(out), "--only", "tiny"]) == 0
    capsys.readouterr()

    # changed settings are refused, naming the key; an added target is welcome
    study.write_text(TINY.replace("cases = 2", "cases = 3"))
    assert main(["study", str(study), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cases: 2 -> 3" in err and err.count("\n") == 1
    study.write_text(TINY + '\n[[target]]\nname = "poly"\ncases = 1\nphysics = { level = "poly", mas = 2.0 }\n')
    assert main(["study", str(study), "--out", str(out)]) == 0
    assert "| tiny | poly | contextual | 1 |" in (out / "table.md").read_text()  # its own case count

    # an existing network as a variant: evaluated as it is, the same numbers as the variant it was
    ckpt = out / "variants" / "tiny" / "checkpoint.pt"
    study.write_text(TINY + '\n[[target]]\nname = "poly"\ncases = 1\nphysics = { level = "poly", mas = 2.0 }\n'
                     + f'\n[[variant]]\nname = "as-is"\nmodel = "{ckpt}"\n')
    assert main(["study", str(study), "--out", str(out)]) == 0
    assert "variant as-is: the model" in capsys.readouterr().out
    res = json.loads((out / "results.json").read_text())["results"]
    assert res["as-is"]["line"]["contextual"]["mtre_mm"]["mean"] == pytest.approx(
        res["tiny"]["line"]["contextual"]["mtre_mm"]["mean"], rel=1e-9)
    assert "as-is" not in (out / "commands.sh").read_text()  # nothing to train


BAD = {
    "no study table": ("", "needs a [study] table"),
    "unknown study key": ("[study]\nct = 'phantom'\nfoo = 1\n", "unknown key(s) ['foo']"),
    "cmaes is not a network method": (TINY.replace('methods = ["contextual"]', 'methods = ["cmaes"]'),
                                      "study.methods: distinct contextual methods"),
    "size out of range": (TINY.replace("size = [64, 64]", "size = [64, 100000]"), "study.size"),
    "cases zero": (TINY.replace("cases = 2", "cases = 0"), "study.cases: an integer in [1, 10000]"),
    "bad variant name": (TINY.replace('name = "tiny"', 'name = "a/b"'), "variant[0].name"),
    "out set by hand": (TINY.replace("iterations = 2", "iterations = 2\nout = 'x'"), "train.out: set by the study"),
    "train key of a wrong type": (TINY.replace("batch_size = 2", 'batch_size = "2"'), "variant[0].train"),
    "unknown train key": (TINY.replace("batch_size = 2", "batchsize = 2"), "variant[0].train"),
    "kvp out of range": (TINY.replace("kvp = 80", "kvp = 400"), "target[1].physics"),
    "xray without scatter": (TINY.replace('level = "full", kvp', 'level = "poly", kvp'),
                             "target[1].physics.level: kind 'xray'"),
    "unknown target kind": (TINY.replace('kind = "xray"', 'kind = "photo"'), "target[1].kind"),
    "display on a drr target": (TINY + '\n[[target]]\nname = "p"\ndisplay = { bits = 8 }\n',
                                "collimator and display apply to kind 'xray' only"),
    "bad collimator": (TINY.replace("radius = 0.45", "radius = -1.0"), "target[1].collimator"),
    "two targets alike": (TINY + '\n[[target]]\nname = "line"\n', "two targets are named alike"),
    "target cases zero": (TINY.replace('kind = "xray"', 'kind = "xray"\ncases = 0'), "target[1].cases: an integer"),
    "tools on a drr target": (TINY + '\n[[target]]\nname = "p"\ntools = [1, 2]\n',
                              "target[2].tools: tools apply to kind 'xray' only"),
    "tools reversed": (TINY.replace('kind = "xray"', 'kind = "xray"\ntools = [3, 1]'), "target[1].tools: [low, high]"),
    "tools not whole": (TINY.replace('kind = "xray"', 'kind = "xray"\ntools = [1, 2.5]'), "target[1].tools: [low, high]"),
    "second variant's dataset missing": (_SMOKE.join(TINY.split(_SMOKE, 2)[:2]) + str(ROOT / "campaigns" / "nope.toml")
                                         + TINY.split(_SMOKE, 2)[2],
                                         "variant[1] (tiny-realistic).train.dataset: campaign file"),
    "a dataset folder missing": (TINY.replace(_SMOKE, str(ROOT / "campaigns" / "no_folder"), 1),
                                 "variant[0] (tiny).train.dataset: "),
    "init_from missing": (TINY.replace("iterations = 2\n", 'init_from = "no_such.pt"\niterations = 2\n', 1),
                          "variant[0] (tiny).train.init_from: "),
    "not TOML": ("[study\n", "not valid TOML"),
    "model and train": (TINY.replace('name = "tiny"\n', 'name = "tiny"\nmodel = "x.pt"\n', 1),
                        "either train (a [variant.train] table) or model"),
    "missing model": (TINY + '\n[[variant]]\nname = "m"\nmodel = "no/such.pt"\n',
                      "variant[2].model: an existing checkpoint file"),
    "unknown randomize key": (TINY.replace('scatter = ["none", "kernel"]', 'kvpp = 3'),
                              "unknown key(s) train.randomize.kvpp"),
    "monte-carlo in training": (TINY.replace('scatter = ["none", "kernel"]', 'kvp = [70, 90]'),
                                "randomize.scatter: online training cannot run a Monte Carlo"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_study_files_name_the_key(tmp_path, case):
    text, words = BAD[case]
    path = tmp_path / "s.toml"
    path.write_text(text)
    with pytest.raises(StudyError) as e:
        load_study(path)
    assert words in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_a_missing_study_file_is_named(tmp_path):
    with pytest.raises(StudyError, match="not found"):
        load_study(tmp_path / "none.toml")


@pytest.mark.parametrize("path", sorted((ROOT / "studies").glob("*.toml")), ids=lambda p: p.name)
def test_the_shipped_study_files_load(path):
    study = load_study(path)
    assert study.variants and study.targets


@pytest.mark.parametrize("kw, words", [({"only": ("nope",)}, "--only nope: not a variant of the study"),
                                       ({"targets": ("nope",)}, "--targets nope: not a target of the study")])
def test_unknown_variant_or_target_filters_are_named(tmp_path, kw, words):
    from register.evaluation.study import run_domain_study

    path = tmp_path / "s.toml"
    path.write_text(TINY)
    with pytest.raises(StudyError, match=words):
        run_domain_study(load_study(path), tmp_path / "o", log=lambda s: None, **kw)
