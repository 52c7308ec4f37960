#!/usr/bin/env bash
# Set up kdtrace on a fresh machine: a virtualenv in .venv with every dependency
# (torch pinned to the local CPU wheel), the project installed in editable mode, and,
# when possible, the LLVM that Mitsuba's fast variant needs and a browser for the verdict
# page's test. Idempotent.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e '.[test]'
if [ -x scripts/setup-llvm.sh ]; then
    scripts/setup-llvm.sh || echo "setup: no LLVM 19 for Mitsuba's llvm_ad_rgb; it will fall back to scalar_rgb"
fi
if [ -x scripts/setup-browser.sh ]; then
    scripts/setup-browser.sh || echo "setup: no browser; the verdict page's browser test will be skipped"
fi
