//! The act path every transport shares: what answers ([`resolve`]: a policy by id, or a named
//! model's version through its aliases, canaries and shadows), observations validated into one
//! batch ([`Observations`]), the policy run on it and what follows it ([`Served::act`]: a named
//! model's statistics, safety tally and shadow), and what can go wrong on the way
//! ([`ServeError`], which `http/` answers as a status and a body and `grpc/` as a gRPC status).
//! `/v1/policies/{id}/act`, `/v1/models/{name}/act`, the KServe v2 `infer` route and the gRPC
//! `ModelInfer` and `ModelStreamInfer` all come through here: a transport resolves, decodes its
//! body into observations with the policy's width, and calls [`Served::timed`] around
//! [`Served::act`].

use std::sync::Arc;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::registry::{Answer, ResolveError};
use super::shadow::Comparison;
use super::PolicyLoadError;
use super::Serving;
use crate::algo::safety::SafetyScores;
use crate::algo::Policy;
use crate::data::Actions;
use crate::domain::model::ModelRef;
use crate::domain::shadow::ComparisonKey;
use crate::domain::PolicyId;

/// Largest batch one request may send.
pub const MAX_BATCH_ROWS: usize = 16_384;
/// Largest request of the action routes and RPCs (`/act`, `/v2/…/infer`, gRPC `ModelInfer`): a
/// full batch of 16,384 observations as JSON needs far more than the 2 MB every other JSON body
/// may have (about 12 bytes per value: 16,384 rows of 80 values), and as binary tensor data up
/// to 256 values per row. A larger request is refused before it is read.
pub const ACTION_BODY_LIMIT: usize = 16 << 20;
/// Batches up to this many rows run on the request's task (a few microseconds of matrix
/// products); larger ones move to a blocking thread so they cannot stall other requests.
const INLINE_ROWS: usize = 64;

