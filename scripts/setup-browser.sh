#!/bin/sh
# Install Debian's chromium so the verdict page's browser test (tests/test_verdict_page.py) runs.
#
# The test loads verdict.html in headless Chromium and is skipped, saying so, without a
# browser. Idempotent: does nothing when chromium (or Chrome) is already on PATH. Installs with
# apt-get only when run as root with apt-get available; otherwise prints what to do. Never
# fails the caller (always exits 0).
#
# Usage: sh scripts/setup-browser.sh

find_browser() {
    for name in chromium chromium-browser google-chrome google-chrome-stable chrome; do
        if command -v "$name" >/dev/null 2>&1; then
            command -v "$name"
            return 0
        fi
    done
    return 1
}

if browser=$(find_browser); then
    echo "setup-browser: browser already installed: $browser"
    exit 0
fi

if [ "$(id -u)" != "0" ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "setup-browser: no chromium or chrome found and cannot install one here (need root and apt-get)."
    echo "setup-browser: run as root: apt-get update && apt-get install -y chromium"
    echo "setup-browser: until then the browser test of the verdict page is skipped."
    exit 0
fi

echo "setup-browser: installing chromium with apt-get"
if ! { apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium; }; then
    echo "setup-browser: apt-get failed; the browser test of the verdict page will be skipped."
    exit 0
fi

if browser=$(find_browser); then
    echo "setup-browser: installed: $browser"
else
    echo "setup-browser: chromium installed but not on PATH; the browser test looks for /usr/bin/chromium too"
fi
exit 0
