//! The fused engine against the reference: losses, weights and gradients of both hot loops
//! against candle autograd on [`super::super::objectives`]' formulation (to 1e-5, on one, two
//! and three threads: the engine's shards), the penalty's
//! second-order gradient against finite differences, and the whole trainer on its fused path
//! against its candle path, step by step.

use candle_core::backprop::GradStore;
use candle_core::{Device, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::*;
use crate::algo::columns::ActionColumn;
use crate::algo::losses::{
    interpolate, self_normalized_weights, unit_gradient_penalty, zero_gradient_penalty,
};
use crate::algo::policy::PolicyNet;
use crate::algo::safedice::{discriminator_loss, nu_loss, policy_loss};
use crate::data::ActionSpace;

const B: usize = 16;

fn normals(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.sample::<f32, _>(StandardNormal)).collect()
}

fn uniforms(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.random::<f32>()).collect()
}

fn tensor(values: &[f32], rows: usize) -> Tensor {
    Tensor::from_slice(values, (rows, values.len() / rows), &Device::Cpu).unwrap()
}

/// Fused gradients against candle autograd, parameter by parameter, to 1e-5 of the largest.
fn assert_grads_match(what: &str, net: &Mlp, fused: &[f32], store: &GradStore) {
    let ours = net.grads_from_fused(fused).unwrap();
    for ((name, var), g) in net.named_vars().iter().zip(ours) {
        let ours = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let theirs = store.get(var.as_tensor()).expect("autograd gradient");
        let theirs = theirs.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let scale = theirs.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
        for (i, (a, b)) in ours.iter().zip(&theirs).enumerate() {
            assert!((a - b).abs() <= 1e-5 * scale, "{what} {name}[{i}]: fused {a}, autograd {b}");
        }
    }
}

fn assert_close(what: &str, a: f32, b: f32) {
    assert!((a - b).abs() <= 1e-5 * b.abs().max(1.0), "{what}: fused {a}, candle {b}");
}

/// A job's threads: one shard, two, and three (16 rows do not split evenly in three).
const SHARD_COUNTS: [usize; 3] = [1, 2, 3];

fn engine_threads(shards: usize) -> EngineThreads {
    EngineThreads::new(shards, shards).unwrap()
}

#[test]
fn discriminator_step_matches_candle_autograd() {
    for shards in SHARD_COUNTS {
        check_discriminator_step(shards);
    }
}

fn check_discriminator_step(shards: usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let d = 7;
    let disc = Mlp::new("discriminator", &[d, 12, 10, 1], false, &Device::Cpu, &mut rng).unwrap();
    let nu = Mlp::new("nu", &[5, 12, 10, 1], false, &Device::Cpu, &mut rng).unwrap();
    let policy = Mlp::new("policy", &[5, 12, 10, 6], true, &Device::Cpu, &mut rng).unwrap();
    let (x_n, x_u) = (normals(&mut rng, B * d), normals(&mut rng, B * d));
    let (u1, u2) = (uniforms(&mut rng, B), uniforms(&mut rng, B));
    let mut perm: Vec<u32> = (0..B as u32).collect();
    perm.reverse();
    let lambda = 10.0;
    let mut fused = FusedSafedice::new(&disc, &nu, &policy, B, &engine_threads(shards)).unwrap();
    let out = fused
        .disc_grads(
            &disc,
            &HostDiscBatch {
                x_n: &x_n,
                x_u: &x_u,
                penalty: Some((&u1, &u2, &perm)),
                penalty_coef: lambda,
            },
        )
        .unwrap();

    let (tn, tu) = (tensor(&x_n, B), tensor(&x_u, B));
    let logits = disc.forward(&Tensor::cat(&[&tn, &tu], 0).unwrap()).unwrap().squeeze(1).unwrap();
    let classification =
        discriminator_loss(&logits.narrow(0, 0, B).unwrap(), &logits.narrow(0, B, B).unwrap())
            .unwrap();
    let idx = Tensor::from_slice(&perm, B, &Device::Cpu).unwrap();
    let shuffled = tu.index_select(&idx, 0).unwrap();
    let points = Tensor::cat(
        &[
            interpolate(&tn, &tu, &tensor(&u1, B)).unwrap(),
            interpolate(&shuffled, &tu, &tensor(&u2, B)).unwrap(),
        ],
        0,
    )
    .unwrap();
    let penalty = unit_gradient_penalty(&disc, &points).unwrap();
    let loss = (&classification + (&penalty * lambda as f64).unwrap()).unwrap();
    let scalar = |t: &Tensor| t.to_scalar::<f32>().unwrap();
    assert_close("classification", out.classification, scalar(&classification));
    assert_close("penalty", out.penalty, scalar(&penalty));
    assert_close("loss", out.loss, scalar(&loss));
    assert_grads_match("discriminator", &disc, &fused.disc_grads, &loss.backward().unwrap());
}

