"""Temporary: the old path of :mod:`register.engines.search` until prepare.py moves (issue 30)."""
from register.engines.search import GlobalSearch, GlobalSearchSettings  # noqa: F401
