//! The tables and minibatches of SafeDICE's two phases: the flow table the ν step samples from
//! (D^U with the Eq. 10 reward and each row's discount, per [`TerminalHandling`]), and the
//! minibatches each step draws once from the run's RNG, whichever engine runs it.

use candle_core::{DType, Tensor};
use rand::Rng;

use crate::algo::columns::{ActionColumn, Columns};
use crate::algo::hyperparams::SafediceConfig;
use crate::algo::TerminalHandling;

/// The table the ν step samples from: D^U's rows with the reward and the per-row discount that
/// the terminal handling dictates (plus absorbing-state rows for `absorbing`).
pub(super) struct FlowColumns {
    pub(super) obs: Tensor,
    pub(super) next_obs: Tensor,
    /// γ, or γ(1 − done) with `mask` (`M`).
    pub(super) discount: Tensor,
    /// Eq. 10 reward, standardised if asked (`M`).
    pub(super) reward: Tensor,
    /// Rows of the initial-state set p0.
    pub(super) starts: Vec<u32>,
    /// Rows `0..real_rows` are D^U; the rest are absorbing-state rows (no action).
    pub(super) real_rows: usize,
    pub(super) rows: usize,
}

impl FlowColumns {
    /// `b` rows of the flow table and `b` initial states of p0, both uniform with replacement.
    pub(super) fn sample_batch(&self, rng: &mut impl Rng, b: usize) -> (Vec<u32>, Vec<u32>) {
        let rows = (0..b).map(|_| rng.random_range(0..self.rows as u32)).collect();
        let initial = (0..b).map(|_| self.starts[rng.random_range(0..self.starts.len())]).collect();
        (rows, initial)
    }

    /// The policy's rows for flow rows `rows`: D^U rows as they are, absorbing-state rows (only
    /// with `absorbing`; they carry no action) replaced by a placeholder row and reported in the
    /// mask (None when every row has an action).
    pub(super) fn policy_rows(&self, rows: &[u32]) -> (Vec<u32>, Option<Vec<bool>>) {
        let real = self.real_rows as u32;
        let has_action: Vec<bool> = rows.iter().map(|&r| r < real).collect();
        let policy_rows = rows.iter().map(|&r| r.min(real - 1)).collect();
        (policy_rows, has_action.contains(&false).then_some(has_action))
    }

    pub(super) fn build(
        u: &Columns,
        rewards: Vec<f32>,
        cfg: &SafediceConfig,
    ) -> candle_core::Result<FlowColumns> {
        let device = u.obs.device();
        let n = u.len;
        let gamma = cfg.gamma as f32;
        let terminal_rows: Vec<usize> = (0..n).filter(|&i| u.terminals[i]).collect();
        // Without terminal rows there is nothing to absorb: the flow is D^U as it is.
        let handling = match cfg.terminal_handling {
            TerminalHandling::Absorbing if terminal_rows.is_empty() => TerminalHandling::None,
            other => other,
        };
        let (obs, next_obs, rows, reward, discount) = match handling {
            TerminalHandling::None | TerminalHandling::Mask => {
                let discount: Vec<f32> = match handling {
                    TerminalHandling::Mask => {
                        u.terminals.iter().map(|&t| if t { 0.0 } else { gamma }).collect()
                    }
                    _ => vec![gamma; n],
                };
                (u.obs.clone(), u.next_obs.clone(), n, rewards, discount)
            }
            TerminalHandling::Reset => {
                // Row i of cat(next_obs, obs) for a non-terminal row, its episode's start otherwise.
                let source: Vec<u32> = (0..n)
                    .map(|i| if u.terminals[i] { (n as u32) + u.start_of_row[i] } else { i as u32 })
                    .collect();
                let both = Tensor::cat(&[&u.next_obs, &u.obs], 0)?;
                let next = both.index_select(&Tensor::from_vec(source, n, device)?, 0)?;
                (u.obs.clone(), next, n, rewards, vec![gamma; n])
            }
            TerminalHandling::Absorbing => {
                let k = terminal_rows.len();
                let flag = |rows: usize, value: f32| Tensor::full(value, (rows, 1), device);
                let absorbing_state = Tensor::cat(
                    &[Tensor::zeros((1, u.obs_dim), DType::F32, device)?, flag(1, 1.0)?],
                    1,
                )?;
                let absorbing = absorbing_state.broadcast_as((k, u.obs_dim + 1))?.contiguous()?;
                let obs = Tensor::cat(
                    &[Tensor::cat(&[&u.obs, &flag(n, 0.0)?], 1)?, absorbing.clone()],
                    0,
                )?;
                let real_next = Tensor::cat(&[&u.next_obs, &flag(n, 0.0)?], 1)?;
                // Terminal rows lead to the absorbing state; absorbing rows loop on it.
                let source: Vec<u32> =
                    (0..n).map(|i| if u.terminals[i] { n as u32 } else { i as u32 }).collect();
                let both = Tensor::cat(&[&real_next, &absorbing_state], 0)?;
                let next_real = both.index_select(&Tensor::from_vec(source, n, device)?, 0)?;
                let next = Tensor::cat(&[next_real, absorbing], 0)?;
                let mut reward = rewards;
                reward.extend(std::iter::repeat_n(0.0, k));
                (obs, next, n + k, reward, vec![gamma; n + k])
            }
        };
        Ok(FlowColumns {
            obs: obs.contiguous()?,
            next_obs: next_obs.contiguous()?,
            discount: Tensor::from_vec(discount, rows, device)?,
            reward: Tensor::from_vec(reward, rows, device)?,
            starts: u.episode_starts.clone(),
            real_rows: n,
            rows,
        })
    }
}

/// One discriminator step's minibatch, drawn once from the run's RNG for whichever engine runs
/// the step.
pub(super) struct DiscDraws {
    /// `cat(s, a)` of `B` rows of D^N and of D^U.
    pub x_n: Tensor,
    pub x_u: Tensor,
    /// `(u1, u2, perm)` of the penalty's points `u1 x_N + (1−u1) x_U` and
    /// `u2 x_U[perm] + (1−u2) x_U` (`B × 1` each); None without a penalty.
    pub penalty: Option<(Tensor, Tensor, Vec<u32>)>,
}

/// One main-loop iteration's minibatch, drawn once from the run's RNG for whichever engine runs
/// the step.
pub(super) struct MainDraws {
    /// `s`, `s'` of `B` flow rows and `B` initial states `s0`.
    pub s: Tensor,
    pub s_next: Tensor,
    pub s0: Tensor,
    /// Eq. 10 reward and γ' of the same rows.
    pub reward: Tensor,
    pub discount: Tensor,
    /// ν's penalty: interpolation weights `u` (`B × 1`) of the points `u s0 + (1−u) s` and
    /// `u s' + (1−u) s`; None without a penalty.
    pub penalty_u: Option<Tensor>,
    /// The policy's observations and dataset actions (D^U rows).
    pub policy_obs: Tensor,
    pub actions: ActionColumn,
    /// Rows with an action (all but absorbing-state rows); None when all have one.
    pub has_action: Option<Vec<bool>>,
}
