"""Mitsuba 3 / Dr.Jit set-up: pick a variant, check libLLVM, register ctxreg's plugins.

Only this module (and the modules that call :func:`ensure_variant`) imports Mitsuba. Variants:
``llvm_ad_mono`` on the CPU (default), ``cuda_ad_mono`` where an NVIDIA GPU and Mitsuba's CUDA
build are available. The environment variable ``CTXREG_VARIANT`` overrides the choice.
"""

from __future__ import annotations

import os

from sim.projection import llvm
from sim.core.errors import SetupError

DEFAULT_CPU_VARIANT = "llvm_ad_mono"
DEFAULT_GPU_VARIANT = "cuda_ad_mono"
SUPPORTED_VARIANTS = (DEFAULT_CPU_VARIANT, DEFAULT_GPU_VARIANT)


class BackendError(SetupError):
    """Mitsuba / Dr.Jit cannot run here (no usable libLLVM, unknown variant, no GPU)."""


_registered = False


def _cuda_available() -> bool:
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # noqa: BLE001 - any failure to probe CUDA means "no CUDA"
        return False


def ensure_variant(variant: str | None = None) -> str:
    """Set the Mitsuba variant (once per process) and register ctxreg's plugins.

    Args:
        variant: ``"llvm_ad_mono"``, ``"cuda_ad_mono"`` or None for the default (``CTXREG_VARIANT``,
            else CUDA when available, else LLVM).

    Returns:
        The variant in use.

    Raises:
        BackendError: unsupported variant, or a CPU variant without libLLVM >= 16.
    """
    global _registered
    import mitsuba as mi

    current = mi.variant()
    if variant is None:
        variant = os.environ.get("CTXREG_VARIANT") or current
    if variant is None:
        variant = DEFAULT_GPU_VARIANT if _cuda_available() else DEFAULT_CPU_VARIANT
    if variant not in SUPPORTED_VARIANTS:
        raise BackendError(f"unsupported Mitsuba variant {variant!r}; use one of {SUPPORTED_VARIANTS}")
    if variant.startswith("llvm"):
        try:
            llvm.require()
        except llvm.LLVMNotFoundError as e:
            raise BackendError(str(e)) from None
    if current != variant:
        if current is not None and _registered:
            raise BackendError(
                f"Mitsuba variant is already {current!r} in this process; cannot switch to {variant!r}"
            )
        mi.set_variant(variant)
        if variant.startswith("llvm"):
            import drjit as dr

            major = dr.detail.llvm_version()[0]
            if major < llvm.MIN_LLVM_MAJOR:
                raise BackendError(
                    f"Dr.Jit loaded LLVM {major} ({os.environ.get(llvm.ENV_VAR, 'its own search')}); "
                    + llvm.INSTALL_HINT
                )
    if not _registered:
        from sim.projection.integrators import drr  # noqa: F401  (registers 'ctxreg_drr')

        drr.register()
        _registered = True
    return variant
