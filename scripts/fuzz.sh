#!/usr/bin/env bash
# Runs each libFuzzer target (tests/fuzz) from the instrumented build
# (build-instrumented/: clang, ASan, UBSan, libFuzzer coverage;
# scripts/build-instrumented.sh builds it, the same folder as the sanitized
# test suite), after making its seed corpus.
#
#   bash scripts/fuzz.sh [SECONDS_PER_TARGET]    (default 30)
#
# A short run (the default) is a smoke test; the documented longer run is
# `bash scripts/fuzz.sh 600` (ten minutes per target). Installs nothing: clang
# and libFuzzer come from scripts/install-deps.sh. Exits non-zero when a
# target crashes, leaks, times out (-timeout=10 s per input) or exceeds
# -rss_limit_mb=2048; the input that did it is kept in
# build-instrumented/fuzz/<target>/crashes/ (reproduce:
# build-instrumented/tests/fuzz/<target> <file>). What each target found
# stays in build-instrumented/fuzz/<target>/corpus/ and seeds the next run.
#
# Environment: INTERSLICE_FUZZ_JOBS (compile jobs, default nproc),
# INTERSLICE_FUZZ_TARGETS (default "dicom_ingest_fuzzer job_spec_fuzzer
# upload_stream_fuzzer dicom_listener_fuzzer multipart_fuzzer
# stow_body_fuzzer"),
# INTERSLICE_FUZZ_ARGS (more libFuzzer flags for every target, e.g.
# "-max_len=65536": about twice the executions per second for
# dicom_ingest_fuzzer, at the price of truncating the 512 x 512 seeds).
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"

seconds="${1:-30}"
if ! [[ "$seconds" =~ ^[0-9]+$ ]] || [ "$seconds" -lt 1 ]; then
  echo "usage: $0 [SECONDS_PER_TARGET]" >&2
  exit 2
fi
jobs="${INTERSLICE_FUZZ_JOBS:-$(nproc)}"
targets=(${INTERSLICE_FUZZ_TARGETS:-dicom_ingest_fuzzer job_spec_fuzzer upload_stream_fuzzer dicom_listener_fuzzer multipart_fuzzer stow_body_fuzzer})
build="${INTERSLICE_INSTRUMENTED_BUILD_DIR:-$root/build-instrumented}"
work="$build/fuzz"
probe="$(mktemp -d)"
trap 'rm -rf "$probe"' EXIT

start=$(date +%s)
JOBS="$jobs" bash scripts/build-instrumented.sh "${targets[@]}"
echo "fuzz: built in $(($(date +%s) - start)) s"

