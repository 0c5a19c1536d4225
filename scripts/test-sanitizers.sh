#!/usr/bin/env bash
# The whole test suite under AddressSanitizer + UndefinedBehaviorSanitizer
# (LeakSanitizer included): configures and builds build-asan with
# -DINTERSLICE_SANITIZE=address,undefined, runs every ctest test with the
# suppressions in tools/sanitizers/, and exits non-zero on any failing test or
# any sanitizer report from any process (the test binaries and the
# `interslice` / `interslice-server` processes they start).
#   bash scripts/test-sanitizers.sh            # CI: after scripts/test.sh
#   JOBS=1 bash scripts/test-sanitizers.sh     # build and ctest parallelism
#   bash scripts/test-sanitizers.sh -R Volume  # extra arguments go to ctest
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"

build="${INTERSLICE_SANITIZE_BUILD_DIR:-$root/build-asan}"
jobs="${JOBS:-$(nproc)}"
supp="$root/tools/sanitizers"

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

common="halt_on_error=1:exitcode=86:print_stacktrace=1:log_exe_name=1"
export ASAN_OPTIONS="$common:log_path=$reports/asan:detect_leaks=1:detect_stack_use_after_return=1:check_initialization_order=1:strict_string_checks=1"
export LSAN_OPTIONS="suppressions=$supp/lsan.supp:print_suppressions=0"
export UBSAN_OPTIONS="$common:log_path=$reports/ubsan:report_error_type=1:suppressions=$supp/ubsan.supp"

# Benchmarks and evaluation tools are not part of ctest: not built here.
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DINTERSLICE_SANITIZE=address,undefined \
  -DINTERSLICE_BUILD_BENCHMARKS=OFF -DINTERSLICE_BUILD_TOOLS=OFF >/dev/null
cmake --build "$build" -j"$jobs"

start=$SECONDS
status=0
ctest --test-dir "$build" --output-on-failure -j"$jobs" "$@" || status=1
echo "sanitized suite: $((SECONDS - start)) s"
exit "$status"
