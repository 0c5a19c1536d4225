#!/usr/bin/env bash
# What running each job in a supervised worker process costs: the shipped
# phantom's main job (direct solver, NIfTI + STL) through a server with
# --isolation process and with --isolation thread, alternating, RUNS times
# each; prints the medians and their ratio, and checks the artifacts agree.
#   bench/isolation_cost.sh [BUILD_DIR] [RUNS]
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
runs=${2:-5}
cli=$build/client/interslice
server=$build/server/interslice-server
job=("$root/data/ct-head-phantom-thick" --threshold 300 --method direct)
work=$(mktemp -d /tmp/interslice-isolation-XXXXXX)
pids=()
trap 'kill "${pids[@]}" 2>/dev/null || true; wait 2>/dev/null || true; rm -rf "$work"' EXIT
start() {  # start ISOLATION -> sets addr_ISOLATION
  "$server" --listen 127.0.0.1:0 --spool "$work/spool-$1" --port-file "$work/port-$1" \
    --isolation "$1" --log-level warn >"$work/server-$1.log" 2>&1 &
  pids+=($!)
  for _ in $(seq 200); do [[ -s $work/port-$1 ]] && break; sleep 0.05; done
  printf -v "addr_$1" '%s' "127.0.0.1:$(head -1 "$work/port-$1")"
}
start process
start thread
now() { date +%s.%N; }
echo "machine: $(nproc) CPUs, load $(cut -d' ' -f1-3 /proc/loadavg)"
for i in $(seq "$runs"); do
  for mode in process thread; do
    addr_var=addr_$mode
    t0=$(now)
    "$cli" interpolate --server "${!addr_var}" "${job[@]}" --quiet --out "$work/out-$mode"
    awk -v a="$t0" -v b="$(now)" 'BEGIN { print b - a }' >>"$work/times-$mode"
  done
done
for f in "$work"/out-process/*; do
  cmp -s "$f" "$work/out-thread/$(basename "$f")" || echo "MISMATCH: $(basename "$f")"
done
median() { sort -n "$1" | awk '{ v[NR] = $1 } END { print (NR % 2) ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }
p=$(median "$work/times-process")
t=$(median "$work/times-thread")
awk -v p="$p" -v t="$t" -v n="$runs" 'BEGIN {
  printf "one call, shipped phantom, median of %d: worker process %.2f s, in-server thread %.2f s, ratio %.3f (+%.0f ms)\n",
         n, p, t, p / t, (p - t) * 1000 }'