/// `uniform_share` is `policy_uniform_share`, applied before the mask as trainer.rs does.
fn check_main_step(space: ActionSpace, masked_rows: bool, uniform_share: f32, shards: usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let (obs, gamma, lambda) = (5, 0.99f32, 0.3f32);
    let dev = Device::Cpu;
    let disc = Mlp::new("discriminator", &[9, 12, 10, 1], false, &dev, &mut rng).unwrap();
    let nu = Mlp::new("nu", &[obs, 12, 10, 1], false, &dev, &mut rng).unwrap();
    let policy = PolicyNet::new("policy", obs, &[12, 10], &space, &dev, &mut rng).unwrap();
    let (s, s_next, s0) =
        (normals(&mut rng, B * obs), normals(&mut rng, B * obs), normals(&mut rng, B * obs));
    let reward = normals(&mut rng, B);
    let discount: Vec<f32> = (0..B).map(|i| if i % 5 == 0 { 0.0 } else { gamma }).collect();
    let u = uniforms(&mut rng, B);
    let policy_obs = normals(&mut rng, B * obs);
    let has_action: Vec<bool> = (0..B).map(|i| !masked_rows || i % 4 != 1).collect();
    let (pretanh, log_jacobian) = (normals(&mut rng, B * 3), normals(&mut rng, B));
    let index: Vec<u32> = (0..B as u32).map(|i| i % 4).collect();
    let (actions, column) = match space {
        ActionSpace::Continuous { .. } => (
            HostActions::Continuous { pretanh: &pretanh, log_jacobian: &log_jacobian },
            ActionColumn::Continuous {
                pretanh: tensor(&pretanh, B),
                log_jacobian: Tensor::from_slice(&log_jacobian, B, &dev).unwrap(),
            },
        ),
        ActionSpace::Discrete { .. } => (
            HostActions::Discrete { index: &index },
            ActionColumn::Discrete { index: Tensor::from_slice(&index, B, &dev).unwrap() },
        ),
    };
    let mut fused =
        FusedSafedice::new(&disc, &nu, policy.mlp(), B, &engine_threads(shards)).unwrap();
    let out = fused
        .main_grads(
            &nu,
            policy.mlp(),
            &HostMainBatch {
                s: &s,
                s_next: &s_next,
                s0: &s0,
                reward: &reward,
                discount: &discount,
                gamma,
                penalty: Some((&u, lambda)),
                policy_obs: &policy_obs,
                actions,
                has_action: masked_rows.then_some(&has_action[..]),
                uniform_share,
            },
        )
        .unwrap();

    // The candle formulation of the trainer's main step (trainer.rs).
    let (ts, tn, t0) = (tensor(&s, B), tensor(&s_next, B), tensor(&s0, B));
    let values =
        nu.forward(&Tensor::cat(&[&ts, &tn, &t0], 0).unwrap()).unwrap().squeeze(1).unwrap();
    let (v, v_next, v0) = (
        values.narrow(0, 0, B).unwrap(),
        values.narrow(0, B, B).unwrap(),
        values.narrow(0, 2 * B, B).unwrap(),
    );
    let r = Tensor::from_slice(&reward, B, &dev).unwrap();
    let g = Tensor::from_slice(&discount, B, &dev).unwrap();
    let adv = ((r + (g * v_next).unwrap()).unwrap() - v).unwrap();
    let tu = tensor(&u, B);
    let points =
        Tensor::cat(&[interpolate(&t0, &ts, &tu).unwrap(), interpolate(&tn, &ts, &tu).unwrap()], 0)
            .unwrap();
    let penalty = zero_gradient_penalty(&nu, &points).unwrap();
    let loss_nu =
        (nu_loss(&adv, &v0, gamma as f64).unwrap() + (&penalty * lambda as f64).unwrap()).unwrap();
    let mut weights = self_normalized_weights(&adv).unwrap();
    if uniform_share > 0.0 {
        let m = uniform_share as f64;
        weights = weights.affine(1.0 - m, m).unwrap();
    }
    if masked_rows {
        let mask: Vec<f32> = has_action.iter().map(|&k| k as u8 as f32).collect();
        let masked = (weights * Tensor::from_vec(mask, B, &dev).unwrap()).unwrap();
        let mean = masked.mean_all().unwrap();
        weights = masked.broadcast_div(&(mean + 1e-12).unwrap()).unwrap();
    }
    let log_prob = policy.log_prob(&tensor(&policy_obs, B), &column).unwrap();
    let loss_pi = policy_loss(&log_prob, &weights).unwrap();
    let scalar = |t: &Tensor| t.to_scalar::<f32>().unwrap();
    assert_close("nu loss", out.nu_loss, scalar(&loss_nu));
    assert_close("nu penalty", out.nu_penalty, scalar(&penalty));
    assert_close("policy loss", out.policy_loss, scalar(&loss_pi));
    let w = weights.to_vec1::<f32>().unwrap();
    for (a, b) in fused.weights.iter().zip(&w) {
        assert_close("weight", *a, *b);
    }
    let grads = (&loss_nu + &loss_pi).unwrap().backward().unwrap();
    assert_grads_match("nu", &nu, &fused.nu_grads, &grads);
    assert_grads_match("policy", policy.mlp(), &fused.policy.grads, &grads);
}

