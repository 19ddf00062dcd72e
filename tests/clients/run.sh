#!/usr/bin/env bash
# Third-party clients from PyPI, unmodified, against the real server, on policies trained
# through the API (every algorithm, a discrete and a continuous environment):
# - test_tritonclient.py: NVIDIA's tritonclient on the Open Inference Protocol routes, JSON and
#   binary tensor data;
# - test_tritonclient_grpc.py: tritonclient.grpc on the gRPC listener (--grpc-bind): unary,
#   raw and typed tensors, a 1,000-message stream, a canary split, the tokens;
# - test_onnxruntime.py: onnxruntime on the ONNX export (GET /v1/policies/{id}/export) and on
#   `safedice export` of the downloaded policy file;
# - clients/python: the Python client's own tests (pytest; its evaluation in a simulator runs in
#   gymnasium's CartPole-v1) and its walk-through.
# Every action is compared with /v1/policies/{id}/act; any mismatch or error fails the run.
#
#   tests/clients/run.sh [path/to/safedice]     (default: target/debug/safedice)
#
# Installs the clients into .venv-clients/ on first use.
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN="${1:-target/debug/safedice}"
VENV=.venv-clients

if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import tritonclient.http, tritonclient.grpc, onnxruntime, gymnasium, h5py' 2>/dev/null; then
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install --quiet "tritonclient[http,grpc]==2.73.0" "grpcio==1.85.3" "protobuf==6.33.6" "onnxruntime==1.23.2" "numpy==2.4.6" \
    "pytest==8.4.2" "gymnasium==1.2.2" "h5py==3.16.0"
fi
# The client as a user installs it, from this checkout, every run.
"$VENV/bin/pip" install --quiet --no-deps --force-reinstall ./clients/python

WORK="$(mktemp -d)"
SERVER_PID=
cleanup() {
  if [ -n "$SERVER_PID" ]; then kill "$SERVER_PID" 2>/dev/null || true; wait "$SERVER_PID" 2>/dev/null || true; fi
  rm -rf "$WORK"
}
trap cleanup EXIT

free_port() { "$VENV/bin/python" -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
PORT="$(free_port)"
GRPC_PORT="$(free_port)"
RUST_LOG=warn "$BIN" serve --bind "127.0.0.1:$PORT" --grpc-bind "127.0.0.1:$GRPC_PORT" \
  --data-dir "$WORK/data" >"$WORK/server.log" 2>&1 &
SERVER_PID=$!
for env in six-rooms point-goal; do
  "$BIN" datagen --env "$env" --preferred 30 --non-preferred 30 --labeled 10 --out "$WORK/$env" >/dev/null
done
fail() { echo "--- server log ---"; tail -50 "$WORK/server.log"; exit 1; }
for test in test_tritonclient.py test_tritonclient_grpc.py test_onnxruntime.py; do
  "$VENV/bin/python" "tests/clients/$test" "127.0.0.1:$PORT" "$WORK" "$BIN" "127.0.0.1:$GRPC_PORT" || fail
done
SAFEDICE_URL="http://127.0.0.1:$PORT" SAFEDICE_DATA="$WORK" \
  "$VENV/bin/python" -m pytest -q -p no:cacheprovider clients/python/tests || fail
"$BIN" datagen --env point-goal --preferred 200 --non-preferred 200 --labeled 20 \
  --out "$WORK/walkthrough/demo-data" >/dev/null
(cd "$WORK/walkthrough" && "$OLDPWD/$VENV/bin/python" "$OLDPWD/clients/python/walkthrough.py" \
  "http://127.0.0.1:$PORT" demo-data) || fail
