#!/usr/bin/env bash
# interslice next to a real Orthanc, timed: runs the end-to-end tests that
# print timings (tests/server/dicom/orthanc_e2e_test) RUNS times and prints
# the medians of
#  - submission -> every result stored in Orthanc (the phantom job, factor 2:
#    55 intensity images + SEG + Encapsulated STL = 57 instances),
#  - the outbox's C-STORE rate over one association (instances/s),
#  - Orthanc -> interslice C-STORE of the 28-slice phantom, and from its start
#    to the results being in Orthanc (stable_seconds 1 in that test: the wait
#    for the series to be complete is 1 s of it).
#   bench/dicom_send.sh [BUILD_DIR] [RUNS]
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
runs=${2:-3}
test=$build/tests/server/dicom/orthanc_e2e_test
out=$(mktemp /tmp/interslice-dicom-send-XXXXXX)
trap 'rm -f "$out"' EXIT
echo "machine: $(nproc) CPUs, load $(cut -d' ' -f1-3 /proc/loadavg)"
"$test" --gtest_filter='*ResultsLandInTheStudy*:*SeriesFromOrthancComesBack*' \
  --gtest_repeat="$runs" >"$out" 2>&1 || { cat "$out"; exit 1; }
median() { sort -g | awk '{v[NR]=$1} END {if (NR==0) {print "n/a"; exit}
  print (NR%2 ? v[(NR+1)/2] : (v[NR/2]+v[NR/2+1])/2)}'; }
echo "runs: $runs"
echo "submission -> results in Orthanc, s (median): $(
  sed -n 's/^submission to results in Orthanc: \([0-9.]*\) s$/\1/p' "$out" | median)"
echo "outbox C-STORE rate, instances/s (median): $(
  sed -n 's/.*delivered to peer orthanc: .*(\([0-9.]*\) instances\/s).*/\1/p' "$out" | median)"
echo "Orthanc -> interslice C-STORE of 28 instances, s (median): $(
  sed -n 's/^Orthanc -> interslice (C-STORE of 28 instances): \([0-9.]*\) s;.*/\1/p' "$out" | median)"
echo "start of that C-STORE -> results in Orthanc, s (median): $(
  sed -n 's/.*to the results in Orthanc: \([0-9.]*\) s (stable_seconds 1)$/\1/p' "$out" | median)"
