#!/usr/bin/env bash
# Set up (if needed), then simulate a realistic X-ray of the pelvis CT (../shared/data; the built-in
# phantom without it) far from AP and register it from AP with the shipped model into out/demo/.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
bash "$root/scripts/setup.sh"
cd "$root"
exec .venv/bin/ctxreg demo "$@"
