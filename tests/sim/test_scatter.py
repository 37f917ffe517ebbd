"""Monte Carlo scatter (sim/physics/scatter.py) against its distributions, conservation, the
deterministic primary, and an independent simple Monte Carlo (tests/sim/slab_mc.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.projection.geometry import CArmGeometry
from sim.physics import PhysicsError
from sim.physics.poly import Detector, Polychromatic
from sim.physics.scatter import MonteCarloScatter, ScatterSettings, block_average
from sim.physics.spectrum import Spectrum, tube_spectrum

XRAYLIB_COMPOUND = {"soft_tissue": "Tissue, Soft (ICRP)", "cortical_bone": "Bone, Cortical (ICRP)"}


def _slab(thickness_mm=200.0, lateral_mm=400.0, z_entry_mm=700.0, voxel_mm=5.0, materials=("water",)):
    n = (int(lateral_mm / voxel_mm), int(lateral_mm / voxel_mm), int(thickness_mm / voxel_mm))
    dens = np.zeros((len(materials),) + n, np.float32)
    dens[0] = 1.0
    aff = np.diag([voxel_mm, voxel_mm, voxel_mm, 1.0])
    aff[:3, 3] = (-lateral_mm / 2 + voxel_mm / 2, -lateral_mm / 2 + voxel_mm / 2, z_entry_mm + voxel_mm / 2)
    return dens, aff


GEOM = CArmGeometry(sdd_mm=1000.0, sod_mm=800.0, height=150, width=150, pixel_spacing_mm=2.0)


@pytest.fixture(scope="module")
def spectrum():
    return tube_spectrum(120.0)


@pytest.fixture(scope="module")
def sampler():
    """A transport over three materials, only to reach its samplers and pdfs."""
    names = ("soft_tissue", "cortical_bone", "titanium")
    dens = np.ones((3, 4, 4, 4), np.float32)
    return MonteCarloScatter(dens, np.eye(4), names, Spectrum.monochromatic(100.0), Detector(),
                             ScatterSettings(photons=1000))


def _reference_cdf(material, kind, energy):
    """CDF in theta from xraylib's own compound / element DCS (not ctxreg's tables)."""
    import xraylib as xr

    theta = np.linspace(2e-3, math.pi, 40001)
    if material == "titanium":
        f = {"compton": xr.DCS_Compt, "rayleigh": xr.DCS_Rayl}[kind]
        dcs = np.array([f(22, energy, t) for t in theta])
    else:
        f = {"compton": xr.DCS_Compt_CP, "rayleigh": xr.DCS_Rayl_CP}[kind]
        dcs = np.array([f(XRAYLIB_COMPOUND[material], energy, t) for t in theta])
    dens = dcs * 2 * math.pi * np.sin(theta)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(theta))])
    return theta, cdf / cdf[-1]


@pytest.mark.parametrize("kind", ["compton", "rayleigh"])
@pytest.mark.parametrize("material,energy", [("soft_tissue", 30.0), ("cortical_bone", 60.0), ("titanium", 90.0)])
def test_scattering_angles_follow_xraylib_cross_sections(sampler, kind, material, energy):
    """Chi-square of 200k angles from the transport's own sampler (tabulated inverse CDF with
    stochastic energy interpolation; 30, 60, 90 keV lie midway between its 2 keV angular nodes,
    the worst case) against xraylib's DCS (KN x S, Thomson x F^2) in 30 bins equiprobable
    under the reference. Fails at p < 1e-3."""
    from scipy.stats import chi2

    n, bins = 200_000, 30
    theta = sampler.sample_angles(kind, material, energy, n, seed=3)
    grid, cdf = _reference_cdf(material, kind, energy)
    edges = np.interp(np.linspace(0, 1, bins + 1), cdf, grid)
    edges[0], edges[-1] = 0.0, math.pi
    observed = np.histogram(theta, bins=edges)[0]
    expected = np.full(bins, n / bins)
    stat = ((observed - expected) ** 2 / expected).sum()
    assert chi2.sf(stat, bins - 1) > 1e-3, f"chi2={stat:.1f} for {bins - 1} dof"


@pytest.mark.parametrize("kind", ["compton", "rayleigh"])
def test_angular_pdf_is_normalised_and_matches_xraylib(sampler, kind):
    """The per-steradian pdf used by forced detection integrates to 1 over the sphere (0.2 %:
    trapezoid on 20001 angles) and equals xraylib's DCS / sigma (1 %: the integrated DCS and
    xraylib's tabulated CS_* differ by up to ~0.5 %)."""
    import xraylib as xr

    th = np.linspace(0, math.pi, 20001)
    pdf = sampler.angular_pdf(kind, "soft_tissue", 61.0, th)
    total = np.trapezoid(pdf * 2 * math.pi * np.sin(th), th)
    assert total == pytest.approx(1.0, abs=2e-3)
    probe = np.array([0.3, 1.0, 2.0, 3.0])
    dcs = {"compton": xr.DCS_Compt_CP, "rayleigh": xr.DCS_Rayl_CP}[kind]
    cs = {"compton": xr.CS_Compt_CP, "rayleigh": xr.CS_Rayl_CP}[kind]("Tissue, Soft (ICRP)", 61.0)
    ref = np.array([dcs("Tissue, Soft (ICRP)", 61.0, t) for t in probe]) / cs
    np.testing.assert_allclose(sampler.angular_pdf(kind, "soft_tissue", 61.0, probe), ref, rtol=1e-2)


