"""ctxreg.sim: X-ray simulation from CT with Mitsuba 3 / Dr.Jit.

Importing :mod:`sim` locates a libLLVM >= 16 for Dr.Jit's CPU backend (see :mod:`sim.llvm`)
before any Dr.Jit kernel can run. NumPy-only modules (:mod:`sim.se3`, :mod:`sim.geometry`,
:mod:`sim.ct`, :mod:`sim.phantom`) never import Dr.Jit; :mod:`sim.backend` does.
"""

from sim import llvm as _llvm

_llvm.configure()

__version__ = "0.1.0"
