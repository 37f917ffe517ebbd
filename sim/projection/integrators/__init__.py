"""Mitsuba integrator plugins of ctxreg, one per file; each registers itself via ``register()``."""
