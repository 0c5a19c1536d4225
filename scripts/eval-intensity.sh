#!/usr/bin/env bash
# The intensity harness of issue 23 in one command: drop-k (k = 2, 4, 8) on
# the thin CT head phantom and on the tilted one (../shared/data), the derived
# intensity series by linear blending (today's), Catmull-Rom in z and the
# morph (core/morph MorphIntensity) plus its ablations, against the withheld
# slices: RMSE/PSNR inside the body, SSIM, edge rise distance, homogeneous
# soft tissue; sagittal and coronal reformats at k = 4 and 8. Builds
# interslice_grey_eval, runs it on each series, writes intensity.md and the
# figures (tools/eval/grey_report.py) and publishes them to docs/eval/.
#
#   scripts/eval-intensity.sh [--out DIR] [--build-dir DIR] [--threads N]
#                             [--methods LIST] [--no-publish]
#
# Exits 0 with a message when ../shared/data is absent. About 15 minutes on 2
# cores.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
data="$(cd "$repo/.." && pwd)/shared/data"
out="$repo/build-eval/intensity-report"
build="$repo/build-eval"
threads=0
methods="linear,catmull-rom,pchip-z,morph,morph-bwd,morph-nofallback,morph-maps"
publish=1
command_line="scripts/eval-intensity.sh $*"
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out="$2"; shift 2 ;;
    --build-dir) build="$2"; shift 2 ;;
    --threads) threads="$2"; shift 2 ;;
    --methods) methods="$2"; shift 2 ;;
    --no-publish) publish=0; shift ;;
    -h|--help) sed -n 2,15p "$0"; exit 0 ;;
    *) echo "eval-intensity.sh: unknown option $1" >&2; exit 64 ;;
  esac
done
if [ ! -d "$data/ct-head-phantom-thin" ]; then
  echo "eval-intensity.sh: $data/ct-head-phantom-thin not found; skipping."
  exit 0
fi
py=/usr/bin/python3
if ! "$py" -c "import matplotlib, numpy" 2>/dev/null; then
  echo "eval-intensity.sh: $py lacks matplotlib/numpy: run 'bash scripts/install-deps.sh --eval'" >&2
  exit 69
fi
if [ ! -f "$build/build.ninja" ]; then
  cmake -S "$repo" -B "$build" -G Ninja -DINTERSLICE_BUILD_SERVER=OFF \
    -DINTERSLICE_BUILD_TESTS=OFF -DINTERSLICE_BUILD_BENCHMARKS=OFF
fi
ninja -C "$build" -j2 interslice_grey_eval
mkdir -p "$out"
runs=()
# name, folder, drop-k factors; bone edges at 300 HU, body at -500 HU, soft
# tissue -100..100 HU for both (same settings for every series).
for entry in "thin ct-head-phantom-thin" "tilt ct-head-phantom-tilt"; do
  set -- $entry
  [ -d "$data/$2" ] || continue
  rm -rf "${out:?}/$1"
  start=$(date +%s)
  "$build/tools/eval/interslice_grey_eval" --series "$data/$2" --name "$1" \
    --out "$out/$1" --ks 2,4,8 --methods "$methods" --bone 300 --body -500 \
    --soft=-100,100 --threads "$threads" 2> "$out/$1.log"
  echo "eval-intensity.sh: $1 done in $(( $(date +%s) - start )) s (log $out/$1.log)"
  runs+=("$out/$1")
done
machine="$(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg) at the end, $(date -u +%Y-%m-%dT%H:%MZ)"
"$py" "$repo/tools/eval/grey_report.py" "$out" "${runs[@]}" \
  --command "$command_line" --machine "$machine"
if [ "$publish" = 1 ]; then
  docs="$repo/docs/eval"
  rm -f "$docs"/intensity.md "$docs"/intensity_*.png "$docs"/intensity_*.json
  cp "$out"/intensity.md "$out"/intensity_*.png "$docs"/
  for r in "${runs[@]}"; do
    "$py" - "$r" "$docs/intensity_$(basename "$r").json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1] + "/results.json"))
r.pop("planes", None)
json.dump(r, open(sys.argv[2], "w"), indent=1)
PY
  done
  echo "eval-intensity.sh: report published to $docs"
fi
echo "eval-intensity.sh: report at $out/intensity.md"
