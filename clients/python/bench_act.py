"""`act` calls per second in a loop, one observation per call, as an agent stepping a simulator
makes them: through the client (one kept-alive connection per thread) and with a new connection
per call (urllib, what the client did before keep-alive). Trains a small BC policy first.

    python clients/python/bench_act.py http://127.0.0.1:8080 [calls]
"""

import json
import sys
import time
import urllib.request

import numpy as np

from safedice_client import Client


def small_policy(client: Client) -> str:
    rng = np.random.default_rng(0)
    n = 2000
    obs = rng.normal(size=(n, 4)).astype(np.float32)
    arrays = {
        "observations": obs,
        "actions": (obs[:, 2] > 0).astype(np.int64),
        "next_observations": np.roll(obs, -1, axis=0),
        "terminals": np.zeros(n, dtype=bool),
        "timeouts": (np.arange(n) % 100 == 99),
    }
    dataset = client.upload_dataset(arrays, name="bench act")
    job = client.submit_job(dataset["id"], algorithm="bc", config={"iterations": 50, "hidden_sizes": [64, 64]})
    return client.wait(job["id"], progress=False)["policy_id"]


def per_second(calls: int, call) -> float:
    call()  # warm: the policy is loaded, the connection open
    started = time.perf_counter()
    for _ in range(calls):
        call()
    return calls / (time.perf_counter() - started)


def main() -> None:
    url = sys.argv[1]
    calls = int(sys.argv[2]) if len(sys.argv) > 2 else 2000
    client = Client(url)
    policy_id = small_policy(client)
    obs = np.zeros(4, dtype=np.float32)
    body = json.dumps({"observations": [obs.tolist()], "deterministic": True}).encode()

    def fresh_connection() -> None:
        request = urllib.request.Request(f"{url}/v1/policies/{policy_id}/act", data=body,
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request) as response:
            json.loads(response.read())

    kept_alive = per_second(calls, lambda: client.act(policy_id, obs))
    new_each_call = per_second(calls, fresh_connection)
    print(f"act, one observation per call, {calls} calls:")
    print(f"  a new connection per call (urllib):   {new_each_call:8.0f} calls/s")
    print(f"  the client, one kept-alive connection: {kept_alive:8.0f} calls/s ({kept_alive / new_each_call:.2f}x)")


if __name__ == "__main__":
    main()
