#!/usr/bin/env bash
# Quick start, step 1: install what is missing, build, and run the main job on
# the CT head phantom shipped in data/ (28 slices of 5 mm -> 0.45 mm), twice:
# in-process (`interslice run`) and through the daemon (`interslice-server` on
# loopback, `interslice interpolate`), and check both give the same files.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"

bash scripts/install-deps.sh
# build/ is configured exactly as the test suite configures it
# (scripts/test.sh), so that the suite reuses what is built here; only the
# two programs the demo runs are built now, and the suite builds its tests
# next in the same folder.
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DINTERSLICE_TEST_SELECTION=plain >/dev/null
cmake --build build -j"$(nproc)" --target interslice interslice-server

out="${1:-$root/out/phantom}"
job=(data/ct-head-phantom-thick --threshold 300 --method direct
     --mesh stl,ply --volume nii,nrrd)

echo "== in-process: interslice run"
./build/client/interslice run "${job[@]}" --out "$out" --report "$out/report.json"

echo
echo "== through the daemon: interslice-server on loopback + interslice interpolate"
work="$(mktemp -d)"
./build/server/interslice-server --listen 127.0.0.1:0 --spool "$work/spool" \
  --port-file "$work/ports" --log-level warn &
server=$!
trap 'kill "$server" 2>/dev/null || true; rm -rf "$work"' EXIT
for _ in $(seq 1 100); do [ -s "$work/ports" ] && break; sleep 0.1; done
port="$(head -n1 "$work/ports")"
./build/client/interslice interpolate --server "127.0.0.1:$port" "${job[@]}" \
  --out "$out-daemon" --report "$out-daemon/report.json" --deadline 900
kill -TERM "$server"
wait "$server" || true
for f in distance.nii.gz mask.nii.gz distance.nrrd mask.nrrd surface.stl surface.ply \
         previews/axial.png previews/coronal.png previews/sagittal.png previews/3d-front.png; do
  cmp -s "$out/$f" "$out-daemon/$f" || { echo "demo: $f differs between run and daemon" >&2; exit 1; }
done
echo
echo "Outputs are in $out (in-process) and $out-daemon (through the daemon; identical files)."
echo "Open surface.stl in any mesh viewer, distance.nii.gz / mask.nii.gz in 3D Slicer;"
echo "previews/*.png show the outline, the original slices and the surface at a glance."
