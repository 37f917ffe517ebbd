# Sourced last: checkpoint and csv log to $OUT, whatever happened before.
cp runs/gpu_field_tone/checkpoint.pt runs/gpu_field_tone/log.csv "$OUT"/ 2>/dev/null
cp runs/gpu_field_tone/loss.png "$OUT"/ 2>/dev/null
ls -la "$OUT"
[ -f "$OUT"/checkpoint.pt ] && python3 .devbundle/ckpt_iter.py "$OUT"/checkpoint.pt 2>&1 | tail -1
echo "call used $((SECONDS - T_START)) s"
