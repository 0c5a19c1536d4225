#!/usr/bin/env bash
# Load and faults against a real interslice-server on loopback, with every
# result checked against an in-process `interslice run` (SHA-256 of each
# artifact). Prints the figures the hardening work is judged by: lost,
# failed and mismatched jobs, latency p50/p99, peak memory.
#
#   bench/load_fault.sh [BUILD_DIR] [CLIENTS] [JOBS_PER_CLIENT]
#
# Phases (each against the same server unless it says otherwise):
#  1. load: CLIENTS clients x JOBS_PER_CLIENT one-call jobs; every 5th job of
#     each client is a "poisoned" one (threshold 777: the server runs with
#     the worker fault hook INTERSLICE_WORKER_FAULT=abort:contour:777, which
#     stands in for a decoder that aborts on a hostile file). Poisoned jobs
#     must fail alone; every other job must succeed with the reference bytes.
#     The hook exists only in a server built with
#     -DINTERSLICE_FAULT_INJECTION=ON (server/engine/job_worker.h): configure
#     BUILD_DIR with it, or the poisoned jobs succeed and phase 1 says so.
#  2. killed clients: 8 clients killed with SIGKILL mid-upload or mid-job;
#     the server must stay healthy and keep nothing of them.
#  3. stalled uploads: 16 streams that send only a header (and 4 that trickle
#     64 KiB every 5 s) while real jobs run: the real jobs must succeed.
#  4. server killed: 6 detached jobs, the server killed with SIGKILL while
#     they run, restarted: every job must end SUCCEEDED with the reference
#     bytes (nothing lost, nothing duplicated).
#  5. SIGTERM under load: 8 one-call jobs in flight, then SIGTERM: the server
#     exits 0; each client either got its result (reference bytes) or a clear
#     "shutting down" answer.
#  6. the DICOM edge (bench/dicom_load_fault.sh, its own server and an
#     Orthanc): hostile instances and PDUs, senders and the server killed at
#     random points, floods while a real storescu sends, a full spool.
# Every client here is one peer (127.0.0.1), so the per-peer upload limit is
# raised to 64 (the server tests check that limit); stalled uploads are then
# held off by the idle timeout (10 s here) and by uploads taking no queue
# slot. Loopback only; every loop is bounded.
set -uo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
clients=${2:-8}
per_client=${3:-10}
cli=$build/client/interslice
server=$build/server/interslice-server
stall=$build/bench/interslice_stall_client
small=("$root/tests/data/ct-thick" --roi 176,176,0,336,336,4)
work=$(mktemp -d /tmp/interslice-load-XXXXXX)
server_pid=
cleanup() {
  [[ -n $server_pid ]] && kill -9 "$server_pid" 2>/dev/null
  pkill -9 -f "$work" 2>/dev/null
  wait 2>/dev/null
  rm -rf "$work"
}
trap cleanup EXIT

now() { date +%s.%N; }
hash_dir() { (cd "$1" && find . -type f ! -name '*.json' -print0 | sort -z |
  xargs -0 sha256sum | sha256sum | cut -c1-16); }
start_server() {
  rm -f "$work/port"
  INTERSLICE_WORKER_FAULT=abort:contour:777 "$server" --listen 127.0.0.1:0 \
    --spool "$work/spool" --port-file "$work/port" \
    --drain-grace 20 --max-uploads-per-peer 64 --upload-idle-timeout 10 \
    "$@" >>"$work/server.log" 2>&1 &
  server_pid=$!
  for _ in $(seq 200); do [[ -s $work/port ]] && break; sleep 0.05; done
  addr=127.0.0.1:$(head -1 "$work/port")
}
peak_kib() { awk '/VmHWM/ {print $2}' "/proc/$1/status" 2>/dev/null || echo 0; }
percentile() {  # percentile P of the numbers on stdin
  sort -n | awk -v p="$1" '{ v[NR] = $1 } END {
    if (NR == 0) { print "n/a"; exit }
    i = int(p / 100 * NR + 0.999999); if (i < 1) i = 1; if (i > NR) i = NR
    printf "%.2f", v[i] }'
}

