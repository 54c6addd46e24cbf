#!/usr/bin/env bash
# node-opcua for the OPC UA tests (tests/test_opcua.py, tests/test_opcua_model.py): a second,
# independent OPC UA client, and the OPC Foundation's base NodeSet the type check reads. Installed
# from the npm registry into tests/node/node_modules exactly as package-lock.json says, with the
# machine's Node.js (Debian's nodejs and npm when there is none); quick and silent when done.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
    echo "ensure_node_opcua: no node/npm found; installing Debian's nodejs and npm" >&2
    bash "$here/apt_install.sh" ensure_node_opcua nodejs npm
fi
cd "$here/node"
stamp=node_modules/.lathed-installed
if [ -f "$stamp" ] && [ "$stamp" -nt package-lock.json ]; then
    exit 0
fi
npm ci --no-audit --no-fund --loglevel=error --engine-strict=false
touch "$stamp"
