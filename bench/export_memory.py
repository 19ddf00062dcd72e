#!/usr/bin/env python3
"""Memory of concurrent ONNX exports of one large policy (issue 41, item 6).

Trains a BC policy of 3 x 4096 hidden units (~134 MB of weights) through the API, restarts the
server so its peak resident memory (VmHWM) starts from a fresh process, then downloads
`/v1/policies/{id}/export` COUNT times at once and prints the server's resident memory before,
its peak during the exports, and after.

    python3 bench/export_memory.py target/release/safedice [COUNT]   (default COUNT: 4)
"""
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request

BIN = sys.argv[1] if len(sys.argv) > 1 else "target/release/safedice"
COUNT = int(sys.argv[2]) if len(sys.argv) > 2 else 4
MIB = 1 << 20


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def call(api, method, path, body=None, headers=None):
    data = json.dumps(body).encode() if isinstance(body, dict) else body
    request = urllib.request.Request(api + path, data=data, method=method, headers=headers or {})
    if isinstance(body, dict):
        request.add_header("content-type", "application/json")
    try:
        with urllib.request.urlopen(request, timeout=600) as response:
            return response.read()
    except urllib.error.HTTPError as e:
        raise SystemExit(f"{method} {path}: {e.code} {e.read().decode()}") from None


def start(data_dir):
    port = free_port()
    server = subprocess.Popen(
        [BIN, "serve", "--data-dir", data_dir, "--bind", f"127.0.0.1:{port}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    api = f"http://127.0.0.1:{port}"
    for _ in range(600):
        try:
            call(api, "GET", "/readyz")
            return server, api
        except OSError:
            time.sleep(0.1)
    raise SystemExit("the server did not become ready")


def status_kib(pid, field):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise KeyError(field)


def upload(api):
    lines = []
    for episode in range(4):
        for t in range(50):
            x = [episode * 0.1 + t * 0.01, 0.5 - t * 0.01]
            lines.append(json.dumps({"episode": episode, "obs": x, "action": [0.1 * (t % 5) - 0.2],
                                     "reward": 1.0, "cost": 0.0, "terminal": t == 49}))
    boundary = "exportmemory"
    body = (f"--{boundary}\r\ncontent-disposition: form-data; name=\"file\"; filename=\"d.jsonl\"\r\n\r\n"
            + "\n".join(lines) + f"\r\n--{boundary}--\r\n").encode()
    reply = call(api, "POST", "/v1/datasets", body,
                 {"content-type": f"multipart/form-data; boundary={boundary}"})
    return json.loads(reply)["id"]


def train(api, dataset):
    job = json.loads(call(api, "POST", "/v1/jobs", {
        "algorithm": "bc", "unlabeled_dataset": dataset,
        "config": {"hidden_sizes": [4096, 4096, 4096], "iterations": 2, "batch_size": 8, "seed": 0}}))
    while True:
        job = json.loads(call(api, "GET", f"/v1/jobs/{job['id']}"))
        if job["status"] not in ("queued", "running"):
            break
        time.sleep(0.5)
    if job["status"] != "succeeded":
        raise SystemExit(f"training ended {job['status']}: {job.get('error')}")
    return job["policy_id"]


def main():
    with tempfile.TemporaryDirectory() as data_dir:
        server, api = start(data_dir)
        policy = train(api, upload(api))
        server.terminate()
        server.wait()
        server, api = start(data_dir)
        try:
            weights = len(call(api, "GET", f"/v1/policies/{policy}/weights"))
            before = status_kib(server.pid, "VmRSS")
            sizes, errors = [], []

            def export():
                try:
                    sizes.append(len(call(api, "GET", f"/v1/policies/{policy}/export")))
                except Exception as e:  # noqa: BLE001 - reported below
                    errors.append(str(e))

            threads = [threading.Thread(target=export) for _ in range(COUNT)]
            started = time.monotonic()
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
            took = time.monotonic() - started
            peak = status_kib(server.pid, "VmHWM")
            time.sleep(1.0)
            after = status_kib(server.pid, "VmRSS")
        finally:
            server.terminate()
            server.wait()
    print(f"policy file {weights / MIB:.0f} MiB; {COUNT} concurrent exports of "
          f"{(sizes[0] if sizes else 0) / MIB:.0f} MiB in {took:.1f} s ({len(errors)} errors)")
    print(f"server resident memory: {before / 1024:.0f} MiB before, peak {peak / 1024:.0f} MiB "
          f"(+{(peak - before) / 1024:.0f} MiB, {(peak - before) * 1024 / max(weights, 1) / COUNT:.2f} "
          f"policy copies per export), {after / 1024:.0f} MiB 1 s after")
    for error in errors:
        print("error:", error)


if __name__ == "__main__":
    main()
