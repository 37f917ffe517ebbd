"""learn.online.prepare_like_registration of a torch batch equals its NumPy preparation of each
pair (raw_intensity=False, tone=False): the steps of sim/prepare.py, written once for both.

Tolerance: targets (in [0, 1]) and currents (here in [0, 3]) within 1e-4 absolute (measured:
~3e-7 and ~7e-7). A NumPy pair's crop is resampled with F.interpolate in float32;
a batch gathers with F.interpolate's own float32 source indices and weights, so the
two differ by float32 rounding of the interpolation sums only, and the resampled field is the
same (the percentiles and means are over the same pixels). The resample itself is tested in
tests/sim/test_prepare.py.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from learn.online import OnlinePairsError, prepare_like_registration
from sim.physics.chain import apply_chain, field_masks
from sim.randomize import DomainRandomization, draw_tensors, image_rng

TOL = 1e-4


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _check(display, field, current, log_display, bone_dark, mask_current, dtype):
    target, cur = prepare_like_registration(
        torch.from_numpy(np.asarray(display, np.float64)).to(dtype), torch.from_numpy(field),
        torch.from_numpy(current).to(dtype), log_display=torch.from_numpy(log_display),
        bone_dark=torch.from_numpy(bone_dark), mask_current=mask_current)
    assert target.dtype == torch.float32 and cur.dtype == torch.float32
    worst = 0.0
    for i in range(len(display)):
        rt, rc = prepare_like_registration(display[i], field[i], current[i], log_display=bool(log_display[i]),
                                           bone_dark=bool(bone_dark[i]), mask_current=mask_current)
        worst = max(worst, float(np.abs(target[i].numpy() - rt).max()), float(np.abs(cur[i].numpy() - rc).max()))
    assert worst <= TOL, f"{dtype}, mask_current={mask_current}: {worst:.3g} apart"


@pytest.mark.parametrize("size", [(64, 64), (48, 80)], ids=["64x64", "48x80"])
def test_a_batch_equals_each_pair_on_random_pairs(size):
    h, w = size
    n = 56
    dr = DomainRandomization()
    draws = [dr.draw(9, i) for i in range(n)]
    field = field_masks(draw_tensors(draws), h, w).numpy()
    keep = field.reshape(n, -1).any(1)
    field = field[keep]
    n = len(field)
    assert n >= 50 and not field.reshape(n, -1).all(1).all()  # cropped pairs and whole ones
    rng = np.random.default_rng(1)
    bits = rng.choice([8, 12, 16], n)
    display = np.stack([rng.integers(0, 2 ** b, (h, w)) for b in bits]).astype(np.uint16)
    current = rng.random((n, h, w)) * 3.0
    log_display, bone_dark = rng.random(n) < 0.5, rng.random(n) < 0.5
    for dtype in (torch.float64, torch.float32):
        for mask_current in (True, False):
            _check(display, field, current, log_display, bone_dark, mask_current, dtype)


def test_a_batch_equals_each_pair_after_the_imaging_chain():
    """End to end: displays of the batched post-render stages, polarity and log from the draws."""
    h, w, n = 64, 64, 50
    dr = DomainRandomization.from_table({"scatter": ["none", "kernel"]})
    draws = [dr.draw(4, i) for i in range(n)]
    p = draw_tensors(draws, dtype=torch.float64)
    yy, xx = np.mgrid[0:h, 0:w]
    line = np.stack([1.5 * np.exp(-((yy - 20 - i % 9) ** 2 + (xx - 30) ** 2) / 300.0) for i in range(n)])
    raw = torch.from_numpy(1000.0 * np.exp(-line))
    normals = torch.from_numpy(np.stack([image_rng(4, i).standard_normal((h, w)) for i in range(n)]))
    display, field = apply_chain(raw, 1000.0, p, normals)
    bone_dark = (p["polarity"] == 0).numpy()
    _check(display.numpy(), field.numpy(), line, p["log"].numpy(), bone_dark, True, torch.float64)


def test_a_batch_with_bad_inputs_is_refused():
    d, c = torch.zeros(2, 8, 8), torch.zeros(2, 8, 8)
    m = torch.ones(2, 8, 8, dtype=torch.bool)
    kw = dict(log_display=True, bone_dark=False, mask_current=True)
    empty = m.clone()
    empty[1] = False
    with pytest.raises(OnlinePairsError, match=r"pairs \[1\] hold no pixel"):
        prepare_like_registration(d, empty, c, **kw)
    with pytest.raises(OnlinePairsError, match="field must be a bool"):
        prepare_like_registration(d, m.float(), c, **kw)
    with pytest.raises(OnlinePairsError, match="current must have"):
        prepare_like_registration(d, m, c[:, :4], **kw)
    with pytest.raises(OnlinePairsError, match="bone_dark"):
        prepare_like_registration(d, m, c, **{**kw, "bone_dark": torch.zeros(3, dtype=torch.bool)})
    with pytest.raises(OnlinePairsError, match="low < high"):
        prepare_like_registration(d, m, c, low_pct=50.0, high_pct=50.0, **kw)
    for option in ("raw_intensity", "tone"):
        with pytest.raises(OnlinePairsError, match="a batch takes display images"):
            prepare_like_registration(d, m, c, **{**kw, option: True})
    with pytest.raises(OnlinePairsError, match="display must be a real"):
        prepare_like_registration(d[0], m, c, **kw)  # a NumPy-shaped tensor
    with pytest.raises(OnlinePairsError, match="current must be a real"):
        prepare_like_registration(d, m, c.numpy(), **kw)  # a batch and an array mixed


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_a_batch_on_cuda_equals_cpu():
    h, w, n = 48, 80, 64
    field = field_masks(draw_tensors([DomainRandomization().draw(2, i) for i in range(n)]), h, w)
    field = field[field.flatten(1).any(1)]
    rng = np.random.default_rng(5)
    display = torch.from_numpy(rng.integers(0, 4096, (len(field), h, w)).astype(np.float32))
    current = torch.from_numpy(rng.random((len(field), h, w)).astype(np.float32))
    flags = dict(log_display=torch.from_numpy(rng.random(len(field)) < 0.5),
                 bone_dark=torch.from_numpy(rng.random(len(field)) < 0.5), mask_current=True)
    cpu = prepare_like_registration(display, field, current, **flags)
    gpu = prepare_like_registration(display.cuda(), field.cuda(), current.cuda(),
                                    **{k: v.cuda() if isinstance(v, torch.Tensor) else v
                                       for k, v in flags.items()})
    for a, b in zip(cpu, gpu):
        assert b.is_cuda and (a - b.cpu()).abs().max() <= TOL