# ---- Seed corpora (made afresh each run; nothing of it is committed) ------
separator=$'\xffIS-NEXT'  # dicom_ingest_fuzzer: between the files of one input
seeds_dicom() {
  local dir="$1" small="$probe/small"
  mkdir -p "$dir" "$small"
  # Every DICOM file of tests/data as it is.
  find tests/data -name '*.dcm' -print0 | while IFS= read -r -d '' f; do
    cp "$f" "$dir/$(echo "$f" | tr '/' '_')"
  done
  # Small series (64 x 64), one input holding several files, in several
  # transfer syntaxes: fast to execute and they reach the stack checks.
  local series name
  for series in ct-thick ct-tilt; do
    for f in tests/data/$series/*.dcm; do
      name="$(basename "$f" .dcm)"
      dcmscale --quiet --scale-x-size 64 "$f" "$small/$series-$name.dcm"
      dcmcrle --quiet "$small/$series-$name.dcm" "$small/$series-$name-rle.dcm"
      dcmcjpeg --quiet --encode-lossless-sv1 "$small/$series-$name.dcm" "$small/$series-$name-jpeg.dcm"
      dcmcjpls --quiet "$small/$series-$name.dcm" "$small/$series-$name-jpls.dcm"
    done
    local variant
    for variant in "" -rle -jpeg -jpls; do
      : >"$dir/$series$variant-series"
      local first=1
      for f in tests/data/$series/*.dcm; do
        name="$(basename "$f" .dcm)"
        [ $first = 1 ] || printf '%s' "$separator" >>"$dir/$series$variant-series"
        first=0
        cat "$small/$series-$name$variant.dcm" >>"$dir/$series$variant-series"
      done
    done
    cp "$small/$series-"*.dcm "$dir/"
  done
}
seeds_job_spec() {
  local dir="$1" proto=proto/interslice/v1/interslice.proto i=0 spec
  mkdir -p "$dir"
  for spec in \
    'threshold: 300' \
    'threshold: 300 method: SOLVER_METHOD_DIRECT outputs { volume_formats: VOLUME_FORMAT_NIFTI mesh_formats: MESH_FORMAT_STL }' \
    'threshold: 300 upper_threshold: 2000 insertion_factor: 4 method: SOLVER_METHOD_CONJUGATE_GRADIENT max_iterations: 15 tolerance: 0.001' \
    'threshold: -500 slice_spacing_mm: 0.5 energy_units: ENERGY_UNITS_MILLIMETRE mesh_adaptivity: 0.5 band_radius_mm: 3' \
    'threshold: 300 roi { x0: 10 y0: 10 z0: 0 x1: 200 y1: 200 z1: 4 } series_instance_uid: "1.2.3"' \
    'threshold: 300 strict_spacing: true derived_series { contents: "mask" contents: "distance" series_number: 9 } segmentation { enabled: true segment_label: "bone" } uid_root: "1.2.826.0.1" multiframe_volume: "stack 1"' \
    ; do
    printf '%s\n' "$spec" | protoc -I proto --encode=interslice.v1.JobSpec "$proto" >"$dir/spec-$i"
    i=$((i + 1))
  done
}

seeds_upload_stream() {
  # Records: a 2-byte little-endian length, then an interslice.v1.UploadRequest;
  # a first byte of 1 makes the fuzzer fill in whole-file SHA-256s.
  local dir="$1" proto=proto/interslice/v1/interslice.proto sha
  mkdir -p "$dir"
  record() {
    local b n
    b="$(mktemp)"
    printf '%s\n' "$1" | protoc -I proto --encode=interslice.v1.UploadRequest "$proto" >"$b"
    n=$(stat -c %s "$b")
    printf "\\x$(printf %02x $((n & 255)))\\x$(printf %02x $((n >> 8)))"
    cat "$b"
    rm -f "$b"
  }
  sha="$(printf 'hello world' | sha256sum | cut -c1-64 | sed 's/../\\x&/g')"
  { printf '\x01'
    record 'header { spec { threshold: 300 } file_count: 2 total_bytes: 22 }'
    record 'chunk { file_index: 0 file_name: "a.dcm" file_size: 11 data: "hello world" }'
    record 'chunk { file_index: 1 file_name: "d/b.dcm" file_size: 11 data: "second file" }'
  } >"$dir/two-files"
  { printf '\x00'
    record 'header { spec { threshold: 300 } file_count: 1 total_bytes: 11 }'
    record "chunk { file_index: 0 file_name: \"a.dcm\" file_size: 11 sha256: \"$sha\" data: \"hello\" }"
    record 'chunk { file_index: 0 offset: 5 data: " world" }'
  } >"$dir/split-file"
}

seeds_multipart() {
  # A mode byte (1: tiny limits), a chunk-size byte, then a body with the
  # boundary "frontier".
  local dir="$1"
  mkdir -p "$dir"
  printf '\x00\x07preamble\r\n--frontier\r\nContent-Type: application/dicom\r\n\r\nfirst part\r\n--frontier  \r\nContent-Length: 6\r\n\r\nsecond\r\n--frontier--\r\nepilogue' >"$dir/two-parts"
  printf '\x01\x00--frontier\r\n\r\n\r\n--frontie\r\n--frontier\r\nContent-Length: 99\r\n\r\nshort\r\n--frontier--' >"$dir/lying-length"
}

seeds_stow_body() {
  # A first byte choosing a 5-character boundary (taken from the next 5
  # bytes: "abcde"), a second the read size, then STOW-RS bodies: CRLF and
  # LF, preamble and epilogue, a DICOM file of tests/data as a part.
  local dir="$1" nl
  mkdir -p "$dir"
  for nl in $'\r\n' $'\n'; do
    { printf '\x04\x07abcde'
      printf 'preamble%s--abcde%sContent-Type: application/dicom%s%s' "$nl" "$nl" "$nl" "$nl"
      head -c 2048 tests/data/ct-thick/I10.dcm
      printf '%s--abcde  %s%sx%s--abcde--%sepilogue' "$nl" "$nl" "$nl" "$nl" "$nl"
    } >"$dir/body-${#nl}"
  done
}

# run_target TARGET: seeds, then the fuzzer for $seconds s; its summary line
# goes to $dir/summary, and the exit status is the fuzzer's verdict.
run_target() {
  local target="$1"
  local dir="$work/$target"
  rm -rf "$dir/seeds"
  mkdir -p "$dir/corpus" "$dir/crashes"
  case "$target" in
    dicom_ingest_fuzzer) seeds_dicom "$dir/seeds" ;;
    job_spec_fuzzer) seeds_job_spec "$dir/seeds" ;;
    upload_stream_fuzzer) seeds_upload_stream "$dir/seeds" ;;
    dicom_listener_fuzzer) python3 tests/fuzz/dicom_listener_seeds.py "$dir/seeds" ;;
    multipart_fuzzer) seeds_multipart "$dir/seeds" ;;
    stow_body_fuzzer) seeds_stow_body "$dir/seeds" ;;
  esac
  local log="$dir/last-run.log" started="$dir/started" rc
  echo "fuzz: $target for $seconds s (log: ${log#$root/})"
  touch "$started"
  set +e
  # The test suite's suppressions (tools/sanitizers/: GDCM's JPEG 2000
  # codec leaks libopenjp2 objects on undecodable frames; ITK's scanline
  # filters offset a null pointer).
  LSAN_OPTIONS="suppressions=$root/tools/sanitizers/lsan.supp:print_suppressions=0${LSAN_OPTIONS:+:$LSAN_OPTIONS}" \
  UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1:suppressions=$root/tools/sanitizers/ubsan.supp${UBSAN_OPTIONS:+:$UBSAN_OPTIONS}" \
    "$build/tests/fuzz/$target" -max_total_time="$seconds" -rss_limit_mb=2048 -timeout=10 \
      -print_final_stats=1 -artifact_prefix="$dir/crashes/" ${INTERSLICE_FUZZ_ARGS:-} \
      "$dir/corpus" "$dir/seeds" \
      >"$log" 2>&1
  rc=$?
  set -e
  local runs rate line
  runs="$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)"
  rate="$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log" | tail -1)"
  line="$target: ${runs:-?} executions in $seconds s (${rate:-?} exec/s), exit $rc"
  if [ $rc -ne 0 ]; then
    line="$line: FAILED, input kept in ${dir#$root/}/crashes/"
    # The report with its stacks (the CI log is all that is left of a fresh
    # clone's run), at most 80 lines from the first error.
    awk '/^==[0-9]+==ERROR|runtime error/ {on=1} on {print; if (++n >= 80) exit}' "$log" >&2 || true
    # And the input itself when it is small, so that it can be reproduced
    # from the log alone: base64 -d > input && <target> input.
    find "$dir/crashes" -type f -newer "$started" -print0 |
    while IFS= read -r -d '' artifact; do
      if [ "$(stat -c %s "$artifact")" -le 16384 ]; then
        echo "fuzz: $(basename "$artifact") (base64): $(base64 -w0 "$artifact")" >&2
      fi
    done
  fi
  echo "fuzz: $line"
  echo "$line" >"$dir/summary"
  return $rc
}

# The targets run INTERSLICE_FUZZ_PARALLEL at a time (default: the CPUs,
# capped at 2): each fuzzer is one process on one core, so each still gets
# its $seconds of a core, and the stage takes half the wall time on 2 cores.
parallel="${INTERSLICE_FUZZ_PARALLEL:-$(( $(nproc) < 2 ? 1 : 2 ))}"
for target in "${targets[@]}"; do
  rm -f "$work/$target/summary"
  while [ "$(jobs -rp | wc -l)" -ge "$parallel" ]; do
    wait -n || true
  done
  run_target "$target" &
done
wait || true
# The verdict from each target's summary line (a target whose line is
# missing did not finish: a failure too).
status=0
summary=()
for target in "${targets[@]}"; do
  if [ -s "$work/$target/summary" ]; then
    line="$(cat "$work/$target/summary")"
  else
    line="$target: FAILED, no result (the run did not finish)"
  fi
  [[ $line == *", exit 0" ]] || status=1
  summary+=("$line")
done
echo "fuzz: summary (total $(($(date +%s) - start)) s)"
printf '  %s\n' "${summary[@]}"
exit $status
