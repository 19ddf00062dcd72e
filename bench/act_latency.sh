#!/usr/bin/env bash
# Single-observation inference latency on loopback: `wrk -t2 -c32` (Debian's `wrk`) against a
# release build, on a BC policy of the paper's size (256-256) trained on point-goal data:
# POST /v1/policies/{id}/act, and /v2/models/{id}/infer in JSON and in binary tensor data; the
# same policy by model name (POST /v1/models/pilot@production/act, /v2/models/pilot@production).
# wrk shares the machine's cores with the server. Then full batches: 16,384 observations a
# request (the largest the routes take) to /act and /v2 JSON, one request at a time, where
# reading the JSON body is a large part of the time.
#
#   cargo build --release --bin safedice && bench/act_latency.sh [target/release/safedice] [seconds]
set -euo pipefail
cd "$(dirname "$0")/.."
BIN="${1:-target/release/safedice}"
SECONDS_PER_RUN="${2:-10}"
command -v wrk >/dev/null || { echo "needs wrk (apt-get install wrk)"; exit 1; }
WORK="$(mktemp -d)"
SERVER_PID=
cleanup() {
  if [ -n "$SERVER_PID" ]; then kill "$SERVER_PID" 2>/dev/null || true; wait "$SERVER_PID" 2>/dev/null || true; fi
  rm -rf "$WORK"
}
trap cleanup EXIT
PORT="$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')"
API="http://127.0.0.1:$PORT"
RUST_LOG=${RUST_LOG:-warn} "$BIN" serve --bind "127.0.0.1:$PORT" --data-dir "$WORK/data" >"$WORK/server.log" 2>&1 &
SERVER_PID=$!
"$BIN" datagen --env point-goal --preferred 50 --non-preferred 50 --labeled 10 --out "$WORK/d" >/dev/null
until curl -sf "$API/readyz" >/dev/null; do sleep 0.1; done
id_of() { python3 -c 'import json,sys; print(json.load(sys.stdin)[sys.argv[1]])' "$1"; }
U=$(curl -s -F file=@"$WORK/d/unlabeled.npz" "$API/v1/datasets" | id_of id)
JOB=$(curl -s -H 'content-type: application/json' "$API/v1/jobs" -d "{\"algorithm\":\"bc\",
  \"unlabeled_dataset\":\"$U\",\"config\":{\"iterations\":200,\"hidden_sizes\":[256,256]}}" | id_of id)
until [ "$(curl -s "$API/v1/jobs/$JOB" | id_of status)" = succeeded ]; do sleep 0.2; done
POLICY=$(curl -s "$API/v1/jobs/$JOB" | id_of policy_id)
OBS_DIM=$(curl -s "$API/v1/policies/$POLICY" | id_of obs_dim)
curl -sf -H 'content-type: application/json' "$API/v1/models" -d '{"name": "pilot"}' >/dev/null
curl -sf -H 'content-type: application/json' "$API/v1/models/pilot/versions" \
  -d "{\"policy_id\": \"$POLICY\", \"alias\": \"production\"}" >/dev/null

python3 - "$WORK" "$OBS_DIM" <<'PY'
import json, struct, sys
work, dim = sys.argv[1], int(sys.argv[2])
obs = [0.1 * (i % 7) for i in range(dim)]
def lua(name, body, headers):
    escaped = "".join("\\%d" % b for b in body)
    lines = ['wrk.method = "POST"', 'wrk.body = "%s"' % escaped]
    lines += ['wrk.headers["%s"] = "%s"' % kv for kv in headers.items()]
    open(f"{work}/{name}.lua", "w").write("\n".join(lines) + "\n")
lua("act", json.dumps({"observations": [obs]}).encode(), {"Content-Type": "application/json"})
v2 = {"inputs": [{"name": "observations", "datatype": "FP32", "shape": [1, dim], "data": obs}]}
lua("v2_json", json.dumps(v2).encode(), {"Content-Type": "application/json"})
header = json.dumps({"inputs": [{"name": "observations", "datatype": "FP32", "shape": [1, dim],
                                 "parameters": {"binary_data_size": 4 * dim}}],
                     "outputs": [{"name": "actions", "parameters": {"binary_data": True}}]}).encode()
lua("v2_binary", header + struct.pack(f"<{dim}f", *obs),
    {"Inference-Header-Content-Length": str(len(header)), "Content-Type": "application/octet-stream"})
PY

echo "| route | req/s | p50 | p99 | non-2xx |"
echo "|---|---|---|---|---|"
for run in act:/v1/policies/$POLICY/act v2_json:/v2/models/$POLICY/infer v2_binary:/v2/models/$POLICY/infer \
    act:/v1/models/pilot@production/act v2_json:/v2/models/pilot@production/infer; do
  name="${run%%:*}"; path="${run#*:}"
  curl -s -o /dev/null -X POST "$API$path" >/dev/null || true   # warm the policy cache
  out="$(wrk -t2 -c32 -d"${SECONDS_PER_RUN}s" --latency -s "$WORK/$name.lua" "$API$path")"
  rps=$(echo "$out" | awk '/Requests\/sec/ {print $2}')
  p50=$(echo "$out" | awk '$1 == "50%" {print $2}')
  p99=$(echo "$out" | awk '$1 == "99%" {print $2}')
  errors=$(echo "$out" | awk '/Non-2xx/ {print $NF}')
  echo "| $name ${path%/*} | $rps | $p50 | $p99 | ${errors:-0} |"
done

echo
echo "| route, 16,384 observations a request | median ms | min ms | requests |"
echo "|---|---|---|---|"
python3 - "$API" "$POLICY" "$OBS_DIM" <<'PY'
import http.client, json, statistics, sys, time, urllib.parse
api, policy, dim = sys.argv[1], sys.argv[2], int(sys.argv[3])
rows = [[0.01 * ((i * 7 + j) % 97) for j in range(dim)] for i in range(16384)]
bodies = {
    "act": (f"/v1/policies/{policy}/act", json.dumps({"observations": rows})),
    "v2_json": (f"/v2/models/{policy}/infer", json.dumps({"inputs": [
        {"name": "observations", "datatype": "FP32", "shape": [len(rows), dim], "data": rows}]})),
}
url = urllib.parse.urlparse(api)
conn = http.client.HTTPConnection(url.hostname, url.port)
for name, (path, body) in bodies.items():
    times = []
    for i in range(22):
        start = time.perf_counter()
        conn.request("POST", path, body, {"Content-Type": "application/json"})
        response = conn.getresponse()
        response.read()
        assert response.status == 200, (name, response.status)
        if i >= 2:  # two to warm up
            times.append(1000 * (time.perf_counter() - start))
    print(f"| {name} | {statistics.median(times):.1f} | {min(times):.1f} | {len(times)} |")
PY
