#!/usr/bin/env python3
"""How a server's training jobs share its cores: the CPU its process uses and the threads it runs.

Starts `safedice serve` (a fresh data directory, a free port) with the given flags, uploads a
synthetic dataset (obs 17, 6-dim actions), queues `--jobs` SafeDICE jobs at batch 512, hidden
[256, 256] (with `threads` unset: the server's default, or `--threads`), waits until they run,
then samples the server process for `--seconds`: CPU seconds per wall second (cores busy) and
the compute threads running (the job's engine pools, `safedice-engine-*`, and the workers'
training threads). Prints one line per sample and a summary.

    python3 bench/threads_sharing.py --serve-args "--workers 2" --jobs 2
    python3 bench/threads_sharing.py --serve-args "--workers 1" --jobs 2
    python3 bench/threads_sharing.py --serve-args "--workers 1 --job-threads 1" --jobs 1 --threads 4
"""
import argparse
import os
import shlex
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "clients" / "python" / "src"))
from safedice_client import Client  # noqa: E402

TICKS = os.sysconf("SC_CLK_TCK")


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def dataset(rows, episode, seed):
    rng = np.random.default_rng(seed)
    obs = rng.standard_normal((rows, 17)).astype(np.float32)
    terminals = np.zeros(rows, dtype=bool)
    timeouts = np.zeros(rows, dtype=bool)
    timeouts[episode - 1::episode] = True
    nxt = np.roll(obs, -1, axis=0)
    return {
        "observations": obs,
        "next_observations": nxt,
        "actions": np.tanh(rng.standard_normal((rows, 6))).astype(np.float32) * 0.9,
        "rewards": rng.standard_normal(rows).astype(np.float32),
        "costs": rng.random(rows).astype(np.float32),
        "terminals": terminals,
        "timeouts": timeouts,
    }


def cpu_seconds(pid):
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def running_threads(pid):
    """Threads of the process in state R, by name."""
    names = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        state = stat.rsplit(")", 1)[1].split()[0]
        if state == "R":
            key = "engine" if name.startswith("safedice-engin") else name
            names[key] = names.get(key, 0) + 1
    return names


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--bin", default="target/release/safedice")
    p.add_argument("--serve-args", default="--workers 2")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--threads", type=int, default=None, help="the jobs' `threads` (default: unset)")
    p.add_argument("--seconds", type=float, default=20)
    args = p.parse_args()
    data_dir = tempfile.mkdtemp(prefix="threads-sharing-")
    port = free_port()
    cmd = [args.bin, "serve", "--bind", f"127.0.0.1:{port}", "--data-dir", data_dir,
           *shlex.split(args.serve_args)]
    server = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        client = Client(f"http://127.0.0.1:{port}")
        for _ in range(100):
            try:
                client.algorithms()
                break
            except Exception:
                time.sleep(0.1)
        u = client.upload_dataset(dataset(20_000, 100, 0), name="u", role="unlabeled")
        n = client.upload_dataset(dataset(2_000, 100, 1), name="n", role="non_preferred")
        config = {"iterations": 1_000_000, "hidden_sizes": [256, 256], "batch_size": 512}
        if args.threads:
            config["threads"] = args.threads
        jobs = [client.submit_job(u["id"], n["id"], algorithm="safedice", config=dict(config, seed=i))
                for i in range(args.jobs)]
        threads = [j["config"]["threads"] for j in jobs]
        while not any(client.job(j["id"])["status"] == "running" for j in jobs):
            time.sleep(0.5)
        time.sleep(5)  # every free worker has claimed, past the start (data loading)
        print(f"$ safedice serve {args.serve_args}; {args.jobs} job(s), threads {threads}, "
              f"{os.cpu_count()} cores")
        busy, samples = [], []
        t0, c0 = time.time(), cpu_seconds(server.pid)
        end = t0 + args.seconds
        while time.time() < end:
            time.sleep(1)
            t1, c1 = time.time(), cpu_seconds(server.pid)
            busy.append((c1 - c0) / (t1 - t0))
            samples.append(running_threads(server.pid))
            t0, c0 = t1, c1
        statuses = [client.job(j["id"])["status"] for j in jobs]
        print(f"cores busy per second: mean {np.mean(busy):.2f}, max {max(busy):.2f} "
              f"(samples {', '.join(f'{b:.2f}' for b in busy)})")
        peak = max((sum(s.values()) for s in samples), default=0)
        print(f"threads running at a sample: at most {peak}; e.g. {samples[len(samples) // 2]}")
        print(f"jobs: {statuses}")
    finally:
        server.terminate()
        server.wait(timeout=60)


if __name__ == "__main__":
    main()
