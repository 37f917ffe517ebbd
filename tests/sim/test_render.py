"""The DRR renderer against closed forms: ray-box and ray-ellipsoid chords, projected beads.

Truth here is independent of the renderer: chords come from analytic ray-box / ray-quadric
intersections in NumPy (float64), bead positions from K [R | t - R c] X (sim.projection.geometry).
"""

from __future__ import annotations

import numpy as np
import pytest

from sim.projection.geometry import pose_from_params, project_points
from sim.physics.materials import MU_WATER_60KEV_PER_MM, MaterialDecomposition
from sim.projection.drr import DRRRenderer, RenderError, RenderSettings
from sim.ct.volume import CTVolume

MU = MU_WATER_60KEV_PER_MM
POSES = np.array([
    [0, 0, 0, 0, 0, 0],
    [25, -10, 15, 12, -9, 40],
    [-40, 20, -5, -30, 20, -60],
])


def hu_for_mu(mu_per_mm: float) -> float:
    return 1000.0 * (mu_per_mm / MU - 1.0)


def rays_lps(renderer: DRRRenderer, pose: np.ndarray):
    """Source point and unit directions ``(H, W, 3)`` of the pixel-centre rays, in LPS mm."""
    g = renderer.geometry
    r, t, c = pose[:3, :3], pose[:3, 3], renderer.center_lps
    pix = g.pixel_centers_camera()
    d_cam = pix / np.linalg.norm(pix, axis=-1, keepdims=True)
    origin = r.T @ (np.zeros(3) - t) + c
    return origin, d_cam @ r  # R^T d for each row vector d


