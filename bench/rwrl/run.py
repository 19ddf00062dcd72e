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
DEFAULT_PENALTY = {"cartpole": 0.5, "walker": 1.0}  # cartpole: the committed demonstrator's


def cmd_train_demonstrator(args) -> None:
    import sac

    penalty = 0.0 if args.kind == "non_preferred" else (
        args.penalty if args.penalty is not None else DEFAULT_PENALTY[args.env])
    out = Path(args.work) / "sac" / f"{args.env}-{args.kind}-seed{args.seed}{args.tag}"
    state = sac.train(args.env, args.kind, out, args.steps, args.seed, penalty,
                      args.checkpoint_every, args.eval_episodes, args.hidden,
                      Path(args.init_from) if args.init_from else None, args.gamma)
    DEMOS.mkdir(exist_ok=True)
    target = DEMOS / f"{args.env}-{args.kind}.npz"
    target.write_bytes((out / "actor.npz").read_bytes())
    (DEMOS / f"{args.env}-{args.kind}.json").write_text(json.dumps(state, indent=1) + "\n")
    print(f"exported {target}")


def cmd_pick_demonstrator(args) -> None:
    """Commit one checkpoint of a SAC run as the demonstrator: the checkpoint with the lowest
    mean cost among those within --return-floor of the best return, on fresh episodes."""
    import sac

    run = Path(args.run)
    state = json.loads((run / "state.json").read_text())
    rows = []
    for snap in sorted((run / "snapshots").glob("actor-*.npz"), key=lambda p: int(p.stem.split("-")[1])):
        if args.min_step and int(snap.stem.split("-")[1]) < args.min_step:
            continue
        r, c = sac.evaluate(snap, state["env"], args.episodes, seed=args.seed, deterministic=False)
        rows.append({"steps": int(snap.stem.split("-")[1]), "return": float(r.mean()), "cost": float(c.mean()),
                     "path": str(snap)})
        print(f"{snap.name}: return {r.mean():.1f} cost {c.mean():.1f}", flush=True)
    best_return = max(r["return"] for r in rows)
    eligible = [r for r in rows if r["return"] >= args.return_floor * best_return]
    chosen = min(eligible, key=lambda r: r["cost"])
    DEMOS.mkdir(exist_ok=True)
    kind = state["kind"]
    (DEMOS / f"{state['env']}-{kind}.npz").write_bytes(Path(chosen["path"]).read_bytes())
    state["chosen"] = {"steps": chosen["steps"], "return": chosen["return"], "cost": chosen["cost"],
                       "episodes": args.episodes, "seed": args.seed, "return_floor": args.return_floor,
                       "candidates": [{k: r[k] for k in ("steps", "return", "cost")} for r in rows]}
    (DEMOS / f"{state['env']}-{kind}.json").write_text(json.dumps(state, indent=1) + "\n")
    print(f"chose step {chosen['steps']}: return {chosen['return']:.1f} cost {chosen['cost']:.1f}")


def demonstrator(env: str, kind: str, folder: Path = DEMOS):
    """A committed demonstrator as a batch policy (stochastic, as the paper samples)."""
    from actor_np import NumpyActor

    actor = NumpyActor(Path(folder) / f"{env}-{kind}.npz")
    return lambda obs, rng: actor.act(obs, rng)


def data_dir(args) -> Path:
    return Path(args.work) / "data" / args.env


