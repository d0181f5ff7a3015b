#!/usr/bin/env bash
# Installs Debian's chromium + chromedriver for the viewer's browser test (tests/test_viewer.py)
# when they are missing. Idempotent and quiet; needs root for apt-get (CI runs as root).
# Without root or apt it only says why and exits 0: the browser test then skips with a reason.
set -euo pipefail
if [ -x /usr/bin/chromium ] && [ -x /usr/bin/chromedriver ]; then
    exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "install-browser: no apt-get here; install chromium and chromedriver yourself" >&2
    exit 0
fi
if [ "$(id -u)" -ne 0 ]; then
    echo "install-browser: not root; run 'sudo apt-get install chromium chromium-driver'" >&2
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
log=$(mktemp)
if apt-get update -qq >"$log" 2>&1 \
    && apt-get install -y -qq --no-install-recommends chromium chromium-driver fonts-liberation >>"$log" 2>&1; then
    echo "install-browser: $(/usr/bin/chromium --version 2>/dev/null | head -n1)"
else
    echo "install-browser: apt-get failed (the browser test will skip):" >&2
    tail -n 20 "$log" >&2
fi
rm -f "$log"