def test_energy_is_conserved_and_primary_matches_deterministic(spectrum):
    """Emitted energy = deposited + escaped + truncated (float64 tallies: 1e-9), nothing is
    truncated; the Monte Carlo primary on the detector equals the deterministic polychromatic
    primary of the same slab (path 200 mm / cos of each pixel's ray) within 4 standard errors
    of 8 independent runs, and within 2 %."""
    det = Detector()
    dens, aff = _slab(thickness_mm=100.0)
    mc = MonteCarloScatter(dens, aff, ("water",), spectrum, det, ScatterSettings(photons=100_000, cell_px=15))
    runs = [mc.run(np.eye(4), GEOM, photons_per_pixel=1.0, seed=s) for s in range(8)]
    for out in runs:
        en = out["energy_keV"]
        assert en["truncated"] == 0.0
        assert en["deposited"] + en["escaped"] == pytest.approx(en["emitted"], rel=1e-9)
        assert en["deposited"] > 0.3 * en["emitted"]
    totals = np.array([r["primary"].mean() for r in runs])
    # deterministic: every pixel's ray crosses 100 mm of water at 1 / cos(angle)
    rows = (np.arange(150) - 74.5) * 2.0
    x, y = np.meshgrid(rows, rows)
    path_cm = 10.0 * np.sqrt(x**2 + y**2 + 1000.0**2) / 1000.0
    model = Polychromatic(spectrum, det, ("water",))
    expected = model.expected(path_cm[None, None], mas=1.0, sdd_mm=1000.0, pixel_area_mm2=4.0)
    expected = expected.mean() / model.photons_per_pixel(mas=1.0, sdd_mm=1000.0, pixel_area_mm2=4.0).sum()
    sem = totals.std(ddof=1) / math.sqrt(len(totals))
    assert abs(totals.mean() - expected) < 4 * sem + 1e-12
    assert totals.mean() == pytest.approx(expected, rel=0.02)


