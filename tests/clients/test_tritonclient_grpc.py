"""tritonclient.grpc, unmodified, against a running safedice server's gRPC listener (see run.sh).

Usage: test_tritonclient_grpc.py HOST:PORT WORKDIR BINARY GRPC_HOST:PORT (see common.py). Trains
policies through the REST API, then checks the calls tritonclient.grpc makes on
inference.GRPCInferenceService: metadata, configuration, readiness, unary inference with raw
inputs (tritonclient's own) and typed `fp32_contents` (through the package's generated stub),
raw and typed outputs, a 1,000-message stream with one request key, a canary split by request
key, a shadow version compared on a stream, the repository and statistics extensions, the tokens (a second server with tokens:
no or a wrong token is UNAUTHENTICATED), and a SafeDICE policy's safety scores (the parameter
`safety_score` and the outputs by name; a BC policy answers INVALID_ARGUMENT). Every action is compared with
/v1/policies/{id}/act bit for bit. Exits non-zero on the first mismatch.
"""

import json
import os
import queue
import socket
import subprocess
import sys
import tempfile
import urllib.request

import grpc
import numpy as np
import tritonclient.grpc as grpcclient
from tritonclient.grpc import service_pb2, service_pb2_grpc
from tritonclient.utils import InferenceServerException

from common import act, call, safety_scores, train, wait_until

ADDRESS, WORKDIR, BINARY, GRPC_ADDRESS = sys.argv[1:5]


def same(got, expected):
    """Bit for bit: /act's JSON numbers are the shortest forms that read back to the same
    32-bit floats (or the action indices)."""
    expected = expected.astype(got.dtype)
    return got.shape == expected.shape and np.array_equal(got, expected)


def inputs_of(observations):
    inputs = [grpcclient.InferInput("observations", list(observations.shape), "FP32")]
    inputs[0].set_data_from_numpy(observations)
    return inputs


def check_policy(client, stub, policy, env):
    metadata = client.get_model_metadata(policy, as_json=True)
    assert metadata["name"] == policy and metadata["platform"] == "safedice", metadata
    assert metadata["versions"] == ["1"], metadata
    assert client.is_model_ready(policy) and client.is_model_ready(policy, "1")
    (tensor,) = metadata["inputs"]
    (output,) = metadata["outputs"]
    obs_dim = int(tensor["shape"][1])
    config = client.get_model_config(policy, as_json=True)["config"]
    assert config["name"] == policy and config["input"][0]["data_type"] == "TYPE_FP32", config
    assert config["output"][0]["data_type"] == "TYPE_" + output["datatype"], config
    assert config["parameters"]["algorithm"]["string_value"] == "bc", config
    observations = np.random.default_rng(0).uniform(-1, 1, size=(64, obs_dim)).astype(np.float32)
    expected = act(policy, observations)
    dtype = np.int64 if output["datatype"] == "INT64" else np.float32
    # tritonclient's own calls: raw input, raw output (what as_numpy reads).
    for version in ("", "1"):
        outputs = [grpcclient.InferRequestedOutput("actions")]
        result = client.infer(policy, inputs_of(observations), model_version=version,
                              outputs=outputs, request_id="r1")
        got = result.as_numpy("actions")
        assert got.dtype == dtype and same(got, expected), (env, version, got, expected)
        assert result.get_response().id == "r1"
    # The typed forms, through the package's generated stub: fp32_contents in, typed out.
    request = service_pb2.ModelInferRequest(model_name=policy)
    tensor = request.inputs.add(name="observations", datatype="FP32", shape=observations.shape)
    tensor.contents.fp32_contents.extend(observations.flatten().tolist())
    request.parameters["binary_data_output"].bool_param = False
    response = stub.ModelInfer(request)
    assert len(response.raw_output_contents) == 0, response
    contents = response.outputs[0].contents
    typed = contents.int64_contents if dtype == np.int64 else contents.fp32_contents
    got = np.array(typed, dtype=dtype).reshape(response.outputs[0].shape)
    assert same(got, expected), (env, "typed", got, expected)
    print(f"{env}: {output['datatype']} actions of {policy} agree with /act bit for bit "
          "(raw and typed inputs and outputs, with and without a version)")


def check_errors(client, policy):
    for call_, code in [
        (lambda: client.get_model_metadata("no-such-policy"), "StatusCode.NOT_FOUND"),
        (lambda: client.infer("no-such-policy", inputs_of(np.zeros((1, 4), np.float32))),
         "StatusCode.NOT_FOUND"),
        (lambda: client.infer(policy, inputs_of(np.zeros((1, 3), np.float32))),
         "StatusCode.INVALID_ARGUMENT"),
    ]:
        try:
            call_()
        except InferenceServerException as e:
            assert e.status() == code, (e.status(), str(e))
        else:
            raise AssertionError(f"no {code}")
    print("errors: NOT_FOUND for unknown models, INVALID_ARGUMENT for a wrong shape")


