"""The metal-tool segmenter (learn.tool_mask): its labels against the simulator's chords, its input
normalisation, the network's shapes, its training's checkpoint and resume, and its model folder's
refusals."""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch

from learn.tool_mask import (METAL_CHANNELS, TOOL_LINE_INTEGRAL, ToolMask, ToolMaskError, ToolTrainSettings,
                             export_tool_mask, metal_weights, segmenter_input, tool_segmenter, train_tool_mask)
from sim.physics.two_basis import TOOL_CHANNELS

ROOT = Path(__file__).resolve().parents[2]
#: one tube setting (one spectral table row: quick to build), tools on most frames
TABLE = {"scatter": ["none", "kernel"], "kvp": 80, "al_mm": 2.5, "cu_mm": {"0.1": 1.0}, "ideal": 0.0, "tools": 0.8}


def test_metal_weights_are_the_metals_mass_attenuation_at_60_kev():
    """Per g/cm^2 of density integral the line integral is mu/rho (cm^2/g): NIST XCOM at 60 keV gives
    iron 1.205, chromium 0.9755 (20 % of a stainless steel), nickel 1.445 (10 %): 1.19 for the
    steel, within 5 % (the steel's exact recipe); copper 1.593 within 5 %; titanium (Z 22) between
    aluminium's 0.2778 (Z 13) and iron's (Z 26); the carbon table and the PVC sheath are not
    labelled (0)."""
    w = dict(zip(TOOL_CHANNELS, metal_weights()))
    assert set(METAL_CHANNELS) <= set(TOOL_CHANNELS)
    assert w["carbon"] == 0 and w["pvc"] == 0
    assert w["stainless_steel"] == pytest.approx(0.7 * 1.205 + 0.2 * 0.9755 + 0.1 * 1.445, rel=0.05)
    assert 0.2778 < w["titanium"] < 1.205
    assert w["copper"] == pytest.approx(1.593, rel=0.05)


def test_segmenter_input_maps_the_fields_percentiles_and_keeps_polarity():
    """Channel 0: the field's 1st / 99th percentiles at 0 / 1 (a ramp over the field: values linear
    in its rank), 0 outside, a bright tool stays above 1 in a bone-bright image and below 0 when the
    image is inverted; channel 1 the field; a constant field gives zeros; bad shapes are named."""
    img = torch.linspace(0, 1, 64 * 64).reshape(1, 64, 64).clone()
    field = torch.zeros(1, 64, 64, dtype=torch.bool)
    field[:, 8:56, 8:56] = True
    img[:, 31, 15:25] = 5.0  # a thin steel rod (under 1 % of the field), far above the anatomy
    x = segmenter_input(img, field)
    assert x.shape == (1, 2, 64, 64) and x.dtype == torch.float32
    assert torch.equal(x[0, 1], field[0].float())
    assert float(x[0, 0][~field[0]].abs().max()) == 0
    inside = x[0, 0][field[0]]
    assert float((inside < 0).float().mean()) == pytest.approx(0.01, abs=0.005)
    assert float(x[0, 0, 31, 20]) == 2.0  # clipped at the top
    inverted = segmenter_input(-img, field)
    assert float(inverted[0, 0, 31, 20]) == -1.0
    flat = segmenter_input(torch.ones(1, 64, 64), field)
    assert float(flat[0, 0].abs().max()) == 0
    with pytest.raises(ToolMaskError, match="bool fields"):
        segmenter_input(img, field.float())
    with pytest.raises(ToolMaskError, match="images"):
        segmenter_input(img[0], field[0])


@pytest.mark.parametrize("shape", [(64, 64), (50, 77), (8, 8)])
def test_the_segmenter_keeps_any_image_size_and_sees_each_pixel(shape):
    """Logits of the input's size (padded to multiples of 8 inside, cropped back); a change at one
    pixel changes the logits there (the output is not shifted by the padding)."""
    torch.manual_seed(0)
    net = tool_segmenter(width=4).eval()
    x = torch.randn(2, 2, *shape)
    with torch.no_grad():
        y = net(x)
    assert y.shape == (2, 1, *shape)
    x2 = x.clone()
    x2[0, 0, shape[0] - 1, shape[1] - 1] += 50.0
    with torch.no_grad():
        y2 = net(x2)
    d = (y2 - y)[0, 0].abs()
    assert float(d[shape[0] - 1, shape[1] - 1]) > 0
    assert torch.equal(y2[1], y[1])
    with pytest.raises(ToolMaskError, match="width"):
        tool_segmenter(width=3)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """A :class:`learn.tool_mask.ToolFrames` of the smoke campaign at 64 px, tools from one bank."""
    from learn.tool_mask import ToolFrames
    from sim.campaign.config import load_campaign
    from sim.randomize import DomainRandomization

    cfg = load_campaign(ROOT / "campaigns" / "smoke.toml")
    r = DomainRandomization.from_table(TABLE)
    return ToolFrames(cfg, "train", randomization=r, seed=2, banks=1, tables=tmp_path_factory.mktemp("tables"))