def test_scatter_of_a_water_slab_matches_an_independent_monte_carlo(spectrum):
    """20 cm water slab, 120 kVp, 30 x 30 cm field at the detector, no grid, 100 mm air gap:
    the scatter signal on the central 6 x 6 cm and on the whole detector agrees with the simple
    analog NumPy Monte Carlo of tests/sim/slab_mc.py within 10 % (the issue's bound; measured
    agreement is ~1 %, the reference's standard error ~3 % centrally). The SPR at the centre is
    also checked to lie in 1.5-5, the range reported for such slabs."""
    from tests.sim.slab_mc import run_slab

    det = Detector()
    ref = run_slab(thickness_mm=200.0, lateral_mm=400.0, z_entry_mm=700.0, sdd_mm=1000.0, detector_mm=300.0,
                   spectrum=spectrum, detector=det, photons=500_000, seed=1)
    dens, aff = _slab()
    mc = MonteCarloScatter(dens, aff, ("water",), spectrum, det, ScatterSettings(photons=1_000_000, cell_px=15,
                                                                                 voxel_mm=5.0))
    out = mc.run(np.eye(4), GEOM, photons_per_pixel=1.0, seed=2)
    n_px, area = 150 * 150, 4.0
    central = out["scatter"][4:6, 4:6].mean() / area / n_px
    whole = out["scatter"].mean() / area / n_px
    assert central == pytest.approx(ref["central"], rel=0.10)
    assert whole == pytest.approx(ref["whole"], rel=0.10)
    assert abs(whole / ref["whole"] - 1) < 4 * ref["whole_rel_se"] + 0.02
    model = Polychromatic(spectrum, det, ("water",))
    primary = model.expected(np.full((1, 1, 1, 1), 20.0), mas=1.0, sdd_mm=1000.0, pixel_area_mm2=4.0)[0, 0, 0]
    primary /= model.photons_per_pixel(mas=1.0, sdd_mm=1000.0, pixel_area_mm2=4.0).sum()
    spr = out["scatter"][4:6, 4:6].mean() / primary
    assert 1.5 < spr < 5.0


def test_anti_scatter_grid_removes_most_scatter_and_passes_primary(spectrum):
    """A ratio-10 grid passes the primary at its transmission (the primary tally scales by it,
    within the 1e-6 float32 relative error: same seed, same photons) and removes > 70 % of the
    scatter reaching the detector through a 20 cm slab."""
    det = Detector()
    dens, aff = _slab()
    free = MonteCarloScatter(dens, aff, ("water",), spectrum, det, ScatterSettings(photons=200_000, cell_px=15))
    grid = MonteCarloScatter(dens, aff, ("water",), spectrum, det,
                             ScatterSettings(photons=200_000, cell_px=15, grid_ratio=10.0, grid_transmission=0.7))
    a = free.run(np.eye(4), GEOM, photons_per_pixel=1.0, seed=5)
    b = grid.run(np.eye(4), GEOM, photons_per_pixel=1.0, seed=5)
    np.testing.assert_allclose(b["primary"], 0.7 * a["primary"], rtol=1e-5)
    assert b["scatter"].mean() < 0.3 * a["scatter"].mean()


def test_block_average_conserves_mass():
    rng = np.random.default_rng(0)
    d = rng.random((2, 7, 5, 9)).astype(np.float32)
    coarse, f, spacing = block_average(d, (1.0, 1.0, 2.0), 3.0)
    assert tuple(f) == (3, 3, 2) and coarse.shape == (2, 3, 2, 5)
    np.testing.assert_allclose(coarse.sum(axis=(1, 2, 3)) * np.prod(f), d.sum(axis=(1, 2, 3)), rtol=1e-5)
    np.testing.assert_allclose(spacing, (3.0, 3.0, 4.0))


@pytest.mark.parametrize("kwargs,match", [
    (dict(photons=10), "photons"), (dict(voxel_mm=0.0), "voxel_mm"), (dict(grid_ratio=-1.0), "grid_ratio"),
    (dict(grid_transmission=1.5), "grid_transmission"), (dict(cell_px=0), "cell_px"),
    (dict(photons=1.5e6), "photons"),
])
def test_bad_scatter_settings_are_refused(kwargs, match):
    with pytest.raises(PhysicsError, match=match):
        ScatterSettings(**kwargs)


def test_bad_volumes_are_refused(spectrum):
    det = Detector()
    with pytest.raises(PhysicsError, match="densities must be"):
        MonteCarloScatter(np.ones((2, 4, 4, 4)), np.eye(4), ("water",), spectrum, det)
    with pytest.raises(PhysicsError, match="finite"):
        MonteCarloScatter(np.full((1, 4, 4, 4), np.nan), np.eye(4), ("water",), spectrum, det)
    with pytest.raises(PhysicsError, match="empty"):
        MonteCarloScatter(np.zeros((1, 4, 4, 4)), np.eye(4), ("water",), spectrum, det)
    sheared = np.eye(4)
    sheared[0, 2] = 0.5
    with pytest.raises(PhysicsError, match="orthogonal"):
        MonteCarloScatter(np.ones((1, 4, 4, 4)), sheared, ("water",), spectrum, det)


