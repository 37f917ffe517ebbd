"""Shipped models: weights-only export with a card, the card checked against its weights, and
every model committed under models/ loads and matches its card."""

from __future__ import annotations

import pytest
import torch

from learn.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from learn.shipped import DEFAULT_MODEL, ModelCardError, export_model, load_card, shipped_models


def _trained(tmp_path):
    from learn.model import pose_update_net

    net = pose_update_net(backbone="tiny", head_channels=8)
    ckpt = Checkpoint(model_state=net.state_dict(), backbone="tiny", head_channels=8, preprocess=("normalize",),
                      config={"iterations": 3}, image_size=(32, 32), physics={"name": "line", "level": "line"},
                      iteration=3, optimizer={"state": {}, "param_groups": []}, rng={"torch": torch.get_rng_state()})
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, ckpt)
    return path, net


TRAINING = {"trained_on": "a few test pairs", "data": "none", "images": "32 x 32 line DRRs", "physics": "line",
            "randomization": "none", "init_from": "random weights", "config": "x.toml", "command": "ctxreg train x.toml",
            "iterations": 3, "batch_size": 4, "pairs_seen": 12, "seed": 0, "duration_s": 1.5, "machine": "a test"}


def _accuracy(success=0.5):
    return {"protocol": "the network alone", "headline": ["line_drrs"],
            "line_drrs": {"what": "line DRRs, 2 poses from AP", "command": "ctxreg evaluate", "measured": "today",
                          "cases": 2, "success": success, "rotation_deg_mean": 1.5, "translation_mm_mean": 12.0}}


def test_export_keeps_the_weights_drops_the_training_state_and_writes_a_checked_card(tmp_path):
    src, net = _trained(tmp_path)
    card_path = export_model(src, tmp_path / "m", name="m", summary="test", training=TRAINING,
                             accuracy=_accuracy())
    card = load_card(tmp_path / "m")
    assert card["model"]["image_size"] == [32, 32] and card["model"]["preprocess"] == ["normalize"]
    assert card["model"]["current_field"] == "masked"  # the default of a checkpoint that does not record it
    assert card["training"]["command"] == "ctxreg train x.toml" and card["accuracy"]["line_drrs"]["success"] == 0.5
    out = load_checkpoint(tmp_path / "m" / "model.pt")
    assert out.optimizer is None and out.rng is None and out.iteration == 3
    for k, v in net.state_dict().items():
        assert torch.equal(out.model_state[k], v)
    assert (tmp_path / "m" / "model.pt").stat().st_size < src.stat().st_size
    # a card that says something its weights do not: refused, naming the key
    text = card_path.read_text()
    card_path.write_text(text.replace("image_size = [32, 32]", "image_size = [64, 64]"))
    with pytest.raises(ModelCardError, match=r"model.image_size is \[64, 64\] but"):
        load_card(tmp_path / "m")
    card_path.write_text(text)
    # weights changed after the card: refused
    with open(tmp_path / "m" / "model.pt", "ab") as f:
        f.write(b"\0")
    with pytest.raises(ModelCardError, match="sha256 does not match"):
        load_card(tmp_path / "m")
    with pytest.raises(ModelCardError, match="no model.toml"):
        load_card(tmp_path)


@pytest.mark.parametrize("name", sorted(shipped_models()) or ["(none)"])
def test_every_shipped_model_loads_and_matches_its_card(name):
    if name == "(none)":
        pytest.skip("no model under models/ yet")
    folder = shipped_models()[name]
    card = load_card(folder)
    assert card["model"]["name"] == name
    assert {"command", "config", "trained_on"} <= set(card["training"]) and card["accuracy"]["headline"]
    # the network's own accuracy only: no pipeline (refinement, global search) numbers on a card
    assert not [k for k in card["accuracy"] if "cmaes" in k or k.startswith("register")]
    assert (folder / card["model"]["file"]).stat().st_size < 20 * 2**20  # weights only: a few MB


def test_no_shipped_model_trained_on_the_validation_pelvis():
    """pelvis_chiconasa_2mm validates work on a patient never seen: no shipped or base model's
    training config names it among its campaign's CTs (comments may say it is left out)."""
    from sim.core.atomic import read_toml

    root = shipped_models()[DEFAULT_MODEL].parents[1]
    for name, folder in shipped_models().items():
        config = root / load_card(folder)["training"]["config"]
        if not config.is_file():  # the oldest cards name a config by its run, not its file
            continue
        dataset = (config.parent / read_toml(config, ValueError, "config")["train"]["dataset"]).resolve()
        if dataset.suffix != ".toml":
            continue
        paths = [ct["path"] for ct in read_toml(dataset, ValueError, "campaign").get("cts", [])]
        assert paths and not [p for p in paths if "chiconasa" in p], f"{name}: {dataset.name} trains on {paths}"