def cmd_generate(args) -> None:
    from rollouts import concat_datasets, rollouts
    from rwrl_env import PAPER_DEMONSTRATORS

    paper = PAPER_DEMONSTRATORS[args.env]
    n_u = args.unlabeled if args.unlabeled is not None else paper["unlabeled_episodes"]
    n_n = args.labeled if args.labeled is not None else paper["labeled_episodes"]
    n_u_np = int(round(n_u * args.non_preferred_share))
    n_u_p = n_u - n_u_np
    out = data_dir(args)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    common = dict(lanes=args.lanes, max_steps=args.max_steps)
    # Distinct seeds per part, so D^N never repeats an episode of D^U.
    # Each part is cached in <out>/parts/ under a key of what made it (demonstrator file,
    # episodes, seed, cut), so parts can be made in separate processes (--only) and a rerun
    # reuses them.
    import hashlib

    def part(name, kind, episodes, seed):
        if args.only and args.only != name:
            return None
        actor = Path(args.demonstrators) / f"{args.env}-{kind}.npz"
        key = hashlib.sha256(actor.read_bytes() + repr((episodes, seed, args.max_steps)).encode()).hexdigest()[:16]
        path = out / "parts" / f"{name}-{key}.npz"
        if path.exists():
            z = np.load(path)
            return {"returns": z["returns"], "costs": z["costs"], "seconds": float(z["seconds"]),
                    "data": {k[5:]: z[k] for k in z.files if k.startswith("data_")}}
        t = time.time()
        r = rollouts(args.env, demonstrator(args.env, kind, args.demonstrators), episodes, seed, **common)
        r["seconds"] = time.time() - t
        path.parent.mkdir(exist_ok=True)
        np.savez(path, returns=r["returns"], costs=r["costs"], seconds=r["seconds"],
                 **{f"data_{k}": v for k, v in r["data"].items()})
        print(f"{name}: {episodes} episodes in {r['seconds']:.0f} s", flush=True)
        return r

    pref = part("unlabeled_preferred", "preferred", n_u_p, args.data_seed * 10 + 1)
    nonp = part("unlabeled_non_preferred", "non_preferred", n_u_np, args.data_seed * 10 + 2)
    lab = part("labeled", "non_preferred", n_n, args.data_seed * 10 + 3)
    if args.only:
        return
    seconds = pref["seconds"] + nonp["seconds"] + lab["seconds"]  # CPU-bound, one thread each

    # D^U: both parts, episodes shuffled; the ground truth (which demonstrator made each
    # episode) stays in the manifest and is never uploaded.
    merged = concat_datasets([p["data"] for p in (pref, nonp) if "data" in p and len(p["data"]["rewards"])])
    source = np.array([0] * n_u_p + [1] * n_u_np)
    order = np.random.default_rng(args.data_seed).permutation(len(source))
    ids = merged["episode_ids"]
    starts = np.searchsorted(ids, np.arange(len(source)))
    ends = np.append(starts[1:], len(ids))
    idx = np.concatenate([np.arange(starts[e], ends[e]) for e in order])
    unlabeled = {k: v[idx] for k, v in merged.items()}
    new_id = np.empty(len(order), np.int64)
    new_id[order] = np.arange(len(order))
    unlabeled["episode_ids"] = new_id[unlabeled["episode_ids"]]
    # Both tasks' action box is [-1, 1]; say so, rather than let the service infer it from the
    # data's extremes.
    box = dict(action_low=np.full(unlabeled["actions"].shape[1], -1.0, np.float32),
               action_high=np.full(unlabeled["actions"].shape[1], 1.0, np.float32))
    np.savez(out / "unlabeled.npz", **unlabeled, **box)
    np.savez(out / "non_preferred.npz", **lab["data"], **box)

    def summary(r):
        return dict(episodes=int(len(r["returns"])), mean_return=float(r["returns"].mean()) if len(r["returns"]) else None,
                    mean_cost=float(r["costs"].mean()) if len(r["costs"]) else None)

    manifest = dict(
        env=args.env, data_seed=args.data_seed, unlabeled_episodes=n_u, labeled_episodes=n_n,
        unlabeled_non_preferred_episodes=n_u_np, non_preferred_share=args.non_preferred_share,
        max_steps=args.max_steps, transitions=dict(unlabeled=int(len(unlabeled["rewards"])),
                                                   non_preferred=int(len(lab["data"]["rewards"]))),
        unlabeled_preferred=summary(pref), unlabeled_non_preferred=summary(nonp), labeled=summary(lab),
        # The normalisation of evaluate: the preferred demonstrations' mean return, kappa
        # the midpoint of both demonstrators' mean costs (as the service's metrics).
        reference=dict(preferred_return=summary(pref)["mean_return"], preferred_cost=summary(pref)["mean_cost"],
                       non_preferred_return=summary(nonp)["mean_return"] if n_u_np else summary(lab)["mean_return"],
                       non_preferred_cost=summary(nonp)["mean_cost"] if n_u_np else summary(lab)["mean_cost"]),
        unlabeled_episode_is_non_preferred=source[order].tolist(),
        seconds=round(seconds, 1), cpu=_cpu_name(),
    )
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    print(json.dumps({k: v for k, v in manifest.items() if k != "unlabeled_episode_is_non_preferred"}, indent=1))


