"""``ctxreg_drr``: a Mitsuba 3 integrator that integrates a voxel volume along camera rays.

The volume is a multi-channel voxel grid (for example attenuation mu in 1/mm, or per-material
densities in g/cm^3) placed in the scene by a per-pose affine map from Mitsuba world
coordinates to voxel index coordinates. For every pixel the integrator traces the sensor's ray
through the pixel centre and returns, per channel, the line integral of the volume along the
ray (channel unit x mm). Rays are marched in a single symbolic Dr.Jit loop, so one kernel serves
every pose, image size and CT; a batch of B poses is rendered in one kernel launch.

Ray models:

``siddon`` (default)
    Exact integral of the piecewise-constant voxel function (incremental Siddon / Amanatides-Woo
    traversal): one gather per voxel crossed.
``trilinear``
    Midpoint rule over the trilinear interpolant of the voxel centres, with a step of
    ``step_fraction`` times the smallest voxel spacing (mm), the step shrunk so that a whole
    number of steps spans the ray's chord. Eight gathers per step.

Storage (:meth:`DRRIntegrator.set_volume`, ``storage=``):

``float32`` (default)
    One float per channel and voxel.
``fixed16``
    Exactly two channels, each as 16-bit fixed point, packed in one 32-bit word: one gather per
    voxel step serves both channels (the two-basis density render of training pairs is
    gather-bound: about 1.8x faster on a CPU). Each channel's codes span its range (zero
    included, and exactly representable), so a voxel's value is off by at most half a step,
    ``(max - min) / 65535 / 2``; the error of a line integral is bounded by that times the chord
    (mm) and is in practice far smaller (rounding errors of neighbouring voxels cancel).

Both treat the volume as zero outside the grid: ``siddon`` integrates over the voxel boxes,
``trilinear`` over the interpolant's support (half a voxel further, where it falls to zero).

Plugin parameters (XML / ``props``):

=================  ========  ==========  ================================================
name               type      default     meaning
=================  ========  ==========  ================================================
``ray_model``      string    "siddon"    "siddon" or "trilinear"
``step_fraction``  float     0.5         trilinear step / smallest voxel spacing, in (0, 1]
=================  ========  ==========  ================================================

The volume and poses are not XML properties: :class:`sim.projection.drr.DRRRenderer` sets them with
:meth:`DRRIntegrator.set_volume` and :meth:`DRRIntegrator.set_world_to_index`; they are also
exposed to ``mi.traverse`` as ``volume`` (flat, read-only shape) and ``world_to_index``.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

RAY_MODELS = ("siddon", "trilinear")
STORAGES = ("float32", "fixed16")

#: Opaque scalars (sizes, strides, steps) by type and value, made once per process: each
#: ``dr.opaque`` call materialises its value with a kernel launch of its own (about 30 us on a
#: CPU, 11 of them per render before this cache: a third of a 32 x 32 render's time).
_OPAQUES: dict = {}


def _opaque(tp, value):
    """``dr.opaque(tp, value)``, made once per ``(tp, value)`` and reused (the arrays are never written)."""
    key = (tp, type(value), value)
    if key not in _OPAQUES:
        _OPAQUES[key] = dr.opaque(tp, value)
    return _OPAQUES[key]


#: Codes of one ``fixed16`` channel: 0 .. 65535.
_FIXED16_MAX = 65535


class DRRIntegrator(mi.SamplingIntegrator):
    """Line integrals of a voxel volume along the sensor's pixel-centre rays (see module doc)."""

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.ray_model = str(props.get("ray_model", "siddon"))
        if self.ray_model not in RAY_MODELS:
            raise ValueError(f"ctxreg_drr: ray_model must be one of {RAY_MODELS}, got {self.ray_model!r}")
        self.step_fraction = float(props.get("step_fraction", 0.5))
        if not (0.0 < self.step_fraction <= 1.0):
            raise ValueError(f"ctxreg_drr: step_fraction must be in (0, 1], got {self.step_fraction}")
        self.volume: mi.Float | None = None  # flat ((I+2)*(J+2)*(K+2)*C), zero-padded by one voxel
        self.shape: tuple[int, int, int] | None = None  # (I, J, K), unpadded
        self.storage = "float32"
        self.fixed16: tuple[tuple[float, float], tuple[float, float]] | None = None  # (step, zero code) per channel
        self.channels = 0
        self.min_spacing_mm = 1.0
        self.world_to_index = mi.Float(np.eye(4, dtype=np.float32)[:3].ravel())  # (B*12,)
        self.n_poses = 1

    # ------------------------------------------------------------------ data
    def set_volume(self, data: np.ndarray, spacing_mm, memory_order=(0, 1, 2),
                   storage: str = "float32") -> "StoredVolume":
        """Upload a volume once; later renders reuse it. Returns the uploaded volume, which
        :meth:`use_volume` gives to other integrators of the same scene type without a copy.

        Args:
            data: ``(C, I, J, K)`` float32, channel-first, indexed like the CT (``[c, i, j, k]``).
            spacing_mm: ``(3,)`` voxel spacing along i, j, k in mm (sets the trilinear step).
            memory_order: the index axes from slowest to fastest in memory. Neighbouring rays
                of a SIMD packet lie along the detector rows; storing the volume axis that runs
                along the rows contiguously lets one packet's gathers share cache lines (see
                :meth:`sim.projection.drr.DRRRenderer` for the choice). Only the strides change.
            storage: ``"float32"`` or ``"fixed16"`` (``C = 2`` only; module doc).
        """
        stored = store_volume(data, spacing_mm, memory_order, storage)
        self.use_volume(stored)
        return stored

    def use_volume(self, stored: "StoredVolume") -> None:
        """Render ``stored`` (a :meth:`set_volume` result, possibly another integrator's)."""
        if not isinstance(stored, StoredVolume):
            raise ValueError(f"ctxreg_drr: use_volume takes a StoredVolume, got {type(stored).__name__}")
        self.volume = stored.array
        self.strides = stored.strides
        self.fixed16 = stored.fixed16
        self.storage = stored.storage
        self.shape = stored.shape
        self.channels = stored.channels
        self.min_spacing_mm = stored.min_spacing_mm

    def _values(self, index, mask):
        """The ``channels`` values of the voxel at flat word ``index`` (masked lanes read 0)."""
        if self.fixed16 is None:
            return [dr.gather(mi.Float, self.volume, index + c, mask) for c in range(self.channels)]
        word = dr.gather(mi.UInt32, self.volume, index, mask)
        # opaque: one compiled kernel serves every volume's steps
        (step0, zero0), (step1, zero1) = (tuple(_opaque(mi.Float, x) for x in p) for p in self.fixed16)
        v0 = (mi.Float(word & 0xFFFF) - zero0) * step0
        v1 = (mi.Float(word >> 16) - zero1) * step1
        return [dr.select(mask, v0, 0.0), dr.select(mask, v1, 0.0)]

    def set_world_to_index(self, matrices: np.ndarray) -> None:
        """Place the volume for a batch of poses.

        Args:
            matrices: ``(B, 4, 4)`` or ``(4, 4)`` affine maps from Mitsuba world mm to voxel index
                coordinates (voxel centres at integers). Their linear part must map unit world
                vectors to index vectors of the same length in mm (a rigid motion followed by the
                CT's index<-LPS affine), so that ray parameters stay in mm.
        """
        m = np.asarray(matrices, dtype=np.float64)
        if m.ndim == 2:
            m = m[None]
        if m.ndim != 3 or m.shape[1:] != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"ctxreg_drr: world_to_index must be finite (B, 4, 4), got {m.shape}")
        self.world_to_index = mi.Float(m[:, :3, :].astype(np.float32).ravel())
        self.n_poses = int(m.shape[0])

    def traverse(self, callback) -> None:
        if self.volume is not None:
            callback.put("volume", self.volume, mi.ParamFlags.NonDifferentiable)
        callback.put("world_to_index", self.world_to_index, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys=None) -> None:
        self.n_poses = max(1, dr.width(self.world_to_index) // 12)

    def to_string(self) -> str:
        return (
            f"DRRIntegrator[ray_model={self.ray_model}, step_fraction={self.step_fraction}, "
            f"shape={self.shape}, channels={self.channels}, storage={self.storage}, poses={self.n_poses}]"
        )

    # ---------------------------------------------------------------- render
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True) -> mi.TensorXf:
        """Render all poses: a tensor ``(B, H, W, C)`` of line integrals (channel unit x mm)."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        if self.volume is None or self.shape is None:
            raise RuntimeError("ctxreg_drr: no volume set (DRRIntegrator.set_volume)")
        width, height = (int(v) for v in sensor.film().crop_size())
        n_rays = self.n_poses * height * width
        acc = self._line_integrals(sensor, width, height, n_rays)
        if self.channels == 1:
            return mi.TensorXf(acc[0], shape=(self.n_poses, height, width, 1))
        # every channel from one launch of the loop: interleaving scatters queued on the loop's
        # outputs would replay the whole loop once per channel (measured: C launches)
        dr.eval(*acc)
        values = dr.zeros(mi.Float, n_rays * self.channels)
        idx = dr.arange(mi.UInt32, n_rays)
        for c in range(self.channels):
            dr.scatter(values, acc[c], idx * self.channels + c)
        return mi.TensorXf(values, shape=(self.n_poses, height, width, self.channels))

    def rays_in_index_space(self, sensor, width: int, height: int, n_rays: int):
        """The pixel-centre rays of ``n_rays / (width * height)`` poses in the volume's index
        space (``set_world_to_index``): origins and directions, pose-major then row-major, as the
        renderer traces them (also used to trace tool meshes, :mod:`sim.distractors`)."""
        idx = dr.arange(mi.UInt32, n_rays)
        w = _opaque(mi.UInt32, width)
        hw = _opaque(mi.UInt32, width * height)
        pose = idx // hw
        pix = idx - pose * hw
        row = pix // w
        col = pix - row * w
        pos = mi.Point2f(
            (mi.Float(col) + 0.5) / _opaque(mi.Float, width),
            (mi.Float(row) + 0.5) / _opaque(mi.Float, height),
        )
        ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), pos, mi.Point2f(0.5, 0.5))
        m = [dr.gather(mi.Float, self.world_to_index, pose * 12 + k) for k in range(12)]
        o, d = ray.o, ray.d
        o_idx = mi.Vector3f(
            m[0] * o.x + m[1] * o.y + m[2] * o.z + m[3],
            m[4] * o.x + m[5] * o.y + m[6] * o.z + m[7],
            m[8] * o.x + m[9] * o.y + m[10] * o.z + m[11],
        )
        d_idx = mi.Vector3f(
            m[0] * d.x + m[1] * d.y + m[2] * d.z,
            m[4] * d.x + m[5] * d.y + m[6] * d.z,
            m[8] * d.x + m[9] * d.y + m[10] * d.z,
        )
        return o_idx, d_idx

    @staticmethod
    def _slab(o, d, lo, hi):
        """Ray parameters (mm) where the ray enters and leaves the box [lo, hi]^3 (index coords)."""
        tiny = 1e-12
        d_safe = dr.select(dr.abs(d) < tiny, dr.copysign(tiny, d), d)
        inv = dr.rcp(d_safe)
        t0 = (lo - o) * inv
        t1 = (hi - o) * inv
        t_near = dr.max(dr.minimum(t0, t1))
        t_far = dr.min(dr.maximum(t0, t1))
        return dr.maximum(t_near, 0.0), t_far, inv

    def _line_integrals(self, sensor, width, height, n_rays):
        ni, nj, nk = self.shape
        c_count = self.channels
        o, d = self.rays_in_index_space(sensor, width, height, n_rays)
        n = mi.Vector3f(_opaque(mi.Float, ni), _opaque(mi.Float, nj), _opaque(mi.Float, nk))
        # Strides of index axes i, j, k in the padded, permuted array, in floats.
        si, sj, sk = (_opaque(mi.Int32, st) for st in self.strides)
        if self.ray_model == "siddon":
            return self._siddon(o, d, n, (si, sj, sk), c_count)
        return self._trilinear(o, d, n, (si, sj, sk), c_count)

    def _siddon(self, o, d, n, strides, c_count):
        volume = self.volume
        si, sj, sk = strides
        # Padded boundary coordinates: original voxel i spans [i + 1, i + 2].
        p = o + 1.5
        s_in, s_out, inv = self._slab(p, d, 1.0, n + 1.0)
        hit = s_in < s_out
        start = p + d * (0.5 * (s_in + dr.minimum(s_out, s_in + 1e-3)))
        v = mi.Vector3i(dr.clip(dr.floor(start), 1.0, n))
        step = mi.Vector3i(dr.select(d > 0, 1, -1))
        # Clamped at the entry: rounding can put a boundary just before it. Then every
        # s_next = min(t_max) is >= the current s, and segments are never negative.
        t_max = dr.maximum((mi.Vector3f(v) + dr.select(d > 0, 1.0, 0.0) - p) * inv, s_in)
        t_delta = dr.abs(inv)
        # unsigned flat index: one compare bounds it on both sides
        flat = mi.UInt32(v.x * si + v.y * sj + v.z * sk)
        dflat = mi.Vector3u(mi.UInt32(step.x * si), mi.UInt32(step.y * sj), mi.UInt32(step.z * sk))
        size = _opaque(mi.UInt32, dr.width(volume))
        acc = [mi.Float(0.0) for _ in range(c_count)]
        s = mi.Float(s_in)

        def cond(active, s, flat, t_max, *acc):
            return active

        def body(active, s, flat, t_max, *acc):
            t_min = dr.min(t_max)
            s_next = dr.minimum(t_min, s_out)
            seg = s_next - s
            # The zero padding absorbs the single step past the exit face that rounding can
            # cause; the bounds check only guards memory (a negative index wraps to a large one).
            inside = flat < size
            acc = [dr.fma(val, seg, a) for val, a in zip(self._values(flat, active & inside), acc)]
            # the axis whose boundary comes first (ties: x, then y), as Siddon's order counts them
            mx = t_max.x == t_min
            my = ~mx & (t_max.y == t_min)
            mz = ~mx & ~my
            flat = flat + dr.select(mx, dflat.x, dr.select(my, dflat.y, dflat.z))
            t_max = mi.Vector3f(
                dr.select(mx, t_max.x + t_delta.x, t_max.x),
                dr.select(my, t_max.y + t_delta.y, t_max.y),
                dr.select(mz, t_max.z + t_delta.z, t_max.z),
            )
            active = active & (s_next < s_out) & inside
            return (active, s_next, flat, t_max, *acc)

        state = dr.while_loop(
            state=(hit, s, flat, t_max, *acc), cond=cond, body=body, label="ctxreg_siddon"
        )
        return list(state[4:])

    def _trilinear(self, o, d, n, strides, c_count):
        si, sj, sk = strides
        # Padded centre coordinates: original voxel centre i sits at i + 1; the interpolant's
        # support (zero padding) is [0, n + 1].
        r0 = o + 1.0
        s_in, s_out, _ = self._slab(r0, d, 0.0, n + 1.0)
        chord = dr.maximum(s_out - s_in, 0.0)
        step_mm = _opaque(mi.Float, self.step_fraction * self.min_spacing_mm)
        n_steps = mi.UInt32(dr.ceil(chord / step_mm))
        ds = dr.select(n_steps > 0, chord / mi.Float(dr.maximum(n_steps, 1)), 0.0)
        n_hi = mi.Vector3i(n)  # largest lower corner index: n (then +1 = n + 1 is padding)
        acc = [mi.Float(0.0) for _ in range(c_count)]
        k = mi.UInt32(0)

        def cond(k, *acc):
            return k < n_steps

        def body(k, *acc):
            s = s_in + (mi.Float(k) + 0.5) * ds
            r = r0 + d * s
            f = dr.floor(r)
            w = r - f
            i0 = dr.clip(mi.Vector3i(f), 0, n_hi)
            base = i0.x * si + i0.y * sj + i0.z * sk
            wx0, wy0, wz0 = 1.0 - w.x, 1.0 - w.y, 1.0 - w.z
            corners = (
                (0, wx0 * wy0 * wz0), (sk, wx0 * wy0 * w.z),
                (sj, wx0 * w.y * wz0), (sj + sk, wx0 * w.y * w.z),
                (si, w.x * wy0 * wz0), (si + sk, w.x * wy0 * w.z),
                (si + sj, w.x * w.y * wz0), (si + sj + sk, w.x * w.y * w.z),
            )
            val = [mi.Float(0.0) for _ in range(c_count)]
            for off, wt in corners:
                val = [dr.fma(v, wt, a) for v, a in zip(self._values(base + off, mi.Bool(True)), val)]
            return (k + 1, *(a + v for a, v in zip(acc, val)))

        state = dr.while_loop(state=(k, *acc), cond=cond, body=body, label="ctxreg_trilinear")
        return [a * ds for a in state[1:]]


@dataclass(frozen=True, eq=False)
class StoredVolume:
    """A volume as the integrator reads it (:func:`store_volume`): zero-padded by one voxel,
    permuted to ``memory_order``, flat in Dr.Jit memory. Immutable once made; integrators share it.

    Attributes:
        array: ``mi.Float`` (``float32``: ``C`` floats per voxel) or ``mi.UInt32`` (``fixed16``).
        strides: words between neighbouring voxels along index axes i, j, k.
        shape: ``(I, J, K)`` unpadded; channels: ``C``; storage: ``"float32"`` or ``"fixed16"``.
        fixed16: ``((step, zero code), (step, zero code))`` of the two channels, or None.
        min_spacing_mm: the smallest voxel spacing (mm), for the trilinear step.
        nbytes: the bytes the array holds.
    """

    array: object
    strides: tuple[int, int, int]
    shape: tuple[int, int, int]
    channels: int
    storage: str
    fixed16: tuple[tuple[float, float], tuple[float, float]] | None
    min_spacing_mm: float
    nbytes: int


def store_volume(data: np.ndarray, spacing_mm, memory_order=(0, 1, 2), storage: str = "float32") -> StoredVolume:
    """Upload ``data`` ``(C, I, J, K)`` for the integrator; arguments as :meth:`DRRIntegrator.set_volume`."""
    data = np.asarray(data, dtype=np.float32)
    if data.ndim != 4 or min(data.shape[1:]) < 1 or data.shape[0] < 1:
        raise ValueError(f"ctxreg_drr: volume must be (C, I, J, K), got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise ValueError("ctxreg_drr: volume contains NaN or infinite values")
    order = tuple(int(a) for a in memory_order)
    if sorted(order) != [0, 1, 2]:
        raise ValueError(f"ctxreg_drr: memory_order must be a permutation of (0, 1, 2), got {memory_order}")
    if storage not in STORAGES:
        raise ValueError(f"ctxreg_drr: storage must be one of {STORAGES}, got {storage!r}")
    c = data.shape[0]
    if storage == "fixed16" and c != 2:
        raise ValueError(f"ctxreg_drr: storage 'fixed16' packs exactly 2 channels, got {c}")
    padded_shape = tuple(data.shape[1 + a] + 2 for a in order) + (c,)
    stored = np.zeros(padded_shape, np.float32)  # in memory order: one copy of the data
    stored[1:-1, 1:-1, 1:-1, :] = np.transpose(data, (order[0] + 1, order[1] + 1, order[2] + 1, 0))
    fixed16 = None
    if storage == "fixed16":
        stored, fixed16 = _pack_fixed16(stored)
    # strides (in 32-bit words) of index axes i, j, k in the stored array
    strides = tuple(int(stored.strides[order.index(a)] // 4) for a in range(3))
    array = mi.UInt32(stored.ravel()) if storage == "fixed16" else mi.Float(stored.ravel())
    return StoredVolume(array=array, strides=strides, shape=tuple(int(n) for n in data.shape[1:]), channels=c,
                        storage=storage, fixed16=fixed16, min_spacing_mm=float(np.min(spacing_mm)),
                        nbytes=int(stored.nbytes))


def _pack_fixed16(stored: np.ndarray):
    """``(..., 2)`` float32 -> ``(...)`` uint32 words (channel 0 in the low 16 bits) and each
    channel's ``(step, zero code)``: value = (code - zero) * step, zero exactly representable."""
    words = np.zeros(stored.shape[:-1], np.uint32)
    params = []
    for c in range(2):
        x = stored[..., c].astype(np.float64)
        lo, hi = min(float(x.min()), 0.0), max(float(x.max()), 0.0)
        step = (hi - lo) / _FIXED16_MAX if hi > lo else 1.0
        zero = float(np.round(-lo / step))
        code = np.clip(np.round(x / step) + zero, 0, _FIXED16_MAX).astype(np.uint32)
        words |= code << np.uint32(16 * c)
        params.append((float(np.float32(step)), zero))
    return words, tuple(params)


def register() -> None:
    """Register the plugin with Mitsuba as ``ctxreg_drr`` (needs a variant to be set)."""
    mi.register_integrator("ctxreg_drr", lambda props: DRRIntegrator(props))
