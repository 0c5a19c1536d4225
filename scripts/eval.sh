#!/usr/bin/env bash
# The quality harness in one command (DESIGN.md section 5): drop-k on a thin
# real series, thick -> thin, the paper's artificial data, Figure 5
# convergence, voxel vs mm energy, topology and baselines. Builds
# interslice_eval, runs it, draws the figures and writes report.md.
#
#   scripts/eval.sh [--series DIR] [--thick DIR] [--threshold HU] [--out DIR]
#                   [--threads N] [--build-dir DIR] [--no-run] [--no-publish]
#                   [-- extra interslice_eval options, e.g. --ks 4,8]
#
# Defaults: ../shared/data/ct-head-phantom-thin (+ -thick) at 300 HU, output
# build-eval/eval-report. With the default data the report (markdown, PNG,
# CSV, JSON) is also copied to docs/eval/. Exits 0 with a message when the
# series folder is absent. --no-run redraws figures and the report from an
# existing output folder. Takes about 10 minutes on 2 cores.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
data="$(cd "$repo/.." && pwd)/shared/data"
series="$data/ct-head-phantom-thin"
thick=""
thick_set=0
threshold=300
out="$repo/build-eval/eval-report"
build="$repo/build-eval"
threads=0
run=1
publish=1
extra=()
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
command_line="scripts/eval.sh"
for arg in "$@"; do command_line+=" $(repo_arg "$arg")"; done
while [ $# -gt 0 ]; do
  case "$1" in
    --series) series="$2"; shift 2 ;;
    --thick) thick="$2"; thick_set=1; shift 2 ;;
    --threshold) threshold="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --threads) threads="$2"; shift 2 ;;
    --build-dir) build="$2"; shift 2 ;;
    --no-run) run=0; shift ;;
    --no-publish) publish=0; shift ;;
    --) shift; extra=("$@"); break ;;
    -h|--help) sed -n 2,17p "$0"; exit 0 ;;
    *) echo "eval.sh: unknown option $1" >&2; exit 64 ;;
  esac
done

if [ ! -d "$series" ]; then
  echo "eval.sh: series folder $series not found; skipping the quality evaluation."
  exit 0
fi
default_data=0
if [ "$(cd "$series" && pwd)" = "$data/ct-head-phantom-thin" ] && [ "$threshold" = "300" ]; then
  default_data=1
fi
if [ "$thick_set" = 0 ] && [ "$(cd "$series" && pwd)" = "$data/ct-head-phantom-thin" ] \
   && [ -d "$data/ct-head-phantom-thick" ]; then
  thick="$data/ct-head-phantom-thick"
fi
py=/usr/bin/python3
if ! "$py" -c "import matplotlib, numpy" 2>/dev/null; then
  echo "eval.sh: $py lacks matplotlib/numpy: run 'bash scripts/install-deps.sh --eval'" >&2
  exit 69
fi

mkdir -p "$out"
if [ "$run" = 1 ]; then
  if [ ! -f "$build/build.ninja" ]; then
    cmake -S "$repo" -B "$build" -G Ninja -DINTERSLICE_BUILD_SERVER=OFF \
      -DINTERSLICE_BUILD_TESTS=OFF -DINTERSLICE_BUILD_BENCHMARKS=OFF
  fi
  ninja -C "$build" -j2 interslice_eval
  rm -rf "$out/raw" "$out"/*.png
  # The series as paths relative to the repository (results.json and the
  # report name no folder of one machine); interslice_eval runs from it.
  cd "$repo"
  args=(--thin "$(realpath --relative-to="$repo" "$series")" --threshold "$threshold"
        --out "$out" --threads "$threads")
  if [ -n "$thick" ]; then
    args+=(--thick "$(realpath --relative-to="$repo" "$thick")")
  else
    args+=(--experiments dropk,artificial,convergence)
  fi
  start=$(date +%s)
  status=0
  "$build/tools/eval/interslice_eval" "${args[@]}" "${extra[@]}" 2> "$out/run.log" || status=$?
  echo "eval.sh: interslice_eval finished in $(( $(date +%s) - start )) s (exit $status; log $out/run.log)"
  if [ "$status" = 1 ]; then exit 1; fi
fi
"$py" "$repo/tools/eval/plots.py" "$out"
report_args=("$out" --command "$command_line")
if [ "$default_data" = 1 ]; then report_args+=(--default-data); fi
"$py" "$repo/tools/eval/report.py" "${report_args[@]}"

if [ "$publish" = 1 ] && [ "$default_data" = 1 ]; then
  docs="$repo/docs/eval"
  mkdir -p "$docs"
  # Replace this harness's files only: docs/eval also holds other reports'
  # files (segmentations.md's fill_*.csv and segmentations_dice.png).
  rm -f "$docs"/report.md "$docs"/results.json "$docs"/skull_top_k8.json \
    "$docs"/metrics.csv "$docs"/convergence.csv "$docs"/reformat_*.png \
    "$docs"/fig5_convergence.png "$docs"/skull_top_*.png
  cp "$out"/report.md "$out"/*.png "$out"/*.csv "$out"/results.json "$docs"/
  [ -f "$out/skull_top_k8.json" ] && cp "$out/skull_top_k8.json" "$docs"/
  echo "eval.sh: report published to $docs"
fi
echo "eval.sh: report at $out/report.md"
