"""Polychromatic physics against truth: Beer-Lambert with xraylib, beam hardening against an
independent integration over spekpy's unbinned spectrum, binning, materials, detector, noise."""

from __future__ import annotations

import numpy as np
import pytest
import xraylib as xr

from sim.physics.materials import TISSUE_DECOMPOSITION, MaterialError, mass_attenuation, mu_linear
from sim.physics import PhysicsError
from sim.physics.poly import Detector, Polychromatic, compton_mean_energy_fraction
from sim.physics.filters import parse_filters
from sim.physics.spectrum import Spectrum, fine_spectrum, tube_spectrum
from tests.sim.test_render import box_chords, rays_lps

EXPOSURE = dict(mas=1.0, sdd_mm=1020.0, pixel_area_mm2=0.194**2)


@pytest.fixture(scope="module")
def spectrum():
    return tube_spectrum(120.0, filters=(("Al", 2.5),))


def test_monochromatic_signal_is_beer_lambert_with_xraylib_on_a_box():
    """A soft-tissue box in air, rendered as density line integrals: at 60 keV the signal ratio
    equals exp(-mu chord) with mu from xraylib called here, within 0.5 % (the chord of the
    voxelised box is exact for rays through faces away from edges; air adds < 0.01 %)."""
    from sim.projection.geometry import pose_from_params
    from sim.projection.drr import DRRRenderer, RenderSettings
    from sim.ct.volume import CTVolume

    hu = np.full((40, 30, 24), -1000.0, np.float32)
    hu[8:32, 6:24, 5:19] = 40.0  # exactly the soft-tissue anchor: fraction 1 of soft tissue
    spacing = np.array([4.0, 4.0, 4.0])
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = -spacing * (np.array(hu.shape) - 1) / 2
    vol = CTVolume(hu, affine, source="box")
    lo = vol.voxel_to_lps(np.array([[8, 6, 5]]) - 0.5)[0]
    hi = vol.voxel_to_lps(np.array([[32, 24, 19]]) - 0.5)[0]
    r = DRRRenderer(vol, RenderSettings(size=(24, 24), quantity="density"), center_lps=[0, 0, 0],
                    materials=TISSUE_DECOMPOSITION)
    params = np.array([20.0, 10.0, -5.0, 5.0, -3.0, 0.0])
    L = r.render_params(params)  # (1, 7, 24, 24) g/cm^2
    poly = Polychromatic(Spectrum.monochromatic(60.0), Detector(mode="counting"), TISSUE_DECOMPOSITION.names)
    ratio = poly.expected(L, **EXPOSURE)[0] / poly.flat_field(**EXPOSURE)
    origin, d = rays_lps(r, pose_from_params(params, r.geometry.sod_mm))
    chord = box_chords(origin, d, lo, hi)
    rho = TISSUE_DECOMPOSITION.density(np.array(40.0))
    mu_per_mm = xr.CS_Total_CP("Tissue, Soft (ICRP)", 60.0) * rho / 10.0
    inside = chord > 20.0
    assert inside.sum() > 50
    np.testing.assert_allclose(ratio[inside], np.exp(-mu_per_mm * chord[inside]), rtol=5e-3)


def test_beam_hardening_of_a_water_wedge_matches_an_independent_integration(spectrum):
    """mu_eff(t) = -ln(I/I0)/t falls with the thickness t of water (beam hardening) and equals
    a fine-grid integration over spekpy's unbinned spectrum (0.25 keV, xraylib mu per energy)
    within 1 % (the 30-bin approximation; measured < 0.5 %)."""
    t_mm = np.array([10.0, 50.0, 100.0, 200.0, 300.0])
    L = np.zeros((1, 1, 1, len(t_mm)))
    L[0, 0, 0] = 1.0 * t_mm / 10.0  # water as soft tissue's neighbour: use the "soft_tissue" channel
    det = Detector(mode="counting")
    poly = Polychromatic(spectrum, det, ("soft_tissue",))
    mu_eff = -np.log(poly.expected(L, **EXPOSURE)[0, 0] / poly.flat_field(**EXPOSURE)) / t_mm
    assert np.all(np.diff(mu_eff) < 0)
    k, n = fine_spectrum(120.0, filters=(("Al", 2.5),))
    keep = k >= 10.0
    k, n = k[keep], n[keep]
    mu_k = np.array([xr.CS_Total_CP("Tissue, Soft (ICRP)", float(e)) for e in k]) / 10.0  # 1/mm at 1 g/cm^3
    eta = np.array([1 - np.exp(-xr.CS_Total_CP("CsI", float(e)) * 4.51 * 0.06) for e in k])
    ref = -np.log((n * eta * np.exp(-mu_k[None] * t_mm[:, None])).sum(1) / (n * eta).sum()) / t_mm
    np.testing.assert_allclose(mu_eff, ref, rtol=1e-2)


