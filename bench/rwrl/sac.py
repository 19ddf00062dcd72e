"""Demonstrators as the paper made them: SAC (stable-baselines3, CPU) on the task's reward
(non-preferred: high return, high cost) or on reward - penalty * cost (preferred: high return,
low cost).

Needs requirements-train.txt (torch, stable-baselines3, gymnasium); nothing else in this folder
imports it. Training is seeded and resumable: every ``--checkpoint-every`` steps the model, its
replay buffer and a state file (steps done, wall and CPU seconds spent, evaluations so far) are
written to ``<out>/``; the same command again continues from there. At the end (and at every
checkpoint) the actor is exported to ``<out>/actor.npz`` for actor_np.py (numpy only).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from rwrl_env import SafeEnv


def _gym_env(name: str, seed: int, penalty: float):
    import gymnasium as gym

    class Wrapped(gym.Env):
        """SafeEnv as a gymnasium Env; the reward it trains on is reward - penalty * cost."""

        metadata: dict = {}

        def __init__(self):
            self.env = SafeEnv(name, seed=seed)
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.env.obs_dim,), np.float32)
            self.action_space = gym.spaces.Box(self.env.action_low, self.env.action_high,
                                               dtype=np.float32)

        def reset(self, *, seed=None, options=None):
            return self.env.reset(), {}

        def step(self, action):
            s = self.env.step(action)
            info = {"reward": s.reward, "cost": s.cost}
            # 1000 steps is a time limit, never a terminal state.
            return s.observation, s.reward - penalty * s.cost, False, s.last, info

    return Wrapped()


def evaluate(actor_path: Path, name: str, episodes: int, seed: int, deterministic: bool):
    """Return and cost per episode of an exported actor (numpy only)."""
    from actor_np import NumpyActor

    actor = NumpyActor(actor_path)
    env = SafeEnv(name, seed=seed)
    rng = np.random.default_rng(seed)
    returns, costs = [], []
    for _ in range(episodes):
        obs, ret, cost, last = env.reset(), 0.0, 0.0, False
        while not last:
            s = env.step(actor.act(obs, rng, deterministic))
            obs, last = s.observation, s.last
            ret += s.reward
            cost += s.cost
        returns.append(ret)
        costs.append(cost)
    return np.array(returns), np.array(costs)


def export_actor(model, path: Path, meta: dict) -> None:
    """The SB3 SAC actor's weights as numpy arrays (see actor_np.py)."""
    actor = model.actor
    arrays = {}
    linears = [m for m in actor.latent_pi if m.__class__.__name__ == "Linear"]
    for i, layer in enumerate(linears):
        arrays[f"latent_{i}_w"] = layer.weight.detach().cpu().numpy().astype(np.float32)
        arrays[f"latent_{i}_b"] = layer.bias.detach().cpu().numpy().astype(np.float32)
    arrays["mu_w"] = actor.mu.weight.detach().cpu().numpy().astype(np.float32)
    arrays["mu_b"] = actor.mu.bias.detach().cpu().numpy().astype(np.float32)
    arrays["log_std_w"] = actor.log_std.weight.detach().cpu().numpy().astype(np.float32)
    arrays["log_std_b"] = actor.log_std.bias.detach().cpu().numpy().astype(np.float32)
    arrays["meta"] = np.array(json.dumps(meta))
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


def train(name: str, kind: str, out: Path, steps: int, seed: int, penalty: float,
          checkpoint_every: int, eval_episodes: int, hidden: int, init_from: Path | None = None,
          gamma: float = 0.99) -> dict:
    import torch
    from stable_baselines3 import SAC

    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    state_path = out / "state.json"
    state = json.loads(state_path.read_text()) if state_path.exists() else {
        "env": name, "kind": kind, "seed": seed, "penalty": penalty, "hidden": [hidden, hidden], "gamma": gamma,
        "steps": 0, "wall_seconds": 0.0, "cpu_seconds": 0.0, "evaluations": [],
    }
    if state["steps"] and (state["seed"] != seed or state["penalty"] != penalty):
        raise SystemExit(f"{out} holds a run with seed {state['seed']} and penalty "
                         f"{state['penalty']}; use another --out")
    env = _gym_env(name, seed, penalty)
    model_path, buffer_path = out / "model.zip", out / "replay_buffer.pkl"
    if state["steps"] and model_path.exists():
        model = SAC.load(model_path, env=env, device="cpu")
        if buffer_path.exists():
            model.load_replay_buffer(buffer_path)
        print(f"resuming {out} at step {state['steps']}", flush=True)
    else:
        if init_from is not None:
            # Fine-tuning: another run's whole model (networks, optimisers and the entropy
            # coefficient, which set_parameters would leave at its initial 1.0), on this run's
            # reward and discount, with an empty replay buffer filled for 1,000 steps first.
            model = SAC.load(init_from, env=env, device="cpu")
            model.gamma = gamma
            model.set_random_seed(seed)
            model.learning_starts = model.num_timesteps + 1000
            state["init_from"] = str(init_from)
        else:
            model = SAC("MlpPolicy", env, seed=seed, device="cpu", verbose=0, gamma=gamma,
                        policy_kwargs=dict(net_arch=[hidden, hidden]))
        state["steps"] = 0
        if init_from is not None:
            print(f"starting from the networks of {init_from}", flush=True)
    while state["steps"] < steps:
        chunk = min(checkpoint_every, steps - state["steps"])
        t0, c0 = time.time(), time.process_time()
        model.learn(total_timesteps=chunk, reset_num_timesteps=False, progress_bar=False)
        state["wall_seconds"] += time.time() - t0
        state["cpu_seconds"] += time.process_time() - c0
        state["steps"] += chunk
        model.save(model_path)
        model.save_replay_buffer(buffer_path)
        meta = {k: state[k] for k in ("env", "kind", "seed", "penalty", "steps", "hidden")}
        export_actor(model, out / "actor.npz", meta)
        (out / "snapshots").mkdir(exist_ok=True)  # every checkpoint's actor, to choose from
        (out / "snapshots" / f"actor-{state['steps']}.npz").write_bytes((out / "actor.npz").read_bytes())
        rets, costs = evaluate(out / "actor.npz", name, eval_episodes, seed=10_000 + state["steps"],
                               deterministic=False)
        state["evaluations"].append({"steps": state["steps"], "return": float(rets.mean()),
                                     "cost": float(costs.mean()), "episodes": eval_episodes})
        state_path.write_text(json.dumps(state, indent=1))
        print(f"{name}/{kind} step {state['steps']}: return {rets.mean():.1f} cost {costs.mean():.1f}"
              f" ({state['wall_seconds']:.0f} s wall, {state['cpu_seconds']:.0f} s CPU)", flush=True)
    return state
