#!/usr/bin/env bash
# Soak run of the KD-tree stress properties: every hypothesis property of
# tests/test_kdtree_stress.py with KDTRACE_SOAK_EXAMPLES examples (default 10,000), one at a time,
# resumable (scripts/soak.py; records in results/soak/). Hours on 2 cores; on demand, not in CI.
set -euo pipefail
cd "$(dirname "$0")/.."
exec .venv/bin/python scripts/soak.py "$@"