def test_binning_conserves_the_photons_and_filters_harden():
    k, n = fine_spectrum(100.0, filters=(("Al", 2.5),))
    s = tube_spectrum(100.0, filters=(("Al", 2.5),), bins=20)
    assert s.total_fluence == pytest.approx(n[k >= 10.0].sum(), rel=1e-9)
    assert s.mean_energy_keV == pytest.approx((n * k)[k >= 10.0].sum() / n[k >= 10.0].sum(), rel=1e-9)
    assert np.all((s.energies_keV >= s.edges_keV[:-1]) & (s.energies_keV <= s.edges_keV[1:]))
    hard = tube_spectrum(100.0, filters=(("Al", 2.5), ("Cu", 0.3)), bins=20)
    assert hard.mean_energy_keV > s.mean_energy_keV + 3.0 and hard.total_fluence < s.total_fluence
    sd = s.to_spectral_distribution()
    np.testing.assert_allclose(sd.values * np.diff(s.edges_keV), s.fluence)


def test_materials_come_from_xraylib_and_partition_smoothly():
    assert mass_attenuation("soft_tissue", 60.0) == pytest.approx(xr.CS_Total_CP("Tissue, Soft (ICRP)", 60.0))
    assert mass_attenuation("titanium", [50.0])[0] == pytest.approx(xr.CS_Total(22, 50.0))
    parts = sum(mass_attenuation("cortical_bone", 80.0, k) for k in ("photo", "compton", "rayleigh"))
    assert parts == pytest.approx(mass_attenuation("cortical_bone", 80.0), rel=1e-6)
    assert mu_linear("titanium", 60.0) == pytest.approx(xr.CS_Total(22, 60.0) * xr.ElementDensity(22) / 10)
    hu = np.linspace(-1100, 3500, 46001)
    f = TISSUE_DECOMPOSITION.fractions(hu)
    np.testing.assert_allclose(f.sum(0), 1.0, atol=1e-6)
    assert np.abs(np.diff(f, axis=1)).max() < 1e-3  # no jumps: hats change by < 0.1 % per 0.1 HU
    assert len(TISSUE_DECOMPOSITION.names) == 7 and "titanium" in TISSUE_DECOMPOSITION.names
    with pytest.raises(MaterialError, match="unknown material"):
        mass_attenuation("steel", 60.0)


def test_detector_response():
    e = np.array([30.0, 60.0, 100.0])
    count = Detector(mode="counting").response(e)
    expect = 1 - np.exp(-np.array([xr.CS_Total_CP("CsI", v) for v in e]) * 4.51 * 0.06)
    np.testing.assert_allclose(count, expect)
    integ = Detector().response(e)
    assert np.all(integ <= e * count + 1e-12) and np.all(integ > 0.5 * e * count)
    # free-electron Klein-Nishina mean energy-transfer fraction rises with energy; at 1 MeV the
    # tabulated sigma_tr / sigma is 0.440 (Attix, Introduction to Radiological Physics)
    f = compton_mean_energy_fraction([10.0, 100.0, 1000.0])
    assert np.all(np.diff(f) > 0) and f[-1] == pytest.approx(0.440, abs=0.01)
    with pytest.raises(PhysicsError, match="mode"):
        Detector(mode="film")