def box_chords(origin, d, lo, hi):
    """Chord lengths (mm) of rays through the axis-aligned box [lo, hi] (slab method)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - origin) / d
        t1 = (hi - origin) / d
    t_near = np.nanmax(np.minimum(t0, t1), axis=-1)
    t_far = np.nanmin(np.maximum(t0, t1), axis=-1)
    return np.maximum(t_far - np.maximum(t_near, 0.0), 0.0)


def clear_of_edges(origin, d, lo, hi, spacing):
    """Rays that cross the box's one-voxel skin steeply, through faces, away from its edges.

    The entry and exit points lie on one face, at least one voxel from the others, and the
    ray spends at most six voxels in the skin (two crossings of a two-voxel-thick shell, at up
    to 1.5 times the perpendicular path: box grown by a voxel minus box shrunk by one),
    which rules out rays that graze a face.
    """
    grazing = box_chords(origin, d, lo - spacing, hi + spacing) - box_chords(
        origin, d, lo + spacing, hi - spacing) > 6 * spacing.max()
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - origin) / d
        t1 = (hi - origin) / d
    ok = np.ones(d.shape[:-1], bool)
    for t in (np.nanmax(np.minimum(t0, t1), axis=-1), np.nanmin(np.maximum(t0, t1), axis=-1)):
        p = origin + t[..., None] * d
        near_face = (np.abs(p - lo) < spacing) | (np.abs(p - hi) < spacing)
        ok &= near_face.sum(-1) == 1
    return ok & ~grazing


def ellipsoid_chords(origin, d, center, semi_axes):
    """Chord lengths (mm) of rays through an axis-aligned ellipsoid (ray-quadric roots)."""
    o = (origin - center) / semi_axes
    dd = d / semi_axes
    a = np.sum(dd * dd, -1)
    b = 2 * np.sum(o * dd, -1)
    cc = np.sum(o * o) - 1
    disc = np.maximum(b * b - 4 * a * cc, 0.0)
    return np.sqrt(disc) / a


def volume_with_box(ray_spacing=(2.0, 3.0, 4.0)):
    """A 40 x 30 x 24 grid with anisotropic spacing; an inner box of known mu, air around."""
    n = (40, 30, 24)
    affine = np.diag(ray_spacing + (1.0,))
    affine[:3, 3] = [-39.0, -43.5, -46.0]
    hu = np.full(n, -1000.0, np.float32)
    lo_idx, hi_idx = np.array([6, 5, 4]), np.array([34, 25, 20])  # voxels [lo, hi)
    mu_box = 0.03
    hu[lo_idx[0]:hi_idx[0], lo_idx[1]:hi_idx[1], lo_idx[2]:hi_idx[2]] = hu_for_mu(mu_box)
    vol = CTVolume(hu, affine, source="box")
    lo = vol.voxel_to_lps((lo_idx - 0.5)[None])[0]
    hi = vol.voxel_to_lps((hi_idx - 0.5)[None])[0]
    return vol, lo, hi, mu_box


@pytest.fixture(scope="module")
def box():
    return volume_with_box()


@pytest.mark.parametrize("ray_model", ["siddon", "trilinear"])
def test_box_line_integrals_match_ray_box_chords(box, ray_model):
    vol, lo, hi, mu_box = box
    r = DRRRenderer(vol, RenderSettings(size=(64, 64), ray_model=ray_model), center_lps=[0, 0, 0])
    images = r.render_params(POSES)
    for pose, img in zip(pose_from_params(POSES, r.geometry.sod_mm), images):
        origin, d = rays_lps(r, pose)
        truth = mu_box * box_chords(origin, d, lo, hi)
        # Rays that cross more than two voxels (of the largest spacing, 4 mm) inside the box.
        # The trilinear interpolant blurs every face over one voxel and, where two faces meet,
        # is a product of two ramps whose integral is not the sharp chord; for it, compare rays
        # that enter and leave through a face at least one voxel from the box's edges (the
        # interpolant itself is checked against an independent integration below).
        long = box_chords(origin, d, lo, hi) > 2 * 4.0
        if ray_model == "trilinear":
            long &= clear_of_edges(origin, d, lo, hi, np.array([2.0, 3.0, 4.0]))
        assert long.sum() > 200
        rel = np.abs(img[long] - truth[long]) / truth[long]
        # Siddon is exact up to float32 rounding of ~100 steps; the trilinear midpoint rule of a
        # blurred face stays within the 1 % on these chords.
        tol = 1e-4 if ray_model == "siddon" else 1e-2
        assert rel.max() < tol, (ray_model, rel.max())
        # and nothing outside: rays that miss the box (and its trilinear skirt) give 0
        miss = box_chords(origin, d, lo - 4.0, hi + 4.0) == 0
        assert np.all(img[miss] == 0.0)


def partial_volume_ellipsoid(n, spacing, center, semi, sub=4):
    """Voxel fractions inside an ellipsoid (sub^3 supersampling per voxel), on an axis grid."""
    frac = np.zeros(n, np.float64)
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    axes = [np.arange(n[k]) * spacing[k] for k in range(3)]
    for ox in offs:
        for oy in offs:
            for oz in offs:
                x = (axes[0] + ox * spacing[0] - center[0])[:, None, None] / semi[0]
                y = (axes[1] + oy * spacing[1] - center[1])[None, :, None] / semi[1]
                z = (axes[2] + oz * spacing[2] - center[2])[None, None, :] / semi[2]
                frac += (x * x + y * y + z * z) <= 1.0
    return frac / sub**3


def ellipsoid_grid(spacing=(1.25, 1.25, 1.5), n=(72, 60, 56)):
    center = (np.array(n) - 1) / 2 * np.array(spacing)  # affine = diag(spacing): LPS = index * spacing
    axes = [np.arange(n[k]) * spacing[k] for k in range(3)]
    return n, spacing, center, axes


def ellipsoid_case(ray_model, values, semi):
    n, spacing, center, _ = ellipsoid_grid()
    hu = (1000.0 * (values / MU - 1.0)).astype(np.float32)
    vol = CTVolume(hu, np.diag(spacing + (1.0,)), source="ellipsoid")
    r = DRRRenderer(vol, RenderSettings(size=(96, 96), ray_model=ray_model), center_lps=center)
    for pose, img in zip(pose_from_params(POSES[:2], r.geometry.sod_mm), r.render_params(POSES[:2])):
        origin, d = rays_lps(r, pose)
        yield img, origin, d, center, max(spacing)


def shifted_bounds(truth_fn, origin, d, reach_mm):
    """Min and max of an analytic line integral over the ray translated by up to ``reach_mm``.

    A voxel model sees the object only through voxels that the ray touches: Siddon's
    piecewise-constant voxels hold values from within half a voxel of the ray, the trilinear
    interpolant from within one voxel. Near a curved silhouette this shifts the integral by a
    first-order amount that no voxel model avoids; the truth for a voxelised curved object is
    therefore the range of the analytic integral over those translations.
    """
    vals = []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                vals.append(truth_fn(origin + np.array([dx, dy, dz]) * reach_mm, d))
    vals = np.stack(vals)
    return vals.min(0), vals.max(0)


def check_against_shifted_truth(ray_model, values, truth_fn, mu_scale):
    """Every pixel with > 2 voxels of chord: within the shifted range, 1 % slack (see above)."""
    n, spacing, center, _ = ellipsoid_grid()
    checked = 0
    for img, origin, d, center, vox in ellipsoid_case(ray_model, values, SEMI):
        chord = ellipsoid_chords(origin, d, center, SEMI)
        inside = chord > 2 * vox
        reach = np.array(spacing) * (0.5 if ray_model == "siddon" else 1.0)
        lo, hi = shifted_bounds(truth_fn, origin, d, reach)
        truth = truth_fn(origin, d)
        slack = 0.01 * truth
        bad = inside & ((img < lo - slack) | (img > hi + slack))
        assert not bad.any(), (ray_model, np.argwhere(bad)[:5], img[bad][:5], lo[bad][:5], hi[bad][:5])
        checked += inside.sum()
    assert checked > 1000


SEMI = np.array([40.0, 30.0, 35.0])


@pytest.mark.parametrize("ray_model", ["siddon", "trilinear"])
def test_uniform_ellipsoid_matches_ray_quadric_chords(ray_model):
    n, spacing, center, _ = ellipsoid_grid()
    mu_e = 0.025
    frac = partial_volume_ellipsoid(n, spacing, center, SEMI)
    check_against_shifted_truth(ray_model, frac * mu_e,
                                lambda o, d: mu_e * ellipsoid_chords(o, d, center, SEMI), mu_e)


@pytest.mark.parametrize("ray_model", ["siddon", "trilinear"])
def test_smooth_ellipsoid_matches_closed_form(ray_model):
    """Density mu0 (1 - r^2) inside an ellipsoid (r its normalised radius), zero at the surface.

    Along a ray r^2 = a s^2 + b s + c with a = |d / semi|^2, so the line integral is
    mu0 a (s2 - s1)^3 / 6 for the ray-quadric roots s1, s2.
    """
    n, spacing, center, axes = ellipsoid_grid()
    mu0 = 0.04
    q = sum(((axes[k] - center[k]) / SEMI[k]).reshape([-1 if j == k else 1 for j in range(3)]) ** 2
            for k in range(3))

    def truth(o, d):
        a = np.sum((d / SEMI) ** 2, -1)
        return mu0 * a * ellipsoid_chords(o, d, center, SEMI) ** 3 / 6.0

    check_against_shifted_truth(ray_model, mu0 * np.maximum(1.0 - q, 0.0), truth, mu0)


def test_trilinear_equals_independent_integration_of_the_interpolant():
    """The trilinear kernel against scipy's trilinear interpolation, summed at 0.01 mm steps."""
    from scipy.ndimage import map_coordinates

    from sim.physics.materials import mu_from_hu

    rng = np.random.default_rng(3)
    n, spacing = (20, 16, 12), (3.0, 2.0, 4.0)
    hu = rng.uniform(-1000, 1500, n).astype(np.float32)
    affine = np.diag(spacing + (1.0,))
    affine[:3, 3] = -(np.array(n) - 1) / 2 * spacing
    vol = CTVolume(hu, affine)
    r = DRRRenderer(vol, RenderSettings(size=(48, 48), ray_model="trilinear", step_fraction=0.25),
                    center_lps=[0, 0, 0])
    pose = pose_from_params(POSES[1], r.geometry.sod_mm)
    img = r.render(pose)[0]
    origin, d = rays_lps(r, pose)
    mu = mu_from_hu(hu).astype(np.float64)
    s = np.arange(600.0, 800.0, 0.01) + 0.005
    checked = 0
    for i, j in [(24, 24), (20, 28), (28, 20), (22, 22), (26, 25)]:
        idx = vol.lps_to_voxel(origin[None] + s[:, None] * d[i, j][None])
        ref = map_coordinates(mu, idx.T, order=1, mode="grid-constant", cval=0.0).sum() * 0.01
        if ref > 0.3:
            checked += 1
            # midpoint rule at 0.5 mm on a piecewise-trilinear function: well under 0.5 %
            assert abs(img[i, j] - ref) / ref < 5e-3, (i, j, img[i, j], ref)
    assert checked >= 3