def test_full_physics_images_add_scatter_before_noise():
    """XRayImager at level full on the phantom: the same seed gives identical images, another
    seed other noise and Monte Carlo; without noise raw = primary + scatter; with noise the
    image mean stays primary + scatter (2 %: Poisson means over 4096 pixels) and its variance
    grows by the scatter's photons; scatter lowers the log image's contrast."""
    from sim.projection.geometry import pose_from_params
    from sim.ct.phantom import make_pelvis_phantom
    from sim.physics.imaging import PhysicsSettings, XRayImager

    vol = make_pelvis_phantom(0)
    quiet = XRayImager(vol, PhysicsSettings(level="full", noise=False, scatter_photons=50_000), size=(64, 64))
    pose = pose_from_params(np.zeros(6), quiet.geometry.sod_mm)
    a = quiet.render(pose, seed=1)
    np.testing.assert_allclose(a["raw"], a["primary"] + a["scatter"], rtol=1e-5)
    assert np.array_equal(quiet.render(pose, seed=1)["scatter"], a["scatter"])
    assert not np.array_equal(quiet.render(pose, seed=2)["scatter"], a["scatter"])
    poly = XRayImager(vol, PhysicsSettings(level="poly", noise=False), size=(64, 64)).render(pose)
    np.testing.assert_allclose(poly["primary"], a["primary"], rtol=1e-6)
    assert np.ptp(a["log"]) < np.ptp(poly["log"])
    noisy = XRayImager(vol, PhysicsSettings(level="full", noise=True, blur_mm=0.0, scatter_photons=50_000),
                       size=(64, 64)).render(pose, seed=1)
    assert noisy["raw"].mean() == pytest.approx((a["primary"] + a["scatter"]).mean(), rel=0.02)
    np.testing.assert_array_equal(noisy["scatter"], a["scatter"])


