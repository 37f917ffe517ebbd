# Sourced first by every device command (bash, repo root = cwd).  Installs .devbundle and moves to
# /work/main, a copy of the repo at the same absolute path as on the workstation, so that the
# checkpoint's absolute config paths (learn.train.load_train_config resolves them) match there.
# DEV_ROOT / SITE exist for a dry run on the workstation only (see build.sh); never run it with
# DEV_ROOT=/work/main on the workstation: it replaces sim/ learn/ register/ there.
T_START=${T_START:-$SECONDS}
R=$PWD
DEV_ROOT=${DEV_ROOT:-/work/main}; SITE=${SITE:-/tmp/site}
if [ "$DEV_ROOT" = /work/main ] && [ -d /work/main/.venv ]; then
  echo "device.sh: /work/main/.venv exists: this is the workstation, not the device"; exit 1
fi
if [ ! -f $SITE/.done ]; then
  mkdir -p $SITE && tar -xJf .devbundle/site.tar.xz -C $SITE && touch $SITE/.done
fi
mkdir -p /tmp/syslibs
for f in .devbundle/syslibs/*.xz; do
  n=$(basename "$f" .xz)
  if ldconfig -p | grep -qE "^\s*$n "; then :; else xz -dc "$f" > /tmp/syslibs/$n; echo "syslib carried: $n"; fi
done
export LD_LIBRARY_PATH=/tmp/syslibs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
if ! mkdir -p $DEV_ROOT 2>/dev/null || ! mkdir -p $DEV_ROOT/../shared/data/ct 2>/dev/null; then
  echo "WARNING: cannot create $DEV_ROOT or its ../shared: training in $R (checkpoint paths will differ)"
  DEV_ROOT=$R
fi
if [ "$R" != "$DEV_ROOT" ]; then
  mkdir -p $DEV_ROOT && (cd "$R" && tar --exclude=./.devbundle/site.tar.xz --exclude=./.venv -cf - .) | (cd $DEV_ROOT && tar -xf -)
fi
for d in sim learn register; do rm -rf $DEV_ROOT/$d && cp -a "$R"/.devbundle/src/$d $DEV_ROOT/$d; done
mkdir -p $DEV_ROOT/../shared/data/ct && cp "$R"/.devbundle/pelvis_abdomen_3mm.nii.gz $DEV_ROOT/../shared/data/ct/
cd $DEV_ROOT
export PYTHONPATH=$SITE:$DEV_ROOT PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-16} MPLBACKEND=Agg
CTX="python3 $DEV_ROOT/.devbundle/ctxreg.py"
TS="python3 $DEV_ROOT/.devbundle/ts.py"
echo "installed in $((SECONDS - T_START)) s; repo $R -> $PWD; nproc $(nproc)"
