"""Temporary: the old path of :mod:`register.engines.cmaes` until prepare.py moves (issue 30)."""
from register.engines.result import RegistrationError  # noqa: F401
