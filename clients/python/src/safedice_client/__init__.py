"""Python client of the safedice service (offline safe imitation learning over HTTP).

    >>> from safedice_client import Client
    >>> client = Client("http://127.0.0.1:8080", token=None)
    >>> unlabeled = client.upload_dataset({"observations": obs, "actions": act, ...}, name="u")
    >>> job = client.submit_job(unlabeled["id"], non_preferred["id"], config={"iterations": 2000})
    >>> job = client.wait(job["id"])                  # a progress line on stderr
    >>> actions = client.act(job["policy_id"], observations)

Only the standard library and numpy (onnxruntime too for `evaluate(..., local=True)`): datasets go up as NPZ in the D4RL/DSRL layout (see the
service's docs/datasets.md), policies come down as safetensors or ONNX files.
"""

from .client import ApiError, Client, JobFailed
from .simulator import Rollouts

__all__ = ["ApiError", "Client", "JobFailed", "Rollouts"]
