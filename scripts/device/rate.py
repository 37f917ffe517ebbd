"""Steady iterations/s from a ts.py-stamped training log: between the first progress line at or
after iteration 5 and the last one (JIT compilation and set-up excluded)."""
import re, sys
pts = []
for line in open(sys.argv[1]):
    m = re.match(r"\[\s*([\d.]+)s\] train \S+: (\d+)/\d+ iterations", line)
    if m:
        pts.append((float(m.group(1)), int(m.group(2))))
pts = [p for p in pts if p[1] >= 5]
if len(pts) >= 2 and pts[-1][0] > pts[0][0]:
    (t0, i0), (t1, i1) = pts[0], pts[-1]
    print(f"{(i1 - i0) / (t1 - t0):.3f} it/s  ({i1 - i0} iterations in {t1 - t0:.1f} s, from iteration {i0})")
else:
    print("0 it/s (too few progress lines)")