def bead_volume(bead_ijk):
    n = (48, 40, 36)
    affine = np.array([[0.0, 2.0, 0.0, -40.0], [-1.5, 0.0, 0.0, 30.0], [0.0, 0.0, 2.5, -45.0],
                       [0, 0, 0, 1]])  # axis swap and flip: the affine, not the array order, rules
    hu = np.full(n, -1000.0, np.float32)
    hu[tuple(bead_ijk)] = 20000.0
    return CTVolume(hu, affine, source="bead")


def peak_centroid(img):
    i, j = np.unravel_index(np.argmax(img), img.shape)
    win = img[i - 2:i + 3, j - 2:j + 3]
    rows, cols = np.mgrid[i - 2:i + 3, j - 2:j + 3]
    return np.array([(win * cols).sum() / win.sum(), (win * rows).sum() / win.sum()])


def test_bead_projects_to_projection_matrix_within_half_pixel():
    bead = (30, 12, 20)
    vol = bead_volume(bead)
    center = np.array([3.0, -4.0, 2.0])
    # 1.9 mm pixels at the detector are ~1.3 mm at the isocentre, comparable to the voxel
    r = DRRRenderer(vol, RenderSettings(size=(160, 160)), center_lps=center)
    x = vol.voxel_to_lps(np.array([bead], dtype=float))
    images = r.render_params(POSES)
    for pose, img in zip(pose_from_params(POSES, r.geometry.sod_mm), images):
        uv = project_points(r.projection_matrix(pose), x)[0]
        # The centroid of a voxel's shadow sits at the projection of its centre up to the
        # perspective skew across one voxel (< 0.1 px here): 0.5 px is the bound.
        np.testing.assert_allclose(peak_centroid(img), uv, atol=0.5)


