"""The projection stage: where the C-arm is and the line integrals it sees.

- :mod:`sim.projection.se3`, :mod:`sim.projection.geometry`: SE(3) on NumPy and torch arrays, the
  C-arm's pose parameters, intrinsics and projection (docs/conventions.md);
- :mod:`sim.projection.scene`: C-arm scenes (``scenes/``);
- :mod:`sim.projection.drr`: the DRR renderer (many poses per Dr.Jit launch) and its checks;
- :mod:`sim.projection.integrators`: the Mitsuba 3 integrator plugin ``ctxreg_drr``;
- :mod:`sim.projection.raymarch`: the torch ray marcher (the same line integrals on a GPU);
- :mod:`sim.projection.backend`, :mod:`sim.projection.llvm`: Dr.Jit's variant and its libLLVM.

NumPy-only modules (se3, geometry, scene) never import Dr.Jit.
"""
