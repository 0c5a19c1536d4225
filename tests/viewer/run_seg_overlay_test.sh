#!/usr/bin/env bash
# Writes a DICOM SEG and the intensity series it overlays with the interslice CLI, then loads them the
# way OHIF v3 does (seg_overlay_test.mjs) and checks the overlay against the mask NIfTI.
#   bash tests/viewer/run_seg_overlay_test.sh BIN_DIR [CASE]  (BIN_DIR holds the interslice executable)
# CASE: phantom (default: the shipped thick CT phantom) or tilt (tests/data/ct-tilt, a real
# gantry-tilted CT: an oblique grid, whose NIfTI qform is a float32 quaternion near 180 degrees).
# Needs node (>= 18.19) and, when node_modules is missing or older than the lockfile, npm.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
bin_dir="${1:?usage: run_seg_overlay_test.sh BIN_DIR}"
interslice="$bin_dir/interslice"
node="${NODE:-node}"
[ -x "$interslice" ] || { echo "FAIL: no interslice executable in $bin_dir"; exit 1; }
command -v "$node" >/dev/null || { echo "FAIL: $node not found"; exit 1; }

# npm records what it installed in node_modules/.package-lock.json; reinstall when that is missing
# or older than the committed lockfile.
if [ ! -f "$here/node_modules/.package-lock.json" ] ||
   [ "$here/package-lock.json" -nt "$here/node_modules/.package-lock.json" ]; then
  npm ci --prefix "$here" --no-audit --no-fund --ignore-scripts
fi

tmp="$(mktemp -d "${TMPDIR:-/tmp}/seg-overlay.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT

case "${2:-phantom}" in
  phantom)
    "$interslice" run "$repo/data/ct-head-phantom-thick" --threshold 300 --method direct \
      --roi 200,150,0,300,250,28 --seg --output-series intensity --volume nii --mesh none \
      --out "$tmp/out" --quiet
    ;;
  tilt)
    "$interslice" run "$repo/tests/data/ct-tilt" --threshold 300 --method direct \
      --roi 150,150,0,350,350,2 --seg --output-series intensity --volume nii --mesh none \
      --out "$tmp/out" --quiet
    ;;
  *)
    echo "FAIL: unknown case $2"
    exit 1
    ;;
esac

"$node" "$here/seg_overlay_test.mjs" --seg "$tmp/out/seg.dcm" \
  --series "$tmp/out/series-intensity" --mask "$tmp/out/mask.nii.gz"
