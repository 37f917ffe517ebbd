"""Bad inputs to ctxreg train and ctxreg accuracy: each is refused in one line that names the key,
option or file (tables of cases; nothing here trains)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

# key, TOML value, words the message must hold (after "train.KEY must be")
TYPE_CASES = [
    ("dataset", "5", "a string, got the integer 5"),
    ("out", '["runs"]', "a string, got the list ['runs']"),
    ("backbone", "1", "a string, got the integer 1"),
    ("weights", "false", "a string, got false (a boolean)"),
    ("weights_path", "3.0", "a string, got the number 3.0"),
    ("freeze_backbone", "1", "true or false, got the integer 1"),
    ("freeze_backbone", '"yes"', "true or false, got the string 'yes'"),
    ("train_backbone_from", "11", "a string, got the integer 11"),
    ("backbone_lr_scale", '"0.1"', "a finite number, got the string '0.1'"),
    ("physics", "2", "a string, got the integer 2"),
    ("current_physics", "[]", "a string, got the list []"),
    ("subjects_per_batch", "2.0", "an integer, got the number 2.0"),
    ("preprocess", '"normalize"', "a list of step names or tables with a name"),
    ("preprocess", "[1]", "a list of step names or tables with a name"),
    ("preprocess", "[{sigma = 1.0}]", "a list of step names or tables with a name"),
    ("batch_size", '"2"', "an integer, got the string '2'"),
    ("batch_size", "2.5", "an integer, got the number 2.5"),
    ("batch_size", "true", "an integer, got true (a boolean)"),
    ("iterations", "true", "an integer, got true (a boolean)"),
    ("iterations", "1e3", "an integer, got the number 1000.0"),
    ("lr", '"1e-3"', "a finite number, got the string '1e-3'"),
    ("lr", "true", "a finite number, got true (a boolean)"),
    ("lr", "nan", "a finite number, got the number nan"),
    ("lr_decay", "inf", "a finite number, got the number inf"),
    ("lr_step", "false", "an integer, got false (a boolean)"),
    ("lr_schedule", "1", "a string, got the integer 1"),
    ("lr_warmup", '"0.1"', "a finite number, got the string '0.1'"),
    ("pairs_per_epoch", '"all"', "an integer, got the string 'all'"),
    ("val_pairs", "8.0", "an integer, got the number 8.0"),
    ("val_every", "true", "an integer, got true (a boolean)"),
    ("checkpoint_every", "[100]", "an integer, got the list [100]"),
    ("near_fraction", "true", "a finite number, got true (a boolean)"),
    ("near_rot_deg", "[1.0]", "a list of two finite numbers [low, high], got the list [1.0]"),
    ("near_rot_deg", '[1.0, "20"]', "a list of two finite numbers"),
    ("near_trans_mm", "5.0", "a list of two finite numbers [low, high], got the number 5.0"),
    ("near_trans_mm", "[true, 40.0]", "a list of two finite numbers"),
    ("loss", "2", "a string, got the integer 2"),
    ("relative_eps", '"0.1"', "a finite number, got the string '0.1'"),
    ("head_channels", "64.5", "an integer, got the number 64.5"),
    ("cache_features", '"true"', "true or false, got the string 'true'"),
    ("seed", "true", "an integer, got true (a boolean)"),
    ("init_from", "false", "a string, got false (a boolean)"),
    ("randomize", "3", "a table, got the integer 3"),
    ("current_field", "2", "a string, got the integer 2"),
    ("tone", "true", "a string, got true (a boolean)"),
    ("pairs", "1", "a string, got the integer 1"),
    ("framing", "true", "a string, got true (a boolean)"),
    ("precision", "16", "a string, got the integer 16"),
    ("cosine_over", "1", "a string, got the integer 1"),
    ("image_weight", '"0.5"', "a finite number, got the string '0.5'"),
    ("image_pairs", "16.0", "an integer, got the number 16.0"),
    ("image_size", "true", "an integer, got true (a boolean)"),
]


def _config_file(tmp_path, line: str):
    path = tmp_path / "train.toml"
    body = line if line.startswith("dataset") else f'dataset = "campaign.toml"\n{line}'
    path.write_text(f"[train]\n{body}\n")
    return path


@pytest.mark.parametrize("key,value,words", TYPE_CASES, ids=[f"{k}={v}" for k, v, _ in TYPE_CASES])
def test_a_config_value_of_the_wrong_type_is_refused(tmp_path, key, value, words):
    from learn.train import TrainConfigError, load_train_config

    path = _config_file(tmp_path, f"{key} = {value}")
    with pytest.raises(TrainConfigError) as info:
        load_train_config(path)
    msg = str(info.value)
    assert msg == f"{path}: train.{key} must be {words}" or msg.startswith(f"{path}: train.{key} must be {words}"), msg
    assert "\n" not in msg


def test_every_config_key_has_a_wrong_type_case_and_python_values_are_checked_too():
    from learn.train import TrainConfig, TrainConfigError

    assert {f.name for f in dataclasses.fields(TrainConfig)} == {k for k, _, _ in TYPE_CASES}
    for kw in ({"batch_size": True}, {"iterations": 2.0}, {"lr": "0.1"}, {"freeze_backbone": 0}):
        with pytest.raises(TrainConfigError, match=f"train.{next(iter(kw))} must be"):
            TrainConfig(dataset="x.toml", **kw)


def test_right_types_still_load(tmp_path):
    """Integers are numbers (lr = 1), tables are preprocessing steps; the values are kept as written."""
    from learn.train import load_train_config

    path = _config_file(tmp_path, 'lr = 1\nlr_decay = 1\nrelative_eps = 1\nnear_rot_deg = [1, 10]\n'
                                  'preprocess = ["normalize", {name = "gaussian", sigma = 1.0}]\nseed = 0')
    cfg = load_train_config(path)
    assert cfg.lr == 1 and cfg.near_rot_deg == (1, 10) and cfg.preprocess[1] == {"name": "gaussian", "sigma": 1.0}


def test_a_tone_other_than_ct_or_off_or_without_realistic_targets_is_refused():
    from learn.train import TrainConfig, TrainConfigError

    with pytest.raises(TrainConfigError, match="train.tone must be one of ct, off, got 'histogram'"):
        TrainConfig(dataset="x.toml", tone="histogram", randomize={})
    with pytest.raises(TrainConfigError, match="train.tone = 'ct' needs train.randomize"):
        TrainConfig(dataset="x.toml", tone="ct")


def test_seed_out_of_range_is_refused():
    from learn.train import TrainConfig, TrainConfigError

    for seed in (-1, 2**32):
        with pytest.raises(TrainConfigError, match=r"train.seed must be in \[0, 2\^32\)"):
            TrainConfig(dataset="x.toml", seed=seed)


# --------------------------------------------------------------------------------------------
# --resume and init_from on bad checkpoints
# --------------------------------------------------------------------------------------------


def _cfg(tmp_path, **kw):
    from learn.train import TrainConfig

    # the dataset is never opened: the checkpoint is checked first
    return TrainConfig(dataset=str(tmp_path / "missing_campaign.toml"), out=str(tmp_path / "run"), backbone="tiny",
                       head_channels=16, lr=1e-3, **kw)


def _saved(cfg, path, **kw):
    from learn.checkpoint import Checkpoint, capture_rng, save_checkpoint
    from learn.model import pose_update_net

    model = pose_update_net(backbone=cfg.backbone, head_channels=cfg.head_channels)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    base = dict(model_state=model.state_dict(), backbone=cfg.backbone, head_channels=cfg.head_channels,
                preprocess=tuple(cfg.preprocess), config=dataclasses.asdict(cfg), image_size=(32, 32),
                iteration=2, optimizer=opt.state_dict(),
                scheduler=torch.optim.lr_scheduler.StepLR(opt, step_size=5).state_dict(), rng=capture_rng())
    base.update(kw)
    save_checkpoint(path, Checkpoint(**base))


RESUME_CASES = {
    "empty": (lambda p: p.write_bytes(b""), "is empty (0 bytes)"),
    "truncated": (lambda p: p.write_bytes(p.read_bytes()[:3000]), "is truncated or corrupt"),
    "foreign-state-dict": (lambda p: torch.save({"w": torch.zeros(2)}, p), "it is a bare state dict"),
    "foreign-bytes": (lambda p: p.write_bytes(b"\x00" * 64), "is not a PyTorch file"),
    "pickled-object": (lambda p: torch.save({"model": {}, "config": {}, "x": np.random.default_rng(0)}, p),
                       "contains objects other than tensors and plain data"),
}


@pytest.mark.parametrize("case", list(RESUME_CASES))
def test_resume_from_a_damaged_or_foreign_checkpoint_is_one_line(tmp_path, case):
    from learn.checkpoint import CheckpointError
    from learn.train import train

    cfg = _cfg(tmp_path)
    ckpt = tmp_path / "run" / "checkpoint.pt"
    _saved(cfg, ckpt)
    damage, words = RESUME_CASES[case]
    damage(ckpt)
    with pytest.raises(CheckpointError) as info:
        train(cfg, resume=True, log=lambda *_: None)
    msg = str(info.value)
    assert words in msg and str(ckpt) in msg and "\n" not in msg, msg


def test_resume_with_another_config_names_the_changed_keys(tmp_path):
    from learn.train import TrainConfigError, train

    _saved(_cfg(tmp_path), tmp_path / "run" / "checkpoint.pt")
    with pytest.raises(TrainConfigError) as info:
        train(_cfg(tmp_path, batch_size=8, preprocess=("normalize", "median")), resume=True, log=lambda *_: None)
    msg = str(info.value)
    assert "was written with another config (train.batch_size 16 -> 8; train.preprocess ('normalize',) -> " \
           "('normalize', 'median')): resume with the same config" in msg


def test_resume_from_a_checkpoint_without_training_state_is_refused(tmp_path):
    from learn.checkpoint import CheckpointError
    from learn.train import train

    cfg = _cfg(tmp_path)
    _saved(cfg, tmp_path / "run" / "checkpoint.pt", optimizer=None, rng=None)
    with pytest.raises(CheckpointError, match=r"holds no training state \(optimizer, rng missing\)"):
        train(cfg, resume=True, log=lambda *_: None)


def test_resume_removes_the_temporary_file_of_a_killed_write(tmp_path):
    """The stale temporary file is gone once the run starts again (here it stops at the missing dataset)."""
    from learn.train import TrainConfigError, train

    cfg = _cfg(tmp_path)
    _saved(cfg, tmp_path / "run" / "checkpoint.pt")
    (tmp_path / "run" / ".checkpoint.pt.k1ll3d00.tmp.pt").write_bytes(b"half")
    with pytest.raises(TrainConfigError, match="missing_campaign.toml"):
        train(cfg, resume=True, log=lambda *_: None)
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [".ctxreg.lock", "checkpoint.pt"]  # the run's lock


def test_init_from_a_checkpoint_of_other_weights_is_one_line(tmp_path):
    from learn.model import pose_update_net
    from learn.train import TrainConfigError, train

    other = tmp_path / "other.pt"
    torch.save(pose_update_net(backbone="tiny", head_channels=16).state_dict(), other)
    with pytest.raises(TrainConfigError, match=r"^train.init_from: checkpoint .*other.pt is not a ctxreg checkpoint: "
                                               r"it is a bare state dict"):
        train(_cfg(tmp_path, init_from=str(other)), log=lambda *_: None)


# --------------------------------------------------------------------------------------------
# ctxreg accuracy
# --------------------------------------------------------------------------------------------


def _nan_weights(state):
    state["heads.2.fc1.bias"][:] = float("nan")
    return state, 16, ("heads.2.fc1.bias", "NaN or infinite")


def _other_head_channels(state):
    from learn.model import pose_update_net

    return pose_update_net(backbone="tiny", head_channels=32).state_dict(), 16, (
        "was trained with head_channels 32 (tiny), the model has head_channels 16 (tiny)", "heads.0.stem.weight")


@pytest.mark.parametrize("edit", [_nan_weights, _other_head_channels], ids=["nan-weights", "weights-do-not-fit"])
def test_accuracy_refuses_a_bad_checkpoint_in_one_line(tmp_path, capsys, edit):
    """Before: a NaN checkpoint gave a table of NaN and JSON with bare NaN; weights that do not fit
    gave PyTorch's list of every mismatching tensor. Now one line, and nothing is written."""
    from learn.checkpoint import Checkpoint
    from learn.model import pose_update_net
    from register.cli import main

    state, head_channels, words = edit(pose_update_net(backbone="tiny", head_channels=16).state_dict())
    ckpt = Checkpoint(model_state=state, backbone="tiny", head_channels=head_channels, preprocess=("normalize",),
                      config={}, image_size=(32, 32))
    torch.save(ckpt.payload(), tmp_path / "bad.pt")
    out = tmp_path / "acc"
    assert main(["accuracy", "--model", str(tmp_path / "bad.pt"), "--ct", "phantom:0", "--pairs", "2",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ctxreg accuracy: error: checkpoint {tmp_path / 'bad.pt'}") and "\n" not in err, err
    assert all(w in err for w in words), err
    assert not out.exists()  # no table of NaN, no JSON


def test_accuracy_options_say_what_they_are():
    """--model is the checkpoint (as in register and evaluate); the campaign entries are --entry and
    --current-entry; --physics (a level elsewhere) is not an accuracy option."""
    from register.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["accuracy", "--model", "m.pt", "--campaign", "c.toml", "--entry", "full",
                              "--current-entry", "poly_clean"])
    assert (args.model, args.entry, args.current_entry) == ("m.pt", "full", "poly_clean")
    for argv in (["accuracy", "m.pt", "--ct", "phantom"], ["accuracy", "--model", "m.pt", "--physics", "full"]):
        with pytest.raises(SystemExit):
            parser.parse_args(argv)


def test_non_finite_predictions_are_refused_and_json_has_no_bare_nan():
    from learn.accuracy import AccuracyError, finite_or_none, prediction_errors
    from learn.predict import Prediction

    class Renderer:
        def render(self, T):
            return np.zeros((len(T), 32, 32))

    class Diverged:
        def predict(self, fixed, drr):
            g = np.zeros((len(fixed), 6))
            g[1, 2] = np.nan
            return Prediction(g, np.zeros((len(fixed), 3, 6)))

    T = np.repeat(np.eye(4)[None], 3, axis=0)
    with pytest.raises(AccuracyError, match="NaN or infinite for 1 of 3 pairs"):
        prediction_errors(Diverged(), Renderer(), T, T)
    record = finite_or_none({"a": float("nan"), "b": [float("inf"), 1.5, ("x", -float("inf"))], "c": "nan"})
    assert record == {"a": None, "b": [None, 1.5, ["x", None]], "c": "nan"}
    json.dumps(record, allow_nan=False)  # strict JSON


@pytest.mark.parametrize("command", ["train", "accuracy"])
@pytest.mark.parametrize("where", ["file", "folder-where-a-file-goes"])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys, command, where):
    """``--out`` (accuracy) or ``[train] out`` that is an existing file, or holds a folder where an
    output file goes: one line naming it, before the checkpoint, CT or campaign is even read."""
    from learn.commands import ACCURACY_FILES, TRAIN_FILES
    from register.cli import main

    out = tmp_path / "out"
    if where == "file":
        out.write_text("not a folder")
    else:
        (out / (TRAIN_FILES if command == "train" else ACCURACY_FILES)[0]).mkdir(parents=True)
    if command == "train":
        cfg = tmp_path / "train.toml"
        cfg.write_text(f'[train]\ndataset = "missing.toml"\nout = "{out}"\n')
        argv = ["train", str(cfg)]
    else:
        argv = ["accuracy", "--model", str(tmp_path / "missing.pt"), "--ct", "phantom", "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ctxreg {command}: error: ") and "\n" not in err and str(out) in err, err
    assert ("existing file" if where == "file" else "existing folder") in err


