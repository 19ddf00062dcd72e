#!/usr/bin/env python3
"""PyTorch CPU reference for `safedice speed`: the same two workloads, the same shapes.

Workloads (docs/performance.md defines them; src/bench/speed.rs times them in the trainer):
  main loop      one SafeDICE iteration with the discriminator frozen (rewards precomputed):
                 nu on cat(s, s', s0) (Eq. 36, log-mean-exp of A plus (1-gamma) mean nu(s0)),
                 zero-centred nu gradient penalty on 2B interpolated states, Adam step on nu;
                 policy step Eq. 37 (softmax(A) weights, detached), Adam step on the policy.
  discriminator  one step of Eq. 9: logits on cat(x_N, x_U), softplus losses, gradient penalty
                 lambda * mean((|grad_x c(x_hat)| - 1)^2) on 2B interpolates (double backprop),
                 Adam step.
Usage: python bench/pytorch_reference.py --obs-dim 17 --act-dim 6 --batch 512 --iters 200 --threads 1
       (--device cuda: the same steps on a GPU; losses stay on the device and each timed run ends
       with a synchronize, so the rate is the GPU's, not one host round trip per step)
"""
import argparse
import math
import statistics
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

GAMMA = 0.99
DISC_GP = 10.0
NU_GP = 1e-6
NORM_EPS = 1e-12  # inside sqrt of the gradient norm, as losses::GRAD_NORM_EPS in src/algo
ATANH_EPS = 1e-6


def mlp(inp, hidden, out, last_bias):
    layers, d = [], inp
    for h in hidden:
        layers += [nn.Linear(d, h), nn.ReLU()]
        d = h
    layers.append(nn.Linear(d, out, bias=last_bias))
    return nn.Sequential(*layers)


def flops_linear(rows, din, dout):
    return 2 * rows * din * dout


def mlp_fwd_flops(rows, dims):
    return sum(flops_linear(rows, a, b) for a, b in zip(dims[:-1], dims[1:]))


def mlp_train_flops(rows, dims):
    """forward + weight gradients + input gradients of every layer but the first."""
    f = mlp_fwd_flops(rows, dims)
    dx = sum(flops_linear(rows, a, b) for a, b in zip(dims[1:-1], dims[2:]))
    return f + f + dx


def gp_flops(rows, dims):
    """Scalar-output MLP: forward, input-gradient, and its backward to all weights."""
    fwd = mlp_fwd_flops(rows, dims)
    inp_grad = sum(flops_linear(rows, a, b) for a, b in zip(dims[:-2], dims[1:-1]))
    # backward of the input-gradient: per hidden layer a weight gradient and a delta gradient
    back = 2 * inp_grad
    return fwd + inp_grad + back


def count_flops(obs_dim, act_in, policy_out, batch, hidden):
    nu_dims = [obs_dim] + hidden + [1]
    disc_dims = [obs_dim + act_in] + hidden + [1]
    pi_dims = [obs_dim] + hidden + [policy_out]
    main = mlp_train_flops(3 * batch, nu_dims) + gp_flops(2 * batch, nu_dims) + mlp_train_flops(batch, pi_dims)
    disc = mlp_train_flops(2 * batch, disc_dims) + gp_flops(2 * batch, disc_dims)
    return main, disc


