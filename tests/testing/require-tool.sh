#!/usr/bin/env bash
# Runs a script-level test only when the tools it needs are installed:
#   bash tests/testing/require-tool.sh TOOL... -- COMMAND [ARGS...]
# Each TOOL is looked up on PATH when the test runs (not when CMake
# configures, so a run with a tool removed shows what happens). When one is
# missing: in CI (CI=true) the test FAILS naming it (exit 1); elsewhere it is
# SKIPPED naming it (exit 77, which the tests registering this wrapper declare
# as ctest's SKIP_RETURN_CODE, so ctest lists it as "Skipped", never as
# passed). scripts/install-deps.sh installs every tool the suite needs.
set -euo pipefail
tools=()
while (($#)) && [[ $1 != -- ]]; do tools+=("$1"); shift; done
[[ ${1:-} == -- ]] || { echo "usage: $0 TOOL... -- COMMAND [ARGS...]" >&2; exit 2; }
shift
# An executable regular file on PATH (bash's `command -v` also accepts a
# file it cannot execute when there is no other).
installed() {
  local dir
  local IFS=:
  for dir in $PATH; do
    [[ -f ${dir:-.}/$1 && -x ${dir:-.}/$1 ]] && return 0
  done
  return 1
}
for tool in "${tools[@]}"; do
  if ! installed "$tool"; then
    if [[ ${CI:-} == true ]]; then
      echo "FAIL: $tool is not installed (not on PATH); this test needs it" \
           "(scripts/install-deps.sh installs it) [CI=true: a missing tool is a failure]"
      exit 1
    fi
    echo "SKIPPED: $tool is not installed (not on PATH); scripts/install-deps.sh installs it"
    exit 77
  fi
done
exec "$@"