echo "machine: $(nproc) CPUs, $(awk '/MemTotal/ {printf "%.1f GiB", $2/1048576}' /proc/meminfo), load $(cut -d' ' -f1-3 /proc/loadavg)"
"$cli" run "${small[@]}" --threshold 300 --threads 1 --quiet --out "$work/ref" ||
  { echo "reference run failed"; exit 1; }
ref=$(hash_dir "$work/ref")

start_server
echo "server $addr: $("$cli" info --server "$addr" | sed -n 2p | sed 's/^ *//')"
server_peak=0
sample_peak() {
  local k; k=$(peak_kib "$server_pid"); ((k > server_peak)) && server_peak=$k
}

# 1. load with poisoned jobs
echo "== 1. load: $clients clients x $per_client jobs, every 5th poisoned"
: >"$work/load.txt"
start=$(now)
for c in $(seq "$clients"); do
  (
    for j in $(seq "$per_client"); do
      threshold=300
      ((j % 5 == 0)) && threshold=777
      out=$work/load-$c-$j
      t0=$(now)
      "$cli" interpolate --server "$addr" "${small[@]}" --threshold $threshold \
        --quiet --out "$out" --report "$out.json" 2>"$out.err" >/dev/null
      rc=$?
      t1=$(now)
      h=-
      [[ $rc == 0 ]] && h=$(hash_dir "$out")
      rss=$(grep -o '"peak_rss_bytes": *[0-9]*' "$out.json" 2>/dev/null | grep -o '[0-9]*$')
      echo "$threshold $rc $(awk -v a="$t0" -v b="$t1" 'BEGIN{print b-a}') $h ${rss:-0} $(grep -c 'crashed' "$out.err")" >>"$work/load.txt"
      rm -rf "$out"
    done
  ) &
done
while [[ $(jobs -rp | grep -vc "^$server_pid$") -gt 0 ]]; do sample_peak; sleep 0.5; done
end=$(now)
total=$((clients * per_client))
awk -v ref="$ref" -v total="$total" -v secs="$(awk -v a="$start" -v b="$end" 'BEGIN{print b-a}')" '
  { n++
    if ($1 == 777) { p++; if ($2 != 0 && $6 > 0) pf++ }
    else { g++; if ($2 != 0) f++; else if ($4 != ref) m++; if ($5 > w) w = $5 } }
  END { printf "jobs %d of %d answered (lost %d) in %.1f s\n", n, total, total - n, secs
        printf "good jobs: %d, failed %d, mismatched %d\n", g, f + 0, m + 0
        printf "poisoned jobs: %d, failed alone with a crash message %d\n", p, pf + 0
        printf "worker peak RSS (largest job): %.0f MiB\n", w / 1048576 }' "$work/load.txt"
awk '$1 == 300 && $2 == 0 {print $3}' "$work/load.txt" >"$work/lat.txt"
echo "latency of good jobs: p50 $(percentile 50 <"$work/lat.txt") s, p99 $(percentile 99 <"$work/lat.txt") s"

# 2. killed clients
echo "== 2. killed clients"
for k in $(seq 8); do
  "$cli" interpolate --server "$addr" "$root/data/ct-head-phantom-thick" \
    --threshold 300 --quiet --out "$work/killed-$k" >/dev/null 2>&1 &
  victim=$!
  sleep "0.$((RANDOM % 9 + 1))"
  kill -9 "$victim" 2>/dev/null
  wait "$victim" 2>/dev/null
done
for _ in $(seq 60); do
  left=$(find "$work/spool" -mindepth 2 -maxdepth 2 -type d 2>/dev/null | wc -l)
  [[ $left == 0 ]] && break
  sleep 0.5
done
echo "health after: $("$cli" health --server "$addr" 2>&1 | head -1); job folders left in the spool: $left"

