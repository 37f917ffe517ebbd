"""Prefix each stdin line with seconds since start (device logs); steady rates come from two lines."""
import sys, time
t0 = time.time()
for line in sys.stdin:
    sys.stdout.write(f"[{time.time() - t0:7.1f}s] {line}")
    sys.stdout.flush()
