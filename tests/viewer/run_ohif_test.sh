#!/usr/bin/env bash
# The SEG in a real viewer (ohif_test.mjs): writes the SEG and the intensity series with the
# interslice CLI, serves the pinned prebuilt OHIF (ohif/ohif-app.pin) against a real Orthanc with
# DICOMweb and checks in headless chromium that the overlay tracks the anatomy.
#   bash tests/viewer/run_ohif_test.sh BIN_DIR CASE [--displaced]
# CASE: phantom (the shipped thick CT phantom), tilt (the real tilted CT of tests/data/ct-tilt), uneven (the phantom with gaps). --displaced runs the same check against a copy of
# the SEG moved 12 columns and succeeds only if the check FAILS on it (the test can fail).
# Needs node, npm (first run), chromium and Orthanc with its DICOMweb plugin.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
bin_dir="${1:?usage: run_ohif_test.sh BIN_DIR CASE [--displaced]}"
case_name="${2:?usage: run_ohif_test.sh BIN_DIR CASE [--displaced]}"
displaced="${3:-}"
interslice="$bin_dir/interslice"
[ -x "$interslice" ] || { echo "FAIL: no interslice executable in $bin_dir"; exit 1; }

if [ ! -f "$here/node_modules/.package-lock.json" ] ||
   [ "$here/package-lock.json" -nt "$here/node_modules/.package-lock.json" ]; then
  npm ci --prefix "$here" --no-audit --no-fund --ignore-scripts
fi
dist="$(bash "$here/ohif/fetch_ohif.sh" | tail -n 1)"

tmp="$(mktemp -d "${TMPDIR:-/tmp}/ohif-test.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT

case "$case_name" in
  phantom)
    threshold=300
    "$interslice" run "$repo/data/ct-head-phantom-thick" --threshold $threshold --method direct \
      --roi 200,150,0,300,250,28 --seg --output-series intensity --volume nii --mesh none \
      --out "$tmp/out" --quiet
    ;;
  tilt)
    # a real gantry-tilted head CT (tests/data/ct-tilt, three slices of dcm_qa_ct: the slice plane
    # tilted 18.5 degrees about the patient x axis)
    threshold=300
    "$interslice" run "$repo/tests/data/ct-tilt" --threshold $threshold --method direct \
      --roi 150,150,0,350,350,2 --seg --output-series intensity --volume nii --mesh none \
      --out "$tmp/out" --quiet
    ;;
  uneven)
    # the shipped phantom with three slices left out (I100, I110, I200): gaps of 2, 3 and 4 times
    # the spacing in one series
    mkdir "$tmp/uneven"
    for f in "$repo"/data/ct-head-phantom-thick/I*.dcm; do
      case "$(basename "$f")" in I100.dcm | I110.dcm | I200.dcm) ;; *) cp "$f" "$tmp/uneven/" ;; esac
    done
    threshold=300
    "$interslice" run "$tmp/uneven" --threshold $threshold --method direct \
      --roi 200,150,0,300,250,25 --seg --output-series intensity --volume nii --mesh none \
      --out "$tmp/out" --quiet
    ;;
  *)
    echo "FAIL: unknown case $case_name"
    exit 1
    ;;
esac

seg="$tmp/out/seg.dcm"
if [ "$displaced" = "--displaced" ]; then
  node "$here/make_displaced_seg.mjs" "$seg" "$tmp/seg-displaced.dcm" 12
  seg="$tmp/seg-displaced.dcm"
fi
rc=0
node "$here/ohif_test.mjs" --dist "$dist" --series "$tmp/out/series-intensity" --seg "$seg" \
  --mask "$tmp/out/mask.nii.gz" --threshold "$threshold" || rc=$?
if [ "$displaced" = "--displaced" ]; then
  if [ "$rc" -eq 1 ]; then
    echo "PASS: the check failed on the displaced SEG, as it must"
    exit 0
  fi
  echo "FAIL: the check did not fail on a SEG displaced by 12 columns (exit $rc)"
  exit 1
fi
exit "$rc"
