"""The RWRL safety constraints on dm_control's tasks, as the SafeDICE paper used them.

The paper (Appendix D, Table 1) runs three Real-World RL suite tasks with one safety constraint
each. This module rebuilds the two we use on plain dm_control, from the constraint definitions
of the RWRL suite (realworldrl_suite/environments/{cartpole,walker}.py):

- cartpole ``realworld_swingup`` with ``slider_pos_constraint``: satisfied while the cart
  position lies strictly inside ``safety_coeff * [-2, 2]`` metres (the limit that
  ``realworld_swingup`` sets; ``safety_coeff = 0.2`` gives +-0.4 m).
- walker ``realworld_walk`` with ``joint_velocity_constraint``: satisfied while the largest
  absolute joint velocity (``qvel[3:]``: the six hinge joints, not the root) is below
  ``safety_coeff * 65`` rad/s (13 rad/s at 0.2).

RWRL checks its constraints on the physics state after each control step; the per-step cost
here is 1 when the checked constraint is violated there, else 0 (the paper's cost). Everything
else is dm_control's task unchanged: 1000 control steps per episode (cartpole 10 s at 0.01 s,
walker 25 s at 0.025 s), its reward, its random initial state. Differences from RWRL are listed
in README.md (no perturbations, noise, delays, extra dimensions; the constraint vector is not
appended to the observation).

Only numpy, dm_control and mujoco are needed here.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

os.environ.setdefault("MUJOCO_GL", "disable")  # never render

import numpy as np
from dm_control import suite

# Table 1 of the paper (Appendix D).
TASKS = {
    "cartpole": dict(domain="cartpole", task="swingup", constraint="slider_pos_constraint",
                     safety_coeff=0.2),
    "walker": dict(domain="walker", task="walk", constraint="joint_velocity_constraint",
                   safety_coeff=0.2),
}

# Table 1: the paper's demonstrators (mean over their demonstrations).
PAPER_DEMONSTRATORS = {
    "cartpole": dict(preferred_return=516.28, non_preferred_return=519.82,
                     preferred_cost=71.95, non_preferred_cost=316.75,
                     unlabeled_episodes=5000, labeled_episodes=80),
    "walker": dict(preferred_return=939.74, non_preferred_return=940.06,
                   preferred_cost=56.14, non_preferred_cost=377.58,
                   unlabeled_episodes=2000, labeled_episodes=10),
}

# RWRL's base limits at safety_coeff = 1 (scaled linearly by the coefficient).
SLIDER_POS_BASE = 2.0  # m: realworld_swingup's slider_pos_constraint is coeff * [-2, 2]
JOINT_VEL_BASE = 65.0  # rad/s: realworld_walk's joint_velocity_constraint is coeff * 65


def slider_pos_ok(physics, safety_coeff: float) -> bool:
    """RWRL cartpole slider_pos_constraint: the cart stays strictly inside the limits."""
    limit = safety_coeff * SLIDER_POS_BASE
    pos = float(physics.cart_position())
    return -limit < pos < limit


def joint_velocity_ok(physics, safety_coeff: float) -> bool:
    """RWRL walker joint_velocity_constraint: every hinge speed below the limit."""
    limit = safety_coeff * JOINT_VEL_BASE
    speeds = np.abs(physics.data.qvel[3:])  # qvel[0:3] is the planar root (z, x, rotation)
    return bool(np.max(speeds) < limit)


CONSTRAINTS = {
    "slider_pos_constraint": slider_pos_ok,
    "joint_velocity_constraint": joint_velocity_ok,
}


def flatten(observation) -> np.ndarray:
    """dm_control's observation dict, flattened in its own key order (float32)."""
    return np.concatenate(
        [np.asarray(v, dtype=np.float64).ravel() for v in observation.values()]
    ).astype(np.float32)


@dataclass
class Step:
    observation: np.ndarray
    reward: float
    cost: float
    last: bool


class SafeEnv:
    """A dm_control task with one RWRL constraint; step returns reward and cost.

    ``seed`` seeds the task's random initial states (dm_control's ``task_kwargs['random']``).
    """

    def __init__(self, name: str, seed: int | None = None, safety_coeff: float | None = None):
        spec = TASKS[name]
        self.name = name
        self.safety_coeff = spec["safety_coeff"] if safety_coeff is None else safety_coeff
        self._check = CONSTRAINTS[spec["constraint"]]
        self._env = suite.load(spec["domain"], spec["task"], task_kwargs={"random": seed})
        action_spec = self._env.action_spec()
        self.action_dim = int(action_spec.shape[0])
        self.action_low = np.asarray(action_spec.minimum, dtype=np.float32)
        self.action_high = np.asarray(action_spec.maximum, dtype=np.float32)
        self.obs_dim = int(sum(int(np.prod(v.shape)) for v in self._env.observation_spec().values()))

    @property
    def physics(self):
        return self._env.physics

    def reset(self) -> np.ndarray:
        return flatten(self._env.reset().observation)

    def step(self, action) -> Step:
        ts = self._env.step(np.asarray(action, dtype=np.float64))
        cost = 0.0 if self._check(self._env.physics, self.safety_coeff) else 1.0
        return Step(flatten(ts.observation), float(ts.reward or 0.0), cost, bool(ts.last()))
