#!/usr/bin/env python3
"""The SafeDICE paper's RWRL experiment, through the service.

Subcommands (each writes under --work, default bench/rwrl/work/, ignored by git):

  train-demonstrator  SAC on a task (stable-baselines3; needs requirements-train.txt),
                      resumable; exports the actor to demonstrators/<env>-<kind>.npz
  demonstrators       return and cost of the committed demonstrators (numpy only)
  generate            D^U and D^N as NPZ in the D4RL/DSRL layout, from the demonstrators
  train               upload D^U and D^N with the Python client, train SafeDICE and BC (and
                      any other algorithm) per seed with the service defaults
  evaluate            download each trained policy's ONNX export, run it with onnxruntime in
                      the MuJoCo simulator, compute the paper's metrics
  report              results.md and results.json from the evaluations

Every long stage runs on one CPU thread (OMP/MKL/torch set to 1).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "1")
os.environ.setdefault("MUJOCO_GL", "disable")

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parents[1] / "clients" / "python" / "src"))

import numpy as np  # noqa: E402

DEMOS = HERE / "demonstrators"
# The cost penalty of the preferred demonstrator's reward (reward - penalty * cost).
DEFAULT_PENALTY = {"cartpole": 1.0, "walker": 1.0}


def cmd_train_demonstrator(args) -> None:
    import sac

    penalty = 0.0 if args.kind == "non_preferred" else (
        args.penalty if args.penalty is not None else DEFAULT_PENALTY[args.env])
    out = Path(args.work) / "sac" / f"{args.env}-{args.kind}-seed{args.seed}"
    state = sac.train(args.env, args.kind, out, args.steps, args.seed, penalty,
                      args.checkpoint_every, args.eval_episodes, args.hidden)
    DEMOS.mkdir(exist_ok=True)
    target = DEMOS / f"{args.env}-{args.kind}.npz"
    target.write_bytes((out / "actor.npz").read_bytes())
    (DEMOS / f"{args.env}-{args.kind}.json").write_text(json.dumps(state, indent=1) + "\n")
    print(f"exported {target}")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", default=str(HERE / "work"))
    sub = p.add_subparsers(dest="cmd", required=True)

    t = sub.add_parser("train-demonstrator")
    t.add_argument("--env", choices=["cartpole", "walker"], required=True)
    t.add_argument("--kind", choices=["preferred", "non_preferred"], required=True)
    t.add_argument("--steps", type=int, default=100_000)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--penalty", type=float, default=None,
                   help="preferred only: reward - penalty * cost (default: 1.0)")
    t.add_argument("--checkpoint-every", type=int, default=10_000)
    t.add_argument("--eval-episodes", type=int, default=5)
    t.add_argument("--hidden", type=int, default=256)
    t.set_defaults(fn=cmd_train_demonstrator)

    args = p.parse_args(argv)
    args.fn(args)


if __name__ == "__main__":
    main()
