"""The HTTP client: one method per thing a user does, typed, raising on every error."""

from __future__ import annotations

import http.client
import io
import json
import os
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from . import simulator
from .progress import print_grid_progress, progress_line

Json = Dict[str, Any]
DatasetSource = Union[str, os.PathLike, Mapping[str, np.ndarray]]

#: Rows per /act request when `act` splits a large batch (the service takes at most 16,384).
ACT_BATCH = 4096


class ApiError(Exception):
    """An error answer of the service: its HTTP status, error code and message."""

    def __init__(self, status: int, code: str, message: str):
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message = status, code, message


class JobFailed(Exception):
    """A job `wait` followed ended in a final status the vocabulary does not call a success."""

    def __init__(self, job: Json):
        super().__init__(f"job {job['id']} ended {job['status']}: {job.get('error')}")
        self.job = job


class Client:
    """A safedice server at `base_url` (e.g. ``http://127.0.0.1:8080``).

    `token` is the API token (``--api-token``); it defaults to the ``SAFEDICE_API_TOKEN``
    environment variable, so it need not appear in scripts or process lists.
    """

    def __init__(self, base_url: str, token: Optional[str] = None, timeout: float = 60.0):
        self.base_url = base_url.rstrip("/")
        self.token = token if token is not None else os.environ.get("SAFEDICE_API_TOKEN")
        self.timeout = timeout
        # One kept-alive connection per thread for the JSON calls: an agent calling `act` in a
        # loop pays the TCP handshake once, not once per step.
        self._local = threading.local()
        self._statuses: Optional[list] = None

    # -- environments and datasets -------------------------------------------------------

    def envs(self) -> list:
        """The built-in environments (name, spaces, reference statistics)."""
        return self._get("/v1/envs")["items"]

    def upload_dataset(
        self,
        data: DatasetSource,
        name: Optional[str] = None,
        description: Optional[str] = None,
        role: Optional[str] = None,
    ) -> Json:
        """Uploads a dataset; the stored dataset's description.

        `data` is a file path (JSONL, CSV, NPZ or HDF5, by extension) or a mapping of numpy
        arrays in the D4RL/DSRL layout (``observations``, ``actions``, ``next_observations``,
        ``terminals``, optional ``timeouts``, ``rewards``, ``costs``, ``episode_ids``), sent
        as NPZ. ``role`` (``unlabeled`` or ``non_preferred``) says what it is for; jobs refuse
        it in the other's place.

        Arrays whose episodes nothing marks (no ``timeouts`` or ``episode_ids``, while
        ``next_observations[i]`` differs from ``observations[i + 1]`` at a row that is not
        terminal) raise ``ValueError`` instead of uploading as one long episode.
        """
        if isinstance(data, Mapping):
            arrays = {key: np.asarray(value) for key, value in data.items()}
            _check_episode_ends(arrays)
            buffer = io.BytesIO()
            np.savez(buffer, **arrays)
            filename, content = f"{name or 'dataset'}.npz", buffer.getvalue()
        else:
            path = Path(data)
            filename, content = path.name, path.read_bytes()
        fields = {"name": name, "description": description, "role": role}
        body, content_type = _multipart(fields, filename, content)
        return self._request("POST", "/v1/datasets", body, content_type)

    def datasets(self, limit: int = 50, offset: int = 0) -> Json:
        """A page of datasets, newest first (``items``, ``total``, ``next_offset``)."""
        return self._get(f"/v1/datasets?limit={limit}&offset={offset}")

    def dataset(self, dataset_id: str) -> Json:
        """One dataset's description (role, sizes, statistics)."""
        return self._get(f"/v1/datasets/{dataset_id}")

    def preview(self, dataset_id: str, rows: int = 10, episodes: int = 20) -> Json:
        """The first `rows` transitions (0-100) and a summary of the first `episodes` episodes
        (0-1000: length, return, cost, how it ended) as stored."""
        return self._get(f"/v1/datasets/{dataset_id}/preview?rows={rows}&episodes={episodes}")

    def download_dataset(self, dataset_id: str, path: Union[str, os.PathLike]) -> Path:
        """The dataset as stored, as an NPZ file in the D4RL/DSRL layout (``numpy.load`` reads
        it; uploading it again gives the same dataset)."""
        return self._download(f"/v1/datasets/{dataset_id}/download", path)

    def delete_dataset(self, dataset_id: str) -> None:
        self._request("DELETE", f"/v1/datasets/{dataset_id}")

    def algorithms(self) -> list:
        """The algorithms a job can run: name, what it needs, its config keys and defaults."""
        return self._get("/v1/algorithms")["items"]

    def plan(self, algorithm: str, config: Optional[Json] = None) -> Json:
        """What a job of ``algorithm`` with ``config`` would run, queueing nothing: ``config``
        resolved (every knob) and ``steps`` (pretraining_steps, pretraining_phase, iterations,
        total_steps). A configuration a job would be refused for raises the same ApiError."""
        return self._post_json(f"/v1/algorithms/{algorithm}/plan", config or {})

    def vocabulary(self) -> Json:
        """The service's words with what each means: ``job_statuses`` (name, final, success,
        meaning) and
        ``evaluation_metrics`` (key, history_name, label, lower_is_better, kind)."""
        return self._get("/v1/vocabulary")

    def final_statuses(self) -> frozenset:
        """The job statuses a job never leaves, as the server names them (read once)."""
        return frozenset(s["name"] for s in self._job_statuses() if s["final"])

    def success_statuses(self) -> frozenset:
        """The final statuses that mean the job did what it was for (read once)."""
        return frozenset(s["name"] for s in self._job_statuses() if s["success"])

    def _job_statuses(self) -> list:
        if self._statuses is None:
            self._statuses = self.vocabulary()["job_statuses"]
        return self._statuses

    # -- jobs -----------------------------------------------------------------------------

    def submit_job(
        self,
        unlabeled_dataset: str,
        non_preferred_dataset: Optional[str] = None,
        algorithm: str = "safedice",
        config: Optional[Json] = None,
        runner: Optional[Json] = None,
        eval: Optional[Json] = None,
        name: Optional[str] = None,
        tags: Optional[Sequence[str]] = None,
        notes: Optional[str] = None,
        register: Optional[Mapping[str, str]] = None,
    ) -> Json:
        """Queues a training job; the job (status ``queued``). See GET /v1/algorithms for each
        algorithm's configuration keys and defaults. ``name``, ``tags`` and ``notes`` are for
        people (``jobs(tag=...)`` finds them) and never change what is trained. ``register``
        (``{"model": name, "alias": "staging"}``) makes the policy the model's next version when
        the job succeeds."""
        job: Json = {"algorithm": algorithm, "unlabeled_dataset": unlabeled_dataset}
        optional = {
            "non_preferred_dataset": non_preferred_dataset,
            "config": config,
            "runner": runner,
            "eval": eval,
            "name": name,
            "tags": list(tags) if tags is not None else None,
            "notes": notes,
            "register": dict(register) if register is not None else None,
        }
        job.update({key: value for key, value in optional.items() if value is not None})
        return self._request("POST", "/v1/jobs", json.dumps(job).encode(), "application/json")

    def job(self, job_id: str) -> Json:
        return self._get(f"/v1/jobs/{job_id}")

    def jobs(
        self,
        status: Optional[str] = None,
        tag: Optional[str] = None,
        search: Optional[str] = None,
        limit: int = 50,
    ) -> Iterator[Json]:
        """Every job the filters select, newest first, fetched a page at a time (page tokens:
        jobs queued meanwhile do not shift the pages)."""
        query: Dict[str, Any] = {"limit": limit}
        query.update({k: v for k, v in {"status": status, "tag": tag, "q": search}.items() if v})
        while True:
            page = self._get("/v1/jobs?" + urllib.parse.urlencode(query))
            yield from page["items"]
            if not page.get("next_page_token"):
                return
            query["page_token"] = page["next_page_token"]

    def update_job(self, job_id: str, **labels: Any) -> Json:
        """Sets ``name``, ``tags`` and/or ``notes`` (``None`` clears one); the job."""
        unknown = set(labels) - {"name", "tags", "notes"}
        if unknown:
            raise TypeError(f"update_job takes name, tags and notes, not {sorted(unknown)}")
        body = json.dumps(labels).encode()
        return self._request("PATCH", f"/v1/jobs/{job_id}", body, "application/json")

    def delete_job(self, job_id: str) -> None:
        """Deletes a finished job with its metrics, log and policy (409 while it runs)."""
        self._request("DELETE", f"/v1/jobs/{job_id}")

    def logs(self, job_id: str) -> list:
        """The job's log lines: ``seq``, ``time``, ``level``, ``worker``, ``message``."""
        return self._get(f"/v1/jobs/{job_id}/logs")

    def cancel(self, job_id: str) -> Json:
        return self._request("POST", f"/v1/jobs/{job_id}/cancel")

    def wait(
        self, job_id: str, timeout: Optional[float] = None, progress: bool = True, poll: float = 0.5
    ) -> Json:
        """Waits until the job ends; the job, when its final status is a success. Raises
        `JobFailed` when it ends any other way (the vocabulary's other final statuses), `TimeoutError` after `timeout` seconds. With
        `progress`, a bar on stderr."""
        started = time.monotonic()
        while True:
            job = self.job(job_id)
            if progress:
                progress_line(job)
            if job["status"] in self.final_statuses():
                if progress:
                    sys.stderr.write("\n")
                if job["status"] not in self.success_statuses():
                    raise JobFailed(job)
                return job
            if timeout is not None and time.monotonic() - started > timeout:
                raise TimeoutError(f"job {job_id} still {job['status']} after {timeout} s")
            time.sleep(poll)

    def events(self, job_id: str) -> Iterator[Tuple[str, Json]]:
        """The job's server-sent events as they come: ``("status", job)`` and
        ``("progress", progress)``, until the job ends (or ``("deleted", {"id": ...})``). The
        service ends a stream after 15 minutes; this reconnects until the job has ended."""
        while True:
            request = self._build("GET", f"/v1/jobs/{job_id}/events")
            with self._open(request, timeout=None) as response:
                name, data = None, []
                for raw in response:
                    line = raw.decode().rstrip("\n")
                    if line.startswith("event:"):
                        name = line[6:].strip()
                    elif line.startswith("data:"):
                        data.append(line[5:].strip())
                    elif not line and name is not None:
                        payload = json.loads("\n".join(data))
                        yield name, payload
                        if name == "deleted" or (
                            name == "status" and payload["status"] in self.final_statuses()
                        ):
                            return
                        name, data = None, []

    def metrics(self, job_id: str, names: Optional[Sequence[str]] = None) -> Dict[str, np.ndarray]:
        """The job's recorded metrics: name -> array of (step, value) rows."""
        query = f"?names={','.join(names)}" if names else ""
        rows = self._get(f"/v1/jobs/{job_id}/metrics{query}")["rows"]
        series: Dict[str, list] = {}
        for row in rows:
            series.setdefault(row["name"], []).append((row["step"], row["value"]))
        return {name: np.array(points, dtype=np.float64) for name, points in series.items()}

    # -- policies -------------------------------------------------------------------------

    def policy(self, policy_id: str) -> Json:
        return self._get(f"/v1/policies/{policy_id}")

    def download_policy(self, policy_id: str, path: Union[str, os.PathLike]) -> Path:
        """The policy file (safetensors whose metadata holds the spec and training run)."""
        return self._download(f"/v1/policies/{policy_id}/weights", path)

    def download_onnx(self, policy_id: str, path: Union[str, os.PathLike]) -> Path:
        """The policy as an ONNX model: observations in, deterministic actions out."""
        return self._download(f"/v1/policies/{policy_id}/export?format=onnx", path)

    def act(
        self,
        policy_id: Optional[str] = None,
        observations: Optional[np.ndarray] = None,
        deterministic: bool = True,
        seed: Optional[int] = None,
        batch_size: int = ACT_BATCH,
        model: Optional[str] = None,
    ) -> np.ndarray:
        """Actions for observations (``[B, obs_dim]`` or one ``[obs_dim]``), in batches of
        `batch_size` requests: float ``[B, dim]`` (continuous) or int ``[B]`` (discrete). From a
        policy by id, or from a named model: ``model="pilot"`` (its latest version) or
        ``model="pilot@production"`` (the alias's version)."""
        if (policy_id is None) == (model is None):
            raise ValueError("act needs a policy_id or a model, not both")
        if observations is None:
            raise ValueError("act needs observations")
        path = f"/v1/policies/{policy_id}/act" if model is None else f"/v1/models/{model}/act"
        observations = np.asarray(observations, dtype=np.float32)
        single = observations.ndim == 1
        batch = observations[None, :] if single else observations
        parts = []
        for start in range(0, len(batch), batch_size):
            body: Json = {
                "observations": batch[start : start + batch_size].tolist(),
                "deterministic": deterministic,
            }
            if seed is not None:
                body["seed"] = seed + start
            answer = self._request("POST", path, json.dumps(body).encode(), "application/json")
            parts.append(np.asarray(answer["actions"]))
        actions = np.concatenate(parts)
        return actions[0] if single else actions

    # -- experiments ----------------------------------------------------------------------

    def create_experiment(
        self,
        unlabeled_dataset: str,
        algorithms: Sequence[Union[str, Json]],
        seeds: Union[int, Sequence[int]] = 5,
        non_preferred_dataset: Optional[str] = None,
        config: Optional[Json] = None,
        eval: Optional[Json] = None,
        name: Optional[str] = None,
        tags: Sequence[str] = (),
    ) -> Json:
        """Queues algorithms × seeds as jobs (`seeds`: a count, or the seeds themselves); poll
        `experiment(id)` for progress and the paper's metrics as mean ± SE per algorithm."""
        body: Json = {"unlabeled_dataset": unlabeled_dataset, "algorithms": list(algorithms), "tags": list(tags)}
        if isinstance(seeds, int):
            body["seed_count"] = seeds
        else:
            body["seeds"] = [int(s) for s in seeds]
        optional = {"non_preferred_dataset": non_preferred_dataset, "config": config, "eval": eval, "name": name}
        body.update({key: value for key, value in optional.items() if value is not None})
        return self._post_json("/v1/experiments", body)

    def experiment(self, experiment_id: str, protocol: Optional[str] = None) -> Json:
        """An experiment with its results under one evaluation protocol: `protocol` (a key of
        its ``protocols``), else the newest protocol every job has."""
        query = "?" + urllib.parse.urlencode({"protocol": protocol}) if protocol else ""
        return self._get(f"/v1/experiments/{experiment_id}{query}")

    def results(self, job_ids: Sequence[str], protocol: Optional[str] = None) -> Json:
        """Jobs' results side by side under one evaluation protocol, by the rule experiments
        follow: ``protocol``, ``protocols`` and per job its ``metrics``."""
        params = {"jobs": ",".join(job_ids)}
        if protocol:
            params["protocol"] = protocol
        return self._get(f"/v1/results?{urllib.parse.urlencode(params)}")

    def experiments(self, limit: int = 50) -> list:
        return self._get(f"/v1/experiments?limit={limit}")["items"]

    def wait_experiment(
        self,
        experiment_id: str,
        timeout: Optional[float] = None,
        poll: float = 1.0,
        on_progress: Optional[Callable[[Json], None]] = None,
    ) -> Json:
        """Polls until no job of the experiment is queued or running; the experiment.
        `on_progress(progress)` is called with the jobs' counts by status each time they change
        (default: a line on stderr when it is a terminal)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        report = on_progress or (print_grid_progress if sys.stderr.isatty() else None)
        last = None
        while True:
            experiment = self.experiment(experiment_id)
            progress = experiment["progress"]
            if report is not None and progress != last:
                report(progress)
                last = progress
            if sum(progress.get(s, 0) for s in self.final_statuses()) == progress["total"]:
                return experiment
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"experiment {experiment_id} still running: {progress}")
            time.sleep(poll)

    def cancel_experiment(self, experiment_id: str) -> Json:
        return self._post_json(f"/v1/experiments/{experiment_id}/cancel", {})

    def delete_experiment(self, experiment_id: str) -> None:
        self._request("DELETE", f"/v1/experiments/{experiment_id}")

    # -- models ---------------------------------------------------------------------------

    def create_model(self, name: str, description: str = "", tags: Sequence[str] = ()) -> Json:
        """A named model agents address; its versions are registered policies."""
        return self._post_json("/v1/models", {"name": name, "description": description, "tags": list(tags)})

    def model(self, name: str) -> Json:
        return self._get(f"/v1/models/{name}")

    def models(self, limit: int = 50) -> list:
        return self._get(f"/v1/models?limit={limit}")["items"]

    def register(self, model: str, policy_id: str, alias: Optional[str] = None, description: str = "") -> Json:
        """Registers a policy as the model's next version (moving `alias` to it if given)."""
        body: Json = {"policy_id": policy_id, "description": description}
        if alias is not None:
            body["alias"] = alias
        return self._post_json(f"/v1/models/{model}/versions", body)

    def versions(self, model: str) -> list:
        """The model's versions, newest first."""
        return self._get(f"/v1/models/{model}/versions?limit=500")["items"]

    def set_alias(
        self,
        model: str,
        alias: str,
        version: int,
        canary: Optional[Tuple[int, float]] = None,
        actor: Optional[str] = None,
        reason: Optional[str] = None,
    ) -> Json:
        """Points `alias` at `version` (``canary=(version, weight)`` sends that share of the
        requests to another version); the move as the history keeps it."""
        body: Json = {"version": version}
        if canary is not None:
            body["canary"] = {"version": canary[0], "weight": canary[1]}
        body.update({k: v for k, v in {"actor": actor, "reason": reason}.items() if v is not None})
        return self._request(
            "PUT", f"/v1/models/{model}/aliases/{alias}", json.dumps(body).encode(), "application/json"
        )

    def delete_alias(self, model: str, alias: str, actor: Optional[str] = None) -> None:
        query = f"?actor={urllib.parse.quote(actor)}" if actor else ""
        self._request("DELETE", f"/v1/models/{model}/aliases/{alias}{query}")

    def model_history(self, model: str, alias: Optional[str] = None) -> list:
        """Every move of the model's aliases (of `alias` only, if given), newest first."""
        query = f"?alias={urllib.parse.quote(alias)}" if alias else ""
        return self._get(f"/v1/models/{model}/history{query}")["items"]

    def delete_model(self, name: str) -> None:
        self._request("DELETE", f"/v1/models/{name}")

    # -- evaluations ----------------------------------------------------------------------

    def evaluate(
        self,
        policy_id: str,
        env: Any,
        episodes: int = 500,
        seed: int = 0,
        deterministic: Optional[bool] = None,
        *,
        reference: Optional[Mapping[str, float]] = None,
        cost: Optional[simulator.CostFn] = None,
        local: bool = False,
        max_steps: Optional[int] = None,
        name: Optional[str] = None,
    ) -> Json:
        """Evaluates a policy with the paper's metrics.

        `env` a built-in environment's name: queues the evaluation on the service (poll
        `evaluation(id)` until it ends) and returns it.

        `env` a gymnasium-style environment object (your simulator): rolls the policy out
        `episodes` times here (episode i reset with seed ``seed + i``), acting through ``act``
        over HTTP, or with ``local=True`` through the policy's ONNX export in onnxruntime
        (deterministic actions only). `deterministic` defaults to False (sampled actions, as the
        paper evaluates) through ``act`` and on built-in environments, True with ``local=True``.
        Each step's cost is ``info["cost"]`` unless `cost`
        (``cost(obs, action, next_obs, info)``) says otherwise. The episodes' returns and costs
        are recorded with `reference` (the demonstrators' ``preferred_return``,
        ``preferred_cost``, ``non_preferred_return``, ``non_preferred_cost`` on that
        simulator) under `name` (default: the environment's id); returns the stored evaluation
        (``source: external``, ``runtime`` ``act`` or ``onnx``) with the metrics the service
        computed."""
        if deterministic is None:
            deterministic = local
        if isinstance(env, str):
            body = {"env": env, "episodes": episodes, "seed": seed, "deterministic": deterministic}
            return self._post_json(f"/v1/policies/{policy_id}/evaluate", body)
        if reference is None:
            raise ValueError(
                "an evaluation in your own simulator needs reference= (the demonstrators' mean "
                "returns and costs there) to normalise the return and set the cost threshold"
            )
        rollouts = self.rollout(policy_id, env, episodes, seed, deterministic, cost=cost,
                                local=local, max_steps=max_steps)
        return self.record_evaluation(
            policy_id, name or simulator.env_name(env), rollouts.returns, rollouts.costs,
            reference, lengths=rollouts.lengths, seed=seed, deterministic=deterministic,
            runtime="onnx" if local else "act",
        )

    def rollout(
        self,
        policy_id: str,
        env: Any,
        episodes: int = 10,
        seed: int = 0,
        deterministic: bool = True,
        *,
        cost: Optional[simulator.CostFn] = None,
        local: bool = False,
        max_steps: Optional[int] = None,
    ) -> simulator.Rollouts:
        """Rolls the policy out in a gymnasium-style environment (see `evaluate`) without
        recording anything: each episode's return, cost and length."""
        policy = self.policy(policy_id)
        discrete = policy["action_space"]["type"] == "discrete"
        if local:
            if not deterministic:
                raise ValueError("the ONNX export acts deterministically: pass deterministic=True, or local=False to sample through act")
            actor = simulator.onnx_actor(self, policy_id, discrete)
        else:
            actor = simulator.http_actor(self, policy_id, discrete, deterministic, seed)
        return simulator.roll_out(env, actor, episodes, seed, cost or simulator.info_cost, max_steps)

    def record_evaluation(
        self,
        policy_id: str,
        env: str,
        returns: Sequence[float],
        costs: Sequence[float],
        reference: Mapping[str, float],
        lengths: Optional[Sequence[int]] = None,
        seed: int = 0,
        deterministic: bool = False,
        runtime: Optional[str] = None,
    ) -> Json:
        """Records an evaluation run in your own simulator: each episode's return and cost, and
        `reference` (the demonstrators' `preferred_return`, `preferred_cost`,
        `non_preferred_return`, `non_preferred_cost` on that simulator). The service computes
        the paper's metrics and keeps them with the policy (`source: external`). `seed`,
        `deterministic` and `runtime` (how the policy acted: ``"act"``, ``"onnx"`` or
        ``"other"``) are the evaluation's protocol: results are compared and averaged only
        between evaluations that share it."""
        body: Json = {
            "env": env,
            "returns": [float(r) for r in returns],
            "costs": [float(c) for c in costs],
            "reference": dict(reference),
            "seed": seed,
            "deterministic": deterministic,
        }
        if runtime is not None:
            body["runtime"] = runtime
        if lengths is not None:
            body["lengths"] = [int(n) for n in lengths]
        return self._post_json(f"/v1/policies/{policy_id}/evaluations", body)

    def evaluation(self, evaluation_id: str) -> Json:
        return self._get(f"/v1/evaluations/{evaluation_id}")

    def evaluations(self, policy_id: Optional[str] = None, limit: int = 100) -> list:
        """A policy's evaluations (built-in and external), newest first."""
        query = f"?limit={limit}" + (f"&policy_id={policy_id}" if policy_id else "")
        return self._get(f"/v1/evaluations{query}")["items"]

    # -- plumbing -------------------------------------------------------------------------

    def _post_json(self, path: str, body: Json) -> Any:
        return self._request("POST", path, json.dumps(body).encode(), "application/json")


    def _get(self, path: str) -> Json:
        return self._request("GET", path)

    def _build(
        self, method: str, path: str, body: Optional[bytes] = None, content_type: Optional[str] = None
    ) -> urllib.request.Request:
        request = urllib.request.Request(self.base_url + path, data=body, method=method)
        if content_type:
            request.add_header("Content-Type", content_type)
        if self.token:
            request.add_header("Authorization", f"Bearer {self.token}")
        return request

    def _open(self, request: urllib.request.Request, timeout: Optional[float]):
        try:
            return urllib.request.urlopen(request, timeout=timeout)
        except urllib.error.HTTPError as e:
            raise _api_error(e) from None

    def _request(
        self, method: str, path: str, body: Optional[bytes] = None, content_type: Optional[str] = None
    ) -> Any:
        """A JSON call on this thread's kept-alive connection. A connection the server closed
        while it sat idle (its keep-alive deadline) fails before the server reads anything: the
        call is sent once more on a fresh connection."""
        headers = {"Content-Type": content_type} if content_type else {}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        target = urllib.parse.urlsplit(self.base_url).path + path
        for attempt in range(2):
            connection, reused = self._connection()
            try:
                connection.request(method, target, body=body, headers=headers)
                response = connection.getresponse()
                content = response.read()
            except (http.client.RemoteDisconnected, ConnectionError):
                self._drop_connection()
                if attempt == 0 and reused:
                    continue
                raise
            except BaseException:
                self._drop_connection()
                raise
            if response.will_close:
                self._drop_connection()
            if response.status >= 400:
                raise _api_error_from(response.status, content)
            return json.loads(content) if content else None
        raise AssertionError("unreachable")

    def _connection(self) -> Tuple[http.client.HTTPConnection, bool]:
        """This thread's connection, and whether it served a call before."""
        connection = getattr(self._local, "connection", None)
        if connection is not None:
            return connection, True
        parts = urllib.parse.urlsplit(self.base_url)
        kind = http.client.HTTPSConnection if parts.scheme == "https" else http.client.HTTPConnection
        connection = kind(parts.hostname, parts.port, timeout=self.timeout)
        self._local.connection = connection
        return connection, False

    def _drop_connection(self) -> None:
        connection = getattr(self._local, "connection", None)
        if connection is not None:
            connection.close()
            self._local.connection = None

    def _download(self, path: str, target: Union[str, os.PathLike]) -> Path:
        target = Path(target)
        with self._open(self._build("GET", path), self.timeout) as response:
            with open(target, "wb") as out:
                while chunk := response.read(1 << 20):
                    out.write(chunk)
        return target


