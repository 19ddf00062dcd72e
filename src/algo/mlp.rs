//! The multilayer perceptron behind every network (discriminator, nu, policy body, reward model).
//!
//! ReLU hidden layers, He-normal truncated initialisation from our own seeded RNG (candle's
//! initialisers use an unseeded thread RNG), and an analytic input-gradient built from ordinary
//! tensor ops: the gradient penalties differentiate it with plain first-order autograd, so
//! nothing depends on `CANDLE_GRAD_DO_NOT_DETACH`.
//!
//! The public API is batch-first: callers stack everything that goes through one network into
//! one call (e.g. nu on `cat(s, s', s0)`), which is where candle's per-op overhead is amortised.

use std::collections::HashMap;

use candle_core::{DType, Device, Result, Tensor, Var};

use super::fused_mlp::{FusedMlp, MlpShape};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// Standard deviation of a standard normal truncated at ±2 (TensorFlow/Keras divide by it so the
/// truncated He-normal keeps the intended variance).
const TRUNCATED_NORMAL_STD: f64 = 0.879_625_661_034_239_8;

/// One dense layer `y = x·W + b`, `W` stored `in × out` so the forward needs no transpose.
#[derive(Clone)]
struct Dense {
    weight: Var,
    bias: Option<Var>,
}

/// A ReLU MLP `dims[0] → dims[1] → … → dims[last]`.
#[derive(Clone)]
pub struct Mlp {
    name: String,
    dims: Vec<usize>,
    layers: Vec<Dense>,
}

impl Mlp {
    /// A freshly initialised MLP. `last_bias: false` drops the output bias (critics: the
    /// discriminator, nu and the reward model, as in the authors' code). Weights are He-normal
    /// truncated at 2 std, drawn from `rng` in sorted parameter-name order; biases are zero.
    pub fn new(
        name: &str,
        dims: &[usize],
        last_bias: bool,
        device: &Device,
        rng: &mut ChaCha8Rng,
    ) -> Result<Mlp> {
        assert!(dims.len() >= 2, "an MLP needs an input and an output width");
        let n_layers = dims.len() - 1;
        let mut order: Vec<usize> = (0..n_layers).collect();
        order.sort_by_key(|&i| weight_name(name, i));
        let mut weights: Vec<Option<Var>> = vec![None; n_layers];
        for i in order {
            let values = he_truncated_normal(dims[i], dims[i] * dims[i + 1], rng);
            let w = Tensor::from_vec(values, (dims[i], dims[i + 1]), device)?;
            weights[i] = Some(Var::from_tensor(&w)?);
        }
        let layers = weights
            .into_iter()
            .enumerate()
            .map(|(i, w)| {
                let has_bias = last_bias || i + 1 < n_layers;
                let bias = if has_bias {
                    Some(Var::zeros(dims[i + 1], DType::F32, device)?)
                } else {
                    None
                };
                Ok(Dense { weight: w.expect("every layer initialised"), bias })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Mlp { name: name.to_string(), dims: dims.to_vec(), layers })
    }

    /// Output for a batch `x` (`B × dims[0]` → `B × dims[last]`).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut h = x.clone();
        for (i, layer) in self.layers.iter().enumerate() {
            h = layer.apply(&h)?;
            if i + 1 < self.layers.len() {
                h = h.relu()?;
            }
        }
        Ok(h)
    }

    /// For a scalar-output MLP: the output (`B × 1`) and its gradient with respect to each input
    /// row (`B × dims[0]`), computed with ordinary tensor ops (ReLU masks times transposed
    /// weights, back to front), so first-order autograd can differentiate a penalty on it with
    /// respect to the weights. ReLU's second derivative is zero almost everywhere, so treating
    /// the masks as constants is exact.
    pub fn forward_with_input_grad(&self, x: &Tensor) -> Result<(Tensor, Tensor)> {
        assert_eq!(self.output_dim(), 1, "input gradients are defined for scalar outputs");
        let last = self.layers.len() - 1;
        let mut h = x.clone();
        let mut masks = Vec::with_capacity(last);
        for layer in &self.layers[..last] {
            let z = layer.apply(&h)?;
            masks.push(z.gt(0.0)?.to_dtype(z.dtype())?);
            h = z.relu()?;
        }
        let out = self.layers[last].apply(&h)?;
        // d out / d h_last = W_last^T, one row broadcast over the batch.
        let mut grad = self.layers[last].weight.as_tensor().t()?;
        for (layer, mask) in self.layers[..last].iter().zip(&masks).rev() {
            grad = mask.broadcast_mul(&grad)?.matmul(&layer.weight.as_tensor().t()?)?;
        }
        Ok((out, grad))
    }

