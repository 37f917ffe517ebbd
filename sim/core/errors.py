"""The errors a user can act on: one base for all of ctxreg.

Every error that means "the input is wrong" (a file, an option, a config value, a model, an
image) derives from :class:`InputError`; every error that means "this machine lacks something"
(LLVM, a Dr.Jit backend) from :class:`SetupError`. Both derive from :class:`CtxregError`, which
the ``ctxreg`` command line prints as one line (exit status 2). Any other exception is a bug and
keeps its traceback.

:class:`InputError` is also a :class:`ValueError`, and :class:`SetupError` a
:class:`RuntimeError`, so code that caught those before still does.

Example::

    >>> from sim.core.errors import InputError
    >>> class RenderError(InputError):
    ...     '''Bad render settings; the message names the setting.'''
    >>> issubclass(RenderError, ValueError)
    True
"""

from __future__ import annotations

__all__ = ["CtxregError", "InputError", "SetupError", "USER_OS_ERRORS"]


class CtxregError(Exception):
    """Base of the errors a user can act on; the message says what to change."""


class InputError(CtxregError, ValueError):
    """Bad input: a file, an option, a config value, a model or an image."""


class SetupError(CtxregError, RuntimeError):
    """The machine lacks something ctxreg needs (LLVM, a Dr.Jit backend, a free folder)."""


#: Operating-system errors about a path the user named (missing, a folder where a file was
#: expected, no permission): the command line shows them in one line too.
USER_OS_ERRORS: tuple[type[OSError], ...] = (FileNotFoundError, NotADirectoryError, IsADirectoryError,
                                             PermissionError, FileExistsError)