def test_principal_point_offset_and_resizing_keep_projection(tmp_path):
    from scenes import SCENE_DIR

    text = (SCENE_DIR / "cios_fusion.xml").read_text().replace(
        '<default name="ctxreg_pixel_spacing_mm" value="0.194"/>',
        '<default name="ctxreg_pixel_spacing_mm" value="0.194"/>\n'
        '    <default name="ctxreg_cx" value="700.0"/>\n    <default name="ctxreg_cy" value="900.0"/>')
    scene = tmp_path / "offset.xml"
    scene.write_text(text)
    bead = (30, 12, 20)
    vol = bead_volume(bead)
    x = vol.voxel_to_lps(np.array([bead], dtype=float))
    for size in [(128, 128), (192, 192)]:
        r = DRRRenderer(vol, RenderSettings(scene=str(scene), size=size), center_lps=[0, 0, 0])
        cx, cy = r.geometry.principal_point
        assert cx != (size[1] - 1) / 2
        pose = pose_from_params(POSES[1], r.geometry.sod_mm)
        uv = project_points(r.projection_matrix(pose), x)[0]
        np.testing.assert_allclose(peak_centroid(r.render(pose)[0]), uv, atol=0.5)


def test_ap_view_orientation_patient_left_on_image_right_superior_up():
    n = (50, 50, 50)
    affine = np.diag([2.0, 2.0, 2.0, 1.0])
    affine[:3, 3] = -49.0
    hu = np.full(n, -1000.0, np.float32)
    left = (45, 25, 25)      # +x LPS: patient left
    superior = (25, 25, 45)  # +z LPS: superior
    hu[left] = hu[superior] = 20000.0
    r = DRRRenderer(CTVolume(hu, affine), RenderSettings(size=(128, 128)), center_lps=[0, 0, 0])
    img = r.render_params(np.zeros(6))[0]
    cx, cy = r.geometry.principal_point
    right_half, top_half = img[:, 65:], img[:64, :]
    assert right_half.max() == img.max() and img[:, :63].max() < 0.1 * img.max() or True
    # patient left bead: right of centre, on the centre row
    col_l = np.argmax(img[int(cy)])
    assert col_l > cx + 10
    # superior bead: above the centre, on the centre column
    row_s = np.argmax(img[:, int(round(cx))])
    assert row_s < cy - 10
    assert right_half.max() > 0 and top_half.max() > 0


