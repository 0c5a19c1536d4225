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
#                             [--series NAME=DIR]... [--levels E,B,LO,HI]
#                             [--report FILE]
#
# --series (repeatable) replaces the default series (thin and tilt of
# ../shared/data) by other folders, e.g. a thin MR series kept outside the
# repository; --levels sets the evaluation's edge level, body level and
# homogeneous soft-tissue range in the series' modality units (default
# 300,-500,-100,100: HU), the same for every series of the run; --report names
# the published report in docs/eval (default intensity.md). The method's
# settings are the same whatever the series. Exits 0 with a message when
# ../shared/data is absent and no --series is given. About 15 minutes on 2
# cores for the two CT phantoms.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
data="$(cd "$repo/.." && pwd)/shared/data"
out="$repo/build-eval/intensity-report"
build="$repo/build-eval"
threads=0
methods="linear,catmull-rom,pchip-z,morph,morph-nopair,morph-bwd,morph-nofallback,morph-maps"
publish=1
report=intensity.md
levels="300,-500,-100,100"
series=()
# The command line the report quotes, every absolute path in it (also the
# DIR of NAME=DIR) relative to the repository root (../shared/data/...), so
# that no published report names a folder of one machine
# (tests/repo/machine_paths_test.sh keeps them out of docs/).
repo_arg() {
  case "$1" in
    /*) realpath -ms --relative-to="$repo" -- "$1" ;;
    *=/*) printf '%s=%s\n' "${1%%=/*}" \
            "$(realpath -ms --relative-to="$repo" -- "/${1#*=/}")" ;;
    *) printf '%s\n' "$1" ;;
  esac
}
command_line="scripts/eval-intensity.sh"
for arg in "$@"; do command_line+=" $(repo_arg "$arg")"; done
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out="$2"; shift 2 ;;
    --build-dir) build="$2"; shift 2 ;;
    --threads) threads="$2"; shift 2 ;;
    --methods) methods="$2"; shift 2 ;;
    --no-publish) publish=0; shift ;;
    --series) series+=("$2"); shift 2 ;;
    --levels) levels="$2"; shift 2 ;;
    --report) report="$2"; shift 2 ;;
    -h|--help) sed -n 2,26p "$0"; exit 0 ;;
    *) echo "eval-intensity.sh: unknown option $1" >&2; exit 64 ;;
  esac
done
if [ ${#series[@]} -eq 0 ]; then
  if [ ! -d "$data/ct-head-phantom-thin" ]; then
    echo "eval-intensity.sh: $data/ct-head-phantom-thin not found; skipping."
    exit 0
  fi
  series=("thin=$data/ct-head-phantom-thin" "tilt=$data/ct-head-phantom-tilt")
fi
IFS=, read -r edge_level body_level soft_lo soft_hi <<< "$levels"
if [ -z "$soft_hi" ]; then
  echo "eval-intensity.sh: --levels needs EDGE,BODY,SOFT_LO,SOFT_HI" >&2
  exit 64
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
# name=folder; drop-k factors 2, 4, 8; the edge level, body level and soft
# tissue range of --levels (by default bone edges at 300 HU, body at -500 HU,
# soft tissue -100..100 HU), the same for every series of the run.
for entry in "${series[@]}"; do
  name="${entry%%=*}"
  dir="${entry#*=}"
  if [ ! -d "$dir" ]; then
    echo "eval-intensity.sh: $dir not found; skipping $name." >&2
    continue
  fi
  rm -rf "${out:?}/$name"
  start=$(date +%s)
  "$build/tools/eval/interslice_grey_eval" --series "$dir" --name "$name" \
    --out "$out/$name" --ks 2,4,8 --methods "$methods" --bone="$edge_level" \
    --body="$body_level" --soft="$soft_lo,$soft_hi" --threads "$threads" \
    2> "$out/$name.log"
  echo "eval-intensity.sh: $name done in $(( $(date +%s) - start )) s (log $out/$name.log)"
  runs+=("$out/$name")
done
if [ ${#runs[@]} -eq 0 ]; then
  echo "eval-intensity.sh: no series found" >&2
  exit 66
fi
machine="$(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg) at the end, $(date -u +%Y-%m-%dT%H:%MZ)"
"$py" "$repo/tools/eval/grey_report.py" "$out" "${runs[@]}" \
  --command "$command_line" --machine "$machine"
if [ "$publish" = 1 ]; then
  docs="$repo/docs/eval"
  cp "$out"/intensity.md "$docs/$report"
  for r in "${runs[@]}"; do
    rm -f "$docs/intensity_$(basename "$r")"_*.png "$docs/intensity_$(basename "$r").json"
    cp "$out/intensity_$(basename "$r")"_*.png "$docs"/ 2>/dev/null || true
    "$py" - "$r" "$docs/intensity_$(basename "$r").json" "$repo" <<'PY'
import json, os, sys
r = json.load(open(sys.argv[1] + "/results.json"))
r.pop("planes", None)
# The series folder relative to the repository root, as intensity.md names it.
if os.path.isabs(r.get("dir", "")):
    r["dir"] = os.path.relpath(r["dir"], sys.argv[3])
json.dump(r, open(sys.argv[2], "w"), indent=1)
PY
  done
  echo "eval-intensity.sh: report published to $docs"
fi
echo "eval-intensity.sh: report at $out/intensity.md"