def test_the_base_network_is_one_ctxreg_adapt_starts_from(tmp_path):
    """pelvis_base is a realistic randomized network: ctxreg adapt builds its run from it (its
    weights the run's start, its randomization the pairs')."""
    from learn.adapt import ADAPT, _train_config
    from learn.shipped import resolve_model

    path = resolve_model("pelvis_base")
    base = load_checkpoint(path)
    cfg = _train_config(tmp_path, path, base, ADAPT)
    assert cfg.init_from == str(path) and cfg.backbone == "small" and not cfg.freeze_backbone
    # the default model's randomization, and what was added since at its off value (field_missed 0)
    shipped = load_checkpoint(resolve_model(DEFAULT_MODEL)).physics["randomize"]
    assert {k: v for k, v in cfg.randomize.items() if k in shipped} == shipped
    assert all(v == 0.0 for k, v in cfg.randomize.items() if k not in shipped)


def test_a_model_is_named_or_a_path_and_the_default_is_shipped(tmp_path):
    from learn.shipped import DEFAULT_MODEL, describe_models, resolve_model
    from learn.predict import NetworkPredictor

    src, _ = _trained(tmp_path)
    export_model(src, tmp_path / "models" / "mine", name="mine", summary="a test model", training=TRAINING,
                 accuracy=_accuracy())
    root = tmp_path / "models"
    assert resolve_model("mine", root) == root / "mine" / "model.pt"
    assert resolve_model(str(src), root) == src  # a file is a file
    with pytest.raises(ModelCardError, match=r"--model yours: neither a checkpoint file nor a shipped model "
                                             r"\(shipped: mine"):
        resolve_model("yours", root)
    with pytest.raises(ModelCardError, match=f"the default model '{DEFAULT_MODEL}' is not in"):
        resolve_model(None, root)
    text = describe_models(root, width=80)
    assert text.startswith("mine: a test model\n  image 32 x 32 px, preprocessing normalize, backbone tiny\n"
                           "  trained on a few test pairs\n"
                           "  alone: line DRRs, 2 poses from AP: 50 % with success, 1.50 deg / 12.0 mm mean")
    assert max(len(line) for line in text.splitlines()) <= 80
    # the repository's default model exists, and a predictor takes a name
    assert DEFAULT_MODEL in shipped_models()
    assert NetworkPredictor(DEFAULT_MODEL).size == tuple(load_card(shipped_models()[DEFAULT_MODEL])["model"]
                                                         ["image_size"])
    # a missing checkpoint path still gets the checkpoint's own message
    from learn.checkpoint import CheckpointError

    with pytest.raises(CheckpointError, match="not found|No such file|does not exist"):
        NetworkPredictor(str(tmp_path / "none.pt"))


def test_ctxreg_models_lists_the_shipped_models_and_prints_a_whole_card(capsys):
    import json

    from register.cli import main

    assert main(["models"]) == 0
    out = capsys.readouterr().out
    for name in shipped_models():
        assert f"\n{name}" in f"\n{out}"
    assert max(len(line) for line in out.splitlines()) <= 100  # a terminal's width
    assert "issue" not in out.lower()
    assert main(["models", "pelvis_line"]) == 0
    card = json.loads(capsys.readouterr().out)
    assert card["model"]["name"] == "pelvis_line" and "line_drrs" in card["accuracy"]
    assert main(["models", "--json"]) == 0
    assert set(json.loads(capsys.readouterr().out)) == set(shipped_models())
    assert main(["models", "no_such_model"]) != 0
    assert "no shipped model 'no_such_model' (shipped: " in capsys.readouterr().err