def test_quantum_noise_is_seeded_and_poisson(spectrum):
    poly = Polychromatic(spectrum, Detector(mode="counting"), ("soft_tissue",))
    L = np.full((1, 1, 64, 64), 10.0)  # 10 cm of tissue-like material
    exp = dict(mas=0.001, sdd_mm=1020.0, pixel_area_mm2=0.194**2)
    a = poly.noisy(L, np.random.default_rng(3), pixel_spacing_mm=0.194, **exp)
    b = poly.noisy(L, np.random.default_rng(3), pixel_spacing_mm=0.194, **exp)
    np.testing.assert_array_equal(a, b)
    mean = poly.expected(L, **exp)[0, 0, 0]
    # counts of a thinned Poisson process are Poisson: the variance equals the mean; with 4096
    # pixels the sample mean is within 4 standard errors and the variance ratio within 10 %
    assert abs(a.mean() - mean) < 4 * np.sqrt(mean / a.size)
    assert a.var() / mean == pytest.approx(1.0, rel=0.1)


def test_blockwise_expected_signal_equals_the_per_bin_sum(spectrum, monkeypatch):
    """``expected`` (pixel blocks, matrix products) equals the plain sum over energy bins of
    ``expected_counts x response`` to rounding (1e-12 relative), across block boundaries."""
    poly = Polychromatic(spectrum, Detector(), TISSUE_DECOMPOSITION.names)
    L = np.random.default_rng(1).gamma(1.0, 2.0, (2, len(TISSUE_DECOMPOSITION.names), 33, 17))
    monkeypatch.setattr(Polychromatic, "BLOCK_PIXELS", 100)  # 1122 pixels: 12 blocks, the last partial
    reference = np.einsum("behw,e->bhw", poly.expected_counts(L, **EXPOSURE), poly.response)
    np.testing.assert_allclose(poly.expected(L, **EXPOSURE), reference, rtol=1e-12, atol=0)


def test_bad_inputs_are_named():
    with pytest.raises(PhysicsError, match="kvp"):
        tube_spectrum(300.0)
    with pytest.raises(PhysicsError, match="Cu:0.1"):
        parse_filters(["Xx:1"])
    assert parse_filters(["Al:2.5", "Cu:0.1"]) == (("Al", 2.5), ("Cu", 0.1))
    poly = Polychromatic(Spectrum.monochromatic(60.0), Detector(), ("soft_tissue",))
    with pytest.raises(PhysicsError, match=r"\(B, M=1, H, W\)"):
        poly.expected(np.zeros((1, 2, 4, 4)), **EXPOSURE)
    with pytest.raises(PhysicsError, match="finite"):
        poly.expected(np.full((1, 1, 2, 2), np.nan), **EXPOSURE)
    from sim.physics.imaging import PhysicsSettings

    # settings fail when made, before any rendering or spekpy call
    for kwargs, words in ((dict(kvp=300.0), "kvp: must be a number in [20, 150] kV, got 300.0"),
                          (dict(bins=0), "bins: must be an integer in [1, 1000], got 0"),
                          (dict(anode_angle_deg=60.0), "anode_angle_deg: must be a number in [1, 45] deg"),
                          (dict(detector_mode="hybrid"), "detector_mode: must be one of integrating, counting"),
                          (dict(blur_mm=-1.0), "blur_mm: must be a number >= 0 mm"),
                          (dict(detector_mm=0.0), "detector_mm: must be a number > 0 mm"),
                          (dict(level="full", scatter_photons=10), "scatter_photons: must be an integer >= 1000")):
        with pytest.raises(PhysicsError) as info:
            PhysicsSettings(**kwargs)
        assert words in str(info.value), (kwargs, str(info.value))


def test_imager_log_image_tracks_the_line_integral_and_noise_is_reproducible():
    """On the phantom, the noise-free poly log image follows the independently rendered 60 keV
    line-integral DRR (correlation > 0.99, values within 10 %: the 120 kVp beam's effective
    energy is near 60 keV), and noise is reproducible for a seed and differs between seeds."""
    from sim.ct.phantom import make_pelvis_phantom
    from sim.physics.imaging import PhysicsSettings, XRayImager
    from sim.projection.drr import DRRRenderer, RenderSettings

    vol = make_pelvis_phantom(0, spacing_mm=4.0)
    imager = XRayImager(vol, PhysicsSettings(noise=False), size=(32, 32))
    line = DRRRenderer(vol, RenderSettings(size=(32, 32)), center_lps=imager.renderer.center_lps)
    from sim.projection.geometry import pose_from_params

    pose = pose_from_params(np.array([10.0, 5.0, 0.0, 0.0, 0.0, 0.0]), imager.geometry.sod_mm)
    out = imager.render(pose)
    ref = line.render(pose)[0]
    log = out["log"][0]
    assert np.corrcoef(log.ravel(), ref.ravel())[0, 1] > 0.99
    # an effective energy near 60 keV: the poly image is within 10 % of the 60 keV line integral
    # (beam hardening itself is checked on the water wedge above)
    np.testing.assert_allclose(log, ref, rtol=0.1)
    noisy = XRayImager(vol, PhysicsSettings(noise=True, seed=4), size=(32, 32))
    a, b = noisy.render(pose)["raw"], noisy.render(pose)["raw"]
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, noisy.render(pose, seed=5)["raw"])