    pub fn input_dim(&self) -> usize {
        self.dims[0]
    }

    pub fn output_dim(&self) -> usize {
        *self.dims.last().expect("non-empty dims")
    }

    pub fn dims(&self) -> &[usize] {
        &self.dims
    }

    /// Multiply-adds ×2 of one forward pass over `batch` rows.
    pub fn forward_flops(&self, batch: usize) -> u64 {
        self.dims.windows(2).map(|w| 2 * (batch * w[0] * w[1]) as u64).sum()
    }

    /// Parameters with their stable names (`{name}.{layer}.weight|bias`), sorted by name.
    pub fn named_vars(&self) -> Vec<(String, Var)> {
        let mut vars = Vec::new();
        for (i, layer) in self.layers.iter().enumerate() {
            vars.push((weight_name(&self.name, i), layer.weight.clone()));
            if let Some(b) = &layer.bias {
                vars.push((format!("{}.{i}.bias", self.name), b.clone()));
            }
        }
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        vars
    }

    /// Overwrites every parameter with the tensor of the same name in `tensors`.
    pub fn load(&self, tensors: &HashMap<String, Tensor>) -> Result<()> {
        for (name, var) in self.named_vars() {
            let t = tensors
                .get(&name)
                .ok_or_else(|| candle_core::Error::Msg(format!("missing tensor `{name}`")))?;
            if t.dims() != var.dims() {
                candle_core::bail!(
                    "tensor `{name}` has shape {:?}, expected {:?}",
                    t.dims(),
                    var.dims()
                );
            }
            var.set(&t.to_dtype(DType::F32)?.to_device(var.device())?)?;
        }
        Ok(())
    }

    /// An independent copy whose parameters do not follow later updates of `self`.
    pub fn frozen_copy(&self) -> Result<Mlp> {
        self.cast(DType::F32)
    }

