"""Pose distributions for simulation campaigns: one distribution per pose parameter.

A pose is the 6 parameters of :func:`sim.projection.geometry.pose_from_params`: ``phi, theta, psi`` in
degrees (rotations about the patient's S, L and P axes) and ``tx, ty, tz`` in mm (camera frame,
``tz`` relative to the source-to-isocentre distance). See ``docs/conventions.md``.

Each parameter has its own :class:`ParamDistribution`:

* ``uniform``: ``low <= x < high`` (``low < high``);
* ``normal``: mean ``mean``, standard deviation ``std > 0``; with ``clip = [lo, hi]`` a normal
  truncated to ``[lo, hi]`` (sampled by the inverse CDF, so no draw is rejected);
* ``fixed``: always ``value``.

Every number must be finite and within its parameter's declared range (:data:`PARAM_LIMITS`:
+-360 deg, +-10000 mm; ``std`` up to twice that), so a typo cannot ask for poses that no C-arm
could show.

Sampling is by the inverse CDF of one uniform number per parameter and pose:
:meth:`PoseDistribution.sample` draws ``rng.random((n, 6))`` and maps column ``k`` through
parameter ``k``'s inverse CDF. So every distribution kind consumes the same random numbers, the
values of one parameter do not depend on the others' distributions, and the first ``m`` poses of
``sample(rng, n)`` equal ``sample(rng', m)`` for an identically seeded ``rng'`` (``m <= n``).
"""

from __future__ import annotations

import difflib
import math
import os
from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np

from sim.core.errors import InputError
from sim.core.atomic import atomic_path

#: Pose parameter names, in the order of :func:`sim.projection.geometry.pose_from_params`.
PARAM_NAMES: tuple[str, ...] = ("phi", "theta", "psi", "tx", "ty", "tz")
#: Unit of each parameter in :data:`PARAM_NAMES`.
PARAM_UNITS: tuple[str, ...] = ("deg", "deg", "deg", "mm", "mm", "mm")
#: Distribution kinds (the ``dist`` key).
KINDS: tuple[str, ...] = ("uniform", "normal", "fixed")
#: Declared range of each parameter (its unit): every ``low``, ``high``, ``mean``, ``value``
#: and ``clip`` bound must lie in ``[-limit, limit]`` and ``std`` in ``(0, 2 limit]``. Angles
#: beyond one turn mean nothing new; offsets beyond 10 m leave any C-arm's field of view
#: (the campaign runner also checks every sampled pose against each CT's box).
PARAM_LIMITS: dict[str, float] = {"phi": 360.0, "theta": 360.0, "psi": 360.0,
                                  "tx": 10_000.0, "ty": 10_000.0, "tz": 10_000.0}

#: Keys each kind takes besides ``dist`` (required, optional).
_KIND_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "uniform": (("low", "high"), ()),
    "normal": (("mean", "std"), ("clip",)),
    "fixed": (("value",), ()),
}

# Inverse-CDF guards: keep the probability strictly inside (0, 1) so ndtri stays finite.
_P_MIN = np.finfo(np.float64).tiny
_P_MAX = 1.0 - 2.0**-53


class PoseDistributionError(InputError):
    """An invalid pose distribution; the message names the key (e.g. ``poses.phi.std``)."""


