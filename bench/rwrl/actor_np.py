"""A SAC actor (squashed Gaussian) run with numpy alone, from the .npz that sac.py exports.

The file holds the actor of stable-baselines3's SAC: ``latent`` layers (Linear + ReLU), a
``mu`` head and a ``log_std`` head (clipped to [-20, 2] as SB3 does). The action is
``tanh(mu + std * eps)`` when sampling and ``tanh(mu)`` when deterministic, in [-1, 1], the
action box of both tasks here.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


class NumpyActor:
    def __init__(self, path: str | Path):
        data = np.load(path)
        self.layers = []
        i = 0
        while f"latent_{i}_w" in data:
            self.layers.append((data[f"latent_{i}_w"].astype(np.float64),
                                data[f"latent_{i}_b"].astype(np.float64)))
            i += 1
        self.mu = (data["mu_w"].astype(np.float64), data["mu_b"].astype(np.float64))
        self.log_std = (data["log_std_w"].astype(np.float64), data["log_std_b"].astype(np.float64))
        self.meta = json.loads(str(data["meta"])) if "meta" in data else {}

    def distribution(self, obs: np.ndarray):
        """Mean and std of the Gaussian before tanh, for one observation or a batch."""
        h = np.asarray(obs, dtype=np.float64)
        for w, b in self.layers:
            h = np.maximum(h @ w.T + b, 0.0)
        mean = h @ self.mu[0].T + self.mu[1]
        log_std = np.clip(h @ self.log_std[0].T + self.log_std[1], LOG_STD_MIN, LOG_STD_MAX)
        return mean, np.exp(log_std)

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None,
            deterministic: bool = False) -> np.ndarray:
        mean, std = self.distribution(obs)
        if deterministic:
            return np.tanh(mean)
        return np.tanh(mean + std * rng.standard_normal(mean.shape))
