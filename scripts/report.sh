#!/usr/bin/env bash
# Regenerates the whole measurement report: quality (docs/eval, needs
# ../shared/data; skipped with a message when it is absent) and speed
# (docs/speed). About 15 minutes on 2 cores; run on an otherwise idle machine.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$repo/scripts/install-deps.sh" --eval
bash "$repo/scripts/eval.sh"
bash "$repo/scripts/bench.sh"
echo "report.sh: quality report in docs/eval/, speed report in docs/speed/"
