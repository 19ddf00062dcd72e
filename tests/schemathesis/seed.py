"""Seeds a running server with one real resource of every kind and writes a schemathesis
configuration that sends their ids (and names) in path parameters half of the time.

Without it, nearly every generated id names nothing, so each operation behind a path parameter
is only ever tested on its 404. With it, the same generated bodies, queries and headers reach a
dataset, a job, a policy, an evaluation, an experiment and a model that exist.

    python seed.py BASE_URL DATA_DIR BASE_CONFIG OUT_CONFIG [TOKEN]

DATA_DIR holds `unlabeled.npz` and `non_preferred.npz` (from `safedice datagen`).
"""

import json
import sys
import time

import requests

BASE, DATA, BASE_CONFIG, OUT = sys.argv[1:5]
TOKEN = sys.argv[5] if len(sys.argv) > 5 else None
HEADERS = {"Authorization": f"Bearer {TOKEN}"} if TOKEN else {}
# The share of generated cases that take a seeded value where the parameter admits one.
PROBABILITY = 0.5
TINY = {"iterations": 20, "hidden_sizes": [8], "batch_size": 16, "seed": 0}


def call(method, path, expected, **kwargs):
    response = requests.request(method, BASE + path, headers=HEADERS, timeout=60, **kwargs)
    if response.status_code != expected:
        sys.exit(f"seeding: {method} {path} answered {response.status_code}: {response.text}")
    return response.json() if response.content else None


def upload(role):
    with open(f"{DATA}/{role}.npz", "rb") as f:
        return call("POST", "/v1/datasets", 201, files={"file": f}, data={"role": role})["id"]


def wait_for(path, done):
    for _ in range(600):
        body = call("GET", path, 200)
        if done(body):
            return body
        time.sleep(0.1)
    sys.exit(f"seeding: {path} did not finish: {body}")


def job(unlabeled, non_preferred):
    created = call("POST", "/v1/jobs", 201, json={
        "algorithm": "safedice", "unlabeled_dataset": unlabeled,
        "non_preferred_dataset": non_preferred, "config": TINY, "name": "seeded"})
    finished = wait_for(f"/v1/jobs/{created['id']}", lambda j: j["status"] == "succeeded")
    return created["id"], finished["policy_id"]


def seed():
    unlabeled, non_preferred = upload("unlabeled"), upload("non_preferred")
    job_id, policy = job(unlabeled, non_preferred)
    evaluation = call("POST", f"/v1/policies/{policy}/evaluations", 201, json={
        "env": "seeded-sim", "returns": [1.0, 2.0], "costs": [0.0, 1.0],
        "reference": {"preferred_return": 2.0, "preferred_cost": 0.0,
                      "non_preferred_return": 2.0, "non_preferred_cost": 3.0}})["id"]
    experiment = call("POST", "/v1/experiments", 201, json={
        "name": "seeded", "unlabeled_dataset": unlabeled, "algorithms": ["bc"], "seed_count": 1,
        "config": {k: v for k, v in TINY.items() if k != "seed"}})["id"]
    wait_for(f"/v1/experiments/{experiment}", lambda e: e["progress"]["succeeded"] == 1)
    call("POST", "/v1/models", 201, json={"name": "seeded"})
    call("POST", "/v1/models/seeded/versions", 201, json={"policy_id": policy})
    call("PUT", "/v1/models/seeded/aliases/production", 200, json={"version": 1})
    return {
        "dataset": [unlabeled, non_preferred],
        "job": [job_id],
        "policy": [policy],
        "evaluation": [evaluation],
        "experiment": [experiment],
        # /v1 names a model; /v2 names a policy id, a model, or a model's alias.
        "model": ["seeded"],
        "served": [policy, "seeded", "seeded@production"],
        "alias": ["production"],
        "version": [1, "1"],
        "algorithm": ["safedice", "bc"],
    }


# Which dictionary each path parameter takes, by the path's prefix.
BINDINGS = [
    ("^/v1/datasets/", "path.id", "dataset"),
    ("^/v1/jobs/", "path.id", "job"),
    ("^/v1/policies/", "path.id", "policy"),
    ("^/v1/evaluations/", "path.id", "evaluation"),
    ("^/v1/experiments/", "path.id", "experiment"),
    ("^/v1/algorithms/", "path.name", "algorithm"),
    ("^/v1/models/", "path.name", "model"),
    ("^/v1/models/", "path.alias", "alias"),
    ("^/v1/models/", "path.version", "version"),
    ("^/v2/models/", "path.id", "served"),
    ("^/v2/models/", "path.name", "served"),
    ("^/v2/models/", "path.version", "version"),
    ("^/v2/repository/models/", "path.name", "served"),
]


def toml_value(value):
    return json.dumps(value)


def config(seeded):
    lines = [open(BASE_CONFIG).read(), "", "# Written by tests/schemathesis/seed.py."]
    for name, values in seeded.items():
        lines += [f"[dictionaries.{name}]", f"values = {toml_value(values)}", ""]
    by_path = {}
    for regex, parameter, dictionary in BINDINGS:
        by_path.setdefault(regex, []).append((parameter, dictionary))
    for regex, parameters in by_path.items():
        bound = ", ".join(
            f'"{p}" = {{ dictionary = "{d}", probability = {PROBABILITY} }}' for p, d in parameters)
        lines += ["[[operations]]", f"include-path-regex = {toml_value(regex)}",
                  f"parameters = {{ {bound} }}", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    seeded = seed()
    with open(OUT, "w") as f:
        f.write(config(seeded))
    print("seeded:", json.dumps(seeded))
