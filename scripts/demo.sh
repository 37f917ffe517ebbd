#!/usr/bin/env bash
# Set up (if needed), then render the built-in pelvis phantom at a few poses into out/demo/.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
bash "$root/scripts/setup.sh"
cd "$root"
exec .venv/bin/ctxreg demo "$@"
