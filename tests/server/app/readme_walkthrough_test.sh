#!/usr/bin/env bash
# README's "Next to a PACS" walk-through, followed literally (issue 25):
#   readme_walkthrough_test.sh SOURCE_DIR INTERSLICE_SERVER INTERSLICE
# The ```sh blocks between <!-- walkthrough:begin --> and
# <!-- walkthrough:end --> in README.md are run in order, as one shell
# session, from a folder that stands for the repository root (symbolic links
# to the checkout's top-level entries, so that the files the blocks write land
# in a temporary folder, not in the checkout). The only changes are the ones
# README itself tells a user to make: free ports for 4242, 8042, 11112 and
# 50051, and a folder of the test's own for /var/tmp. `interslice-server` and
# `interslice` are the build's (put first on PATH, as an installed copy would
# be). Then: the results of the shipped rule's job must be in Orthanc, in the
# source's study, every DICOM file the job wrote, and nothing elsewhere.
# Registered in tests/server/dicom/CMakeLists.txt through
# tests/testing/require-tool.sh (Orthanc, storescu, curl, python3 looked up
# when it runs: missing, the test is skipped, or fails in CI).
set -euo pipefail

source_dir=$(cd "$1" && pwd)
server_bin=$(realpath "$2")
client_bin=$(realpath "$3")
readme=$source_dir/README.md
series=$source_dir/tests/data/ct-tilt

fail() {
  echo "FAIL: $*" >&2
  exit 1
}

