//! Actions from a loaded policy, whichever route asks: `/v1/policies/{id}/act`,
//! `/v1/models/{name}/act` and the KServe v2 `infer` routes all validate observations into
//! [`Observations`] and run them through [`act`] here; `/act`'s body and answer live here too.

use std::sync::Arc;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::ApiError;
use crate::algo::Policy;
use crate::data::Actions;

/// Largest batch one request may send.
pub const MAX_BATCH_ROWS: usize = 16_384;
/// Largest request body of the action routes (`/act`, `/v2/…/infer`): a full batch of 16,384
/// observations as JSON needs far more than the 2 MB every other JSON body may have (about 12
/// bytes per value: 16,384 rows of 80 values), and as binary tensor data up to 256 values per
/// row. A larger body is refused with 413 before it is read.
pub const ACTION_BODY_LIMIT: usize = 16 << 20;
/// Batches up to this many rows run on the request's task (a few microseconds of matrix
/// products); larger ones move to a blocking thread so they cannot stall other requests.
const INLINE_ROWS: usize = 64;

/// Validated observations: `rows × obs_dim`, row-major, all finite.
pub struct Observations {
    pub values: Vec<f32>,
    pub rows: usize,
}

impl Observations {
    /// From `/act`'s list of rows.
    pub fn from_rows(rows: &[Vec<f64>], obs_dim: usize) -> Result<Self, ApiError> {
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

    /// From a flat row-major buffer of `rows × obs_dim` values.
    pub(super) fn from_flat(flat: &[f64], rows: usize, obs_dim: usize) -> Result<Self, ApiError> {
        check_batch_size(rows)?;
        let values = flat
            .iter()
            .enumerate()
            .map(|(k, &v)| finite(v, || format!("data[{}][{}]", k / obs_dim, k % obs_dim)))
            .collect::<Result<_, _>>()?;
        Ok(Observations { values, rows })
    }
}

fn check_batch_size(rows: usize) -> Result<(), ApiError> {
    if rows == 0 {
        return Err(invalid("the batch is empty: send at least one observation".into()));
    }
    if rows > MAX_BATCH_ROWS {
        return Err(ApiError::unprocessable(
            "batch_too_large",
            format!("{rows} observations in one request; at most {MAX_BATCH_ROWS}"),
        ));
    }
    Ok(())
}

fn finite(v: f64, at: impl FnOnce() -> String) -> Result<f32, ApiError> {
    let x = v as f32;
    if x.is_finite() {
        Ok(x)
    } else {
        Err(invalid(format!("{} is {v}, which is not a finite 32-bit float", at())))
    }
}

fn invalid(message: String) -> ApiError {
    ApiError::unprocessable("invalid_observations", message)
}

/// Runs the policy on validated observations: deterministic (tanh of the mean / argmax), or
/// sampled with `seed` (reproducible) or fresh entropy.
pub async fn act(
    policy: Arc<Policy>,
    observations: Observations,
    deterministic: bool,
    seed: Option<u64>,
) -> Result<Actions, ApiError> {
    let mut rng = match seed {
        Some(seed) => ChaCha8Rng::seed_from_u64(seed),
        None if deterministic => ChaCha8Rng::seed_from_u64(0),
        None => ChaCha8Rng::from_os_rng(),
    };
    let mut run = move || {
        policy
            .act(&observations.values, deterministic, &mut rng)
            .map_err(|e| ApiError::Internal(anyhow::anyhow!("policy inference failed: {e}")))
    };
    if observations.rows <= INLINE_ROWS {
        run()
    } else {
        tokio::task::spawn_blocking(run).await?
    }
}

/// `POST /v1/policies/{id}/act` body.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ActRequest {
    /// A batch of observations (1 to 16384 rows of `obs_dim` finite numbers each), in the
    /// dataset's original units. The body may be up to 16 MiB (other JSON bodies: 2 MB).
    #[schema(min_items = 1, max_items = 16384)]
    pub observations: Vec<Vec<f64>>,
    /// true (default): tanh of the Gaussian mean / argmax. false: sample.
    #[serde(default = "yes")]
    pub deterministic: bool,
    /// Seed for sampling (`deterministic: false`); the same seed gives the same actions. At
    /// most 2^63 - 1.
    #[serde(default, deserialize_with = "crate::domain::deserialize_optional_seed")]
    #[schema(maximum = 9223372036854775807_u64)]
    pub seed: Option<u64>,
}

fn yes() -> bool {
    true
}

/// One action per observation.
#[derive(Debug, Serialize, ToSchema)]
#[serde(untagged)]
pub enum ActionList {
    /// Continuous spaces: a list of floats inside the action box per observation.
    Continuous(Vec<Vec<f32>>),
    /// Discrete spaces: an action index per observation.
    Discrete(Vec<u32>),
}

/// Actions for the observations, in order.
#[derive(Debug, Serialize, ToSchema)]
pub struct ActResponse {
    pub actions: ActionList,
}

/// `/act` on a loaded policy (by id in [`super::policies`], by model name in
/// [`super::model_serving`]).
pub(crate) async fn act_on(
    policy: std::sync::Arc<crate::algo::Policy>,
    request: ActRequest,
) -> Result<ActResponse, ApiError> {
    let spec = policy.spec();
    let observations = Observations::from_rows(&request.observations, spec.obs_dim)?;
    let width = spec.action_space.width();
    let actions = act(policy, observations, request.deterministic, request.seed).await?;
    let actions = match actions {
        Actions::Continuous(values) => {
            ActionList::Continuous(values.chunks(width).map(<[f32]>::to_vec).collect())
        }
        Actions::Discrete(indices) => ActionList::Discrete(indices),
    };
    Ok(ActResponse { actions })
}
