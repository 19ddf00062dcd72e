//! Policy heads (tanh-squashed Gaussian, categorical), action rescaling, and the policy artefact
//! (safetensors weights + a JSON [`PolicySpec`]) that a deployed [`Policy`] is loaded from.

use std::collections::HashMap;

use candle_core::{Device, Result, Tensor, D};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use super::columns::{from_unit_box, ActionColumn, ObsNormalizer};
use super::fused_mlp::{FusedMlp, Workspace};
use super::mlp::Mlp;
use super::safety::{SafetyHead, SafetyScores, SafetySpec};
use super::{Algorithm, TrainError};
use crate::data::{ActionSpace, Actions};

/// Clipping of the Gaussian head, as in the authors' code: mean to [−7, 7], log-std to [−5, 2].
pub const MEAN_CLIP: f64 = 7.0;
pub const LOG_STD_MIN: f64 = -5.0;
pub const LOG_STD_MAX: f64 = 2.0;

/// A policy network: a ReLU body with a linear head giving `[mean | log_std]` (continuous; the
/// concatenation of the two separate heads) or logits (discrete).
#[derive(Clone)]
pub struct PolicyNet {
    mlp: Mlp,
    space: ActionSpace,
}

impl PolicyNet {
    pub fn new(
        name: &str,
        obs_dim: usize,
        hidden: &[usize],
        space: &ActionSpace,
        device: &Device,
        rng: &mut ChaCha8Rng,
    ) -> Result<PolicyNet> {
        let mlp = Mlp::new(name, &dims(obs_dim, hidden, space), true, device, rng)?;
        Ok(PolicyNet { mlp, space: space.clone() })
    }

    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    /// Clipped `(mean, log_std)` of the pre-tanh Gaussian (continuous policies).
    pub fn gaussian(&self, obs: &Tensor) -> Result<(Tensor, Tensor)> {
        let out = self.mlp.forward(obs)?;
        let dim = self.space.width();
        let mean = out.narrow(1, 0, dim)?.clamp(-MEAN_CLIP, MEAN_CLIP)?;
        let log_std = out.narrow(1, dim, dim)?.clamp(LOG_STD_MIN, LOG_STD_MAX)?;
        Ok((mean, log_std))
    }

    /// `log π(a|s)` of dataset actions (a vector of length B).
    pub fn log_prob(&self, obs: &Tensor, actions: &ActionColumn) -> Result<Tensor> {
        match actions {
            ActionColumn::Continuous { pretanh, log_jacobian } => {
                let (mean, log_std) = self.gaussian(obs)?;
                tanh_gaussian_log_prob(&mean, &log_std, pretanh, log_jacobian)
            }
            ActionColumn::Discrete { index } => {
                categorical_log_prob(&self.mlp.forward(obs)?, index)
            }
        }
    }

    /// Action probabilities `B × n` (discrete policies).
    pub fn probabilities(&self, obs: &Tensor) -> Result<Tensor> {
        candle_nn::ops::softmax(&self.mlp.forward(obs)?, D::Minus1)
    }
}

fn dims(obs_dim: usize, hidden: &[usize], space: &ActionSpace) -> Vec<usize> {
    let out = match space {
        ActionSpace::Continuous { dim, .. } => 2 * dim,
        ActionSpace::Discrete { n } => *n,
    };
    std::iter::once(obs_dim).chain(hidden.iter().copied()).chain(std::iter::once(out)).collect()
}

/// Log-density of a tanh-squashed diagonal Gaussian at `a = tanh(u)`:
/// `Σ_j log N(u_j; mean_j, std_j) − Σ_j log(1 − a_j² + ε)`, with `u = atanh(clip(a))` and the
/// Jacobian term precomputed per row (see [`super::columns::ActionColumn`]).
pub fn tanh_gaussian_log_prob(
    mean: &Tensor,
    log_std: &Tensor,
    pretanh: &Tensor,
    log_jacobian: &Tensor,
) -> Result<Tensor> {
    let z = ((pretanh - mean)? / log_std.exp()?)?;
    let log_normal =
        ((z.sqr()? * -0.5)? - log_std)?.affine(1.0, -0.5 * (2.0 * std::f64::consts::PI).ln())?;
    log_normal.sum(D::Minus1)? - log_jacobian
}