def alias(model, body):
    request = urllib.request.Request(
        f"http://{ADDRESS}/v1/models/{model}/aliases/production", method="PUT",
        data=json.dumps(body).encode(), headers={"Content-Type": "application/json"})
    urllib.request.urlopen(request, timeout=60).read()


def stream(client, model, observations, count, key, bad=None):
    """`count` requests on one stream with one request key: the results, in order."""
    results = queue.Queue()
    client.start_stream(callback=lambda result, error: results.put((result, error)),
                        headers={"x-safedice-request-key": key})
    for i in range(count):
        data = np.zeros((1, 3), np.float32) if i == bad else observations
        client.async_stream_infer(model, inputs_of(data), request_id=str(i))
    client.stop_stream()
    answered = []
    while not results.empty():
        answered.append(results.get())
    assert len(answered) == count, len(answered)
    return answered


def check_named_model(client, first, second):
    """`rover` with two versions, `production` at version 1 with a 50% canary of version 2:
    a stream of 1,000 messages with one key stays on one version; keys split between them; the
    repository and statistics extensions see it."""
    call("POST", "/v1/models", json.dumps({"name": "rover"}).encode())
    for policy in (first, second):
        call("POST", "/v1/models/rover/versions", json.dumps({"policy_id": policy}).encode())
    alias("rover", {"version": 1, "canary": {"version": 2, "weight": 0.5}})
    observations = np.random.default_rng(1).uniform(-1, 1, size=(4, 21)).astype(np.float32)
    by_version = {"1": act(first, observations), "2": act(second, observations)}
    assert not same(by_version["1"].astype(np.float32), by_version["2"]), "the versions agree"
    answered = stream(client, "rover@production", observations, 1000, "agent-7", bad=500)
    versions = set()
    for i, (result, error) in enumerate(answered):
        if i == 500:
            assert result is None and "input shape must be" in str(error), (result, error)
            continue
        assert error is None, (i, error)
        response = result.get_response()
        assert response.id == str(i), (i, response.id)
        versions.add(response.model_version)
        assert same(result.as_numpy("actions"), by_version[response.model_version]), i
    assert len(versions) == 1, versions
    print(f"stream: 1,000 messages with one request key, all from version {versions.pop()}, "
          "agree with /act bit for bit; the bad one answered its error and the stream went on")
    seen = {}
    for key in range(60):
        headers = {"x-safedice-request-key": f"agent-{key}"}
        result = client.infer("rover@production", inputs_of(observations), headers=headers)
        version = result.get_response().model_version
        assert same(result.as_numpy("actions"), by_version[version]), key
        again = client.infer("rover@production", inputs_of(observations), headers=headers)
        assert again.get_response().model_version == version, key
        seen[version] = seen.get(version, 0) + 1
    assert set(seen) == {"1", "2"}, seen
    print(f"canary: 60 keys split {seen} between versions 1 and 2, each key on its own side")
    index = {m["name"]: m for m in client.get_model_repository_index(as_json=True)["models"]}
    assert index["rover"]["state"] == "READY", index
    stats = client.get_inference_statistics("rover", as_json=True)["model_stats"]
    counted = sum(int(s["inference_stats"]["success"].get("count", 0)) for s in stats)
    assert counted == 999 + 120, stats
    print("repository index and statistics: rover READY, 1,119 successful inferences counted")
    check_shadow(client, observations, by_version)


