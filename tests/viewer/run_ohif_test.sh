#!/usr/bin/env bash
# The SEG in a real viewer (ohif_test.mjs): writes the SEG and the intensity series with the
# interslice CLI, serves the pinned prebuilt OHIF (ohif/ohif-app.pin) against a real Orthanc with
# DICOMweb and checks in headless chromium that the overlay tracks the anatomy.
#   bash tests/viewer/run_ohif_test.sh BIN_DIR CASE [--displaced|--flipped-distance]
# CASE: phantom (the shipped thick CT phantom), tilt (the real tilted CT of tests/data/ct-tilt),
# uneven (the phantom with gaps). The phantom and tilt cases also send the distance map (Parametric
# Map) and the mesh (Encapsulated STL): the viewer must list the mesh and show the distance map's
# values where distance.nii.gz has them.
# --displaced runs the same check against a copy of the SEG moved 12 columns, --flipped-distance
# against a distance.nii.gz whose slices are reversed (what a viewer showing the map's frames in the
# wrong order would disagree with); each succeeds only if the check FAILS for that reason (the
# test can fail).
# Needs node, npm (first run), chromium and Orthanc with its DICOMweb plugin.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
bin_dir="${1:?usage: run_ohif_test.sh BIN_DIR CASE [--displaced|--flipped-distance]}"
case_name="${2:?usage: run_ohif_test.sh BIN_DIR CASE [--displaced|--flipped-distance]}"
variant="${3:-}"
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
      --roi 200,150,0,300,250,28 --output-series intensity,distance,mask --volume nii --mesh stl \
      --out "$tmp/out" --quiet
    ;;
  tilt)
    # a real gantry-tilted head CT (tests/data/ct-tilt, three slices of dcm_qa_ct: the slice plane
    # tilted 18.5 degrees about the patient x axis)
    threshold=300
    "$interslice" run "$repo/tests/data/ct-tilt" --threshold $threshold --method direct \
      --roi 150,150,0,350,350,2 --output-series intensity,distance,mask --volume nii --mesh stl \
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
others=()
if [ -f "$tmp/out/distance.dcm" ]; then
  distance="$tmp/out/distance.nii.gz"
  if [ "$variant" = "--flipped-distance" ]; then
    node "$here/make_flipped_distance.mjs" "$distance" "$tmp/distance-flipped.nii.gz"
    distance="$tmp/distance-flipped.nii.gz"
  fi
  others+=(--pmap "$tmp/out/distance.dcm" --distance "$distance")
fi
[ -f "$tmp/out/surface-stl.dcm" ] && others+=(--mesh "$tmp/out/surface-stl.dcm")
if [ "$variant" = "--displaced" ]; then
  node "$here/make_displaced_seg.mjs" "$seg" "$tmp/seg-displaced.dcm" 12
  seg="$tmp/seg-displaced.dcm"
fi
rc=0
node "$here/ohif_test.mjs" --dist "$dist" --series "$tmp/out/series-intensity" --seg "$seg" \
  --mask "$tmp/out/mask.nii.gz" --threshold "$threshold" "${others[@]}" | tee "$tmp/ohif.log" || rc=$?
# A variant passes only by failing for the reason it plants: the overlay off the mask, or the
# distance map off distance.nii.gz (not by a viewer that did not load, which would prove nothing).
case "$variant" in
  --displaced) expected="overlay vs mask Dice" ;;
  --flipped-distance) expected="distance map differs from distance.nii.gz" ;;
  "") exit "$rc" ;;
  *) echo "FAIL: unknown variant $variant"; exit 1 ;;
esac
if [ "$rc" -eq 1 ] && grep -q "^FAIL: .*$expected" "$tmp/ohif.log"; then
  echo "PASS: the check failed on the planted defect ($expected), as it must"
  exit 0
fi
echo "FAIL: the check did not fail for the planted defect ($expected) (exit $rc)"
exit 1
