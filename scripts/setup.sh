#!/usr/bin/env bash
# ctxreg set-up, safe to re-run: a libLLVM >= 16 for Dr.Jit, and the virtual environment .venv
# with the pinned packages of pyproject.toml (reinstalled only when pyproject.toml changes).
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
PY=${PYTHON:-python3}

if ! "$PY" -c 'import sys; sys.exit(sys.version_info[:2] < (3, 11))' 2>/dev/null; then
    echo "ctxreg setup: Python >= 3.11 is needed (found: $("$PY" --version 2>&1)); set PYTHON=..." >&2
    exit 1
fi

llvm_found() {
    [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -f "$DRJIT_LIBLLVM_PATH" ] && return 0
    local f
    for f in /usr/lib/*/libLLVM-{16,17,18,19,20,21}*.so* /usr/lib/llvm-{16,17,18,19,20,21}/lib/libLLVM*.so* \
             /usr/lib64/libLLVM-{16,17,18,19,20,21}*.so* /usr/lib64/libLLVM.so.{16,17,18,19,20,21}*; do
        [ -e "$f" ] && return 0
    done
    return 1
}

if ! llvm_found; then
    if command -v apt-get >/dev/null 2>&1; then
        sudo=""; [ "$(id -u)" = 0 ] || sudo="sudo"
        echo "ctxreg setup: installing libllvm19 (Dr.Jit needs LLVM >= 16; LLVM 15 aborts in kernels)"
        $sudo apt-get update -qq
        $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null \
            || $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm16 >/dev/null
    fi
    if ! llvm_found; then
        echo "ctxreg setup: no libLLVM >= 16 found. Install one (Debian/Ubuntu: apt-get install libllvm19;" \
             "macOS: brew install llvm) or set DRJIT_LIBLLVM_PATH to its libLLVM.so." >&2
        exit 1
    fi
fi

want=$(cat pyproject.toml | sha256sum | cut -d' ' -f1)
stamp=.venv/.ctxreg-setup
if [ ! -x .venv/bin/python ]; then
    echo "ctxreg setup: creating .venv"
    "$PY" -m venv .venv
fi
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "ctxreg setup: installing pinned packages into .venv (a few minutes the first time)"
    # pip's notes about this machine's unused local package indexes are dropped; errors stay
    pip_quiet() { .venv/bin/python -m pip "$@" 2>&1 | { grep -v -e "is ignored: it is neither" || true; }; }
    pip_quiet install -q --upgrade pip
    # setuptools' banner on every editable install ("folders ... with the same name as your package"):
    # the layout is known (sim/, learn/, register/ are the packages), so it says nothing here
    PYTHONWARNINGS="ignore::UserWarning:setuptools.command.editable_wheel" pip_quiet install -q -e ".[dev]"
    echo "$want" > "$stamp"
fi
