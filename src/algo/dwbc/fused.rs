//! DWBC's discriminator step (Eq. 38 with its interpolated gradient penalty) on the fused CPU
//! engine, as [`crate::algo::safedice::fused`] does SafeDICE's: [`super::objectives`] writes the loss once as
//! candle tensor code (the reference, checked against this in the tests), this file computes it
//! with a hand-derived gradient and reused buffers. The policy step is the shared
//! [`super::fused_policy`] one.
//!
//! Eq. 38 on logits clipped to `±ln 9` (zero gradient outside): `η·mean softplus(−x_N) +
//! mean softplus(x_U) − η·mean softplus(x_N)`. Since `d/dx [softplus(−x) − softplus(x)] = −1`,
//! a D^N row's gradient is `−η/B` inside the clip and a D^U row's `σ(x_U)/B`.

use candle_core::Result;

use super::objectives::LOGIT_CLIP;
use crate::algo::fused_mlp::{EngineThreads, FusedMlp, TrainingWorkspace};
use crate::algo::fused_ops::{interpolate_rows, sigmoid_f32, softplus_f32, unit_penalty_and_grad};
use crate::algo::mlp::Mlp;

/// One discriminator step's inputs: `B` rows of D^N and of D^U (`cat(s, a, log π)`), and the
/// penalty's interpolation weights (`u·x_N + (1−u)·x_U`; None without a penalty).
pub struct DwbcDiscBatch<'a> {
    pub x_n: &'a [f32],
    pub x_u: &'a [f32],
    pub penalty: Option<&'a [f32]>,
    /// λ of the penalty.
    pub penalty_coef: f32,
    /// η of Eq. 38.
    pub eta: f32,
}

/// A fused copy of DWBC's discriminator with its buffers.
pub struct FusedDwbcDisc {
    net: FusedMlp,
    ws: TrainingWorkspace,
    /// The last step's gradient, flat in [`FusedMlp`] order.
    pub grads: Vec<f32>,
    /// The last step's D^U logits (before clipping), for Eq. 39's weights.
    pub logits_u: Vec<f32>,
}

impl FusedDwbcDisc {
    /// Buffers for batch size `batch`, steps on the job's `threads`.
    pub fn new(disc: &Mlp, batch: usize, threads: &EngineThreads) -> Result<Self> {
        let net = disc.to_fused()?;
        Ok(Self {
            ws: TrainingWorkspace::new(net.shape(), 3 * batch, threads),
            grads: vec![0.0; net.num_params()],
            logits_u: vec![0.0; batch],
            net,
        })
    }

    /// Eq. 38 plus `λ mean((‖∇ₓc(x̂)‖ − 1)²)`: the total loss, its gradient into
    /// [`Self::grads`] (parameters copied from `disc` first).
    pub fn grads(&mut self, disc: &Mlp, batch: &DwbcDiscBatch) -> Result<f32> {
        disc.copy_into_fused(&mut self.net)?;
        let d = self.net.shape().input();
        let b = batch.x_n.len() / d;
        let input = self.ws.input_mut();
        input[..b * d].copy_from_slice(batch.x_n);
        input[b * d..2 * b * d].copy_from_slice(batch.x_u);
        let penalty_rows = match batch.penalty {
            Some(u) => {
                interpolate_rows(&mut input[2 * b * d..3 * b * d], batch.x_n, batch.x_u, u, d);
                b
            }
            None => 0,
        };
        let (eta, lambda, clip) = (batch.eta, batch.penalty_coef, LOGIT_CLIP as f32);
        let logits_u = &mut self.logits_u;
        let mut loss = 0.0;
        self.grads.fill(0.0);
        let penalty = self.ws.train_pass(
            &self.net,
            (2 * b, penalty_rows),
            &mut self.grads,
            |out, dout| {
                let inv_b = 1.0 / b as f32;
                let inside = |c: f32| if c.abs() <= clip { 1.0 } else { 0.0 };
                for i in 0..b {
                    let (c_n, c_u) = (out[i], out[b + i]);
                    let (x_n, x_u) = (c_n.clamp(-clip, clip), c_u.clamp(-clip, clip));
                    loss += (eta * (softplus_f32(-x_n) - softplus_f32(x_n)) + softplus_f32(x_u))
                        * inv_b;
                    dout[i] = -eta * inv_b * inside(c_n);
                    dout[b + i] = sigmoid_f32(x_u) * inv_b * inside(c_u);
                    logits_u[i] = c_u;
                }
            },
            |g, dp| unit_penalty_and_grad(g, dp, d, lambda),
        );
        Ok(loss + lambda * penalty)
    }

