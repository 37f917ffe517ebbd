# Device side of a batched-pairs config (default configs/train_batched_gpu.toml; see
# batched_bundle.sh): probes, then trains on CUDA for BUDGET seconds in all (stopping with a
# checkpoint: ctxreg train --stop-after), resuming from the config's out folder's checkpoint when it
# was carried; checkpoint and log.csv to $OUT.
#   bash scripts/device/batched.sh 540 [configs/train_batched_small_gpu.toml]
set -o pipefail
T0=$SECONDS; BUDGET=${1:-540}; CONFIG=${2:-configs/train_batched_gpu.toml}
R=$PWD; B=$R/.devbundle_batched
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 -c 'import sys, torch, torchvision, numpy, scipy; print("python", sys.version.split()[0], "torch", torch.__version__, "torchvision", torchvision.__version__, "numpy", numpy.__version__, "scipy", scipy.__version__, "cuda", torch.cuda.is_available())' || { echo "missing packages: stopping"; exit 1; }
# the checkpoint records absolute config paths: train where the workstation does (/work/main)
ROOT=/work/main
if [ "$R" != "$ROOT" ]; then
  if mkdir -p $ROOT 2>/dev/null; then (tar --exclude=./.devbundle_batched -cf - .) | (cd $ROOT && tar -xf -); else ROOT=$R; echo "WARNING: training in $R"; fi
fi
mkdir -p $ROOT/../shared/data/ct && cp $B/pelvis_abdomen_3mm.nii.gz $ROOT/../shared/data/ct/
cd $ROOT
export PYTHONPATH=$B/site:$ROOT PYTHONUNBUFFERED=1 MPLBACKEND=Agg OMP_NUM_THREADS=8
RUN=$(python3 -c "import sys, tomllib, os; c = tomllib.load(open(sys.argv[1], 'rb'))['train']; print(os.path.normpath(os.path.join(os.path.dirname(sys.argv[1]), c['out'])))" $CONFIG)
resume=; [ -f $RUN/checkpoint.pt ] && resume=--resume
left=$((BUDGET - (SECONDS - T0) - 75))
echo "set-up $((SECONDS - T0)) s; $CONFIG -> $RUN: training for $left s $resume"
# learn's own entry (ctxreg train's run_train), so that nothing of register/ is imported
python3 -c "from learn.commands import TrainCommand, run_train; run_train(TrainCommand(config='$CONFIG', resume=bool('$resume'), device='cuda', stop_after=float($left)))" 2>&1 \
  | python3 $R/scripts/device/ts.py | tr '\r' '\n' | grep -v "ETA" | tee $OUT/train.log | tail -40
cp $RUN/checkpoint.pt $RUN/log.csv $OUT/ 2>/dev/null
ls -la $OUT; echo "call used $((SECONDS - T0)) s"