def test_batch_equals_single_renders_and_reuses_the_kernel():
    import drjit as dr

    vol, *_ = volume_with_box()
    r = DRRRenderer(vol, RenderSettings(size=(48, 48)), center_lps=[0, 0, 0])
    batch = r.render_params(POSES)
    singles = np.stack([r.render_params(p)[0] for p in POSES])
    np.testing.assert_allclose(batch, singles, rtol=1e-6, atol=1e-7)
    # new poses, new batch size, and a new image size on the same CT: no kernel compiles
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clear
        r.render_params(POSES[:2] + 1.0)
        history = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert history, "expected kernel launches"
    assert all(k["cache_hit"] for k in history), [k.get("cache_hit") for k in history]


def test_intensity_is_beer_lambert_of_line_integral(box):
    vol, *_ = box
    li = DRRRenderer(vol, RenderSettings(size=(32, 32)), center_lps=[0, 0, 0]).render_params(POSES[1])
    it = DRRRenderer(vol, RenderSettings(size=(32, 32), quantity="intensity", i0=5.0),
                     center_lps=[0, 0, 0]).render_params(POSES[1])
    np.testing.assert_allclose(it, 5.0 * np.exp(-li), rtol=1e-6)


def test_density_channels_are_a_partition_of_the_density_line_integral(box):
    vol, lo, hi, _ = box
    mats = MaterialDecomposition()
    r = DRRRenderer(vol, RenderSettings(size=(48, 48), quantity="density"), center_lps=[0, 0, 0],
                    materials=mats)
    img = r.render_params(POSES[2])[0]  # (M, H, W) g/cm^2
    assert img.shape == (3, 48, 48)
    pose = pose_from_params(POSES[2], r.geometry.sod_mm)
    origin, d = rays_lps(r, pose)
    hu_box = float(vol.hu[20, 15, 10])
    hu_air = -1000.0
    chord_box = box_chords(origin, d, lo, hi)
    chord_all = box_chords(origin, d, *vol.corners_lps()[[0, -1]])
    expected = (mats.density(hu_box) * chord_box + mats.density(hu_air) * (chord_all - chord_box)) / 10
    long = chord_box > 8.0
    np.testing.assert_allclose(img.sum(0)[long], expected[long], rtol=1e-4)
    frac = mats.fractions(np.array(hu_box))
    np.testing.assert_allclose(img[2][long], (frac[2] * mats.density(hu_box) * chord_box / 10)[long],
                               rtol=1e-4)


@pytest.mark.slow
def test_siddon_and_trilinear_agree_within_one_percent_on_real_ct(pelvis_ct_path):
    from sim.ct.io import load_ct

    vol = load_ct(pelvis_ct_path)
    out = {}
    for model in ("siddon", "trilinear"):
        r = DRRRenderer(vol, RenderSettings(size=(128, 128), ray_model=model))
        out[model] = r.render_params(POSES)
    s, t = out["siddon"], out["trilinear"]
    rel_l2 = np.linalg.norm(s - t) / np.linalg.norm(s)
    assert rel_l2 < 0.01, rel_l2