def test_tool_labels_are_the_visible_part_of_each_draws_metal(frames):
    """Each frame's label lies inside the metal of its own draw's tools (the numpy
    :meth:`sim.randomize.ToolBank.for_draw` of the same draw: arrangement and look; line integral
    >= the threshold; inside the field); frames whose draw has no tools have none; and the labelled
    pixels are the visible metal: over 80 % of them brighter than the mean of the non-tool field
    pixels in the 11 x 11 px around them in a bone-bright display, darker in a bone-dark one, on
    every frame with 20 or more (a tool crosses air and bone: only a local comparison holds)."""
    from scipy import ndimage

    from sim.distractors import mu_line
    from sim.randomize import ToolBank

    n = 16
    image, field, tools = frames.frames(0, n)
    bank = ToolBank(2 * 1000, frames.geometry, scene=frames.cfg.scene.name)
    judged = 0
    for i in range(n):
        draw = frames.randomization.draw(frames.seed, i)
        picked = bank.for_draw(draw)
        if picked is None:
            assert not tools[i].any()
            continue
        chords, channels = picked
        line = sum(mu_line(m, rho) * chords[c] for c, (m, rho) in enumerate(channels) if m in METAL_CHANNELS)
        metal = (np.asarray(line) >= TOOL_LINE_INTEGRAL) & field[i].numpy()
        label = tools[i].numpy()
        assert not (label & ~metal).any(), i
        if label.sum() < 20:
            continue
        judged += 1
        values = image[i].numpy().astype(float)
        around = field[i].numpy() & ~ndimage.binary_dilation(label, iterations=1)
        local = ndimage.uniform_filter(values * around, 11) / np.maximum(ndimage.uniform_filter(around * 1.0, 11), 1e-9)
        brighter = np.mean(values[label] > local[label])
        assert (brighter if draw["polarity"] == "bone-bright" else 1 - brighter) > 0.8, (i, brighter)
    assert judged >= 4


def test_a_training_run_writes_its_curve_resumes_and_refuses_other_settings(tmp_path):
    """A short run writes checkpoint.pt (tensors and plain data) and log.csv; resumed it continues
    from the time and frames it had (the curve grows, nothing restarts); a resume with other settings
    and a fresh run into a folder with a checkpoint are refused, naming why."""
    from learn.torch_file import read_plain_torch_file

    settings = ToolTrainSettings(minutes=0.1, width=4, crop=32, frames=2, val_frames=4, val_every_s=2.0, banks=1)
    campaign = ROOT / "campaigns" / "smoke.toml"
    path = train_tool_mask(tmp_path, settings, campaign=campaign, log=lambda line: None)
    state = read_plain_torch_file(path, "checkpoint", error=ToolMaskError)
    rows = list(csv.reader(open(tmp_path / "log.csv")))
    assert rows[0][:4] == ["minutes", "frames", "train_loss", "val_loss"] and len(rows) >= 2
    assert state["elapsed_s"] >= 6.0 and state["frames"] == 2 * state["step"]
    longer = ToolTrainSettings(**{**settings.__dict__, "minutes": 0.2})
    with pytest.raises(ToolMaskError, match="was trained with"):
        train_tool_mask(tmp_path, longer, resume=True, campaign=campaign, log=lambda line: None)
    with pytest.raises(ToolMaskError, match="exists: resume it"):
        train_tool_mask(tmp_path, settings, campaign=campaign, log=lambda line: None)
    state2 = read_plain_torch_file(train_tool_mask(tmp_path, settings, resume=True, campaign=campaign,
                                                   log=lambda line: None), "checkpoint", error=ToolMaskError)
    assert state2["step"] >= state["step"] and len(state2["log"]) >= len(state["log"])
    folder = export_tool_mask(path, tmp_path / "model", threshold=0.4, low=0.3, min_px=3, dilate_px=2)
    mask = ToolMask(folder)
    assert (mask.threshold, mask.low, mask.min_px, mask.dilate_px) == (0.4, 0.3, 3, 2)
    assert mask.card["training"]["frames"] == state2["frames"] and mask.card["training"]["curve"]
    for key, value in mask.net.state_dict().items():  # the checkpoint's weights, as tensors only
        assert torch.equal(value, state2["model"][key])