/// The pre-tanh Gaussian's kernel at dataset actions, `exp(−½ Σ_j z_j²)` with
/// `z = (u − mean) / std` per row: the action's density relative to the policy's mode
/// (the normalising constant and tanh's Jacobian cancel in that ratio), in (0, 1].
pub fn gaussian_kernel(mean: &Tensor, log_std: &Tensor, pretanh: &Tensor) -> Result<Tensor> {
    let z = ((pretanh - mean)? / log_std.exp()?)?;
    (z.sqr()?.sum(D::Minus1)? * -0.5)?.exp()
}

/// `log softmax(logits)[a]` per row.
pub fn categorical_log_prob(logits: &Tensor, index: &Tensor) -> Result<Tensor> {
    let log_p = candle_nn::ops::log_softmax(logits, D::Minus1)?;
    log_p.gather(&index.unsqueeze(1)?, 1)?.squeeze(1)
}

/// How the artefact's networks turn into actions.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Decoder {
    /// One policy network (`policy.*`).
    Single,
    /// DExperts at decoding time (Eq. 44, discrete actions): `π = π^U − α π^N` from the
    /// networks `policy.*` (π^U) and `policy_n.*` (π^N), negative mass clipped, renormalised.
    Dexperts { alpha: f64 },
}

/// Everything needed to rebuild a policy without the training datasets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PolicySpec {
    /// Version of this layout.
    pub format_version: u32,
    pub algorithm: Algorithm,
    pub obs_dim: usize,
    /// Continuous policies act in `[-1, 1]^dim`; actions are rescaled to this box's
    /// `[low, high]` affinely (`low + (a + 1)/2 · (high − low)`).
    pub action_space: ActionSpace,
    /// Hidden layer widths (ReLU); continuous heads output `[mean | log_std]` clipped to
    /// [−7, 7] / [−5, 2] and squashed by tanh.
    pub hidden_sizes: Vec<usize>,
    /// Observation standardisation applied before the network, if the run used it.
    pub observation_normalization: Option<ObsNormalizer>,
    pub decoder: Decoder,
    /// SafeDICE's safety head (the frozen discriminator and D^U's reference states), which
    /// serving answers `safety_score` requests with; absent for other algorithms and for
    /// policies trained before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub safety: Option<SafetySpec>,
}

pub const POLICY_FORMAT_VERSION: u32 = 1;

/// Weights (safetensors bytes) + the JSON spec needed to rebuild the policy without datasets.
#[derive(Clone, Debug)]
pub struct PolicyArtifact {
    pub spec: PolicySpec,
    pub weights: Vec<u8>,
}

impl PolicyArtifact {
    /// Serialises the parameters of `nets` (names as in [`Mlp::named_vars`]).
    pub fn new(
        spec: PolicySpec,
        nets: &[&PolicyNet],
    ) -> std::result::Result<PolicyArtifact, TrainError> {
        PolicyArtifact::with_tensors(spec, nets, Vec::new())
    }

    /// [`Self::new`] with more tensors in the file (the safety head's).
    pub fn with_tensors(
        spec: PolicySpec,
        nets: &[&PolicyNet],
        extra: Vec<(String, Tensor)>,
    ) -> std::result::Result<PolicyArtifact, TrainError> {
        let mut tensors: Vec<(String, Tensor)> = nets
            .iter()
            .flat_map(|n| n.mlp.named_vars())
            .map(|(name, var)| Ok((name, var.as_tensor().to_device(&Device::Cpu)?)))
            .collect::<Result<_>>()?;
        tensors.extend(extra);
        let weights = safetensors::serialize(tensors.iter().map(|(n, t)| (n.as_str(), t)), None)
            .map_err(|e| TrainError::Other(format!("serialising policy weights: {e}")))?;
        Ok(PolicyArtifact { spec, weights })
    }
}

/// The one key of a portable policy file's safetensors `__metadata__`: its value is the JSON of
/// [`PortableMetadata`]. One key, because safetensors writes the metadata map in hash order and a
/// file with several keys would differ byte for byte between two downloads of the same policy.
pub const PORTABLE_METADATA_KEY: &str = "safedice.policy";

/// What a policy file carries besides its tensors: everything needed to rebuild the policy
/// (architecture, spaces, action scaling, observation normalisation, algorithm: the spec) and
/// how it was trained.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PortableMetadata {
    pub spec: PolicySpec,
    /// The training run: resolved configuration and dataset ids (free-form JSON, for people and
    /// tools; [`Policy::from_file`] needs only the spec).
    pub training: serde_json::Value,
}