def runs_dir(args) -> Path:
    return Path(args.work) / "runs" / (getattr(args, "run_name", None) or args.env)


def _server(args):
    """The service: --url if given (token from SAFEDICE_API_TOKEN), else a `safedice serve` of
    our own on a free port with its data in --service-dir (kept, so that `evaluate` finds the
    policies `train` made)."""
    import contextlib

    from service import Client, Server, find_binary

    if args.url:
        return contextlib.nullcontext(Client(args.url, timeout=600))
    service_dir = Path(args.service_dir or Path(args.work) / "service")
    server = Server(find_binary(args.safedice), service_dir / "data", service_dir / "serve.log",
                    extra=["--workers", str(args.workers)])

    class Ctx:
        def __enter__(self):
            c = server.client()
            c.timeout = 600
            return c

        def __exit__(self, *exc):
            server.stop()

    return Ctx()


def cmd_train(args) -> None:
    out = runs_dir(args)
    out.mkdir(parents=True, exist_ok=True)
    record_path = out / "jobs.json"
    record = json.loads(record_path.read_text()) if record_path.exists() else {"env": args.env, "jobs": []}
    data = data_dir(args)
    manifest = json.loads((data / "manifest.json").read_text())
    with _server(args) as client:
        ds = record.get("datasets")
        if ds is None or args.reupload:
            t0 = time.time()
            u = client.upload_dataset(str(data / "unlabeled.npz"), name=f"rwrl-{args.env}-unlabeled", role="unlabeled",
                                      description=f"RWRL {args.env}: {manifest['unlabeled_episodes']} episodes, "
                                                  f"{manifest['unlabeled_non_preferred_episodes']} non-preferred")
            n = client.upload_dataset(str(data / "non_preferred.npz"), name=f"rwrl-{args.env}-non-preferred",
                                      role="non_preferred",
                                      description=f"RWRL {args.env}: {manifest['labeled_episodes']} labeled non-preferred episodes")
            ds = record["datasets"] = {"unlabeled": u["id"], "non_preferred": n["id"],
                                       "unlabeled_transitions": u["transitions"],
                                       "non_preferred_transitions": n["transitions"],
                                       "upload_seconds": round(time.time() - t0, 1)}
            record["jobs"] = []
            record_path.write_text(json.dumps(record, indent=1) + "\n")
            print(f"uploaded D^U {u['id']} ({u['transitions']} transitions) and D^N {n['id']}", flush=True)
        # What each algorithm is called and whether it trains on D^N: the service's registry, recorded
        # for the report, so nothing here names an algorithm.
        catalogue = {a["name"]: a for a in client.algorithms()}
        unknown = [a for a in args.algorithms if a not in catalogue]
        if unknown:
            sys.exit(f"unknown algorithm(s) {', '.join(unknown)}; the service trains {', '.join(catalogue)}")
        record["algorithms"] = [{k: a[k] for k in ("name", "label", "needs_non_preferred")}
                                for a in catalogue.values()]
        record_path.write_text(json.dumps(record, indent=1) + "\n")
        # Cancelled or failed jobs are queued again.
        record["jobs"] = [j for j in record["jobs"] if j.get("status") not in ("cancelled", "failed")]
        done = {(j["algorithm"], j["seed"]) for j in record["jobs"]}
        for seed in args.seeds:
            for algo in args.algorithms:
                if (algo, seed) in done:
                    continue
                config = {"seed": seed}
                if args.iterations:
                    config["iterations"] = args.iterations
                if args.discriminator_iterations and algo == "safedice":
                    config["discriminator_iterations"] = args.discriminator_iterations
                non_preferred = ds["non_preferred"] if catalogue[algo]["needs_non_preferred"] else None
                job = client.submit_job(ds["unlabeled"], non_preferred,
                                        algorithm=algo, config=config,
                                        name=f"rwrl {args.env} {algo} seed {seed}",
                                        tags=["bench=rwrl", f"env=rwrl-{args.env}", f"algorithm={algo}"])
                record["jobs"].append({"algorithm": algo, "seed": seed, "job_id": job["id"], "config": config,
                                       "status": job["status"]})
                record_path.write_text(json.dumps(record, indent=1) + "\n")
                print(f"queued {algo} seed {seed}: job {job['id']}", flush=True)
        # Finished jobs are read again too (one request each): their record then carries any
        # weighting metric added to WEIGHTING_METRICS since.
        for j in record["jobs"]:
            try:
                job = client.wait(j["job_id"], progress=False, poll=5)
            except Exception as e:  # a failed job is recorded, the others go on
                job = client.job(j["job_id"])
                print(f"job {j['job_id']} ({j['algorithm']} seed {j['seed']}): {e}", flush=True)
            j.update(status=job["status"], policy_id=job.get("policy_id"), error=job.get("error"),
                     started_at=job.get("started_at"), finished_at=job.get("finished_at"),
                     alpha_hat=job.get("alpha_hat"), weighting=_weighting(client, job))
            record_path.write_text(json.dumps(record, indent=1) + "\n")
            print(f"{j['algorithm']} seed {j['seed']}: {job['status']} policy {job.get('policy_id')}", flush=True)


