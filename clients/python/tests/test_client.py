"""The client against a real safedice server (started by tests/clients/run.sh, which passes its
address in SAFEDICE_URL and a `safedice datagen` directory in SAFEDICE_DATA)."""

import os
import socket
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from safedice_client import ApiError, Client, JobFailed

URL = os.environ["SAFEDICE_URL"]
DATA = Path(os.environ["SAFEDICE_DATA"])


@pytest.fixture(scope="module")
def client() -> Client:
    return Client(URL)


def point_goal_arrays() -> dict:
    """The point-goal unlabeled set as numpy arrays in the D4RL layout."""
    with np.load(DATA / "point-goal" / "unlabeled.npz") as npz:
        return {key: npz[key] for key in npz.files}


@pytest.fixture(scope="module")
def trained(client: Client) -> dict:
    unlabeled = client.upload_dataset(point_goal_arrays(), name="from numpy")
    non_preferred = client.upload_dataset(
        DATA / "point-goal" / "non_preferred.npz", role="non_preferred"
    )
    assert non_preferred["role"] == "non_preferred"
    job = client.submit_job(
        unlabeled["id"],
        non_preferred["id"],
        config={"iterations": 300, "hidden_sizes": [32, 32], "batch_size": 64, "seed": 3},
        runner={"log_every": 10},
    )
    return client.wait(job["id"], timeout=300)


def test_a_numpy_dict_uploads_as_the_same_dataset_as_its_file(client: Client) -> None:
    from_arrays = client.upload_dataset(point_goal_arrays(), name="arrays")
    from_file = client.upload_dataset(DATA / "point-goal" / "unlabeled.npz", name="file")
    for key in ("transitions", "episodes", "obs_dim", "action_space", "stats"):
        assert from_arrays[key] == from_file[key], key
    assert from_arrays["name"] == "arrays"


def test_arrays_whose_episode_ends_nothing_marks_are_refused_before_upload(client: Client) -> None:
    arrays = point_goal_arrays()
    arrays.pop("timeouts", None)
    arrays.pop("episode_ids", None)
    arrays["terminals"] = np.zeros_like(arrays["terminals"])
    before = client.datasets()["total"]
    with pytest.raises(ValueError, match="no terminal marks"):
        client.upload_dataset(arrays, name="one long episode")
    assert client.datasets()["total"] == before


def test_a_trained_policy_acts_in_batches_like_one_request(client: Client, trained: dict) -> None:
    assert trained["status"] == "succeeded"
    policy = client.policy(trained["policy_id"])
    observations = np.random.default_rng(0).uniform(-1, 1, (100, policy["obs_dim"]))
    whole = client.act(policy["id"], observations)
    batched = client.act(policy["id"], observations, batch_size=7)
    assert whole.shape == (100, policy["action_space"]["dim"])
    assert np.array_equal(whole, batched)
    assert np.array_equal(client.act(policy["id"], observations[0]), whole[0])


def test_calls_share_one_kept_alive_connection(client: Client, trained: dict) -> None:
    observation = np.zeros(client.policy(trained["policy_id"])["obs_dim"])
    client.act(trained["policy_id"], observation)
    first = client._local.connection.sock
    for _ in range(20):
        client.act(trained["policy_id"], observation)
    assert client._local.connection.sock is first, "every act on the same TCP connection"
    # A connection the server closed meanwhile is replaced without the caller noticing.
    client._local.connection.sock.shutdown(socket.SHUT_RDWR)
    assert client.policy(trained["policy_id"])["id"] == trained["policy_id"]


def test_metrics_come_back_as_arrays_per_name(client: Client, trained: dict) -> None:
    metrics = client.metrics(trained["id"])
    assert metrics and all(series.shape[1] == 2 for series in metrics.values())
    some = next(iter(metrics))
    only = client.metrics(trained["id"], names=[some])
    assert list(only) == [some] and np.array_equal(only[some], metrics[some])


def test_policy_files_download(client: Client, trained: dict, tmp_path: Path) -> None:
    weights = client.download_policy(trained["policy_id"], tmp_path / "policy.safetensors")
    model = client.download_onnx(trained["policy_id"], tmp_path / "policy.onnx")
    assert weights.read_bytes()[8:9] == b"{"  # a safetensors header follows its length
    assert model.stat().st_size > 1000


