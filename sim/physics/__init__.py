"""Realistic X-ray physics: materials with NIST cross sections, tube spectra, detector, noise.

The ray marching is done once per pose: the renderer (:mod:`sim.projection.drr`, ``quantity="density"``)
gives per-material density line integrals ``L_m`` (g/cm^2), and :mod:`sim.physics.poly` turns
them into the polychromatic detector signal for any spectrum and detector. The settings (kVp,
filtration, detector, noise, Monte Carlo) are declared once in :mod:`sim.physics.settings`; the
materials and their cross sections are :mod:`sim.physics.materials`. Status and validation:
``docs/physics.md``.
"""

from sim.core.errors import InputError


class PhysicsError(InputError):
    """A physics setting or input cannot be used; the message names it and the allowed values."""
