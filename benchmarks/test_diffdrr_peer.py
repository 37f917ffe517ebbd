"""Checks that the DiffDRR adaptor renders true line integrals in ctxreg's camera convention.

The expected values are computed here in NumPy from ctxreg's convention alone (pixel centres
``((j - (W-1)/2) s, (i - (H-1)/2) s, SDD)`` in the camera, ``X_cam = E X_lps``, pinhole
``K = [[SDD/s, 0, (W-1)/2], [0, SDD/s, (H-1)/2], [0, 0, 1]]``), independently of how the adaptor
maps that convention onto DiffDRR's detector.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("diffdrr.drr", reason="DiffDRR 0.6.1 is not installed (optional 'bench' extra)")

try:
    from benchmarks.diffdrr_peer import (
        MU_WATER_PER_MM,
        DiffDRRPeerInputError,
        prepare,
        render,
        render_diffdrr,
    )
except ImportError:  # benchmarks/ is not a package; pytest's rootdir insertion puts it on sys.path
    from diffdrr_peer import (  # type: ignore[no-redef]
        MU_WATER_PER_MM,
        DiffDRRPeerInputError,
        prepare,
        render,
        render_diffdrr,
    )

SDD_MM = 1020.0
H = W = 64
PIXEL_MM = 2.0
RENDERERS = ("siddon", "trilinear")

#: AP view, LPS -> camera: patient left -> +x (image right), posterior -> +z, superior -> -y.
R_AP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _rot(axis: str, deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def _extrinsic(R_cam: np.ndarray, center_lps: np.ndarray, t_cam: np.ndarray) -> np.ndarray:
    """``(4, 4)`` LPS -> camera: ``X_cam = R_cam R_AP (X - c) + (0, 0, 700) + t_cam``."""
    R = R_cam @ R_AP
    E = np.eye(4)
    E[:3, :3] = R
    E[:3, 3] = np.array([0.0, 0.0, 700.0]) + t_cam - R @ center_lps
    return E


def _hu_for_mu(mu_per_mm: float) -> float:
    """HU whose ``mu_water (1 + HU/1000)`` is ``mu_per_mm``."""
    return 1000.0 * (mu_per_mm / MU_WATER_PER_MM - 1.0)


def _pixel_ray_lps(E: np.ndarray, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
    """Source and pixel-centre target of pixel ``(row i, col j)`` in LPS mm."""
    p_cam = np.array([(j - (W - 1) / 2) * PIXEL_MM, (i - (H - 1) / 2) * PIXEL_MM, SDD_MM, 1.0])
    E_inv = np.linalg.inv(E)
    return E_inv[:3, 3], (E_inv @ p_cam)[:3]


def _chord_mm(src: np.ndarray, tgt: np.ndarray, affine: np.ndarray, shape: tuple[int, ...]) -> float:
    """Length in mm of the segment source->target inside the voxel box (slab method in index space)."""
    inv = np.linalg.inv(affine)
    s = inv[:3, :3] @ src + inv[:3, 3]
    d = inv[:3, :3] @ (tgt - src)
    lo, hi = -0.5 * np.ones(3), np.array(shape, dtype=float) - 0.5
    t0, t1 = (lo - s) / d, (hi - s) / d
    enter = max(0.0, float(np.minimum(t0, t1).max()))
    leave = min(1.0, float(np.maximum(t0, t1).min()))
    return max(0.0, leave - enter) * float(np.linalg.norm(tgt - src))


def _peak_centroid(img: np.ndarray) -> tuple[float, float]:
    """Intensity-weighted ``(u, v)`` = (column, row) centroid of the brightest pixel's 3 x 3."""
    i, j = np.unravel_index(int(np.argmax(img)), img.shape)
    assert 1 <= i < img.shape[0] - 1 and 1 <= j < img.shape[1] - 1, "peak on the image border"
    win = img[i - 1 : i + 2, j - 1 : j + 2].astype(np.float64)
    rows, cols = np.mgrid[i - 1 : i + 2, j - 1 : j + 2]
    return float((win * cols).sum() / win.sum()), float((win * rows).sum() / win.sum())


def _project(E: np.ndarray, x_lps: np.ndarray) -> tuple[float, float]:
    K = np.array([[SDD_MM / PIXEL_MM, 0, (W - 1) / 2], [0, SDD_MM / PIXEL_MM, (H - 1) / 2], [0, 0, 1]])
    p = K @ (E[:3, :3] @ x_lps + E[:3, 3])
    return float(p[0] / p[2]), float(p[1] / p[2])


