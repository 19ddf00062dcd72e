//! `/act`'s body and answer, whichever route asks (`/v1/policies/{id}/act`,
//! `/v1/models/{name}/act`): the observations are validated and run by the act path every
//! transport shares ([`crate::serving::act`]).

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::ApiError;
use crate::data::Actions;
pub use crate::serving::act::ACTION_BODY_LIMIT;
use crate::serving::act::{ActOptions, Acted, Observations, Served};

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
    /// true: also the safety scores of the returned actions (`safety`). Only SafeDICE policies
    /// carry the discriminator they come from; others answer 422 `safety_score_unavailable`.
    #[serde(default)]
    pub safety_score: bool,
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
    /// With `safety_score: true`: one score of each kind per observation.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub safety: Option<SafetyScoreList>,
}

/// The safety head's scores of the returned actions (docs/safety-scores.md).
#[derive(Debug, Serialize, ToSchema)]
pub struct SafetyScoreList {
    /// The discriminator's `log d^N(s,a) / d^U(s,a)` for the returned action: above 0, the pair
    /// looks more like the non-preferred demonstrations than like the unlabeled data.
    pub non_preferred_log_ratio: Vec<f32>,
    /// Distance from the observation to the nearest state of the training data, over the 99th
    /// percentile of that distance within the data: above 1, off the data's support.
    pub out_of_support: Vec<f32>,
}

/// `/act` on what a request resolved to (a policy by id in [`super::policies`], a named model
/// in [`super::model_serving`], whose statistics and shadow follow the request).
pub(crate) async fn act_on(served: &Served, request: ActRequest) -> Result<ActResponse, ApiError> {
    let spec = served.policy.spec();
    let observations = Observations::from_rows(&request.observations, spec.obs_dim)?;
    let width = spec.action_space.width();
    let options = ActOptions {
        deterministic: request.deterministic,
        seed: request.seed,
        safety_score: request.safety_score,
    };
    let Acted { actions, safety } = served.act(observations, options).await?;
    let actions = match actions {
        Actions::Continuous(values) => {
            ActionList::Continuous(values.chunks(width).map(<[f32]>::to_vec).collect())
        }
        Actions::Discrete(indices) => ActionList::Discrete(indices),
    };
    let safety = safety.map(|s| SafetyScoreList {
        non_preferred_log_ratio: s.non_preferred_log_ratio,
        out_of_support: s.out_of_support,
    });
    Ok(ActResponse { actions, safety })
}
