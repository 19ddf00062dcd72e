//! Adam (PyTorch's formulation, no weight decay) with state that can be checkpointed exactly.
//!
//! candle-nn's `AdamW` keeps its moment estimates private, so a resumed run could not continue
//! the same optimiser trajectory; this one exposes them for [`super::checkpoint`].

use std::collections::HashMap;

use candle_core::backprop::GradStore;
use candle_core::{Result, Tensor, Var};

pub struct Adam {
    lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
    params: Vec<(String, Var)>,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    /// Number of updates applied so far (bias correction uses it).
    t: u64,
}

impl Adam {
    /// Adam over `params` (named, as from [`super::mlp::Mlp::named_vars`]) with β = (0.9, 0.999)
    /// and ε = 1e-8.
    pub fn new(params: Vec<(String, Var)>, lr: f64) -> Result<Adam> {
        let zeros = |p: &Vec<(String, Var)>| -> Result<Vec<Tensor>> {
            p.iter().map(|(_, v)| v.as_tensor().zeros_like()).collect()
        };
        Ok(Adam {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            m: zeros(&params)?,
            v: zeros(&params)?,
            params,
            t: 0,
        })
    }

    /// Backpropagates `loss` and applies one update to every parameter that received a gradient.
    pub fn minimize(&mut self, loss: &Tensor) -> Result<()> {
        let grads = loss.backward()?;
        self.step(&grads)
    }

