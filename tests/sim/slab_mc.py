"""An independent, deliberately simple NumPy Monte Carlo of a homogeneous slab (test reference).

It shares only the input data with :mod:`sim.physics.scatter` (xraylib cross sections, the
spekpy spectrum, the detector response) and none of its algorithms: analog transport in a box
with exact exponential free paths (no delta tracking), angles by rejection sampling from the
closed-form Klein-Nishina and Thomson cross sections times xraylib's S(x) and F(x)^2 of the
atoms of water (no tables of inverse CDFs), and analog detection (a scattered photon counts
where its straight flight crosses the detector plane; no forced detection).
"""

from __future__ import annotations

import numpy as np

ME_C2_KEV = 510.99895


def _water_atoms():
    import xraylib as xr

    d = xr.GetCompoundDataNISTByName("Water, Liquid")
    zs = np.array(d["Elements"], dtype=np.int64)
    per_gram = np.array([f / xr.AtomicWeight(int(z)) for z, f in zip(d["Elements"], d["massFractions"])])
    return zs, per_gram


def _functions_of_x():
    """S(x) and F(x)^2 of water (per-gram atom weighting), on a log grid in x (1/Angstrom)."""
    import xraylib_np as xrn

    zs, per_gram = _water_atoms()
    x = np.geomspace(1e-3, 15.0, 4000)
    s = (per_gram[:, None] * xrn.SF_Compt(zs, x)).sum(0)
    f2 = (per_gram[:, None] * xrn.FF_Rayl(zs, x) ** 2).sum(0)
    s_max = (per_gram * zs).sum()
    f2_max = (per_gram * zs.astype(float) ** 2).sum()
    return x, s / s_max, f2 / f2_max


def _interp_x(xq, x, y, small):
    xq = np.maximum(xq, 1e-12)
    out = np.interp(np.log(np.maximum(xq, x[0])), np.log(x), y)
    return np.where(xq < x[0], small(xq, out), out)


