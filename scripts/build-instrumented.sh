#!/usr/bin/env bash
# The instrumented build, build-instrumented/: clang with AddressSanitizer
# and UndefinedBehaviorSanitizer (LeakSanitizer included) on every target and
# libFuzzer's coverage instrumentation (-fsanitize=fuzzer-no-link) on the
# libraries the fuzz inputs reach (tests/fuzz/CMakeLists.txt), the gtest
# suite and the libFuzzer targets (tests/fuzz) in one folder. One
# compile serves scripts/test-sanitizers.sh (the suite under ASan/UBSan) and
# scripts/fuzz.sh (the fuzzers), which both call this script.
#
#   bash scripts/build-instrumented.sh [TARGET...]   # default: everything
#
# Environment: JOBS (compile jobs, default nproc),
# INTERSLICE_INSTRUMENTED_BUILD_DIR (default build-instrumented).
# Installs nothing: clang and its sanitizer/libFuzzer runtimes come from
# scripts/install-deps.sh (Debian: clang, libclang-rt-14-dev); without them
# this fails, naming what is missing.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"
export CCACHE_BASEDIR="${CCACHE_BASEDIR:-$root}"
build="${INTERSLICE_INSTRUMENTED_BUILD_DIR:-$root/build-instrumented}"
jobs="${JOBS:-$(nproc)}"

# clang with the libFuzzer and sanitizer runtimes.
probe="$(mktemp -d)"
trap 'rm -rf "$probe"' EXIT
printf 'extern "C" int LLVMFuzzerTestOneInput(const unsigned char*, unsigned long) { return 0; }\n' \
  >"$probe/probe.cc"
if ! command -v clang++ >/dev/null; then
  echo "build-instrumented: FAILED: clang++ is not installed (the Debian packages clang and" \
       "libclang-rt-14-dev; scripts/install-deps.sh installs them)" >&2
  exit 1
fi
if ! clang++ -fsanitize=fuzzer,address,undefined "$probe/probe.cc" -o "$probe/probe" 2>"$probe/err"; then
  cat "$probe/err" >&2
  echo "build-instrumented: FAILED: clang++ cannot link -fsanitize=fuzzer,address,undefined" \
       "(the Debian package libclang-rt-14-dev; scripts/install-deps.sh installs it)" >&2
  exit 1
fi

# Benchmarks and evaluation tools are not tested: not built here. Only the
# test binaries with a test labelled `sanitized` (INTERSLICE_TEST_SELECTION);
# the server's fault hook for the crash tests (INTERSLICE_FAULT_INJECTION).
CC=clang CXX=clang++ cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DINTERSLICE_BUILD_FUZZERS=ON -DINTERSLICE_SANITIZE=address,undefined \
  -DINTERSLICE_BUILD_TESTS=ON -DINTERSLICE_BUILD_BENCHMARKS=OFF \
  -DINTERSLICE_BUILD_TOOLS=OFF -DINTERSLICE_TEST_SELECTION=sanitized \
  -DINTERSLICE_FAULT_INJECTION=ON -DINTERSLICE_TEST_CODE_OPTIMIZATION=-O0 >/dev/null
targets=()
(($#)) && targets=(--target "$@")
cmake --build "$build" -j"$jobs" "${targets[@]}"
