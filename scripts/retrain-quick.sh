#!/usr/bin/env bash
# Retrain the quick profile's committed networks (models/quick) on this machine, measure the quick
# report with them from scratch, record both baselines from that run, and commit weights and
# baselines together. CI never trains: it evaluates what this script committed.
set -euo pipefail
cd "$(dirname "$0")/.."
cache="${KDTRACE_CACHE:-.cache/kdtrace}"
if [ -d models/quick ]; then
    for stored in models/quick/*/; do rm -rf "$cache/models/$(basename "$stored")"; done
    git rm -rq --ignore-unmatch models/quick
    rm -rf models/quick
fi
.venv/bin/kdtrace report --profile quick --fresh
.venv/bin/kdtrace update-baseline --profile quick
git add models/quick reports/baseline
git commit -m "models/quick and the quick baselines: networks retrained on $(.venv/bin/python -c 'from kdtrace.provenance import cpu_kind; print(cpu_kind())')"
