"""onnxruntime (PyPI, unmodified) on the ONNX export of policies of every algorithm, on a discrete
and a continuous environment.

Usage: test_onnxruntime.py HOST:PORT WORKDIR BINARY (see common.py). For each policy: the model
from GET /v1/policies/{id}/export?format=onnx, and the one `safedice export` makes from the
downloaded policy file, run by onnxruntime on random observations, must give /act's
deterministic actions (discrete: equal; continuous: within 1e-5), and for SafeDICE the safety
outputs `non_preferred_log_ratio` and `out_of_support` must give /act's `safety` scores (within
1e-5, relative above 1; the log-ratio's bound times its recalibration's scale, which multiplies
the logit's float error). Other algorithms' models have no safety outputs. Exits non-zero
otherwise.
"""

import json
import subprocess
import sys

import numpy as np
import onnxruntime

from common import act, get_bytes, safety_scores, train, WORKDIR

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
    safety = check_safety(session, policy, env, algorithm)
    print(f"{env} {algorithm}: {actions.dtype} actions of {len(actions)} observations agree "
          f"with /act (max difference {error:.2e}){safety}")


def check_safety(session, policy, env, algorithm):
    """SafeDICE's exported safety outputs against /act's scores, on the states of the data and
    on random ones; none for other algorithms."""
    names = [o.name for o in session.get_outputs()]
    safety_names = ["non_preferred_log_ratio", "out_of_support"]
    if algorithm != "safedice":
        assert not set(safety_names) & set(names), (algorithm, names)
        return ""
    assert names[-2:] == safety_names, names
    # The data's states: random ones, standardised by a one-hot dimension's tiny spread, reach
    # thousands and the float error of the network with them.
    observations = np.load(f"{WORKDIR}/{env}/unlabeled.npz")["observations"][:256]
    observations = observations.astype(np.float32)
    outputs = session.run(None, {"observations": observations})
    expected = safety_scores(policy, observations)
    # The recalibration `scale * c + shift` multiplies the float error of the discriminator's
    # logit c: the bound is on c's scale.
    scale = max(1.0, policy_spec(policy)["safety"]["logit_scale"])
    worst = 0.0
    for name, want in zip(safety_names, expected):
        got = outputs[names.index(name)]
        assert got.shape == want.shape, (name, got.shape, want.shape)
        bound = np.maximum(1.0, np.abs(want)) * (scale if name == safety_names[0] else 1.0)
        error = float(np.max(np.abs(got - want) / bound))
        assert error <= TOLERANCE, (algorithm, name, error, scale)
        worst = max(worst, error)
    return (f"; safety outputs agree (max relative difference {worst:.2e}, logit scale "
            f"{scale:.3g})")


def policy_spec(policy):
    """The spec in the policy file's safetensors metadata."""
    data = get_bytes(f"/v1/policies/{policy}/weights")
    header = json.loads(data[8:8 + int.from_bytes(data[:8], "little")])
    return json.loads(header["__metadata__"]["safedice.policy"])["spec"]


def main():
    for env in ("six-rooms", "point-goal"):
        for algorithm in ALGORITHMS:
            check(env, algorithm)
    print("onnxruntime: all checks passed")


if __name__ == "__main__":
    main()
