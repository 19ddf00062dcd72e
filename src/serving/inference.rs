//! The Open Inference Protocol (KServe v2) as every transport serves it: what a model name
//! resolves to ([`served`]), a model's description (metadata and Triton's configuration come
//! from [`Description`]), the one input checked into observations ([`observations`]), the
//! actions and their layout ([`infer`]), and the statistics of named models. `http/inference/`
//! speaks it as JSON and binary tensor data, `grpc/` as protobuf; neither decides anything this
//! module decides.
//!
//! A model is a policy (its id is the model name, its one version `1`) or a named model
//! (`name`: its latest version; `name@alias`: the alias's version, or its canary's for its
//! share of request keys; a version by number). It takes one FP32 input `observations` of shape
//! `[B, obs_dim]` and answers the output `actions`: FP32 `[B, action_dim]` for continuous spaces,
//! INT64 `[B]` for discrete ones; deterministic unless the request says `deterministic: false`
//! (with an optional `seed`), exactly as `/act`. A SafeDICE policy also answers, when asked
//! (parameter `safety_score`, or the outputs by name), the safety scores of those actions:
//! `non_preferred_log_ratio` and `out_of_support`, FP32 `[B]` each ([`crate::algo::safety`]).

use super::act::{resolve, safety_unavailable, ActOptions, ActTarget, Observations, ServeError};
use super::registry::VersionStats;
use super::tally::ScoreCounts;
use super::Serving;
use crate::algo::Policy;
use crate::data::{ActionSpace, Actions};
use crate::domain::model::ModelRef;
use crate::domain::PolicyId;

/// The name of a model's one input tensor.
pub const INPUT_NAME: &str = "observations";
/// The name of its actions' output tensor.
pub const OUTPUT_NAME: &str = "actions";
/// The safety head's outputs (SafeDICE policies), FP32 `[B]` each, in this order.
pub const SAFETY_OUTPUTS: [&str; 2] = crate::algo::safety::SCORE_NAMES;
/// A policy never changes once trained: a policy served by id has this one version.
pub const MODEL_VERSION: &str = "1";
/// The protocol's extensions served, on REST and gRPC alike.
pub const EXTENSIONS: [&str; 4] =
    ["binary_tensor_data", "model_repository", "statistics", "model_configuration"];
/// What every model is run by, as other servers name their runtimes (`onnxruntime_onnx`).
pub const PLATFORM: &str = "safedice";

/// A model reference from a name and an optional version: a name that breaks the rules names no
/// model (not found).
pub fn reference(name: &str, version: Option<&str>) -> Result<ModelRef, ServeError> {
    match version {
        None => ModelRef::parse(name),
        Some(version) => ModelRef::with_version(name, version),
    }
    .map_err(|rule| ServeError::not_found(format!("model {name:?} does not exist ({rule})")))
}

pub use super::act::Served;

/// Resolves a model name (a policy id or a named model) and an optional version; `key` (a
/// client's request key) picks the same side of a canary every time.
pub async fn served(
    serving: &Serving,
    name: String,
    version: Option<String>,
    key: Option<&str>,
) -> Result<Served, ServeError> {
    let target = match uuid::Uuid::try_parse(&name) {
        Ok(_) => {
            if let Some(version) = version.filter(|v| v != MODEL_VERSION) {
                return Err(ServeError::not_found(format!(
                    "model version {version} of model {name} (its only version is \
                     {MODEL_VERSION}) does not exist"
                )));
            }
            ActTarget::Policy(PolicyId::from(name.clone()))
        }
        Err(_) => ActTarget::Model(reference(&name, version.as_deref())?),
    };
    let mut served = resolve(serving, &target, key).await?;
    served.name = name;
    Ok(served)
}

/// A tensor's name, datatype (`FP32`, `INT64`) and shape (-1: the batch dimension).
pub struct Tensor {
    pub name: &'static str,
    pub datatype: &'static str,
    pub shape: Vec<i64>,
}

/// What model metadata and model configuration say of a model.
pub struct Description {
    /// The name as requested.
    pub name: String,
    /// Every version of the model, in order.
    pub versions: Vec<String>,
    /// The version that answers.
    pub version: String,
    /// The algorithm that trained the policy.
    pub algorithm: String,
    pub input: Tensor,
    /// `actions`, then the safety outputs when the policy has them.
    pub outputs: Vec<Tensor>,
}

impl Served {
    pub fn describe(&self) -> Description {
        let versions = match &self.answer {
            Some((_, versions)) => versions.iter().map(u32::to_string).collect(),
            None => vec![MODEL_VERSION.into()],
        };
        let spec = self.policy.spec();
        let (datatype, shape) = output_layout(&spec.action_space);
        Description {
            name: self.name.clone(),
            versions,
            version: self.version.clone(),
            algorithm: spec.algorithm.to_string(),
            input: Tensor {
                name: INPUT_NAME,
                datatype: "FP32",
                shape: vec![-1, spec.obs_dim as i64],
            },
            outputs: std::iter::once(Tensor { name: OUTPUT_NAME, datatype, shape })
                .chain(self.policy.has_safety_head().then(safety_tensors).into_iter().flatten())
                .collect(),
        }
    }
}

