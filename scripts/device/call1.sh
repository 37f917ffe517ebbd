# Device call 1: install, probe, time 60 iterations per variant, then the real run with the faster
# one until DEADLINE (s after the start); always leaves checkpoint + logs in $OUT.
#   bash .devbundle/call1.sh 560
set -o pipefail
T_START=$SECONDS; DEADLINE=${1:-560}
source .devbundle/device.sh
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 -c 'import torch, sys; print("python", sys.version.split()[0], "torch", torch.__version__, "threads", torch.get_num_threads())'
echo "--- probes: OptiX / CUDA driver libs, libLLVM (Dr.Jit's CPU backend needs LLVM >= 16's C API)"
ldconfig -p | grep -iE "optix|libcuda\.so|libLLVM"; ls -d /usr/lib/llvm-* 2>/dev/null
LLVM_OK=
for f in $(timeout 40 find /usr /opt -xdev \( -name 'libLLVM*.so*' -o -name 'libllvmlite.so' \) 2>/dev/null | head -20); do
  if python3 -c "import ctypes, sys; l = ctypes.CDLL(sys.argv[1]); l.LLVMOrcCreateLLJIT; l.LLVMGetVersion" $f 2>/dev/null; then
    echo "LLVM C API in $f"; [ -z "$LLVM_OK" ] && LLVM_OK=$f
  else echo "no LLVM C API in $f"; fi
done
if ! python3 -c "import sim.projection.llvm as l; print('sim.projection.llvm finds', l.find())" && [ -n "$LLVM_OK" ]; then
  export DRJIT_LIBLLVM_PATH=$LLVM_OK; echo "DRJIT_LIBLLVM_PATH=$LLVM_OK"
fi
for v in cuda_ad_mono llvm_ad_mono; do
  timeout 120 python3 -c "
import sim, mitsuba as mi, drjit as dr, pymeshlab, xraylib, spekpy, nibabel, pydicom
from sim.projection.backend import ensure_variant
print('$v ->', ensure_variant('$v'), 'mitsuba', mi.__version__, 'drjit', dr.__version__, 'pymeshlab filters', len(pymeshlab.filter_list()))
" 2>&1 | tail -4 | tee $OUT/import_$v.txt
done
best=; best_rate=-1
for v in cuda_ad_mono llvm_ad_mono; do
  grep -q "^$v -> $v" $OUT/import_$v.txt || { echo "skip timing $v (import failed)"; continue; }
  [ -z "$best" ] && best=$v
  sed -e "s#^out = .*#out = \"/tmp/time_$v\"#" -e "s#^iterations = .*#iterations = ${TIME_ITERS:-60}#" \
      -e "s#^val_every = .*#val_every = ${TIME_ITERS:-60}#" -e "s#^checkpoint_every = .*#checkpoint_every = ${TIME_ITERS:-60}#" \
      -e "s#^dataset = .*#dataset = \"$DEV_ROOT/campaigns/pelvis_vp.toml\"#" \
      -e "s#^init_from = .*#init_from = \"$DEV_ROOT/models/pelvis_line/model.pt\"#" \
      configs/train_field_tone_gpu.toml > /tmp/time_$v.toml
  echo "--- timing $v (60 iterations)"
  CTXREG_VARIANT=$v timeout 150 $CTX train /tmp/time_$v.toml 2>&1 | $TS | tee $OUT/time_$v.log | tail -4
  r=$(python3 .devbundle/rate.py $OUT/time_$v.log); echo "RATE $v: $r" | tee -a $OUT/rates.txt
  rv=${r%% *}
  if python3 -c "import sys; sys.exit(0 if float('$rv') > float('$best_rate') else 1)"; then best=$v; best_rate=$rv; fi
done
[ -z "$best" ] && { echo "no variant imports: stopping"; source .devbundle/finish.sh; exit 1; }
echo "best variant: $best ($best_rate it/s)" | tee -a $OUT/rates.txt; echo "$best ${DRJIT_LIBLLVM_PATH:-}" > $OUT/variant.txt
left=$((DEADLINE - (SECONDS - T_START)))
echo "--- real run with $best for $left s"
resume=; [ -f runs/gpu_field_tone/checkpoint.pt ] && resume=--resume
CTXREG_VARIANT=$best timeout $left $CTX train configs/train_field_tone_gpu.toml $resume 2>&1 | $TS | tee $OUT/train.log | grep -v "ETA"
echo "train exit ${PIPESTATUS[0]}"; tail -2 $OUT/train.log
source .devbundle/finish.sh