# 3. stalled uploads while real jobs run
echo "== 3. stalled and trickling uploads (45 s) while real jobs run"
if [[ -x $stall ]]; then
  "$stall" --server "$addr" --streams 16 --seconds 45 >"$work/stall.txt" 2>&1 &
  stall_pid=$!
  "$stall" --server "$addr" --streams 4 --seconds 45 --trickle-seconds 5 \
    >"$work/trickle.txt" 2>&1 &
  trickle_pid=$!
  sleep 2
  ok=0 failed=0
  : >"$work/lat3.txt"
  for j in $(seq 6); do
    t0=$(now)
    if "$cli" interpolate --server "$addr" "${small[@]}" --threshold 300 --quiet \
      --out "$work/s-$j" >/dev/null 2>"$work/s-$j.err" &&
      [[ $(hash_dir "$work/s-$j") == "$ref" ]]; then
      ok=$((ok + 1))
    else
      failed=$((failed + 1))
      head -1 "$work/s-$j.err"
    fi
    awk -v a="$t0" -v b="$(now)" 'BEGIN{print b-a}' >>"$work/lat3.txt"
    sleep 3
  done
  wait "$stall_pid" "$trickle_pid"
  echo "real jobs during the stall: $ok succeeded, $failed failed; latency p50 $(percentile 50 <"$work/lat3.txt") s"
  echo "stalled streams ended with: $(cut -d' ' -f3- "$work/stall.txt" | sort | uniq -c | tr '\n' ';')"
  echo "trickling streams ended with: $(cut -d' ' -f3- "$work/trickle.txt" | sort | uniq -c | tr '\n' ';')"
else
  echo "skipped: $stall not built"
fi
sample_peak

# 4. server killed with detached jobs running
echo "== 4. server killed (SIGKILL) with 6 detached jobs, restarted"
ids=()
for j in $(seq 6); do
  ids+=("$("$cli" submit --server "$addr" "${small[@]}" --threshold 300 2>/dev/null)")
done
sleep 1.5
kill -9 "$server_pid"
wait "$server_pid" 2>/dev/null
start_server
succeeded=0 mismatched=0 lost=0
for id in "${ids[@]}"; do
  if [[ -z $id ]]; then lost=$((lost + 1)); continue; fi
  "$cli" watch "$id" --server "$addr" --quiet >/dev/null 2>&1
  if "$cli" fetch "$id" --server "$addr" --quiet --out "$work/d-$id" >/dev/null 2>&1; then
    succeeded=$((succeeded + 1))
    [[ $(hash_dir "$work/d-$id") == "$ref" ]] || mismatched=$((mismatched + 1))
  else
    lost=$((lost + 1))
  fi
done
listed=$("$cli" list --all --server "$addr" 2>/dev/null | grep -c "^[0-9a-f]\{16\}")
echo "detached jobs: 6 submitted, $succeeded succeeded, $mismatched mismatched, $lost lost; $listed listed after the restart"

# 5. SIGTERM under load
echo "== 5. SIGTERM with 8 one-call jobs in flight"
for j in $(seq 8); do
  (
    "$cli" interpolate --server "$addr" "${small[@]}" --threshold 300 --quiet \
      --out "$work/t-$j" >/dev/null 2>"$work/t-$j.err"
    echo $? >"$work/t-$j.rc"
  ) &
done
sleep 0.7
sample_peak
kill -TERM "$server_pid"
wait "$server_pid"
server_rc=$?
server_pid=
wait
done_ok=0 drained=0 other=0
for j in $(seq 8); do
  if [[ $(cat "$work/t-$j.rc") == 0 ]]; then
    [[ $(hash_dir "$work/t-$j") == "$ref" ]] && done_ok=$((done_ok + 1)) || other=$((other + 1))
  elif grep -qi "shutting down" "$work/t-$j.err"; then
    drained=$((drained + 1))
  else
    other=$((other + 1))
    echo "  client $j: $(head -1 "$work/t-$j.err")"
  fi
done
echo "server exit code $server_rc; clients: $done_ok finished with the reference bytes, $drained told 'shutting down', $other other"
echo "server peak RSS: $((server_peak / 1024)) MiB"

# 6. the DICOM edge
echo "== 6. DICOM edge (bench/dicom_load_fault.sh)"
bash "$root/bench/dicom_load_fault.sh" "$build"
