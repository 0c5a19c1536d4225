#!/usr/bin/env bash
# Quick start, step 2: the whole test suite.
#   1. build (if needed) and run every ctest test (unit, end to end, viewer);
#   2. the deployment: the container images, the compose stack and the
#      phantom through it (scripts/test-deploy.sh; INTERSLICE_SKIP_DEPLOY=1
#      skips it, and it skips itself without a container runtime);
#   3. the same suite under AddressSanitizer + UndefinedBehaviorSanitizer
#      (scripts/test-sanitizers.sh, build-asan/);
#   4. each libFuzzer target for a bounded time (scripts/fuzz.sh, build-fuzz/;
#      INTERSLICE_FUZZ_SECONDS per target, default 30).
# INTERSLICE_QUICK=1 runs step 1 only (for a quick local check).
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"
# ccache keys on paths relative to the checkout, so clones share the cache.
export CCACHE_BASEDIR="$root"

bash scripts/install-deps.sh
start=$SECONDS
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build build -j"$(nproc)"
ctest --test-dir build --output-on-failure -j"$(nproc)"
echo "test.sh: main suite done after $((SECONDS - start)) s"
if [ "${INTERSLICE_QUICK:-0}" = "1" ]; then exit 0; fi

bash scripts/test-deploy.sh
echo "test.sh: deployment test done after $((SECONDS - start)) s"

bash scripts/test-sanitizers.sh
echo "test.sh: sanitizer suite done after $((SECONDS - start)) s"
bash scripts/fuzz.sh "${INTERSLICE_FUZZ_SECONDS:-30}"
echo "test.sh: fuzzing done after $((SECONDS - start)) s"