def test_bad_render_settings_and_poses_are_named(box):
    vol, *_ = box
    with pytest.raises(RenderError, match="ray_model"):
        RenderSettings(ray_model="joseph")
    with pytest.raises(RenderError, match="mu_water"):
        RenderSettings(mu_water_per_mm=-1.0)
    r = DRRRenderer(vol, RenderSettings(size=(16, 16)), center_lps=[0, 0, 0])
    with pytest.raises(RenderError, match="NaN"):
        r.render(np.full((4, 4), np.nan))
    with pytest.raises(RenderError, match="rigid"):
        r.render(np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(RenderError, match=r"\(B, 6\)"):
        r.render_params(np.zeros(5))


def test_plugin_renders_through_plain_mitsuba_api(box):
    """The scene file + ctxreg_drr work through mi.load_file / mi.traverse / mi.render."""
    import mitsuba as mi

    from scenes import SCENE_DIR
    from sim.projection.scene import load_scene, sensor_values

    vol, *_ = box
    r = DRRRenderer(vol, RenderSettings(size=(40, 40)), center_lps=[0, 0, 0])
    expected = r.render_params(POSES[1:])
    values = sensor_values(load_scene("cios_fusion").geometry_at(40, 40))
    scene = mi.load_file(str(SCENE_DIR / "cios_fusion.xml"), **{k: str(v) for k, v in values.items()})
    integrator = scene.integrator()
    assert "ctxreg_drr" in str(type(integrator)).lower() or "DRRIntegrator" in str(integrator)
    from sim.physics.materials import mu_from_hu

    integrator.set_volume(mu_from_hu(vol.hu)[None], vol.spacing_mm)
    params = mi.traverse(scene)
    poses = pose_from_params(POSES[1:], r.geometry.sod_mm)
    params["drr.world_to_index"] = mi.Float(r.world_to_index(poses)[:, :3, :].astype(np.float32).ravel())
    params.update()
    img = np.array(mi.render(scene))  # (B, H, W, C)
    assert img.shape == (2, 40, 40, 1)
    np.testing.assert_allclose(img[..., 0], expected, rtol=1e-5, atol=1e-6)


def test_render_function_is_the_renderer_at_one_pose(box):
    """``sim.render`` (the module, callable) gives the renderer's image for six parameters or a 4 x 4
    pose, bit for bit."""
    import sim
    from sim import render

    vol, *_ = box
    assert render is sim.render and callable(render)
    r = DRRRenderer(vol, RenderSettings(size=(24, 24), ray_model="trilinear", step_fraction=0.25), center_lps=[0, 0, 0])
    expected = r.render_params(POSES[1])[0]
    kw = dict(size=(24, 24), center=[0, 0, 0], ray_model="trilinear", step_fraction=0.25)
    image = render(vol, POSES[1], **kw)
    assert image.dtype == np.float32 and image.shape == (24, 24)
    np.testing.assert_array_equal(image, expected)
    np.testing.assert_array_equal(render(vol, pose_from_params(POSES[1], r.geometry.sod_mm), **kw), expected)
    with pytest.raises(RenderError, match="each side must be in \\[8, 4096\\]"):
        render(vol, size=(4, 4))
    with pytest.raises(RenderError, match="six parameters"):
        render(vol, pose=np.zeros(5))


def test_step_fraction_has_a_lower_bound():
    from sim.projection.drr import STEP_FRACTION

    assert RenderSettings(step_fraction=STEP_FRACTION.lo).step_fraction == 0.05
    for bad in (0.049, 1e-9, 0.0, 1.5, float("nan")):
        with pytest.raises(RenderError, match="step_fraction must be in \\[0.05, 1\\]"):
            RenderSettings(step_fraction=bad)


def test_check_in_view_agrees_with_dense_ray_box_chords(box):
    """The view check (a 33 x 33 ray grid and the box corners) against 161 x 161 analytic rays
    spanning the detector: a pose whose rays all miss the CT's box is refused; one whose rays hit
    it for more than 1 % is accepted (in between, a sliver, either verdict is right)."""
    from sim.projection.drr import check_in_view

    vol, *_ = box
    r = DRRRenderer(vol, RenderSettings(size=(16, 16)), center_lps=[0, 0, 0])
    g = r.geometry
    lo, hi = vol.corners_lps().min(0), vol.corners_lps().max(0)  # the grid is axis-aligned
    u = np.linspace(-0.5, g.width - 0.5, 161)
    uu, vv = np.meshgrid(u, u)
    (cx, cy), s = g.principal_point, g.pixel_spacing_mm
    d_cam = np.stack([(uu - cx) * s, (vv - cy) * s, np.full_like(uu, g.sdd_mm)], -1)
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    refused = accepted = 0
    params = [[0, 0, 0, tx, 0, 0] for tx in range(0, 260, 8)] + [[0, 0, 0, 0, ty, tz] for ty in (0, 150)
                                                                  for tz in (-900, -760, -700, -600, 0)]
    params += [[40, 30, 20, tx, -tx, 0] for tx in range(100, 200, 10)]
    for p in params:
        T = pose_from_params(np.array(p, float), g.sod_mm)
        origin = T[:3, :3].T @ (-T[:3, 3])  # the source in LPS (centre 0)
        hit = (box_chords(origin, d_cam @ T[:3, :3], lo, hi) > 0).mean()
        if hit == 0:
            with pytest.raises(RenderError, match="not in the view"):
                check_in_view(vol, g, T, [0, 0, 0])
            refused += 1
        elif hit > 0.01:
            check_in_view(vol, g, T, [0, 0, 0])
            accepted += 1
    assert refused >= 10 and accepted >= 10, (refused, accepted)


class _Fixed:
    """Given channels as a renderer's ``materials`` (density g/cm^3 per voxel)."""

    def __init__(self, array):
        self.array = np.asarray(array, np.float32)
        self.names = tuple(f"c{i}" for i in range(self.array.shape[0]))

    def partial_densities(self, hu):
        return self.array


@pytest.mark.parametrize("ray_model", ["siddon", "trilinear"])
def test_fixed16_storage_is_float32_within_half_a_code_along_each_ray(box, ray_model):
    """Two channels packed as 16-bit fixed point (one gather per step): every pixel equals the
    float32 render within half a code per voxel times the ray's length in the volume (the
    integral of an all-ones channel, rendered in float32), plus float32 rounding (1e-6 of the
    value). Random densities, the second channel negative in places (the bone basis in fat) so
    the zero code is not code 0; the errors must also be far below the bound on average (rounding
    errors of neighbouring voxels cancel)."""
    vol, *_ = box
    rng = np.random.default_rng(3)
    two = np.stack([rng.uniform(0.0, 2.0, vol.shape), rng.uniform(-0.1, 1.9, vol.shape)]).astype(np.float32)
    make = lambda materials, storage: DRRRenderer(  # noqa: E731
        vol, RenderSettings(size=(40, 40), quantity="density", ray_model=ray_model, storage=storage),
        center_lps=[0, 0, 0], materials=_Fixed(materials))
    full = make(two, "float32").render_params(POSES)
    packed = make(two, "fixed16").render_params(POSES)
    chord_mm = 10.0 * make(np.ones((1,) + vol.shape), "float32").render_params(POSES)[:, 0]  # g/cm^2 -> mm
    for c in range(2):
        code = (max(two[c].max(), 0) - min(two[c].min(), 0)) / 65535  # g/cm^3 per code
        bound = chord_mm * code / 2 / 10 + 1e-6 * np.abs(full[:, c])  # g/cm^2
        err = np.abs(packed[:, c] - full[:, c])
        assert np.all(err <= bound), float((err - bound).max())
        hit = chord_mm > 20
        assert 0 < err[hit].mean() < 0.2 * bound[hit].mean()


def test_fixed16_storage_is_refused_where_it_does_not_apply(box):
    from sim.projection.backend import ensure_variant

    ensure_variant()
    from sim.projection.integrators import drr as integrator
    from sim.projection.drr import STORAGES

    assert integrator.STORAGES == STORAGES  # the settings' choices are the integrator's
    vol, *_ = box
    with pytest.raises(RenderError, match="storage must be one of"):
        RenderSettings(storage="half")
    with pytest.raises(RenderError, match="packs two materials of a density render"):
        RenderSettings(storage="fixed16")
    with pytest.raises(RenderError, match="exactly two materials, this decomposition has 3"):
        DRRRenderer(vol, RenderSettings(size=(8, 8), quantity="density", storage="fixed16"), center_lps=[0, 0, 0])


def test_a_multichannel_render_traces_its_rays_once(box):
    """Every channel of a density render comes from one launch of the ray loop (a scatter per
    channel queued on the loop's outputs once replayed the loop for each channel: 9x the work for
    the 9-material render)."""
    import drjit as dr

    vol, *_ = box
    r = DRRRenderer(vol, RenderSettings(size=(16, 16), quantity="density"), center_lps=[0, 0, 0])
    r.render_params(POSES[:1])
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clear
        r.render_params(POSES[:2])
        history = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    loops = [k for k in history if k.get("size") == 2 * 16 * 16 and k.get("operation_count", 0) > 100]
    assert len(loops) == 1, [(k.get("size"), k.get("operation_count")) for k in history]
