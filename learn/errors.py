"""The errors of reading a network's files, without torch: a command that only reads model cards
(``ctxreg models``) or refuses a bad path answers before torch is imported."""

from __future__ import annotations

from sim.core.errors import InputError

__all__ = ["CheckpointError"]


class CheckpointError(InputError):
    """A checkpoint cannot be used; the one-line message names the file and the problem."""