def test_evaluations_from_the_service_and_from_your_own_simulator(client: Client, trained: dict) -> None:
    policy_id = trained["policy_id"]
    queued = client.evaluate(policy_id, "point-goal", episodes=20, seed=1)
    assert queued["status"] == "queued" and queued["source"] == "builtin"
    reference = {"preferred_return": 10.0, "preferred_cost": 1.0,
                 "non_preferred_return": 10.0, "non_preferred_cost": 3.0}
    recorded = client.record_evaluation(
        policy_id, "my-sim", returns=[5.0, 15.0], costs=[0.0, 4.0], reference=reference, lengths=[10, 30]
    )
    assert recorded["source"] == "external" and recorded["status"] == "succeeded"
    # 100 * 10 / 10; kappa = 2; one of two episodes above it; CVaR 10% is the worst episode.
    metrics = recorded["metrics"]
    assert (metrics["normalized_return"], metrics["cost_threshold"]) == (100.0, 2.0)
    assert (metrics["cost_violation_ratio"], metrics["cvar_cost"]["10"]) == (0.5, 4.0)
    assert recorded["mean_episode_length"] == 20.0
    ids = {e["id"] for e in client.evaluations(policy_id)}
    assert {queued["id"], recorded["id"]} <= ids
    assert client.evaluation(recorded["id"]) == recorded
    for _ in range(600):
        finished = client.evaluation(queued["id"])
        if finished["status"] in ("succeeded", "failed"):
            break
        time.sleep(0.1)
    assert finished["status"] == "succeeded" and finished["metrics"]["cvar_cost"]["10"] >= 0
    with pytest.raises(ApiError) as refused:
        client.record_evaluation(policy_id, "my-sim", returns=[1.0], costs=[-1.0], reference=reference)
    assert (refused.value.status, refused.value.code) == (422, "invalid_evaluation")


def test_events_stream_until_the_job_ends(client: Client, trained: dict) -> None:
    events = list(client.events(trained["id"]))
    assert events[0][0] == "status" and events[-1][1]["status"] == "succeeded"


def test_errors_carry_the_services_code_and_message(client: Client) -> None:
    with pytest.raises(ApiError) as missing:
        client.job("no-such-job")
    assert (missing.value.status, missing.value.code) == (404, "not_found")
    with pytest.raises(ApiError) as refused:
        client.upload_dataset({"observations": np.zeros((3, 2))}, name="broken")
    assert (refused.value.status, refused.value.code) == (422, "invalid_dataset")
    assert "missing required key" in refused.value.message


def test_wait_raises_when_the_job_is_cancelled(client: Client, trained: dict) -> None:
    job = client.submit_job(
        trained["unlabeled_dataset"],
        trained["non_preferred_dataset"],
        config={"iterations": 100_000_000, "hidden_sizes": [32, 32]},
    )
    client.cancel(job["id"])
    with pytest.raises(JobFailed) as failed:
        client.wait(job["id"], timeout=60, progress=False)
    assert failed.value.job["status"] == "cancelled"


def test_jobs_are_named_found_by_tag_and_deleted(client: Client, trained: dict) -> None:
    job = client.update_job(trained["id"], name="client test", tags=["py", "env=rooms"])
    assert (job["name"], job["tags"]) == ("client test", ["py", "env=rooms"])
    assert [j["id"] for j in client.jobs(tag="py", limit=1)] == [job["id"]]
    assert [j["id"] for j in client.jobs(search="CLIENT")] == [job["id"]]
    messages = [line["message"] for line in client.logs(job["id"])]
    assert messages[0].startswith("claimed by worker") and "succeeded" in messages[-1]
    with pytest.raises(TypeError):
        client.update_job(job["id"], status="failed")
    with pytest.raises(ApiError) as bad:
        client.update_job(job["id"], tags=["no spaces"])
    assert (bad.value.status, bad.value.code) == (422, "invalid_labels")
    client.delete_job(job["id"])
    with pytest.raises(ApiError) as gone:
        client.job(job["id"])
    assert gone.value.status == 404



