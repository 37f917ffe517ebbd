"""The DRR renderer: digitally reconstructed radiographs of a CT at many C-arm poses, batched.

:class:`DRRRenderer` loads a C-arm scene (:mod:`sim.projection.scene`) into Mitsuba, uploads the CT once
to the ``ctxreg_drr`` integrator (:mod:`sim.projection.integrators.drr`) and renders any number of poses,
one batch per kernel launch; later calls reuse the uploaded volume and the compiled kernel.

Poses follow ``docs/conventions.md``: ``T = (R, t)`` with ``X_cam = R (X_lps - c) + t`` for the
anatomy centre ``c`` (LPS mm); :func:`sim.projection.geometry.pose_from_params` builds ``T`` from
(phi, theta, psi) degrees and (tx, ty, tz) mm.

Quantities (``quantity=``):

``line-integral``  the line integral of mu (dimensionless), mu = mu_water (1 + HU/1000) >= 0.
``intensity``      ``i0 * exp(-line integral)``.
``density``        per-material density line integrals in g/cm^2, shape ``(B, M, H, W)``, for the
                   materials of a :class:`sim.physics.materials.MaterialDecomposition`.

:func:`check_in_view` refuses a pose at which the CT is not in the view. One image of a CT at any
physics level, the renderer chosen for it, is :mod:`sim.render`.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from sim.core.errors import InputError
from sim.projection.geometry import CArmGeometry, extrinsic_lps_to_camera, pose_from_params, projection_matrix
from sim.physics.materials import MU_WATER_60KEV_PER_MM, MaterialDecomposition, mu_from_hu
from sim.projection.scene import DEFAULT_SCENE, CArmScene, load_mitsuba_scene, load_scene
from sim.core.cliargs import Range
from sim.ct.volume import CTVolume

QUANTITIES = ("line-integral", "intensity", "density")
RAY_MODELS = ("siddon", "trilinear")
#: The volume's storage in the integrator (:mod:`sim.projection.integrators.drr`): ``fixed16`` packs the two
#: materials of a two-material density render into one 16+16-bit word per voxel.
STORAGES = ("float32", "fixed16")

#: The trilinear step as a fraction of the smallest voxel spacing. The midpoint rule's error
#: falls as the step squared: at 0.05 it is 1.5e-5 of the image's largest value on the phantom
#: (float32 accumulation is of that order), while the time grows as 1 / step (0.05 takes 6x as
#: long as 0.5); a smaller step buys nothing and a tiny one would never finish.
STEP_FRACTION = Range(0.05, 1.0)

#: Largest number of rays traced in one kernel launch; bigger batches are split (memory bound:
#: about 100 bytes of loop state per ray).
MAX_RAYS_PER_LAUNCH = 1 << 23

_FLIP_XY = np.diag([-1.0, -1.0, 1.0, 1.0])


def camera_from_sensor(sensor) -> np.ndarray:
    """``(4, 4)`` map from Mitsuba's world frame to ctxreg's camera frame for a scene's sensor
    (Mitsuba's sensor-local x and y point against the image's columns and rows)."""
    to_world = np.array(sensor.world_transform().matrix, dtype=np.float64).reshape(4, 4)
    return _FLIP_XY @ np.linalg.inv(to_world)


class RenderError(InputError):
    """Invalid render settings or poses; the message names the setting and the problem."""


@dataclass(frozen=True)
class RenderSettings:
    """What to render and how. Units: mm, 1/mm.

    Attributes:
        scene: shipped scene name or path to a scene XML.
        size: ``(rows, cols)`` of the rendered image; None = the detector's full size. Must keep
            the detector's aspect (square pixels).
        ray_model: ``"siddon"`` (exact voxel traversal) or ``"trilinear"``.
        step_fraction: trilinear step as a fraction of the smallest voxel spacing, in
            :data:`STEP_FRACTION` ([0.05, 1]).
        quantity: ``"line-integral"``, ``"intensity"`` or ``"density"``.
        mu_water_per_mm: attenuation of water (1/mm) for the mu quantities.
        i0: unattenuated intensity for ``intensity``.
        storage: ``"float32"`` (default) or ``"fixed16"``: two materials of a ``density`` render
            as 16-bit fixed point in one word, one gather per voxel step for both (about 1.8x
            faster; each voxel within half a code of its value, :mod:`sim.projection.integrators.drr`).
        coarsen: render from a coarser copy of the CT where its voxels are finer than the image
            resolves (:func:`coarsening`): each axis is averaged over 2, 4, ... voxels while its
            spacing stays at most half the pixel's footprint at the isocentre (pixel pitch x SOD
            / SDD). Fewer voxel steps for nearly the same image (a 512 x 512 x 133 chest CT at
            0.7 mm: 64 x 64 images from 1.4 mm voxels, tested in ``tests/sim/test_drr_volumes.py``).
            Default False: the CT's own voxels.
    """

    scene: str = DEFAULT_SCENE
    size: tuple[int, int] | None = (256, 256)
    ray_model: str = "siddon"
    step_fraction: float = 0.5
    quantity: str = "line-integral"
    mu_water_per_mm: float = MU_WATER_60KEV_PER_MM
    i0: float = 1.0
    storage: str = "float32"
    coarsen: bool = False

    def __post_init__(self) -> None:
        if self.ray_model not in RAY_MODELS:
            raise RenderError(f"ray_model must be one of {RAY_MODELS}, got {self.ray_model!r}")
        if self.quantity not in QUANTITIES:
            raise RenderError(f"quantity must be one of {QUANTITIES}, got {self.quantity!r}")
        if self.storage not in STORAGES:
            raise RenderError(f"storage must be one of {STORAGES}, got {self.storage!r}")
        if self.storage == "fixed16" and self.quantity != "density":
            raise RenderError(f"storage 'fixed16' packs two materials of a density render, not {self.quantity!r}")
        if not (np.isfinite(self.step_fraction) and self.step_fraction in STEP_FRACTION):
            raise RenderError(f"step_fraction must be {STEP_FRACTION} (a fraction of the smallest voxel "
                              f"spacing), got {self.step_fraction}")
        if not (np.isfinite(self.mu_water_per_mm) and self.mu_water_per_mm > 0):
            raise RenderError(f"mu_water must be a positive number in 1/mm, got {self.mu_water_per_mm}")
        if not (np.isfinite(self.i0) and self.i0 > 0):
            raise RenderError(f"i0 must be positive, got {self.i0}")
        if self.size is not None:
            if len(self.size) != 2 or min(int(s) for s in self.size) < 1:
                raise RenderError(f"size must be (rows, cols) of positive integers, got {self.size}")


def memory_order(affine: np.ndarray) -> tuple[int, int, int]:
    """Index axes from slowest to fastest in memory for a CT with this ``(4, 4)`` affine.

    C-arm views are near AP/lateral with the patient's S axis along the detector columns, so
    the rays of one SIMD packet (neighbouring pixels of a row) lie along the patient's L axis
    (AP) or P axis (lateral). The volume axis most aligned with L is stored fastest, the one
    most aligned with S next: a packet's gathers then share cache lines (about 1.8x faster on
    a 512 x 512 x 133 CT at AP than the file's own order).
    """
    dirs = np.abs(affine[:3, :3] / np.linalg.norm(affine[:3, :3], axis=0))  # [lps_axis, index_axis]
    fastest = int(np.argmax(dirs[0]))
    rest = [a for a in range(3) if a != fastest]
    middle = max(rest, key=lambda a: dirs[2, a])
    slowest = next(a for a in rest if a != middle)
    return (slowest, middle, fastest)


#: Each CT's uploaded volumes (:class:`sim.projection.integrators.drr.StoredVolume`), by what they hold:
#: every renderer of one :class:`CTVolume` in a process shares one upload per quantity and storage
#: (a registration builds several renderers; a 512 x 512 x 133 CT takes about 1 s to upload).
#: Dropped with the CTVolume. A CTVolume's arrays are not to be changed in place once rendered.
_UPLOADS: "weakref.WeakKeyDictionary[CTVolume, dict]" = weakref.WeakKeyDictionary()


def shared_upload(volume: CTVolume, what: tuple, storage: str, channels, factors=(1, 1, 1)):
    """The volume of ``volume`` holding ``what`` (``("mu", mu_water_per_mm)`` or ``("density",
    materials)``) in ``storage``, averaged over ``factors`` voxels per axis (:func:`coarsened`),
    uploaded once per process: ``channels()`` gives the full ``(C, I, J, K)`` array on the first call."""
    from sim.projection.integrators.drr import store_volume  # loads Dr.Jit, Mitsuba, SciPy: imported where first needed (start-up)

    factors = tuple(int(f) for f in factors)
    key = (what, storage, factors)
    per_volume = _UPLOADS.setdefault(volume, {})
    if key not in per_volume:
        data = channels()
        if factors != (1, 1, 1):
            data = coarsened(data, factors)
        per_volume[key] = store_volume(data, volume.spacing_mm * np.asarray(factors), storage=storage,
                                       memory_order=memory_order(volume.affine))
    return per_volume[key]


#: Coarse voxels are at most this fraction of the pixel's footprint at the isocentre
#: (:func:`coarsening`). Measured on the 512 x 512 x 133 chest CT (0.7 x 0.7 x 2.5 mm) at 8 poses:
#: 64 px from 1.4 mm voxels 0.4 % (rel. L2) off its own voxels' image, 32 px from 2.8 mm 1.0 %.
COARSE_VOXEL_PER_FOOTPRINT = 0.5


def coarsening(volume: CTVolume, geometry: CArmGeometry) -> tuple[int, int, int]:
    """Per-axis averaging factors (powers of two) for images of ``geometry``: the largest with
    ``spacing x factor`` at most :data:`COARSE_VOXEL_PER_FOOTPRINT` times the pixel's footprint
    at the isocentre, ``pixel_spacing_mm x sod_mm / sdd_mm`` (an axis already coarser keeps 1)."""
    limit = COARSE_VOXEL_PER_FOOTPRINT * geometry.pixel_spacing_mm * geometry.sod_mm / geometry.sdd_mm
    factors = []
    for spacing in volume.spacing_mm:
        f = 1
        while spacing * f * 2 <= limit * (1 + 1e-9):
            f *= 2
        factors.append(f)
    return tuple(factors)


def coarsened(channels: np.ndarray, factors) -> np.ndarray:
    """``(C, I, J, K)`` channels averaged over blocks of ``factors`` voxels per axis ->
    ``(C, ceil(I / fi), ceil(J / fj), ceil(K / fk))``; the last block of an axis that does not
    divide is completed with zeros (outside the CT). Line integrals through the coarse voxels
    keep the mass of the fine ones (the mean times the block's size)."""
    c = np.asarray(channels, np.float32)
    f = tuple(int(x) for x in factors)
    out_shape = tuple(-(-n // k) for n, k in zip(c.shape[1:], f))
    padded = np.zeros((c.shape[0],) + tuple(n * k for n, k in zip(out_shape, f)), np.float32)
    padded[:, :c.shape[1], :c.shape[2], :c.shape[3]] = c
    blocks = padded.reshape(c.shape[0], out_shape[0], f[0], out_shape[1], f[1], out_shape[2], f[2])
    return blocks.mean(axis=(2, 4, 6), dtype=np.float64).astype(np.float32)


def coarse_affine(affine: np.ndarray, factors) -> np.ndarray:
    """The ``(4, 4)`` index-to-LPS affine of the grid :func:`coarsened` makes: coarse voxel ``n``
    covers fine voxels ``n f .. n f + f - 1``; its centre is their centres' mean."""
    f = np.asarray(factors, np.float64)
    scale = np.eye(4)
    scale[:3, :3] = np.diag(f)
    scale[:3, 3] = (f - 1.0) / 2.0
    return np.asarray(affine, np.float64) @ scale


class DRRRenderer:
    """Renders DRRs of one CT; the volume is uploaded once, the kernel compiled once.

    Args:
        volume: the CT.
        settings: :class:`RenderSettings`.
        center_lps: ``(3,)`` anatomy centre c in LPS mm; None = :func:`sim.ct.anatomy.anatomy_center`.
        materials: the decomposition for ``quantity="density"`` (default
            :class:`MaterialDecomposition()`).
        geometry: a :class:`CArmGeometry` to use instead of the scene's (e.g. an X-ray's own
            SDD and pixel spacing); its size replaces ``settings.size``. The scene file still
            provides the Mitsuba sensor and integrator.
    """

    def __init__(self, volume: CTVolume, settings: RenderSettings | None = None, *,
                 center_lps=None, materials: MaterialDecomposition | None = None,
                 geometry: CArmGeometry | None = None):
        import mitsuba as mi

        self.settings = settings or RenderSettings()
        self.volume = volume
        self.scene_info: CArmScene = load_scene(self.settings.scene)
        if geometry is not None:
            if not isinstance(geometry, CArmGeometry):
                raise RenderError(f"geometry must be a CArmGeometry, got {type(geometry).__name__}")
            self.geometry: CArmGeometry = geometry
        else:
            rows, cols = self.settings.size if self.settings.size is not None else (None, None)
            self.geometry = self.scene_info.geometry_at(rows, cols)
        if center_lps is None:
            from sim.ct.anatomy import anatomy_center  # loads SciPy: imported where first needed (start-up)

            center_lps = anatomy_center(volume)
        center = np.asarray(center_lps, dtype=np.float64).reshape(-1)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise RenderError(f"anatomy centre must be 3 finite LPS mm values, got {center_lps}")
        self.center_lps = center
        self.materials = materials or MaterialDecomposition()
        self.scene = load_mitsuba_scene(
            self.scene_info, self.geometry, ray_model=self.settings.ray_model,
            step_fraction=self.settings.step_fraction,
        )
        self.integrator = self.scene.integrator()
        self.sensor = self.scene.sensors()[0]
        self._camera_from_world = camera_from_sensor(self.sensor)
        self.factors = coarsening(volume, self.geometry) if self.settings.coarsen else (1, 1, 1)
        self._index_from_lps = np.linalg.inv(coarse_affine(volume.affine, self.factors))
        density = self.settings.quantity == "density"
        self.integrator.use_volume(shared_upload(
            volume, ("density", self.materials) if density else ("mu", self.settings.mu_water_per_mm),
            self.settings.storage, lambda: self._channels(density), self.factors))
        self.channel_names = (
            self.materials.names if self.settings.quantity == "density" else ("mu",)
        )
        self._mi = mi

    def _channels(self, density: bool) -> np.ndarray:
        """The ``(C, I, J, K)`` channels the integrator integrates: densities (g/cm^3) or mu (1/mm)."""
        channels = (self.materials.partial_densities(self.volume.hu) if density
                    else mu_from_hu(self.volume.hu, self.settings.mu_water_per_mm)[None])
        if self.settings.storage == "fixed16" and len(channels) != 2:
            raise RenderError(f"storage 'fixed16' packs exactly two materials, this decomposition has "
                              f"{len(channels)}")
        return channels

    # ------------------------------------------------------------ geometry
    def world_to_index(self, poses: np.ndarray) -> np.ndarray:
        """``(B, 4, 4)`` maps from Mitsuba world mm to voxel index coordinates for poses ``(B, 4, 4)``."""
        ext = extrinsic_lps_to_camera(poses, self.center_lps)  # (B, 4, 4) LPS -> camera
        return self._index_from_lps @ np.linalg.inv(ext) @ self._camera_from_world

    def projection_matrix(self, pose: np.ndarray) -> np.ndarray:
        """``(..., 3, 4)`` projection from homogeneous LPS mm to pixels (u=column, v=row)."""
        return projection_matrix(self.geometry, pose, self.center_lps)

    # -------------------------------------------------------------- render
    def render(self, poses: np.ndarray) -> np.ndarray:
        """Render poses.

        Args:
            poses: ``(4, 4)`` or ``(B, 4, 4)`` volume poses T (rotation orthonormal, mm).

        Returns:
            float32 ``(B, H, W)`` for line-integral / intensity, ``(B, M, H, W)`` for density
            (g/cm^2); a single ``(4, 4)`` pose gives ``B = 1``.
        """
        poses = self._check_poses(poses)
        h, w = self.geometry.height, self.geometry.width
        per_launch = max(1, MAX_RAYS_PER_LAUNCH // (h * w))
        out = np.empty((poses.shape[0], len(self.channel_names), h, w), np.float32)
        for start in range(0, poses.shape[0], per_launch):
            batch = poses[start:start + per_launch]
            self.integrator.set_world_to_index(self.world_to_index(batch))
            img = np.array(self.integrator.render(self.scene, self.sensor), copy=False)
            out[start:start + len(batch)] = np.moveaxis(img.reshape(len(batch), h, w, -1), -1, 1)
        q = self.settings.quantity
        if q == "density":
            return out / 10.0  # g/cm^3 x mm -> g/cm^2
        out = out[:, 0]
        if q == "intensity":
            return (self.settings.i0 * np.exp(-out)).astype(np.float32)
        return out

    def render_params(self, params: np.ndarray) -> np.ndarray:
        """Render poses given as ``(6,)`` or ``(B, 6)`` parameters (degrees, mm); see :meth:`render`."""
        params = np.asarray(params, dtype=np.float64)
        if params.shape[-1:] != (6,) or params.ndim > 2 or not np.all(np.isfinite(params)):
            raise RenderError(f"pose parameters must be finite (6,) or (B, 6), got shape {params.shape}")
        return self.render(pose_from_params(params.reshape(-1, 6), self.geometry.sod_mm))

    @staticmethod
    def _check_poses(poses) -> np.ndarray:
        p = np.asarray(poses, dtype=np.float64)
        if p.ndim == 2:
            p = p[None]
        if p.ndim != 3 or p.shape[1:] != (4, 4) or p.shape[0] == 0:
            raise RenderError(f"poses must be (4, 4) or (B, 4, 4) with B >= 1, got shape {np.shape(poses)}")
        if not np.all(np.isfinite(p)):
            raise RenderError("poses contain NaN or infinite values")
        r = p[:, :3, :3]
        err = np.abs(np.swapaxes(r, 1, 2) @ r - np.eye(3)).max()
        if err > 1e-4 or np.any(np.linalg.det(r) < 0) or np.abs(p[:, 3] - (0, 0, 0, 1)).max() > 1e-9:
            raise RenderError(f"poses must be rigid transforms (orthonormal rotation, last row 0 0 0 1); "
                              f"rotation error {err:.2e}")
        return p


def check_in_view(volume: CTVolume, geometry: CArmGeometry, pose: np.ndarray, center_lps, *,
                  what: str = "the pose") -> None:
    """Raise :class:`RenderError` when no ray of the view meets the CT's box at ``pose`` ``(4, 4)``.

    Rays from the source through a 33 x 33 grid spanning the detector (edges included) are
    tested against the box of the voxels (slab test in voxel coordinates, in front of the
    source), and the box's corners are projected: a CT smaller than the grid's gaps still counts
    when a corner falls on the detector. ``what`` names the inputs in the message.
    """
    camera_from_lps = extrinsic_lps_to_camera(np.asarray(pose, np.float64), np.asarray(center_lps, np.float64))
    index_from_camera = np.linalg.inv(volume.affine) @ np.linalg.inv(camera_from_lps)
    s, (cx, cy) = geometry.pixel_spacing_mm, geometry.principal_point
    u = np.linspace(-0.5, geometry.width - 0.5, 33)
    v = np.linspace(-0.5, geometry.height - 0.5, 33)
    uu, vv = np.meshgrid(u, v)
    d_cam = np.stack([(uu - cx) * s, (vv - cy) * s, np.full_like(uu, geometry.sdd_mm)], -1).reshape(-1, 3)
    o = index_from_camera[:3, 3]
    d = d_cam @ index_from_camera[:3, :3].T
    lo, hi = np.full(3, -0.5), np.asarray(volume.shape, np.float64) - 0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    parallel = d == 0  # a ray parallel to a slab: inside it for every t, or never
    inside = (o >= lo) & (o <= hi)
    t_near = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=1)
    t_far = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=1)
    if np.any(t_far > np.maximum(t_near, 0.0)):
        return
    cam = np.c_[volume.corners_lps(), np.ones(8)] @ camera_from_lps.T  # (8, 4)
    front = cam[:, 2] > 0
    if front.any():
        col = cam[front, 0] / cam[front, 2] * geometry.sdd_mm / s + cx
        row = cam[front, 1] / cam[front, 2] * geometry.sdd_mm / s + cy
        if np.any((col >= -0.5) & (col <= geometry.width - 0.5) & (row >= -0.5) & (row <= geometry.height - 0.5)):
            return
    raise RenderError(f"the CT is not in the view at {what}: no ray from the source to the detector meets "
                      f"it (check the pose, the anatomy centre and the scene)")
