#!/usr/bin/env bash
# The DICOM edge under faults and floods (issue 22), against a real
# interslice-server and a real Orthanc on loopback (the results of every job
# go to Orthanc by C-STORE). Prints the figures the work is judged by:
# server crashes, partial series interpolated, duplicate result sets, how
# fast a real sender is served during floods, refused connections counted.
#
#   bench/dicom_load_fault.sh [BUILD_DIR]      (bench/load_fault.sh runs it last)
#
# Phases:
#  A. hostile instances and PDUs: a data set nested 10,000 deep, a command
#     set nested so, 20 connections of random bytes, 20 requests claiming a
#     4 GiB PDU; the server must answer or cut each and stay up.
#  B. senders killed at random points: 8 storescu runs of a 28-slice copy
#     of the phantom (sent 4 times over) killed (SIGKILL) after 0.1 s to half
#     a whole transfer's time, then one clean run: exactly one job, of all
#     28 instances.
#  C. floods while a real storescu sends the series: 200 half-open
#     connections, 20 sending their request at a byte a second, 20 of
#     garbage; echoscu every 0.5 s meanwhile (its time measured) and one
#     storescu of the series (its time measured against a quiet run).
#  D. the server killed (SIGKILL) during a receive, restarted: no job of the
#     interrupted transfer; the series re-sent: one job.
#  E. the server killed during a delivery to Orthanc, restarted: the
#     delivery resumes, its attempt count includes the killed one, Orthanc
#     holds one derived series.
#  G. (issue 39, finding 1) a series' transfer killed midway (14 of its 28
#     instances held), then one of them stored again unchanged in a clean
#     association: no job
#     (the series stays incomplete); then the whole series: one job of 28.
#  H. (finding 2) a STOW-RS body whole but one byte short of its
#     Content-Length, the client waiting: 400, no job.
#  I. (finding 3) a series by STOW-RS one instance per request (28 requests,
#     one part each) under a rule with complete_on_release: one job, of
#     28 instances.
#  J. (finding 4) the node's own results (a job's derived series) sent back
#     to it: no job.
#  F. a spool on a 6 MB tmpfs (unshare -m, needs root or user namespaces):
#     every instance answered (success or 0xA700), the association kept.
# Every loop is bounded; loopback only.
set -uo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
server=$build/server/interslice-server
hostile="python3 $root/bench/dicom_hostile.py"
work=$(mktemp -d /tmp/interslice-dicom-load-XXXXXX)
phantom=("$root"/data/ct-head-phantom-thick/*.dcm)
server_pid= orthanc_pid=
cleanup() {
  [[ -n $server_pid ]] && kill -9 "$server_pid" 2>/dev/null
  [[ -n $orthanc_pid ]] && kill "$orthanc_pid" 2>/dev/null
  wait 2>/dev/null
  if [[ -n ${KEEP:-} ]]; then echo "kept: $work"; else rm -rf "$work"; fi
}
trap cleanup EXIT
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN{printf "%.2f", b-a}'; }
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

echo "machine: $(nproc) CPUs, $(awk '/MemTotal/ {printf "%.1f GiB", $2/1048576}' /proc/meminfo), load $(cut -d' ' -f1-3 /proc/loadavg)"

# Orthanc (Debian's), the PACS the results go to.
o_http=$(free_port) o_dicom=$(free_port)
mkdir -p "$work/orthanc"
cat >"$work/orthanc.json" <<JSON
{"Name": "bench", "StorageDirectory": "$work/orthanc", "IndexDirectory": "$work/orthanc",
 "HttpPort": $o_http, "DicomPort": $o_dicom, "DicomAet": "ORTHANC",
 "RemoteAccessAllowed": false, "AuthenticationEnabled": false,
 "DicomCheckCalledAet": false, "DicomAlwaysAllowStore": true, "Plugins": []}
JSON
/usr/sbin/Orthanc "$work/orthanc.json" >"$work/orthanc.log" 2>&1 &
orthanc_pid=$!
for _ in $(seq 200); do curl -sf "http://127.0.0.1:$o_http/system" >/dev/null && break; sleep 0.1; done
orthanc_series() { curl -sf "http://127.0.0.1:$o_http/series" | python3 -c 'import json,sys; print(len(json.load(sys.stdin)))'; }
orthanc_instances() { curl -sf "http://127.0.0.1:$o_http/instances" | python3 -c 'import json,sys; print(len(json.load(sys.stdin)))'; }

cat >"$work/peers.yaml" <<YAML
peers:
  - {name: tools, ae_title: STORESCU, host: 127.0.0.1, port: 1}
  - {name: echo, ae_title: ECHOSCU, host: 127.0.0.1, port: 1}
  - {name: orthanc, ae_title: ORTHANC, host: 127.0.0.1, port: $o_dicom}
YAML
cat >"$work/rules.yaml" <<YAML
stable_seconds: 1
rules:
  - name: stow
    match: {modality: CT, calling_ae: STOW}
    complete_on_release: true
    job: {threshold: 300, roi: [208, 208, 0, 304, 304, 28], factor: 4,
          output_series: [intensity], mesh: none, volume: none}
  - name: ct
    match: {modality: CT, slice_count: {min: 20}}
    complete_on_release: true
    job: {threshold: 300, roi: [208, 208, 0, 304, 304, 28], factor: 4,
          output_series: [intensity], mesh: none, volume: none}
    send_to: [orthanc]
YAML

# Copies of the phantom as series of their own (other Study and Series
# UIDs, the same for every file of a copy), for phases B, D, E, G and I:
# a series whose job was made and that arrives again unchanged makes no job.
relabel() {  # name study-uid series-uid
  mkdir -p "$work/$1"
  cp "${phantom[@]}" "$work/$1/"
  dcmodify -nb -m "(0020,000d)=$2" -m "(0020,000e)=$3" "$work/$1"/*.dcm >/dev/null 2>&1
}
relabel cut 1.2.826.0.1.3680043.10.1039.1 1.2.826.0.1.3680043.10.1039.2
relabel stow 1.2.826.0.1.3680043.10.1039.3 1.2.826.0.1.3680043.10.1039.4
relabel killed 1.2.826.0.1.3680043.10.1039.5 1.2.826.0.1.3680043.10.1039.6
relabel interrupted 1.2.826.0.1.3680043.10.1039.7 1.2.826.0.1.3680043.10.1039.8
relabel delivered 1.2.826.0.1.3680043.10.1039.9 1.2.826.0.1.3680043.10.1039.10
cut_series=("$work"/cut/*.dcm)
stow_series=("$work"/stow/*.dcm)

crashes=0
hport=$(free_port)
start_server() {  # extra flags
  rm -f "$work/port"
  "$server" --listen 127.0.0.1:0 --metrics-listen 127.0.0.1:0 \
    --http-listen "127.0.0.1:$hport" \
    --spool "$work/spool" --port-file "$work/port" --workers 1 --drain-grace 5 \
    --dicom-listen 127.0.0.1:0 --dicom-peers "$work/peers.yaml" \
    --rules "$work/rules.yaml" --dicom-acse-timeout 5 --delivery-retry 0.5 \
    "$@" >>"$work/server.log" 2>&1 &
  server_pid=$!
  for _ in $(seq 300); do [[ -f $work/port && $(wc -l <"$work/port") -ge 3 ]] && break; sleep 0.05; done
  mport=$(sed -n 2p "$work/port") dport=$(sed -n 3p "$work/port")
}
alive() {  # counts a crash (and restarts) if the server is gone
  if ! kill -0 "$server_pid" 2>/dev/null; then
    crashes=$((crashes + 1))
    echo "  SERVER DOWN after: $1"
    wait "$server_pid" 2>/dev/null
    start_server
  fi
}
metric() {  # sample name with labels -> value (0 if absent)
  curl -sf "http://127.0.0.1:$mport/metrics" | awk -v s="$1" '$1 == s {print $2; f=1} END {if (!f) print 0}'
}
refused() { metric "interslice_dicom_connections_refused_total{reason=\"$1\"}"; }
jobs_made() { grep -c "made by rule" "$work/server.log"; }
wait_jobs() {  # until N jobs were made (bounded)
  for _ in $(seq 600); do [[ $(jobs_made) -ge $1 ]] && return 0; sleep 0.1; done
  return 1
}
store() { storescu -aec INTERSLICE 127.0.0.1 "$dport" "$@"; }
echo_ms() {
  local t0; t0=$(now)
  echoscu -to 10 -ta 10 -aec INTERSLICE 127.0.0.1 "$dport" >/dev/null 2>&1 || { echo fail; return; }
  echo "$(since "$t0")"
}
# The phantom four times over (112 instances, re-sent ones replace
# themselves): a transfer long enough to be cut at a random point.
long=("${phantom[@]}" "${phantom[@]}" "${phantom[@]}" "${phantom[@]}")
killed_series=("$work"/killed/*.dcm)
killed_long=("${killed_series[@]}" "${killed_series[@]}" "${killed_series[@]}" "${killed_series[@]}")
interrupted_series=("$work"/interrupted/*.dcm)
interrupted_long=("${interrupted_series[@]}" "${interrupted_series[@]}" "${interrupted_series[@]}" "${interrupted_series[@]}")
delivered_series=("$work"/delivered/*.dcm)
random_delay() { awk -v r=$RANDOM -v a="$1" -v b="$2" 'BEGIN{printf "%.3f", a + (b - a) * r / 32767}'; }
aborted_mid() {  # associations the server saw end without a release, with instances kept
  grep -E "STORESCU -> INTERSLICE aborted: [1-9][0-9]* instance" "$work/server.log" | wc -l
}

start_server
echo "server: DICOM port $dport, Orthanc ORTHANC@$o_dicom"

echo "== A. hostile instances and PDUs"
for mode in nested command; do echo "  $($hostile "$dport" "$mode")"; alive "$mode"; done
echo "  $($hostile "$dport" garbage 20)"; alive garbage
echo "  $($hostile "$dport" huge 20)"; alive huge
echo "  echoscu afterwards: $(echo_ms) s"

echo "== B. storescu killed at random points (8 runs), then one clean run"
t0=$(now)
store "${long[@]}" >/dev/null 2>&1
whole=$(since "$t0")
wait_jobs 1 || true
made=$(jobs_made) aborted=$(aborted_mid)
for k in $(seq 8); do
  storescu -aec INTERSLICE 127.0.0.1 "$dport" "${killed_long[@]}" >/dev/null 2>&1 &
  sender=$!  # storescu itself (not a subshell), so that the kill reaches it
  sleep "$(random_delay 0.1 "$(awk -v w="$whole" 'BEGIN{print w * 0.5}')")"
  kill -9 "$sender" 2>/dev/null
  wait "$sender" 2>/dev/null
  sleep 0.3
done
alive "killed senders"
sleep 3
echo "  a whole transfer takes ${whole} s; killed senders the server saw abort with instances kept: $(($(aborted_mid) - aborted)) of 8; jobs made since: $(($(jobs_made) - made)); series made incomplete: $(metric 'interslice_dicom_events_total{event="series_incomplete"}')"
store "${killed_series[@]}" >/dev/null 2>&1 || echo "  clean run failed"
wait_jobs $((made + 1)) || echo "  no job after the clean run"
echo "  after the clean run: $(($(jobs_made) - made)) job(s)"

echo "== C. floods while a real storescu sends the series"
t0=$(now)
store "${phantom[@]}" >/dev/null 2>&1
quiet=$(since "$t0")
before_pending=$(($(refused pending_per_source) + $(refused pending_total) + $(refused request_deadline)))
floods=()
$hostile "$dport" halfopen 200 20 >"$work/halfopen.txt" &
floods+=($!)
$hostile "$dport" slowloris 20 20 >"$work/slow.txt" &
floods+=($!)
$hostile "$dport" garbage 20 >"$work/garbage.txt" &
floods+=($!)
sleep 1
: >"$work/echo.txt"
( for _ in $(seq 30); do echo_ms >>"$work/echo.txt"; sleep 0.5; done ) &
echoer=$!
t0=$(now)
store "${phantom[@]}" >"$work/flood-store.txt" 2>&1 && flood_rc=0 || flood_rc=$?
during=$(since "$t0")
wait "$echoer" "${floods[@]}"
alive floods
echo "  $(cat "$work/halfopen.txt")"
echo "  $(cat "$work/slow.txt")"
echo "  $(cat "$work/garbage.txt")"
echo "  storescu of 28 instances: ${quiet} s quiet, ${during} s during the floods (exit $flood_rc)"
echo "  echoscu during the floods: $(grep -c fail "$work/echo.txt") failed of $(wc -l <"$work/echo.txt"), max $(grep -v fail "$work/echo.txt" | sort -n | tail -1) s, median $(grep -v fail "$work/echo.txt" | sort -n | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}') s"
after_pending=$(($(refused pending_per_source) + $(refused pending_total) + $(refused request_deadline)))
echo "  idle/slow connections opened 220, counted as refused or cut: $((after_pending - before_pending)) (pending_per_source $(refused pending_per_source), pending_total $(refused pending_total), request_deadline $(refused request_deadline))"
echo "== D. server killed (SIGKILL) during a receive, restarted"
refused_c=$(curl -sf "http://127.0.0.1:$mport/metrics" | awk -F'[{}]' '/^interslice_dicom_connections_refused_total\{/ {split($3, v, " "); sub(/reason=/, "", $2); printf "%s %s ", $2, v[1]}')
refused_sum=$(curl -sf "http://127.0.0.1:$mport/metrics" | awk '/^interslice_dicom_connections_refused_total\{/ {s += $2} END {print s + 0}')
sleep 2
made=$(jobs_made)
storescu -aec INTERSLICE 127.0.0.1 "$dport" "${interrupted_long[@]}" >/dev/null 2>&1 &
sender=$!
delay=$(random_delay 0.1 "$(awk -v w="$whole" 'BEGIN{print w * 0.5}')")
sleep "$delay"
kill -9 "$server_pid"; wait "$server_pid" 2>/dev/null
wait "$sender" 2>/dev/null
start_server
sleep 4
echo "  killed ${delay} s into a ${whole} s transfer; restarts that found an interrupted series: $(grep -c '1 of them interrupted mid-association' "$work/server.log"); jobs made since: $(($(jobs_made) - made))"
store "${interrupted_series[@]}" >/dev/null 2>&1 || echo "  resend failed"
wait_jobs $((made + 1)) || echo "  no job after the resend"
echo "  after the resend: $(($(jobs_made) - made)) job(s)"

echo "== E. server killed (SIGKILL) during a delivery to Orthanc, restarted"
# The outbox sends one delivery at a time: let the earlier ones finish.
for _ in $(seq 1800); do
  [[ $(grep -c "delivered to peer orthanc" "$work/server.log") -ge $(grep -c "succeeded:" "$work/server.log") ]] && break
  sleep 0.1
done
made=$(jobs_made)
store "${delivered_series[@]}" >/dev/null 2>&1
wait_jobs $((made + 1)) || true
job=$(grep "made by rule" "$work/server.log" | tail -1 | sed 's/.*job=\([^ ]*\) .*/\1/')
for _ in $(seq 900); do grep -q "job=$job succeeded" "$work/server.log" && break; sleep 0.05; done
sleep 2  # a delivery of this job's 109 instances takes about 10 s
kill -9 "$server_pid"; wait "$server_pid" 2>/dev/null
in_orthanc=$(orthanc_instances)
start_server
for _ in $(seq 1200); do grep -q "job=$job delivered" "$work/server.log" && break; sleep 0.1; done
echo "  killed 2 s into the delivery; after the restart: $(grep "job=$job delivered" "$work/server.log" | tail -1 | sed 's/^[^ ]* [^ ]* dicom: //; s/^[^ ]* [^ ]* //')"

jobs_by() { grep -c "made by rule $1 " "$work/server.log"; }
event() { metric "interslice_dicom_events_total{event=\"$1\"}"; }

echo "== G. a transfer killed midway, then one of its instances re-sent unchanged"
made=$(jobs_made) before_resend=$(event series_resend_not_completing) cut_aborted=$(aborted_mid)
# The first half of the series, 8 times over in one association (a
# transfer as long as phase B's), killed halfway: 14 of 28 instances held,
# the association never released, whatever the machine's speed.
half=("${cut_series[@]:0:14}")
storescu -aec INTERSLICE 127.0.0.1 "$dport" "${half[@]}" "${half[@]}" "${half[@]}" "${half[@]}" \
  "${half[@]}" "${half[@]}" "${half[@]}" "${half[@]}" >/dev/null 2>&1 &
sender=$!
sleep "$(awk -v w="$whole" 'BEGIN{printf "%.2f", w / 2}')"
kill -9 "$sender" 2>/dev/null; wait "$sender" 2>/dev/null
# The re-send must begin after the server saw the abort (it may still be
# reading what the killed sender had written): else it proves nothing.
for _ in $(seq 100); do [[ $(aborted_mid) -gt $cut_aborted ]] && break; sleep 0.1; done
store "${cut_series[0]}" >/dev/null 2>&1 || echo "  the re-send failed"
sleep 3  # three stable waits
alive "cut transfer"
echo "  jobs made after the cut and the unchanged re-send: $(($(jobs_made) - made)) (series_resend_not_completing +$(($(event series_resend_not_completing) - before_resend)))"
store "${cut_series[@]}" >/dev/null 2>&1 || echo "  the whole re-send failed"
wait_jobs $((made + 1)) || echo "  no job after the whole re-send"
sleep 2
echo "  after the whole series was sent: $(($(jobs_made) - made)) job(s): $(grep "made by rule" "$work/server.log" | tail -1 | sed 's/.*for a series from //')"

echo "== H. a STOW-RS body one byte short of its Content-Length, the client waiting"
made=$(jobs_made)
h_answer=$(python3 - "$hport" "${stow_series[@]:0:3}" <<'PY'
import socket, sys
port, files = int(sys.argv[1]), sys.argv[2:]
body = b""
for f in files:
    body += b"--b\r\nContent-Type: application/dicom\r\n\r\n" + open(f, "rb").read() + b"\r\n"
body += b"--b--\r\n"
s = socket.create_connection(("127.0.0.1", port))
s.sendall(b"POST /dicomweb/studies HTTP/1.1\r\nHost: x\r\n"
          b"Content-Type: multipart/related; type=\"application/dicom\"; boundary=b\r\n"
          b"Content-Length: %d\r\n\r\n" % (len(body) + 1) + body)
s.settimeout(60)
answer = b""
while True:
    try:
        chunk = s.recv(65536)
    except socket.timeout:
        break
    if not chunk:
        break
    answer += chunk
print(answer.split(b"\r\n", 1)[0].decode(errors="replace"))
PY
)
sleep 3
alive "short STOW body"
echo "  answer: ${h_answer:-none}; jobs made since: $(($(jobs_made) - made))"

echo "== I. a series by STOW-RS, one instance per request (complete_on_release)"
made=$(jobs_by stow)
codes=()
for f in "${stow_series[@]}"; do
  # One part per request, in the multipart/related form every STOW-RS
  # client sends (a single-part body is also accepted, docs/dicomweb.md).
  { printf -- '--b\r\nContent-Type: application/dicom\r\n\r\n'; cat "$f"; printf -- '\r\n--b--\r\n'; } >"$work/part"
  codes+=("$(curl -s -o /dev/null -w '%{http_code}' -H 'Content-Type: multipart/related; type="application/dicom"; boundary=b' --data-binary "@$work/part" "http://127.0.0.1:$hport/dicomweb/studies")")
done
for _ in $(seq 100); do [[ $(jobs_by stow) -gt $made ]] && break; sleep 0.1; done
sleep 3  # more stable waits: no second job
alive "STOW per instance"
echo "  28 requests answered: $(printf '%s\n' "${codes[@]}" | sort | uniq -c | awk '{printf "%s x%s ", $2, $1}'); jobs made: $(($(jobs_by stow) - made)), of $(grep "made by rule stow " "$work/server.log" | tail -n +$((made + 1)) | sed 's/.*(\([0-9]*\) instance(s).*/\1/' | sort -n | uniq -c | awk '{printf "%s%s instances x%s", (NR > 1 ? ", " : ""), $2, $1}')"

echo "== J. the node's own results sent back to it"
made=$(jobs_made) before_own=$(event own_results_not_run)
own_job=$(grep "made by rule ct " "$work/server.log" | tail -1 | sed 's/.*job=\([^ ]*\) .*/\1/')
mapfile -t own < <(find "$work/spool" -path "*$own_job*/out/*" -name '*.dcm' | sort)
((${#own[@]})) || echo "  no result instances of job $own_job found in the spool"
store "${own[@]}" >/dev/null 2>&1 || echo "  sending the results back failed"
sleep 3
alive "own results"
echo "  ${#own[@]} result instances of job $own_job sent back: jobs made $(($(jobs_made) - made)), own_results_not_run +$(($(event own_results_not_run) - before_own))"

echo "== F. a spool on a 6 MB tmpfs"
if unshare -m true 2>/dev/null; then
  mkdir -p "$work/small"
  rm -f "$work/small.port"
  unshare -m --propagation private sh -c 'mount -t tmpfs -o size=6m tmpfs "$0" && exec "$@"' \
    "$work/small" "$server" --listen 127.0.0.1:0 --spool "$work/small" \
    --port-file "$work/small.port" --dicom-listen 127.0.0.1:0 \
    --dicom-peers "$work/peers.yaml" >"$work/small.log" 2>&1 &
  small_pid=$!
  for _ in $(seq 300); do [[ -f $work/small.port && $(wc -l <"$work/small.port") -ge 3 ]] && break; sleep 0.05; done
  storescu -v -nh -aec INTERSLICE 127.0.0.1 "$(sed -n 3p "$work/small.port")" "${phantom[@]}" >"$work/small-store.txt" 2>&1
  rc=$?
  echo "  storescu exit $rc: $(grep -c 'Store Response (Success)' "$work/small-store.txt") stored, $(grep -c 'Refused: OutOfResources' "$work/small-store.txt") refused 0xA700, aborted: $(grep -c 'Peer aborted' "$work/small-store.txt"); server up: $(kill -0 $small_pid 2>/dev/null && echo yes || echo NO)"
  kill "$small_pid"; wait "$small_pid" 2>/dev/null
else
  echo "  skipped: no mount namespace (unshare -m)"
fi

echo "== summary"
sleep 2
partial=$(grep "made by rule" "$work/server.log" | grep -vc "(28 instance(s)")
echo "server crashes: $crashes"
echo "jobs made: $(jobs_made), of a partial series: $partial"
# Five source series reach the `ct` rule, whose results go to Orthanc: the
# phantom (phases A-C) and its copies of phases B, D, E and G; each must
# give exactly one derived series.
in_orthanc=$(orthanc_series)
echo "derived series in Orthanc: $in_orthanc (five source series: duplicates $((in_orthanc > 5 ? in_orthanc - 5 : 0)), missing $((in_orthanc < 5 ? 5 - in_orthanc : 0))), instances $(orthanc_instances)"
# A-C opened 281 connections that must be refused or cut: the nested
# command (1), garbage (20 + 20), 4 GiB requests (20), half-open (200),
# slow requests (20). The nested data set's association is not refused.
echo "refused or cut connections counted (phases A-C, one server): $refused_sum of 281 hostile or idle ones opened; by reason: $refused_c"
