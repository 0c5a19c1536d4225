#!/usr/bin/env bash
# Service benchmark: throughput of small one-call jobs with 1, 4 and 16
# concurrent clients, and the service path's overhead relative to the
# in-process `interslice run` on the shipped series (wall-time ratio).
#
#   bench/service_bench.sh [BUILD_DIR] [JOBS_PER_LEVEL]
#
# Uses BUILD_DIR/client/interslice and BUILD_DIR/server/interslice-server
# (default: build-server). The server runs with its defaults (workers and
# threads from the CPU count), on loopback, plaintext.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build-server}
jobs_per_level=${2:-32}
cli=$build/client/interslice
server=$build/server/interslice-server
small=("$root/tests/data/ct-thick" --threshold 300 --roi 176,176,0,336,336,4)
full=("$root/data/ct-head-phantom-thick" --threshold 300 --method direct)
work=$(mktemp -d /tmp/interslice-bench-XXXXXX)
trap 'kill $server_pid 2>/dev/null || true; wait 2>/dev/null || true; rm -rf "$work"' EXIT

"$server" --listen 127.0.0.1:0 --spool "$work/spool" --port-file "$work/port" \
  --max-queued 64 --max-uploads-per-peer 64 --log-level warn >"$work/server.log" 2>&1 &
server_pid=$!
for _ in $(seq 100); do [[ -s $work/port ]] && break; sleep 0.05; done
addr=127.0.0.1:$(head -1 "$work/port")
echo "server $addr: $("$cli" info --server "$addr" | sed -n 2p | sed 's/^ *//')"

now() { date +%s.%N; }

echo "== throughput, small jobs (160x160 ROI of tests/data/ct-thick, CG 15 it.)"
for clients in 1 4 16; do
  per_client=$(( (jobs_per_level + clients - 1) / clients ))
  total=$(( per_client * clients ))
  start=$(now)
  for c in $(seq "$clients"); do
    (
      for j in $(seq "$per_client"); do
        "$cli" interpolate --server "$addr" "${small[@]}" --quiet \
          --out "$work/out-$c-$j" >/dev/null
        rm -rf "$work/out-$c-$j"
      done
    ) &
  done
  wait $(jobs -p | grep -v "^$server_pid$") 2>/dev/null || true
  end=$(now)
  awk -v n="$total" -v c="$clients" -v s="$start" -v e="$end" \
    'BEGIN { printf "clients %2d: %d jobs in %.2f s = %.2f jobs/s\n", c, n, e - s, n / (e - s) }'
done

echo "== overhead on data/ct-head-phantom-thick (28 slices, direct solver)"
threads=$("$cli" info --server "$addr" | sed -n 2p | awk '{print $4}')
best_local=1e9
best_remote=1e9
for i in 1 2 3; do
  start=$(now)
  "$cli" run "${full[@]}" --threads "$threads" --quiet --out "$work/local"
  t=$(awk -v s="$start" -v e="$(now)" 'BEGIN { print e - s }')
  best_local=$(awk -v a="$best_local" -v b="$t" 'BEGIN { print (b < a) ? b : a }')
  start=$(now)
  "$cli" interpolate --server "$addr" "${full[@]}" --quiet --out "$work/remote"
  t=$(awk -v s="$start" -v e="$(now)" 'BEGIN { print e - s }')
  best_remote=$(awk -v a="$best_remote" -v b="$t" 'BEGIN { print (b < a) ? b : a }')
done
for f in "$work"/local/*; do cmp -s "$f" "$work/remote/$(basename "$f")" ||
  echo "MISMATCH: $(basename "$f")"; done
awk -v l="$best_local" -v r="$best_remote" -v t="$threads" \
  'BEGIN { printf "in-process run (%s threads): %.2f s; one call via the server: %.2f s; ratio %.3f (best of 3)\n", t, l, r, r / l }'