/// The policy's weights as one self-contained safetensors file: the same tensors, and
/// [`PortableMetadata`] under [`PORTABLE_METADATA_KEY`].
pub fn portable_file(
    weights: &[u8],
    metadata: &PortableMetadata,
) -> std::result::Result<Vec<u8>, TrainError> {
    let error = |e: &dyn std::fmt::Display| TrainError::Other(format!("policy file: {e}"));
    let tensors = safetensors::SafeTensors::deserialize(weights).map_err(|e| error(&e))?;
    let json = serde_json::to_string(metadata).map_err(|e| error(&e))?;
    let info = HashMap::from([(PORTABLE_METADATA_KEY.to_owned(), json)]);
    safetensors::serialize(tensors.tensors(), Some(info)).map_err(|e| error(&e))
}

/// A loaded policy; Send + Sync so concurrent requests share one.
///
/// Inference runs on the fused CPU engine's forward pass ([`FusedMlp`]: one GEMM per layer into
/// buffers sized for the request) rather than candle's: a deployed agent sends one observation
/// at a time, and for one row candle's per-op dispatch and allocations cost more than the
/// arithmetic (bench/act_latency.sh).
pub struct Policy {
    spec: PolicySpec,
    /// π (`policy.*`), then π^N (`policy_n.*`) for [`Decoder::Dexperts`].
    nets: Vec<FusedMlp>,
    safety: Option<SafetyHead>,
}

impl Policy {
    pub fn load(spec: &PolicySpec, weights: &[u8]) -> std::result::Result<Policy, TrainError> {
        if spec.format_version != POLICY_FORMAT_VERSION {
            return Err(TrainError::Other(format!(
                "policy format version {} is not supported (expected {POLICY_FORMAT_VERSION})",
                spec.format_version
            )));
        }
        let device = Device::Cpu;
        let tensors: HashMap<String, Tensor> =
            candle_core::safetensors::load_buffer(weights, &device)?;
        let names: &[&str] = match spec.decoder {
            Decoder::Single => &["policy"],
            Decoder::Dexperts { .. } => &["policy", "policy_n"],
        };
        let mut rng = rand::SeedableRng::seed_from_u64(0);
        let nets = names
            .iter()
            .map(|name| {
                let net = PolicyNet::new(
                    name,
                    spec.obs_dim,
                    &spec.hidden_sizes,
                    &spec.action_space,
                    &device,
                    &mut rng,
                )?;
                net.mlp.load(&tensors)?;
                net.mlp.to_fused()
            })
            .collect::<Result<Vec<_>>>()?;
        let safety = match &spec.safety {
            Some(safety) => {
                Some(SafetyHead::load(safety, spec.obs_dim, &spec.action_space, &tensors)?)
            }
            None => None,
        };
        Ok(Policy { spec: spec.clone(), nets, safety })
    }

    /// A policy as the store keeps it: the spec as JSON beside the safetensors weights.
    pub fn from_stored(spec_json: &str, weights: &[u8]) -> std::result::Result<Policy, TrainError> {
        let spec: PolicySpec = serde_json::from_str(spec_json).map_err(|e| {
            TrainError::Other(format!("the stored policy spec does not parse: {e}"))
        })?;
        Policy::load(&spec, weights)
    }

    /// A policy from a portable file's bytes (`GET /v1/policies/{id}/weights`), with what the
    /// file says of its training.
    pub fn from_portable(
        bytes: &[u8],
    ) -> std::result::Result<(Policy, PortableMetadata), TrainError> {
        let error = |message: String| TrainError::Other(format!("policy file: {message}"));
        let (_, header) =
            safetensors::SafeTensors::read_metadata(bytes).map_err(|e| error(e.to_string()))?;
        let json = header
            .metadata()
            .as_ref()
            .and_then(|m| m.get(PORTABLE_METADATA_KEY))
            .ok_or_else(|| error(format!("no `{PORTABLE_METADATA_KEY}` in its metadata")))?;
        let metadata: PortableMetadata =
            serde_json::from_str(json).map_err(|e| error(e.to_string()))?;
        let policy = Policy::load(&metadata.spec, bytes)?;
        Ok((policy, metadata))
    }

