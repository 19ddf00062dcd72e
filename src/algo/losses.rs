//! Loss pieces shared by several algorithms: numerically safe logistic losses, the two gradient
//! penalties, self-normalised importance weights and their effective sample size.

use candle_core::{Result, Tensor, D};

use super::mlp::Mlp;

/// `softplus(x) = log(1 + eˣ)`, computed as `max(x, 0) + log(1 + e^{−|x|})` so large logits stay
/// finite (candle's `binary_cross_entropy_with_logit` goes through `log(sigmoid)` and overflows).
pub fn softplus(x: &Tensor) -> Result<Tensor> {
    x.relu()? + x.abs()?.neg()?.exp()?.affine(1.0, 1.0)?.log()?
}

/// `−log σ(x)` = softplus(−x): the loss of a logit that should say "positive".
pub fn neg_log_sigmoid(x: &Tensor) -> Result<Tensor> {
    softplus(&x.neg()?)
}

/// `−log(1 − σ(x))` = softplus(x): the loss of a logit that should say "negative".
pub fn neg_log_one_minus_sigmoid(x: &Tensor) -> Result<Tensor> {
    softplus(x)
}

/// Interpolates rows: `u·a + (1 − u)·b` with `u` a `B × 1` column.
pub fn interpolate(a: &Tensor, b: &Tensor, u: &Tensor) -> Result<Tensor> {
    (a.broadcast_mul(u)? + b.broadcast_mul(&u.affine(-1.0, 1.0)?)?)?.contiguous()
}

/// Added to `‖∇ₓ f‖²` under the square root of [`unit_gradient_penalty`] (and the fused
/// engine's copy of it), so the norm's derivative stays finite at a zero gradient.
pub const GRAD_NORM_EPS: f64 = 1e-12;

/// WGAN-GP style penalty of a scalar network at points `x`: `mean((‖∇ₓ f(x)‖ − 1)²)`
/// (the discriminator regulariser of the authors' code for Eq. 9). Differentiable with respect
/// to the weights through the analytic input-gradient.
pub fn unit_gradient_penalty(net: &Mlp, x: &Tensor) -> Result<Tensor> {
    let (_, grad) = net.forward_with_input_grad(x)?;
    let norm = (grad.sqr()?.sum(D::Minus1)? + GRAD_NORM_EPS)?.sqrt()?;
    (norm - 1.0)?.sqr()?.mean_all()
}

/// Zero-centred penalty `mean(‖∇ₓ f(x)‖²)` (the nu regulariser of the authors' code).
pub fn zero_gradient_penalty(net: &Mlp, x: &Tensor) -> Result<Tensor> {
    let (_, grad) = net.forward_with_input_grad(x)?;
    grad.sqr()?.sum(D::Minus1)?.mean_all()
}

/// Eq. 37's self-normalised weights `w̃ / mean(w̃)` with `w̃ = exp(A − 1)`, computed as
/// `B · softmax(A)`: subtracting the max keeps it finite for any `A` (the authors' code can
/// overflow), and the `−1` cancels in the normalisation. Detached: the policy step must not
/// move nu. `advantages` is a vector of length B.
pub fn self_normalized_weights(advantages: &Tensor) -> Result<Tensor> {
    let b = advantages.dim(0)? as f64;
    let a = advantages.detach();
    let shifted = a.broadcast_sub(&a.max_keepdim(0)?)?;
    let e = shifted.exp()?;
    (e.broadcast_div(&e.sum_keepdim(0)?)? * b)?.detach().contiguous()
}

/// Effective sample size of weights as a fraction of the batch: `(Σw)² / (B Σw²)`, 1 for
/// uniform weights, 1/B when one sample holds all the weight.
pub fn ess_fraction(weights: &[f32]) -> f64 {
    let sum: f64 = weights.iter().map(|&w| w as f64).sum();
    let sum_sq: f64 = weights.iter().map(|&w| (w as f64).powi(2)).sum();
    if sum_sq == 0.0 {
        return 0.0;
    }
    sum * sum / (weights.len() as f64 * sum_sq)
}

/// `−mean(w · log π)`: weighted behaviour cloning (Eq. 14/37/39/41); `weights` detached.
pub fn weighted_nll(log_prob: &Tensor, weights: &Tensor) -> Result<Tensor> {
    (log_prob * weights)?.mean_all()?.neg()
}

