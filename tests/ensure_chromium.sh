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
bash "$(dirname "$0")/apt_install.sh" ensure_chromium chromium
[ -x /usr/bin/chromium ] || { echo "ensure_chromium: chromium installed but /usr/bin/chromium missing" >&2; exit 1; }
