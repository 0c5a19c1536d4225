#!/usr/bin/env bash
# What the previews cost (issue 28): the shipped phantom's main job
# (threshold 300 HU, direct solver, the default outputs) run N times with
# --previews png and N times with --previews none, interleaved, each in its
# own process. Prints the median of the "preview" stage (JobReport), of the
# job's stages summed, and of the wall time of each variant, and the machine's
# load before and after (the machine is shared: quote medians with the load).
#
#   bash bench/preview_bench.sh [RUNS] [THREADS]     (default 5 runs, 2 threads)
#
# Needs build/client/interslice (cmake --build build --target interslice).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
runs=${1:-5}
threads=${2:-2}
cli="$root/build/client/interslice"
data="$root/data/ct-head-phantom-thick"
work=$(mktemp -d "${TMPDIR:-/tmp}/preview-bench.XXXXXX")
trap 'rm -rf "$work"' EXIT
echo "load before: $(cut -d' ' -f1-3 /proc/loadavg); $(nproc) cores; $runs runs each, $threads threads"
for n in $(seq 1 "$runs"); do
  for variant in png none; do
    start=$(date +%s.%N)
    "$cli" run "$data" --threshold 300 --method direct --threads "$threads" --quiet \
      --previews "$variant" --out "$work/out-$variant" --report "$work/$variant-$n.json"
    end=$(date +%s.%N)
    echo "$start $end" > "$work/$variant-$n.wall"
  done
done
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)"
python3 - "$work" "$runs" <<'EOF'
import json, statistics, sys
work, runs = sys.argv[1], int(sys.argv[2])
for variant in ("png", "none"):
    preview, stages, wall = [], [], []
    for n in range(1, runs + 1):
        report = json.load(open(f"{work}/{variant}-{n}.json"))
        preview.append(report["stages"].get("preview", 0.0))
        stages.append(sum(report["stages"].values()))
        a, b = map(float, open(f"{work}/{variant}-{n}.wall").read().split())
        wall.append(b - a)
    print(f"--previews {variant:4s}: preview stage median {statistics.median(preview):.2f} s "
          f"(min {min(preview):.2f}, max {max(preview):.2f}); stages summed median "
          f"{statistics.median(stages):.2f} s; wall median {statistics.median(wall):.2f} s")
EOF
