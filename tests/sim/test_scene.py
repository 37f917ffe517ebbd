"""C-arm scene files: the geometry they declare, and the Mitsuba sensor derived from it."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from scenes import SCENE_DIR, available
from sim.projection.scene import SceneError, load_mitsuba_scene, load_scene, sensor_values


def test_cios_fusion_geometry_is_as_documented():
    scene = load_scene("cios_fusion")
    g = scene.geometry
    assert (g.sdd_mm, g.height, g.width, g.pixel_spacing_mm) == (1020.0, 1536, 1536, 0.194)
    assert 0 < g.sod_mm < g.sdd_mm
    assert "cios_fusion" in available()


def test_the_file_renders_on_its_own_in_plain_mitsuba():
    """The file's own Mitsuba defaults equal the values ctxreg derives from its geometry."""
    scene = load_scene("cios_fusion")
    defaults = {el.get("name"): el.get("value") for el in ET.parse(scene.path).getroot().iter("default")}
    derived = sensor_values(scene.geometry)
    assert int(defaults["width"]) == derived["width"] and int(defaults["height"]) == derived["height"]
    assert float(defaults["fov"]) == pytest.approx(derived["fov"], abs=1e-4)
    # independent: the detector's half-width seen from the focal spot
    assert derived["fov"] == pytest.approx(math.degrees(2 * math.atan(1536 * 0.194 / 2 / 1020)), abs=1e-9)


def test_mitsuba_sensor_rays_hit_the_pixel_centres():
    """Mitsuba's ray through film position ((j+.5)/W, (i+.5)/H) points at ((j-cx)s, (i-cy)s, SDD)."""
    import drjit as dr
    import mitsuba as mi

    scene = load_scene("cios_fusion")
    g = scene.geometry_at(64, 64)
    ms = load_mitsuba_scene(scene, g)
    sensor = ms.sensors()[0]
    i = np.array([0, 10, 63, 31])
    j = np.array([0, 50, 63, 32])
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((j + 0.5) / 64, (i + 0.5) / 64), mi.Point2f(0.5, 0.5))
    d = np.array(dr.detach(ray.d)).T  # Mitsuba world = camera frame (to_world flips x and y)
    target = np.stack([(j - g.principal_point[0]) * g.pixel_spacing_mm,
                       (i - g.principal_point[1]) * g.pixel_spacing_mm, np.full(4, g.sdd_mm)], -1)
    np.testing.assert_allclose(d, target / np.linalg.norm(target, axis=-1, keepdims=True), atol=2e-7)


def test_bad_scenes_are_named(tmp_path):
    with pytest.raises(SceneError, match="unknown scene 'nope'"):
        load_scene("nope")
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "missing.xml")
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene><default name=")
    with pytest.raises(SceneError, match="not valid XML"):
        load_scene(bad)
    text = (SCENE_DIR / "cios_fusion.xml").read_text()
    no_sdd = tmp_path / "no_sdd.xml"
    no_sdd.write_text(text.replace('name="ctxreg_sdd_mm"', 'name="other"'))
    with pytest.raises(SceneError, match="ctxreg_sdd_mm"):
        load_scene(no_sdd)
    sod = tmp_path / "sod.xml"
    sod.write_text(text.replace('name="ctxreg_sod_mm" value="700.0"', 'name="ctxreg_sod_mm" value="2000"'))
    with pytest.raises(SceneError, match="invalid C-arm geometry"):
        load_scene(sod)
    with pytest.raises(SceneError, match="aspect"):
        load_scene("cios_fusion").geometry_at(100, 50)
