"""Temporary: the old path of :mod:`register.xray.io` until prepare.py moves (issue 30)."""
from register.xray.io import XRayImage, load_xray, resolve_geometry  # noqa: F401