# The weighting stage's record of a job that estimated alpha-hat: its interval, the bin it came
# from (and its interval counting episodes), the held-out AUC, whether the stage fell back to
# uniform weights and whether Eq. 10 read episode means (each metric's last value; the service
# logs them once, when the discriminator phase ends; an unbounded upper end is not recorded).
WEIGHTING_METRICS = ("alpha_hat_lower", "alpha_hat_upper", "alpha_hat_bin_ratio", "alpha_hat_bin_share_du",
                     "alpha_hat_bin_share_dn", "alpha_hat_min_ratio", "discriminator_heldout_auc",
                     "discriminator_heldout_auc_lower", "discriminator_heldout_auc_upper", "weighting_uniform",
                     "alpha_hat_episodes_lower", "alpha_hat_episodes_upper",
                     "discriminator_scores_pooled_by_episode")


def _weighting(client, job) -> dict | None:
    if job.get("alpha_hat") is None:
        return None
    series = client.metrics(job["id"], names=WEIGHTING_METRICS)
    return {name: float(points[-1][1]) for name, points in series.items() if len(points)}


def _onnx_policy(path: Path):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    name = sess.get_inputs()[0].name
    return lambda obs, rng: sess.run(None, {name: np.asarray(obs, np.float32)})[0]


def cmd_evaluate(args) -> None:
    from rollouts import metrics, rollouts

    out = runs_dir(args)
    record = json.loads((out / "jobs.json").read_text())
    reference = json.loads((data_dir(args) / "manifest.json").read_text())["reference"]
    evals_path = out / "evaluations.json"
    evals = json.loads(evals_path.read_text()) if evals_path.exists() else []
    have = {(e["policy_id"], e["mode"], e["episodes"], e["seed"]) for e in evals}

    def add(entry, returns, costs, seconds):
        m = metrics(returns, costs, reference)
        entry.update(env=args.env, episodes=args.episodes, seed=args.seed, mode=args.mode,
                     metrics={k: m[k] for k in ("normalized_return", "average_return", "average_cost", "cvar10_cost")},
                     more_metrics={k: v for k, v in m.items()
                                   if k not in ("normalized_return", "average_return", "average_cost", "cvar10_cost")},
                     seconds=round(seconds, 1))
        evals.append(entry)
        evals_path.write_text(json.dumps(evals, indent=1) + "\n")
        print(f"{entry.get('algorithm')} seed {entry.get('train_seed')}: normalized return "
              f"{m['normalized_return']:.1f}, average cost {m['average_cost']:.1f}, CVaR10 {m['cvar10_cost']:.1f}"
              f" ({seconds:.0f} s)", flush=True)

    common = dict(lanes=args.lanes, record=False, max_steps=args.max_steps)
    if args.demonstrators_too:
        for kind in ("preferred", "non_preferred"):
            pid = f"demonstrator:{args.env}-{kind}"
            if (pid, "sampled", args.episodes, args.seed) in have:
                continue
            t0 = time.time()
            r = rollouts(args.env, demonstrator(args.env, kind, args.demonstrators), args.episodes, args.seed, **common)
            mode, args.mode = args.mode, "sampled"
            add({"policy_id": pid, "algorithm": f"demonstrator ({kind})", "train_seed": None},
                r["returns"], r["costs"], time.time() - t0)
            args.mode = mode
    with _server(args) as client:
        jobs = []
        for j in record["jobs"]:
            if j.get("status") != "succeeded":  # `train` may still be waiting on an earlier job
                job = client.job(j["job_id"])
                j = dict(j, status=job["status"], policy_id=job.get("policy_id"))
            if j["status"] == "succeeded":
                jobs.append(j)
        for j in jobs:
            pid = j["policy_id"]
            if (pid, args.mode, args.episodes, args.seed) in have:
                continue
            t0 = time.time()
            if args.mode == "onnx":
                path = out / "policies" / f"{pid}.onnx"
                path.parent.mkdir(exist_ok=True)
                if not path.exists():
                    client.download_onnx(pid, path)
                policy = _onnx_policy(path)
            else:  # sampled actions through POST /v1/policies/{id}/act
                policy = (lambda p: lambda obs, rng: client.act(p, obs, deterministic=False,
                                                                seed=int(rng.integers(1 << 30))))(pid)
            r = rollouts(args.env, policy, args.episodes, args.seed, **common)
            # Recorded in the service too, beside its own evaluations (the policy page shows it).
            recorded = client.record_evaluation(
                pid, f"dm_control/{args.env} ({args.mode})", r["returns"].tolist(), r["costs"].tolist(),
                reference, seed=args.seed, deterministic=args.mode == "onnx")
            add({"policy_id": pid, "job_id": j["job_id"], "algorithm": j["algorithm"], "train_seed": j["seed"],
                 "service_evaluation_id": recorded["id"]},
                r["returns"], r["costs"], time.time() - t0)


