"""Usage: needed_closure.py PKGROOT start1.so [start2.so ...]
Resolve DT_NEEDED transitively inside PKGROOT (searching RPATH/RUNPATH with $ORIGIN and all dirs of PKGROOT).
Prints KEEP files (relative to PKGROOT) and EXTERNAL sonames."""
import os, re, subprocess, sys
root = os.path.abspath(sys.argv[1])
index = {}
for d, _, fs in os.walk(root):
    for f in fs:
        index.setdefault(f, []).append(os.path.join(d, f))
def dyn(path):
    out = subprocess.run(['readelf', '-d', path], capture_output=True, text=True).stdout
    needed = re.findall(r'\(NEEDED\)\s+Shared library: \[(.+?)\]', out)
    rp = re.findall(r'\((?:RPATH|RUNPATH)\)\s+Library r(?:un)?path: \[(.+?)\]', out)
    return needed, [p for r in rp for p in r.split(':')]
keep, external, todo = set(), {}, [os.path.abspath(p) for p in sys.argv[2:]]
while todo:
    p = todo.pop()
    real = os.path.realpath(p)
    if p in keep: continue
    keep.add(p); keep.add(real)
    needed, rpaths = dyn(real)
    for n in needed:
        found = None
        for r in rpaths:
            cand = os.path.normpath(os.path.join(r.replace('$ORIGIN', os.path.dirname(p)), n))
            if os.path.exists(cand): found = cand; break
        if found is None and n in index:
            found = index[n][0]
            if not any(r for r in rpaths): print(f"# note: {n} for {os.path.relpath(p, root)} found by name only", file=sys.stderr)
        if found: todo.append(found)
        else: external.setdefault(n, set()).add(os.path.relpath(p, root))
for k in sorted(keep): print('KEEP', os.path.relpath(k, root))
for n, by in sorted(external.items()): print('EXTERNAL', n, 'by', ','.join(sorted(by))[:120])