def _suggest(key: str, valid) -> str:
    close = difflib.get_close_matches(key, list(valid), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _number(value: Any, key: str) -> float:
    """A finite real number (TOML int or float, not bool)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise PoseDistributionError(f"{key}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise PoseDistributionError(f"{key}: expected a finite number, got {value!r}")
    return v


@dataclass(frozen=True)
class ParamDistribution:
    """The distribution of one pose parameter (degrees for angles, mm for offsets).

    Attributes:
        kind: ``"uniform"``, ``"normal"`` or ``"fixed"``.
        low, high: uniform range, ``low < high``.
        mean, std: normal mean and standard deviation (``std > 0``).
        clip: optional ``(lo, hi)`` truncation of the normal, ``lo < hi``.
        value: the constant of ``fixed``.

    Build with :meth:`from_dict` (validates) or directly (validated in ``__post_init__``).
    """

    kind: str
    low: float | None = None
    high: float | None = None
    mean: float | None = None
    std: float | None = None
    clip: tuple[float, float] | None = None
    value: float | None = None

    def __post_init__(self) -> None:
        self._validate("param")

    # -- validation ---------------------------------------------------------------------------

    def _validate(self, key: str) -> None:
        if self.kind not in KINDS:
            raise PoseDistributionError(
                f"{key}.dist: unknown distribution {self.kind!r}; allowed: {', '.join(KINDS)}"
                f"{_suggest(str(self.kind), KINDS)}"
            )
        required, optional = _KIND_KEYS[self.kind]
        for f in fields(self):
            if f.name == "kind":
                continue
            v = getattr(self, f.name)
            if f.name in required and v is None:
                raise PoseDistributionError(f"{key}: dist = {self.kind!r} needs {f.name!r} "
                                            f"(keys: {', '.join(required + optional)})")
            if f.name not in required + optional and v is not None:
                raise PoseDistributionError(f"{key}: {f.name!r} does not apply to dist = {self.kind!r} "
                                            f"(keys: {', '.join(required + optional)})")
        if self.kind == "uniform":
            lo, hi = _number(self.low, f"{key}.low"), _number(self.high, f"{key}.high")
            if not lo < hi:
                raise PoseDistributionError(f"{key}: uniform needs low < high, got low = {lo}, high = {hi}")
        elif self.kind == "normal":
            _number(self.mean, f"{key}.mean")
            std = _number(self.std, f"{key}.std")
            if not std > 0:
                raise PoseDistributionError(f"{key}.std: must be > 0, got {std}")
            if self.clip is not None:
                clip = self.clip
                if isinstance(clip, (str, bytes)) or not hasattr(clip, "__len__") or len(clip) != 2:
                    raise PoseDistributionError(f"{key}.clip: expected [lo, hi] (2 numbers), got {clip!r}")
                lo, hi = _number(clip[0], f"{key}.clip[0]"), _number(clip[1], f"{key}.clip[1]")
                if not lo < hi:
                    raise PoseDistributionError(f"{key}.clip: needs lo < hi, got [{lo}, {hi}]")
                pa, pb, _ = self._truncation()
                if not pb > pa:
                    raise PoseDistributionError(
                        f"{key}.clip: [{lo}, {hi}] lies too far from the mean ({self.mean}, std "
                        f"{std}) to hold any probability; move the clip within ~35 std of the mean"
                    )
        else:
            _number(self.value, f"{key}.value")
        # normalise: floats and a tuple clip, so equal distributions compare and hash equal
        for name in ("low", "high", "mean", "std", "value"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, float(v))
        if self.clip is not None:
            object.__setattr__(self, "clip", (float(self.clip[0]), float(self.clip[1])))

    # -- construction / serialisation ---------------------------------------------------------

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], key: str = "param") -> "ParamDistribution":
        """Build from a table such as ``{"dist": "uniform", "low": -40.0, "high": 40.0}``.

        Args:
            d: the table; ``dist`` plus the keys of that kind (see the module docstring).
            key: dotted key path used in error messages (e.g. ``"poses.phi"``).

        Raises:
            PoseDistributionError: naming ``key`` and the allowed kinds, keys or range.
        """
        if not isinstance(d, Mapping):
            raise PoseDistributionError(
                f"{key}: expected a table such as {{ dist = \"uniform\", low = -40.0, high = 40.0 }}, got {d!r}"
            )
        if "dist" not in d:
            raise PoseDistributionError(f"{key}: missing 'dist' (allowed: {', '.join(KINDS)})")
        kind = d["dist"]
        if not isinstance(kind, str) or kind not in KINDS:
            raise PoseDistributionError(
                f"{key}.dist: unknown distribution {kind!r}; allowed: {', '.join(KINDS)}"
                f"{_suggest(str(kind), KINDS)}"
            )
        required, optional = _KIND_KEYS[kind]
        allowed = ("dist",) + required + optional
        for k in d:
            if k not in allowed:
                raise PoseDistributionError(
                    f"{key}.{k}: unknown key for dist = {kind!r}; allowed keys: {', '.join(allowed)}"
                    f"{_suggest(str(k), allowed)}"
                )
        for k in required:
            if k not in d:
                raise PoseDistributionError(f"{key}: dist = {kind!r} needs {k!r} (keys: {', '.join(allowed)})")
        kw: dict[str, Any] = {k: _number(d[k], f"{key}.{k}") for k in required}
        if "clip" in d and d["clip"] is not None:
            c = d["clip"]
            if isinstance(c, (str, bytes)) or not isinstance(c, (list, tuple)) or len(c) != 2:
                raise PoseDistributionError(f"{key}.clip: expected [lo, hi] (2 numbers), got {c!r}")
            kw["clip"] = (_number(c[0], f"{key}.clip[0]"), _number(c[1], f"{key}.clip[1]"))
        obj = cls.__new__(cls)
        for name, v in {"kind": kind, "low": None, "high": None, "mean": None, "std": None,
                        "clip": None, "value": None, **kw}.items():
            object.__setattr__(obj, name, v)
        obj._validate(key)
        return obj

    def to_dict(self) -> dict[str, Any]:
        """The table form (``dist`` plus the kind's keys; floats; ``clip`` as a list if set)."""
        out: dict[str, Any] = {"dist": self.kind}
        required, optional = _KIND_KEYS[self.kind]
        for k in required + optional:
            v = getattr(self, k)
            if v is None:
                continue
            out[k] = [float(v[0]), float(v[1])] if k == "clip" else float(v)
        return out

    # -- sampling -----------------------------------------------------------------------------

    def _truncation(self) -> tuple[float, float, bool]:
        """Normal CDF at the clip bounds in standard units ``(p_lo, p_hi, mirrored)``.

        An interval entirely above the mean is mirrored below it, where the CDF keeps its
        relative precision in the tail.
        """
        from scipy.special import ndtr

        lo, hi = self.clip if self.clip is not None else (-math.inf, math.inf)
        a, b = (lo - self.mean) / self.std, (hi - self.mean) / self.std
        mirrored = a > 0
        if mirrored:
            a, b = -b, -a
        return float(ndtr(a)), float(ndtr(b)), mirrored

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        """Map uniform numbers ``u`` in ``[0, 1)`` (any shape) to this distribution (inverse CDF)."""
        u = np.asarray(u, dtype=np.float64)
        if self.kind == "uniform":
            return self.low + (self.high - self.low) * u
        if self.kind == "fixed":
            return np.full(u.shape, float(self.value))
        from scipy.special import ndtri

        pa, pb, mirrored = self._truncation()
        p = np.clip(pa + (pb - pa) * u, max(pa, _P_MIN), min(pb, _P_MAX))
        z = ndtri(p)
        if mirrored:
            z = -z
        x = self.mean + self.std * z
        if self.clip is not None:
            x = np.clip(x, self.clip[0], self.clip[1])
        return x

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n,)`` float64 draws (one ``rng.random`` number each, for every kind)."""
        n = _check_n(n)
        return self.from_unit(rng.random(n))

    def support(self) -> tuple[float, float]:
        """``(lo, hi)`` that every draw lies in; ``(-inf, inf)`` for an unclipped normal."""
        if self.kind == "uniform":
            return float(self.low), float(self.high)
        if self.kind == "fixed":
            return float(self.value), float(self.value)
        if self.clip is not None:
            return float(self.clip[0]), float(self.clip[1])
        return self.mean - math.inf, self.mean + math.inf


def check_limits(dist: ParamDistribution, name: str, key: str) -> None:
    """Refuse a distribution of parameter ``name`` outside :data:`PARAM_LIMITS`, naming ``key``."""
    limit = PARAM_LIMITS[name]
    unit = PARAM_UNITS[PARAM_NAMES.index(name)]
    values = {"low": dist.low, "high": dist.high, "mean": dist.mean, "value": dist.value}
    if dist.clip is not None:
        values.update({"clip[0]": dist.clip[0], "clip[1]": dist.clip[1]})
    for k, v in values.items():
        if v is not None and not -limit <= v <= limit:
            raise PoseDistributionError(f"{key}.{k}: must be in [{-limit:g}, {limit:g}] {unit}, got {v!r}")
    if dist.std is not None and not dist.std <= 2 * limit:
        raise PoseDistributionError(f"{key}.std: must be in (0, {2 * limit:g}] {unit}, got {dist.std!r}")


def _check_n(n: Any) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise PoseDistributionError(f"n: the number of draws must be an integer >= 0, got {n!r}")
    return int(n)


@dataclass(frozen=True)
class PoseDistribution:
    """One :class:`ParamDistribution` per pose parameter (angles in degrees, offsets in mm)."""

    phi: ParamDistribution
    theta: ParamDistribution
    psi: ParamDistribution
    tx: ParamDistribution
    ty: ParamDistribution
    tz: ParamDistribution

    def __post_init__(self) -> None:
        for name in PARAM_NAMES:
            if not isinstance(getattr(self, name), ParamDistribution):
                raise PoseDistributionError(f"{name}: expected a ParamDistribution, got {getattr(self, name)!r}")
            check_limits(getattr(self, name), name, name)

    @property
    def params(self) -> tuple[ParamDistribution, ...]:
        """The 6 distributions in :data:`PARAM_NAMES` order."""
        return tuple(getattr(self, name) for name in PARAM_NAMES)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n, 6)`` float64 poses ``(phi, theta, psi [deg], tx, ty, tz [mm])``.

        Draws ``rng.random((n, 6))`` (row by row) and maps each column through its parameter's
        inverse CDF: the first ``m`` rows do not depend on ``n``.
        """
        n = _check_n(n)
        u = rng.random((n, 6))
        out = np.empty((n, 6), dtype=np.float64)
        for k, dist in enumerate(self.params):
            out[:, k] = dist.from_unit(u[:, k])
        return out

    def bounds(self) -> np.ndarray:
        """``(6, 2)`` float64: ``[lo, hi]`` per parameter (see :meth:`ParamDistribution.support`)."""
        return np.array([d.support() for d in self.params], dtype=np.float64)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """``{"phi": {"dist": ...}, ...}`` for all 6 parameters."""
        return {name: d.to_dict() for name, d in zip(PARAM_NAMES, self.params)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], key: str = "poses",
                  defaults: "PoseDistribution | None" = None) -> "PoseDistribution":
        """Build from ``{"phi": {...}, ...}``; missing parameters come from ``defaults``.

        Args:
            d: parameter name -> distribution table.
            key: dotted key path for error messages.
            defaults: where missing parameters come from (:data:`ORIGINAL_PROTOCOL` if None).

        Raises:
            PoseDistributionError: unknown parameter (with a suggestion) or invalid distribution.
        """
        if not isinstance(d, Mapping):
            raise PoseDistributionError(f"{key}: expected a table of pose parameters, got {d!r}")
        base = ORIGINAL_PROTOCOL if defaults is None else defaults
        for k in d:
            if k not in PARAM_NAMES:
                raise PoseDistributionError(
                    f"{key}.{k}: unknown pose parameter; allowed: {', '.join(PARAM_NAMES)}"
                    f"{_suggest(str(k), PARAM_NAMES)}"
                )
        kw = {name: (ParamDistribution.from_dict(d[name], f"{key}.{name}") if name in d else getattr(base, name))
              for name in PARAM_NAMES}
        for name in d:
            check_limits(kw[name], name, f"{key}.{name}")
        return cls(**kw)


