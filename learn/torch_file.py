"""Reading a PyTorch file safely: tensors and plain data only, every refusal one line naming the file.

``torch.load(..., weights_only=True)`` never runs code from the file; :func:`read_plain_torch_file`
adds the checks that turn an empty, truncated, foreign or code-carrying file into one line (a
checkpoint, :mod:`learn.checkpoint`; ImageNet weights, :mod:`learn.model`), each caller raising its
own error class.
"""

from __future__ import annotations

import pickle
import re
import zipfile
from pathlib import Path

import numpy as np
import torch

__all__ = ["read_plain_torch_file", "first_line"]

#: First bytes of a torch.save file (a zip archive, PyTorch 1.6 and later)
_ZIP_MAGIC = b"PK\x03\x04"
#: First bytes of a torch.save file in the format before PyTorch 1.6 (a pickled magic number)
_LEGACY_MAGIC = b"\x80\x02\x8a\x0a"


def _numpy_array_globals() -> list:
    """What a version-0 file's NumPy random state needs besides tensors and plain data (arrays
    of numbers only: a NumPy array's pickle names these and nothing that runs code)."""
    reconstruct = np._core.multiarray._reconstruct if hasattr(np, "_core") else np.core.multiarray._reconstruct
    return [(reconstruct, "numpy._core.multiarray._reconstruct"),
            (reconstruct, "numpy.core.multiarray._reconstruct"), np.ndarray, np.dtype,
            *(type(np.dtype(t)) for t in ("uint32", "int64", "float64"))]


_ALLOWED_NUMPY = {"numpy._core.multiarray._reconstruct", "numpy.core.multiarray._reconstruct", "numpy.ndarray",
                  "numpy.dtype", "numpy.dtypes.UInt32DType", "numpy.dtypes.Int64DType", "numpy.dtypes.Float64DType"}


def read_plain_torch_file(path: str | Path, what: str, *, error: type[Exception], allow_numpy: bool = False):
    """``torch.load(path, weights_only=True)`` with one-line errors.

    Refuses (raising ``error`` with a message that starts with ``"<what> <path>"``): a missing
    file, a folder, an empty file, a truncated or corrupt one, a file that is not a PyTorch
    file, and a file that pickles any object other than tensors and plain data (such a file
    could run code when loaded; nothing of it is executed here). ``allow_numpy`` also accepts
    NumPy arrays of numbers (version-0 checkpoints).
    """
    path = Path(path)
    name = f"{what} {path}"
    if not path.exists():
        raise error(f"{name} not found")
    if not path.is_file():
        raise error(f"{name} is not a file")
    size = path.stat().st_size
    if size == 0:
        raise error(f"{name} is empty (0 bytes): was its write interrupted?")
    with open(path, "rb") as f:
        head = f.read(4)
    unsafe: set[str] = set()
    if head == _ZIP_MAGIC:  # torch.save's format since PyTorch 1.6
        if not zipfile.is_zipfile(path):
            raise error(f"{name} is truncated or corrupt ({size} bytes, an incomplete zip archive): was its write "
                        f"interrupted? Use an intact copy")
        try:
            unsafe = set(torch.serialization.get_unsafe_globals_in_checkpoint(path))
        except ValueError as e:  # a zip archive, but no torch.save pickle in it (e.g. TorchScript)
            raise error(f"{name} is not a torch.save file ({first_line(e)})") from None
        except (RuntimeError, KeyError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError) as e:
            raise error(f"{name} is corrupt ({first_line(e)})") from None
    elif head != _LEGACY_MAGIC:  # the format before 1.6 (e.g. torchvision's ImageNet files): torch.load checks
        raise error(f"{name} is not a PyTorch file (torch.save writes a zip archive; this one starts with "
                    f"{head!r})")
    if allow_numpy:
        unsafe -= _ALLOWED_NUMPY
    if unsafe:
        shown = ", ".join(sorted(unsafe)[:3]) + (f" and {len(unsafe) - 3} more" if len(unsafe) > 3 else "")
        raise error(f"{name} contains objects other than tensors and plain data ({shown}); refused: loading it "
                    f"could run code. Only load files whose source you trust, re-saved as tensors and plain data")
    try:
        if allow_numpy:
            with torch.serialization.safe_globals(_numpy_array_globals()):
                return torch.load(path, map_location="cpu", weights_only=True)
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:  # weights_only's refusal (never executed) or a broken pickle stream
        detail = re.search(r"WeightsUnpickler error: ([^\n]*)", str(e))
        detail = detail.group(1).strip() if detail else first_line(e)
        if re.search(r"Unsupported (global|class)|allowed global", detail):
            # (in the pre-1.6 format a cut stream can also end in a cut, unknown name)
            damaged = "" if head == _ZIP_MAGIC else ", or it is damaged"
            raise error(f"{name} contains objects other than tensors and plain data{damaged}; refused: loading it "
                        f"could run code ({detail[:200]})") from None
        raise error(f"{name} is truncated or corrupt ({detail[:200]})") from None
    # torch raises these for a damaged archive (bad CRC, missing record, cut pickle stream)
    except (RuntimeError, EOFError, KeyError, ValueError, zipfile.BadZipFile) as e:
        raise error(f"{name} is truncated or corrupt ({first_line(e)})") from None


def first_line(e: BaseException) -> str:
    """``Type: first line of the message`` (at most 200 characters) of an exception, for one-line errors."""
    text = str(e).strip().splitlines()
    line = text[0] if text else ""
    line = line[:200] + ("..." if len(line) > 200 else "")
    return f"{type(e).__name__}: {line}" if line else type(e).__name__
