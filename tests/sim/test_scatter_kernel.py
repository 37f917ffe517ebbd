"""Scatter-kernel model (sim/physics/scatter_kernel.py) against the Monte Carlo it replaces, its
convolution against closed forms, its record, and its refusals.

The Monte Carlo cases (marked slow) use the built-in phantom at 6 mm, 32 x 32 images (9.3 mm
pixels at the detector), cells of 4 pixels, a 12 mm transport grid and 10^5 histories per
image: about 10 s for the module's fixture on 2 cores."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.special import ndtr

from sim.projection.geometry import CArmGeometry, pose_from_params
from sim.physics import PhysicsError
from sim.physics.scatter_kernel import (ScatterKernelModel, cell_means, fit_maps, interpolate_kvp, monte_carlo_maps,
                                        physics_record)

PHOTONS = 100_000
#: Bounds of test_model_matches_monte_carlo_on_held_out_poses (its docstring gives the reasoning).
SPR_TOL, L2_TOL, SPR_NOISE_MAX = 0.15, 0.20, 0.08
CELL = 4
SIZE = (32, 32)


def _poses(seed: int, n: int, sod_mm: float) -> np.ndarray:
    lim = np.array([40.0, 20.0, 20.0, 30.0, 30.0, 30.0])
    return pose_from_params(np.random.default_rng(seed).uniform(-lim, lim, (n, 6)), sod_mm)


@pytest.fixture(scope="module")
def phantom():
    from sim.ct.phantom import make_pelvis_phantom

    return make_pelvis_phantom(0, spacing_mm=6.0)


def _imager(vol, **physics):
    from sim.physics.imaging import PhysicsSettings, XRayImager

    return XRayImager(vol, PhysicsSettings(level="poly", noise=False, scatter_voxel_mm=12.0, **physics), size=SIZE)


@pytest.fixture(scope="module")
def case(phantom):
    """A model fitted on 8 poses at 120 kVp without a grid; 4 held-out poses with two Monte
    Carlo seeds each (the reference is their mean)."""
    im = _imager(phantom)
    sod = im.geometry.sod_mm
    train = monte_carlo_maps(im, _poses(1, 8, sod), cell_px=CELL, photons=PHOTONS, seeds=range(100, 108))
    test_poses = _poses(2, 4, sod)
    a = monte_carlo_maps(im, test_poses, cell_px=CELL, photons=PHOTONS, seeds=range(200, 204), mc=train["mc"])
    b = monte_carlo_maps(im, test_poses, cell_px=CELL, photons=PHOTONS, seeds=range(300, 304), mc=train["mc"])
    model = fit_maps(train["log"], train["cells"], im.geometry, cell_px=CELL, gap_mm=train["gap_mm"],
                     signal_per_photon=train["signal_per_photon"], settings=physics_record(im.physics))
    return dict(imager=im, train=train, a=a, b=b, model=model, test_poses=test_poses)


def _spr_field(scatter, primary):
    return scatter.reshape(len(scatter), -1).sum(1) / primary.reshape(len(primary), -1).sum(1)


@pytest.mark.slow
def test_model_matches_monte_carlo_on_held_out_poses(case):
    """On 4 held-out poses the model's scatter-to-primary ratio (sum S / sum P over the
    detector) is within SPR_TOL = 15 % of the Monte Carlo reference (the mean of two seeds) at
    every pose, and its image within L2_TOL = 0.20 (relative L2) at every pose.

    Reasoning: the Monte Carlo's own noise is measured from its two seeds (asserted < 8 % in
    SPR so that the bound means something; measured 2-4 %, so the reference is good to ~2 %;
    seed-to-seed L2 0.14-0.17, so one run is ~0.11 from the truth and the reference ~0.08).
    Measured: SPR within 1.6-9.2 % (the 9 % pose lies 15 mm farther from the detector than any
    fitting pose), L2 0.10-0.16. The bounds leave room for other platforms' random streams,
    and still fail a model without the air-gap dependence (SPR 19.5 %, L2 0.23 at that pose).
    On the pelvis at 64 x 64 with 2 x 10^5 histories the held-out errors are ~3 % SPR
    (docs/physics.md); this case is coarser (9 mm pixels, 12 mm transport voxels, 8 poses)."""
    a, b, model = case["a"], case["b"], case["model"]
    g = case["imager"].geometry
    ref = 0.5 * (a["image"] + b["image"])
    pred = model.predict(a["log"], g, flat_signal=a["flat"], gap_mm=a["gap_mm"])
    spr_ref = _spr_field(ref, a["primary"])
    noise = np.abs(_spr_field(a["image"], a["primary"]) / _spr_field(b["image"], a["primary"]) - 1)
    assert noise.max() < SPR_NOISE_MAX, f"MC seed-to-seed SPR differences {noise}"
    err = np.abs(_spr_field(pred, a["primary"]) / spr_ref - 1)
    assert err.max() < SPR_TOL, f"SPR errors {err} (MC seed-to-seed {noise})"
    l2 = np.linalg.norm((pred - ref).reshape(4, -1), axis=1) / np.linalg.norm(ref.reshape(4, -1), axis=1)
    assert l2.max() < L2_TOL, f"relative L2 {l2}"
    # the fit itself: relative RMS of the cell residuals of the fitting poses, MC noise included
    assert model.fit_rms < 0.3


def test_scatter_is_zero_without_object_and_never_negative():
    model = ScatterKernelModel((2.0, 5.0), (0.3, 0.8), (10.0, 30.0), (60.0, 150.0), (0.5, 0.5))
    g = CArmGeometry(sdd_mm=1000.0, sod_mm=700.0, height=32, width=32, pixel_spacing_mm=9.0)
    assert np.array_equal(model.predict(np.zeros(SIZE), g), np.zeros(SIZE))
    rng = np.random.default_rng(0)
    logs = rng.uniform(0, 12, (3,) + SIZE)
    logs[0, :16] = 0.0  # half of the detector in air
    s = model.predict(logs, g, flat_signal=5.0)
    assert s.shape == logs.shape and s.min() >= 0 and s.max() > 0
    # negative log values (brighter than the flat field) count as no object
    assert np.array_equal(model.predict(-np.ones(SIZE), g), np.zeros(SIZE))


def _one_node(a=0.3, s1=10.0, s2=30.0, f=0.4):
    return ScatterKernelModel((2.0,), (a,), (s1,), (s2,), (f,))


def _mass(n_lo: int, n_hi: int, sp: float, sigma: float) -> float:
    """Mass of a unit 1-D Gaussian centred on a pixel with n_lo pixels before and n_hi after it."""
    return ndtr((n_hi + 0.5) * sp / sigma) - ndtr(-(n_lo + 0.5) * sp / sigma)


@pytest.mark.parametrize("row,col", [(50, 60), (0, 0), (100, 5)])
def test_one_pixel_spreads_its_scatter_as_the_kernel(row, col):
    """One source pixel at tau = 2: the detector receives a g(tau) (exp(-2) * 2 * a) times the
    kernel's mass on the detector, from the closed form of the pixel-integrated Gaussians
    (1e-5, the float32 FFTs: a circular convolution without the zero padding would fold the
    part beyond the edges back in and fail at the corner), and the kernel is symmetric about
    the source."""
    g = CArmGeometry(sdd_mm=1000.0, sod_mm=700.0, height=101, width=121, pixel_spacing_mm=2.0)
    m = _one_node()
    tau = np.zeros((101, 121))
    tau[row, col] = 2.0
    s = m.predict(tau, g, flat_signal=3.0)
    mass = sum(share * _mass(row, 100 - row, 2.0, sig) * _mass(col, 120 - col, 2.0, sig)
               for share, sig in ((0.6, 10.0), (0.4, 30.0)))
    assert s.sum() == pytest.approx(3.0 * 0.3 * 2.0 * math.exp(-2.0) * mass, rel=1e-5)
    if (row, col) == (50, 60):
        assert s[50, 65] == pytest.approx(s[55, 60], rel=1e-5)
        assert s[50, 55] == pytest.approx(s[50, 65], rel=1e-5)
        assert s[50, 60] > s[50, 61] > s[50, 70] > 0
        assert mass > 0.99
    else:
        assert mass < 0.5  # most of the kernel falls beyond the edges: a wrapped convolution would keep it


@pytest.mark.slow
def test_scatter_scales_linearly_with_exposure(phantom, case):
    """The Monte Carlo scatter and the flat field both scale with mAs (the photons per history
    do), so the Monte Carlo's scatter / flat does not change (same seed: equal within float32
    rounding, 1e-5), and the model, given the flat of each exposure, scales by the same 2.5."""
    im1 = _imager(phantom, mas=1.0)
    im2 = _imager(phantom, mas=2.5)
    pose = case["test_poses"][:1]
    mc = case["train"]["mc"]  # the same CT, spectrum and detector: only the exposure differs
    m1 = monte_carlo_maps(im1, pose, cell_px=CELL, photons=PHOTONS, seeds=[5], mc=mc)
    m2 = monte_carlo_maps(im2, pose, cell_px=CELL, photons=PHOTONS, seeds=[5], mc=mc)
    assert m2["flat"] == pytest.approx(2.5 * m1["flat"], rel=1e-12)
    np.testing.assert_allclose(m2["cells"], m1["cells"], rtol=1e-5)
    np.testing.assert_allclose(m2["log"], m1["log"], rtol=1e-9)
    model, g = case["model"], im1.geometry
    np.testing.assert_allclose(model.predict(m2["log"], g, flat_signal=m2["flat"], gap_mm=m2["gap_mm"]),
                               2.5 * model.predict(m1["log"], g, flat_signal=m1["flat"], gap_mm=m1["gap_mm"]),
                               rtol=1e-5)


@pytest.mark.slow
def test_grid_model_removes_scatter_as_the_monte_carlo_grid_does(phantom, case):
    """A ratio-10 grid: a model fitted with it (same poses) predicts on the held-out poses a
    scatter (relative to the flat with the grid) whose ratio to the no-grid model's equals the
    Monte Carlo's ratio within 15 %, and the grid removes most of it (ratio < 0.4; the slab
    test of test_scatter.py measures > 70 % removed)."""
    im = _imager(phantom, grid_ratio=10.0)
    train = monte_carlo_maps(im, _poses(1, 8, im.geometry.sod_mm), cell_px=CELL, photons=PHOTONS,
                             seeds=range(100, 108))
    test = monte_carlo_maps(im, case["test_poses"], cell_px=CELL, photons=PHOTONS, seeds=range(200, 204),
                            mc=train["mc"])
    grid_model = fit_maps(train["log"], train["cells"], im.geometry, cell_px=CELL, gap_mm=train["gap_mm"],
                          settings=physics_record(im.physics))
    free = case["a"]
    mc_ratio = (test["image"].sum() / test["flat"]) / (free["image"].sum() / free["flat"])
    model_ratio = (grid_model.predict(test["log"], im.geometry, gap_mm=test["gap_mm"]).sum()
                   / case["model"].predict(free["log"], im.geometry, gap_mm=free["gap_mm"]).sum())
    assert mc_ratio < 0.4
    assert model_ratio == pytest.approx(mc_ratio, rel=0.15)


@pytest.mark.slow
def test_fitted_parameters_round_trip_through_json(case):
    model, g, a = case["model"], case["imager"].geometry, case["a"]
    assert model.gap_ref_mm > 0 and model.settings_dict["kvp"] == 120.0
    back = ScatterKernelModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert back == model
    assert back.settings_dict["filters"] == (("Al", 2.5),)
    np.testing.assert_array_equal(back.predict(a["log"], g, gap_mm=a["gap_mm"]),
                                  model.predict(a["log"], g, gap_mm=a["gap_mm"]))


def test_air_gap_scales_the_kernel_widths():
    """A model with gap exponent 1 at 300 mm predicts at 450 mm what the same model with 1.5x
    wider kernels and no gap dependence predicts (float32 FFTs: 1e-5); the record keeps it."""
    kw = dict(tau_nodes=(2.0, 5.0), amplitude=(0.3, 0.8), broad_fraction=(0.3, 0.6), aspect=2.0)
    with_gap = ScatterKernelModel(sigma1_mm=(10.0, 20.0), sigma2_mm=(60.0, 90.0), gap_ref_mm=300.0, gap_exponent=1.0,
                                  **kw)
    wider = ScatterKernelModel(sigma1_mm=(15.0, 30.0), sigma2_mm=(90.0, 135.0), **kw)
    g = CArmGeometry(sdd_mm=1000.0, sod_mm=700.0, height=40, width=40, pixel_spacing_mm=5.0)
    logs = np.random.default_rng(1).uniform(0, 8, (2, 40, 40))
    np.testing.assert_allclose(with_gap.predict(logs, g, gap_mm=450.0), wider.predict(logs, g), rtol=1e-5)
    np.testing.assert_array_equal(with_gap.predict(logs, g), with_gap.predict(logs, g, gap_mm=[300.0, 300.2]))
    assert not np.allclose(with_gap.predict(logs, g, gap_mm=[300.0, 450.0])[1], with_gap.predict(logs[1], g))
    assert ScatterKernelModel.from_dict(json.loads(json.dumps(with_gap.to_dict()))) == with_gap


def test_kvp_interpolation_hits_the_fitted_models_and_lies_between():
    lo = ScatterKernelModel((1.0, 3.0), (0.2, 0.4), (10.0, 20.0), (50.0, 80.0), (0.2, 0.6), 30.0, {"kvp": 80.0})
    hi = ScatterKernelModel((1.0, 3.0), (0.8, 0.1), (20.0, 20.0), (50.0, 160.0), (0.4, 0.6), 50.0, {"kvp": 120.0})
    assert interpolate_kvp([hi, lo], 80.0).amplitude == pytest.approx(lo.amplitude)
    assert interpolate_kvp([hi, lo], 120.0).sigma2_mm == pytest.approx(hi.sigma2_mm)
    mid = interpolate_kvp([lo, hi], 100.0)
    assert mid.amplitude == pytest.approx((0.4, 0.2))  # geometric means
    assert mid.broad_fraction == pytest.approx((0.3, 0.6))
    assert mid.signal_per_photon == pytest.approx(40.0)
    assert mid.settings_dict["kvp"] == 100.0


def test_cell_means_average_partial_cells():
    img = np.arange(5 * 7, dtype=float).reshape(1, 5, 7)
    c = cell_means(img, 4)
    assert c.shape == (1, 2, 2)
    assert c[0, 0, 0] == pytest.approx(img[0, :4, :4].mean())
    assert c[0, 1, 1] == pytest.approx(img[0, 4:, 4:].mean())


GEOM = CArmGeometry(sdd_mm=1000.0, sod_mm=700.0, height=8, width=8, pixel_spacing_mm=2.0)


def _gap_model():
    return ScatterKernelModel((2.0,), (0.3,), (10.0,), (30.0,), (0.4,), gap_ref_mm=300.0, gap_exponent=1.0)


@pytest.mark.parametrize("call,match", [
    (lambda m: m.predict(np.zeros((8, 9)), GEOM), "log_primary must be"),
    (lambda m: m.predict(np.full((8, 8), np.nan), GEOM), "finite"),
    (lambda m: m.predict(np.zeros((8, 8)), GEOM, flat_signal=0.0), "flat_signal"),
    (lambda m: m.predict(np.zeros((8, 8)), "cios"), "CArmGeometry"),
    (lambda m: _gap_model().predict(np.zeros((2, 8, 8)), GEOM, gap_mm=[300.0]), "gap_mm"),
    (lambda m: _gap_model().predict(np.zeros((8, 8)), GEOM, gap_mm=-5.0), "gap_mm"),
    (lambda m: fit_maps(np.zeros((1, 8, 8)), np.ones((1, 2, 2)), GEOM, cell_px=4, gap_mm=[0.0]), "gap_mm"),
    (lambda m: fit_maps(np.zeros((2, 8, 8)), np.ones((2, 3, 3)), GEOM, cell_px=4), "scatter_cells must be"),
    (lambda m: fit_maps(np.zeros((1, 8, 8)), np.zeros((1, 2, 2)), GEOM, cell_px=4), "needs some scatter"),
    (lambda m: fit_maps(np.zeros((1, 8, 8)), np.ones((1, 2, 2)), GEOM, cell_px=0), "cell_px"),
    (lambda m: interpolate_kvp([m], 100.0), "two or more"),
    (lambda m: interpolate_kvp([m, m], 100.0), "kvp"),
])
def test_bad_inputs_are_refused(call, match):
    with pytest.raises(PhysicsError, match=match):
        call(_one_node())


@pytest.mark.parametrize("change,match", [
    (dict(tau_nodes=[3.0, 1.0]), "increasing"),
    (dict(amplitude=[0.1]), "one per thickness node"),
    (dict(sigma1_mm=[-1.0, 2.0]), "sigma1_mm"),
    (dict(sigma2_mm=[1.5, 1.5]), "sigma2_mm must be >= sigma1_mm"),
    (dict(broad_fraction=[0.5, 1.5]), "broad_fraction"),
    (dict(signal_per_photon=0.0), "signal_per_photon"),
    (dict(settings={"kv": 120}), "unknown key 'kv'"),
    (dict(format=2), "format"),
    (dict(extra=1), "unknown key 'extra'"),
    (dict(aspect=0.0), "aspect"),
    (dict(gap_ref_mm=-1.0), "gap_ref_mm"),
])
def test_bad_records_are_refused(change, match):
    good = ScatterKernelModel((1.0, 3.0), (0.2, 0.4), (2.0, 2.0), (5.0, 8.0), (0.2, 0.6), settings={"kvp": 80.0})
    d = {**good.to_dict(), **change}
    assert ScatterKernelModel.from_dict(good.to_dict()) == good
    with pytest.raises(PhysicsError, match=match):
        ScatterKernelModel.from_dict(d)
    with pytest.raises(PhysicsError, match="missing key 'amplitude'"):
        ScatterKernelModel.from_dict({k: v for k, v in good.to_dict().items() if k != "amplitude"})


# -- the table of models over kV and grid ratio -------------------------------------------------------


def _table_models():
    """Synthetic models at 60 / 120 kV, without a grid and with ratios 6 and 16."""
    out = []
    for kvp in (60.0, 120.0):
        for ratio, amp in ((0.0, 0.4), (6.0, 0.1), (16.0, 0.05)):
            a = amp * (1.0 + kvp / 120.0)
            out.append(ScatterKernelModel((1.0, 3.0), (a, 2 * a), (10.0 + ratio, 20.0), (40.0, 80.0), (0.3, 0.5),
                                          settings={"kvp": kvp, "grid_ratio": ratio}, gap_ref_mm=300.0,
                                          gap_exponent=1.0, aspect=1.0 + ratio / 4))
    return out


def test_table_interpolates_kvp_and_grid_ratio_and_round_trips(tmp_path):
    from sim.physics.scatter_kernel import ScatterKernelTable

    models = _table_models()
    table = ScatterKernelTable(tuple(models), "synthetic")
    assert table.kvps == (60.0, 120.0) and table.grid_ratios == (0.0, 6.0, 16.0)
    for m in models:  # the fitted points are the fitted models
        s = m.settings_dict
        got = table.model_for(s["kvp"], s["grid_ratio"])
        assert got.amplitude == pytest.approx(m.amplitude) and got.aspect == pytest.approx(m.aspect)
    mid = table.model_for(90.0, 0.0)  # halfway in kV: the geometric mean of the amplitudes
    assert mid.amplitude[0] == pytest.approx(math.sqrt(models[0].amplitude[0] * models[3].amplitude[0]))
    r11 = table.model_for(60.0, 11.0)  # halfway between the grids, not towards "no grid"
    assert models[2].amplitude[0] < r11.amplitude[0] < models[1].amplitude[0]
    assert r11.settings_dict == {**models[0].settings_dict, "kvp": 60.0, "grid_ratio": 11.0}
    d = table.drawn(60.0, 0.0, 2.0, 0.5)
    assert d.amplitude == pytest.approx(tuple(2 * a for a in models[0].amplitude))
    assert d.sigma1_mm == pytest.approx((5.0, 10.0)) and d.sigma2_mm == pytest.approx((20.0, 40.0))
    path = tmp_path / "t.json"
    table.save(path)
    assert ScatterKernelTable.load(path) == table


def test_table_refuses_bad_tables_and_files(tmp_path):
    from sim.physics.scatter_kernel import ScatterKernelTable

    models = _table_models()
    with pytest.raises(PhysicsError, match="grid_ratio 0"):
        ScatterKernelTable(tuple(m for m in models if m.settings_dict["grid_ratio"] > 0))
    with pytest.raises(PhysicsError, match="same two or more"):
        ScatterKernelTable(tuple(models[:-1]))
    with pytest.raises(PhysicsError, match="kvp and grid_ratio"):
        ScatterKernelTable((_one_node(), _one_node()))
    table = ScatterKernelTable(tuple(models))
    with pytest.raises(PhysicsError, match="kvp must be"):
        table.model_for(float("nan"), 0.0)
    with pytest.raises(PhysicsError, match="amplitude_factor"):
        table.drawn(80.0, 0.0, 0.0, 1.0)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(PhysicsError, match="not valid JSON"):
        ScatterKernelTable.load(tmp_path / "bad.json")
    with pytest.raises(PhysicsError, match="cannot be read"):
        ScatterKernelTable.load(tmp_path / "missing.json")
    (tmp_path / "keys.json").write_text(json.dumps({"format": 1, "models": []}))
    with pytest.raises(PhysicsError, match="keys format, subject, models"):
        ScatterKernelTable.load(tmp_path / "keys.json")


def test_default_table_covers_the_randomized_tube_and_grid():
    """The committed table spans the declared kV and grid-ratio ranges of sim.randomize."""
    from sim.physics.scatter_kernel import default_table
    from sim.randomize import DomainRandomization

    table = default_table()
    r = DomainRandomization.from_table(None).by_name
    assert table.kvps[0] <= r["kvp"].low and table.kvps[-1] >= r["kvp"].high
    grids = [x for x in table.grid_ratios if x > 0]
    assert 0.0 in table.grid_ratios and grids[0] <= r["grid_ratio"].low and grids[-1] >= r["grid_ratio"].high
