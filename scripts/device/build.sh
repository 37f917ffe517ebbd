#!/usr/bin/env bash
# Build .devbundle/ (git-ignored) from scripts/device/: what the lent GPU machine (Python 3.12, torch, no mitsuba etc.,
# no internet) needs to run `ctxreg train configs/train_field_tone_gpu.toml` there.
#
#   bash scripts/device/build.sh            # build site.tar.xz, spekpy shim, code snapshot, CT copy
#   bash scripts/device/build.sh --test311  # also: same stripping applied to the local venv's cp311
#                                       # packages, then 3 training iterations with them here
#
# .devbundle/ is git-ignored through .git/info/exclude (line /.devbundle/), so it travels to the
# device only when a `run` names it in `carry` (with runs/gpu_field_tone when resuming).
#
# Contents:
#   site.tar.xz   cp312 site dir, extracted to /tmp/site on the device:
#                 mitsuba 3.9.1 (only llvm_ad_mono / cuda_ad_mono + the 7 plugins ctxreg loads + a few
#                 defaults), drjit 1.5.0, pymeshlab 2025.7.post1 (only the 5 filter plugins
#                 sim/distractors.py uses and their NEEDED closure), xraylib 4.3.0, nibabel 5.4.2,
#                 pydicom 3.0.2, and a spekpy shim (spectra precomputed here with spekpy 2.5.4)
#   syslibs/      libGL & co. from this machine, copied to the device's LD_LIBRARY_PATH only where
#                 the device lacks them (pymeshlab's Qt needs libGL.so.1 / libOpenGL.so.0)
#   src/          snapshot of sim/ learn/ register/ (the code tested here; the working tree is
#                 being edited concurrently), copied over the device's copy of the repo
#   pelvis_abdomen_3mm.nii.gz  the CT (../shared does not travel)
#   device.sh     sourced first by every device command: installs all of the above (site to
#                 /tmp/site, missing syslibs to /tmp/syslibs + LD_LIBRARY_PATH, code snapshot over
#                 the device's checkout, the CT to ../shared/data/ct); ctxreg.py = the CLI entry
#   call1.sh      first call: probes, 60-iteration timing of cuda_ad_mono and llvm_ad_mono, then
#                 the real run with the faster variant until its deadline
#   resume.sh     later calls: --resume, stopping just after the first checkpoint written past
#                 DEADLINE-110 s (hard stop at DEADLINE); finish.sh copies checkpoint + log.csv to $OUT
#
# Device calls used on 2026-11-24 (run tool, kind nvidia-h100-x1; the device's checkout is at
# /work/main there too, so the checkpoint's absolute paths match the workstation's):
#   run(command="bash .devbundle/call1.sh 555 2>&1", carry=[".devbundle"], timeout_s=600)
#   # then, after each call: cp $files_at/checkpoint.pt $files_at/log.csv runs/gpu_field_tone/
#   # (keep nothing else under runs/gpu_field_tone: it is carried, and the tree must stay < 64 MiB)
#   run(command="bash .devbundle/resume.sh 555 cuda_ad_mono 2>&1", carry=[".devbundle", "runs/gpu_field_tone"], timeout_s=600)
#   run(command="bash .devbundle/resume.sh 560 cuda_ad_mono 2>&1", carry=[".devbundle", "runs/gpu_field_tone"], timeout_s=600)
#   run(command="bash .devbundle/resume.sh 130 cuda_ad_mono 2>&1", carry=[".devbundle", "runs/gpu_field_tone"], timeout_s=150)
set -euo pipefail
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
REPO=$(cd "$HERE/../.." && pwd)
B=$REPO/.devbundle
mkdir -p "$B"
grep -qx '/.devbundle/' "$REPO/.git/info/exclude" 2>/dev/null || { mkdir -p "$REPO/.git/info"; echo /.devbundle/ >> "$REPO/.git/info/exclude"; }
# the device-side scripts travel in the bundle
[ "$HERE" = "$B" ] || cp "$HERE"/*.sh "$HERE"/*.py "$B"/
WHL=${WHL:-/tmp/whl}
STAGE=${STAGE:-/tmp/devbundle_stage}
PY=$REPO/.venv/bin/python

mkdir -p "$WHL"
dl() {  # cp312 manylinux wheel, no deps
  ls "$WHL"/$1-$2-*.whl >/dev/null 2>&1 && return 0
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_35_x86_64 --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any -d "$WHL" "$1==$2"
}
dl mitsuba 3.9.1; dl drjit 1.5.0; dl pymeshlab 2025.7.post1; dl xraylib 4.3.0; dl nibabel 5.4.2; dl pydicom 3.0.2

# ---- stripping rules (applied to a site dir holding mitsuba/ drjit/ pymeshlab/) -------------------
MI_KEEP_PLUGINS="box diffuse hdrfilm independent merge perspective uniform srgb d65 regular irregular stratified path direct"
strip_mitsuba() {  # $1 = site dir
  local m=$1/mitsuba
  for f in "$m"/*.cpython-*.so; do
    case $(basename "$f") in llvm_ad_mono.*|cuda_ad_mono.*|mitsuba_ext.*|mitsuba_alias.*) ;; *) rm -f "$f";; esac
  done
  for f in "$m"/plugins/*.so; do
    local n; n=$(basename "$f" .so)
    case " $MI_KEEP_PLUGINS " in *" $n "*) ;; *) rm -f "$f";; esac
  done
  # data/srgb.coeff is the RGB->spectrum table of the spectral variants; mono runs without it (tested)
  rm -rf "$m"/include "$m"/cmake "$m"/pkgconfig "$m"/mitsuba "$m"/data/sunsky "$m"/data/srgb.coeff \
         "$m"/python/test "$m"/__pycache__
  find "$m" -name '*.pyi' -delete
  rm -rf "$1"/drjit/include "$1"/drjit/cmake
  find "$1"/drjit -name '*.pyi' -delete
}
PML_KEEP_PLUGINS="libfilter_create.so libfilter_clean.so libfilter_meshing.so libfilter_measure.so libfilter_mesh_booleans.so"
strip_pymeshlab() {  # $1 = site dir; keeps the plugins above and the NEEDED closure inside pymeshlab/
  local p=$1/pymeshlab
  rm -rf "$p"/tests "$p"/__pycache__
  for f in "$p"/lib/plugins/*; do
    case " $PML_KEEP_PLUGINS " in *" $(basename "$f") "*) ;; *) rm -f "$f";; esac
  done
  local starts=("$p"/pmeshlab*.so)
  for n in $PML_KEEP_PLUGINS; do starts+=("$p/lib/plugins/$n"); done
  python3 "$B"/needed_closure.py "$p" "${starts[@]}" > "$STAGE/pml_closure_$(basename "$1").txt"
  grep '^EXTERNAL' "$STAGE/pml_closure_$(basename "$1").txt" >&2 || true
  # delete every lib/ file (not plugins) outside the closure
  ( cd "$p" && for f in lib/*; do [ -f "$f" ] || continue
      grep -qx "KEEP $f" "$STAGE/pml_closure_$(basename "$1").txt" || rm -f "$f"; done )
}

rm -rf "$STAGE" && mkdir -p "$STAGE/site"
S=$STAGE/site
for w in mitsuba drjit pymeshlab xraylib nibabel pydicom; do
  (cd "$S" && unzip -q -o "$WHL"/$w-*.whl)
done
# pymeshlab's wheel keeps the package under pymeshlab-*.data/purelib
if [ -d "$S"/pymeshlab-2025.7.post1.data ]; then
  mv "$S"/pymeshlab-2025.7.post1.data/purelib/pymeshlab "$S"/ && rm -rf "$S"/pymeshlab-2025.7.post1.data
fi
rm -rf "$S"/share "$S"/*.dist-info/RECORD
strip_mitsuba "$S"
strip_pymeshlab "$S"
# xraylib_np: only sim/physics/interactions.py (Monte Carlo scatter, not in this config's scatter
# choices) imports it, and it repeats _xraylib's 18 MB of tables; test data of nibabel / pydicom
rm -f "$S"/xraylib_np.cpython-*.so
find "$S"/nibabel -type d -name tests -prune -exec rm -rf {} +
rm -rf "$S"/pydicom/data/test_files
# mitsuba: check the NEEDED closure of what is kept (every NEEDED resolved in the package or external)
python3 "$B"/needed_closure.py "$S" "$S"/mitsuba/*.so "$S"/mitsuba/plugins/*.so "$S"/drjit/*.so \
  > "$STAGE/mi_closure.txt"
echo "mitsuba/drjit external NEEDED:" >&2; grep '^EXTERNAL' "$STAGE/mi_closure.txt" >&2 || true

# ---- spekpy shim: the unfiltered spectra ctxreg asks for (anode 12 deg, dk 0.25, 20-150 kV in 5 kV) --
mkdir -p "$S"/spekpy
"$PY" "$B"/make_spekpy_shim.py "$S"/spekpy

# ---- pack ----------------------------------------------------------------------------------------
find "$S" -name __pycache__ -prune -exec rm -rf {} +
du -sh "$S"
tar -C "$S" -cf - . | xz -T0 -9e > "$B"/site.tar.xz
ls -la "$B"/site.tar.xz

# ---- system libraries the device may lack (installed there only where ldconfig lacks them) -------
rm -rf "$B"/syslibs && mkdir -p "$B"/syslibs
for l in libGL.so.1 libGLX.so.0 libGLdispatch.so.0 libOpenGL.so.0 libX11.so.6 libxcb.so.1 libXau.so.6 \
         libXdmcp.so.6 libbsd.so.0 libmd.so.0 libgmp.so.10 libcom_err.so.2; do
  cp -L /usr/lib/x86_64-linux-gnu/$l "$B"/syslibs/$l
done
xz -T0 -9 -f "$B"/syslibs/*.so.*

# ---- code snapshot and the CT --------------------------------------------------------------------
rm -rf "$B"/src && mkdir -p "$B"/src
for d in sim learn register; do cp -a "$REPO/$d" "$B/src/"; done
find "$B"/src -name __pycache__ -prune -exec rm -rf {} +
cp $REPO/../shared/data/ct/pelvis_abdomen_3mm.nii.gz "$B"/
du -sh "$B"; du -sh "$B"/*

if [ "${1:-}" = "--test311" ]; then
  # the same stripping on the local cp311 packages, and 3 training iterations with them (CPU, llvm)
  T=/tmp/devtest311 && rm -rf $T && mkdir -p $T
  SP=$REPO/.venv/lib/python3.11/site-packages
  cp -a $SP/mitsuba $SP/drjit $SP/pymeshlab $T/
  strip_mitsuba $T; strip_pymeshlab $T
  mkdir -p $T/spekpy && tar -xJf "$B"/site.tar.xz -C $T ./spekpy
  sed -e 's#^out = .*#out = "/tmp/gpu_test311"#' -e 's#^iterations = .*#iterations = 3#' \
      -e 's#^val_every = .*#val_every = 3#' -e 's#^checkpoint_every = .*#checkpoint_every = 3#' \
      -e "s#^dataset = .*#dataset = \"$REPO/campaigns/pelvis_vp.toml\"#" \
      -e "s#^init_from = .*#init_from = \"$REPO/models/pelvis_line/model.pt\"#" \
      $REPO/configs/train_field_tone_gpu.toml > /tmp/gpu_test311.toml
  rm -rf /tmp/gpu_test311
  (cd $REPO && PYTHONPATH=$T:$B/src PYTHONUNBUFFERED=1 CTXREG_VARIANT=llvm_ad_mono \
     $PY -c 'import sys; from register.cli import main; sys.argv[0]="ctxreg"; main()' train /tmp/gpu_test311.toml)
fi
