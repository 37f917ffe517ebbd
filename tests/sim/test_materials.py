"""HU to attenuation and to material densities."""

from __future__ import annotations

import numpy as np
import pytest

from sim.core.errors import InputError
from sim.physics.materials import MU_WATER_60KEV_PER_MM, MaterialDecomposition, MaterialError, mu_from_hu


def test_default_mu_water_is_xraylib_water_at_60_kev():
    xraylib = pytest.importorskip("xraylib")
    # NIST liquid water, total attenuation with coherent scattering, cm^2/g x 1 g/cm^3 -> 1/mm
    expected = xraylib.CS_Total_CP("Water, Liquid", 60.0) * 1.0 / 10.0
    assert MU_WATER_60KEV_PER_MM == pytest.approx(expected, rel=1e-4)


def test_mu_from_hu_is_linear_and_clipped():
    hu = np.array([-1200.0, -1000.0, 0.0, 1000.0])
    np.testing.assert_allclose(mu_from_hu(hu, 0.02), [0.0, 0.0, 0.02, 0.04], rtol=1e-6)
    with pytest.raises(MaterialError, match="mu_water"):
        mu_from_hu(hu, 0.0)


def test_fractions_are_a_smooth_partition_of_unity():
    m = MaterialDecomposition()
    hu = np.linspace(-1500, 3000, 9001)
    f = m.fractions(hu)
    np.testing.assert_allclose(f.sum(0), 1.0, atol=1e-12)
    assert f.min() >= 0.0
    # continuous: no jump larger than the slope over one 0.5 HU step allows
    assert np.abs(np.diff(f, axis=1)).max() < 0.5 / 960 + 1e-12
    # pure at the anchors
    for k, (_, h) in enumerate(m.anchors):
        np.testing.assert_allclose(m.fractions(np.array(h))[:, ...], np.eye(len(m.anchors))[k], atol=1e-12)


def test_density_curve_passes_its_knots_and_stays_non_negative():
    m = MaterialDecomposition()
    for h, rho in m.density_points:
        assert m.density(np.array(h)) == pytest.approx(rho)
    assert m.density(np.array(-3000.0)) == 0.0
    assert np.all(np.diff(m.density(np.linspace(-1000, 4000, 100))) > 0)
    np.testing.assert_allclose(m.partial_densities(np.array([0.0, 500.0])).sum(0),
                               m.density(np.array([0.0, 500.0])), rtol=1e-6)


def test_bad_decompositions_are_rejected():
    with pytest.raises(MaterialError, match="increasing"):
        MaterialDecomposition(anchors=(("a", 0.0), ("b", -10.0)))
    with pytest.raises(MaterialError, match="increasing"):
        MaterialDecomposition(density_points=((0.0, 1.0),))
    assert issubclass(MaterialError, InputError)  # a user-facing error: one line from the CLI


def test_one_materials_module_without_dr_jit():
    """The HU decomposition and the materials' cross sections live once, in sim.physics.materials (no
    sim.materials beside it); importing it loads neither Dr.Jit/Mitsuba nor the rest of sim.physics
    (the package's __init__ holds its error type only)."""
    import importlib.util
    import subprocess
    import sys

    from tests.conftest import REPO

    assert importlib.util.find_spec("sim.materials") is None
    code = ("import sys, sim.physics.materials as m; m.TISSUE_DECOMPOSITION.partial_densities(m.np.zeros(3)); "
            "print(sorted(k for k in sys.modules if k.split('.')[0] in ('drjit', 'mitsuba') "
            "or (k.startswith('sim.physics.') and k != 'sim.physics.materials')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "[]", (r.stdout, r.stderr)


def test_material_names_and_label_materials_are_refused_with_what_is_allowed():
    from sim.physics.materials import LabelOverride, mass_attenuation, parse_label_materials

    with pytest.raises(MaterialError, match="unknown material 'steel'; known: air, lung"):
        mass_attenuation("steel", 60.0)
    with pytest.raises(MaterialError, match="integer label > 0"):
        parse_label_materials(["0:titanium"])
    with pytest.raises(MaterialError, match="given twice"):
        parse_label_materials(["3:titanium", "3:cortical_bone"])
    assert parse_label_materials(["3:titanium", " 7 : cortical_bone"]) == {3: "titanium", 7: "cortical_bone"}
    with pytest.raises(MaterialError, match="integers"):
        LabelOverride(np.zeros((2, 2, 2), np.float32), {1: "titanium"})


def test_fractions_and_partial_densities_equal_the_hat_function_definition():
    """The scattered (two channels per voxel) implementation equals the definition, written
    here with full (M, N) arrays: hat weights of the two anchors around each HU, clamped at both
    ends, times the density. Exact equality: the same float64 operations per value."""
    import numpy as np

    from sim.physics.materials import MaterialDecomposition

    m = MaterialDecomposition()
    hu = np.concatenate([np.linspace(-3000.0, 6000.0, 9002), [-1000.0, 0.0, 3071.0, 3.5]]).reshape(3, -1)
    a = np.array([h for _, h in m.anchors])
    pos = np.interp(hu, a, np.arange(len(a), dtype=np.float64))
    lower = np.clip(np.floor(pos), 0, len(a) - 2)
    t = pos - lower
    k = np.arange(len(a)).reshape(-1, 1, 1)
    ref = np.where(k == lower, 1.0 - t, 0.0) + np.where(k == lower + 1, t, 0.0)
    np.testing.assert_array_equal(m.fractions(hu), ref)
    np.testing.assert_array_equal(m.partial_densities(hu), (ref * m.density(hu)[None]).astype(np.float32))
    np.testing.assert_allclose(m.fractions(hu).sum(axis=0), 1.0, rtol=0, atol=1e-12)