    /// Eq. 39's weights `1 − σ(clip(c_U))` of the last step (constants to the policy step).
    pub fn preference_weights(&self) -> Vec<f32> {
        let clip = LOGIT_CLIP as f32;
        self.logits_u.iter().map(|&c| 1.0 - sigmoid_f32(c.clamp(-clip, clip))).collect()
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    use super::*;
    use crate::algo::dwbc::objectives::{negative_unlabeled_loss, preference_weights};
    use crate::algo::losses::{interpolate, unit_gradient_penalty};

    /// Loss, gradient and weights against candle autograd on [`super::objectives`]' formulation, with some
    /// logits outside the clip (inputs scaled up so the clip is reached).
    #[test]
    fn discriminator_step_matches_candle_autograd() {
        let (b, d) = (16, 6);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let disc =
            Mlp::new("discriminator", &[d, 12, 10, 1], false, &Device::Cpu, &mut rng).unwrap();
        let mut normals = |n: usize, scale: f32| -> Vec<f32> {
            (0..n).map(|_| scale * rng.sample::<f32, _>(StandardNormal)).collect()
        };
        let (x_n, x_u) = (normals(b * d, 4.0), normals(b * d, 4.0));
        let u: Vec<f32> = normals(b, 1.0).iter().map(|v| v.abs().min(1.0)).collect();
        for shards in [1, 2] {
            let threads = EngineThreads::new(shards, shards).unwrap();
            check_against_candle(
                &disc,
                FusedDwbcDisc::new(&disc, b, &threads).unwrap(),
                &x_n,
                &x_u,
                &u,
            );
        }
    }

    fn check_against_candle(
        disc: &Mlp,
        mut fused: FusedDwbcDisc,
        x_n: &[f32],
        x_u: &[f32],
        u: &[f32],
    ) {
        let (b, d, eta, lambda) = (16, 6, 0.3f32, 0.1f32);
        let batch = DwbcDiscBatch { x_n, x_u, penalty: Some(u), penalty_coef: lambda, eta };
        let ours = fused.grads(disc, &batch).unwrap();

        let t = |v: &[f32]| Tensor::from_slice(v, (b, d), &Device::Cpu).unwrap();
        let (tn, tu) = (t(x_n), t(x_u));
        let logits =
            disc.forward(&Tensor::cat(&[&tn, &tu], 0).unwrap()).unwrap().squeeze(1).unwrap();
        let (c_n, c_u) = (logits.narrow(0, 0, b).unwrap(), logits.narrow(0, b, b).unwrap());
        let clipped =
            c_u.to_vec1::<f32>().unwrap().iter().filter(|c| c.abs() > LOGIT_CLIP as f32).count();
        assert!(clipped > 0, "some logits are clipped");
        let mix = Tensor::from_slice(u, (b, 1), &Device::Cpu).unwrap();
        let penalty = unit_gradient_penalty(disc, &interpolate(&tn, &tu, &mix).unwrap()).unwrap();
        let loss = (negative_unlabeled_loss(&c_n, &c_u, eta as f64).unwrap()
            + (penalty * lambda as f64).unwrap())
        .unwrap();
        let theirs = loss.to_scalar::<f32>().unwrap();
        assert!((ours - theirs).abs() <= 1e-5 * theirs.abs().max(1.0), "{ours} vs {theirs}");
        let store = loss.backward().unwrap();
        let grads = disc.grads_from_fused(&fused.grads).unwrap();
        for ((name, var), g) in disc.named_vars().iter().zip(grads) {
            let ours = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let theirs = store.get(var.as_tensor()).unwrap().flatten_all().unwrap();
            let theirs = theirs.to_vec1::<f32>().unwrap();
            let scale = theirs.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
            for (i, (a, b)) in ours.iter().zip(&theirs).enumerate() {
                assert!((a - b).abs() <= 1e-5 * scale, "{name}[{i}]: fused {a}, candle {b}");
            }
        }
        let weights = preference_weights(&c_u).unwrap().to_vec1::<f32>().unwrap();
        for (a, b) in fused.preference_weights().iter().zip(&weights) {
            assert!((a - b).abs() <= 1e-6, "weight {a} vs {b}");
        }
    }
}
