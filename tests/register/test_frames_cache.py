"""The benchmarks' frame cache (:meth:`register.evaluation.frames.FrameSimulator.cached`): a cached
frame is reused only when it was made by the same simulator, settings, pose and seed."""

from __future__ import annotations

import numpy as np

from register.evaluation.frames import FrameSimulator
from register.xray.io import load_xray
from sim.projection.geometry import pose_from_params
from sim.ct.phantom import make_pelvis_phantom
from sim.physics.display import DisplayChain
from sim.physics.imaging import PhysicsSettings, XRayImager


def _frames(kvp: float) -> FrameSimulator:
    vol = make_pelvis_phantom(0)
    imager = XRayImager(vol, PhysicsSettings(level="poly", kvp=kvp, mas=0.5), size=(24, 24), center_lps=[0, 0, 0])
    return FrameSimulator(imager, DisplayChain(polarity="bone-bright", bits=12, shutter="none"))


def test_a_cached_frame_is_made_again_when_its_settings_change(tmp_path):
    a = _frames(70.0)
    pose = pose_from_params(np.zeros(6), a.imager.geometry.sod_mm)
    path = tmp_path / "case_000.dcm"
    a.cached(path, pose, 3)
    first = load_xray(path).pixels.copy()
    stamp = (tmp_path / "case_000.dcm.sim").read_text().strip()
    assert len(stamp) == 64

    # the same frame: not rendered again (a file changed by hand survives, the stamp matching)
    path.write_bytes(path.read_bytes())
    mtime = path.stat().st_mtime_ns
    a.cached(path, pose, 3)
    assert path.stat().st_mtime_ns == mtime

    # another tube voltage, seed or pose: another fingerprint, the frame made again
    b = _frames(110.0)
    assert b.fingerprint(pose, 3) != stamp
    assert a.fingerprint(pose, 4) != stamp
    moved = pose.copy()
    moved[0, 3] += 1.0
    assert a.fingerprint(moved, 3) != stamp
    b.cached(path, pose, 3)
    assert (tmp_path / "case_000.dcm.sim").read_text().strip() == b.fingerprint(pose, 3)
    assert not np.array_equal(load_xray(path).pixels, first)

    # a frame without its stamp (cached before stamps existed) is made again
    (tmp_path / "case_000.dcm.sim").unlink()
    a.cached(path, pose, 3)
    np.testing.assert_array_equal(load_xray(path).pixels, first)


def test_frames_with_tools_darken_where_the_tools_lie_and_draw_them_from_the_seed():
    """tools = (low, high): each frame shows metal tools fixed to the patient, drawn from its seed
    (the same seed the same tools, another seed others). Their attenuation only removes photons
    (poly, no noise): the detector signal is below the frame without tools exactly where the
    tools' chords are, and unchanged elsewhere; the fingerprint names the tools."""
    from sim.distractors import DistractorField

    vol = make_pelvis_phantom(0)
    imager = XRayImager(vol, PhysicsSettings(level="poly", kvp=70.0, noise=False), size=(24, 24), center_lps=[0, 0, 0])
    plain = FrameSimulator(imager, DisplayChain(polarity="bone-bright", bits=12, shutter="none"))
    tooled = FrameSimulator(plain.imager, plain.chain, tools=(3, 5))
    assert tooled.implants(4) and [t.mesh.kind for t in tooled.implants(4)] == [t.mesh.kind for t in tooled.implants(4)]
    first = [t.pose for t in tooled.implants(4)]
    assert not all(np.array_equal(a, b) for a, b in zip(first, [t.pose for t in tooled.implants(5)]))
    assert plain.implants(4) == []
    pose = pose_from_params(np.array([0.0, 0.0, 0.0, 5.0, 0.0, 0.0]), plain.imager.geometry.sod_mm)
    seed = next(s for s in range(20)
                if DistractorField(tooled.implants(s), plain.imager.geometry, [0, 0, 0]).chords(pose).max() > 2.0)
    chords = DistractorField(tooled.implants(seed), plain.imager.geometry, [0, 0, 0]).chords(pose)[0].sum(0)
    without, with_tools = plain.raw(pose, seed), tooled.raw(pose, seed)
    inside, outside = chords > 2.0, chords == 0
    assert inside.any() and outside.any()
    assert np.all(with_tools[inside] < 0.9 * without[inside])  # 2 mm of titanium or steel: > 10 % fewer photons
    np.testing.assert_allclose(with_tools[outside], without[outside], rtol=1e-5)
    assert tooled.fingerprint(pose, seed) != plain.fingerprint(pose, seed)
