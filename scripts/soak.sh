#!/usr/bin/env bash
# Soak run of the KD-tree stress properties (tests/test_kdtree_stress.py): every hypothesis
# property, default-tier and slow, draws at least KDTRACE_SOAK_EXAMPLES examples (default
# 10,000), with hypothesis's statistics and the durations printed at the end. Extra
# arguments go to pytest, e.g. `bash scripts/soak.sh -k split_plane` for the split-plane
# properties only. Hours on 2 cores for the whole file; run it on demand, not in CI.
set -euo pipefail
cd "$(dirname "$0")/.."
export KDTRACE_SOAK_EXAMPLES="${KDTRACE_SOAK_EXAMPLES:-10000}"
exec .venv/bin/python -m pytest tests/test_kdtree_stress.py -m "slow or not slow" -p no:cacheprovider \
    -q --durations=0 --hypothesis-show-statistics "$@"
