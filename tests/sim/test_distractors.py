"""Tools in the field (sim.distractors) against closed forms.

Truth is independent of Mitsuba: rays from the pixel centres of sim.projection.geometry (source at the
camera origin, placed in LPS by R^T and c), chords from analytic ray-cylinder and ray-slab
intersections in NumPy float64, the screw's tip from sim.projection.geometry.project_points, attenuation
coefficients from xraylib called here.

Faceting: a round part is the n-gon inscribed in its circle, which contains the circle of the
apothem ``r cos(pi / n)`` and lies inside the circle ``r``. Chords of a line through nested
convex sets are nested, so the mesh's chord lies between the chords of the two cylinders: the
polygon-vs-circle error is at most ``2 (sqrt(r^2 - d^2) - sqrt(r^2 cos^2(pi/n) - d^2))`` per unit
of perpendicular direction, i.e. below ``1 - cos(pi / n)`` of the diameter at the axis (0.86 % for
24 sides). Float32 ray parameters add about 1e-4 mm.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim.distractors import (
    Distractor,
    DistractorError,
    DistractorField,
    RendererWithDistractors,
    ToolMesh,
    add_to_density_integrals,
    add_to_line_integral,
    cable,
    clean_mesh,
    imager_with_distractors,
    k_wire,
    mu_line,
    plate,
    retractor,
    screw,
    table,
    topology,
)
from sim.core.errors import InputError
from sim.projection.geometry import CArmGeometry, pose_from_params, project_points, projection_matrix

GEOM = CArmGeometry(sdd_mm=1000.0, sod_mm=600.0, height=40, width=48, pixel_spacing_mm=0.6)
CENTER = np.array([5.0, -3.0, 10.0])
POSE = pose_from_params(np.array([10.0, -5.0, 20.0, 2.0, -1.0, 0.0]), GEOM.sod_mm)
FLOAT_MM = 5e-4  # float32 ray parameters at ~600 mm


def rays_lps(pose, center=CENTER, geometry=GEOM):
    """Source (3,) and unit directions (H, W, 3) of the pixel-centre rays in LPS mm."""
    r, t = pose[:3, :3], pose[:3, 3]
    pix = geometry.pixel_centers_camera()
    d_cam = pix / np.linalg.norm(pix, axis=-1, keepdims=True)
    return r.T @ (-t) + center, d_cam @ r


def cylinder_chords(origin, d, axis_point, axis_dir, radius):
    """Chords (mm) of rays through the infinite cylinder (ray-quadric roots, float64)."""
    w = origin - axis_point
    w_perp = w - np.dot(w, axis_dir) * axis_dir
    d_perp = d - (d @ axis_dir)[..., None] * axis_dir
    a = np.sum(d_perp * d_perp, -1)
    b = 2 * d_perp @ w_perp
    c = np.dot(w_perp, w_perp) - radius**2
    disc = b * b - 4 * a * c
    return np.where(disc > 0, np.sqrt(np.maximum(disc, 0.0)) / a, 0.0)


def tool_pose(z_axis, origin):
    """A rigid (4, 4) whose z axis is ``z_axis`` and translation ``origin``."""
    z = np.asarray(z_axis, float) / np.linalg.norm(z_axis)
    x = np.cross(z, [0.3, 0.9, 0.1])
    x /= np.linalg.norm(x)
    p = np.eye(4)
    p[:3, :3] = np.c_[x, np.cross(z, x), z]
    p[:3, 3] = origin
    return p


def wire_across_view(length=400.0, offset=(0.4, 0.0)):
    """Pose of a wire through (near) the anatomy centre, perpendicular to the central ray."""
    view = POSE[:3, :3].T @ [0.0, 0.0, 1.0]  # central ray direction in LPS
    u = np.cross(view, [0.2, 0.1, 1.0])
    u /= np.linalg.norm(u)
    side = np.cross(view, u)
    mid = CENTER + offset[0] * side + offset[1] * view
    return tool_pose(u, mid - u * length / 2), mid, u


def test_k_wire_chords_lie_between_the_inscribed_and_the_circumscribed_cylinder():
    r, sides = 1.0, 24
    wire = k_wire(400.0, 2 * r, sides=sides)
    pose, mid, u = wire_across_view()
    field = DistractorField([Distractor(wire, pose)], GEOM, CENTER)
    chords = field.chords(POSE)
    assert chords.shape == (1, 1, GEOM.height, GEOM.width) and field.channels == (("stainless_steel", 7.874),)
    o, d = rays_lps(POSE)
    upper = cylinder_chords(o, d, mid, u, r)
    lower = cylinder_chords(o, d, mid, u, r * np.cos(np.pi / sides))
    c = chords[0, 0]
    assert (upper > 0).sum() > 100 and (upper == 0).sum() > 100
    assert np.all(c >= lower - FLOAT_MM) and np.all(c <= upper + FLOAT_MM)
    assert np.all(c[upper == 0] == 0.0)  # nothing outside the tool
    # the stated bound is tight enough to mean something: 2 r at the axis within 0.86 %
    assert abs(c.max() - 2 * r) <= 2 * r * (1 - np.cos(np.pi / sides)) + FLOAT_MM
    assert field.unpaired_rays == 0
    # the central column crosses the wire perpendicularly: 2 sqrt(r^2 - d^2) there
    perpendicular = np.abs(d @ u) < 1e-3
    assert perpendicular.any()


def test_a_slab_gives_its_thickness_over_the_cosine_of_the_ray_angle():
    t = 3.0
    slab = plate(300.0, 300.0, t, holes=0)
    for theta in (0.0, 35.0):
        a = np.radians(theta)
        pose = np.eye(4)
        pose[:3, :3] = [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
        pose[:3, 3] = [3.0, -2.0, 450.0]
        field = DistractorField([Distractor(slab, pose, frame="camera")], GEOM, CENTER)
        c = field.chords(np.stack([POSE, np.eye(4)]))  # camera-frame tools ignore the volume pose
        pix = GEOM.pixel_centers_camera()
        d = pix / np.linalg.norm(pix, axis=-1, keepdims=True)
        expected = t / np.abs(d @ pose[:3, 2])
        np.testing.assert_allclose(c[0, 0], expected, rtol=0, atol=FLOAT_MM)
        np.testing.assert_array_equal(c[0], c[1])
        # the rays next to the principal ray (half a pixel, 3e-4 rad, off) see t / cos(theta)
        assert np.min(np.abs(c[0, 0] - t / np.cos(a))) < 0.002


def test_the_screw_image_starts_at_the_projected_tip():
    s = screw(40.0, 6.0, tip_mm=0.3)
    view = POSE[:3, :3].T @ [0.0, 0.0, 1.0]
    axis = np.cross(view, [0.1, 0.2, 1.0])
    tip = CENTER + np.array([0.5, -0.7, 0.3])
    pose = tool_pose(axis, tip)
    field = DistractorField([Distractor(s, pose)], GEOM, CENTER)
    c = field.chords(POSE)[0, 0]
    P = projection_matrix(GEOM, POSE, CENTER)
    uv_tip, uv_head = project_points(P, np.stack([tip, tip + 40.0 * pose[:3, 2]]))
    along = (uv_head - uv_tip) / np.linalg.norm(uv_head - uv_tip)
    vv, uu = np.mgrid[:GEOM.height, :GEOM.width]
    s_px = (uu - uv_tip[0]) * along[0] + (vv - uv_tip[1]) * along[1]
    assert (c > 0).sum() > 50
    assert abs(s_px[c > 0].min()) <= 1.0  # the first pixel of the screw is the tip's
    # the pixel nearest the projected tip, a few pixels up the axis, is inside the shaft
    i, j = (np.round(uv_tip[::-1] + 3 * along[::-1])).astype(int)
    assert c[i, j] > 5.0


def test_meshes_are_closed_outward_and_of_the_right_volume():
    n = 24
    polygon = 0.5 * n * np.sin(2 * np.pi / n)  # area of the unit circle's inscribed n-gon
    path = np.c_[np.linspace(0, 120, 12), 15 * np.sin(np.linspace(0, 2, 12)), np.zeros(12)]
    core, sheath = cable(path, core_diameter_mm=1.0, outer_diameter_mm=3.0, sides=n)
    cases = [
        (k_wire(100.0, 2.0, sides=n), polygon * 1.0 * 100.0),
        (plate(60.0, 10.0, 2.0, holes=3, hole_diameter_mm=4.0, sides=n), 60 * 10 * 2 - 3 * polygon * 4.0 * 2.0),
        (table(400.0, 1000.0, 20.0), 400 * 1000 * 20.0),
        (retractor(50.0, 100.0, 20.0, 2.0, bend_deg=90.0), (100 + 1) * 20 * 2 + (50 + 1) * 20 * 2 - 2 * 2 * 20),
        (screw(30.0, 4.0, head_diameter_mm=7.0, head_height_mm=2.0, tip_mm=2.0, sides=n),
         # exposed tip: the cone (rim 0.97 r at z = tip) below the shaft's start at 0.6 tip; the
         # shaft to the head's overlap 0.1 x head height below z = length; the head
         polygon * ((0.97 * 2.0 * 0.6) ** 2 * 1.2 / 3 + 4.0 * (30.0 - 1.2 - 0.2) + 12.25 * 2.2)),
        (core, None),
        (sheath, None),
    ]
    for mesh, volume in cases:
        topo = topology(mesh.vertices, mesh.faces)
        assert topo["boundary_edges"] == 0 and topo["non_two_manifold_edges"] == 0, mesh.kind
        assert topo["connected_components_number"] == 1, mesh.kind
        if volume is not None:
            assert mesh.volume_mm3 == pytest.approx(volume, rel=1e-6), mesh.kind
    # the hollow sheath: genus 1 and the annulus's volume (a bent tube keeps its length x area)
    assert topology(sheath.vertices, sheath.faces)["genus"] == 1
    assert sheath.volume_mm3 == pytest.approx(core.volume_mm3 * 8.0, rel=0.03)
    assert (core.material, sheath.material) == ("copper", "pvc")
    # cleaning refuses an open or inside-out surface, naming the check
    v, f = k_wire(10.0, 2.0).vertices, k_wire(10.0, 2.0).faces
    with pytest.raises(DistractorError, match="boundary_edges"):
        clean_mesh(v, f[1:])
    with pytest.raises(DistractorError, match="outward"):
        clean_mesh(v, f[:, ::-1])
    # duplicated vertices are merged: a soup of triangles becomes the same closed mesh
    soup_v, soup_f = v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3)
    cv, cf = clean_mesh(soup_v, soup_f)
    assert len(cv) == len(v) and len(cf) == len(f)
    user = ToolMesh.from_arrays(soup_v, soup_f, "aluminium", kind="bracket")
    assert user.volume_mm3 == pytest.approx(polygon * 10.0, rel=1e-6) and user.density_g_cm3 == pytest.approx(2.6989)
    with pytest.raises(DistractorError, match="bracket mesh: vertices must be finite and faces index them"):
        ToolMesh.from_arrays(v, f + len(v), "aluminium", kind="bracket")


def test_overlapping_tools_of_two_materials_have_their_own_channels_and_frames():
    wire = k_wire(400.0, 2.0)
    wpose, _, _ = wire_across_view()
    slab = plate(300.0, 300.0, 2.0, holes=0)  # titanium, fixed to the C-arm
    spose = np.eye(4)
    spose[:3, 3] = [0.0, 0.0, 500.0]
    tools = [Distractor(slab, spose, frame="camera"), Distractor(wire, wpose)]
    both = DistractorField(tools, GEOM, CENTER).chords(POSE)
    alone = [DistractorField([t], GEOM, CENTER).chords(POSE)[:, 0] for t in tools]
    assert both.shape[1] == 2
    np.testing.assert_array_equal(both[:, 0], alone[0])
    np.testing.assert_array_equal(both[:, 1], alone[1])
    assert ((both[:, 0] > 0) & (both[:, 1] > 0)).sum() > 50  # they overlap in the image
    # two tools of one material (crossing wires) share a channel and their lengths add
    _, mid, u = wire_across_view()
    view = POSE[:3, :3].T @ [0.0, 0.0, 1.0]
    u2 = np.cos(0.5) * u + np.sin(0.5) * np.cross(view, u)
    other = Distractor(wire, tool_pose(u2, mid + 0.8 * view - 200.0 * u2))
    same = DistractorField([tools[1], other], GEOM, CENTER)
    second = DistractorField([other], GEOM, CENTER).chords(POSE)[:, 0]
    assert same.channels == (("stainless_steel", 7.874),) and ((alone[1] > 0) & (second > 0)).sum() > 3
    np.testing.assert_allclose(same.chords(POSE)[:, 0], alone[1] + second, atol=2 * FLOAT_MM)
    # a tool behind the source is not in the image
    behind = spose.copy()
    behind[2, 3] = -100.0
    assert DistractorField([Distractor(slab, behind, frame="camera")], GEOM, CENTER).chords(POSE).max() == 0.0


def test_line_and_density_attenuation_of_the_chords():
    xr = pytest.importorskip("xraylib")
    assert mu_line("stainless_steel", 7.9) == pytest.approx(xr.CS_Total(26, 60.0) * 7.9 / 10, rel=1e-9)
    assert mu_line("pvc", 1.3) == pytest.approx(xr.CS_Total_CP("Polyvinyl Chloride", 60.0) * 1.3 / 10, rel=1e-9)
    wire = k_wire(400.0, 2.0, density_g_cm3=7.9)
    pose, _, _ = wire_across_view()
    field = DistractorField([Distractor(wire, pose)], GEOM, CENTER)
    chords = field.chords(POSE)
    np.testing.assert_allclose(field.line_integral(POSE)[0], xr.CS_Total(26, 60.0) * 0.79 * chords[0, 0], rtol=1e-6)
    rng = np.random.default_rng(0)
    L = rng.uniform(0, 2, (2, 2, 3, 4)).astype(np.float32)
    ch = rng.uniform(0, 5, (2, 2, 3, 4)).astype(np.float32)
    out, names = add_to_density_integrals(L, ("air", "titanium"), ch, (("titanium", 4.5), ("copper", 8.96)))
    assert names == ("air", "titanium", "copper")
    np.testing.assert_array_equal(out[:, 0], L[:, 0])
    np.testing.assert_allclose(out[:, 1], L[:, 1] + 0.45 * ch[:, 0], rtol=1e-6)
    np.testing.assert_allclose(out[:, 2], 0.896 * ch[:, 1], rtol=1e-6)
    line = add_to_line_integral(L[:, 0], ch, (("titanium", 4.5), ("copper", 8.96)))
    np.testing.assert_allclose(line, L[:, 0] + mu_line("titanium", 4.5) * ch[:, 0] + mu_line("copper", 8.96) * ch[:, 1],
                               rtol=1e-6)
    with pytest.raises(DistractorError, match="chords"):
        add_to_line_integral(L[:, 0], ch[:, :1], (("titanium", 4.5), ("copper", 8.96)))


def test_renderers_with_tools_add_them_and_without_tools_are_unchanged():
    from sim.physics.imaging import PhysicsSettings, XRayImager
    from sim.projection.drr import DRRRenderer, RenderSettings
    from sim.ct.volume import CTVolume

    hu = np.zeros((12, 12, 12), np.float32)
    affine = np.diag([3.0, 3.0, 3.0, 1.0])
    affine[:3, 3] = -16.5
    vol = CTVolume(hu, affine, source="water cube")
    renderer = DRRRenderer(vol, RenderSettings(size=(24, 24)), center_lps=[0, 0, 0])
    T = pose_from_params(np.array([5.0, 3.0, -4.0, 0.0, 0.0, 0.0]), renderer.geometry.sod_mm)
    wire = Distractor(k_wire(300.0, 2.5), tool_pose([1.0, 0.2, 0.1], [-150.0, -30.0, 0.0]))
    plain = renderer.render(T)
    np.testing.assert_array_equal(RendererWithDistractors(renderer, []).render(T), plain)
    wrapped = RendererWithDistractors(renderer, [wire])
    extra = wrapped.field.line_integral(T)
    assert extra.max() > 0.1
    np.testing.assert_allclose(wrapped.render(T), plain + extra, rtol=1e-6, atol=1e-7)
    imager = XRayImager(vol, PhysicsSettings(noise=False), size=(24, 24), center_lps=[0, 0, 0])
    assert imager_with_distractors(imager, []) is imager
    before = imager.render(T)["log"][0]
    after = imager_with_distractors(imager, [wire]).render(T)["log"][0]
    np.testing.assert_array_equal(imager.render(T)["log"][0], before)  # the original is untouched
    chord = wrapped.field.chords(T)[0, 0]
    assert (chord > 0.5).sum() >= 3
    assert np.all(after[chord > 0.5] > before[chord > 0.5] + 0.05)
    np.testing.assert_allclose(after[chord == 0], before[chord == 0], rtol=1e-6)


def test_bad_tools_are_refused_in_one_line():
    assert issubclass(DistractorError, InputError)
    cases = [
        (lambda: screw(0.0), "screw length_mm: must be a positive number"),
        (lambda: k_wire(diameter_mm=-2.0), "k_wire diameter_mm: must be a positive number"),
        (lambda: plate(thickness_mm=float("nan")), "plate thickness_mm"),
        (lambda: k_wire(material="unobtainium"), "material 'unobtainium': not one of air, lung"),
        (lambda: table(density_g_cm3=0.0), "density_g_cm3 of carbon"),
        (lambda: screw(10.0, 4.0, tip_mm=12.0), "screw tip_mm"),
        (lambda: plate(holes=2, hole_diameter_mm=20.0), "plate hole_diameter_mm"),
        (lambda: cable([[0, 0, 0]]), "cable path_mm"),
        (lambda: Distractor(k_wire(), frame="world"), "frame"),
        (lambda: Distractor(k_wire(), np.diag([2.0, 1.0, 1.0, 1.0])), "k_wire pose: must be a rigid transform"),
        (lambda: DistractorField(["wire"], GEOM, CENTER), "tools"),
    ]
    for make, message in cases:
        with pytest.raises(DistractorError, match=message) as e:
            make()
        assert "\n" not in str(e.value)


def test_random_tools_are_reproducible_closed_and_in_view():
    from sim.distractors import random_tools

    geom = CArmGeometry(sdd_mm=1020.0, sod_mm=700.0, height=32, width=32, pixel_spacing_mm=9.3)
    kinds = set()
    for seed in range(12):
        tools = random_tools(np.random.default_rng(seed), geom)
        again = random_tools(np.random.default_rng(seed), geom)
        assert [t.mesh.kind for t in tools] == [t.mesh.kind for t in again]
        for t, u in zip(tools, again):
            np.testing.assert_array_equal(t.pose, u.pose)
            topo = topology(t.mesh.vertices, t.mesh.faces)
            assert t.frame == "camera" and topo["boundary_edges"] == 0 and topo["non_two_manifold_edges"] == 0
        kinds |= {t.mesh.kind for t in tools}
        # something of each arrangement is in the view: its chords are not all zero
        c = DistractorField(tools, geom, CENTER).chords(np.eye(4))
        assert c.max() > 0
    assert {"screw", "k_wire", "plate", "retractor", "table"} <= kinds
    with pytest.raises(DistractorError, match="random_tools needs a numpy Generator"):
        random_tools(0, geom)


def test_implanted_tools_are_reproducible_in_their_box_and_move_with_the_patient():
    """implanted_tools: the same seed the same tools; every tool's origin in the box centre +-
    spread; tools in the patient frame, so that their chords at a pose are those of the same
    meshes placed in the camera frame by that pose's extrinsic (the anatomy's own map)."""
    from sim.distractors import implanted_tools
    from sim.projection.geometry import extrinsic_lps_to_camera

    geom = CArmGeometry(sdd_mm=1020.0, sod_mm=700.0, height=32, width=32, pixel_spacing_mm=9.3)
    center, spread = np.array([10.0, -20.0, 150.0]), np.array([80.0, 50.0, 70.0])
    kinds, counts = set(), set()
    for seed in range(10):
        tools = implanted_tools(np.random.default_rng(seed), center, tools=(2, 5))
        again = implanted_tools(np.random.default_rng(seed), center, tools=(2, 5))
        assert [t.mesh.kind for t in tools] == [t.mesh.kind for t in again]
        for t, u in zip(tools, again):
            np.testing.assert_array_equal(t.pose, u.pose)
            assert t.frame == "lps" and np.all(np.abs(t.pose[:3, 3] - center) <= spread)
        kinds |= {t.mesh.kind for t in tools}
        counts.add(len(tools))
    assert kinds == {"screw", "k_wire", "plate", "retractor"} and counts <= {2, 3, 4, 5} and len(counts) >= 3
    T = pose_from_params(np.array([12.0, -7.0, 20.0, 5.0, -10.0, 8.0]), geom.sod_mm)
    E = extrinsic_lps_to_camera(T[None], center)[0]
    in_camera = [Distractor(t.mesh, E @ t.pose, frame="camera") for t in tools]
    got = DistractorField(tools, geom, center).chords(T)
    want = DistractorField(in_camera, geom, center).chords(np.eye(4))
    assert got.max() > 1.0
    np.testing.assert_allclose(got, want, atol=1e-2)  # float32 ray parameters of two placements
    with pytest.raises(DistractorError, match="implanted_tools needs a numpy Generator"):
        implanted_tools(3, center)
    with pytest.raises(DistractorError, match="0 <= low <= high"):
        implanted_tools(np.random.default_rng(0), center, tools=(4, 2))
    with pytest.raises(DistractorError, match="must be finite"):
        implanted_tools(np.random.default_rng(0), [0.0, np.nan, 0.0])


@pytest.mark.parametrize("length, diameter", [(25.0, 4.5), (31.7, 6.1), (57.3, 7.4), (80.0, 5.2)])
def test_screws_of_any_size_are_closed_manifolds(length, diameter):
    # the parts of a screw overlap: coincident rims made some sizes non-manifold before
    topo = topology(*(lambda m: (m.vertices, m.faces))(screw(length, diameter)))
    assert topo["boundary_edges"] == 0 and topo["non_two_manifold_edges"] == 0