def _turned(deg: float, shift_mm=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A camera frame rotated by ``deg`` about the slab's y axis through z = 750 mm, then shifted."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    m = np.eye(4)
    m[:3, :3] = rot
    pivot = np.array([0.0, 0.0, 750.0])
    m[:3, 3] = pivot - rot @ pivot + np.asarray(shift_mm)
    return m


def test_batched_poses_equal_one_pose_runs(spectrum):
    """run_batch over three poses (several chunks per pose, chunks of different poses sharing
    launches, an anti-scatter grid that reads each lane's own detector frame) gives each pose
    exactly what run() gives it alone: the same random streams, and float64 tallies summed
    in the same order, so equality is exact, not statistical."""
    dens, aff = _slab(thickness_mm=100.0)
    mc = MonteCarloScatter(dens, aff, ("water",), spectrum, Detector(),
                           ScatterSettings(photons=5000, batch=2048, cell_px=15, grid_ratio=6.0))
    cams = np.stack([np.eye(4), _turned(20.0), _turned(-35.0, (30.0, -20.0, 10.0))])
    seeds = [3, 4, 3]
    batched = mc.run_batch(cams, GEOM, photons_per_pixel=2.0, seeds=seeds)
    for cam, seed, out in zip(cams, seeds, batched):
        alone = mc.run(cam, GEOM, photons_per_pixel=2.0, seed=seed)
        for name in ("scatter", "scatter_counts", "primary"):
            np.testing.assert_array_equal(out[name], alone[name])
        assert out["energy_keV"] == alone["energy_keV"]
    # the poses differ, so the check is not vacuous
    assert not np.allclose(batched[0]["scatter"], batched[1]["scatter"])
    assert batched[0]["scatter"].sum() > 0


@pytest.mark.parametrize("cams, seeds, match", [
    (np.eye(4), [0], "B, 4, 4"),
    (np.zeros((0, 4, 4)), [], "B >= 1"),
    (np.stack([np.eye(4)] * 2), [0], "one seed per pose"),
    (np.full((1, 4, 4), np.nan), [0], "finite"),
])
def test_batched_run_rejects_bad_input(spectrum, cams, seeds, match):
    dens, aff = _slab(thickness_mm=50.0, lateral_mm=100.0)
    mc = MonteCarloScatter(dens, aff, ("water",), spectrum, Detector(), ScatterSettings(photons=1000))
    with pytest.raises(PhysicsError, match=match):
        mc.run_batch(cams, GEOM, photons_per_pixel=1.0, seeds=seeds)


def test_automatic_smoothing_follows_the_histories_per_detector_area():
    """``auto_smooth_mm``: 24 mm at the reference density (10^6 histories over 298 x 298 mm, the
    measured least-error sigma), less with more histories or a smaller detector, by the power
    law; an explicit ``smooth_mm`` is used as given; nonsense is refused."""
    from sim.physics.scatter import auto_smooth_mm

    area = 298.0 ** 2
    assert auto_smooth_mm(1_000_000, area) == 24.0
    assert auto_smooth_mm(4_000_000, area) == pytest.approx(24.0 * 4 ** -0.2, abs=0.05)
    assert auto_smooth_mm(4_000_000, 4 * area) == 24.0  # the same histories per area
    assert auto_smooth_mm(250_000, area) > 24.0 > auto_smooth_mm(2_000_000, area)
    g = CArmGeometry(sdd_mm=1000.0, sod_mm=800.0, height=128, width=128, pixel_spacing_mm=298.0 / 128)
    assert ScatterSettings().smoothing_mm(g) == 24.0
    assert ScatterSettings().smoothing_mm(g, photons=4_000_000) == auto_smooth_mm(4_000_000, area)
    assert ScatterSettings(smooth_mm=6.0).smoothing_mm(g) == 6.0
    assert ScatterSettings(smooth_mm=0.0).smoothing_mm(g) == 0.0
    for bad in ((0, area), (1000, 0.0), (1000, float("nan"))):
        with pytest.raises(PhysicsError, match="auto_smooth_mm"):
            auto_smooth_mm(*bad)
    with pytest.raises(PhysicsError, match="smooth_mm"):
        ScatterSettings(smooth_mm=-1.0)


def test_automatic_smoothing_brings_an_estimate_closer_to_the_expected_scatter():
    """The pelvis phantom at 64 x 64 px, AP: an estimate of 40,000 histories smoothed by the
    automatic sigma is closer to the mean of 8 independent runs of 80,000 histories (unsmoothed,
    its own noise subtracted) than the same estimate at the former 6 mm, by more than 1.3x
    (measured 1.6-1.8x over three seeds: 15-22 % -> 9-12 %; unsmoothed it would be 1x; the study's
    frames at 10^6 histories: 11.6 % -> 4.4 %, benchmarks/scatter_denoise.py), and its error is
    under 15 % of the mean scatter."""
    from sim.projection.geometry import extrinsic_lps_to_camera, pose_from_params
    from sim.ct.phantom import make_pelvis_phantom
    from sim.physics.imaging import PhysicsSettings, XRayImager
    from sim.physics.scatter import upsample_cells

    im = XRayImager(make_pelvis_phantom(0), PhysicsSettings(level="full", noise=False, scatter_photons=40_000),
                    size=(64, 64))
    g, mc = im.geometry, im.scatter
    pose = pose_from_params(np.zeros(6), g.sod_mm)
    cam = np.linalg.inv(extrinsic_lps_to_camera(pose[None], im.renderer.center_lps))
    ppp = float(im.model.photons_per_pixel(**im.exposure).sum())
    cp = mc.settings.cell_px
    runs = np.stack([upsample_cells(r["scatter"], g.height, g.width, cp, 0.0) for r in
                     mc.run_batch(np.repeat(cam, 8, 0), g, photons_per_pixel=ppp, seeds=range(100, 108),
                                  photons=80_000)])
    ref, var_ref = runs.mean(0), runs.var(0, ddof=1).mean() / len(runs)
    x = mc.run_batch(cam, g, photons_per_pixel=ppp, seeds=[7])[0]["scatter"]

    def error(sigma_mm):
        xs = upsample_cells(x, g.height, g.width, cp, sigma_mm / (g.pixel_spacing_mm * cp))
        return math.sqrt(max(np.mean((xs - ref) ** 2) - var_ref, 0.0)) / ref.mean()

    auto = mc.settings.smoothing_mm(g)
    assert auto > 24.0  # fewer histories than the reference density: more smoothing
    assert error(auto) * 1.3 < error(6.0)
    assert error(auto) < 0.15