@pytest.mark.parametrize("bad, match", [({"crop": 16}, "crop"), ({"lr": 0}, "lr"), ({"width": 100}, "width"),
                                        ({"frames": True}, "frames")])
def test_training_settings_out_of_range_are_named(bad, match):
    with pytest.raises(ToolMaskError, match=match):
        ToolTrainSettings(**bad)


def _folder(tmp_path, **card):
    net = tool_segmenter(width=4)
    torch.save(net.state_dict(), tmp_path / "weights.pt")
    digest = hashlib.sha256((tmp_path / "weights.pt").read_bytes()).hexdigest()
    model = {"file": "weights.pt", "sha256": digest, "width": 4, "threshold": 0.5, "low": 0.3, "min_px": 2, "dilate_px": 1,
             **card}
    lines = "\n".join(f"{k} = {v!r}".replace("'", '"') for k, v in model.items())
    (tmp_path / "card.toml").write_text(f"[model]\n{lines}\n")
    return tmp_path


def test_a_tool_mask_folder_is_read_and_its_detections_stay_in_the_field(tmp_path):
    """A folder of a card and weights loads; its detections are bool, of the image's shape, inside
    the field, at any image size (resampled to the segmenter's side and back)."""
    mask = ToolMask(_folder(tmp_path, threshold=0.01, low=0.01, min_px=0))
    for shape in ((300, 520), (100, 100)):
        field = np.zeros(shape, bool)
        field[10:-10, 20:-20] = True
        image = np.random.default_rng(0).random(shape)
        p = mask.probabilities(image, field)
        assert p.shape == shape and p.dtype == np.float32 and float(p[~field].max()) == 0
        hit = mask.detect(image, field)
        assert hit.shape == shape and hit.dtype == bool and not (hit & ~field).any()
    with pytest.raises(ToolMaskError, match="NaN"):
        mask.detect(np.full((64, 64), np.nan), np.ones((64, 64), bool))
    with pytest.raises(ToolMaskError, match="bool field"):
        mask.detect(np.zeros((64, 64)), np.ones((64, 32), bool))


@pytest.mark.parametrize("change, match", [
    ({"sha256": "0" * 64}, "sha256 does not match"), ({"width": 8}, "do not fit a width-8"),
    ({"threshold": 1.5}, "low <= threshold < 1"), ({"low": 0.6}, "low <= threshold"), ({"file": "other.pt"}, "not found"), ({"width": "4"}, "model.width")])
def test_a_broken_tool_mask_folder_is_named(tmp_path, change, match):
    with pytest.raises(ToolMaskError, match=match):
        ToolMask(_folder(tmp_path, **change))


def test_a_tool_mask_folder_without_a_card_or_with_a_corrupt_one_is_named(tmp_path):
    with pytest.raises(ToolMaskError, match="no card.toml"):
        ToolMask(tmp_path)
    (tmp_path / "card.toml").write_text("[model\n")
    with pytest.raises(ToolMaskError, match="not valid TOML"):
        ToolMask(tmp_path)


def test_confident_pieces_keep_whole_pieces_with_a_confident_core():
    """Hysteresis: a piece over ``low`` is kept whole where it holds ``min_px`` px at the threshold,
    dropped whole where it holds fewer; 8-connected (a diagonal step joins)."""
    from learn.tool_mask import confident_pieces

    p = np.zeros((20, 20))
    p[2, 2:12] = 0.6  # a wire's rim ...
    p[2, 5:8] = 0.95  # ... with a 3 px confident core
    p[10, 2:12] = 0.6  # a weak streak, no core
    p[15, 3] = p[16, 4] = p[17, 5] = 0.95  # a diagonal confident piece of 3 px
    hit = confident_pieces(p, 0.9, 0.5, 3)
    assert hit[2, 2:12].all() and not hit[10].any() and hit[15, 3] and hit[17, 5]
    assert hit.sum() == 13
    assert not confident_pieces(p, 0.9, 0.5, 4)[2].any()
