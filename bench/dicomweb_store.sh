#!/usr/bin/env bash
# STOW-RS against C-STORE: the outbox's send rate (server/node/outbox.h
# StoreFiles, through build/bench/interslice_dicom_store_bench) to one
# Debian Orthanc on loopback that has both doors open (its DICOM port and its
# DICOMweb plugin; TCP_NODELAY=1 for its DCMTK side), senders interleaved
# over REPEAT rounds:
#   cstore-4  C-STORE over 4 associations (the DIMSE default)
#   stow-1    STOW-RS, one request at a time
#   stow-4    STOW-RS, 4 requests in flight (the default max_associations)
# The 28-slice phantom (532 KiB a slice) is sent COPIES times per run (the
# same instances again: Orthanc replaces them). Prints the medians in
# instances/s and the stow-4 / cstore-4 ratio.
#   bench/dicomweb_store.sh [BUILD_DIR]      (REPEAT=5 COPIES=4 by default)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
bench=$build/bench/interslice_dicom_store_bench
repeat=${REPEAT:-5}
copies=${COPIES:-4}
phantom=$root/data/ct-head-phantom-thick
plugin=/usr/share/orthanc/plugins/libOrthancDicomWeb.so
[[ -f $plugin ]] || { echo "needs Debian's orthanc-dicomweb ($plugin)" >&2; exit 1; }
work=$(mktemp -d "${TMPDIR:-/tmp}/interslice-dicomweb-store.XXXXXX")
receiver=
cleanup() { [[ -n $receiver ]] && kill "$receiver" 2>/dev/null; wait 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
wait_port() { for _ in $(seq 600); do (exec 3<>/dev/tcp/127.0.0.1/"$1") 2>/dev/null && return 0; sleep 0.1; done; return 1; }
median() { sort -g | awk '{v[NR]=$1} END {print (NR%2 ? v[(NR+1)/2] : (v[NR/2]+v[NR/2+1])/2)}'; }

port=$(free_port); http=$(free_port)
mkdir -p "$work/orthanc"
cat >"$work/orthanc.json" <<JSON
{"Name": "bench", "StorageDirectory": "$work/orthanc", "IndexDirectory": "$work/orthanc",
 "HttpPort": $http, "DicomPort": $port, "DicomAet": "ORTHANC", "RemoteAccessAllowed": false,
 "DicomServerEnabled": true, "DicomCheckCalledAet": false, "DicomAlwaysAllowStore": true,
 "DicomAlwaysAllowEcho": true, "StorageCompression": false, "HttpThreadsCount": 10,
 "Plugins": ["$plugin"], "DicomWeb": {"Enable": true, "Root": "/dicom-web/"}}
JSON
TCP_NODELAY=1 Orthanc "$work/orthanc.json" >"$work/orthanc.log" 2>&1 &
receiver=$!
wait_port "$port"; wait_port "$http"
url=http://127.0.0.1:$http/dicom-web

echo "machine: $(nproc) CPUs, load $(cut -d' ' -f1-3 /proc/loadavg); $repeat rounds; $((28 * copies)) instances a run"
declare -A rates=([cstore-4]="" [stow-1]="" [stow-4]="") fails=()
# Untimed: the first association and the first request after the start.
"$bench" "$phantom" --port "$port" --ae ORTHANC >/dev/null 2>&1 || true
"$bench" "$phantom" --url "$url" >/dev/null 2>&1 || true
for ((r = 0; r < repeat; ++r)); do
  for variant in cstore-4 stow-1 stow-4; do
    case $variant in
      cstore-4) args=(--port "$port" --ae ORTHANC --associations 4) ;;
      stow-1) args=(--url "$url" --associations 1) ;;
      stow-4) args=(--url "$url" --associations 4) ;;
    esac
    if line=$("$bench" "$phantom" --copies "$copies" "${args[@]}" 2>>"$work/bench.err"); then
      rates[$variant]+="$(sed -n 's/.*s, \([0-9.]*\) instances\/s$/\1/p' <<<"$line") "
    else  # said, not hidden: the run counts as failed
      fails[$variant]=$((${fails[$variant]:-0} + 1))
      echo "  ${variant}: $(tail -1 "$work/bench.err")"
    fi
  done
done
declare -A med=()
for variant in cstore-4 stow-1 stow-4; do
  med[$variant]=$(tr ' ' '\n' <<<"${rates[$variant]}" | grep . | median)
  printf '%-9s median %7.1f instances/s (runs: %s; failed runs: %d)\n' "$variant" \
    "${med[$variant]}" "${rates[$variant]}" "${fails[$variant]:-0}"
done
awk -v s="${med[stow-4]}" -v c="${med[cstore-4]}" 'BEGIN {printf "stow-4 / cstore-4: %.2f\n", s / c}'