# ---------------------------------------------------------------------------------------------
# (a) Uniform box: the line integral equals mu x the closed-form chord length.
# ---------------------------------------------------------------------------------------------

BOX_SHAPE = (40, 30, 20)
# LPS-like affine as from a RAS NIfTI (first two axes flipped), 2 x 3 x 4 mm, centre off the origin.
BOX_AFFINE = np.array(
    [[-2.0, 0, 0, 39.0 + 4.0], [0, -3.0, 0, 43.5 - 6.0], [0, 0, 4.0, -38.0 + 3.0], [0, 0, 0, 1.0]]
)
BOX_MU = 0.03  # 1/mm


@pytest.mark.parametrize("renderer", RENDERERS)
@pytest.mark.parametrize(
    "R_cam",
    [np.eye(3), _rot("x", 25.0) @ _rot("y", -20.0) @ _rot("z", 30.0)],
    ids=["AP", "oblique"],
)
def test_box_line_integral_equals_mu_times_chord(renderer: str, R_cam: np.ndarray) -> None:
    hu = np.full(BOX_SHAPE, _hu_for_mu(BOX_MU), dtype=np.float32)
    center = BOX_AFFINE[:3, :3] @ ((np.array(BOX_SHAPE) - 1) / 2) + BOX_AFFINE[:3, 3]
    E = _extrinsic(R_cam, center, np.zeros(3))
    img = render_diffdrr(hu, BOX_AFFINE, E, SDD_MM, H, W, PIXEL_MM, renderer=renderer)
    assert img.shape == (H, W) and img.dtype == np.float32
    # Central pixel and two off-centre pixels whose rays still cross the box far from its edges.
    for i, j in [(H // 2, W // 2), (H // 2 - 6, W // 2 + 9), (H // 2 + 8, W // 2 - 5)]:
        chord = _chord_mm(*_pixel_ray_lps(E, i, j), BOX_AFFINE, BOX_SHAPE)
        assert chord > 30.0  # the ray crosses the box well inside (precondition of the check)
        expected = BOX_MU * chord
        # Siddon sums exact segment lengths (float32 rounding only): 1e-4. Trilinear samples
        # DiffDRR's rectangle rule (500 points over the global span) with a half-voxel ramp at
        # each face: 1 %.
        rtol = 1e-4 if renderer == "siddon" else 1e-2
        assert img[i, j] == pytest.approx(expected, rel=rtol), (i, j, img[i, j], expected)


def test_trilinear_step_mm_sets_sampling_and_keeps_units() -> None:
    hu = np.full(BOX_SHAPE, _hu_for_mu(BOX_MU), dtype=np.float32)
    center = BOX_AFFINE[:3, :3] @ ((np.array(BOX_SHAPE) - 1) / 2) + BOX_AFFINE[:3, 3]
    E = _extrinsic(np.eye(3), center, np.zeros(3))
    prep = prepare(hu, BOX_AFFINE, E, SDD_MM, H, W, PIXEL_MM, renderer="trilinear", step_mm=1.0)
    # DiffDRR samples between the smallest entry and largest exit over all rays. Along the AP
    # view every ray crosses the box's 90 mm depth (30 voxels x 3 mm along LPS y), so a 1 mm step
    # needs more than 90 points; no ray spends longer in the box than its diagonal (plus DiffDRR's
    # one-voxel overshoot at the far face), which bounds the count from above.
    diag_mm = float(np.linalg.norm(np.array(BOX_SHAPE) * np.array([2.0, 3.0, 4.0])))
    assert prep.n_points is not None and 90 < prep.n_points <= math.ceil(diag_mm + 4.0) + 1
    img = render(prep)
    chord = _chord_mm(*_pixel_ray_lps(E, H // 2, W // 2), BOX_AFFINE, BOX_SHAPE)
    assert img[H // 2, W // 2] == pytest.approx(BOX_MU * chord, rel=1e-2)


# ---------------------------------------------------------------------------------------------
# (b) A single dense voxel projects where the pinhole model K (E X) says.
# ---------------------------------------------------------------------------------------------

BEAD_SHAPE = (24, 20, 28)
BEAD_SPACING = np.array([1.5, 2.0, 2.5])
BEAD_AFFINE = np.diag([*BEAD_SPACING, 1.0])
BEAD_AFFINE[:3, 3] = [-12.0, 5.0, -30.0]
BEAD_INDEX = (18, 4, 21)

EXTRINSICS = {
    "z25": (_rot("z", 25.0), np.array([12.0, -6.0, 25.0])),
    "x-30": (_rot("x", -30.0), np.array([10.0, 11.0, -40.0])),
    "y20x15": (_rot("y", 20.0) @ _rot("x", 15.0), np.array([5.0, 8.0, 10.0])),
}


@pytest.mark.parametrize("renderer", RENDERERS)
@pytest.mark.parametrize("name", sorted(EXTRINSICS))
def test_bead_projects_to_pinhole_position(renderer: str, name: str) -> None:
    hu = np.full(BEAD_SHAPE, -1000.0, dtype=np.float32)
    hu[BEAD_INDEX] = _hu_for_mu(2.0)
    bead_lps = BEAD_AFFINE[:3, :3] @ np.array(BEAD_INDEX, dtype=float) + BEAD_AFFINE[:3, 3]
    center = BEAD_AFFINE[:3, :3] @ ((np.array(BEAD_SHAPE) - 1) / 2) + BEAD_AFFINE[:3, 3]
    R_cam, t_cam = EXTRINSICS[name]
    E = _extrinsic(R_cam, center, t_cam)
    u, v = _project(E, bead_lps)
    # Precondition: the bead lands inside the image and away from both centre lines, so that a
    # row flip, column flip or transpose would move it by several pixels.
    c = (W - 1) / 2
    assert 3 < u < W - 4 and 3 < v < H - 4 and abs(u - c) > 4 and abs(v - c) > 4 and abs(u - v) > 4
    img = render_diffdrr(hu, BEAD_AFFINE, E, SDD_MM, H, W, PIXEL_MM, renderer=renderer)
    u_img, v_img = _peak_centroid(img)
    # The bead (1.5-2.5 mm at ~1.4x magnification, 2 mm pixels) covers 1-2 pixels; the 3 x 3
    # centroid locates it to a fraction of a pixel, so 1 pixel is a clear margin.
    assert math.hypot(u_img - u, v_img - v) < 1.0, (name, (u_img, v_img), (u, v))


# ---------------------------------------------------------------------------------------------
# (c) Orientation under the AP view.
# ---------------------------------------------------------------------------------------------

E_AP = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 700.0], [0, 0, 0, 1.0]])


@pytest.mark.parametrize("renderer", RENDERERS)
def test_ap_view_patient_left_is_image_right_and_superior_is_up(renderer: str) -> None:
    shape = (31, 31, 31)
    affine = np.diag([2.0, 2.0, 2.0, 1.0])
    affine[:3, 3] = -30.0  # volume centred at the LPS origin
    hu = np.full(shape, -1000.0, dtype=np.float32)
    hu[15 + 12, 15, 15] = _hu_for_mu(2.0)  # +24 mm LPS x: patient left
    hu[15, 15, 15 + 10] = _hu_for_mu(2.0)  # +20 mm LPS z: superior
    img = render_diffdrr(hu, affine, E_AP, SDD_MM, H, W, PIXEL_MM, renderer=renderer)
    c = (W - 1) / 2
    # Left bead: on the central row, right half. Superior bead: on the central column, upper half.
    left = img[int(c) : int(c) + 2, :]
    col_left = int(np.argmax(left.max(axis=0)))
    sup = img[:, int(c) : int(c) + 2]
    row_sup = int(np.argmax(sup.max(axis=1)))
    assert col_left > c + 10, col_left  # 24 mm x 1020/700 / 2 mm = 17.5 px right of centre
    assert row_sup < c - 10, row_sup  # 20 mm x 1020/700 / 2 mm = 14.6 px above centre


# ---------------------------------------------------------------------------------------------
# Input checks at the boundary.
# ---------------------------------------------------------------------------------------------


def test_bad_inputs_raise_named_errors() -> None:
    hu = np.zeros((4, 4, 4), dtype=np.float32)
    A = np.eye(4)
    with pytest.raises(DiffDRRPeerInputError, match="renderer"):
        prepare(hu, A, E_AP, SDD_MM, 8, 8, 1.0, renderer="raymarch")
    with pytest.raises(DiffDRRPeerInputError, match="hu"):
        prepare(hu[:, :, :1], A, E_AP, SDD_MM, 8, 8, 1.0)
    skew = E_AP.copy()
    skew[0, 1] = 0.3
    with pytest.raises(DiffDRRPeerInputError, match="extrinsic_lps_to_cam"):
        prepare(hu, A, skew, SDD_MM, 8, 8, 1.0)
    with pytest.raises(DiffDRRPeerInputError, match="n_points"):
        prepare(hu, A, E_AP, SDD_MM, 8, 8, 1.0, renderer="siddon", n_points=100)
    with pytest.raises(DiffDRRPeerInputError, match="pixel_spacing_mm"):
        prepare(hu, A, E_AP, SDD_MM, 8, 8, -1.0)
