"""Temporary: the old path of :mod:`register.xray.field` until preprocess.py moves (issue 30)."""
from register.xray.field import FieldSettings, detect_field  # noqa: F401