    /// A policy from a portable file on disk: the file alone rebuilds it.
    pub fn from_file(
        path: &std::path::Path,
    ) -> std::result::Result<(Policy, PortableMetadata), TrainError> {
        let bytes = std::fs::read(path)
            .map_err(|e| TrainError::Other(format!("cannot read {}: {e}", path.display())))?;
        Policy::from_portable(&bytes)
    }

    /// A policy from networks in memory (e.g. a trainer's): a copy of their current weights.
    pub fn from_nets(spec: PolicySpec, nets: &[PolicyNet]) -> Result<Policy> {
        let nets = nets.iter().map(|n| n.mlp.to_fused()).collect::<Result<_>>()?;
        Ok(Policy { spec: PolicySpec { safety: None, ..spec }, nets, safety: None })
    }

    pub fn spec(&self) -> &PolicySpec {
        &self.spec
    }

    /// `observations`: B × obs_dim row-major in the dataset's original units. Returns B actions in
    /// the dataset's original action units (continuous: B × dim inside the box; discrete: B
    /// indices). deterministic: tanh(mean) / argmax; else a sample drawn with `rng`.
    pub fn act(
        &self,
        observations: &[f32],
        deterministic: bool,
        rng: &mut ChaCha8Rng,
    ) -> std::result::Result<Actions, TrainError> {
        let dim = self.spec.obs_dim;
        if dim == 0 || !observations.len().is_multiple_of(dim) {
            return Err(TrainError::Other(format!(
                "observations must be rows of {dim} values, got {} values",
                observations.len()
            )));
        }
        let rows = observations.len() / dim;
        let mut obs = observations.to_vec();
        if let Some(norm) = &self.spec.observation_normalization {
            norm.apply(&mut obs);
        }
        match &self.spec.action_space {
            ActionSpace::Continuous { low, high, .. } => {
                let out = self.forward(&self.nets[0], &obs, rows);
                Ok(Actions::Continuous(squashed_actions(&out, low, high, deterministic, rng)))
            }
            ActionSpace::Discrete { n } => {
                let scores = self.discrete_scores(&obs, rows);
                let picks = scores.chunks_exact(*n).map(|p| pick(p, deterministic, rng)).collect();
                Ok(Actions::Discrete(picks))
            }
        }
    }

    /// Whether the policy carries a safety head ([`Self::safety_scores`] answers).
    pub fn has_safety_head(&self) -> bool {
        self.safety.is_some()
    }

    /// The safety head's scores of `actions` (as [`Self::act`] returned them) at
    /// `observations`; None when the policy has no safety head (not trained by SafeDICE).
    pub fn safety_scores(&self, observations: &[f32], actions: &Actions) -> Option<SafetyScores> {
        let head = self.safety.as_ref()?;
        let dim = self.spec.obs_dim;
        let rows = observations.len() / dim.max(1);
        let mut obs = observations[..rows * dim].to_vec();
        if let Some(norm) = &self.spec.observation_normalization {
            norm.apply(&mut obs);
        }
        Some(head.scores(&obs, actions, &self.spec.action_space))
    }

    /// For a discrete policy, the distribution [`Self::act`] samples from for each row of
    /// `observations` (`B × n`, row-major): the softmax, or for DExperts Eq. 44's scores
    /// clipped at 0 and renormalised (all mass on the argmax where none is positive). None for
    /// a continuous policy.
    pub fn action_probabilities(&self, observations: &[f32]) -> Option<Vec<f32>> {
        let ActionSpace::Discrete { n } = self.spec.action_space else { return None };
        let dim = self.spec.obs_dim;
        let rows = observations.len() / dim.max(1);
        let mut obs = observations[..rows * dim].to_vec();
        if let Some(norm) = &self.spec.observation_normalization {
            norm.apply(&mut obs);
        }
        let mut scores = self.discrete_scores(&obs, rows);
        for row in scores.chunks_exact_mut(n) {
            let total: f32 = row.iter().map(|s| s.max(0.0)).sum();
            if total > 0.0 {
                row.iter_mut().for_each(|s| *s = s.max(0.0) / total);
            } else {
                let best = pick(row, true, &mut rand::SeedableRng::seed_from_u64(0)) as usize;
                row.iter_mut().enumerate().for_each(|(i, s)| *s = f32::from(u8::from(i == best)));
            }
        }
        Some(scores)
    }

