//! FLOP counts of one training step, for the speed benchmark's fraction of peak and for
//! ordering work by cost. Matrix products only: element-wise work and Adam are not counted.
//! Each algorithm's module says what its step trains (its `step_flops`), on the shapes here;
//! the registry points at it.

use super::fused_mlp::MlpShape;

/// The sizes a step's networks are built from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StepShape {
    pub obs_dim: usize,
    /// The action as a network input: its width, or the number of actions (one-hot).
    pub act_input: usize,
    /// The policy head's width: 2 × the action width (mean and log-std), or the number of actions.
    pub policy_output: usize,
    pub hidden: Vec<usize>,
    pub batch: usize,
}

impl StepShape {
    /// The policy: observations to its head.
    pub fn policy(&self) -> MlpShape {
        MlpShape::new(self.obs_dim, &self.hidden, self.policy_output, true)
    }

    /// A scalar critic of the observation and `extra` more columns (SafeDICE's ν: 0).
    pub fn state_critic(&self, extra: usize) -> MlpShape {
        MlpShape::new(self.obs_dim + extra, &self.hidden, 1, false)
    }

    /// A scalar critic of the state-action and `extra` more columns (a discriminator, a reward
    /// model).
    pub fn critic(&self, extra: usize) -> MlpShape {
        MlpShape::new(self.obs_dim + self.act_input + extra, &self.hidden, 1, false)
    }
}

fn linear_flops(rows: usize, din: usize, dout: usize) -> u64 {
    2 * (rows * din * dout) as u64
}

/// The forward of `rows` rows.
pub fn forward_flops(shape: &MlpShape, rows: usize) -> u64 {
    shape.forward_flops_per_row() * rows as u64
}

/// Forward, weight gradients, and input gradients of every layer but the first.
pub fn train_flops(shape: &MlpShape, rows: usize) -> u64 {
    let dx: u64 = shape.dims[1..].windows(2).map(|w| linear_flops(rows, w[0], w[1])).sum();
    2 * forward_flops(shape, rows) + dx
}

/// A scalar critic's gradient penalty: forward, input-gradient through the hidden layers, and
/// the backward of that input-gradient (a weight gradient and a delta gradient per hidden layer).
pub fn penalty_flops(shape: &MlpShape, rows: usize) -> u64 {
    let hidden_layers = &shape.dims[..shape.dims.len() - 1];
    let input_grad: u64 = hidden_layers.windows(2).map(|w| linear_flops(rows, w[0], w[1])).sum();
    forward_flops(shape, rows) + 3 * input_grad
}
