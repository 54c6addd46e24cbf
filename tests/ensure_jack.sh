#!/usr/bin/env bash
# Make sure a JACK server (jackd2, run with its dummy backend: no sound card needed) and
# PortAudio exist for the audio tests (tests/jack_fixtures.py starts its own server under a
# private server name; no system service is used). Installs the Debian packages only when
# missing; quick and silent when they are there.
set -euo pipefail

have_jack() {
    command -v jackd >/dev/null 2>&1 || [ -x /usr/bin/jackd ] || return 1
    # read whole, then searched: `ldconfig -p | grep -q` under pipefail fails whenever grep
    # matches and exits before ldconfig has written everything (SIGPIPE), found or not
    local libs
    libs=$(ldconfig -p 2>/dev/null) || return 1
    grep -q 'libportaudio\.so\.2' <<<"$libs" && grep -q 'libjack\.so\.0' <<<"$libs"
}

if have_jack; then
    exit 0
fi

echo "ensure_jack: no jackd or PortAudio found; installing the Debian jackd2 and libportaudio2 packages" >&2
# jackd2 asks (debconf) whether to enable real-time priority: the noninteractive answer is no,
# which the dummy backend does not need
bash "$(dirname "$0")/apt_install.sh" ensure_jack jackd2 libjack-jackd2-0 libportaudio2
have_jack || { echo "ensure_jack: jackd2 and libportaudio2 installed but jackd or a library still not found" >&2; exit 1; }
