"""Rollouts of a policy in a SafeEnv, several environments in lockstep so that the policy runs
on a batch; the datasets in the D4RL/DSRL flat layout the service accepts; the paper's metrics.
numpy, dm_control and mujoco only (plus onnxruntime for ONNX policies, see evaluate.py).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from rwrl_env import SafeEnv

# policy(observations [k, obs_dim], rng) -> actions [k, act_dim]
Policy = Callable[[np.ndarray, np.random.Generator], np.ndarray]


def rollouts(env_name: str, policy: Policy, episodes: int, seed: int, lanes: int = 8,
             record: bool = True, max_steps: int | None = None) -> dict:
    """``episodes`` episodes from dm_control's random initial states, ``lanes`` environments
    stepped together. Environment ``i`` is seeded ``seed * 1000 + i`` and the action noise by
    ``seed``, so the same arguments give the same data. ``max_steps`` cuts every episode short
    (a timeout), for smoke tests only.

    Returns per-episode ``returns`` and ``costs`` and, with ``record``, the transitions
    (observations, actions, next_observations, rewards, costs, terminals, timeouts,
    episode_ids), episodes in the order they finished.
    """
    lanes = max(1, min(lanes, episodes))
    envs = [SafeEnv(env_name, seed=seed * 1000 + i) for i in range(lanes)]
    rng = np.random.default_rng(seed)
    # Lane i runs the episodes i, i + lanes, ...: a fixed share per lane.
    todo = [len(range(i, episodes, lanes)) for i in range(lanes)]
    obs = [env.reset() for env in envs]
    active = [i for i in range(lanes) if todo[i] > 0]
    bufs = [dict(o=[], a=[], no=[], r=[], c=[]) for _ in range(lanes)]
    steps = [0] * lanes
    out = dict(returns=[], costs=[], lengths=[])
    cols = dict(observations=[], actions=[], next_observations=[], rewards=[], costs=[],
                terminals=[], timeouts=[], episode_ids=[])
    while active:
        batch = np.stack([obs[i] for i in active])
        actions = np.asarray(policy(batch, rng), dtype=np.float32)
        still = []
        for j, i in enumerate(active):
            a = np.clip(actions[j], envs[i].action_low, envs[i].action_high)
            s = envs[i].step(a)
            steps[i] += 1
            b = bufs[i]
            if record:
                b["o"].append(obs[i])
                b["a"].append(a)
                b["no"].append(s.observation)
            b["r"].append(s.reward)
            b["c"].append(s.cost)
            obs[i] = s.observation
            if s.last or (max_steps is not None and steps[i] >= max_steps):
                n = len(b["r"])
                out["returns"].append(float(np.sum(b["r"])))
                out["costs"].append(float(np.sum(b["c"])))
                out["lengths"].append(n)
                if record:
                    ep = len(out["returns"]) - 1
                    cols["observations"].append(np.asarray(b["o"], np.float32))
                    cols["actions"].append(np.asarray(b["a"], np.float32))
                    cols["next_observations"].append(np.asarray(b["no"], np.float32))
                    cols["rewards"].append(np.asarray(b["r"], np.float32))
                    cols["costs"].append(np.asarray(b["c"], np.float32))
                    cols["terminals"].append(np.zeros(n, bool))  # time limit, never terminal
                    t = np.zeros(n, bool)
                    t[-1] = True
                    cols["timeouts"].append(t)
                    cols["episode_ids"].append(np.full(n, ep, np.int64))
                bufs[i] = dict(o=[], a=[], no=[], r=[], c=[])
                steps[i] = 0
                todo[i] -= 1
                if todo[i] > 0:
                    obs[i] = envs[i].reset()
                    still.append(i)
            else:
                still.append(i)
        active = still
    out = {k: np.asarray(v) for k, v in out.items()}
    if record:
        out["data"] = {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}
    return out


def concat_datasets(parts: list[dict]) -> dict:
    """Datasets one after the other, episode ids renumbered."""
    result, offset = {}, 0
    for part in parts:
        ids = part["episode_ids"] + offset
        offset = int(ids.max()) + 1 if len(ids) else offset
        for k, v in part.items():
            result.setdefault(k, []).append(ids if k == "episode_ids" else v)
    return {k: np.concatenate(v) for k, v in result.items()}


def metrics(returns: np.ndarray, costs: np.ndarray, reference: dict) -> dict:
    """The paper's metrics over per-episode sums (the service's definitions, src/envs/metrics.rs):
    normalized return = 100 * mean return / the preferred demonstrations' mean return; average
    cost; cost-violation ratio = share of episodes whose cost exceeds kappa, the midpoint of
    the two demonstrators' mean costs; CVaR k% cost = mean cost of the worst ceil(k% * n)
    episodes."""
    n = len(costs)
    worst = np.sort(costs)[::-1]
    kappa = 0.5 * (reference["preferred_cost"] + reference["non_preferred_cost"])
    m = {
        "normalized_return": float(100.0 * returns.mean() / reference["preferred_return"]),
        "average_return": float(returns.mean()),
        "average_cost": float(costs.mean()),
        "cost_violation_ratio": float((costs > kappa).mean()),
    }
    for k in (50, 20, 10, 5):
        m[f"cvar{k}_cost"] = float(worst[: max(1, math.ceil(k / 100 * n))].mean())
    return m
