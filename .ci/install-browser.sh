#!/usr/bin/env bash
# Installs Debian's chromium + chromedriver for the viewer's browser tests (tests/test_viewer*.py)
# when they are missing. Idempotent and quiet when they are there.
# Fails (exit 1, with the reason) when no browser can be had: the browser tests never skip in
# CI, so a machine without a browser must stop here, loudly, not pass with the view untested.
set -euo pipefail
have() { [ -x /usr/bin/chromium ] && [ -x /usr/bin/chromedriver ]; }
if have; then
    exit 0
fi
fail() {
    echo "install-browser: FAILED: $*" >&2
    echo "install-browser: the viewer's browser tests need /usr/bin/chromium and /usr/bin/chromedriver" >&2
    exit 1
}
command -v apt-get >/dev/null 2>&1 || fail "no apt-get here; install chromium and chromedriver yourself"
[ "$(id -u)" -eq 0 ] || fail "not root; run 'sudo apt-get install chromium chromium-driver'"
export DEBIAN_FRONTEND=noninteractive
log=$(mktemp)
trap 'rm -f "$log"' EXIT
if ! { apt-get update -qq >"$log" 2>&1 \
        && apt-get install -y -qq --no-install-recommends chromium chromium-driver fonts-liberation >>"$log" 2>&1; }; then
    tail -n 20 "$log" >&2
    fail "apt-get could not install chromium chromium-driver"
fi
have || fail "apt-get ran but /usr/bin/chromium or /usr/bin/chromedriver is still missing"
echo "install-browser: $(/usr/bin/chromium --version 2>/dev/null | head -n1)"
