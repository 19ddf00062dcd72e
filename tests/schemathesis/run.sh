#!/usr/bin/env bash
# Schemathesis (from PyPI) against the real server and the OpenAPI document it serves, once
# without and once with an API token, every check, a bounded number of examples per operation.
# Any server error or check failure fails the run. Before each run, seed.py creates one real
# resource of every kind (datasets, a trained job and its policy, an evaluation, an experiment,
# a model with an alias) and half of the generated path parameters name them.
#
#   tests/schemathesis/run.sh [path/to/safedice]     (default: target/debug/safedice)
#
# Installs schemathesis into .venv-schemathesis/ on first use. SCHEMATHESIS_EXAMPLES (default
# 50) sets the examples per operation of the run without a token; the run with one, which
# exercises the same handlers behind the token check, takes a fifth of them
# (SCHEMATHESIS_TOKEN_EXAMPLES to change).
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN="${1:-target/debug/safedice}"
EXAMPLES="${SCHEMATHESIS_EXAMPLES:-50}"
TOKEN_EXAMPLES="${SCHEMATHESIS_TOKEN_EXAMPLES:-$(( (EXAMPLES + 4) / 5 ))}"
VENV=.venv-schemathesis
SCHEMATHESIS_VERSION=4.32.5

if [ ! -x "$VENV/bin/schemathesis" ]; then
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install --quiet "schemathesis==$SCHEMATHESIS_VERSION"
fi

DATA_DIR="$(mktemp -d)"
SERVER_PID=
cleanup() {
  if [ -n "$SERVER_PID" ]; then kill "$SERVER_PID" 2>/dev/null || true; wait "$SERVER_PID" 2>/dev/null || true; fi
  rm -rf "$DATA_DIR"
}
trap cleanup EXIT

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

# start_server NAME [extra serve flags...]: a fresh data directory per run.
start_server() {
  local name="$1"; shift
  PORT="$(free_port)"
  mkdir -p "$DATA_DIR/$name"
  RUST_LOG=warn "$BIN" serve --bind "127.0.0.1:$PORT" --data-dir "$DATA_DIR/$name" "$@" \
    >"$DATA_DIR/$name.log" 2>&1 &
  SERVER_PID=$!
  for _ in $(seq 1 300); do
    curl -fsS "http://127.0.0.1:$PORT/healthz" >/dev/null 2>&1 && return 0
    sleep 0.1
  done
  echo "the server did not come up:"; cat "$DATA_DIR/$name.log"; exit 1
}

stop_server() {
  kill "$SERVER_PID"; wait "$SERVER_PID" || true; SERVER_PID=
}

"$BIN" datagen --env six-rooms --preferred 10 --non-preferred 10 --labeled 4 \
  --out "$DATA_DIR/demos" >/dev/null

# run_schemathesis NAME EXAMPLES TOKEN [schemathesis flags...]   (TOKEN empty: none)
run_schemathesis() {
  local name="$1" examples="$2" token="${3:-}"; shift 3
  echo "== schemathesis: $name (max $examples examples per operation)"
  "$VENV/bin/python" tests/schemathesis/seed.py "http://127.0.0.1:$PORT" "$DATA_DIR/demos" \
    tests/schemathesis/schemathesis.toml "$DATA_DIR/$name.toml" $token || {
      echo "seeding ($name) failed; the server's log:"; tail -50 "$DATA_DIR/$name.log"; exit 1; }
  "$VENV/bin/schemathesis" --config-file "$DATA_DIR/$name.toml" \
    run "http://127.0.0.1:$PORT/v1/openapi.json" \
    --checks all --max-examples "$examples" --seed 1 --workers 1 \
    --generation-database none --no-color "$@" || {
      echo "schemathesis ($name) failed; the server's log:"; tail -50 "$DATA_DIR/$name.log"; exit 1; }
}

start_server open
run_schemathesis open "$EXAMPLES" ""
stop_server

TOKEN="schemathesis-$(date +%s%N)"
start_server token --api-token "$TOKEN"
run_schemathesis token "$TOKEN_EXAMPLES" "$TOKEN" -H "Authorization: Bearer $TOKEN"
stop_server
echo "schemathesis: both runs passed"
