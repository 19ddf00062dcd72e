"""onnxruntime (PyPI, unmodified) on the ONNX export of policies of every algorithm, on a discrete
and a continuous environment.

Usage: test_onnxruntime.py HOST:PORT WORKDIR BINARY (see common.py). For each policy: the model
from GET /v1/policies/{id}/export?format=onnx, and the one `safedice export` makes from the
downloaded policy file, run by onnxruntime on random observations, must give /act's
deterministic actions (discrete: equal; continuous: within 1e-5). Exits non-zero otherwise.
"""

import subprocess
import sys

import numpy as np
import onnxruntime

from common import act, get_bytes, train, WORKDIR

BINARY = sys.argv[3]
ALGORITHMS = ("bc", "dwbc", "ppl", "dexperts", "safedice")
TOLERANCE = 1e-5


def run(model, observations):
    session = onnxruntime.InferenceSession(model, providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    assert names[0] == "actions", names
    return session.run(None, {"observations": observations})


def exported_by_cli(policy):
    path = f"{WORKDIR}/{policy}.safetensors"
    with open(path, "wb") as f:
        f.write(get_bytes(f"/v1/policies/{policy}/weights"))
    out = f"{WORKDIR}/{policy}.onnx"
    subprocess.run([BINARY, "export", path, "--out", out], check=True, capture_output=True)
    with open(out, "rb") as f:
        return f.read()


def check(env, algorithm):
    policy = train(env, algorithm)
    served = get_bytes(f"/v1/policies/{policy}/export?format=onnx")
    cli = exported_by_cli(policy)
    assert served == cli, "the endpoint and the CLI export the same model"
    session = onnxruntime.InferenceSession(served, providers=["CPUExecutionProvider"])
    obs_dim = session.get_inputs()[0].shape[1]
    rng = np.random.default_rng(1)
    observations = rng.uniform(-2, 2, size=(256, obs_dim)).astype(np.float32)
    expected = act(policy, observations)
    outputs = run(served, observations)
    actions = outputs[0]
    if actions.dtype == np.int64:
        assert np.array_equal(actions, expected), (env, algorithm, actions, expected)
        probabilities = outputs[1]
        assert probabilities.shape == (256, session.get_outputs()[1].shape[1])
        assert np.array_equal(np.argmax(probabilities, axis=1), actions)
        error = 0.0
    else:
        error = float(np.max(np.abs(actions - expected)))
        assert error <= TOLERANCE, (env, algorithm, error)
    print(f"{env} {algorithm}: {actions.dtype} actions of {len(actions)} observations agree "
          f"with /act (max difference {error:.2e})")


def main():
    for env in ("six-rooms", "point-goal"):
        for algorithm in ALGORITHMS:
            check(env, algorithm)
    print("onnxruntime: all checks passed")


if __name__ == "__main__":
    main()
