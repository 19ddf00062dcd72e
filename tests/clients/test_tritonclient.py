"""tritonclient.http, unmodified, against a running safedice server (see run.sh).

Usage: test_tritonclient.py HOST:PORT WORKDIR BINARY (see common.py). Trains one BC policy per
environment through the API, then checks every Open Inference Protocol call tritonclient makes,
in JSON and in binary tensor data, against /v1/policies/{id}/act. Exits non-zero on the first
mismatch.
"""

import sys
import urllib.request

import numpy as np
import tritonclient.http as httpclient
from tritonclient.utils import InferenceServerException

import json

from common import act, call, train, wait_until

ADDRESS = sys.argv[1]


def check_policy(client, policy, env):
    metadata = client.get_model_metadata(policy)
    assert metadata["name"] == policy and metadata["platform"] == "safedice", metadata
    assert client.get_model_metadata(policy, model_version="1") == metadata
    assert client.is_model_ready(policy) and client.is_model_ready(policy, model_version="1")
    (tensor,) = metadata["inputs"]
    obs_dim = tensor["shape"][1]
    (output,) = metadata["outputs"]
    # Triton's model configuration, as get_model_config reads it: the same tensors.
    config = client.get_model_config(policy)
    assert client.get_model_config(policy, model_version="1") == config
    assert (config["name"], config["max_batch_size"]) == (policy, 0), config
    assert [(t["name"], t["data_type"], t["dims"]) for t in config["input"]] == \
        [(tensor["name"], "TYPE_FP32", tensor["shape"])], config
    assert [(t["name"], t["data_type"], t["dims"]) for t in config["output"]] == \
        [(output["name"], "TYPE_" + output["datatype"], output["shape"])], config
    assert config["parameters"]["algorithm"]["string_value"] == metadata["parameters"]["algorithm"]
    rng = np.random.default_rng(0)
    observations = rng.uniform(-1, 1, size=(64, obs_dim)).astype(np.float32)
    expected = act(policy, observations)
    for binary in (False, True):
        for version in ("", "1"):
            inputs = [httpclient.InferInput(tensor["name"], list(observations.shape), "FP32")]
            inputs[0].set_data_from_numpy(observations, binary_data=binary)
            outputs = [httpclient.InferRequestedOutput(output["name"], binary_data=binary)]
            result = client.infer(policy, inputs, model_version=version, outputs=outputs)
            got = result.as_numpy(output["name"])
            assert got.dtype == (np.int64 if output["datatype"] == "INT64" else np.float32), got.dtype
            assert got.shape == expected.shape, (got.shape, expected.shape)
            assert np.allclose(got, expected, rtol=0, atol=1e-6), (env, binary, got, expected)
        # tritonclient's default: binary inputs, no outputs named (binary_data_output).
        inputs = [httpclient.InferInput(tensor["name"], list(observations.shape), "FP32")]
        inputs[0].set_data_from_numpy(observations)
        got = client.infer(policy, inputs).as_numpy(output["name"])
        assert np.allclose(got, expected, rtol=0, atol=1e-6), (env, "default", got, expected)
    print(f"{env}: {output['datatype']} actions of {policy} agree with /act "
          "(JSON and binary, with and without a version)")


def infer(client, name, observations, version=""):
    inputs = [httpclient.InferInput("observations", list(observations.shape), "FP32")]
    inputs[0].set_data_from_numpy(observations)
    result = client.infer(name, inputs, model_version=version)
    return result.as_numpy("actions"), result.get_response()["model_version"]


def check_named_model(client, first, second):
    """A named model with two versions and a `production` alias at version 1: tritonclient
    addresses it by name, by name@alias and by version, and gets /act's actions of the policy
    behind each; the repository and statistics extensions answer it."""
    call("POST", "/v1/models", json.dumps({"name": "pilot"}).encode())
    for policy in (first, second):
        call("POST", "/v1/models/pilot/versions", json.dumps({"policy_id": policy}).encode())
    request = urllib.request.Request(
        f"http://{ADDRESS}/v1/models/pilot/aliases/production", method="PUT",
        data=json.dumps({"version": 1, "actor": "tritonclient-test"}).encode(),
        headers={"Content-Type": "application/json"})
    urllib.request.urlopen(request, timeout=60).read()
    assert client.get_model_metadata("pilot")["versions"] == ["1", "2"]
    assert client.get_model_config("pilot@production")["parameters"]["version"]["string_value"] == "1"
    assert client.get_model_config("pilot", "2")["parameters"]["version"]["string_value"] == "2"
    assert client.is_model_ready("pilot@production") and client.is_model_ready("pilot", "2")
    observations = np.random.default_rng(1).uniform(-1, 1, size=(16, 21)).astype(np.float32)
    by_first, by_second = act(first, observations), act(second, observations)
    for name, version, expected, answered in [
        ("pilot@production", "", by_first, "1"),
        ("pilot", "", by_second, "2"),
        ("pilot", "1", by_first, "1"),
        ("pilot", "2", by_second, "2"),
    ]:
        got, model_version = infer(client, name, observations, version)
        assert model_version == answered, (name, version, model_version)
        assert np.allclose(got, expected, rtol=0, atol=1e-6), (name, version)
    index = {m["name"]: m for m in client.get_model_repository_index()}
    assert index["pilot"]["state"] == "READY", index
    client.unload_model("pilot")
    try:
        infer(client, "pilot@production", observations)
    except InferenceServerException as e:
        assert "unloaded" in str(e), str(e)
    else:
        raise AssertionError("an unloaded model answered")
    client.load_model("pilot")
    assert np.allclose(infer(client, "pilot@production", observations)[0], by_first, rtol=0, atol=1e-6)
    stats = client.get_inference_statistics("pilot", "1")["model_stats"][0]
    assert stats["inference_stats"]["success"]["count"] >= 3, stats
    print("named model: pilot, pilot@production and versions 1-2 agree with /act; repository "
          "index, unload, load and statistics answer")


def check_errors(client, policy):
    for call_, needle in [
        (lambda: client.get_model_metadata("no-such-policy"), "no-such-policy"),
        (lambda: client.infer("no-such-policy", [httpclient.InferInput("observations", [1, 1], "FP32")]), "no-such-policy"),
    ]:
        try:
            call_()
        except InferenceServerException as e:
            assert needle in str(e), str(e)
        else:
            raise AssertionError("an unknown model did not fail")
    wrong = httpclient.InferInput("obs", [1, 4], "FP32")
    wrong.set_data_from_numpy(np.zeros((1, 4), dtype=np.float32))
    try:
        client.infer(policy, [wrong])
    except InferenceServerException as e:
        assert "observations" in str(e), str(e)
    else:
        raise AssertionError("a wrong input name was accepted")
    print("errors: tritonclient reads the protocol's error bodies")


def main():
    client = httpclient.InferenceServerClient(url=ADDRESS)
    wait_until(client.is_server_live, "the server")
    assert client.is_server_ready()
    server = client.get_server_metadata()
    assert server["name"] == "safedice" and "binary_tensor_data" in server["extensions"], server
    policies = {env: train(env, "bc") for env in ("six-rooms", "point-goal")}
    for env, policy in policies.items():
        check_policy(client, policy, env)
    check_errors(client, policies["six-rooms"])
    check_named_model(client, policies["point-goal"], train("point-goal", "safedice"))
    print("tritonclient: all checks passed")


if __name__ == "__main__":
    main()
