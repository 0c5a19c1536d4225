#!/usr/bin/env bash
# Receiving speed of the DICOM listener (server/net/dimse/storage_scp.h), with
# DCMTK's storescu on loopback: instances per second over one association
# and over four at once (the shipped phantom, 28 slices of 532 KiB, sent
# N times per association), and the time from the last instance to the job
# start (complete_on_release vs. a stable wait). Every instance is fsynced
# before its response, so the disk sets the pace. Medians of REPEAT runs.
#   bash bench/dicom_receive.sh [build-dir]     (N=10 REPEAT=3 by default)
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$root/build}"
server="$build/server/interslice-server"
n="${N:-10}"
repeat="${REPEAT:-3}"
stable="${STABLE:-2}"
work="$(mktemp -d "${TMPDIR:-/tmp}/interslice-dicom-bench.XXXXXX")"
trap 'kill "$pid" 2>/dev/null; wait "$pid" 2>/dev/null; rm -rf "$work"' EXIT
files=()
for ((i = 0; i < n; ++i)); do files+=("$root"/data/ct-head-phantom-thick/*.dcm); done
count=${#files[@]}

cat >"$work/peers.yaml" <<PEERS
peers: [{name: bench, ae_title: STORESCU, host: 127.0.0.1, port: 1}]
PEERS
# A rule no series matches (MR), so that no job competes for the CPU while
# receiving; the latency runs below use a matching one.
start_server() {  # $1 rules file
  rm -rf "$work/spool" "$work/ports"
  "$server" --listen 127.0.0.1:0 --spool "$work/spool" --port-file "$work/ports" \
    --dicom-listen 0.0.0.0:0 --dicom-peers "$work/peers.yaml" --rules "$1" \
    --isolation thread >"$work/log" 2>&1 &
  pid=$!
  for _ in $(seq 200); do [[ -s "$work/ports" && $(wc -l <"$work/ports") -ge 3 ]] && break; sleep 0.05; done
  port=$(sed -n 3p "$work/ports")
}
stop_server() { kill "$pid"; wait "$pid" || true; }
median() { sort -n | awk '{a[NR]=$1} END {print (NR%2) ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2}'; }

printf 'stable_seconds: 600\nrules: [{name: none, match: {modality: MR}, job: {threshold: 1}}]\n' >"$work/nomatch.yaml"
for assoc in 1 4; do
  rates=()
  for ((r = 0; r < repeat; ++r)); do
    start_server "$work/nomatch.yaml"
    t0=$(date +%s.%N)
    for ((a = 0; a < assoc; ++a)); do
      storescu -aec INTERSLICE 127.0.0.1 "$port" "${files[@]}" &
    done
    wait $(jobs -p | grep -v "^$pid$") 2>/dev/null || true
    t1=$(date +%s.%N)
    stop_server
    rates+=("$(echo "$assoc * $count / ($t1 - $t0)" | bc -l)")
  done
  printf '%d association(s) x %d instances: median %.1f instances/s (runs: %s)\n' \
    "$assoc" "$count" "$(printf '%s\n' "${rates[@]}" | median)" "$(printf '%.1f ' "${rates[@]}")"
done

# Last instance -> job started, from the server's own log timestamps.
latency() {  # $1 complete_on_release
  printf 'stable_seconds: %s\nrules: [{name: ct, match: {modality: CT}, complete_on_release: %s, job: {threshold: 300, roi: [208, 208, 0, 304, 304, 28], mesh: none, volume: none}}]\n' \
    "$stable" "$1" >"$work/rules.yaml"
  start_server "$work/rules.yaml"
  storescu -aec INTERSLICE 127.0.0.1 "$port" "$root"/data/ct-head-phantom-thick/*.dcm
  for _ in $(seq 600); do grep -q "started" "$work/log" && break; sleep 0.05; done
  stop_server
  python3 - "$work/log" <<'PY'
import re, sys, datetime
t = {}
for line in open(sys.argv[1]):
    m = re.match(r"(\S+) \S+ (.*)", line)
    if not m: continue
    when = datetime.datetime.fromisoformat(m.group(1))
    if "released:" in m.group(2): t["release"] = when
    if re.search(r"job=\S+ started", m.group(2)): t["start"] = when
print("%.3f" % (t["start"] - t["release"]).total_seconds())
PY
}
for cor in true false; do
  values=()
  for ((r = 0; r < repeat; ++r)); do values+=("$(latency "$cor")"); done
  printf 'last instance -> job start, complete_on_release %s (stable_seconds %s): median %s s (runs: %s)\n' \
    "$cor" "$stable" "$(printf '%s\n' "${values[@]}" | median)" "${values[*]}"
done