def _uniform(lo: float, hi: float) -> ParamDistribution:
    return ParamDistribution("uniform", low=lo, high=hi)


#: The original protocol: rotations uniform in +-40 deg (phi) and +-20 deg (theta, psi),
#: translations uniform in +-75 mm.
ORIGINAL_PROTOCOL = PoseDistribution(
    phi=_uniform(-40.0, 40.0),
    theta=_uniform(-20.0, 20.0),
    psi=_uniform(-20.0, 20.0),
    tx=_uniform(-75.0, 75.0),
    ty=_uniform(-75.0, 75.0),
    tz=_uniform(-75.0, 75.0),
)


def pose_histogram(params: np.ndarray, dist: PoseDistribution, path: str | os.PathLike,
                   *, bins: int = 40, title: str | None = None) -> None:
    """Write a PNG with one histogram per pose parameter and its configured range marked.

    Args:
        params: ``(N, 6)`` sampled poses (degrees, mm), as from :meth:`PoseDistribution.sample`.
        dist: the distribution they were drawn from; its support is drawn as red lines
            (an unclipped normal: dashed lines at mean +- 3 std; fixed: one line at the value).
        path: the PNG file, written atomically (:func:`sim.core.atomic.atomic_path`).
        bins: histogram bins per parameter.
        title: optional figure title.

    Raises:
        PoseDistributionError: ``params`` is not ``(N, 6)`` finite numbers or ``bins < 1``.
    """
    p = np.asarray(params, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 6:
        raise PoseDistributionError(f"params: expected shape (N, 6), got {p.shape}")
    if not np.isfinite(p).all():
        raise PoseDistributionError("params: contains NaN or infinite values")
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 1:
        raise PoseDistributionError(f"bins: expected an integer >= 1, got {bins!r}")
    if not isinstance(dist, PoseDistribution):
        raise PoseDistributionError(f"dist: expected a PoseDistribution, got {type(dist).__name__}")

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 6.5), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 3)
    for k, (name, unit, d) in enumerate(zip(PARAM_NAMES, PARAM_UNITS, dist.params)):
        ax = axes.flat[k]
        col = p[:, k]
        lo, hi = d.support()
        if d.kind == "normal" and d.clip is None:
            marks, style = (d.mean - 3 * d.std, d.mean + 3 * d.std), "--"
        else:
            marks, style = (lo, hi), "-"
        span_lo = min(col.min(initial=marks[0]), marks[0])
        span_hi = max(col.max(initial=marks[1]), marks[1])
        if span_hi <= span_lo:
            span_lo, span_hi = span_lo - 0.5, span_hi + 0.5
        pad = 0.05 * (span_hi - span_lo)
        ax.hist(col, bins=bins, range=(span_lo - pad, span_hi + pad), color="0.45")
        for m in sorted(set(marks)):
            ax.axvline(m, color="tab:red", linestyle=style, linewidth=1.2)
        ax.set_xlabel(f"{name} ({unit})")
        ax.set_ylabel("count")
        ax.set_title(f"{name}: {_describe(d)}", fontsize=9)
    fig.suptitle(title or f"sampled pose parameters (N = {len(p)}); red: configured range")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")


def _describe(d: ParamDistribution) -> str:
    if d.kind == "uniform":
        return f"uniform [{d.low:g}, {d.high:g})"
    if d.kind == "fixed":
        return f"fixed {d.value:g}"
    text = f"normal({d.mean:g}, {d.std:g})"
    return text + (f" clipped to [{d.clip[0]:g}, {d.clip[1]:g}]" if d.clip is not None else "")
