"""Issue 29: a study reuses a finished training or evaluation only when it was made with the
settings the study now asks for, and otherwise redoes it naming the keys that changed; a damaged
state file is one line; refusals come before any work.

Training and evaluation are replaced by fakes that record their calls (the real ones are tested
in test_study.py): what is under test is which parts a run redoes, keeps or refuses."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from register.evaluation import study as S
from register.evaluation.study import StudyError, load_study

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "campaigns" / "smoke.toml"


def _variant(name: str, iterations: int = 2, extra: str = "") -> str:
    return f'''
[[variant]]
name = "{name}"
[variant.train]
dataset = "{SMOKE}"
iterations = {iterations}
batch_size = 2
head_channels = 8
{extra}'''


HEAD = '''
[study]
ct = "phantom:0"
cases = 1
methods = ["contextual"]
size = [32, 32]
'''
LINE = '\n[[target]]\nname = "line"\n'
FLUORO = ('\n[[target]]\nname = "fluoro"\nkind = "xray"\n'
          'physics = {{ level = "full", kvp = {kvp}, mas = 1.0, scatter_photons = 2000 }}\n'
          'display = {{ log = true, polarity = "{polarity}", bits = 12, shutter = "black" }}\n')


class Fakes:
    """Training, the network and both evaluations replaced; ``calls`` lists what ran."""

    def __init__(self, monkeypatch):
        import learn.checkpoint
        import learn.predict
        import learn.train

        self.calls: list[tuple] = []

        def train(cfg, *, resume=False, log=print, **kw):
            self.calls.append(("train", Path(cfg.out).name, cfg.iterations, resume))
            from dataclasses import asdict

            Path(cfg.out, "checkpoint.pt").write_text(json.dumps({"iteration": cfg.iterations,
                                                                  "config": S._plain(asdict(cfg))}))

        def load_checkpoint(path):
            try:
                data = json.loads(Path(path).read_text())
            except ValueError:
                raise learn.checkpoint.CheckpointError(f"checkpoint {path}: not a checkpoint") from None
            return SimpleNamespace(iteration=data["iteration"], config=data["config"])

        def evaluate(kind):
            def run(study, target, volume, center, predictor, folder, log, stamp=None, client=None, model=None):
                from register.evaluation.evaluate import EvaluationSettings, summarize

                self.calls.append(("evaluate", folder.parent.name, target.name))
                rows = [{"case": 0, "method": m, "rot_err_deg": 1.0, "trans_err_mm": 2.0, "mtre_mm": 3.0,
                         "mpd_mm": 1.5, "time_s": 0.1, "success": False} for m in study.methods]
                summary = summarize(rows, EvaluationSettings(cases=1))
                from sim.core.atomic import write_json

                write_json(folder / "summary.json", {"summary": summary, **(stamp or {})})
                return summary
            return run

        monkeypatch.setattr(learn.train, "train", train)
        monkeypatch.setattr(learn.checkpoint, "load_checkpoint", load_checkpoint)
        monkeypatch.setattr(learn.predict, "NetworkPredictor", lambda ckpt: object())
        monkeypatch.setattr(S, "NetworkPredictor", lambda ckpt: object())  # as the study imported it
        monkeypatch.setattr(S, "_evaluate_drr", evaluate("drr"))
        monkeypatch.setattr(S, "_evaluate_xray", evaluate("xray"))
        monkeypatch.setattr(S, "_plot", lambda *a: None)

    def run(self, tmp_path, text: str, **kw) -> tuple[list, list[str]]:
        path = tmp_path / "s.toml"
        path.write_text(text)
        self.calls.clear()
        lines: list[str] = []
        S.run_domain_study(load_study(path), tmp_path / "o", log=lines.append, **kw)
        return list(self.calls), lines


@pytest.fixture
def fakes(monkeypatch):
    return Fakes(monkeypatch)


def test_a_variant_removed_and_added_back_changed_is_trained_and_evaluated_again(tmp_path, fakes):
    a, b = _variant("a"), _variant("b")
    calls, _ = fakes.run(tmp_path, HEAD + a + b + LINE)
    assert ("train", "a", 2, False) in calls and ("evaluate", "a", "line") in calls
    calls, log = fakes.run(tmp_path, HEAD + a + b + LINE)  # unchanged: everything kept
    assert calls == [] and "variant a: trained (2 iterations), kept" in log and "a on line: evaluated, kept" in log
    fakes.run(tmp_path, HEAD + a + LINE)  # b removed from the study file ...
    calls, log = fakes.run(tmp_path, HEAD + a + _variant("b", iterations=3) + LINE)  # ... and back, changed
    assert calls == [("train", "b", 3, False), ("evaluate", "b", "line")], calls
    said = "\n".join(log)
    assert "variant b: trained with other settings (train.iterations: 2 -> 3): training again" in said
    assert "b on line: evaluated with other settings (network.training_sha256: the variant's network changed)" in said
    assert list((tmp_path / "o" / "replaced" / "variants").glob("b-*")), "the old training is kept aside"
    record = json.loads((tmp_path / "o" / "variants" / "b" / "settings.json").read_text())
    assert record["settings"]["train"]["iterations"] == 3
    summary = json.loads((tmp_path / "o" / "results" / "b" / "line" / "summary.json").read_text())
    assert summary["study_settings"]["network"]["training_sha256"] == S._digest(record["settings"])


def test_a_changed_input_file_redoes_the_training(tmp_path, fakes):
    campaign = tmp_path / "c.toml"
    campaign.write_text(SMOKE.read_text())
    variant = _variant("a").replace(str(SMOKE), str(campaign))
    fakes.run(tmp_path, HEAD + variant + LINE)
    campaign.write_text(SMOKE.read_text() + "\n# edited\n")
    calls, log = fakes.run(tmp_path, HEAD + variant + LINE)
    assert calls[0] == ("train", "a", 2, False)
    assert "inputs.dataset: its content changed" in "\n".join(log)


def test_a_target_removed_and_added_back_changed_is_evaluated_again(tmp_path, fakes):
    a = _variant("a")
    fluoro = FLUORO.format(kvp=80, polarity="bone-dark")
    fakes.run(tmp_path, HEAD + a + LINE + fluoro)
    fakes.run(tmp_path, HEAD + a + LINE)
    calls, log = fakes.run(tmp_path, HEAD + a + LINE + FLUORO.format(kvp=70, polarity="bone-bright"))
    assert calls == [("evaluate", "a", "fluoro")], calls
    said = "\n".join(log)
    assert "a on fluoro: evaluated with other settings (" in said
    assert "target.physics.kvp: 80 -> 70" in said and 'target.display.polarity: "bone-dark" -> "bone-bright"' in said
    assert "a on line: evaluated, kept" in said
    assert list((tmp_path / "o" / "replaced" / "results" / "a").glob("fluoro-*"))


def test_another_process_s_stale_evaluation_is_left_out_of_the_table(tmp_path, fakes):
    a, b = _variant("a"), _variant("b")
    fakes.run(tmp_path, HEAD + a + b + LINE)
    fakes.run(tmp_path, HEAD + a + LINE)
    calls, log = fakes.run(tmp_path, HEAD + a + _variant("b", iterations=3) + LINE, only=("a",))
    assert calls == []
    assert any(line.startswith("b on line: made with other settings (") and "--only b redoes it" in line
               for line in log), log
    assert "| b |" not in (tmp_path / "o" / "table.md").read_text()


def test_an_evaluation_from_before_the_record_is_redone(tmp_path, fakes):
    a = _variant("a")
    fakes.run(tmp_path, HEAD + a + LINE)
    path = tmp_path / "o" / "results" / "a" / "line" / "summary.json"
    data = json.loads(path.read_text())
    path.write_text(json.dumps({"summary": data["summary"]}))  # as an older ctxreg wrote it
    calls, log = fakes.run(tmp_path, HEAD + a + LINE)
    assert calls == [("evaluate", "a", "line")]
    assert "made before the study recorded each evaluation's settings" in "\n".join(log)


def test_a_training_from_before_the_record_is_checked_against_its_checkpoint(tmp_path, fakes):
    a = _variant("a")
    fakes.run(tmp_path, HEAD + a + LINE)
    (tmp_path / "o" / "variants" / "a" / "settings.json").unlink()  # as an older ctxreg left it
    calls, log = fakes.run(tmp_path, HEAD + a + LINE)
    assert calls == [], calls  # the checkpoint's config matches: kept (and recorded now)
    assert (tmp_path / "o" / "variants" / "a" / "settings.json").is_file()
    (tmp_path / "o" / "variants" / "a" / "settings.json").unlink()
    fakes.run(tmp_path, HEAD + _variant("z") + LINE)  # a out of the study ...
    calls, log = fakes.run(tmp_path, HEAD + _variant("z") + _variant("a", 4) + LINE)
    assert ("train", "a", 4, False) in calls
    assert "train.iterations 2 -> 4" in "\n".join(log)


DAMAGE = {
    "not JSON": "{ nope",
    "a list": "[1, 2]",
    "no summary": '{"target": "line"}',
    "summary without statistics": '{"summary": {"contextual": {"cases": 1}}}',
}


@pytest.mark.parametrize("case", list(DAMAGE))
@pytest.mark.parametrize("chosen", [True, False], ids=["this process's", "another process's"])
def test_a_damaged_summary_is_one_line(tmp_path, fakes, case, chosen):
    a = _variant("a")
    fakes.run(tmp_path, HEAD + a + LINE)
    path = tmp_path / "o" / "results" / "a" / "line" / "summary.json"
    path.write_text(DAMAGE[case])
    with pytest.raises(StudyError) as e:
        fakes.run(tmp_path, HEAD + a + _variant("b") + LINE, only=None if chosen else ("b",))
    msg = str(e.value)
    assert str(path) in msg and "remove it to redo that evaluation" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("name, text", [("settings.json", "{ nope"), ("settings.json", '{"sha256": 3}'),
                                        ("checkpoint.pt", "garbage")])
def test_a_damaged_training_state_is_one_line(tmp_path, fakes, name, text):
    a = _variant("a")
    fakes.run(tmp_path, HEAD + a + LINE)
    folder = tmp_path / "o" / "variants" / "a"
    if name == "checkpoint.pt":
        (folder / "settings.json").unlink()
    (folder / name).write_text(text)
    with pytest.raises(StudyError) as e:
        fakes.run(tmp_path, HEAD + a + LINE)
    assert str(folder / name) in str(e.value) and "remove it to redo" in str(e.value)
    assert "\n" not in str(e.value)


def test_a_damaged_summary_through_the_command_is_one_line(tmp_path, fakes, capsys):
    from register.cli import main

    a = _variant("a")
    fakes.run(tmp_path, HEAD + a + LINE)
    (tmp_path / "o" / "results" / "a" / "line" / "summary.json").write_text("{ nope")
    assert main(["study", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "remove it to redo that evaluation" in err and err.strip().count("\n") == 0 and "Traceback" not in err


@pytest.mark.parametrize("kw, words", [({"only": ("nosuch",)}, "--only nosuch"),
                                       ({"targets": ("nosuch",)}, "--targets nosuch")])
def test_unknown_filters_are_refused_before_study_json_is_written(tmp_path, fakes, kw, words):
    with pytest.raises(StudyError, match=words):
        fakes.run(tmp_path, HEAD + _variant("a") + LINE, **kw)
    assert not (tmp_path / "o" / "study.json").exists()
    calls, _ = fakes.run(tmp_path, HEAD + _variant("b") + LINE)  # the folder takes another study
    assert ("train", "b", 2, False) in calls


@pytest.mark.parametrize("size", [[64, 32], [32, 128]])
def test_a_size_off_the_detector_aspect_is_refused_naming_study_size(tmp_path, size):
    path = tmp_path / "s.toml"
    path.write_text(HEAD.replace("size = [32, 32]", f"size = {size}") + _variant("a") + LINE)
    with pytest.raises(StudyError) as e:
        load_study(path)
    assert "study.size" in str(e.value) and "aspect" in str(e.value) and "\n" not in str(e.value)
