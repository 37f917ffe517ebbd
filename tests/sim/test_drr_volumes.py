"""The renderer's volumes (sim/projection/drr.py): renderers of one CT share one upload with the same images;
coarse levels keep the mass and the voxel centres, follow the pixel's footprint and keep the image
within a stated tolerance."""

from __future__ import annotations

import numpy as np

from sim.ct.volume import CTVolume

from tests.sim.small_ct import small_ct



def test_renderers_of_one_ct_share_one_upload_and_render_the_same_images():
    from sim.projection.drr import DRRRenderer, RenderSettings, _UPLOADS
    from sim.projection.geometry import pose_from_params

    ct = small_ct(2)
    a = DRRRenderer(ct, RenderSettings(size=(24, 24)))
    b = DRRRenderer(ct, RenderSettings(size=(16, 16), ray_model="trilinear"))
    assert a.integrator.volume is b.integrator.volume and len(_UPLOADS[ct]) == 1
    other_water = DRRRenderer(ct, RenderSettings(size=(24, 24), mu_water_per_mm=0.03))
    assert other_water.integrator.volume is not a.integrator.volume and len(_UPLOADS[ct]) == 2
    # the same CT as a new object: its own upload, the same image
    twin = DRRRenderer(CTVolume(hu=ct.hu.copy(), affine=ct.affine, source="twin"), RenderSettings(size=(24, 24)),
                       center_lps=a.center_lps)
    assert twin.integrator.volume is not a.integrator.volume
    pose = pose_from_params(np.array([10.0, -5.0, 3.0, 2.0, -1.0, 4.0]), a.geometry.sod_mm)
    np.testing.assert_array_equal(a.render(pose), twin.render(pose))
    from sim.physics.materials import MU_WATER_60KEV_PER_MM  # mu is linear in mu_water: the image scales with it

    np.testing.assert_allclose(other_water.render(pose), a.render(pose) * (0.03 / MU_WATER_60KEV_PER_MM),
                               rtol=1e-5, atol=1e-6)


def test_coarsened_keeps_the_mass_and_the_coarse_voxel_centres():
    from sim.projection.drr import coarse_affine, coarsened

    rng = np.random.default_rng(3)
    fine = rng.random((2, 7, 6, 5)).astype(np.float32)
    coarse = coarsened(fine, (2, 4, 1))
    assert coarse.shape == (2, 4, 2, 5)
    np.testing.assert_allclose(coarse.sum(axis=(1, 2, 3)) * 8, fine.sum(axis=(1, 2, 3)), rtol=1e-6)
    np.testing.assert_allclose(coarse[:, 1, 0, 3], fine[:, 2:4, 0:4, 3].mean(axis=(1, 2)), rtol=1e-6)
    affine = np.array([[0.0, 1.5, 0, 3], [2.0, 0, 0, -1], [0, 0, -1.0, 7], [0, 0, 0, 1]])
    ca = coarse_affine(affine, (2, 4, 1))
    centres = affine @ np.array([[2, 3, 2, 3], [4, 4, 7, 7], [3, 3, 3, 3], [1, 1, 1, 1]], float)  # fine (2..3, 4..7, 3)
    np.testing.assert_allclose(ca @ [1, 1, 3, 1], centres.mean(axis=1), atol=1e-12)


def test_coarsening_follows_the_pixel_footprint_and_keeps_the_image():
    """Factors: the largest powers of two keeping voxels at most half the pixel's footprint at the
    isocentre. Image: a fine CT (0.75 mm) rendered at 64 px (footprint 3.2 mm) from 1.5 mm voxels
    stays within 2 % (rel. L2; 1.2 % measured, most of it the phantom's uncorrelated 20 HU noise,
    which the coarse voxels average; the chest CT: 0.4 %) of its own voxels' image; a 3 mm CT at
    64 px is not coarsened."""
    from sim.projection.drr import DRRRenderer, RenderSettings, coarsening
    from sim.projection.geometry import pose_from_params
    from sim.projection.scene import load_scene

    g64 = load_scene("cios_fusion").geometry_at(64, 64)
    footprint = g64.pixel_spacing_mm * g64.sod_mm / g64.sdd_mm
    rng = np.random.default_rng(4)
    n = 128
    x = np.linspace(-1, 1, n)
    r2 = x[:, None, None] ** 2 + x[None, :, None] ** 2 + 0.5 * x[None, None, :] ** 2
    hu = np.where(r2 < 0.7, 40.0, -1000.0) + np.where(r2 < 0.15, 900.0, 0.0) + rng.normal(0, 20, (n, n, n))
    fine = CTVolume(hu=hu.astype(np.float32), affine=np.diag([0.75, 0.75, 0.75, 1.0]), source="fine")
    factors = coarsening(fine, g64)
    assert factors == (2, 2, 2) and all(0.75 * f * 2 > footprint / 2 >= 0.75 * f for f in factors), (factors, footprint)
    coarse_3mm = CTVolume(hu=hu.astype(np.float32), affine=np.diag([3.0, 3.0, 3.0, 1.0]), source="3mm")
    assert coarsening(coarse_3mm, g64) == (1, 1, 1)
    full = DRRRenderer(fine, RenderSettings(size=(64, 64)), center_lps=np.zeros(3) + 0.75 * (n - 1) / 2)
    coarse = DRRRenderer(fine, RenderSettings(size=(64, 64), coarsen=True), center_lps=full.center_lps)
    assert coarse.factors == factors and full.factors == (1, 1, 1)
    poses = pose_from_params(rng.uniform(-1, 1, (4, 6)) * [30, 20, 20, 5, 5, 20], g64.sod_mm)
    a, b = full.render(poses), coarse.render(poses)
    assert np.linalg.norm(a - b) / np.linalg.norm(a) < 0.02
    assert abs(a.sum() - b.sum()) / a.sum() < 0.005  # the mass along the rays is kept