/// Why a request for actions (or a model's description) was not answered.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The request's content does not fit the model (REST: 422 with `code`; gRPC:
    /// INVALID_ARGUMENT).
    #[error("{message}")]
    Invalid { code: &'static str, message: String },
    /// No such model, alias, version or policy; an unloaded model (REST: 404; gRPC: NOT_FOUND).
    #[error(transparent)]
    Resolve(#[from] ResolveError),
    /// Anything unexpected (REST: 500; gRPC: INTERNAL), logged by the transport.
    #[error("internal error")]
    Internal(#[from] anyhow::Error),
}

impl ServeError {
    pub fn invalid(code: &'static str, message: impl Into<String>) -> Self {
        ServeError::Invalid { code, message: message.into() }
    }

    pub fn not_found(message: impl Into<String>) -> Self {
        ServeError::Resolve(ResolveError::NotFound(message.into()))
    }
}

impl From<PolicyLoadError> for ServeError {
    fn from(e: PolicyLoadError) -> Self {
        ServeError::Resolve(ResolveError::Load(e))
    }
}

/// Validated observations: `rows × obs_dim`, row-major, all finite.
pub struct Observations {
    pub values: Vec<f32>,
    pub rows: usize,
}

impl Observations {
    /// From `/act`'s list of rows.
    pub fn from_rows(rows: &[Vec<f64>], obs_dim: usize) -> Result<Self, ServeError> {
        check_batch_size(rows.len())?;
        let mut values = Vec::with_capacity(rows.len() * obs_dim);
        for (i, row) in rows.iter().enumerate() {
            if row.len() != obs_dim {
                return Err(invalid(format!(
                    "observations[{i}] has {} values; this policy takes {obs_dim} per observation",
                    row.len()
                )));
            }
            for (j, &v) in row.iter().enumerate() {
                values.push(finite(v, || format!("observations[{i}][{j}]"))?);
            }
        }
        Ok(Observations { values, rows: rows.len() })
    }

    /// From a flat row-major buffer of `rows × obs_dim` values (JSON numbers).
    pub fn from_flat(flat: &[f64], rows: usize, obs_dim: usize) -> Result<Self, ServeError> {
        check_batch_size(rows)?;
        let values = flat
            .iter()
            .enumerate()
            .map(|(k, &v)| finite(v, || format!("data[{}][{}]", k / obs_dim, k % obs_dim)))
            .collect::<Result<_, _>>()?;
        Ok(Observations { values, rows })
    }

    /// From a flat row-major buffer of `rows × obs_dim` 32-bit floats (binary tensor data,
    /// gRPC's `fp32_contents`), kept as they are once checked finite.
    pub fn from_f32(values: Vec<f32>, rows: usize, obs_dim: usize) -> Result<Self, ServeError> {
        check_batch_size(rows)?;
        if let Some(k) = values.iter().position(|v| !v.is_finite()) {
            let at = format!("data[{}][{}]", k / obs_dim, k % obs_dim);
            return Err(invalid(format!(
                "{at} is {}, which is not a finite 32-bit float",
                values[k]
            )));
        }
        Ok(Observations { values, rows })
    }
}

fn check_batch_size(rows: usize) -> Result<(), ServeError> {
    if rows == 0 {
        return Err(invalid("the batch is empty: send at least one observation".into()));
    }
    if rows > MAX_BATCH_ROWS {
        return Err(ServeError::invalid(
            "batch_too_large",
            format!("{rows} observations in one request; at most {MAX_BATCH_ROWS}"),
        ));
    }
    Ok(())
}

fn finite(v: f64, at: impl FnOnce() -> String) -> Result<f32, ServeError> {
    let x = v as f32;
    if x.is_finite() {
        Ok(x)
    } else {
        Err(invalid(format!("{} is {v}, which is not a finite 32-bit float", at())))
    }
}

fn invalid(message: String) -> ServeError {
    ServeError::invalid("invalid_observations", message)
}

/// How the policy acts, and what it answers beside the actions.
#[derive(Clone, Copy, Debug)]
pub struct ActOptions {
    /// tanh of the Gaussian mean / argmax; else a sample.
    pub deterministic: bool,
    /// Makes a sample reproducible.
    pub seed: Option<u64>,
    /// Also the safety head's scores of the returned actions ([`crate::algo::safety`]).
    pub safety_score: bool,
}

/// The actions, and their safety scores when asked for.
pub struct Acted {
    pub actions: Actions,
    pub safety: Option<SafetyScores>,
}

/// Runs the policy on validated observations: deterministic (tanh of the mean / argmax), or
/// sampled with `seed` (reproducible) or fresh entropy.
pub async fn act(
    policy: Arc<Policy>,
    observations: Observations,
    options: ActOptions,
) -> Result<Acted, ServeError> {
    if options.safety_score && !policy.has_safety_head() {
        return Err(safety_unavailable(&policy));
    }
    let mut rng = match options.seed {
        Some(seed) => ChaCha8Rng::seed_from_u64(seed),
        None if options.deterministic => ChaCha8Rng::seed_from_u64(0),
        None => ChaCha8Rng::from_os_rng(),
    };
    let mut run = move || {
        let actions = policy
            .act(&observations.values, options.deterministic, &mut rng)
            .map_err(|e| ServeError::Internal(anyhow::anyhow!("policy inference failed: {e}")))?;
        let safety = match options.safety_score {
            true => policy.safety_scores(&observations.values, &actions),
            false => None,
        };
        Ok(Acted { actions, safety })
    };
    if observations.rows <= INLINE_ROWS {
        run()
    } else {
        tokio::task::spawn_blocking(run)
            .await
            .map_err(|e| ServeError::Internal(anyhow::anyhow!("policy inference failed: {e}")))?
    }
}

/// What a request for actions names.
pub enum ActTarget {
    /// A trained policy by its id (one version, `1`).
    Policy(PolicyId),
    /// A named model: its latest version, an alias's (or its canary's) or a version by number.
    Model(ModelRef),
}

/// What answers a request: the policy, and for a named model the version chosen (with its
/// statistics and shadow) and the model's versions.
pub struct Served {
    /// The name as requested (a policy id, or the model reference's name).
    pub name: String,
    /// The version that answers.
    pub version: String,
    pub policy: Arc<Policy>,
    pub answer: Option<(Answer, Vec<u32>)>,
}

/// Resolves a target; `key` (a client's request key) picks the same side of a canary every
/// time.
pub async fn resolve(
    serving: &Serving,
    target: &ActTarget,
    key: Option<&str>,
) -> Result<Served, ServeError> {
    match target {
        ActTarget::Policy(id) => {
            let policy = serving.policies.get(id).await?;
            Ok(Served { name: id.to_string(), version: "1".into(), policy, answer: None })
        }
        ActTarget::Model(reference) => {
            let answer = serving.models.resolve(reference, key).await?;
            let versions = serving.models.versions(reference.model.as_str());
            Ok(Served {
                name: reference.model.to_string(),
                version: answer.target.version.to_string(),
                policy: answer.target.policy.clone(),
                answer: Some((answer, versions)),
            })
        }
    }
}

impl Served {
    /// Runs `work` for this target and counts it, success or failure and its time, in the
    /// answering version's statistics (named models only).
    pub async fn timed<T, E>(
        &self,
        work: impl std::future::Future<Output = Result<T, E>>,
    ) -> Result<T, E> {
        match &self.answer {
            Some((answer, _)) => answer.timed(work).await,
            None => work.await,
        }
    }

    /// The policy acts on the observations ([`act`]); for a named model, through
    /// [`act_answer`].
    pub async fn act(
        &self,
        observations: Observations,
        options: ActOptions,
    ) -> Result<Acted, ServeError> {
        match &self.answer {
            Some((answer, _)) => act_answer(answer, observations, options).await,
            None => act(self.policy.clone(), observations, options).await,
        }
    }
}

/// [`act`] for a named model's answer: the answering version acts, the safety scores it answers
/// are counted in its statistics, and when the request was drawn for the alias's shadow, the
/// shadow gets a copy of the observations and the actions returned, to run off the response path
/// ([`super::shadow`]). A sampled request without a seed gets one drawn here, so both versions
/// draw the same noise.
pub async fn act_answer(
    answer: &Answer,
    observations: Observations,
    mut options: ActOptions,
) -> Result<Acted, ServeError> {
    let shadowed = answer.shadow.as_ref().map(|_| observations.values.clone());
    if shadowed.is_some() && !options.deterministic && options.seed.is_none() {
        options.seed = Some(rand::random::<u64>() >> 1);
    }
    let acted = act(answer.target.policy.clone(), observations, options).await?;
    if let Some(scores) = &acted.safety {
        answer.target.stats.safety.record_log_ratios(&scores.non_preferred_log_ratio);
        answer.target.stats.safety.record_support(&scores.out_of_support);
    }
    if let (Some(draw), Some(observations)) = (&answer.shadow, shadowed) {
        let key = ComparisonKey {
            model: answer.model.clone(),
            model_created: draw.model_created.clone(),
            alias: draw.alias.clone(),
            production_version: answer.target.version,
            shadow_version: draw.version,
        };
        match &draw.policy {
            Some(shadow) => draw.shadows.submit(Comparison {
                key,
                shadow: shadow.clone(),
                production: answer.target.policy.clone(),
                observations,
                production_actions: acted.actions.clone(),
                deterministic: options.deterministic,
                seed: options.seed.unwrap_or(0),
            }),
            None => draw.shadows.skip(key),
        }
    }
    Ok(acted)
}

/// The answer to a safety score the policy cannot give.
pub fn safety_unavailable(policy: &Policy) -> ServeError {
    ServeError::invalid(
        "safety_score_unavailable",
        format!(
            "this policy was trained by {}: safety scores come from SafeDICE's discriminator, \
             which only SafeDICE policies trained by this version or later carry",
            policy.spec().algorithm
        ),
    )
}
