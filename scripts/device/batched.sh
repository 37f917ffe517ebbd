# Device side of one or more batched-pairs configs (default configs/train_batched_gpu.toml; see
# batched_bundle.sh): probes, then trains every config at once on the one GPU for BUDGET seconds in
# all (each stopping with a checkpoint: ctxreg train --stop-after), each resuming from its out
# folder's checkpoint when that was carried; each run's checkpoint, log.csv and train.log go to
# $OUT/<run folder name>/ (a checkpoint over 15 MB in parts: cat checkpoint.pt.part.* > checkpoint.pt).
#   bash scripts/device/batched.sh 540 [CONFIG ...]
set -o pipefail
T0=$SECONDS; BUDGET=${1:-540}; shift; CONFIGS=("$@"); [ ${#CONFIGS[@]} -eq 0 ] && CONFIGS=(configs/train_batched_gpu.toml)
R=$PWD; B=$R/.devbundle_batched
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 -c 'import sys, torch, torchvision, numpy, scipy; print("python", sys.version.split()[0], "torch", torch.__version__, "torchvision", torchvision.__version__, "numpy", numpy.__version__, "scipy", scipy.__version__, "cuda", torch.cuda.is_available())' || { echo "missing packages: stopping"; exit 1; }
# the checkpoint records absolute config paths: train where the workstation does (/work/main)
ROOT=/work/main
if [ "$R" != "$ROOT" ]; then
  if mkdir -p $ROOT 2>/dev/null; then (tar --exclude=./.devbundle_batched -cf - .) | (cd $ROOT && tar -xf -); else ROOT=$R; echo "WARNING: training in $R"; fi
fi
mkdir -p $ROOT/../shared/data/ct && cp $B/pelvis_abdomen_3mm.nii.gz $ROOT/../shared/data/ct/
cd $ROOT
export PYTHONPATH=$B/site:$ROOT PYTHONUNBUFFERED=1 MPLBACKEND=Agg
# the 16 cores shared between the runs
export OMP_NUM_THREADS=$(( 16 / ${#CONFIGS[@]} > 1 ? 16 / ${#CONFIGS[@]} : 1 ))
left=$((BUDGET - (SECONDS - T0) - 75))
for CONFIG in "${CONFIGS[@]}"; do
  RUN=$(python3 -c "import sys, tomllib, os; c = tomllib.load(open(sys.argv[1], 'rb'))['train']; print(os.path.normpath(os.path.join(os.path.dirname(sys.argv[1]), c['out'])))" $CONFIG)
  NAME=$(basename $RUN); mkdir -p $OUT/$NAME
  # the committed resume state travels with the tree (resume/<name>/): a run with no checkpoint of
  # its own carried starts from it, so that only the tables need carrying (the tree's 64 MiB)
  if [ ! -f $RUN/checkpoint.pt ] && [ -f resume/$NAME/checkpoint.pt ]; then
    mkdir -p $RUN && cp resume/$NAME/checkpoint.pt resume/$NAME/log.csv $RUN/; echo "$NAME: from resume/$NAME"
  fi
  resume=; [ -f $RUN/checkpoint.pt ] && resume=--resume
  echo "set-up $((SECONDS - T0)) s; $CONFIG -> $RUN: training for $left s $resume"
  # learn's own entry (ctxreg train's run_train), so that nothing of register/ is imported
  ( python3 -c "from learn.commands import TrainCommand, run_train; run_train(TrainCommand(config='$CONFIG', resume=bool('$resume'), device='${DEVICE:-cuda}', stop_after=float($left)))" 2>&1 \
      | python3 $R/scripts/device/ts.py | tr '\r' '\n' | grep -v "ETA" > $OUT/$NAME/train.log
    cp $RUN/log.csv $OUT/$NAME/ 2>/dev/null
    # files come back up to 16 MiB each: a larger checkpoint (medium: 19 MB) comes in parts,
    # joined here with: cat checkpoint.pt.part.* > checkpoint.pt (sha256 in train.log)
    if [ -f $RUN/checkpoint.pt ]; then
      sha256sum $RUN/checkpoint.pt >> $OUT/$NAME/train.log
      if [ $(stat -c %s $RUN/checkpoint.pt) -gt 15000000 ]; then split -b 15000000 $RUN/checkpoint.pt $OUT/$NAME/checkpoint.pt.part.
      else cp $RUN/checkpoint.pt $OUT/$NAME/; fi
    fi ) &
done
wait
for d in $OUT/*/; do echo "== $d"; tail -15 $d/train.log; done
ls -laR $OUT; echo "call used $((SECONDS - T0)) s"
