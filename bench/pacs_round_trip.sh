#!/usr/bin/env bash
# The PACS round trip of the shipped rule, timed (issue 25's goal: <= 8 s for
# the 28-slice phantom): from the last instance stored by storescu to every
# result instance in Orthanc.
#   bench/pacs_round_trip.sh [BUILD_DIR] [RUNS]     (RUNS default 3)
# For each series (data/ct-head-phantom-thick: 28 slices of 5 mm;
# tests/data/ct-tilt: 3 tilted slices) and each run: a fresh Orthanc
# (Debian's, TCP_NODELAY=1) and a fresh interslice-server with the shipped
# rule (deploy/config/rules.yaml: complete on release, bone at 300 HU, the
# derived series, the SEG and the Encapsulated STL sent to `orthanc`);
# storescu (TCP_NODELAY=1) sends the series to the node as ORTHANC. t0 is
# storescu's exit: its last C-STORE answered and the association released
# (the release is what completes the series under the shipped rule). Orthanc's
# instance count is polled every 50 ms; t1 is the first poll that sees all
# N results, N being the count the node logs as delivered ("delivered to
# peer orthanc: N instance(s)"). Prints each run,
# the median per series, and the load average before and after: on a shared
# machine the absolute figures move with the load. The job's end is its
# "succeeded" line in the node's log (its results published, its deliveries
# starting), so "job" and "sending" split the total.
# Measured 2026-11-26 on this 2-core machine, idle, 7 runs: the phantom
# 7.38 s (runs 7.14-7.43; job 6.41 s, sending the 300 results 1.02 s),
# ct-tilt 0.47 s (docs/dicom-node.md, "Throughput"). Under a load of 12-14
# (six other engineers building) it was 40.1 s, before the job's changes.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=$(cd "${1:-$root/build}" && pwd)
runs=${2:-3}
server_bin=$build/server/interslice-server
client_bin=$build/client/interslice
for tool in "$server_bin" "$client_bin" /usr/sbin/Orthanc /usr/bin/storescu /usr/bin/curl; do
  [[ -x $tool ]] || { echo "pacs_round_trip.sh: $tool is missing" >&2; exit 1; }