@pytest.mark.parametrize("edit, message", [
    (lambda c: c["model"].pop("summary"), "model.summary is missing"),
    (lambda c: c["model"].update(summary="trained for issue 28"), "without issue numbers"),
    (lambda c: c["training"].update(pairs_seen="many"), "training.pairs_seen must be int"),
    (lambda c: c["training"].update(colour="red"), "training.colour is not a key of the card's schema"),
    (lambda c: c.update(results={}), r"unknown section\(s\) \['results'\]"),
    (lambda c: c["accuracy"]["line_drrs"].update(success=1.5), "success: must be a fraction in"),
    (lambda c: c["accuracy"]["line_drrs"].update(contextual_cmaes_success=1.0),
     "contextual_cmaes_success: not a key of a measurement"),
    (lambda c: c["accuracy"]["line_drrs"].pop("command"), "line_drrs.command: missing"),
    (lambda c: c["accuracy"].update(headline=["grid"]), "headline names 'grid'"),
    (lambda c: c["accuracy"]["line_drrs"].update(rotation_deg_mean=float("nan")), "must be a number >= 0"),
])
def test_a_card_outside_the_schema_is_refused_naming_the_key(tmp_path, edit, message):
    import copy

    from learn.shipped import check_card

    card = {"model": {"name": "m", "summary": "s", "file": "model.pt", "sha256": "0", "backbone": "tiny",
                      "head_channels": 8, "image_size": [32, 32], "preprocess": ["normalize"], "physics": {},
                      "current_physics": {}, "current_field": "masked", "iterations": 3},
            "training": dict(TRAINING), "accuracy": _accuracy()}
    check_card(copy.deepcopy(card))
    edit(card)
    with pytest.raises(ModelCardError, match=message):
        check_card(card)
    src, _ = _trained(tmp_path)  # export_model refuses such tables before writing anything
    with pytest.raises(ModelCardError):
        export_model(src, tmp_path / "x", name="x", summary="trained for issue 28", training=TRAINING,
                     accuracy=_accuracy())
    assert not (tmp_path / "x").exists()


class _Payload:
    """An object a model file could smuggle in: loading must not build it."""

    def __reduce__(self):
        return (print, ("this ran",))


def test_a_model_folder_whose_weights_pickle_an_object_is_refused_by_name(tmp_path, capsys):
    from learn.shipped import resolve_model
    from learn.predict import NetworkPredictor

    src, _ = _trained(tmp_path)
    export_model(src, tmp_path / "models" / "bad", name="bad", summary="x", training=TRAINING, accuracy=_accuracy())
    weights = tmp_path / "models" / "bad" / "model.pt"
    state = torch.load(weights, weights_only=True)
    state["extra"] = _Payload()
    torch.save(state, weights)
    with pytest.raises(ModelCardError, match="sha256 does not match"):  # the card notices first
        resolve_model("bad", tmp_path / "models")
    from learn.checkpoint import CheckpointError

    with pytest.raises(ModelCardError, match="sha256 does not match"):  # by path inside its folder too (issue 29)
        NetworkPredictor(str(weights))
    import shutil

    loose = shutil.copy(weights, tmp_path / "loose.pt")
    with pytest.raises(CheckpointError, match="contains objects other than tensors and plain data"):
        NetworkPredictor(str(loose))  # the file itself, without a card
    assert "this ran" not in capsys.readouterr().out


@pytest.mark.parametrize("field", ["masked", "open", "half"])
def test_the_predictor_follows_the_current_field_its_checkpoint_records(tmp_path, field):
    from dataclasses import replace

    from learn.checkpoint import CheckpointError
    from learn.predict import NetworkPredictor

    src, _ = _trained(tmp_path)
    ckpt = load_checkpoint(src)
    path = tmp_path / "field.pt"
    save_checkpoint(path, replace(ckpt, config={**ckpt.config, "current_field": field}, path=None))
    if field == "half":
        with pytest.raises(CheckpointError, match="config.current_field must be one of masked, open, got 'half'"):
            NetworkPredictor(path)
    else:
        assert NetworkPredictor(path).current_field == field


@pytest.mark.parametrize("tone", [None, "ct", "off", "histogram"])
def test_the_predictor_follows_the_tone_its_checkpoint_records(tmp_path, tone):
    from dataclasses import replace

    from learn.checkpoint import CheckpointError
    from learn.predict import NetworkPredictor

    src, _ = _trained(tmp_path)
    ckpt = load_checkpoint(src)
    config = {k: v for k, v in ckpt.config.items() if k != "tone"}
    path = tmp_path / "tone.pt"
    save_checkpoint(path, replace(ckpt, config=config if tone is None else {**config, "tone": tone}, path=None))
    if tone == "histogram":
        with pytest.raises(CheckpointError, match="config.tone must be one of ct, off, got 'histogram'"):
            NetworkPredictor(path)
    else:
        assert NetworkPredictor(path).tone == (tone or "off")  # not recorded: trained before the tone


def test_ctxreg_models_into_a_reader_that_left_ends_quietly(monkeypatch, capsys):
    import learn.shipped
    from register.cli import main

    def gone(*args, **kwargs):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(learn.shipped, "describe_models", gone)
    assert main(["models"]) == 0  # `ctxreg models | head`: no traceback, no error line
    assert capsys.readouterr().err == ""