@pytest.mark.parametrize("args, words", [
    (["--stop-after", "-3"], "--stop-after -3: must be > 0 s"),
    (["--device", "tpu"], "invalid choice: 'tpu'"),
] + ([] if torch.cuda.is_available() else [(["--device", "cuda"], "torch sees no CUDA GPU")]))
def test_train_run_options_are_refused_in_one_line_before_any_work(tmp_path, capsys, args, words):
    from register.cli import main

    cfg = tmp_path / "train.toml"
    cfg.write_text(f'[train]\ndataset = "campaign.toml"\nout = "{tmp_path / "out"}"\n')
    try:
        code = main(["train", str(cfg), *args])
    except SystemExit as e:  # argparse's own refusal (a choice)
        code = e.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("ctxreg train: error:") and words in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args, words", [
    (["--ct", "{tmp}/missing.nii.gz"], "missing.nii.gz"),
    (["--ct", "{tmp}/not_a_ct.nii.gz"], "not_a_ct.nii.gz"),
    (["--minutes", "0"], "--minutes 0: must be in (0, 1440] min"),
    (["--minutes", "nan"], "--minutes"),
    (["--from", "{tmp}/missing.pt"], "missing.pt"),
    (["--from", "no_such_model"], "--from no_such_model: neither a checkpoint file nor a shipped model"),
    (["--from", "pelvis_line"], "not trained on randomized realistic pairs"),
    (["--resume"], "holds no adaptation to continue"),
    (["--device", "tpu"], "invalid choice: 'tpu'"),
] + ([] if torch.cuda.is_available() else [(["--device", "cuda"], "torch sees no CUDA GPU")]))
def test_adapt_refuses_in_one_line_before_any_training(tmp_path, capsys, args, words):
    """``ctxreg adapt``: a missing or damaged CT, a bad time, base model, device or a resume of
    nothing: one line naming it, exit 2, nothing trained (no run folder)."""
    from register.cli import main
    from sim.ct.phantom import write_phantom_nifti

    ct = tmp_path / "ct.nii.gz"
    write_phantom_nifti(ct, 0, spacing_mm=6.0)
    (tmp_path / "not_a_ct.nii.gz").write_bytes(b"not a NIfTI")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    argv = ["adapt", *(["--ct", str(ct)] if "--ct" not in args else []), "--out", str(tmp_path / "out"), *args]
    try:
        code = main(argv)
    except SystemExit as e:  # argparse's own refusal (a choice, a bound)
        code = e.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("ctxreg adapt: error:") and words in err, err
    assert not (tmp_path / "out" / "run").exists()