def cmd_report(args) -> None:
    import report

    if args.url:  # bring the recorded job statuses up to date first
        from service import Client

        client = Client(args.url)
        for record_path in (Path(args.work) / "runs").glob("*/jobs.json"):
            record = json.loads(record_path.read_text())
            for j in record["jobs"]:
                job = client.job(j["job_id"])
                j.update(status=job["status"], policy_id=job.get("policy_id"), error=job.get("error"),
                         started_at=job.get("started_at"), finished_at=job.get("finished_at"),
                         alpha_hat=job.get("alpha_hat"), progress=job.get("progress"),
                         weighting=_weighting(client, job))
            record_path.write_text(json.dumps(record, indent=1) + "\n")
    res = report.build(Path(args.work), Path(args.demonstrators), args.mode)
    res["cpu"] = _cpu_name()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(res, indent=1) + "\n")
    header = args.header.read_text() if args.header else ""
    (out / "results.md").write_text(header + report.markdown(res, args.mode))
    print(f"wrote {out / 'results.md'} and {out / 'results.json'}")


def _cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip() + f" ({os.cpu_count()} CPUs)"
    except OSError:
        pass
    return "unknown"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", default=str(HERE / "work"))
    p.add_argument("--demonstrators", default=str(DEMOS), help="folder of the demonstrators' .npz")
    sub = p.add_subparsers(dest="cmd", required=True)

    t = sub.add_parser("train-demonstrator")
    t.add_argument("--env", choices=["cartpole", "walker"], required=True)
    t.add_argument("--kind", choices=["preferred", "non_preferred"], required=True)
    t.add_argument("--steps", type=int, default=100_000)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--penalty", type=float, default=None,
                   help="preferred only: reward - penalty * cost (default: cartpole 0.5, walker 1.0)")
    t.add_argument("--checkpoint-every", type=int, default=10_000)
    t.add_argument("--eval-episodes", type=int, default=5)
    t.add_argument("--hidden", type=int, default=256)
    t.add_argument("--gamma", type=float, default=0.99, help="SAC's discount")
    t.add_argument("--init-from", default=None, help="a SAC model.zip to start from (fine-tuning)")
    t.add_argument("--tag", default="", help="suffix of the run folder under work/sac/")
    t.set_defaults(fn=cmd_train_demonstrator)

    pk = sub.add_parser("pick-demonstrator")
    pk.add_argument("--run", required=True, help="a SAC run folder under work/sac/")
    pk.add_argument("--episodes", type=int, default=20)
    pk.add_argument("--seed", type=int, default=777)
    pk.add_argument("--return-floor", type=float, default=0.97)
    pk.add_argument("--min-step", type=int, default=0)
    pk.set_defaults(fn=cmd_pick_demonstrator)

    g = sub.add_parser("generate")
    g.add_argument("--env", choices=["cartpole", "walker"], required=True)
    g.add_argument("--unlabeled", type=int, default=None, help="episodes in D^U (default: the paper's)")
    g.add_argument("--labeled", type=int, default=None, help="episodes in D^N (default: the paper's)")
    g.add_argument("--non-preferred-share", type=float, default=0.5,
                   help="share of D^U's episodes from the non-preferred demonstrator")
    g.add_argument("--data-seed", type=int, default=0)
    g.add_argument("--lanes", type=int, default=8, help="environments stepped together")
    g.add_argument("--max-steps", type=int, default=None, help="cut episodes short (smoke test only)")
    g.add_argument("--only", choices=["unlabeled_preferred", "unlabeled_non_preferred", "labeled"], default=None,
                   help="make only this part (to run parts in parallel processes); a run without it merges")
    g.set_defaults(fn=cmd_generate)

    def service_flags(q):
        q.add_argument("--env", choices=["cartpole", "walker"], required=True)
        q.add_argument("--url", default=None, help="a running service (token: SAFEDICE_API_TOKEN); "
                       "default: start `safedice serve` on a free port with data in --service-dir")
        q.add_argument("--service-dir", default=None, help="default: <work>/service")
        q.add_argument("--run-name", default=None, help="record under <work>/runs/<run-name>/ "
                       "(default: the env), e.g. to keep a shorter-training run apart")
        q.add_argument("--workers", type=int, default=1, help="jobs our own server trains at once "
                       "(one CPU thread each)")
        q.add_argument("--safedice", default=None, help="the safedice binary (default: $SAFEDICE_BIN, "
                       "target/release/safedice, PATH)")

    tr = sub.add_parser("train")
    service_flags(tr)
    tr.add_argument("--algorithms", type=lambda v: v.split(","), default=["safedice", "bc"])
    tr.add_argument("--seeds", type=lambda v: [int(x) for x in v.split(",")], default=[0, 1, 2])
    tr.add_argument("--iterations", type=int, default=None, help="default: the service's")
    tr.add_argument("--discriminator-iterations", type=int, default=None, help="default: the service's")
    tr.add_argument("--reupload", action="store_true")
    tr.set_defaults(fn=cmd_train)

    ev = sub.add_parser("evaluate")
    service_flags(ev)
    ev.add_argument("--episodes", type=int, default=100)
    ev.add_argument("--seed", type=int, default=100, help="evaluation seed (environments 1000*seed + i)")
    ev.add_argument("--mode", choices=["onnx", "act"], default="onnx",
                    help="onnx: the ONNX export's deterministic action in onnxruntime; act: sampled "
                         "actions from POST /v1/policies/{id}/act")
    ev.add_argument("--lanes", type=int, default=10)
    ev.add_argument("--max-steps", type=int, default=None, help="cut episodes short (smoke test only)")
    ev.add_argument("--demonstrators-too", action="store_true", help="also evaluate the demonstrators")
    ev.set_defaults(fn=cmd_evaluate)

    rp = sub.add_parser("report")
    rp.add_argument("--out", default=str(HERE))
    rp.add_argument("--mode", choices=["onnx", "act"], default="onnx", help="which evaluations to tabulate")
    rp.add_argument("--header", type=Path, default=None, help="markdown put before the tables")
    rp.add_argument("--url", default=None, help="refresh the jobs' statuses from this service first")
    rp.set_defaults(fn=cmd_report)

    args = p.parse_args(argv)
    args.fn(args)


if __name__ == "__main__":
    main()