def test_a_policy_is_registered_promoted_and_acted_on_by_name(client: Client) -> None:
    name = f"pilot-{uuid.uuid4().hex[:8]}"
    client.create_model(name, description="the point-goal agent", tags=["client-test"])
    unlabeled = client.upload_dataset(DATA / "point-goal" / "unlabeled.npz")
    job = client.submit_job(
        unlabeled["id"],
        algorithm="bc",
        config={"iterations": 100, "hidden_sizes": [32, 32], "batch_size": 64, "seed": 5},
        register={"model": name, "alias": "staging"},
    )
    policy_id = client.wait(job["id"], timeout=300)["policy_id"]
    (version,) = client.versions(name)
    assert (version["version"], version["policy_id"], version["job_id"]) == (1, policy_id, job["id"])
    assert client.model(name)["aliases"][0]["alias"] == "staging"
    moved = client.set_alias(name, "production", 1, actor="pytest", reason="first")
    assert (moved["from_version"], moved["to_version"], moved["actor"]) == (None, 1, "pytest")
    observations = np.eye(client.policy(policy_id)["obs_dim"], dtype=np.float32)
    by_name = client.act(model=f"{name}@production", observations=observations)
    np.testing.assert_array_equal(by_name, client.act(policy_id, observations))
    np.testing.assert_array_equal(client.act(model=name, observations=observations), by_name)
    assert [m["to_version"] for m in client.model_history(name, alias="production")] == [1]
    with pytest.raises(ApiError) as refused:
        client.delete_model(name)
    assert (refused.value.status, refused.value.code) == (409, "model_in_use")
    for alias in ("production", "staging"):
        client.delete_alias(name, alias, actor="pytest")
    client.delete_model(name)
    with pytest.raises(ValueError):
        client.act(observations=observations)


def test_an_experiment_reports_mean_and_standard_error_per_algorithm(client: Client) -> None:
    unlabeled = client.upload_dataset(DATA / "point-goal" / "unlabeled.npz")
    experiment = client.create_experiment(
        unlabeled["id"],
        ["bc", {"algorithm": "bc", "label": "bc-wide", "config": {"hidden_sizes": [64, 64]}}],
        seeds=[1, 2],
        config={"iterations": 60, "hidden_sizes": [32, 32], "batch_size": 64},
        eval={"env": "point-goal", "every": 60, "episodes": 10, "seed": 0},
        name="client grid",
    )
    seen = []
    done = client.wait_experiment(experiment["id"], timeout=300, on_progress=seen.append)
    assert done["progress"]["succeeded"] == 4, done["progress"]
    assert seen and seen[-1] == done["progress"], seen
    for arm in done["results"]:
        values = [j["metrics"]["normalized_return"] for j in done["jobs"] if j["arm"] == arm["label"]]
        summary = arm["metrics"]["normalized_return"]
        assert summary["values"] == values
        assert summary["mean"] == pytest.approx(np.mean(values))
        assert summary["se"] == pytest.approx(np.std(values, ddof=1) / np.sqrt(len(values)))
    # One seed evaluated again over HTTP through act: a second protocol, the means unmoved.
    first = done["jobs"][0]
    client.record_evaluation(first["policy_id"], "my-sim", returns=[1.0, 3.0], costs=[0.0, 2.0],
                             reference={"preferred_return": 4.0, "preferred_cost": 0.0,
                                        "non_preferred_return": 4.0, "non_preferred_cost": 4.0},
                             runtime="act")
    again = client.experiment(experiment["id"])
    assert again["results"] == done["results"]
    keys = [p["protocol"]["key"] for p in again["protocols"]]
    assert keys == [done["protocol"]["key"], "runtime=act;actions=sampled;episodes=2;seed=0;env=my-sim"]
    under = client.experiment(experiment["id"], protocol=keys[1])
    assert under["jobs"][0]["metrics"]["normalized_return"] == 50.0
    side_by_side = client.results([j["job_id"] for j in done["jobs"]])
    assert side_by_side["protocol"] == done["protocol"]
    assert [j["metrics"] for j in side_by_side["jobs"]] == [j["metrics"] for j in done["jobs"]]
    assert experiment["id"] in [e["id"] for e in client.experiments()]
    client.delete_experiment(experiment["id"])


