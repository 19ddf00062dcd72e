"""What the client tests share: the server they talk to and policies trained through its API.

Every test script is run as `SCRIPT HOST:PORT WORKDIR BINARY` by run.sh: the server's address,
a directory where `safedice datagen` wrote WORKDIR/<env>/{unlabeled,non_preferred}.npz, and the
safedice binary.
"""

import json
import sys
import time
import urllib.request
import uuid

import numpy as np

ADDRESS, WORKDIR = sys.argv[1], sys.argv[2]
BASE = f"http://{ADDRESS}"


def wait_until(ready, what, seconds=60):
    """Polls `ready()` until it answers true (an exception: not yet) for at most `seconds`."""
    deadline = time.time() + seconds
    while True:
        try:
            if ready():
                return
        except Exception:  # still starting
            pass
        assert time.time() < deadline, f"{what} did not come up"
        time.sleep(0.1)


def call(method, path, body=None, content_type="application/json"):
    request = urllib.request.Request(BASE + path, data=body, method=method)
    if body is not None:
        request.add_header("Content-Type", content_type)
    with urllib.request.urlopen(request, timeout=60) as response:
        return json.loads(response.read())


def upload(path):
    boundary = uuid.uuid4().hex
    with open(path, "rb") as f:
        content = f.read()
    body = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; '
        f'filename="{path.rsplit("/", 1)[-1]}"\r\nContent-Type: application/octet-stream\r\n\r\n'
    ).encode() + content + f"\r\n--{boundary}--\r\n".encode()
    return call("POST", "/v1/datasets", body, f"multipart/form-data; boundary={boundary}")["id"]


_DATASETS = {}


def datasets(env):
    """The environment's two datasets, uploaded once per process."""
    if env not in _DATASETS:
        _DATASETS[env] = (
            upload(f"{WORKDIR}/{env}/unlabeled.npz"),
            upload(f"{WORKDIR}/{env}/non_preferred.npz"),
        )
    return _DATASETS[env]


def train(env, algorithm, seed=None):
    """Trains a small policy with `algorithm` on `env`'s data (with `seed`, if given); its id."""
    unlabeled, non_preferred = datasets(env)
    job = {
        "algorithm": algorithm,
        "unlabeled_dataset": unlabeled,
        "non_preferred_dataset": non_preferred,
        "config": {"iterations": 300, "hidden_sizes": [32, 32], "batch_size": 64},
    }
    if seed is not None:
        job["config"]["seed"] = seed
    job_id = call("POST", "/v1/jobs", json.dumps(job).encode())["id"]
    deadline = time.time() + 300
    while True:
        job = call("GET", f"/v1/jobs/{job_id}")
        if job["status"] == "succeeded":
            return job["policy_id"]
        assert job["status"] in ("queued", "running"), job
        assert time.time() < deadline, f"job {job_id} did not finish: {job}"
        time.sleep(0.2)


def get_bytes(path):
    with urllib.request.urlopen(BASE + path, timeout=60) as response:
        return response.read()


def act(policy, observations):
    body = json.dumps({"observations": observations.tolist()}).encode()
    return np.array(call("POST", f"/v1/policies/{policy}/act", body)["actions"])


def safety_scores(policy, observations):
    """/act's safety scores of its deterministic actions: (log-ratios, out-of-support)."""
    body = json.dumps({"observations": observations.tolist(), "safety_score": True}).encode()
    safety = call("POST", f"/v1/policies/{policy}/act", body)["safety"]
    return (np.array(safety["non_preferred_log_ratio"], dtype=np.float32),
            np.array(safety["out_of_support"], dtype=np.float32))