    /// An independent copy in `dtype` (f64 copies make exact finite-difference checks).
    pub fn cast(&self, dtype: DType) -> Result<Mlp> {
        let layers = self
            .layers
            .iter()
            .map(|l| {
                Ok(Dense {
                    weight: Var::from_tensor(&l.weight.as_tensor().to_dtype(dtype)?.copy()?)?,
                    bias: match &l.bias {
                        Some(b) => Some(Var::from_tensor(&b.as_tensor().to_dtype(dtype)?.copy()?)?),
                        None => None,
                    },
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Mlp { name: self.name.clone(), dims: self.dims.clone(), layers })
    }
}

/// Bridge to the fused CPU engine ([`super::fused_mlp`]) used by the training hot loops: the
/// same parameters in one flat buffer, and gradients back as one tensor per parameter.
impl Mlp {
    /// The engine's view of this network's shape.
    pub fn fused_shape(&self) -> MlpShape {
        let last_bias = self.layers.last().is_some_and(|l| l.bias.is_some());
        MlpShape { dims: self.dims.clone(), last_bias }
    }

    /// Copy the current parameters into `fused` (layer by layer: weight `in × out`, then bias).
    pub fn copy_into_fused(&self, fused: &mut FusedMlp) -> Result<()> {
        let mut at = 0;
        for layer in &self.layers {
            for var in std::iter::once(&layer.weight).chain(&layer.bias) {
                let values = var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
                fused.params[at..at + values.len()].copy_from_slice(&values);
                at += values.len();
            }
        }
        Ok(())
    }

    /// A fused copy of this network.
    pub fn to_fused(&self) -> Result<FusedMlp> {
        let mut fused = FusedMlp::zeros(self.fused_shape());
        self.copy_into_fused(&mut fused)?;
        Ok(fused)
    }

    /// Flat gradients in the fused layout as tensors in [`Mlp::named_vars`] order.
    pub fn grads_from_fused(&self, flat: &[f32]) -> Result<Vec<Tensor>> {
        let vars = self.named_vars();
        self.fused_grad_slices(flat)?
            .into_iter()
            .zip(&vars)
            .map(|(g, (_, var))| Tensor::from_slice(g, var.dims(), var.device()))
            .collect()
    }

    /// Flat gradients in the fused layout cut into one slice per parameter, in
    /// [`Mlp::named_vars`] order (what [`super::optim::Adam::step_with_host_grads`] takes for
    /// an optimiser built from `named_vars`).
    pub fn fused_grad_slices<'a>(&self, flat: &'a [f32]) -> Result<Vec<&'a [f32]>> {
        let mut at = 0;
        let mut named = Vec::new();
        let mut take = |len: usize| {
            let slice = flat.get(at..at + len);
            at += len;
            slice
        };
        for (i, layer) in self.layers.iter().enumerate() {
            named.push((weight_name(&self.name, i), take(layer.weight.elem_count())));
            if let Some(b) = &layer.bias {
                named.push((format!("{}.{i}.bias", self.name), take(b.elem_count())));
            }
        }
        if at != flat.len() || named.iter().any(|(_, s)| s.is_none()) {
            candle_core::bail!("{} fused gradients for {} parameters", flat.len(), at);
        }
        named.sort_by(|a, b| a.0.cmp(&b.0));
        Ok(named.into_iter().filter_map(|(_, s)| s).collect())
    }
}

impl Dense {
    fn apply(&self, x: &Tensor) -> Result<Tensor> {
        let y = x.matmul(self.weight.as_tensor())?;
        match &self.bias {
            Some(b) => y.broadcast_add(b.as_tensor()),
            None => Ok(y),
        }
    }
}

fn weight_name(name: &str, layer: usize) -> String {
    format!("{name}.{layer}.weight")
}

/// He-normal values truncated at 2 std: `N(0, 2/fan_in)` rescaled by the truncated std, redrawn
/// outside ±2.
fn he_truncated_normal(fan_in: usize, len: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
    let std = (2.0 / fan_in as f64).sqrt() / TRUNCATED_NORMAL_STD;
    (0..len)
        .map(|_| loop {
            let z: f64 = rng.sample(StandardNormal);
            if z.abs() <= 2.0 {
                break (z * std) as f32;
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn mlp(seed: u64) -> Mlp {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        Mlp::new("critic", &[3, 8, 8, 1], false, &Device::Cpu, &mut rng).unwrap()
    }

    #[test]
    fn init_is_seeded_he_normal_without_last_bias() {
        let (a, b) = (mlp(1), mlp(1));
        let names: Vec<String> = a.named_vars().into_iter().map(|(n, _)| n).collect();
        assert_eq!(
            names,
            [
                "critic.0.bias",
                "critic.0.weight",
                "critic.1.bias",
                "critic.1.weight",
                "critic.2.weight"
            ]
        );
        for ((_, x), (_, y)) in a.named_vars().iter().zip(b.named_vars()) {
            let (x, y) = (
                x.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                y.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            );
            assert_eq!(x, y);
        }
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let values = he_truncated_normal(256, 200_000, &mut rng);
        let var = values.iter().map(|v| (*v as f64).powi(2)).sum::<f64>() / values.len() as f64;
        assert!((var / (2.0 / 256.0) - 1.0).abs() < 0.02, "variance ratio {}", var / (2.0 / 256.0));
        let limit = 2.0 * (2.0f64 / 256.0).sqrt() / TRUNCATED_NORMAL_STD;
        assert!(values.iter().all(|v| (*v as f64).abs() <= limit + 1e-6));
    }

    #[test]
    fn analytic_input_gradient_matches_autograd() {
        let net = mlp(3);
        let x = Var::from_tensor(
            &Tensor::new(&[[0.3f32, -1.2, 0.8], [1.5, 0.1, -0.4], [-0.7, 0.9, 2.0]], &Device::Cpu)
                .unwrap(),
        )
        .unwrap();
        let (out, grad) = net.forward_with_input_grad(x.as_tensor()).unwrap();
        let autograd = out.sum_all().unwrap().backward().unwrap();
        let expected = autograd.get(x.as_tensor()).unwrap().to_vec2::<f32>().unwrap();
        let got = grad.to_vec2::<f32>().unwrap();
        for (e, g) in expected.iter().flatten().zip(got.iter().flatten()) {
            assert!((e - g).abs() < 1e-5, "{e} vs {g}");
        }
    }
}