def check_shadow(client, observations, by_version):
    """Version 2 shadowing `production` (version 1) on every request: a 100-message stream is
    answered by version 1 alone, and the shadow's series counts the 100 requests and the L2
    distance between the two versions' actions (docs/shadow.md)."""
    alias("rover", {"version": 1, "shadow": {"version": 2, "sample": 1.0}})
    answered = stream(client, "rover@production", observations, 100, "agent-9")
    for i, (result, error) in enumerate(answered):
        assert error is None, (i, error)
        assert result.get_response().model_version == "1", i
        assert same(result.as_numpy("actions"), by_version["1"]), i
    report = call("GET", "/v1/models/rover/shadow?alias=production")
    series = [s for s in report["series"] if (s["production_version"], s["shadow_version"]) == (1, 2)]
    assert len(series) == 1, report
    total = series[0]["total"]
    assert (total["requests"], total["skipped"], total["failed"]) == (100, 0, 0), total
    assert total["observations"] == 100 * len(observations), total
    distances = np.linalg.norm(by_version["1"] - by_version["2"], axis=1)
    assert abs(total["mean_l2"] - distances.mean()) < 1e-4, (total, distances)
    print(f"shadow: 100 streamed requests answered by version 1 alone, compared with version 2: "
          f"mean L2 {total['mean_l2']:.4f} as the two versions' own actions give")


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def check_tokens():
    """A second server with an API and an inference token: gRPC calls need one of them in the
    `authorization` metadata, and the repository the API token, as on REST."""
    http_port, grpc_port = free_port(), free_port()
    with tempfile.TemporaryDirectory() as data:
        env = dict(os.environ, SAFEDICE_API_TOKEN="api-secret",
                   SAFEDICE_INFERENCE_TOKEN="agent-secret", RUST_LOG="warn")
        server = subprocess.Popen(
            [BINARY, "serve", "--bind", f"127.0.0.1:{http_port}",
             "--grpc-bind", f"127.0.0.1:{grpc_port}", "--data-dir", data, "--workers", "0"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            client = grpcclient.InferenceServerClient(url=f"127.0.0.1:{grpc_port}")
            agent = {"authorization": "Bearer agent-secret"}
            wait_until(lambda: client.is_server_live(headers=agent), "the server with tokens")
            for headers, code in [(None, "StatusCode.UNAUTHENTICATED"),
                                  ({"authorization": "Bearer wrong"}, "StatusCode.UNAUTHENTICATED")]:
                try:
                    client.get_server_metadata(headers=headers)
                except InferenceServerException as e:
                    assert e.status() == code, (headers, e.status(), str(e))
                else:
                    raise AssertionError(f"{headers} was let through")
            try:
                client.get_model_repository_index(headers=agent)
            except InferenceServerException as e:
                assert e.status() == "StatusCode.PERMISSION_DENIED", e.status()
            else:
                raise AssertionError("the inference token read the repository")
            client.get_model_repository_index(headers={"authorization": "Bearer api-secret"})
            client.close()
        finally:
            server.terminate()
            server.wait(timeout=30)
    print("tokens: none or a wrong one UNAUTHENTICATED, the inference token PERMISSION_DENIED "
          "on the repository, the API token let through")


def check_safety_scores(client, policy, bc):
    """A SafeDICE policy's safety outputs through tritonclient.grpc equal /act's scores."""
    names = [o["name"] for o in client.get_model_metadata(policy, as_json=True)["outputs"]]
    assert names == ["actions", "non_preferred_log_ratio", "out_of_support"], names
    observations = np.random.default_rng(2).uniform(-1, 1, size=(32, 21)).astype(np.float32)
    log_ratio, support = safety_scores(policy, observations)
    result = client.infer(policy, inputs_of(observations), parameters={"safety_score": True})
    assert same(result.as_numpy("actions"), act(policy, observations))
    assert same(result.as_numpy("non_preferred_log_ratio"), log_ratio)
    assert same(result.as_numpy("out_of_support"), support)
    outputs = [grpcclient.InferRequestedOutput("out_of_support")]
    result = client.infer(policy, inputs_of(observations), outputs=outputs)
    assert result.as_numpy("actions") is None and same(result.as_numpy("out_of_support"), support)
    try:
        client.infer(bc, inputs_of(observations), parameters={"safety_score": True})
    except InferenceServerException as e:
        assert e.status() == "StatusCode.INVALID_ARGUMENT" and "SafeDICE" in str(e), str(e)
    else:
        raise AssertionError("a BC policy answered a safety score")
    print(f"safety scores of {policy} agree with /act bit for bit; BC's are refused")


def main():
    client = grpcclient.InferenceServerClient(url=GRPC_ADDRESS)
    stub = service_pb2_grpc.GRPCInferenceServiceStub(grpc.insecure_channel(GRPC_ADDRESS))
    wait_until(client.is_server_live, "the gRPC listener")
    assert client.is_server_ready()
    server = client.get_server_metadata(as_json=True)
    assert server["name"] == "safedice" and "statistics" in server["extensions"], server
    policies = {env: train(env, "bc") for env in ("six-rooms", "point-goal")}
    for env, policy in policies.items():
        check_policy(client, stub, policy, env)
    check_errors(client, policies["six-rooms"])
    check_safety_scores(client, train("point-goal", "safedice"), policies["point-goal"])
    check_named_model(client, policies["point-goal"], train("point-goal", "bc", seed=1))
    check_tokens()
    client.close()
    print("tritonclient.grpc: all checks passed")


if __name__ == "__main__":
    main()
