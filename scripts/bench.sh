#!/usr/bin/env bash
# Speed report: builds the benchmark binary and runs it (solver kernels vs a
# STREAM triad, direct vs CG, scaling, end to end on the shipped phantom),
# writing the raw JSON and a markdown summary with the machine's context.
#
#   scripts/bench.sh [--out DIR] [--before BIN] [--large] [--whole-only]
#
# The whole-job table (bench/whole_jobs.sh: the three jobs of the speed table, each
# in its own process for its peak memory) goes to DIR/whole-job.md; with
# --before BIN (an older `interslice`), both binaries run interleaved in the
# same run. --large adds the synthetic 100 x 5 mm series to 0.7 mm;
# --whole-only skips the kernel benchmarks.
#
# Default output: docs/speed/. Takes about 10 minutes on 2 cores. Timings
# are medians of the repetitions in one run; run it on an otherwise idle
# machine.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
command_line="scripts/bench.sh $*"
out="$repo/docs/speed"
before="" large="" whole_only=0
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out="$2"; shift 2 ;;
    --before) before="$2"; shift 2 ;;
    --large) large="--large"; shift ;;
    --whole-only) whole_only=1; shift ;;
    *) echo "bench.sh: unknown option $1" >&2; exit 2 ;;
  esac
done
cd "$repo"
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build build --target interslice_bench interslice -j"$(nproc)"
mkdir -p "$out"
# Whole jobs, each in its own process (peak memory per job).
whole_args=(--after ./build/client/interslice --repeat 3 --out "$out/whole-job-table.md")
[ -n "$before" ] && whole_args+=(--before "$before")
[ -n "$large" ] && whole_args+=(--large)
load_before="$(cut -d' ' -f1-3 /proc/loadavg)"
bash "$repo/bench/whole_jobs.sh" "${whole_args[@]}"
{
  echo "# Whole jobs"
  echo
  echo "- date: $(date -u +%Y-%m-%dT%H:%MZ), commit: $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
  echo "- machine: $(nproc) cores, $(awk '/MemTotal/ {printf "%.1f GiB", $2/1048576}' /proc/meminfo);" \
       "load average before: $load_before, after: $(cut -d' ' -f1-3 /proc/loadavg)"
  echo "- command: $command_line (bench/whole_jobs.sh; medians of 3 runs, binaries interleaved)"
  echo "- after: ./build/client/interslice${before:+; before: $before}"
  echo
  cat "$out/whole-job-table.md"
} > "$out/whole-job.md"
rm -f "$out/whole-job-table.md"
if [ "$whole_only" = 1 ]; then
  echo "bench.sh: wrote $out/whole-job.md"
  exit 0
fi
bench=./build/bench/interslice_bench
# Kernels and the bandwidth limit: 5 repetitions each, medians reported.
kernels='StreamTriad|OperatorApply|ConjugateGradientIteration|BM_DirectSolve'
"$bench" --benchmark_filter="($kernels)" \
  --benchmark_repetitions=5 --benchmark_report_aggregates_only=true \
  --benchmark_out="$out/kernels.json" --benchmark_out_format=json \
  | tee "$out/kernels.txt"
# Whole solves, direct vs CG, scaling and end to end: once each.
"$bench" --benchmark_filter="DirectVersusCg|SolveScaling|EndToEnd" \
  --benchmark_out="$out/solves.json" --benchmark_out_format=json \
  | tee "$out/solves.txt"
python3 "$repo/bench/summarize.py" "$out/kernels.json" "$out/solves.json" \
  > "$out/summary.md"
{
  echo "# Speed measurements"
  echo
  echo "- date: $(date -u +%Y-%m-%dT%H:%MZ)"
  echo "- commit: $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
  echo "- machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)," \
       "$(awk '/MemTotal/ {printf "%.1f GiB", $2/1048576}' /proc/meminfo)"
  echo "- load average at the end: $(cut -d' ' -f1-3 /proc/loadavg)"
  echo "- command: $command_line"
  echo
  cat "$out/summary.md"
  echo
  echo "## Raw output"
  echo
  echo '```'
  cat "$out/kernels.txt" "$out/solves.txt" | grep -v '^E: '
  echo '```'
} > "$out/README.md"
echo "bench.sh: wrote $out/README.md and $out/benchmarks.json"