fn safety_tensors() -> impl Iterator<Item = Tensor> {
    SAFETY_OUTPUTS.into_iter().map(|name| Tensor { name, datatype: "FP32", shape: vec![-1] })
}

/// The output's datatype and shape (-1: the batch) for an action space.
fn output_layout(space: &ActionSpace) -> (&'static str, Vec<i64>) {
    match space {
        ActionSpace::Continuous { dim, .. } => ("FP32", vec![-1, *dim as i64]),
        ActionSpace::Discrete { .. } => ("INT64", vec![-1]),
    }
}

/// An input tensor's values, as the transport received them.
pub enum InputData<'a> {
    /// JSON numbers, flat in row-major order.
    Numbers(&'a [f64]),
    /// 32-bit floats (gRPC's `fp32_contents`).
    Fp32(Vec<f32>),
    /// Little-endian FP32 bytes (binary tensor data, gRPC's `raw_input_contents`).
    Raw(&'a [u8]),
    /// None came; the message says what the client should have sent.
    Missing(&'static str),
}

/// One input tensor of a request.
pub struct Input<'a> {
    pub name: &'a str,
    pub datatype: &'a str,
    pub shape: &'a [i64],
    pub data: InputData<'a>,
}

impl<'a> Input<'a> {
    pub fn new(name: &'a str, datatype: &'a str, shape: &'a [i64], data: InputData<'a>) -> Self {
        Input { name, datatype, shape, data }
    }
}

/// The observations of a request's inputs: exactly one, named `observations`, FP32, shaped
/// `[B, obs_dim]`, with as many values as its shape says.
pub fn observations(inputs: Vec<Input<'_>>, obs_dim: usize) -> Result<Observations, ServeError> {
    let count = inputs.len();
    let Ok([input]) = <[Input; 1]>::try_from(inputs) else {
        return Err(bad_input(format!("expected exactly one input tensor, got {count}")));
    };
    if input.name != INPUT_NAME {
        return Err(bad_input(format!(
            "unknown input `{}`; this model's only input is `{INPUT_NAME}` (see its metadata)",
            input.name
        )));
    }
    if input.datatype != "FP32" {
        return Err(bad_input(format!("input datatype must be FP32, got {}", input.datatype)));
    }
    let rows = match input.shape[..] {
        [rows, dim] if rows >= 0 && dim == obs_dim as i64 => rows as usize,
        _ => {
            return Err(bad_input(format!(
                "input shape must be [B, {obs_dim}], got {:?}",
                input.shape
            )))
        }
    };
    // Sized by the data that came, never by the shape the client declared.
    let check_count = |values: usize| {
        if rows.checked_mul(obs_dim) == Some(values) {
            return Ok(());
        }
        Err(bad_input(format!(
            "input data has {values} values; shape {:?} needs {}",
            input.shape,
            (rows as u128) * (obs_dim as u128)
        )))
    };
    match input.data {
        InputData::Numbers(flat) => {
            check_count(flat.len())?;
            Observations::from_flat(flat, rows, obs_dim)
        }
        InputData::Fp32(values) => {
            check_count(values.len())?;
            Observations::from_f32(values, rows, obs_dim)
        }
        InputData::Raw(bytes) => {
            let values = f32_values(bytes, input.name)?;
            check_count(values.len())?;
            Observations::from_f32(values, rows, obs_dim)
        }
        InputData::Missing(what) => Err(bad_input(format!("input `{}` {what}", input.name))),
    }
}

/// Little-endian FP32 values.
pub fn f32_values(bytes: &[u8], input: &str) -> Result<Vec<f32>, ServeError> {
    if !bytes.len().is_multiple_of(4) {
        return Err(bad_input(format!(
            "input `{input}` has {} bytes of FP32 data, not a multiple of 4",
            bytes.len()
        )));
    }
    Ok(bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
}

/// The outputs a request wants, in the order to answer them: those it names (each `actions` or
/// a safety output), or else `actions`; with `safety_score` true, the safety outputs too.
pub fn wanted_outputs(
    requested: &[&str],
    safety_score: Option<bool>,
    policy: &Policy,
) -> Result<Vec<&'static str>, ServeError> {
    let mut wanted = Vec::with_capacity(3);
    for &name in requested {
        let known = std::iter::once(OUTPUT_NAME).chain(SAFETY_OUTPUTS).find(|&n| n == name);
        let Some(known) = known else {
            let safety = if policy.has_safety_head() {
                format!(", {}", SAFETY_OUTPUTS.join(", "))
            } else {
                String::new()
            };
            return Err(bad_input(format!(
                "unknown output `{name}`; this model's outputs are {OUTPUT_NAME}{safety}"
            )));
        };
        if !wanted.contains(&known) {
            wanted.push(known);
        }
    }
    if wanted.is_empty() {
        wanted.push(OUTPUT_NAME);
    }
    if safety_score == Some(true) {
        for name in SAFETY_OUTPUTS {
            if !wanted.contains(&name) {
                wanted.push(name);
            }
        }
    }
    if !policy.has_safety_head() && wanted.iter().any(|n| SAFETY_OUTPUTS.contains(n)) {
        return Err(safety_unavailable(policy));
    }
    Ok(wanted)
}

/// One output tensor of an answer.
pub struct Output {
    pub name: &'static str,
    /// `FP32` or `INT64`.
    pub datatype: &'static str,
    /// `[B, action_dim]` or `[B]`.
    pub shape: Vec<i64>,
    pub data: OutputData,
}

/// An output's values, row-major.
pub enum OutputData {
    Fp32(Vec<f32>),
    Int64(Vec<i64>),
}

impl OutputData {
    /// As raw tensor data: little-endian.
    pub fn little_endian(&self) -> Vec<u8> {
        match self {
            OutputData::Fp32(values) => values.iter().flat_map(|v| v.to_le_bytes()).collect(),
            OutputData::Int64(values) => values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }
}

/// Runs the served model's policy on the observations: the `wanted` outputs (see
/// [`wanted_outputs`]), in order; a named model's version counts the safety scores it answers.
pub async fn infer(
    served: &Served,
    observations: Observations,
    deterministic: bool,
    seed: Option<u64>,
    wanted: &[&'static str],
) -> Result<Vec<Output>, ServeError> {
    let policy = served.policy.clone();
    let rows = observations.rows as i64;
    let (datatype, mut shape) = output_layout(&policy.spec().action_space);
    shape[0] = rows;
    let safety_score = wanted.iter().any(|n| SAFETY_OUTPUTS.contains(n));
    let options = ActOptions { deterministic, seed, safety_score };
    let acted = served.act(observations, options).await?;
    let mut actions = Some(match acted.actions {
        Actions::Continuous(values) => OutputData::Fp32(values),
        Actions::Discrete(indices) => {
            OutputData::Int64(indices.into_iter().map(i64::from).collect())
        }
    });
    let mut safety = acted.safety.map(|s| [s.non_preferred_log_ratio, s.out_of_support]);
    let outputs = wanted.iter().map(|&name| {
        if name == OUTPUT_NAME {
            let data = actions.take().expect("wanted once");
            return Output { name, datatype, shape: shape.clone(), data };
        }
        let at = SAFETY_OUTPUTS.iter().position(|&n| n == name).expect("a safety output");
        let values = std::mem::take(&mut safety.as_mut().expect("asked for")[at]);
        Output { name, datatype: "FP32", shape: vec![rows], data: OutputData::Fp32(values) }
    });
    Ok(outputs.collect())
}

fn bad_input(message: String) -> ServeError {
    ServeError::invalid("invalid_input", message)
}

/// One version's statistics on this process, read once.
pub struct Statistics {
    pub name: String,
    pub version: u32,
    /// Milliseconds since the Unix epoch of the last request (0: none).
    pub last_inference: u64,
    pub success: u64,
    pub success_ns: u64,
    pub fail: u64,
    pub fail_ns: u64,
    /// Counts of the safety scores answered: `(non_preferred_log_ratio, out_of_support)`.
    pub safety: (ScoreCounts, ScoreCounts),
}

impl Statistics {
    fn read(name: &str, version: u32, stats: &VersionStats) -> Self {
        use std::sync::atomic::Ordering;
        let load = |v: &std::sync::atomic::AtomicU64| v.load(Ordering::Relaxed);
        Statistics {
            name: name.to_owned(),
            version,
            last_inference: load(&stats.last_inference_ms),
            success: load(&stats.success),
            success_ns: load(&stats.success_ns),
            fail: load(&stats.fail),
            fail_ns: load(&stats.fail_ns),
            safety: stats.safety.read(),
        }
    }
}

/// Request counts and time of a named model on this process: every version requested (no
/// version), or the one `version` answers (a number; statistics are kept for named models
/// only).
pub async fn statistics(
    serving: &Serving,
    name: &str,
    version: Option<&str>,
) -> Result<Vec<Statistics>, ServeError> {
    let reference = reference(name, version)?;
    let model = reference.model.as_str();
    if version.is_some() {
        let answer = serving.models.resolve(&reference, None).await?;
        let version = answer.target.version;
        return Ok(vec![Statistics::read(model, version, &answer.target.stats)]);
    }
    serving.models.check_exists(&reference.model).await?;
    let stats = serving.models.model_stats(model);
    Ok(stats.iter().map(|(version, stats)| Statistics::read(model, *version, stats)).collect())
}

/// Loads a named model on this process (again after an unload) and returns once it is ready.
pub async fn load(serving: &Serving, name: &str) -> Result<(), ServeError> {
    let reference = reference(name, None)?;
    serving.models.load_model(&reference.model).await?;
    tracing::info!(model = %name, "model loaded on request");
    Ok(())
}

/// Stops serving a named model on this process (other processes of a fleet keep serving it).
pub async fn unload(serving: &Serving, name: &str) -> Result<(), ServeError> {
    let reference = reference(name, None)?;
    serving.models.unload_model(&reference.model).await?;
    tracing::info!(model = %name, "model unloaded on request");
    Ok(())
}