def run_slab(*, thickness_mm: float, lateral_mm: float, z_entry_mm: float, sdd_mm: float,
             detector_mm: float, spectrum, detector, photons: int, seed: int = 0,
             central_mm: float = 60.0) -> dict:
    """Water (1 g/cm^3) box ``lateral x lateral x thickness`` mm centred on the axis, entry face
    at ``z_entry_mm`` from the source; square detector of side ``detector_mm`` at ``sdd_mm``; the
    source emits toward uniform points of the detector. Returns the mean scatter signal per mm^2
    on the central ``central_mm`` square and on the whole detector, per emitted photon
    (signal units of ``detector.response``), and their relative standard errors."""
    from sim.physics.materials import mass_attenuation

    rng = np.random.default_rng(seed)
    e_grid = np.linspace(5.0, float(spectrum.edges_keV[-1]) + 1, 600)
    mu = {k: mass_attenuation("water", e_grid, k) / 10.0 for k in ("photo", "compton", "rayleigh")}  # 1/mm
    resp_grid = detector.response(e_grid)
    x_tab, s_tab, f2_tab = _functions_of_x()
    p = spectrum.fluence / spectrum.fluence.sum()
    e = rng.choice(spectrum.energies_keV, size=photons, p=p)
    half = detector_mm / 2
    y = np.stack([rng.uniform(-half, half, photons), rng.uniform(-half, half, photons),
                  np.full(photons, sdd_mm)], axis=1)
    d = y / np.linalg.norm(y, axis=1, keepdims=True)
    pos = d * (z_entry_mm / d[:, 2])[:, None]  # on the entry face
    lo = np.array([-lateral_mm / 2, -lateral_mm / 2, z_entry_mm])
    hi = np.array([lateral_mm / 2, lateral_mm / 2, z_entry_mm + thickness_mm])
    inside0 = np.all((pos[:, :2] >= lo[:2]) & (pos[:, :2] <= hi[:2]), axis=1)
    e, d, pos = e[inside0], d[inside0], pos[inside0]
    scattered = np.zeros(len(e), bool)
    central = np.zeros(0)
    whole = np.zeros(0)
    while len(e):
        mp, mc, mr = (np.interp(e, e_grid, mu[k]) for k in ("photo", "compton", "rayleigh"))
        mt = mp + mc + mr
        t = -np.log1p(-rng.random(len(e))) / mt
        # distance to leave the box
        with np.errstate(divide="ignore"):
            t_out = np.min(np.where(d > 0, (hi - pos) / d, np.where(d < 0, (lo - pos) / d, np.inf)), axis=1)
        leave = t >= t_out
        # escaping scattered photons: analog detection on the detector plane
        esc = leave & scattered & (d[:, 2] > 0)
        if esc.any():
            s_hit = (sdd_mm - pos[esc, 2]) / d[esc, 2]
            hit = pos[esc] + d[esc] * s_hit[:, None]
            signal = np.interp(e[esc], e_grid, resp_grid)
            on_det = np.all(np.abs(hit[:, :2]) <= half, axis=1)
            in_c = np.all(np.abs(hit[:, :2]) <= central_mm / 2, axis=1)
            central = np.concatenate([central, signal[in_c]])
            whole = np.concatenate([whole, signal[on_det]])
        keep = ~leave
        e, d, pos, scattered = e[keep], d[keep], pos[keep] + d[keep] * t[keep][:, None], scattered[keep]
        mp, mc, mr, mt = mp[keep], mc[keep], mr[keep], mt[keep]
        u = rng.random(len(e)) * mt
        photo = u < mp
        compton = ~photo & (u < mp + mc)
        e, d, pos, scattered, compton = e[~photo], d[~photo], pos[~photo], scattered[~photo], compton[~photo]
        cos_t = np.empty(len(e))
        todo = np.ones(len(e), bool)
        while todo.any():
            idx = np.nonzero(todo)[0]
            c = rng.uniform(-1.0, 1.0, len(idx))
            x = np.sqrt((1 - c) / 2) * e[idx] / 12.39841984
            k = e[idx] / ME_C2_KEV
            ratio = 1.0 / (1.0 + k * (1 - c))
            kn = 0.5 * ratio**2 * (ratio + 1 / ratio - (1 - c * c))  # <= 1, Klein-Nishina / r_e^2
            sx = _interp_x(x, x_tab, s_tab, lambda xq, v: s_tab[0] * (xq / x_tab[0]) ** 2)
            f2 = _interp_x(x, x_tab, f2_tab, lambda xq, v: np.full_like(xq, f2_tab[0]))
            accept_p = np.where(compton[idx], kn * sx, 0.5 * (1 + c * c) * f2)
            ok = rng.random(len(idx)) < accept_p
            cos_t[idx[ok]] = c[ok]
            todo[idx[ok]] = False
        phi = rng.uniform(0, 2 * np.pi, len(e))
        sin_t = np.sqrt(np.maximum(1 - cos_t**2, 0))
        a = np.where(np.abs(d[:, 2:3]) < 0.9, np.array([[0, 0, 1.0]]), np.array([[1.0, 0, 0]]))
        t1 = np.cross(d, a)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(d, t1)
        d = d * cos_t[:, None] + (t1 * np.cos(phi)[:, None] + t2 * np.sin(phi)[:, None]) * sin_t[:, None]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        e = np.where(compton, e / (1 + e / ME_C2_KEV * (1 - cos_t)), e)
        scattered = np.ones(len(e), bool)
        alive = e >= 5.0
        e, d, pos, scattered = e[alive], d[alive], pos[alive], scattered[alive]
    n = photons
    out = {}
    for name, vals, area in (("central", central, central_mm**2), ("whole", whole, detector_mm**2)):
        mean = vals.sum() / n / area
        # per-photon scores are i.i.d.: var of the mean = (E[s^2] - E[s]^2) / n
        m1, m2 = vals.sum() / n, (vals**2).sum() / n
        out[name] = mean
        out[name + "_rel_se"] = float(np.sqrt(max(m2 - m1 * m1, 0) / n) / max(m1, 1e-300))
    return out