def test_d4rl_and_dsrl_hdf5_files_upload_as_h5py_writes_them(client: Client, tmp_path: Path) -> None:
    """HDF5 files in D4RL's layout (no next_observations, gzip chunks, infos/ and metadata/
    groups) and DSRL's (every column) upload on the default build; the missing column is derived
    within each episode, and what the server noticed is in the dataset's warnings."""
    import h5py

    arrays = point_goal_arrays()
    episode_ids = arrays.pop("episode_ids")
    ends = np.append(episode_ids[1:] != episode_ids[:-1], True)
    arrays["timeouts"] = ends & ~arrays["terminals"].astype(bool)
    dsrl_path, d4rl_path = tmp_path / "dsrl.hdf5", tmp_path / "d4rl.hdf5"
    with h5py.File(dsrl_path, "w") as f:
        for key, values in arrays.items():
            f.create_dataset(key, data=values, compression="gzip", chunks=True)
    with h5py.File(d4rl_path, "w") as f:
        for key, values in arrays.items():
            if key != "next_observations":
                f.create_dataset(key, data=values, compression="gzip", chunks=True, shuffle=True)
        f.create_group("infos").create_dataset("qpos", data=np.zeros((len(episode_ids), 2)))
        f.create_group("metadata")["algorithm"] = "SAC"
        f.attrs["env"] = "point-goal"

    dsrl = client.upload_dataset(dsrl_path, name="dsrl layout")
    from_npz = client.upload_dataset(DATA / "point-goal" / "unlabeled.npz", name="npz")
    assert dsrl["format"] == "hdf5"
    for key in ("transitions", "episodes", "obs_dim", "action_space"):
        assert dsrl[key] == from_npz[key], key
    assert dsrl["stats"]["warnings"] == []

    d4rl = client.upload_dataset(d4rl_path, name="d4rl layout")
    timed_out = int(arrays["timeouts"].sum())
    assert d4rl["transitions"] == len(episode_ids) - timed_out
    warnings = " ".join(d4rl["stats"]["warnings"])
    assert f"{timed_out} of the {len(episode_ids)} transitions" in warnings, warnings
    assert "`infos/`, `metadata/`" in warnings, warnings
    # The derived successors are the data's own: the rows kept are those with one in the file.
    kept = ~arrays["timeouts"]
    path = client.download_dataset(d4rl["id"], tmp_path / "d4rl.npz")
    with np.load(path) as npz:
        np.testing.assert_array_equal(npz["observations"], arrays["observations"][kept])
        terminal = arrays["terminals"][kept].astype(bool)
        np.testing.assert_array_equal(npz["next_observations"][~terminal],
                                      arrays["next_observations"][kept][~terminal])

    # The same from a dict of arrays: next_observations may be left out there too.
    no_next = {k: v for k, v in arrays.items() if k != "next_observations"}
    assert client.upload_dataset(no_next, name="dict")["transitions"] == d4rl["transitions"]


def test_a_dataset_is_previewed_and_downloads_as_the_arrays_it_was_made_of(
    client: Client, tmp_path: Path
) -> None:
    arrays = point_goal_arrays()
    dataset = client.upload_dataset(arrays, name="round trip")
    assert client.dataset(dataset["id"])["transitions"] == len(arrays["observations"])
    preview = client.preview(dataset["id"], rows=3, episodes=2)
    assert len(preview["transitions"]) == 3
    assert len(preview["episodes"]) == 2
    np.testing.assert_allclose(preview["transitions"][0]["obs"], arrays["observations"][0], rtol=1e-6)
    path = client.download_dataset(dataset["id"], tmp_path / "round-trip.npz")
    with np.load(path) as npz:
        for key in ("observations", "actions", "next_observations"):
            np.testing.assert_array_equal(npz[key], arrays[key].astype(npz[key].dtype), err_msg=key)
    with pytest.raises(ApiError) as missing:
        client.preview(str(uuid.uuid4()))
    assert missing.value.status == 404


def test_algorithms_list_what_each_needs(client: Client) -> None:
    algorithms = {a["name"]: a for a in client.algorithms()}
    assert {"safedice", "bc"} <= set(algorithms)
    assert algorithms["safedice"]["needs_non_preferred"] is True
    assert algorithms["bc"]["needs_non_preferred"] is False


def test_a_plan_resolves_a_config_without_queueing_a_job(client: Client) -> None:
    before = len(list(client.jobs()))
    plan = client.plan("safedice", {"iterations": 300})
    steps = plan["steps"]
    assert steps["iterations"] == 300 and plan["config"]["iterations"] == 300
    assert steps["total_steps"] == steps["pretraining_steps"] + 300
    assert steps["pretraining_phase"] == "discriminator pretraining"
    assert client.plan("bc")["steps"]["pretraining_steps"] == 0
    with pytest.raises(ApiError) as refused:
        client.plan("bc", {"iterations": 0})
    assert (refused.value.status, refused.value.code) == (422, "invalid_config")
    assert len(list(client.jobs())) == before


def test_the_final_statuses_come_from_the_servers_vocabulary(client: Client) -> None:
    vocabulary = client.vocabulary()
    names = [s["name"] for s in vocabulary["job_statuses"]]
    assert names[:2] == ["queued", "running"] and "discarded" in names
    assert client.final_statuses() == frozenset(names[2:])
    assert client.success_statuses() == frozenset(["succeeded"])
    keys = [m["key"] for m in vocabulary["evaluation_metrics"]]
    assert {"normalized_return", "average_cost", "cvar_cost_5"} <= set(keys)


