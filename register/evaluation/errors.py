"""A registered pose's errors against the true pose: rotation, translation, mTRE and mPD.

:func:`pose_errors` is the one function every command and study scores with; :func:`bone_points`
gives the bone points the mTRE places.
"""

from __future__ import annotations

import numpy as np

from sim.ct.anatomy import bone_mask
from sim.projection.geometry import CArmGeometry, project_points, projection_matrix
from sim.projection.se3 import rotation_error_deg, translation_error_mm

__all__ = ["pose_errors", "bone_points"]


def pose_errors(T_est: np.ndarray, T_true: np.ndarray, points_lps: np.ndarray, center_lps: np.ndarray,
                geometry=None, *legacy, projection_est: np.ndarray | None = None) -> dict:
    """The pose errors of one estimate, the one function every command and study scores with.

    * ``rot_err_deg``: the geodesic angle of ``R_est^T R_true`` (deg);
    * ``trans_err_mm``: ``|t_est - t_true|``, the anatomy centre's displacement (mm);
    * ``depth_err_mm``: its component along the camera's axis (source to detector),
      ``|t_est[2] - t_true[2]|`` (mm): what a single view reads from the magnification alone
      (the rest, ``sqrt(trans^2 - depth^2)``, lies across the beam);
    * ``mtre_mm``: the mean 3-D distance between ``points_lps`` (``(N, 3)`` LPS mm, e.g.
      :func:`bone_points`) placed by the two poses (mm);
    * ``mpd_mm``: the mean distance between their projections on the detector, both through
      ``geometry`` (a :class:`sim.projection.geometry.CArmGeometry`: ``K [R | t - R c]`` of each pose), in mm
      at the detector plane (pixels x the pixel spacing); points without an image are left out.

    ``projection_est``: the estimate's own ``(3, 4)`` projection where a method reports one (None:
    from ``geometry``, the usual case; the truth's is always ``geometry``'s). The older form
    ``pose_errors(T_est, T_true, points, centre, P_est, P_true, pixel_spacing_mm)`` still works
    (scripts); it is the same arithmetic.
    """
    if isinstance(geometry, CArmGeometry) and not legacy:
        P_est = projection_matrix(geometry, T_est, center_lps) if projection_est is None else projection_est
        P_true = projection_matrix(geometry, T_true, center_lps)
        spacing = geometry.pixel_spacing_mm
    elif len(legacy) == 2 and geometry is not None:
        P_est, (P_true, spacing) = geometry, legacy
    else:
        raise TypeError("pose_errors(T_est, T_true, points_lps, center_lps, geometry): geometry is a CArmGeometry")
    x = np.asarray(points_lps, float) - center_lps
    cam_est = x @ T_est[:3, :3].T + T_est[:3, 3]
    cam_true = x @ T_true[:3, :3].T + T_true[:3, 3]
    uv_est = project_points(P_est, points_lps)
    uv_true = project_points(P_true, points_lps)
    distances = np.linalg.norm(uv_est - uv_true, axis=1)
    distances = distances[np.isfinite(distances)]
    return {
        "rot_err_deg": float(rotation_error_deg(T_est, T_true)),
        "trans_err_mm": float(translation_error_mm(T_est, T_true)),
        "depth_err_mm": float(abs(np.asarray(T_est, float)[2, 3] - np.asarray(T_true, float)[2, 3])),
        "mtre_mm": float(np.linalg.norm(cam_est - cam_true, axis=1).mean()),
        "mpd_mm": float(distances.mean() * spacing) if distances.size else float("nan"),
    }


def bone_points(volume, max_points: int, seed: int = 0) -> np.ndarray:
    """``(N, 3)`` LPS mm voxel centres of the bone mask (a seeded subset of at most ``max_points``)."""
    ijk = np.argwhere(bone_mask(volume))
    if len(ijk) > max_points:
        ijk = ijk[np.random.default_rng(seed).choice(len(ijk), max_points, replace=False)]
    return volume.voxel_to_lps(ijk.astype(np.float64))
