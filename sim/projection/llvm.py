"""Find a libLLVM that Dr.Jit's CPU backend can use.

Dr.Jit 1.5 compiles its CPU kernels with the system's libLLVM and needs LLVM >= 16: with
LLVM 15 (Debian 12's default) the process aborts inside the first kernel. Dr.Jit reads the
library path from the environment variable ``DRJIT_LIBLLVM_PATH`` when it starts its LLVM
backend, so this module must run before the first kernel; :mod:`sim` calls
:func:`configure` on import.

Search order:

1. ``DRJIT_LIBLLVM_PATH`` if the user set it (kept as it is; it must exist).
2. Versioned libraries ``libLLVM-<major>.so[.1]`` / ``libLLVM.so.<major>[.1]`` in the usual
   library folders (Debian/Ubuntu multiarch, ``/usr/lib/llvm-<major>/lib``, ``/usr/lib64``,
   ``/usr/local/lib``, Homebrew), newest major first, majors 16 and up only.
"""

from __future__ import annotations

import glob
import os
import platform
import re
from dataclasses import dataclass
from pathlib import Path

from sim.core.errors import SetupError

MIN_LLVM_MAJOR = 16
ENV_VAR = "DRJIT_LIBLLVM_PATH"

INSTALL_HINT = (
    "Dr.Jit needs libLLVM >= 16 for its CPU backend (LLVM 15 aborts the process inside kernels). "
    "Install one, e.g. on Debian 12 / Ubuntu: 'sudo apt-get install libllvm19' "
    "(or libllvm16/17/18); on macOS: 'brew install llvm'. "
    f"Or point {ENV_VAR} at a libLLVM.so of version >= 16."
)


class LLVMNotFoundError(SetupError):
    """No libLLVM >= 16 could be found for Dr.Jit's CPU backend."""


@dataclass(frozen=True)
class LLVMLibrary:
    path: Path
    major: int | None  # None when the version cannot be told from the file name
    source: str  # "environment" or "search"


_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)

_VERSION_RE = re.compile(r"libLLVM[-.](?:so\.)?(\d+)")


def _major_from_name(path: Path) -> int | None:
    for name in (path.name, os.path.realpath(path)):
        m = _VERSION_RE.search(os.path.basename(name))
        if m:
            return int(m.group(1))
    return None


def candidates() -> list[LLVMLibrary]:
    """All libLLVM files found on this machine with major >= 16, newest first."""
    dirs = list(_SEARCH_DIRS) + sorted(glob.glob("/usr/lib/llvm-*/lib"), reverse=True)
    found: dict[str, LLVMLibrary] = {}
    ext = "dylib" if platform.system() == "Darwin" else "so"
    for d in dirs:
        for pattern in (f"libLLVM-*.{ext}*", f"libLLVM.{ext}*", f"libLLVM.{ext}"):
            for p in glob.glob(os.path.join(d, pattern)):
                path = Path(p)
                major = _major_from_name(path)
                if major is None or major < MIN_LLVM_MAJOR:
                    continue
                real = os.path.realpath(path)
                found.setdefault(real, LLVMLibrary(path, major, "search"))
    return sorted(found.values(), key=lambda lib: (-(lib.major or 0), len(str(lib.path))))


def find() -> LLVMLibrary:
    """The libLLVM Dr.Jit should use.

    Raises:
        LLVMNotFoundError: ``DRJIT_LIBLLVM_PATH`` names a missing file, or no libLLVM >= 16 exists.
    """
    env = os.environ.get(ENV_VAR)
    if env:
        path = Path(env)
        if not path.is_file():
            raise LLVMNotFoundError(f"{ENV_VAR}={env} does not name an existing file. {INSTALL_HINT}")
        major = _major_from_name(path)
        if major is not None and major < MIN_LLVM_MAJOR:
            raise LLVMNotFoundError(f"{ENV_VAR}={env} is LLVM {major}. {INSTALL_HINT}")
        return LLVMLibrary(path, major, "environment")
    libs = candidates()
    if not libs:
        raise LLVMNotFoundError(f"No libLLVM >= {MIN_LLVM_MAJOR} found on this machine. {INSTALL_HINT}")
    return libs[0]


_configured: LLVMLibrary | None = None
_error: LLVMNotFoundError | None = None


def configure() -> None:
    """Set ``DRJIT_LIBLLVM_PATH`` to the library :func:`find` picks (no-op when set already).

    Never raises: a failure is kept and raised by :func:`require`, so that the NumPy/PyTorch
    parts of ctxreg (SE(3), geometry, CT input) work on a machine without LLVM.
    """
    global _configured, _error
    try:
        _configured = find()
        os.environ[ENV_VAR] = str(_configured.path)
        _error = None
    except LLVMNotFoundError as e:
        _error = e


def require() -> LLVMLibrary:
    """The configured library, or the :class:`LLVMNotFoundError` met by :func:`configure`."""
    if _configured is None and _error is None:
        configure()
    if _error is not None:
        raise _error
    assert _configured is not None
    return _configured
