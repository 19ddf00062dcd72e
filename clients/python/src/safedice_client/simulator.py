"""Rolling a policy out in your own simulator: any gymnasium-style environment (``reset(seed=)``
returning ``(obs, info)``, ``step(action)`` returning ``(obs, reward, terminated, truncated,
info)``), acting through the service's ``act`` or through the policy's ONNX export in
onnxruntime, with the per-step cost from ``info["cost"]`` or a function of yours."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, List, Mapping, Optional

import numpy as np

#: cost(obs, action, next_obs, info) -> the step's cost (at least 0).
CostFn = Callable[[np.ndarray, Any, np.ndarray, Mapping[str, Any]], float]
#: act(obs) -> the action for one observation, as the environment takes it.
ActFn = Callable[[np.ndarray], Any]

# Seeds of sampled actions through `act`: one per step, from the rollout's seed, the episode
# and the step, so the same call gives the same episodes.
_SEED_MASK = (1 << 63) - 1


@dataclass
class Rollouts:
    """Each episode's undiscounted return, cost (sum of per-step costs) and length."""

    returns: List[float] = field(default_factory=list)
    costs: List[float] = field(default_factory=list)
    lengths: List[int] = field(default_factory=list)


def env_name(env: Any) -> str:
    """The environment's registered id (``CartPole-v1``), else its class name."""
    spec = getattr(env, "spec", None)
    return getattr(spec, "id", None) or type(env).__name__


def info_cost(obs: np.ndarray, action: Any, next_obs: np.ndarray, info: Mapping[str, Any]) -> float:
    """The default cost: ``info["cost"]``, as safety-gymnasium and its kin report it."""
    if "cost" not in info:
        raise ValueError(
            "the environment's step info has no 'cost': pass cost=lambda obs, action, "
            "next_obs, info: ... to say what a step costs"
        )
    return float(info["cost"])


def http_actor(client: Any, policy_id: str, discrete: bool, deterministic: bool, seed: int) -> Callable[[int, int], ActFn]:
    """An actor per (episode, step) calling ``client.act`` on one kept-alive connection."""

    def for_step(episode: int, step: int) -> ActFn:
        step_seed = None if deterministic else (seed * 1_000_003 + episode * 100_003 + step) & _SEED_MASK

        def act(obs: np.ndarray) -> Any:
            action = client.act(policy_id, obs, deterministic=deterministic, seed=step_seed)
            return int(action) if discrete else np.asarray(action, dtype=np.float32)

        return act

    return for_step


def onnx_actor(client: Any, policy_id: str, discrete: bool) -> Callable[[int, int], ActFn]:
    """An actor running the policy's ONNX export (deterministic actions) in onnxruntime."""
    import onnxruntime  # only needed for local=True

    with tempfile.TemporaryDirectory() as tmp:
        path = client.download_onnx(policy_id, Path(tmp) / "policy.onnx")
        session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])

    def act(obs: np.ndarray) -> Any:
        (actions,) = session.run(["actions"], {"observations": obs[None, :].astype(np.float32)})
        return int(actions[0]) if discrete else np.asarray(actions[0], dtype=np.float32)

    return lambda episode, step: act


def roll_out(
    env: Any,
    actor: Callable[[int, int], ActFn],
    episodes: int,
    seed: int,
    cost: CostFn,
    max_steps: Optional[int] = None,
) -> Rollouts:
    """`episodes` episodes, the i-th reset with seed ``seed + i``; an episode ends when the
    environment says terminated or truncated, or after `max_steps` steps."""
    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    result = Rollouts()
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        obs = np.asarray(obs, dtype=np.float32)
        total_return = total_cost = 0.0
        steps = 0
        while max_steps is None or steps < max_steps:
            action = actor(episode, steps)(obs)
            next_obs, reward, terminated, truncated, info = env.step(action)
            next_obs = np.asarray(next_obs, dtype=np.float32)
            step_cost = float(cost(obs, action, next_obs, info))
            if not step_cost >= 0.0:
                raise ValueError(f"a step's cost must be at least 0, got {step_cost}")
            total_return += float(reward)
            total_cost += step_cost
            steps += 1
            obs = next_obs
            if terminated or truncated:
                break
        result.returns.append(total_return)
        result.costs.append(total_cost)
        result.lengths.append(steps)
    return result