    /// One update from precomputed gradients.
    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        self.t += 1;
        for i in 0..self.params.len() {
            if let Some(g) = grads.get(self.params[i].1.as_tensor()) {
                let g = g.clone();
                self.update(i, &g)?;
            }
        }
        Ok(())
    }

    /// One update from host gradients given for every parameter in [`Adam::params`] order (the
    /// fused CPU training path computes them without autograd): the same arithmetic as
    /// [`Adam::step`], bit for bit, in one pass per parameter instead of a dozen tensor ops.
    pub fn step_with_host_grads(&mut self, grads: &[&[f32]]) -> Result<()> {
        if grads.len() != self.params.len() {
            candle_core::bail!("{} gradients for {} parameters", grads.len(), self.params.len());
        }
        self.t += 1;
        for (i, g) in grads.iter().enumerate() {
            self.update_host(i, g)?;
        }
        Ok(())
    }

    /// [`Adam::update`] on host values. candle's tensor-scalar ops compute `x · mul + add` in
    /// f32 (`Tensor::affine`; a division by `c` multiplies by `1/c`): written out the same way,
    /// so both paths give the same bits (tested).
    fn update_host(&mut self, i: usize, g: &[f32]) -> Result<()> {
        let correction1 = 1.0 - self.beta1.powi(self.t as i32);
        let correction2 = 1.0 - self.beta2.powi(self.t as i32);
        let f = |x: f64| x as f32;
        let (b1, one_minus_b1) = (f(self.beta1), f(1.0 - self.beta1));
        let (b2, one_minus_b2) = (f(self.beta2), f(1.0 - self.beta2));
        let (inv_c2, eps, step_size) =
            (f(1.0 / correction2), f(self.eps), f(self.lr / correction1));
        let var = &self.params[i].1;
        let (shape, device) = (var.shape().clone(), var.device().clone());
        let host = |t: &Tensor| t.flatten_all()?.to_vec1::<f32>();
        let (mut p, mut m, mut v) = (host(var.as_tensor())?, host(&self.m[i])?, host(&self.v[i])?);
        if g.len() != p.len() {
            candle_core::bail!("{} gradients for parameter {} of {}", g.len(), i, p.len());
        }
        for (((p, m), v), &g) in p.iter_mut().zip(&mut m).zip(&mut v).zip(g) {
            *m = (*m * b1 + 0.0) + (g * one_minus_b1 + 0.0);
            *v = (*v * b2 + 0.0) + (g * g * one_minus_b2 + 0.0);
            let denom = (*v * inv_c2 + 0.0).sqrt() * 1.0 + eps;
            *p -= (*m / denom) * step_size + 0.0;
        }
        self.m[i] = Tensor::from_vec(m, &shape, &device)?;
        self.v[i] = Tensor::from_vec(v, &shape, &device)?;
        var.set(&Tensor::from_vec(p, shape, &device)?)
    }

    /// Adam's update of parameter `i` at step `self.t`.
    fn update(&mut self, i: usize, g: &Tensor) -> Result<()> {
        let correction1 = 1.0 - self.beta1.powi(self.t as i32);
        let correction2 = 1.0 - self.beta2.powi(self.t as i32);
        let step_size = self.lr / correction1;
        let var = &self.params[i].1;
        // A weight gradient from candle's backward is computed from the step's tracked
        // activations, so it still references the whole forward graph. Folded into the moments
        // undetached, every step's graph stays reachable from `m`/`v`: memory grew by one graph
        // per step (6.25 MB for BC at [256, 256] / batch 512) until the run ended.
        let g = g.detach();
        let m = ((&self.m[i] * self.beta1)? + (&g * (1.0 - self.beta1))?)?.detach();
        let v = ((&self.v[i] * self.beta2)? + (g.sqr()? * (1.0 - self.beta2))?)?.detach();
        let denom = ((&v / correction2)?.sqrt()? + self.eps)?;
        let update = ((&m / denom)? * step_size)?;
        var.set(&(var.as_tensor() - update)?)?;
        self.m[i] = m;
        self.v[i] = v;
        Ok(())
    }

    pub fn params(&self) -> &[(String, Var)] {
        &self.params
    }

    pub fn steps_taken(&self) -> u64 {
        self.t
    }

    /// Parameters and moment estimates by name: `param.{name}`, `m.{name}`, `v.{name}`.
    pub fn state(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::with_capacity(3 * self.params.len());
        for (i, (name, var)) in self.params.iter().enumerate() {
            out.push((format!("param.{name}"), var.as_tensor().clone()));
            out.push((format!("m.{name}"), self.m[i].clone()));
            out.push((format!("v.{name}"), self.v[i].clone()));
        }
        out
    }

    /// Restores what [`Adam::state`] saved (looked up under `prefix`) and the step count.
    pub fn restore(
        &mut self,
        tensors: &HashMap<String, Tensor>,
        prefix: &str,
        t: u64,
    ) -> Result<()> {
        let get = |key: String, like: &Tensor| -> Result<Tensor> {
            let t = tensors
                .get(&key)
                .ok_or_else(|| candle_core::Error::Msg(format!("checkpoint lacks `{key}`")))?;
            if t.dims() != like.dims() {
                candle_core::bail!(
                    "checkpoint tensor `{key}` has shape {:?}, expected {:?}",
                    t.dims(),
                    like.dims()
                );
            }
            t.to_device(like.device())
        };
        for (i, (name, var)) in self.params.iter().enumerate() {
            var.set(&get(format!("{prefix}param.{name}"), var.as_tensor())?)?;
            self.m[i] = get(format!("{prefix}m.{name}"), &self.m[i])?;
            self.v[i] = get(format!("{prefix}v.{name}"), &self.v[i])?;
        }
        self.t = t;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Two Adam steps on f(x) = Σ x² against values worked out by hand (PyTorch's formula).
    #[test]
    fn matches_hand_computed_adam_steps() {
        let x = Var::new(&[1.0f32, -2.0], &Device::Cpu).unwrap();
        let mut adam = Adam::new(vec![("x".into(), x.clone())], 0.1).unwrap();
        let mut expected = [1.0f64, -2.0];
        let (mut m, mut v) = ([0.0f64; 2], [0.0f64; 2]);
        for t in 1..=2 {
            adam.minimize(&x.as_tensor().sqr().unwrap().sum_all().unwrap()).unwrap();
            for j in 0..2 {
                let g = 2.0 * expected[j];
                m[j] = 0.9 * m[j] + 0.1 * g;
                v[j] = 0.999 * v[j] + 0.001 * g * g;
                let mhat = m[j] / (1.0 - 0.9f64.powi(t));
                let vhat = v[j] / (1.0 - 0.999f64.powi(t));
                expected[j] -= 0.1 * mhat / (vhat.sqrt() + 1e-8);
            }
        }
        let got = x.as_tensor().to_vec1::<f32>().unwrap();
        for j in 0..2 {
            assert!((got[j] as f64 - expected[j]).abs() < 1e-6, "{got:?} vs {expected:?}");
        }
        assert_eq!(adam.steps_taken(), 2);
    }

    /// The host update gives the tensor update's bits, step after step (moments included).
    #[test]
    fn host_update_matches_tensor_update_bit_for_bit() {
        let values: Vec<f32> = (0..97).map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.3).collect();
        let grads: Vec<Vec<f32>> = (0..4)
            .map(|t| {
                values.iter().map(|v| (v * (t as f32 + 1.3)).sin() * 1e-3f32.powi(t % 3)).collect()
            })
            .collect();
        let make = || {
            let x = Var::from_vec(values.clone(), (97,), &Device::Cpu).unwrap();
            Adam::new(vec![("x".into(), x)], 3e-4).unwrap()
        };
        let (mut tensor, mut host) = (make(), make());
        for g in &grads {
            let g_t = Tensor::from_slice(g, (97,), &Device::Cpu).unwrap();
            tensor.t += 1;
            tensor.update(0, &g_t).unwrap();
            host.step_with_host_grads(&[g]).unwrap();
        }
        let bits = |a: &Adam| -> Vec<Vec<u32>> {
            a.state()
                .iter()
                .map(|(_, t)| t.to_vec1::<f32>().unwrap().iter().map(|v| v.to_bits()).collect())
                .collect()
        };
        assert_eq!(bits(&tensor), bits(&host));
    }
}