def cartpole_demonstrations(episodes: int, seed: int) -> dict:
    """Episodes of a hand-written CartPole-v1 controller (push the cart the way the pole falls)
    in the D4RL layout, from gymnasium itself."""
    import gymnasium

    env = gymnasium.make("CartPole-v1")
    rows: dict = {k: [] for k in ("observations", "actions", "next_observations", "rewards", "terminals", "timeouts")}
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        done = False
        while not done:
            action = int(obs[2] + 0.5 * obs[3] > 0)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            for key, value in zip(rows, (obs, action, next_obs, reward, terminated, truncated)):
                rows[key].append(value)
            obs, done = next_obs, terminated or truncated
    arrays = {k: np.asarray(v) for k, v in rows.items()}
    for key in ("observations", "next_observations", "rewards"):
        arrays[key] = arrays[key].astype(np.float32)
    arrays["actions"] = arrays["actions"].astype(np.int64)
    return arrays


def cart_off_centre(obs, action, next_obs, info) -> float:
    """The test's cost: 1 for each step that ends with the cart more than 0.5 from the centre."""
    return float(abs(next_obs[0]) > 0.5)


def test_a_policy_is_evaluated_in_gymnasium_over_http_and_locally_and_recorded(client: Client) -> None:
    import gymnasium

    demos = client.upload_dataset(cartpole_demonstrations(12, seed=100), name="cartpole demos")
    assert demos["action_space"] == {"type": "discrete", "n": 2}
    job = client.submit_job(demos["id"], algorithm="bc",
                            config={"iterations": 400, "hidden_sizes": [32, 32], "batch_size": 64, "seed": 1})
    policy_id = client.wait(job["id"], timeout=300)["policy_id"]

    env = gymnasium.make("CartPole-v1")
    over_http = client.rollout(policy_id, env, episodes=4, seed=7, cost=cart_off_centre)
    in_onnxruntime = client.rollout(policy_id, env, episodes=4, seed=7, cost=cart_off_centre, local=True)
    # A deterministic policy: the same episodes whichever way it acts.
    assert over_http == in_onnxruntime
    assert all(n >= 1 for n in over_http.lengths)
    assert over_http.returns == [float(n) for n in over_http.lengths]  # CartPole pays 1 per step

    reference = {"preferred_return": 500.0, "preferred_cost": 1.0,
                 "non_preferred_return": 300.0, "non_preferred_cost": 9.0}
    # local=True acts deterministically without being told; the record says it ran in ONNX.
    recorded = client.evaluate(policy_id, env, episodes=4, seed=7,
                               reference=reference, cost=cart_off_centre, local=True)
    assert (recorded["source"], recorded["env"], recorded["episodes"]) == ("external", "CartPole-v1", 4)
    assert (recorded["runtime"], recorded["deterministic"]) == ("onnx", True)
    assert recorded["protocol"]["key"] == "runtime=onnx;actions=deterministic;episodes=4;seed=7;env=CartPole-v1"
    metrics = recorded["metrics"]
    assert metrics["normalized_return"] == pytest.approx(100 * np.mean(over_http.returns) / 500.0)
    assert metrics["average_cost"] == pytest.approx(np.mean(over_http.costs))
    assert metrics["cost_violation_ratio"] == pytest.approx(np.mean(np.asarray(over_http.costs) > 5.0))
    assert recorded["mean_episode_length"] == pytest.approx(np.mean(over_http.lengths))
    assert recorded["id"] in {e["id"] for e in client.evaluations(policy_id)}

    # Sampled actions go through act with a seed per step: the same call, the same episodes.
    sampled = client.rollout(policy_id, env, episodes=2, seed=3, deterministic=False, cost=cart_off_centre)
    assert sampled == client.rollout(policy_id, env, episodes=2, seed=3, deterministic=False, cost=cart_off_centre)
    with pytest.raises(ValueError, match="deterministic"):
        client.rollout(policy_id, env, episodes=1, deterministic=False, local=True, cost=cart_off_centre)
    with pytest.raises(ValueError, match="no 'cost'"):
        client.rollout(policy_id, env, episodes=1)
    with pytest.raises(ValueError, match="reference"):
        client.evaluate(policy_id, env, episodes=1, cost=cart_off_centre)