def _check_episode_ends(arrays: Mapping[str, np.ndarray]) -> None:
    """Refuses arrays in the D4RL layout whose episode ends nothing marks: without ``timeouts``
    or ``episode_ids`` the service ends episodes at terminals only, and a dataset of cut-off
    episodes would become one long episode (one initial state for SafeDICE)."""
    if "timeouts" in arrays or "episode_ids" in arrays:
        return
    obs, next_obs = arrays.get("observations"), arrays.get("next_observations")
    terminals = arrays.get("terminals")
    if obs is None or next_obs is None or terminals is None or len(obs) < 2:
        return
    jumps = np.any(next_obs[:-1].reshape(len(obs) - 1, -1) != obs[1:].reshape(len(obs) - 1, -1), axis=1)
    unmarked = np.flatnonzero(jumps & ~terminals[:-1].astype(bool))
    if len(unmarked):
        raise ValueError(
            f"{len(unmarked)} rows (first: {unmarked[0]}) end a trajectory (next_observations[i] "
            "!= observations[i + 1]) that no terminal marks; add `timeouts` (True where an "
            "episode was cut off) or `episode_ids`, or the dataset uploads as one long episode"
        )


def _api_error(e: urllib.error.HTTPError) -> ApiError:
    return _api_error_from(e.code, e.read())


def _api_error_from(status: int, body: bytes) -> ApiError:
    try:
        error = json.loads(body)["error"]
        if isinstance(error, str):  # the Open Inference Protocol's shape
            return ApiError(status, "error", error)
        return ApiError(status, error["code"], error["message"])
    except (ValueError, KeyError, TypeError):
        return ApiError(status, "http_error", body.decode(errors="replace")[:500])


def _multipart(fields: Mapping[str, Optional[str]], filename: str, content: bytes) -> Tuple[bytes, str]:
    boundary = uuid.uuid4().hex
    parts = []
    for key, value in fields.items():
        if value is not None:
            parts.append(
                f'--{boundary}\r\nContent-Disposition: form-data; name="{key}"\r\n\r\n{value}\r\n'.encode()
            )
    parts.append(
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="{filename}"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n".encode()
        + content
        + b"\r\n"
    )
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"