def test_render_command_writes_log_raw_and_primary(tmp_path):
    import json
    import subprocess
    import sys

    from tests.conftest import REPO

    out = tmp_path / "poly.npy"
    r = subprocess.run([sys.executable, "-m", "register.cli", "render", "--ct", "phantom", "--size", "32", "32",
                        "--physics", "poly", "--kvp", "100", "--filters", "Al:2.5", "Cu:0.1", "--no-noise",
                        "--primary", "--out", str(out)], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr
    log, raw, primary = (np.load(tmp_path / f) for f in ("poly.npy", "poly_raw.npy", "poly_primary.npy"))
    side = json.loads((tmp_path / "poly.json").read_text())
    assert side["physics"]["kvp"] == 100.0 and side["physics"]["filters"] == [["Al", 2.5], ["Cu", 0.1]]
    np.testing.assert_allclose(log, -np.log(raw / side["physics"]["flat_field_signal"]), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(raw, primary)
    # full physics: the scatter image is written with --primary; raw = primary + scatter (no noise)
    r = subprocess.run([sys.executable, "-m", "register.cli", "render", "--ct", "phantom", "--size", "32", "32",
                        "--physics", "full", "--scatter-photons", "20000", "--no-noise", "--primary",
                        "--out", str(tmp_path / "full.npy")], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr
    raw, primary, scatter = (np.load(tmp_path / f) for f in ("full_raw.npy", "full_primary.npy", "full_scatter.npy"))
    assert scatter.min() > 0 and 0.05 < scatter.mean() / primary.mean() < 10
    np.testing.assert_allclose(raw, primary + scatter, rtol=1e-5)
    assert json.loads((tmp_path / "full.json").read_text())["physics"]["scatter_photons"] == 20000
    # options of the other physics level are refused, not ignored
    for args, words in ((["--kvp", "100"], "--kvp: meaningful with --physics poly or full only"),
                        (["--physics", "poly", "--grid-ratio", "10"], "--grid-ratio: meaningful with --physics full only"),
                        (["--physics", "full", "--scatter-photons", "10"], "--scatter-photons 10: must be >= 1000"),
                        (["--physics", "poly", "--quantity", "intensity"], "--quantity: meaningful with --physics line")):
        r = subprocess.run([sys.executable, "-m", "register.cli", "render", "--ct", "phantom", *args, "--out",
                            str(tmp_path / "y.png")], capture_output=True, text=True, cwd=REPO, timeout=300)
        assert r.returncode == 2 and words in r.stderr and r.stderr.count("\n") == 1, r.stderr


def test_campaign_renders_poly_images_reproducibly(tmp_path):
    """A campaign with line, poly and full entries: poly and full images are -log(I/I0) of the
    same poses (correlated with the line DRR; scatter lowers full's contrast), and a second run
    writes bit-identical shards (seeded noise and Monte Carlo)."""
    from sim.campaign import load_campaign, open_dataset, run_campaign

    (tmp_path / "c.toml").write_text('''
[campaign]
name = "poly"
seed = 2
images_per_ct = 4
shard_size = 2
[scene]
size = [32, 32]
[[physics]]
name = "line"
[[physics]]
name = "poly"
level = "poly"
kvp = 100.0
filters = ["Al:2.5", "Cu:0.1"]
mas = 1.0
[[physics]]
name = "full"
level = "full"
mas = 1.0
noise = false
scatter_photons = 20000
[[cts]]
path = "phantom:1"
split = "train"
''')
    cfg = load_campaign(tmp_path / "c.toml")
    assert cfg.physics[1].filters == (("Al", 2.5), ("Cu", 0.1))
    run_campaign(cfg, tmp_path / "a", progress=False)
    run_campaign(cfg, tmp_path / "b", progress=False)
    for shard in sorted((tmp_path / "a").glob("**/*.h5")):
        assert shard.read_bytes() == (tmp_path / "b" / shard.relative_to(tmp_path / "a")).read_bytes()
    data = open_dataset(tmp_path / "a")
    line, poly = data[0]["images"]["line"], data[0]["images"]["poly"]
    assert np.all(np.isfinite(poly)) and np.corrcoef(line.ravel(), poly.ravel())[0, 1] > 0.95
    full = data[0]["images"]["full"]
    assert np.all(np.isfinite(full)) and np.corrcoef(line.ravel(), full.ravel())[0, 1] > 0.95
    data.close()


def test_evaluate_with_poly_targets_registers_through_the_domain_gap(tmp_path):
    """`ctxreg evaluate --target-physics poly`: noisy polychromatic targets, line-DRR CMA-ES from
    a local start; the pose comes back (gradient NCC is insensitive to the beam-hardening
    contrast change) and the run records its cases."""
    import csv

    from register.commands import EvaluateCommand, run_evaluate

    run_evaluate(EvaluateCommand(ct="phantom", cases=1, start="local", size=(64, 64), target_physics="poly",
                                 target_mas=5.0, out=str(tmp_path)))
    rows = list(csv.DictReader(open(tmp_path / "cases.csv")))
    assert len(rows) == 1 and float(rows[0]["rot_err_deg"]) < 2.0 and float(rows[0]["mtre_mm"]) < 10.0


def test_a_label_map_overrides_the_materials():
    """A labelled 'implant' in soft tissue: as titanium it gets titanium's nominal density and
    attenuates like Beer-Lambert with xraylib's titanium mu; unlabelled voxels are unchanged."""
    from sim.physics.materials import LabelOverride, nominal_density

    hu = np.full((4, 4, 4), 40.0, np.float32)
    labels = np.zeros((4, 4, 4), np.int16)
    labels[1:3, 1:3, 1:3] = 7
    over = LabelOverride(labels, {7: "titanium"})
    p = over.partial_densities(hu)
    ti = TISSUE_DECOMPOSITION.names.index("titanium")
    st = TISSUE_DECOMPOSITION.names.index("soft_tissue")
    assert p[ti][labels == 7] == pytest.approx(nominal_density("titanium"))
    assert np.all(np.delete(p, ti, axis=0)[:, labels == 7] == 0)
    np.testing.assert_allclose(p[:, labels == 0], TISSUE_DECOMPOSITION.partial_densities(hu)[:, labels == 0])
    assert p[st][0, 0, 0] == pytest.approx(TISSUE_DECOMPOSITION.density(np.array(40.0)))
    bone = LabelOverride(labels, {7: "cortical_bone"}).partial_densities(hu)  # HU-curve density
    idx = TISSUE_DECOMPOSITION.names.index("cortical_bone")
    assert bone[idx][labels == 7] == pytest.approx(TISSUE_DECOMPOSITION.density(np.array(40.0)))
    with pytest.raises(MaterialError, match="steel"):
        LabelOverride(labels, {7: "steel"})
    with pytest.raises(MaterialError, match="shape"):
        over.partial_densities(np.zeros((2, 2, 2)))


def test_imager_uses_the_label_override_of_a_ct():
    from sim.ct.phantom import make_pelvis_phantom
    from sim.physics.imaging import PhysicsSettings, XRayImager
    from sim.ct.volume import CTVolume

    vol = make_pelvis_phantom(0, spacing_mm=5.0)
    labels = np.zeros(vol.hu.shape, np.int16)
    c = np.array(vol.hu.shape) // 2
    labels[c[0] - 2:c[0] + 2, c[1] - 2:c[1] + 2, c[2] - 2:c[2] + 2] = 9
    lab = CTVolume(vol.hu, vol.affine, source="phantom+implant", labels=labels)
    base = XRayImager(lab, PhysicsSettings(noise=False), size=(32, 32))
    implant = XRayImager(lab, PhysicsSettings(noise=False), size=(32, 32), label_materials={9: "titanium"})
    from sim.projection.geometry import pose_from_params

    pose = pose_from_params(np.zeros(6), base.geometry.sod_mm)
    a, b = base.render(pose)["log"][0], implant.render(pose)["log"][0]
    assert b.max() > a.max() + 1.0  # 20 mm of titanium adds > 1 to -log(I/I0) where it projects
    assert np.median(np.abs(a - b)) < 1e-6  # and nothing elsewhere
    with pytest.raises(PhysicsError, match="label map"):
        XRayImager(CTVolume(vol.hu, vol.affine, source="no labels"), size=(32, 32), label_materials={9: "titanium"})


def test_label_materials_on_the_command_line_and_in_campaigns(tmp_path):
    """`--label-material 3:titanium` (the phantom's left femur as an implant) raises -log(I/I0)
    where the femur projects and nowhere else; a campaign's `label_materials` does the same in
    its poly images and leaves its line images alone."""
    import json
    import subprocess
    import sys

    from sim.campaign import load_campaign, open_dataset, run_campaign
    from tests.conftest import REPO

    def render(*extra):
        out = tmp_path / f"r{len(extra)}.npy"
        r = subprocess.run([sys.executable, "-m", "register.cli", "render", "--ct", "phantom", "--size", "48", "48",
                            "--pose", "0", "0", "0", "0", "0", "250", "--physics", "poly", "--no-noise", *extra,
                            "--out", str(out)], capture_output=True, text=True, cwd=REPO, timeout=300)
        assert r.returncode == 0, r.stderr
        return np.load(out), json.loads(out.with_suffix(".json").read_text())

    (a, _), (b, side) = render(), render("--label-material", "3:titanium")
    assert side["physics"]["label_materials"] == {"3": "titanium"}
    assert (b - a).max() > 1.0 and np.mean(np.abs(b - a) < 1e-6) > 0.5
    r = subprocess.run([sys.executable, "-m", "register.cli", "render", "--ct", "phantom", "--label-material",
                        "3:titanium", "--out", str(tmp_path / "x.png")], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 2 and "--label-material: meaningful with --physics poly or full only" in r.stderr

    text = '''
[campaign]
name = "lm"
seed = 4
images_per_ct = 2
[scene]
size = [32, 32]
[poses]
tz = { dist = "fixed", value = 250.0 }
[[physics]]
name = "line"
[[physics]]
name = "poly"
level = "poly"
noise = false
[[cts]]
path = "phantom:0"
split = "train"
'''
    (tmp_path / "a.toml").write_text(text)
    (tmp_path / "b.toml").write_text(text + 'label_materials = { 3 = "titanium" }\n')
    run_campaign(load_campaign(tmp_path / "a.toml"), tmp_path / "a", progress=False)
    run_campaign(load_campaign(tmp_path / "b.toml"), tmp_path / "b", progress=False)
    da, db = open_dataset(tmp_path / "a"), open_dataset(tmp_path / "b")
    for i in range(2):
        np.testing.assert_array_equal(da[i]["images"]["line"], db[i]["images"]["line"])
        np.testing.assert_array_equal(da[i]["pose"], db[i]["pose"])
    gain = max(float((db[i]["images"]["poly"] - da[i]["images"]["poly"]).max()) for i in range(2))
    assert gain > 1.0
    da.close()
    db.close()


def test_render_command_with_a_photon_counting_detector(tmp_path):
    """`--detector-mode counting`: the raw signal is in counts (the sidecar says so), so the
    integrating detector's flat field over the counting one is the mean energy deposited per
    interacting photon: between the K edges of Cs/I (~33-36 keV) and the tube's 120 kV."""
    import json
    import subprocess
    import sys

    from tests.conftest import REPO

    sides = {}
    for mode in ("integrating", "counting"):
        out = tmp_path / f"{mode}.npy"
        r = subprocess.run([sys.executable, "-m", "register.cli", "render", "--ct", "phantom", "--size", "32", "32",
                            "--physics", "poly", "--no-noise", "--detector-mode", mode, "--out", str(out)],
                           capture_output=True, text=True, cwd=REPO, timeout=300)
        assert r.returncode == 0, r.stderr
        sides[mode] = json.loads(out.with_suffix(".json").read_text())["physics"]
    assert sides["counting"]["detector_mode"] == "counting"
    assert sides["counting"]["signal_units"] == "counts per pixel"
    kev_per_count = sides["integrating"]["flat_field_signal"] / sides["counting"]["flat_field_signal"]
    assert 30.0 < kev_per_count < 80.0, kev_per_count
