//! SafeDICE (Jang et al., NeurIPS 2023), Algorithm 1 of the paper, top to bottom:
//!
//! 1. pretrain the discriminator `c(s, a)` on D^N against D^U (Eq. 9), then freeze it;
//! 2. set α to alpha-hat, Eq. 15: the paper's minimum over every sample of D^U, or (the service
//!    default) the mixture proportion estimated on held-out episodes ([`mixture`]), falling back
//!    to uniform weights (BC) when the held-out data cannot tell D^N from D^U;
//! 3. compute the reward of Eq. 10 for every row of D^U once (the discriminator is frozen);
//! 4. each iteration, update ν by Eq. 36 and the policy by the weighted BC of Eq. 37, both on the
//!    same minibatch and with the pre-update ν.
//!
//! Where the paper is silent we follow the authors' code: the discriminator's interpolated
//! gradient penalty, ν's zero-centred one, the clipping margins of alpha-hat. Our additions are
//! options ([`TerminalHandling`](crate::algo::TerminalHandling), reward standardisation, the
//! alpha-hat quantile diagnostic) with the faithful behaviour available through the presets.
//! docs/algorithm.md lists every choice and where it departs from the paper.
//!
//! Files, from the paper down to the machine:
//! - [`objectives`]: the equations (9, 10, 15, 36, 37), each written once;
//! - [`mixture`]: alpha-hat as mixture proportion estimation (Best Bin Estimation), the held-out
//!   AUC and the discriminator's recalibration; `cross_fit`, the option that scores every row
//!   of D^U with a discriminator that never trained on it; [`kept_share`], whether Eq. 10's
//!   weights remove D^N's rows at all (the uniform fallback's test of the weighting itself);
//!   `pooling`, the option that scores each row by its episode's mean logit;
//! - [`draws`]: the flow table of step 3 and the minibatches both phases draw;
//! - [`trainer`]: Algorithm 1 as a [`crate::algo::Trainer`], the reference in candle autograd,
//!   with its steps 2-3 and the uniform fallback in `weighting`;
//! - [`fused`]: the same two hot loops with hand-derived gradients on the CPU engine, and
//!   [`fused_steps`], which runs the trainer's steps on it;
//! - [`ablation`]: the benchmark's replacements for alpha-hat and the discriminator, and
//!   `diagnostics`, what its report reads off a trained run (Eq. 12's weights on all of D^U).

pub mod ablation;
pub mod bin_by_episode;
pub mod config;
mod cross_fit;
mod diagnostics;
pub mod draws;
mod folds;
pub mod fused;
mod fused_steps;
pub mod heldout;
pub mod kept_share;
pub mod mixture;
pub mod objectives;
mod pooling;
pub mod trainer;
mod weighting;

/// FLOPs of one main-loop iteration: ν trained on s, s' and s0 (3B rows) with its gradient
/// penalty on 2B interpolated rows, and the policy trained on B.
pub fn step_flops(shape: &super::flops::StepShape) -> u64 {
    use super::flops::{penalty_flops, train_flops};
    let (b, nu) = (shape.batch, shape.state_critic(0));
    train_flops(&nu, 3 * b) + penalty_flops(&nu, 2 * b) + train_flops(&shape.policy(), b)
}

/// FLOPs of one discriminator step: trained on B rows of D^U and B of D^N, with its gradient
/// penalty on 2B rows.
pub fn discriminator_step_flops(shape: &super::flops::StepShape) -> u64 {
    use super::flops::{penalty_flops, train_flops};
    let (b, disc) = (shape.batch, shape.critic(0));
    train_flops(&disc, 2 * b) + penalty_flops(&disc, 2 * b)
}

/// Its share of a run's memory (`memory.rs` adds the datasets and what each parameter costs):
/// the discriminator, ν and the policy; the fused engine's workspaces, allocated once for 4B,
/// 5B and B rows; and the flow table over D^U.
pub fn memory(shape: &super::memory::MemoryShape) -> super::memory::Footprint {
    use super::hyperparams::AlgorithmConfig;
    use super::memory::{workspace_floats, Footprint, Network, F32};
    use super::TerminalHandling;
    let AlgorithmConfig::Safedice(config) = &shape.config.specific else {
        unreachable!("the registry asks SafeDICE's memory for SafeDICE runs only")
    };
    let (d, a, b) = (shape.obs_dim(), shape.action_width(), shape.batch());
    let absorbing = config.terminal_handling == TerminalHandling::Absorbing;
    let disc = shape.critic(0);
    let nu = Network { dims: shape.net(d + u64::from(absorbing), 1), last_bias: false };
    let policy = Network::policy(shape);
    // The flow table: next states (built through a 2N concatenation), or with `absorbing` both
    // observation tables again with the flag column; the reward and discount columns; the
    // discriminator's scores and the rewards in f64 while alpha-hat is computed.
    let n_u = shape.unlabeled.transitions;
    let flow_obs = if absorbing { 4 * (d + 1) } else { 3 * d };
    let mut data = n_u * (F32 * (flow_obs + 3) + 3 * 8);
    if config.cross_fit {
        // The folds' row lists, the finished parts' scores and the last's, one each per row of
        // D^U; and the finished parts' discriminators, kept for the safety head.
        let finished_parts = u64::from(config.cross_fit_folds.max(2)) - 1;
        data += n_u * 3 * F32 + finished_parts * F32 * disc.parameters();
        if config.cross_fit_labeled || config.cross_fit_folds > 2 {
            // D^N's folds and the parts' scores on them, one each per row of D^N.
            data += shape.non_preferred.map_or(0, |n| n.transitions) * 3 * F32;
        }
    }
    let workspaces = workspace_floats(&disc.dims, 4 * b)
        + workspace_floats(&nu.dims, 5 * b)
        + workspace_floats(&policy.dims, b);
    // The minibatch gathered as tensors and copied to the host.
    let gathered = 2 * b * (3 * (d + a) + 4 * d + 2 * a + 8);
    Footprint { networks: vec![disc, nu, policy], step: F32 * (workspaces + gathered), data }
}

#[cfg(test)]
mod tests;

pub use ablation::{oracle_logits, SafediceOverrides, ORACLE_PROB_FLOOR};
pub use objectives::{
    alpha_hat_from_logits, discriminator_loss, nu_loss, policy_loss, reward_from_logit, AlphaHat,
};
pub use trainer::SafediceTrainer;