class Bench:
    def __init__(self, a):
        g = torch.Generator().manual_seed(a.seed)
        self.a = a
        n_u, n_n, n_0 = 20000, 4000, 200
        self.discrete = a.discrete > 0
        act_in = a.discrete if self.discrete else a.act_dim
        self.s = torch.randn(n_u, a.obs_dim, generator=g)
        self.s2 = torch.randn(n_u, a.obs_dim, generator=g)
        self.s0 = torch.randn(n_0, a.obs_dim, generator=g)
        self.r = torch.randn(n_u, generator=g)
        if self.discrete:
            self.act_idx = torch.randint(0, a.discrete, (n_u,), generator=g)
            self.act = F.one_hot(self.act_idx, a.discrete).float()
            nact = F.one_hot(torch.randint(0, a.discrete, (n_n,), generator=g), a.discrete).float()
        else:
            self.act = torch.rand(n_u, a.act_dim, generator=g) * 2 - 1
            self.act[::7] = 1.0  # dataset actions often sit exactly on the bound
            nact = torch.rand(n_n, a.act_dim, generator=g) * 2 - 1
        self.x_u = torch.cat([self.s, self.act], 1)
        self.x_n = torch.cat([torch.randn(n_n, a.obs_dim, generator=g), nact], 1)
        hidden = [a.hidden] * 2
        self.policy_out = a.discrete if self.discrete else 2 * a.act_dim
        self.dev = torch.device(a.device)
        for name in ["s", "s2", "s0", "r", "act", "x_u", "x_n"] + (["act_idx"] if self.discrete else []):
            setattr(self, name, getattr(self, name).to(self.dev))
        self.nu = mlp(a.obs_dim, hidden, 1, False).to(self.dev)
        self.pi = mlp(a.obs_dim, hidden, self.policy_out, True).to(self.dev)
        self.disc = mlp(a.obs_dim + act_in, hidden, 1, False).to(self.dev)
        self.opt_nu = torch.optim.Adam(self.nu.parameters(), lr=1e-4)
        self.opt_pi = torch.optim.Adam(self.pi.parameters(), lr=1e-5)
        self.opt_d = torch.optim.Adam(self.disc.parameters(), lr=1e-4)
        self.flops = count_flops(a.obs_dim, act_in, self.policy_out, a.batch, hidden)

    def log_prob(self, out, idx):
        if self.discrete:
            return F.log_softmax(out, -1).gather(1, self.act_idx[idx].unsqueeze(1)).squeeze(1)
        d = self.a.act_dim
        mean = out[:, :d].clamp(-7.0, 7.0)
        log_std = out[:, d:].clamp(-5.0, 2.0)
        act = self.act[idx]
        u = torch.atanh(act.clamp(-1 + ATANH_EPS, 1 - ATANH_EPS))
        z = (u - mean) * torch.exp(-log_std)
        gauss = (-0.5 * z * z - log_std - 0.5 * math.log(2 * math.pi)).sum(1)
        return gauss - torch.log(1 - act * act + ATANH_EPS).sum(1)

    def main_iteration(self):
        b = self.a.batch
        idx = torch.randint(0, self.s.shape[0], (b,), device=self.dev)
        idx0 = torch.randint(0, self.s0.shape[0], (b,), device=self.dev)
        s, s2, s0, r = self.s[idx], self.s2[idx], self.s0[idx0], self.r[idx]
        v = self.nu(torch.cat([s, s2, s0], 0)).squeeze(1)
        v_s, v_s2, v_0 = v[:b], v[b:2 * b], v[2 * b:]
        adv = r + GAMMA * v_s2 - v_s  # Eq. 36 (no terminal mask, as the authors)
        nu_loss = torch.logsumexp(adv, 0) - math.log(b) + (1 - GAMMA) * v_0.mean()
        u = torch.rand(b, 1, device=self.dev)  # shared by both point sets, as src/algo/safedice/draws.rs
        x_hat = torch.cat([u * s0 + (1 - u) * s, u * s2 + (1 - u) * s], 0)
        x_hat.requires_grad_(True)
        g = torch.autograd.grad(self.nu(x_hat).sum(), x_hat, create_graph=True)[0]
        nu_loss = nu_loss + NU_GP * (g * g).sum(1).mean()
        w = torch.softmax(adv.detach(), 0)  # Eq. 37: exp(A - 1) / sum, stable
        pi_loss = -(w * self.log_prob(self.pi(s), idx)).sum()
        self.opt_nu.zero_grad(set_to_none=True)
        self.opt_pi.zero_grad(set_to_none=True)
        (nu_loss + pi_loss).backward()
        self.opt_nu.step()
        self.opt_pi.step()
        return nu_loss.detach(), pi_loss.detach()

    def disc_step(self):
        b = self.a.batch
        xn = self.x_n[torch.randint(0, self.x_n.shape[0], (b,), device=self.dev)]
        xu = self.x_u[torch.randint(0, self.x_u.shape[0], (b,), device=self.dev)]
        c = self.disc(torch.cat([xn, xu], 0)).squeeze(1)
        loss = F.softplus(-c[:b]).mean() + F.softplus(c[b:]).mean()  # Eq. 9
        u = torch.rand(2 * b, 1, device=self.dev)
        x_hat = u * torch.cat([xn, xu[torch.randperm(b, device=self.dev)]], 0) + (1 - u) * torch.cat([xu, xu], 0)
        x_hat.requires_grad_(True)
        g = torch.autograd.grad(self.disc(x_hat).sum(), x_hat, create_graph=True)[0]
        norm = torch.sqrt((g * g).sum(1) + NORM_EPS)
        loss = loss + DISC_GP * ((norm - 1) ** 2).mean()
        self.opt_d.zero_grad(set_to_none=True)
        loss.backward()
        self.opt_d.step()
        return loss.detach()


def time_it(fn, iters, warmup, repeats, sync):
    for _ in range(warmup):
        fn()
    sync()
    rates, cpu_rates = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        for _ in range(iters):
            fn()
        sync()
        rates.append(iters / (time.perf_counter() - t))
        cpu_rates.append(iters / max(time.process_time() - c, 0.01))
    return statistics.median(rates), rates, statistics.median(cpu_rates)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--obs-dim", type=int, default=17)
    p.add_argument("--act-dim", type=int, default=6)
    p.add_argument("--discrete", type=int, default=0)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--iters", type=int, default=200)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="cpu, or cuda for a GPU")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    bench = Bench(a)
    main_flops, disc_flops = bench.flops
    sync = torch.cuda.synchronize if bench.dev.type == "cuda" else (lambda: None)
    where = torch.cuda.get_device_name(bench.dev) if bench.dev.type == "cuda" else "cpu"
    print(f"pytorch {torch.__version__}, {where}, threads {torch.get_num_threads()}, batch {a.batch}, "
          f"hidden [{a.hidden}, {a.hidden}], obs {a.obs_dim}, "
          + (f"discrete {a.discrete}" if a.discrete else f"act {a.act_dim}"))
    for name, fn, flops, unit in [("main loop", bench.main_iteration, main_flops, "iterations/s"),
                                  ("discriminator", bench.disc_step, disc_flops, "steps/s")]:
        med, rates, cpu = time_it(fn, a.iters, warmup=max(5, a.iters // 10), repeats=a.repeats, sync=sync)
        print(f"{name:14} {med:8.1f} {unit:13} (runs {', '.join(f'{x:.1f}' for x in rates)}; "
              f"per CPU-second {cpu:.1f})  "
              f"{flops / 1e6:7.1f} MFLOP each  {med * flops / 1e9:6.1f} GFLOP/s")


if __name__ == "__main__":
    main()
