"""results.md and results.json from what run.py wrote under <work>/ (numpy only)."""

from __future__ import annotations

import datetime as dt
import json
import math
from pathlib import Path

import numpy as np

from rwrl_env import PAPER_DEMONSTRATORS, TASKS

# The paper's Figure 2, as Tables 5 and 6 (Appendix F.1) print it: mean ± SE over 5 runs of
# 500 episodes: normalized return, average cost, cost-violation ratio, CVaR 10% cost.
PAPER_RESULTS = {
    "cartpole": {
        "bc": (100.24, 0.40, 184.44, 0.94, 0.48, 0.00, 392.75, 2.72),
        "dwbc": (99.78, 0.55, 189.97, 3.21, 0.47, 0.00, 408.71, 4.01),
        "ppl": (83.70, 0.87, 229.80, 1.64, 0.48, 0.01, 440.68, 3.49),
        "dexperts": (100.28, 0.38, 186.15, 2.29, 0.48, 0.01, 397.05, 3.11),
        "safedice": (99.91, 0.60, 154.88, 1.79, 0.34, 0.00, 404.22, 1.56),
    },
    "walker": {
        "bc": (98.41, 0.11, 152.25, 5.33, 0.22, 0.01, 531.07, 7.53),
        "dwbc": (98.99, 0.10, 105.63, 3.85, 0.11, 0.01, 378.01, 20.88),
        "ppl": (99.02, 0.10, 128.46, 4.84, 0.17, 0.01, 478.75, 12.53),
        "dexperts": (95.21, 0.75, 173.20, 11.22, 0.27, 0.03, 518.38, 5.25),
        "safedice": (99.67, 0.13, 68.90, 0.83, 0.00, 0.00, 124.54, 2.56),
    },
}


def _algorithms(run: dict, names) -> list:
    """(name, label) of the run's algorithms in the service's order, as `train` recorded them from
    GET /v1/algorithms; a run recorded before that keeps its algorithms' own names."""
    recorded = [(a["name"], a["label"]) for a in run.get("algorithms") or [] if a["name"] in names]
    return recorded + [(n, n) for n in sorted(names) if n not in dict(recorded)]


def _load(path: Path):
    return json.loads(path.read_text()) if path.exists() else None


def _mse(values):
    v = np.asarray(values, dtype=float)
    se = v.std(ddof=1) / math.sqrt(len(v)) if len(v) > 1 else float("nan")
    return float(v.mean()), float(se)


def _fmt(mean, se, digits=1):
    if se != se:  # nan: one seed
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {se:.{digits}f}"


def _seconds(job):
    if "started_at" not in job and "seconds" in job:  # a run restored from results.json
        return job["seconds"]
    try:
        a = dt.datetime.fromisoformat(job["started_at"].replace("Z", "+00:00"))
        b = dt.datetime.fromisoformat(job["finished_at"].replace("Z", "+00:00"))
        return (b - a).total_seconds()
    except (KeyError, TypeError, AttributeError, ValueError):
        return None


def _summary(evals, mode):
    rows = {}
    for e in evals:
        if e["mode"] == mode:
            rows.setdefault(e["algorithm"], []).append(e)
    summary = {}
    for algo, es in rows.items():
        ms = {k: _mse([e["metrics"][k] for e in es]) for k in
              ("normalized_return", "average_return", "average_cost", "cvar10_cost")}
        ms["cost_violation_ratio"] = _mse([e["more_metrics"]["cost_violation_ratio"] for e in es])
        summary[algo] = {"seeds": sorted(e["train_seed"] for e in es), "episodes": es[0]["episodes"],
                         "metrics": {k: {"mean": m, "se": s} for k, (m, s) in ms.items()}}
    return summary


