"""Draw docs/figures/conventions.png: the C-arm camera frame, the patient LPS frame in the AP
pose, detector pixel indexing, and the senses of the three pose rotations.

Run from anywhere: ``python docs/figures/make_conventions_figure.py``. The geometry drawn
comes from :mod:`sim.projection.geometry` (``R_AP``, ``pose_from_params``, ``CArmGeometry``), so the figure
follows the code.
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import FancyArrowPatch  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from sim.projection.geometry import R_AP, CArmGeometry, pose_from_params  # noqa: E402

OUT = Path(__file__).resolve().parent / "conventions.png"

CAM = "#1f4e9c"  # camera frame
PAT = "#c0392b"  # patient frame
DET = "#555555"


def to_plot(p_cam: np.ndarray) -> np.ndarray:
    """Camera mm -> plot coordinates (X, Y, Z) = (z, x, y), a cyclic permutation (a proper
    rotation, so handedness is kept). The Y and Z axes are drawn inverted (two reflections, again
    proper, so the drawing stays right-handed) to put camera -y (image up) up on the page."""
    p = np.asarray(p_cam, dtype=float)
    return np.stack([p[..., 2], p[..., 0], p[..., 1]], -1)


def arrow3d(ax, start, vec, color, label, lw=2.0, label_offset=1.12, fontsize=11):
    a = to_plot(start)
    d = to_plot(np.asarray(start) + np.asarray(vec)) - a
    ax.quiver(*a, *d, color=color, lw=lw, arrow_length_ratio=0.18)
    ax.text(*(a + d * label_offset), label, color=color, fontsize=fontsize, fontweight="bold")


def draw_scene(ax, geo: CArmGeometry) -> None:
    sdd, sod = geo.sdd_mm, geo.sod_mm
    h_mm, w_mm = geo.detector_size_mm
    # Detector plane z = SDD.
    xs = np.array([-w_mm / 2, w_mm / 2, w_mm / 2, -w_mm / 2, -w_mm / 2])
    ys = np.array([-h_mm / 2, -h_mm / 2, h_mm / 2, h_mm / 2, -h_mm / 2])
    corners = np.stack([xs, ys, np.full(5, sdd)], -1)
    ax.plot(*to_plot(corners).T, color=DET, lw=1.5)
    ax.add_collection3d(Poly3DCollection([to_plot(corners[:4])], facecolor="#dddddd", alpha=0.5, edgecolor=DET))
    # X-ray cone to the detector corners.
    for c in corners[:4]:
        ax.plot(*to_plot(np.stack([np.zeros(3), c])).T, color="#e0a800", lw=0.8, alpha=0.8)
    # Principal ray.
    ax.plot(*to_plot(np.array([[0, 0, 0], [0, 0, sdd]])).T, color="#e0a800", lw=1.2, ls="--")
    # Source.
    ax.scatter(*to_plot(np.zeros(3)), color="k", s=40)
    ax.text(*to_plot(np.array([0, -30.0, -40.0])), "source\n(focal spot)", fontsize=9, ha="right")
    # Camera axes at the source.
    L = 180.0
    arrow3d(ax, np.zeros(3), [L, 0, 0], CAM, "$x_c$")
    arrow3d(ax, np.zeros(3), [0, L, 0], CAM, "$y_c$")
    arrow3d(ax, np.zeros(3), [0, 0, 1.6 * L], CAM, "$z_c$")
    # Pixel (0, 0) and the u (column) / v (row) directions on the detector.
    p00 = np.array([-w_mm / 2 + 8, -h_mm / 2 + 8, sdd])
    ax.scatter(*to_plot(p00), color=DET, s=18)
    ax.text(*to_plot(p00 + [0, -28, 0]), "pixel (0, 0)", fontsize=9, color=DET, ha="right")
    arrow3d(ax, p00, [140, 0, 0], DET, "u (column j)", lw=1.5, fontsize=9, label_offset=1.08)
    arrow3d(ax, p00, [0, 140, 0], DET, "v (row i)", lw=1.5, fontsize=9, label_offset=1.12)
    ax.text(*to_plot(np.array([w_mm / 2, h_mm / 2 + 30, sdd])), "detector\n(z = SDD)", fontsize=9, color=DET, ha="left", va="top")
    # Patient LPS axes at the isocentre in the AP pose: columns of R_AP in the camera frame.
    T = pose_from_params(np.zeros(6), sod)
    iso = T[:3, 3]
    ax.scatter(*to_plot(iso), color=PAT, s=25)
    ax.text(*to_plot(iso + [0, 40, -20]), "isocentre =\nanatomy centre c", fontsize=9, color=PAT, ha="right", va="top")
    for k, name in enumerate(["L", "P", "S"]):
        arrow3d(ax, iso, 150.0 * R_AP[:, k], PAT, name, fontsize=12)
    # The patient as an elliptic cylinder along S (half-width 170 mm along L, 110 mm along P).
    s_axis = np.linspace(-200.0, 200.0, 2)
    ang = np.linspace(0, 2 * np.pi, 40)
    for s in s_axis:
        ring_lps = np.stack([170 * np.cos(ang), 110 * np.sin(ang), np.full_like(ang, s)], -1)
        ax.plot(*to_plot(ring_lps @ R_AP.T + iso).T, color=PAT, lw=0.6, alpha=0.45)
    for a in ang[::5]:
        seg = np.stack([[170 * np.cos(a), 110 * np.sin(a), s_axis[0]], [170 * np.cos(a), 110 * np.sin(a), s_axis[1]]])
        ax.plot(*to_plot(seg @ R_AP.T + iso).T, color=PAT, lw=0.4, alpha=0.3)
    # Distances along the principal ray.
    for z, txt in ((sod, f"SOD = {sod:g} mm"), (sdd, f"SDD = {sdd:g} mm")):
        y0 = 270.0 if z == sdd else 230.0
        ax.plot(*to_plot(np.array([[0, y0, 0], [0, y0, z]])).T, color="k", lw=0.8)
        for zz in (0.0, z):
            ax.plot(*to_plot(np.array([[0, y0 - 15, zz], [0, y0 + 15, zz]])).T, color="k", lw=0.8)
        ax.text(*to_plot(np.array([0, y0 + 12 if z == sdd else y0 - 12, z / 2])), txt, fontsize=9,
                ha="center", va="top" if z == sdd else "bottom")
    ax.set_axis_off()
    ax.set_xlim(-120, sdd + 50)
    ax.set_ylim(300, -300)  # inverted: see to_plot
    ax.set_zlim(300, -300)
    ax.set_box_aspect((sdd + 170, 600, 600), zoom=1.25)
    ax.view_init(elev=14, azim=-118)


def draw_pixels(ax) -> None:
    H, W = 4, 6
    geo = CArmGeometry(sdd_mm=1020.0, sod_mm=700.0, height=H, width=W, pixel_spacing_mm=1.0)
    cx, cy = geo.principal_point
    for i in range(H + 1):
        ax.plot([-0.5, W - 0.5], [i - 0.5, i - 0.5], color="#999999", lw=0.8)
    for j in range(W + 1):
        ax.plot([j - 0.5, j - 0.5], [-0.5, H - 0.5], color="#999999", lw=0.8)
    for i in range(H):
        for j in range(W):
            ax.plot(j, i, ".", color=DET, ms=4)
            ax.text(j, i + 0.22, f"({i},{j})", ha="center", va="center", fontsize=7, color=DET)
    ax.plot(cx, cy, "x", color=CAM, ms=10, mew=2)
    ax.annotate(
        "principal point\n(cx, cy) = ((W-1)/2, (H-1)/2)",
        (cx, cy),
        (cx + 0.2, cy + 2.6),
        fontsize=8,
        color=CAM,
        arrowprops=dict(arrowstyle="->", color=CAM),
    )
    ax.annotate("", (2.0, -0.95), (-0.5, -0.95), arrowprops=dict(arrowstyle="->", color=CAM, lw=1.8))
    ax.text(2.1, -0.95, "u = column j, +x_c", va="center", fontsize=9, color=CAM)
    ax.annotate("", (-0.95, 1.8), (-0.95, -0.5), arrowprops=dict(arrowstyle="->", color=CAM, lw=1.8))
    ax.text(-0.95, 1.95, "v = row i\n+y_c", ha="center", va="top", fontsize=9, color=CAM)
    ax.set_xlim(-1.5, W)
    ax.set_ylim(H + 1.0, -1.4)  # rows grow downward, as in an image
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(
        "Detector seen from the source (H = 4, W = 6)\n"
        "centre of pixel (i, j): x = (j - cx) s, y = (i - cy) s, z = SDD",
        fontsize=10,
    )


def draw_rotation(ax, title, right, up, out, note) -> None:
    """A rotation seen from its positive axis (pointing out of the page): CCW from right to up."""
    for vec, name in ((np.array([1.0, 0.0]), right), (np.array([0.0, 1.0]), up)):
        ax.annotate("", vec * 1.0, (0, 0), arrowprops=dict(arrowstyle="-|>", color=PAT, lw=2))
        ax.text(*(vec * 1.22), name, color=PAT, fontsize=13, ha="center", va="center", fontweight="bold")
    ax.plot(0, 0, "o", ms=14, mfc="white", mec=PAT, mew=2)
    ax.plot(0, 0, "o", ms=3, color=PAT)
    ax.text(-0.12, -0.2, f"{out} (toward you)", color=PAT, fontsize=9, ha="right")
    arc = FancyArrowPatch(
        (0.72, 0.0),
        (0.0, 0.72),
        connectionstyle="arc3,rad=0.42",
        arrowstyle="-|>",
        mutation_scale=18,
        color="k",
        lw=1.6,
    )
    ax.add_patch(arc)
    ax.text(0.62, 0.62, "+", fontsize=16, ha="center", va="center")
    ax.text(-0.5, -0.38, note, fontsize=9, ha="left", va="top")
    ax.set_xlim(-0.6, 1.5)
    ax.set_ylim(-0.85, 1.3)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(title, fontsize=10)


def main() -> None:
    geo = CArmGeometry(sdd_mm=1020.0, sod_mm=700.0, height=512, width=512, pixel_spacing_mm=0.6)
    fig = plt.figure(figsize=(16, 10.5))
    gs = fig.add_gridspec(2, 3, height_ratios=[1.5, 1.0], hspace=0.05, wspace=0.05)
    ax3d = fig.add_axes([0.0, 0.38, 0.66, 0.6], projection="3d")
    fig.text(0.3, 0.93, "AP pose (all parameters 0): source anterior, detector posterior;\n"
             "camera frame (blue) at the source, patient LPS axes (red) at the isocentre",
             ha="center", fontsize=11)
    draw_scene(ax3d, geo)
    draw_pixels(fig.add_subplot(gs[0, 2]))
    draw_rotation(
        fig.add_subplot(gs[1, 0]),
        "phi > 0: about S (LPS +z), seen from the head\nRz(90): L -> P",
        "L (+x)",
        "P (+y)",
        "S",
        "At AP: S is image up (-y_c), so phi turns\nthe patient about the image's vertical axis;\n"
        "the left side moves toward the detector.",
    )
    draw_rotation(
        fig.add_subplot(gs[1, 1]),
        "theta > 0: about L (LPS +x), seen from patient left\nRx(90): P -> S",
        "P (+y)",
        "S (+z)",
        "L",
        "At AP: L is image right (+x_c): theta tilts\nthe patient about the image's horizontal axis;\n"
        "the head moves toward the source.",
    )
    draw_rotation(
        fig.add_subplot(gs[1, 2]),
        "psi > 0: about P (LPS +y), seen from behind\nRy(90): S -> L",
        "S (+z)",
        "L (+x)",
        "P",
        "At AP: P is the beam direction (+z_c): psi is\nthe in-plane rotation; the head moves to image\n"
        "right (clockwise on screen).",
    )
    fig.suptitle(
        "ctxreg conventions:  X_cam = R (X_lps - c) + t,   R = R_AP Rz(phi) Rx(theta) Ry(psi),   "
        "t = (tx, ty, SOD + tz)",
        fontsize=13,
    )
    fig.savefig(OUT, dpi=110, bbox_inches="tight")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
