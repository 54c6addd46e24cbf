#!/usr/bin/env bash
# Make sure PostgreSQL server binaries exist for the test suite's throw-away
# server (tests/pg_fixtures.py). Installs the Debian package only when none
# is found; quick and silent when the binaries are already there.
set -euo pipefail

have_server() {
    [ -n "${LATHED_PG_BINDIR:-}" ] && [ -x "${LATHED_PG_BINDIR}/initdb" ] && return 0
    compgen -G "/usr/lib/postgresql/*/bin/initdb" >/dev/null && return 0
    command -v initdb >/dev/null 2>&1 && command -v pg_ctl >/dev/null 2>&1
}

if have_server; then
    exit 0
fi

echo "ensure_postgres: no PostgreSQL server binaries found; installing the Debian postgresql package" >&2
bash "$(dirname "$0")/apt_install.sh" ensure_postgres postgresql
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
# The package's own cluster is not needed (the tests run their own); keep it from holding port 5432.
if command -v pg_lsclusters >/dev/null 2>&1; then
    pg_lsclusters --no-header 2>/dev/null | while read -r ver name _; do
        $SUDO pg_ctlcluster "$ver" "$name" stop 2>/dev/null || true
    done
fi
have_server || { echo "ensure_postgres: postgresql installed but initdb still not found" >&2; exit 1; }
