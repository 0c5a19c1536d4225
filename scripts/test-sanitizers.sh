#!/usr/bin/env bash
# The test suite under AddressSanitizer + UndefinedBehaviorSanitizer
# (LeakSanitizer included), in the instrumented build (build-instrumented/,
# clang; scripts/build-instrumented.sh builds it, also for the fuzzers): runs
# the ctest tests labelled `sanitized` (scripts/test.sh says which and why)
# with the suppressions in tools/sanitizers/, and exits non-zero on any
# failing test or any sanitizer report from any process (the test binaries
# and the `interslice` / `interslice-server` processes they start).
#   bash scripts/test-sanitizers.sh            # CI: stage 6 of scripts/test.sh
#   JOBS=1 bash scripts/test-sanitizers.sh     # build and ctest parallelism
#   bash scripts/test-sanitizers.sh -R Volume  # extra arguments go to ctest
#   INTERSLICE_SANITIZE_LABELS= bash scripts/test-sanitizers.sh  # every test
# STAGE_STOP_TIME (a time of day, set by scripts/test.sh) becomes ctest's
# --stop-time.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"

build="${INTERSLICE_INSTRUMENTED_BUILD_DIR:-$root/build-instrumented}"
jobs="${JOBS:-$(nproc)}"
supp="$root/tools/sanitizers"
labels="${INTERSLICE_SANITIZE_LABELS-sanitized}"

# Every report goes to a file of its own, <dir>/<sanitizer>.<program>.<pid>,
# and the reporting process exits with 86. A test that expects a child to
# fail with exit code 1 then sees 86, and a report from a process whose exit
# code no test checks still fails this script, which prints all reports at
# the end (also when the build fails: gtest_discover_tests runs the test
# binaries at build time).
reports="$(mktemp -d "${TMPDIR:-/tmp}/interslice-sanitizer-reports.XXXXXX")"
finish() {
  local status=$?
  shopt -s nullglob
  local found=("$reports"/*)
  if ((${#found[@]})); then
    echo "FAIL: ${#found[@]} sanitizer report(s):"
    for f in "${found[@]}"; do
      echo "===== ${f##*/}"
      cat "$f"
    done
    status=1
  else
    echo "sanitizers: no reports"
  fi
  rm -rf "$reports"
  exit "$status"
}
trap finish EXIT
trap 'exit 143' TERM INT

common="halt_on_error=1:exitcode=86:print_stacktrace=1:log_exe_name=1"
export ASAN_OPTIONS="$common:log_path=$reports/asan:detect_leaks=1:detect_stack_use_after_return=1:check_initialization_order=1:strict_string_checks=1"
export LSAN_OPTIONS="suppressions=$supp/lsan.supp:print_suppressions=0"
export UBSAN_OPTIONS="$common:log_path=$reports/ubsan:report_error_type=1:suppressions=$supp/ubsan.supp"

JOBS="$jobs" bash scripts/build-instrumented.sh

start=$SECONDS
status=0
args=(--test-dir "$build" --output-on-failure -j"$jobs")
[[ -z $labels ]] || args+=(-L "^($labels)\$")
[[ -z ${STAGE_STOP_TIME:-} ]] || args+=(--stop-time "$STAGE_STOP_TIME")
# JUnit results for scripts/test.sh's table of the slowest tests.
[[ -z ${INTERSLICE_SANITIZED_JUNIT:-} ]] || args+=(--output-junit "$INTERSLICE_SANITIZED_JUNIT")
ctest "${args[@]}" "$@" || status=1
echo "sanitized suite: $((SECONDS - start)) s"
exit "$status"