def build(work: Path, demos: Path, mode: str = "onnx") -> dict:
    out = {"envs": {}}
    for env in TASKS:
        entry = {}
        manifest = _load(work / "data" / env / "manifest.json")
        jobs = _load(work / "runs" / env / "jobs.json")
        evals = _load(work / "runs" / env / "evaluations.json") or []
        states = {k: _load(demos / f"{env}-{k}.json") for k in ("preferred", "non_preferred")}
        if not (manifest or jobs or any(states.values())):
            continue
        entry["demonstrator_training"] = {
            k: ({f: s.get(f) for f in ("steps", "seed", "penalty", "gamma", "hidden", "wall_seconds", "cpu_seconds",
                                       "init_from", "chosen")}
                | {"last_evaluation": s["evaluations"][-1] if s["evaluations"] else None})
            if s else None for k, s in states.items()}
        if manifest:
            entry["data"] = {k: v for k, v in manifest.items() if k != "unlabeled_episode_is_non_preferred"}
        entry["paper_demonstrators"] = PAPER_DEMONSTRATORS[env]
        entry["demonstrator_evaluations"] = [e for e in evals if e["policy_id"].startswith("demonstrator:")]
        entry["runs"] = {}
        for run_dir in sorted((work / "runs").glob(f"{env}*")):
            if run_dir.name != env and not run_dir.name.startswith(env + "-"):
                continue
            r_jobs = _load(run_dir / "jobs.json")
            r_evals = [e for e in (_load(run_dir / "evaluations.json") or [])
                       if not e["policy_id"].startswith("demonstrator:")]
            run = {"summary": {m: _summary(r_evals, m) for m in ("onnx", "act")}, "evaluations": r_evals}
            if r_jobs:
                run["jobs"] = [{k: j.get(k) for k in ("algorithm", "seed", "job_id", "policy_id", "status", "config",
                                                      "alpha_hat", "weighting")} | {"seconds": _seconds(j)} for j in r_jobs["jobs"]]
                run["datasets"] = r_jobs.get("datasets")
                run["algorithms"] = r_jobs.get("algorithms")
            entry["runs"][run_dir.name] = run
        out["envs"][env] = entry
    return out


def _weighting_cells(job: dict) -> str:
    """alpha-hat with its interval (and the bin's counting episodes, where recorded), its bin, the paper's point-wise minimum beside it, the held-out
    AUC and the stage's weighting: the five cells after the status (dashes where the job has no
    weighting stage or predates the record)."""
    ah, w = job.get("alpha_hat"), job.get("weighting") or {}
    if not isinstance(ah, (int, float)):
        return "— | — | — | — | —"
    alpha = f"{ah:.3f}"
    if "alpha_hat_lower" in w and "alpha_hat_upper" in w:
        alpha += f" [{w['alpha_hat_lower']:.3f}, {w['alpha_hat_upper']:.3f}]"
    if "alpha_hat_episodes_lower" in w:
        # The service records no unbounded upper end (D^N's share in the bin could be 0).
        upper = w.get("alpha_hat_episodes_upper")
        alpha += f", by episode [{w['alpha_hat_episodes_lower']:.3f}, {'∞' if upper is None else f'{upper:.3f}'}]"
    shares = (f"{w['alpha_hat_bin_share_du']:.4f} / {w['alpha_hat_bin_share_dn']:.4f}"
              if "alpha_hat_bin_share_du" in w and "alpha_hat_bin_share_dn" in w else "—")
    minimum = f"{w['alpha_hat_min_ratio']:.4f}" if "alpha_hat_min_ratio" in w else "—"
    auc = "—"
    if "discriminator_heldout_auc" in w:
        auc = f"{w['discriminator_heldout_auc']:.3f}"
        if "discriminator_heldout_auc_lower" in w and "discriminator_heldout_auc_upper" in w:
            auc += f" [{w['discriminator_heldout_auc_lower']:.3f}, {w['discriminator_heldout_auc_upper']:.3f}]"
    weighting = "—" if "weighting_uniform" not in w else ("uniform (BC)" if w["weighting_uniform"] else "SafeDICE")
    if w.get("discriminator_scores_pooled_by_episode") == 1.0:
        weighting += ", Eq. 10 on episode means"
    return f"{alpha} | {shares} | {minimum} | {auc} | {weighting}"


