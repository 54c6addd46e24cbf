#!/usr/bin/env bash
# Make sure a Mosquitto broker binary exists for the MQTT tests (tests/test_mqtt.py
# starts its own broker on a free loopback port with a temporary config; the
# package's system service is never used). Installs Debian's mosquitto package
# only when it is missing; quick and silent when it is there.
set -euo pipefail

have_broker() {
    [ -x /usr/sbin/mosquitto ] || command -v mosquitto >/dev/null 2>&1
}

if have_broker; then
    exit 0
fi

echo "ensure_mosquitto: no mosquitto broker found; installing the Debian mosquitto package" >&2
bash "$(dirname "$0")/apt_install.sh" ensure_mosquitto mosquitto
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
# The package's own service is not needed (the tests run their own); keep it from holding port 1883.
if command -v systemctl >/dev/null 2>&1 && [ -d /run/systemd/system ]; then
    $SUDO systemctl disable --now mosquitto 2>/dev/null || true
fi
have_broker || { echo "ensure_mosquitto: mosquitto installed but the broker binary still not found" >&2; exit 1; }