work=$(mktemp -d "${TMPDIR:-/tmp}/interslice-walkthrough.XXXXXX")
trap 'rm -rf "$work"' EXIT  # until the walk-through starts (cleanup below)
root=$work/checkout
mkdir -p "$root" "$work/var" "$work/bin"
for entry in "$source_dir"/*; do
  ln -s "$entry" "$root/$(basename "$entry")"
done
ln -s "$server_bin" "$work/bin/interslice-server"
ln -s "$client_bin" "$work/bin/interslice"
export PATH="$work/bin:/usr/sbin:$PATH"

# The blocks, exactly as README shows them.
script=$work/walkthrough.sh
awk '
  /<!-- walkthrough:begin -->/ { inside = 1; next }
  /<!-- walkthrough:end -->/ { inside = 0; next }
  inside && /^```sh/ { block = 1; next }
  inside && block && /^```/ { block = 0; print ""; next }
  inside && block { print }
' "$readme" > "$script.readme"
[[ -s $script.readme ]] ||
  fail "README.md has no \`\`\`sh block between <!-- walkthrough:begin --> and <!-- walkthrough:end -->"
for port in 4242 8042 11112 50051; do
  grep -qw "$port" "$script.readme" ||
    fail "the walk-through no longer uses port $port: update README's list of substitutions and this test"
done
grep -q '/var/tmp/' "$script.readme" ||
  fail "the walk-through no longer writes under /var/tmp: update README's list of substitutions and this test"

# Four free loopback ports (bound, read, released: another process could
# take one in between; unlikely, and the walk-through would then fail
# loudly at its start).
read -r orthanc_dicom orthanc_http node_dicom node_grpc < <(python3 - <<'PY'
import socket
socks = [socket.socket() for _ in range(4)]
for s in socks:
    s.bind(("127.0.0.1", 0))
print(*(s.getsockname()[1] for s in socks))
PY
)
sed -e "s#/var/tmp/#$work/var/#g" \
    -e "s/\\b4242\\b/$orthanc_dicom/g" -e "s/\\b8042\\b/$orthanc_http/g" \
    -e "s/\\b11112\\b/$node_dicom/g" -e "s/\\b50051\\b/$node_grpc/g" \
    "$script.readme" > "$script"

# The walk-through's waiting loops (`until ...; do sleep 1; done`) end when
# their condition holds; this bounds them, so a server that never comes up
# fails the test with a reason rather than at ctest's timeout.
deadline=$((SECONDS + 120))
sleep() {
  ((SECONDS < deadline)) || fail "a waiting loop of the walk-through did not end in 120 s"
  command sleep "$@"
}

cleanup() {
  local status=$?
  # The walk-through's background processes (Orthanc, the server).
  local pids
  mapfile -t pids < <(jobs -p)
  if ((${#pids[@]})); then
    kill "${pids[@]}" 2>/dev/null || true
    local alive pid
    for _ in $(seq 100); do  # up to 10 s for a clean stop
      alive=0
      for pid in "${pids[@]}"; do kill -0 "$pid" 2>/dev/null && alive=1; done
      ((alive)) || break
      command sleep 0.1
    done
    kill -9 "${pids[@]}" 2>/dev/null || true
  fi
  if ((status != 0)); then
    echo "--- the walk-through as run:" >&2
    cat "$script" >&2
    for log in "$work"/var/*.log; do
      [[ -f $log ]] && { echo "--- $log (last 40 lines):" >&2; tail -n 40 "$log" >&2; }
    done
  fi
  rm -rf "$work"
  exit "$status"
}
trap cleanup EXIT

echo "running README's walk-through ($(grep -c . "$script") lines) in $root"
cd "$root"
# shellcheck disable=SC1090
source "$script"
set -euo pipefail  # whatever the walk-through set

# Every DICOM file the job wrote must reach Orthanc, in the source's study.
orthanc=http://127.0.0.1:$orthanc_http
study_uid=$(dcmdump +P 0020,000d "$series/I10.dcm" | sed -n 's/.*\[\(.*\)\].*/\1/p')
[[ -n $study_uid ]] || fail "no StudyInstanceUID in $series/I10.dcm"
source_files=("$series"/*.dcm)
source_instances=${#source_files[@]}

job_out() {
  local dirs=("$work"/var/interslice/jobs/*/out)
  ((${#dirs[@]} == 1)) && [[ -d ${dirs[0]} ]] || return 1
  echo "${dirs[0]}"
}
count_in_study() {
  curl -sf "$orthanc/tools/find" \
    -d "{\"Level\": \"Instance\", \"Query\": {\"StudyInstanceUID\": \"$study_uid\"}}" |
    python3 -c 'import json, sys; print(len(json.load(sys.stdin)))'
}
expected=-1
got=-1
until ((got >= 0 && got == expected)); do
  ((SECONDS < deadline + 120)) ||
    fail "results not all in Orthanc's study after the job: $got instance(s), expected $expected"
  command sleep 1
  out=$(job_out) || continue
  # The job's state (`list`'s first line): succeeded once it published
  # its results.
  state=$(interslice list --all --server "127.0.0.1:$node_grpc" 2>/dev/null | head -n 1 || true)
  if grep -qw -e failed -e cancelled <<< "$state"; then fail "the job ended: $state"; fi
  grep -qw succeeded <<< "$state" || continue
  expected=$((source_instances + $(find "$out" -name '*.dcm' | wc -l)))
  got=$(count_in_study)
done
echo "Orthanc holds $got instance(s) in the source's study: the $source_instances source instance(s) and every DICOM file of the job"

# Nothing went elsewhere: one patient, one study; the study holds the source
# series and the results (the derived series, the SEG, the Encapsulated STL).
studies=$(curl -sf "$orthanc/studies" | python3 -c 'import json, sys; print(len(json.load(sys.stdin)))')
((studies == 1)) || fail "Orthanc holds $studies studies, expected only the source's"
modalities=$(curl -sf "$orthanc/series?expand" |
  python3 -c 'import json, sys; print(" ".join(sorted(s["MainDicomTags"].get("Modality", "?") for s in json.load(sys.stdin))))')
echo "series in the study, by modality: $modalities"
for modality in SEG M3D; do
  grep -qw "$modality" <<< "$modalities" || fail "no $modality series in the study ($modalities)"
done
ct_series=$(grep -o -w CT <<< "$modalities" | wc -l)
((ct_series == 2)) || fail "expected the source and the derived CT series, got $ct_series CT series"
echo "PASS: README's walk-through, followed literally, put the results in the source's study"