def markdown(res: dict, mode: str) -> str:
    lines = []
    for env, e in res["envs"].items():
        paper = PAPER_DEMONSTRATORS[env]
        lines += [f"## {env} ({TASKS[env]['domain']}.{TASKS[env]['task']}, {TASKS[env]['constraint']}, "
                  f"safety coefficient {TASKS[env]['safety_coeff']})", ""]
        lines += ["### Demonstrators", "",
                  "| demonstrator | SAC steps | penalty | train wall time | return (ours) | cost (ours) | "
                  "return (paper) | cost (paper) |", "|---|---|---|---|---|---|---|---|"]
        dev = {d["algorithm"]: d for d in e.get("demonstrator_evaluations", [])}
        for kind in ("preferred", "non_preferred"):
            st = e["demonstrator_training"].get(kind)
            d = dev.get(f"demonstrator ({kind})")
            ret = f"{d['metrics']['average_return']:.1f}" if d else "—"
            cost = f"{d['metrics']['average_cost']:.1f}" if d else "—"
            steps = f"{st['steps']:,}" if st else "—"
            if st and st.get("chosen"):
                steps = f"fine-tune {st['chosen']['steps']:,} of {st['steps']:,}"
            pen = f"{st['penalty']}" if st else "—"
            wall = f"{st['wall_seconds'] / 60:.0f} min" if st else "—"
            lines.append(f"| {kind.replace('_', '-')} | {steps} | {pen} | {wall} | {ret} | {cost} | "
                         f"{paper[kind + '_return']} | {paper[kind + '_cost']} |")
        if dev:
            any_d = next(iter(dev.values()))
            lines += ["", f"Ours: {any_d['episodes']} episodes each, sampled actions (evaluation seed "
                          f"{any_d['seed']}). Paper: Table 1, the mean over its demonstrations."]
        data = e.get("data")
        if data:
            lines += ["", "### Data", "",
                      f"D^U: {data['unlabeled_episodes']:,} episodes ({data['unlabeled_non_preferred_episodes']:,} "
                      f"non-preferred), {data['transitions']['unlabeled']:,} transitions; D^N: "
                      f"{data['labeled_episodes']} episodes; data seed {data['data_seed']}; generated in "
                      f"{data['seconds'] / 60:.1f} min on {data['cpu']}. Paper: {paper['unlabeled_episodes']:,} / "
                      f"{paper['labeled_episodes']}.",
                      f"D^U's preferred episodes: return {data['unlabeled_preferred']['mean_return']:.1f}, cost "
                      f"{data['unlabeled_preferred']['mean_cost']:.1f}; non-preferred: return "
                      f"{(data['unlabeled_non_preferred']['mean_return'] or float('nan')):.1f}, cost "
                      f"{(data['unlabeled_non_preferred']['mean_cost'] or float('nan')):.1f} (these normalise the "
                      "return and set κ below)."]
        for run_name, run in e.get("runs", {}).items():
            lines += ["", f"### Run `{run_name}`"]
            for mode_ in ("act", "onnx"):
                summ = run["summary"].get(mode_)
                if not summ:
                    continue
                how = ("sampled actions through POST /act (as the paper evaluates)" if mode_ == "act"
                       else "the ONNX export's deterministic action in onnxruntime")
                eps = next(iter(summ.values()))["episodes"]
                lines += ["", f"Policies through the service, {eps} episodes each, {how}:", "",
                          "| algorithm | seeds | normalized return | average cost | cost-violation ratio | CVaR 10% cost | "
                          "paper: return / cost / violation / CVaR 10% |", "|---|---|---|---|---|---|---|"]
                for algo, label in _algorithms(run, summ):
                    s_ = summ[algo]
                    m = s_["metrics"]
                    p = PAPER_RESULTS[env].get(algo)
                    ptxt = (f"{p[0]:.1f} / {p[2]:.1f} / {p[4]:.2f} / {p[6]:.1f}" if p else "—")
                    lines.append(f"| {label} | {len(s_['seeds'])} | "
                                 f"{_fmt(m['normalized_return']['mean'], m['normalized_return']['se'])} | "
                                 f"{_fmt(m['average_cost']['mean'], m['average_cost']['se'])} | "
                                 f"{_fmt(m['cost_violation_ratio']['mean'], m['cost_violation_ratio']['se'], 2)} | "
                                 f"{_fmt(m['cvar10_cost']['mean'], m['cvar10_cost']['se'])} | {ptxt} |")
                bc, sd = summ.get("bc"), summ.get("safedice")
                if bc and sd:
                    rc = sd["metrics"]["average_cost"]["mean"] / max(bc["metrics"]["average_cost"]["mean"], 1e-9)
                    rr = sd["metrics"]["normalized_return"]["mean"] / max(bc["metrics"]["normalized_return"]["mean"], 1e-9)
                    goal = "met" if rc <= 0.6 and rr >= 0.95 else "missed"
                    lines += ["", f"SafeDICE / BC: average cost {rc:.2f}x at {rr:.2f}x the normalized return "
                                  f"(issue goal ≤ 0.6x at ≥ 0.95x: {goal})."]
            if run.get("jobs"):
                share = (e.get("data") or {}).get("non_preferred_share")
                lines += ["", f"| job | seed | config sent | status | alpha-hat [interval] (true {share}) | "
                              "bin: share of D^U / of D^N | Eq. 15's minimum | held-out AUC [interval] | weighting | train time |",
                          "|---|---|---|---|---|---|---|---|---|---|"]
                labels = dict(_algorithms(run, {j["algorithm"] for j in run["jobs"]}))
                for j in run["jobs"]:
                    secs = f"{j['seconds'] / 60:.1f} min" if j.get("seconds") else "—"
                    lines.append(f"| {labels[j['algorithm']]} | {j['seed']} | "
                                 f"`{json.dumps(j['config'])}` | {j['status']} | {_weighting_cells(j)} | {secs} |")
        lines.append("")
    return "\n".join(lines)
