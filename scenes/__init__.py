"""Mitsuba scene files for C-arm geometries (``<name>.xml``); see :mod:`sim.projection.scene`."""

from pathlib import Path

SCENE_DIR = Path(__file__).resolve().parent


def available() -> list[str]:
    """Names of the scenes shipped with ctxreg (file stems)."""
    return sorted(p.stem for p in SCENE_DIR.glob("*.xml"))