done
work=$(mktemp -d /tmp/interslice-pacs-round-trip-XXXXXX)
pids=()
stop_all() {
  ((${#pids[@]})) || return 0
  kill "${pids[@]}" 2>/dev/null || true
  wait "${pids[@]}" 2>/dev/null || true
  pids=()
}
trap 'stop_all; rm -rf "$work"' EXIT

now() { date +%s.%N; }
free_ports() {
  python3 -c '
import socket
s = [socket.socket() for _ in range(3)]
for x in s: x.bind(("127.0.0.1", 0))
print(*(x.getsockname()[1] for x in s))'
}
median() {
  sort -g | awk '{v[NR]=$1} END {if (NR==0) {print "n/a"; exit}
    print (NR%2 ? v[(NR+1)/2] : (v[NR/2]+v[NR/2+1])/2)}'
}

# One run: prints the seconds from storescu's exit to all results in Orthanc.
round_trip() {
  local series=$1 run_dir=$2
  mkdir -p "$run_dir"
  local orthanc_dicom orthanc_http node_grpc
  read -r orthanc_dicom orthanc_http node_grpc < <(free_ports)
  cat > "$run_dir/orthanc.json" <<JSON
{"Name": "bench-pacs", "DicomAet": "ORTHANC", "DicomPort": $orthanc_dicom,
 "HttpPort": $orthanc_http, "StorageDirectory": "$run_dir/orthanc-db",
 "IndexDirectory": "$run_dir/orthanc-db", "RemoteAccessAllowed": false,
 "AuthenticationEnabled": false}
JSON
  printf 'peers:\n  - {name: orthanc, ae_title: ORTHANC, host: 127.0.0.1, port: %s}\n' \
    "$orthanc_dicom" > "$run_dir/peers.yaml"
  TCP_NODELAY=1 /usr/sbin/Orthanc "$run_dir/orthanc.json" > "$run_dir/orthanc.log" 2>&1 &
  pids+=($!)
  "$server_bin" --listen "127.0.0.1:$node_grpc" --spool "$run_dir/spool" \
    --dicom-listen 127.0.0.1:0 --port-file "$run_dir/ports" --dicom-ae INTERSLICE \
    --dicom-peers "$run_dir/peers.yaml" --rules "$root/deploy/config/rules.yaml" \
    > "$run_dir/server.log" 2>&1 &
  pids+=($!)
  local orthanc=http://127.0.0.1:$orthanc_http
  local deadline=$((SECONDS + 120))
  until curl -sf "$orthanc/system" > /dev/null &&
        "$client_bin" health --server "127.0.0.1:$node_grpc" > /dev/null 2>&1 &&
        [[ $(wc -l < "$run_dir/ports" 2>/dev/null || echo 0) -ge 3 ]]; do
    ((SECONDS < deadline)) || { echo "Orthanc or the server did not start" >&2; return 1; }
    sleep 0.2
  done
  local node_dicom
  node_dicom=$(sed -n 3p "$run_dir/ports")
  TCP_NODELAY=1 storescu -aet ORTHANC -aec INTERSLICE 127.0.0.1 "$node_dicom" "$series"/*.dcm
  local t0 t1=""
  t0=$(now)
  # Orthanc's count, every 50 ms (curl: cheap), until it reaches the count the
  # node logs as delivered. The node is not polled: an `interslice list`
  # every 50 ms cost a third of a core on this 2-core machine, taken from the
  # job it times. The job's end is its "succeeded" line in the node's log
  # (millisecond timestamps, the same clock).
  local count delivered="" log_line
  : > "$run_dir/counts"
  deadline=$((SECONDS + 600))
  while :; do
    count=$(curl -sf "$orthanc/statistics" | sed -n 's/.*"CountInstances" : \([0-9]*\).*/\1/p')
    echo "$(now) ${count:-0}" >> "$run_dir/counts"
    if [[ -z $delivered ]]; then
      log_line=$(grep -o 'delivered to peer orthanc: [0-9]* instance' "$run_dir/server.log" || true)
      [[ -n $log_line ]] && delivered=$(awk '{print $5}' <<< "$log_line")
    fi
    if [[ -n $delivered ]] && ((${count:-0} >= delivered)); then break; fi
    ((SECONDS < deadline)) || { echo "results not in Orthanc after 600 s" >&2; return 1; }
    sleep 0.05
  done
  t1=$(awk -v n="$delivered" '$2 >= n {print $1; exit}' "$run_dir/counts")
  stop_all
  local stamp t_job
  stamp=$(grep -m1 ' succeeded: ' "$run_dir/server.log" | cut -d' ' -f1)
  t_job=$(date -d "$stamp" +%s.%N 2>/dev/null || echo "$t1")
  awk -v a="$t0" -v j="$t_job" -v b="$t1" -v n="$delivered" \
    'BEGIN {printf "%.2f %.2f %.2f %d\n", b - a, j - a, b - j, n}'
}

echo "machine: $(nproc) CPUs, load before $(cut -d' ' -f1-3 /proc/loadavg)"
for series in "$root/data/ct-head-phantom-thick" "$root/tests/data/ct-tilt"; do
  name=$(basename "$series")
  files=("$series"/*.dcm)
  instances=${#files[@]}
  times=() jobs=() sends=()
  for run in $(seq "$runs"); do
    read -r seconds job send results < <(round_trip "$series" "$work/$name-$run")
    echo "$name ($instances instances) run $run: last instance in -> $results results in Orthanc: $seconds s (job done at $job s, then sending $send s)"
    times+=("$seconds") jobs+=("$job") sends+=("$send")
  done
  echo "$name: median of $runs: $(printf '%s\n' "${times[@]}" | median) s (job $(printf '%s\n' "${jobs[@]}" | median) s, sending $(printf '%s\n' "${sends[@]}" | median) s)"
done
echo "load after $(cut -d' ' -f1-3 /proc/loadavg)"
