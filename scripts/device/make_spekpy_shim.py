"""Write a stand-in 'spekpy' package into DIR (argv[1]): spectra precomputed here with the real
spekpy (the venv's 2.5.4) for what ctxreg's training asks of it, sim.physics.spectrum._spek:
Spek(kvp, th=anode angle, dk=0.25) with no filter, then get_spectrum().  Online domain
randomization draws kV on a 5 kV grid (60-130) at the default 12 deg anode; the table covers
20-150 kV in 5 kV steps at 12 deg.  Any other request (another kV, angle, dk, or a .filter call)
raises, rather than silently returning something else."""
import os, sys
import numpy as np
import spekpy

out = sys.argv[1]
os.makedirs(out, exist_ok=True)
KVS = [float(k) for k in range(20, 151, 5)]
ANGLES = [12.0]
DK = 0.25
arrays = {}
for th in ANGLES:
    for kv in KVS:
        k, phi = spekpy.Spek(kvp=kv, th=th, dk=DK).get_spectrum()
        arrays[f"k_{kv:g}_{th:g}_{DK:g}"] = np.asarray(k, np.float64)
        arrays[f"phi_{kv:g}_{th:g}_{DK:g}"] = np.asarray(phi, np.float64)
np.savez_compressed(os.path.join(out, "spectra.npz"), **arrays)
with open(os.path.join(out, "__init__.py"), "w") as f:
    f.write('''"""Stand-in for spekpy %s (see .devbundle/make_spekpy_shim.py): precomputed unfiltered spectra."""
import os as _os
import numpy as _np

__version__ = "%s+devbundle-shim"
_TABLE = _np.load(_os.path.join(_os.path.dirname(__file__), "spectra.npz"))


class Spek:
    def __init__(self, kvp=100.0, th=12.0, dk=0.5, **kw):
        if kw:
            raise NotImplementedError(f"spekpy shim: unsupported Spek arguments {sorted(kw)}")
        self.key = f"{float(kvp):g}_{float(th):g}_{float(dk):g}"
        if "k_" + self.key not in _TABLE.files:
            raise NotImplementedError(f"spekpy shim: no precomputed spectrum for kvp={kvp}, th={th}, dk={dk}")

    def filter(self, matl, t):
        if float(t) > 0:
            raise NotImplementedError(f"spekpy shim: filter({matl!r}, {t}) is not precomputed")
        return self

    def get_spectrum(self, **kw):
        if kw:
            raise NotImplementedError(f"spekpy shim: unsupported get_spectrum arguments {sorted(kw)}")
        return _TABLE["k_" + self.key].copy(), _TABLE["phi_" + self.key].copy()
''' % (spekpy.__version__ if hasattr(spekpy, "__version__") else "2.5.4",
       spekpy.__version__ if hasattr(spekpy, "__version__") else "2.5.4"))
print(f"spekpy shim: {len(KVS) * len(ANGLES)} spectra -> {out}")