/// Whether a scalar loss is finite; reads it back to the host.
pub fn scalar(loss: &Tensor) -> Result<f64> {
    loss.to_dtype(candle_core::DType::F64)?.to_scalar::<f64>()
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Var};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn softplus_is_finite_and_exact() {
        let x = Tensor::new(&[-1000f32, -3.0, 0.0, 2.5, 1000.0], &Device::Cpu).unwrap();
        let got = softplus(&x).unwrap().to_vec1::<f32>().unwrap();
        let want =
            [0.0, (1.0f64 + (-3f64).exp()).ln(), 2f64.ln(), (1.0f64 + 2.5f64.exp()).ln(), 1000.0];
        for (g, w) in got.iter().zip(want) {
            assert!((*g as f64 - w).abs() < 1e-5, "{g} vs {w}");
        }
    }

    /// Eq. 37: the stable softmax weights equal exp(A − 1)/mean(exp(A − 1)) where the naive
    /// formula is representable, and stay finite where it overflows.
    #[test]
    fn self_normalized_weights_match_exp_a_minus_one_over_mean_and_stay_finite() {
        let a = [0.3f32, -1.2, 2.0, 0.0, 0.7];
        let got = self_normalized_weights(&Tensor::new(&a, &Device::Cpu).unwrap())
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let naive: Vec<f64> = a.iter().map(|&x| (x as f64 - 1.0).exp()).collect();
        let mean = naive.iter().sum::<f64>() / naive.len() as f64;
        for (g, n) in got.iter().zip(&naive) {
            assert!((*g as f64 - n / mean).abs() < 1e-5, "{g} vs {}", n / mean);
        }
        let big =
            self_normalized_weights(&Tensor::new(&[1000f32, 999.0, -5.0], &Device::Cpu).unwrap())
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
        assert!(big.iter().all(|w| w.is_finite()), "{big:?}");
        let e = (-1f64).exp();
        let want = [3.0 / (1.0 + e), 3.0 * e / (1.0 + e), 0.0];
        for (g, w) in big.iter().zip(want) {
            assert!((*g as f64 - w).abs() < 1e-5, "{g} vs {w}");
        }
    }

    #[test]
    fn ess_fraction_spans_one_to_one_over_b() {
        assert!((ess_fraction(&[1.0; 8]) - 1.0).abs() < 1e-12);
        assert!((ess_fraction(&[8.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]) - 0.125).abs() < 1e-12);
    }

    /// The gradient of both penalties with respect to the weights, through the analytic
    /// input-gradient, against central finite differences of the penalty, all in f64.
    #[test]
    fn gradient_penalty_gradients_match_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let net = Mlp::new("d", &[3, 6, 5, 1], false, &Device::Cpu, &mut rng)
            .unwrap()
            .cast(DType::F64)
            .unwrap();
        let x = Tensor::new(
            &[[0.3f64, -1.2, 0.8], [1.5, 0.1, -0.4], [-0.7, 0.9, 2.0], [0.2, 0.2, -0.1]],
            &Device::Cpu,
        )
        .unwrap();
        type Penalty = fn(&Mlp, &Tensor) -> Result<Tensor>;
        for penalty in [unit_gradient_penalty as Penalty, zero_gradient_penalty as Penalty] {
            let loss = penalty(&net, &x).unwrap();
            let grads = loss.backward().unwrap();
            let mut checked = 0;
            for (name, var) in net.named_vars() {
                // The last hidden bias does not change the input-gradient: no gradient expected.
                let g = match grads.get(var.as_tensor()) {
                    Some(g) => g.flatten_all().unwrap().to_vec1::<f64>().unwrap(),
                    None => vec![0.0; var.elem_count()],
                };
                let base = var.as_tensor().flatten_all().unwrap().to_vec1::<f64>().unwrap();
                for k in 0..base.len() {
                    let at = |delta: f64| -> f64 {
                        let mut v = base.clone();
                        v[k] += delta;
                        var.set(&Tensor::from_vec(v, var.dims(), &Device::Cpu).unwrap()).unwrap();
                        scalar(&penalty(&net, &x).unwrap()).unwrap()
                    };
                    let h = 1e-6;
                    let fd = (at(h) - at(-h)) / (2.0 * h);
                    var.set(&Tensor::from_vec(base.clone(), var.dims(), &Device::Cpu).unwrap())
                        .unwrap();
                    assert!(
                        (fd - g[k]).abs() <= 1e-5 * fd.abs().max(1.0),
                        "{name}[{k}]: finite difference {fd} vs autograd {}",
                        g[k]
                    );
                    checked += (g[k] != 0.0) as usize;
                }
            }
            assert!(checked >= 20, "only {checked} non-zero gradients checked");
        }
    }

    #[test]
    fn interpolation_hits_both_ends() {
        let a = Tensor::new(&[[1f32, 2.0], [3.0, 4.0]], &Device::Cpu).unwrap();
        let b = Tensor::new(&[[-1f32, 0.0], [5.0, 6.0]], &Device::Cpu).unwrap();
        let u = Tensor::new(&[[1f32], [0.0]], &Device::Cpu).unwrap();
        let got = interpolate(&a, &b, &u).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(got, vec![vec![1.0, 2.0], vec![5.0, 6.0]]);
        let _ = Var::new(&[0f32], &Device::Cpu).unwrap();
    }
}
