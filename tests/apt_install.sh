#!/usr/bin/env bash
# Install Debian packages for the test set-up (ensure_postgres.sh, ensure_chromium.sh, ensure_mosquitto.sh):
# as root, or through sudo; one clear line when neither is possible.
# Usage: apt_install.sh WHO PACKAGE...   (WHO names the caller in messages)
set -euo pipefail
who=$1; shift
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1; then
        SUDO="sudo"
    else
        echo "$who: not root and no sudo: install the package(s) $* by hand" >&2
        exit 1
    fi
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends "$@"
