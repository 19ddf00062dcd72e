#!/usr/bin/env bash
# NVIDIA's tritonclient (PyPI, unmodified) against the real server's Open Inference Protocol
# routes: JSON and binary tensor data, on a discrete and a continuous policy trained through the
# API; every action compared with /v1/policies/{id}/act. Any mismatch or error fails the run.
#
#   tests/oip/run.sh [path/to/safedice]     (default: target/debug/safedice)
#
# Installs tritonclient into .venv-oip/ on first use.
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN="${1:-target/debug/safedice}"
VENV=.venv-oip

if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import tritonclient.http' 2>/dev/null; then
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install --quiet "tritonclient[http]==2.73.0" "numpy==2.4.6"
fi

WORK="$(mktemp -d)"
SERVER_PID=
cleanup() {
  if [ -n "$SERVER_PID" ]; then kill "$SERVER_PID" 2>/dev/null || true; wait "$SERVER_PID" 2>/dev/null || true; fi
  rm -rf "$WORK"
}
trap cleanup EXIT

PORT="$("$VENV/bin/python" -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')"
RUST_LOG=warn "$BIN" serve --bind "127.0.0.1:$PORT" --data-dir "$WORK/data" >"$WORK/server.log" 2>&1 &
SERVER_PID=$!
for env in six-rooms point-goal; do
  "$BIN" datagen --env "$env" --preferred 30 --non-preferred 30 --labeled 10 --out "$WORK/$env" >/dev/null
done
if ! "$VENV/bin/python" tests/oip/test_tritonclient.py "127.0.0.1:$PORT" "$WORK"; then
  echo "--- server log ---"; tail -50 "$WORK/server.log"; exit 1
fi
