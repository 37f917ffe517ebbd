# Device calls 2+: carry .devbundle and runs/gpu_field_tone; resume, and stop right after the first
# checkpoint written past DEADLINE-110 s (checkpoint_every = 250 iterations, ~100 s at 2.5 it/s),
# at DEADLINE at the latest; then checkpoint + logs to $OUT.
#   bash .devbundle/resume.sh 560 cuda_ad_mono
set -o pipefail
T_START=$SECONDS; DEADLINE=${1:-560}; VARIANT=${2:-cuda_ad_mono}
source .devbundle/device.sh
C=runs/gpu_field_tone/checkpoint.pt
ls -la runs/gpu_field_tone/ && python3 .devbundle/ckpt_iter.py $C
echo "--- resume with $VARIANT, deadline ${DEADLINE} s"
CTXREG_VARIANT=$VARIANT $CTX train configs/train_field_tone_gpu.toml --resume > >($TS > $OUT/train.log) 2>&1 &
pid=$!
soft=$((DEADLINE - 110)); se=
while kill -0 $pid 2>/dev/null; do
  el=$((SECONDS - T_START))
  if [ $el -ge $DEADLINE ]; then echo "hard stop at $el s"; kill $pid; break; fi
  if [ $el -ge $soft ]; then
    [ -z "$se" ] && se=$(date +%s)
    if [ "$(stat -c %Y $C)" -gt "$se" ]; then sleep 2; echo "stop after checkpoint at $el s"; kill $pid; break; fi
  fi
  sleep 1
done
wait $pid; echo "train exit $?"; sleep 1
grep -v ETA $OUT/train.log | tail -8; tail -1 $OUT/train.log
source .devbundle/finish.sh