    /// `net`'s outputs (`rows × out`, row-major) on normalised observations.
    fn forward(&self, net: &FusedMlp, obs: &[f32], rows: usize) -> Vec<f32> {
        let mut ws = Workspace::for_inference(net.shape(), rows);
        ws.input_mut()[..obs.len()].copy_from_slice(obs);
        net.forward(&mut ws, rows);
        ws.output()[..rows * net.shape().output()].to_vec()
    }

    /// Row-major `B × n` action scores: probabilities (Single) or Eq. 44's `π^U − α π^N`.
    fn discrete_scores(&self, obs: &[f32], rows: usize) -> Vec<f32> {
        let mut p_u = softmax_rows(self.forward(&self.nets[0], obs, rows), rows);
        if let Decoder::Dexperts { alpha } = self.spec.decoder {
            let p_n = softmax_rows(self.forward(&self.nets[1], obs, rows), rows);
            let alpha = alpha as f32;
            p_u.iter_mut().zip(&p_n).for_each(|(u, n)| *u -= alpha * n);
        }
        p_u
    }
}

/// Actions in the box `[low, high]` from `[mean | log_std]` rows: `tanh` of the clipped mean
/// (deterministic) or of a sample `mean + std·z`, drawn row-major from `rng`, rescaled.
fn squashed_actions(
    out: &[f32],
    low: &[f32],
    high: &[f32],
    deterministic: bool,
    rng: &mut ChaCha8Rng,
) -> Vec<f32> {
    let width = low.len();
    let mut actions = Vec::with_capacity(out.len() / 2);
    for row in out.chunks_exact(2 * width) {
        let (mean, log_std) = row.split_at(width);
        for j in 0..width {
            let m = mean[j].clamp(-MEAN_CLIP as f32, MEAN_CLIP as f32);
            let u = if deterministic {
                m
            } else {
                let std = log_std[j].clamp(LOG_STD_MIN as f32, LOG_STD_MAX as f32).exp();
                let z: f32 = rng.sample(StandardNormal);
                m + std * z
            };
            actions.push(from_unit_box(u.tanh(), low[j], high[j]));
        }
    }
    actions
}

/// Softmax of each of the `rows` rows of `logits`, in place (max subtracted first).
fn softmax_rows(mut logits: Vec<f32>, rows: usize) -> Vec<f32> {
    let n = logits.len() / rows.max(1);
    for row in logits.chunks_exact_mut(n.max(1)) {
        let max = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        row.iter_mut().for_each(|v| *v = (*v - max).exp());
        let sum: f32 = row.iter().sum();
        row.iter_mut().for_each(|v| *v /= sum);
    }
    logits
}