#[test]
fn main_step_matches_candle_autograd_continuous() {
    let space = ActionSpace::Continuous { dim: 3, low: vec![-1.0; 3], high: vec![1.0; 3] };
    for shards in SHARD_COUNTS {
        check_main_step(space.clone(), false, 0.0, shards);
    }
}

#[test]
fn main_step_matches_candle_autograd_discrete_with_actionless_rows_and_a_uniform_share() {
    for shards in SHARD_COUNTS {
        check_main_step(ActionSpace::Discrete { n: 4 }, true, 0.2, shards);
    }
}

/// The penalty's weight gradient (double backprop) against central finite differences of
/// the fused loss itself, in f32 on a small net (hence the 5% tolerance; the 1e-5 check is
/// the autograd comparison above).
#[test]
fn discriminator_penalty_gradient_matches_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let (d, dev) = (7, Device::Cpu);
    let disc = Mlp::new("discriminator", &[d, 12, 10, 1], false, &dev, &mut rng).unwrap();
    let nu = Mlp::new("nu", &[5, 12, 10, 1], false, &dev, &mut rng).unwrap();
    let policy = Mlp::new("policy", &[5, 12, 10, 6], true, &dev, &mut rng).unwrap();
    let (x_n, x_u) = (normals(&mut rng, B * d), normals(&mut rng, B * d));
    let (u1, u2) = (uniforms(&mut rng, B), uniforms(&mut rng, B));
    let perm: Vec<u32> = (0..B as u32).map(|i| (i * 5 + 3) % B as u32).collect();
    let batch = HostDiscBatch {
        x_n: &x_n,
        x_u: &x_u,
        penalty: Some((&u1, &u2, &perm)),
        penalty_coef: 10.0,
    };
    let mut fused = FusedSafedice::new(&disc, &nu, &policy, B, &EngineThreads::single()).unwrap();
    let loss = |fused: &mut FusedSafedice| fused.disc_grads(&disc, &batch).unwrap().loss;
    let center = loss(&mut fused);
    let analytic = disc.grads_from_fused(&fused.disc_grads).unwrap();
    let h = 2e-3;
    let mut checked = 0;
    // Weights of layers 1, 2 and 3 (biases get no gradient from the penalty; their loss
    // gradient is covered against autograd). The input-gradient jumps where a ReLU mask
    // flips, so a difference that straddles a flip (one-sided slopes disagree) is skipped.
    for ((name, var), grad) in disc.named_vars().iter().zip(&analytic) {
        if !name.ends_with("weight") {
            continue;
        }
        let grad = grad.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let values = var.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let set = |values: &[f32]| {
            let t = Tensor::from_slice(values, var.as_tensor().dims(), &dev).unwrap();
            var.set(&t).unwrap();
        };
        for i in [0usize, 3, 7, 9] {
            let mut moved = values.clone();
            moved[i] = values[i] + h;
            set(&moved);
            let up = loss(&mut fused);
            moved[i] = values[i] - h;
            set(&moved);
            let down = loss(&mut fused);
            set(&values);
            let (right, left) = ((up - center) / h, (center - down) / h);
            if (right - left).abs() > 0.1 * right.abs().max(left.abs()).max(0.1) {
                continue;
            }
            checked += 1;
            let numeric = (up - down) / (2.0 * h);
            assert!(
                (numeric - grad[i]).abs() < 5e-2 * grad[i].abs().max(0.1),
                "{name}[{i}]: {numeric} vs {}",
                grad[i]
            );
        }
    }
    assert!(checked >= 8, "only {checked} parameters away from a ReLU kink");
}

/// The trainer's fused path and its candle autograd path draw the same batches and report
/// the same losses, step after step, through the discriminator phase, alpha-hat and the main
/// loop (they drift apart only by float rounding).
#[test]
fn trainer_fused_and_candle_paths_agree() {
    use crate::bench::speed::engines::{assert_engines_agree, tiny};
    use crate::bench::speed::synthetic_trainer;
    for discrete in [None, Some(4)] {
        let cfg = tiny(crate::algo::Algorithm::Safedice, discrete);
        let make = || -> Box<dyn crate::algo::Trainer> {
            Box::new(synthetic_trainer(&cfg, (400, 200), 4, 3).unwrap())
        };
        assert_engines_agree(&format!("SafeDICE {discrete:?}"), make, 7);
    }
}
