#!/usr/bin/env bash
# Make sure a Chromium exists for the operator view's browser tests
# (tests/test_web.py drives /usr/bin/chromium through Playwright; Playwright's
# own browser download is never used). Installs Debian's chromium package only
# when it is missing; quick and silent when it is there.
set -euo pipefail

if [ -x /usr/bin/chromium ]; then
    exit 0
fi

echo "ensure_chromium: /usr/bin/chromium not found; installing the Debian chromium package" >&2
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1; then
        SUDO="sudo"
    else
        echo "ensure_chromium: not root and no sudo: install the 'chromium' package by hand" >&2
        exit 1
    fi
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends chromium
[ -x /usr/bin/chromium ] || { echo "ensure_chromium: chromium installed but /usr/bin/chromium missing" >&2; exit 1; }
