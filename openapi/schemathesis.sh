#!/bin/sh
# Checks that openapi/openapi.yaml says exactly what the server does: schemathesis (PyPI, in a
# virtual environment outside the repository) with every check, against a running build served
# on 127.0.0.1 with an admin key and a throw-away data folder. Bounded by MAX_SECONDS.
# openapi/schemathesis.toml says which statuses answer a request that is valid by the document.
# usage: openapi/schemathesis.sh BINARY [MAX_SECONDS] [SCHEMATHESIS]
#   e.g. python3 -m venv /tmp/st && /tmp/st/bin/pip install schemathesis
#        openapi/schemathesis.sh target/debug/seasonloc 150 /tmp/st/bin/st
# With SEASONLOC_DATABASE_URL set, the server runs on that PostgreSQL database instead of the
# embedded store (use a throw-away database: the run creates maps and trips in it).
set -eu
BIN=$1; T=${2:-150}; ST=${3:-st}
CONFIG=$(cd "$(dirname "$0")" && pwd)/schemathesis.toml
D=$(mktemp -d)
trap 'kill $PID 2>/dev/null || true; rm -rf "$D"' EXIT
KEY=schemathesis-admin-key-$(od -An -N8 -tx1 /dev/urandom | tr -d ' \n')
SHA=$(printf %s "$KEY" | sha256sum | cut -d' ' -f1)
printf '{"keys": [{"name": "st", "role": "admin", "sha256": "%s"}]}' "$SHA" > "$D/keys.json"
PORT=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
set -- --addr "127.0.0.1:$PORT" --data-dir "$D/data" --api-keys "$D/keys.json" --max-requests-per-key 1000
[ -n "${SEASONLOC_DATABASE_URL:-}" ] && set -- "$@" --database-url "$SEASONLOC_DATABASE_URL"
"$BIN" serve "$@" > "$D/server.log" 2>&1 &
PID=$!
for _ in $(seq 100); do
  python3 -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:$PORT/readyz', timeout=1)" 2>/dev/null && break
  sleep 0.1
done
cd "$D"
"$ST" --config-file "$CONFIG" run "http://127.0.0.1:$PORT/openapi.json" --checks all -H "Authorization: Bearer $KEY" \
  --max-time "$T" --workers 1 --request-timeout 30 --suppress-health-check all