/// argmax, or a sample from the positive part of `scores` renormalised (argmax if none is
/// positive, which only Eq. 44 with a large α can produce).
fn pick(scores: &[f32], deterministic: bool, rng: &mut ChaCha8Rng) -> u32 {
    let argmax = scores
        .iter()
        .enumerate()
        .fold((0, f32::NEG_INFINITY), |best, (i, &s)| if s > best.1 { (i, s) } else { best })
        .0 as u32;
    let total: f32 = scores.iter().map(|s| s.max(0.0)).sum();
    if deterministic || total <= 0.0 {
        return argmax;
    }
    let mut u = rng.random::<f32>() * total;
    for (i, s) in scores.iter().enumerate() {
        u -= s.max(0.0);
        if u < 0.0 {
            return i as u32;
        }
    }
    argmax
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The tanh-Gaussian log-density against its closed form in one dimension:
    /// p(a) = N(atanh a; m, s) / (1 − a²).
    #[test]
    fn tanh_gaussian_log_prob_matches_closed_form() {
        let (m, log_s) = (0.4f64, -0.3f64);
        for a in [-0.95f64, -0.5, 0.0, 0.3, 0.9, 0.999] {
            let u = a.atanh();
            let s = log_s.exp();
            let want = -0.5 * ((u - m) / s).powi(2)
                - s.ln()
                - 0.5 * (2.0 * std::f64::consts::PI).ln()
                - (1.0 - a * a).ln();
            let t = |v: f64| Tensor::new(&[[v as f32]], &Device::Cpu).unwrap();
            let jac = Tensor::new(
                &[(1.0 - a * a + super::super::columns::ACTION_EPS).ln() as f32],
                &Device::Cpu,
            )
            .unwrap();
            let got = tanh_gaussian_log_prob(&t(m), &t(log_s), &t(u), &jac)
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()[0];
            assert!(
                (got as f64 - want).abs() < 2e-3 * want.abs().max(1.0),
                "a={a}: {got} vs {want}"
            );
        }
    }

    /// The density integrates to one over (−1, 1) (midpoint rule on a fine grid).
    #[test]
    fn tanh_gaussian_density_integrates_to_one() {
        let n = 20_000;
        let a: Vec<f64> = (0..n).map(|i| -1.0 + (i as f64 + 0.5) * 2.0 / n as f64).collect();
        let pre: Vec<f32> = a.iter().map(|x| x.atanh() as f32).collect();
        let jac: Vec<f32> = a.iter().map(|x| (1.0 - x * x).ln() as f32).collect();
        let dev = Device::Cpu;
        let mean = Tensor::full(0.7f32, (n, 1), &dev).unwrap();
        let log_std = Tensor::full(0.2f32, (n, 1), &dev).unwrap();
        let lp = tanh_gaussian_log_prob(
            &mean,
            &log_std,
            &Tensor::from_vec(pre, (n, 1), &dev).unwrap(),
            &Tensor::from_vec(jac, n, &dev).unwrap(),
        )
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
        let integral: f64 = lp.iter().map(|l| (*l as f64).exp() * 2.0 / n as f64).sum();
        assert!((integral - 1.0).abs() < 1e-3, "integral {integral}");
    }

    #[test]
    fn categorical_log_prob_is_log_softmax_of_the_action() {
        let logits = Tensor::new(&[[1f32, 2.0, 0.5], [0.0, 0.0, 3.0]], &Device::Cpu).unwrap();
        let idx = Tensor::new(&[1u32, 0], &Device::Cpu).unwrap();
        let got = categorical_log_prob(&logits, &idx).unwrap().to_vec1::<f32>().unwrap();
        let lse0 = (1f64.exp() + 2f64.exp() + 0.5f64.exp()).ln();
        let lse1 = (2.0 + 3f64.exp()).ln();
        assert!((got[0] as f64 - (2.0 - lse0)).abs() < 1e-6);
        assert!((got[1] as f64 - (0.0 - lse1)).abs() < 1e-6);
    }

    fn spec(space: ActionSpace, decoder: Decoder) -> PolicySpec {
        PolicySpec {
            format_version: POLICY_FORMAT_VERSION,
            algorithm: Algorithm::Safedice,
            obs_dim: 3,
            action_space: space,
            hidden_sizes: vec![8, 8],
            observation_normalization: Some(ObsNormalizer {
                mean: vec![0.5, -1.0, 2.0],
                std: vec![2.0, 0.5, 1.0],
            }),
            decoder,
            safety: None,
        }
    }

    /// Weights through safetensors bytes and the spec through JSON give a policy whose
    /// deterministic and sampled actions equal the in-memory policy's, bit for bit.
    #[test]
    fn safetensors_round_trip_gives_identical_actions() {
        let cases = [
            (
                ActionSpace::Continuous { dim: 2, low: vec![-2.0, 0.0], high: vec![2.0, 10.0] },
                Decoder::Single,
            ),
            (ActionSpace::Discrete { n: 4 }, Decoder::Single),
            (ActionSpace::Discrete { n: 4 }, Decoder::Dexperts { alpha: 0.4 }),
        ];
        let obs: Vec<f32> = (0..30).map(|i| ((i * 7919) % 23) as f32 / 5.0 - 2.0).collect();
        for (space, decoder) in cases {
            let spec = spec(space.clone(), decoder.clone());
            let mut rng = rand::SeedableRng::seed_from_u64(5);
            let names: &[&str] =
                if decoder == Decoder::Single { &["policy"] } else { &["policy", "policy_n"] };
            let nets: Vec<PolicyNet> = names
                .iter()
                .map(|n| PolicyNet::new(n, 3, &[8, 8], &space, &Device::Cpu, &mut rng).unwrap())
                .collect();
            let artifact =
                PolicyArtifact::new(spec.clone(), &nets.iter().collect::<Vec<_>>()).unwrap();
            let json = serde_json::to_string(&artifact.spec).unwrap();
            let loaded =
                Policy::load(&serde_json::from_str(&json).unwrap(), &artifact.weights).unwrap();
            // The portable file rebuilds it alone, and is the same bytes every time.
            let metadata = PortableMetadata {
                spec: spec.clone(),
                training: serde_json::json!({"config": {"seed": 1}, "unlabeled_dataset": "d"}),
            };
            let file = portable_file(&artifact.weights, &metadata).unwrap();
            assert_eq!(file, portable_file(&artifact.weights, &metadata).unwrap());
            let (portable, read_back) = Policy::from_portable(&file).unwrap();
            assert_eq!(read_back, metadata);
            assert!(Policy::from_portable(&artifact.weights).is_err(), "no metadata, no policy");
            let original = Policy::from_nets(spec, &nets).unwrap();
            for deterministic in [true, false] {
                let mut r1 = rand::SeedableRng::seed_from_u64(9);
                let mut r2 = rand::SeedableRng::seed_from_u64(9);
                let mut r3 = rand::SeedableRng::seed_from_u64(9);
                let a = original.act(&obs, deterministic, &mut r1).unwrap();
                let b = loaded.act(&obs, deterministic, &mut r2).unwrap();
                assert_eq!(a, b);
                assert_eq!(a, portable.act(&obs, deterministic, &mut r3).unwrap());
                if let Actions::Continuous(values) = &a {
                    assert!(values
                        .chunks(2)
                        .all(|r| (-2.0..=2.0).contains(&r[0]) && (0.0..=10.0).contains(&r[1])));
                }
            }
        }
    }

    /// Inference (the fused engine) computes what the training networks (candle) define: the
    /// deterministic action `tanh(clip(mean))` and the action probabilities, on random inputs.
    #[test]
    fn inference_matches_the_candle_networks() {
        let mut rng: ChaCha8Rng = rand::SeedableRng::seed_from_u64(4);
        let rows = 5;
        let obs: Vec<f32> = (0..rows * 6).map(|_| rng.random_range(-3.0..3.0)).collect();
        let input = Tensor::from_vec(obs.clone(), (rows, 6), &Device::Cpu).unwrap();
        let spaces = [
            ActionSpace::Continuous { dim: 2, low: vec![-1.0, -1.0], high: vec![1.0, 1.0] },
            ActionSpace::Discrete { n: 4 },
        ];
        for space in spaces {
            let net =
                PolicyNet::new("policy", 6, &[16, 16], &space, &Device::Cpu, &mut rng).unwrap();
            let spec = PolicySpec {
                format_version: POLICY_FORMAT_VERSION,
                algorithm: Algorithm::Bc,
                obs_dim: 6,
                action_space: space.clone(),
                hidden_sizes: vec![16, 16],
                observation_normalization: None,
                decoder: Decoder::Single,
                safety: None,
            };
            let policy = Policy::from_nets(spec, std::slice::from_ref(&net)).unwrap();
            let (want, got): (Vec<f32>, Vec<f32>) = match space {
                ActionSpace::Continuous { .. } => {
                    let (mean, _) = net.gaussian(&input).unwrap();
                    let want = mean.tanh().unwrap().flatten_all().unwrap().to_vec1().unwrap();
                    let Actions::Continuous(got) = policy.act(&obs, true, &mut rng).unwrap() else {
                        panic!("continuous actions expected")
                    };
                    (want, got)
                }
                ActionSpace::Discrete { .. } => {
                    let p = net.probabilities(&input).unwrap();
                    (
                        p.flatten_all().unwrap().to_vec1().unwrap(),
                        policy.discrete_scores(&obs, rows),
                    )
                }
            };
            assert_eq!(want.len(), got.len());
            for (w, g) in want.iter().zip(&got) {
                assert!((w - g).abs() < 1e-5, "{w} vs {g}");
            }
        }
    }

    #[test]
    fn policies_can_be_shared_between_request_threads() {
        fn shared<T: Send + Sync>() {}
        shared::<Policy>();
    }

    #[test]
    fn pick_samples_only_positive_scores() {
        let mut rng = rand::SeedableRng::seed_from_u64(0);
        for _ in 0..200 {
            let a = pick(&[0.5, -0.2, 0.5], false, &mut rng);
            assert!(a == 0 || a == 2);
        }
        assert_eq!(pick(&[0.1, 0.7, 0.2], true, &mut rng), 1);
        assert_eq!(pick(&[-0.1, -0.7, -0.2], false, &mut rng), 0);
    }
}
