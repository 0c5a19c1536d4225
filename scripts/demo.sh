#!/usr/bin/env bash
# Quick start, step 1: install what is missing, build, and run the main job
# on the CT head phantom shipped in data/ (28 slices of 5 mm -> 0.45 mm).
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"

bash scripts/install-deps.sh
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build build -j"$(nproc)"

out="${1:-$root/out/phantom}"
./build/client/interslice run data/ct-head-phantom-thick \
  --threshold 300 --method direct \
  --mesh stl,ply --volume nii,nrrd \
  --out "$out" --report "$out/report.json"
echo
echo "Outputs are in $out (open surface.stl in any mesh viewer, distance.nii.gz / mask.nii.gz in 3D Slicer)."
