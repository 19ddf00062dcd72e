"""The README's walk through training jobs and policies, in Python with safedice_client.

    python walkthrough.py http://127.0.0.1:8080 demo-data

`demo-data` is what `safedice datagen --env point-goal --preferred 200 --non-preferred 200
--labeled 20 --out demo-data` writes. The API token, if the server has one, comes from
SAFEDICE_API_TOKEN. CI runs this file against a fresh server (tests/clients/run.sh).
"""

import sys
from pathlib import Path

import numpy as np

from safedice_client import Client

url, data = sys.argv[1], Path(sys.argv[2])
client = Client(url)

# The built-in environments and their spaces.
print("environments:", [env["name"] for env in client.envs()])

# Upload the unlabeled (mixed) and the labeled non-preferred demonstrations.
unlabeled = client.upload_dataset(data / "unlabeled.npz", name="point-goal unlabeled")
non_preferred = client.upload_dataset(data / "non_preferred.npz", name="point-goal non-preferred")
print(f"uploaded {unlabeled['transitions']} + {non_preferred['transitions']} transitions")

# Queue SafeDICE: only iterations and seed; every other knob has a documented default.
job = client.submit_job(
    unlabeled["id"], non_preferred["id"], config={"iterations": 2000, "seed": 0, "hidden_sizes": [64, 64]}
)
job = client.wait(job["id"])
print(f"job {job['id']} succeeded, alpha-hat {job['alpha_hat']:.3f}")

# Its metrics, as numpy arrays of (step, value).
metrics = client.metrics(job["id"], names=["alpha_hat"])
print("alpha_hat recorded at", len(metrics["alpha_hat"]), "steps")

# Actions for a batch of observations, and the policy's files.
policy = client.policy(job["policy_id"])
observations = np.zeros((4, policy["obs_dim"]), dtype=np.float32)
print("actions:", client.act(policy["id"], observations).round(3).tolist())
client.download_policy(policy["id"], "policy.safetensors")
client.download_onnx(policy["id"], "policy.onnx")
print("wrote policy.safetensors and policy.onnx")
