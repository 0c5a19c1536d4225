#!/usr/bin/env bash
# The outbox's send rate (server/node/outbox.h StoreFiles, through
# build/bench/interslice_dicom_store_bench) to DCMTK's storescp and to
# Debian's Orthanc, each started with and without TCP_NODELAY=1 (their own
# Nagle setting), for three senders run in turn (interleaved, REPEAT rounds):
#   before  Nagle on, one association (the server before issue 25)
#   nodelay Nagle off, one association
#   four    Nagle off, max_associations 4
# The 28-slice phantom (532 KiB a slice) is sent COPIES times per run.
# Prints the medians in instances/s.
#   bench/dicom_store.sh [BUILD_DIR]      (REPEAT=5 COPIES=4 by default)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
bench=$build/bench/interslice_dicom_store_bench
repeat=${REPEAT:-5}
copies=${COPIES:-4}
phantom=$root/data/ct-head-phantom-thick
work=$(mktemp -d "${TMPDIR:-/tmp}/interslice-dicom-store.XXXXXX")
receiver=
cleanup() { [[ -n $receiver ]] && kill "$receiver" 2>/dev/null; wait 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
wait_port() { for _ in $(seq 600); do (exec 3<>/dev/tcp/127.0.0.1/"$1") 2>/dev/null && return 0; sleep 0.1; done; return 1; }
median() { sort -g | awk '{v[NR]=$1} END {print (NR%2 ? v[(NR+1)/2] : (v[NR/2]+v[NR/2+1])/2)}'; }

start_storescp() {  # $1: TCP_NODELAY value or "" (unset)
  port=$(free_port); ae=STORESCP
  rm -rf "$work/in"; mkdir -p "$work/in"
  if [[ -n $1 ]]; then TCP_NODELAY=$1 storescp --fork -od "$work/in" "$port" >"$work/scp.log" 2>&1 &
  else env -u TCP_NODELAY storescp --fork -od "$work/in" "$port" >"$work/scp.log" 2>&1 & fi
  receiver=$!; wait_port "$port"
}
start_orthanc() {  # $1: TCP_NODELAY value or ""
  port=$(free_port); ae=ORTHANC; local http; http=$(free_port)
  rm -rf "$work/orthanc"; mkdir -p "$work/orthanc"
  cat >"$work/orthanc.json" <<JSON
{"Name": "bench", "StorageDirectory": "$work/orthanc", "IndexDirectory": "$work/orthanc",
 "HttpPort": $http, "DicomPort": $port, "DicomAet": "ORTHANC", "RemoteAccessAllowed": false,
 "DicomServerEnabled": true, "DicomCheckCalledAet": false, "DicomAlwaysAllowStore": true,
 "DicomAlwaysAllowEcho": true, "Plugins": [], "StorageCompression": false}
JSON
  if [[ -n $1 ]]; then TCP_NODELAY=$1 Orthanc "$work/orthanc.json" >"$work/orthanc.log" 2>&1 &
  else env -u TCP_NODELAY Orthanc "$work/orthanc.json" >"$work/orthanc.log" 2>&1 & fi
  receiver=$!; wait_port "$port"
}
stop_receiver() { kill "$receiver"; wait "$receiver" 2>/dev/null || true; receiver=; }

echo "machine: $(nproc) CPUs, load $(cut -d' ' -f1-3 /proc/loadavg); $repeat rounds; $((28 * copies)) instances a run"
for target in storescp orthanc; do
  for receiver_nodelay in "" 1; do
    "start_$target" "$receiver_nodelay"
    declare -A rates=([before]="" [nodelay]="" [four]="") fails=()
    # One untimed run: the receiver's first association after its start.
    "$bench" "$phantom" --port "$port" --ae "$ae" >/dev/null 2>&1 || true
    for ((r = 0; r < repeat; ++r)); do
      for variant in before nodelay four; do
        case $variant in
          before) args=(--associations 1 --nagle-on) ;;
          nodelay) args=(--associations 1) ;;
          four) args=(--associations 4) ;;
        esac
        if line=$("$bench" "$phantom" --port "$port" --ae "$ae" --copies "$copies" "${args[@]}" 2>>"$work/bench.err"); then
          rates[$variant]+="$(sed -n 's/.*s, \([0-9.]*\) instances\/s$/\1/p' <<<"$line") "
        else  # said, not hidden: the run counts as failed
          fails[$variant]=$((${fails[$variant]:-0} + 1))
          echo "  $target ${variant}: $(tail -1 "$work/bench.err")"
        fi
      done
    done
    stop_receiver
    label="$target, receiver TCP_NODELAY=${receiver_nodelay:-unset}"
    for variant in before nodelay four; do
      printf '%-40s %-8s median %7.1f instances/s (runs: %s; failed runs: %d)\n' "$label" "$variant" \
        "$(tr ' ' '\n' <<<"${rates[$variant]}" | grep . | median)" "${rates[$variant]}" "${fails[$variant]:-0}"
    done
  done
done
