//! `/v1/algorithms`: the algorithms the service trains, with every preset's resolved
//! configuration. It is the one place clients (the dashboard among them) learn names, colours and
//! defaults from, so none of them keeps its own copy.

use axum::extract::Path;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::{ApiError, ErrorBody};
use super::extract::Json;
use super::AppState;
use crate::algo::registry::{Knob, StepPlan};
use crate::algo::{self, Algorithm, Preset};

/// An algorithm and its presets.
#[derive(Debug, serde::Serialize, ToSchema)]
pub struct AlgorithmInfo {
    pub name: Algorithm,
    /// The name as the paper writes it.
    #[schema(example = "SafeDICE")]
    pub label: &'static str,
    /// Its accent colour in charts and the dashboard (CSS hex).
    #[schema(example = "#2563eb")]
    pub color: &'static str,
    /// Whether a job needs a labeled non-preferred dataset.
    pub needs_non_preferred: bool,
    /// The configuration keys a job form offers as fields, in order: the common ones, then the
    /// algorithm's own.
    pub knobs: Vec<Knob>,
    /// Each preset (`service`, `paper`, `authors-code`) with every knob's value: what a job's
    /// `config` resolves to when it names only the preset.
    pub presets: Vec<PresetConfig>,
}

/// One preset's resolved configuration.
#[derive(Debug, serde::Serialize, ToSchema)]
pub struct PresetConfig {
    #[schema(example = "service")]
    pub name: String,
    #[schema(value_type = Object)]
    pub config: serde_json::Value,
}

/// Every algorithm, in the order the service lists them.
#[derive(Debug, serde::Serialize, ToSchema)]
pub struct AlgorithmList {
    pub items: Vec<AlgorithmInfo>,
}

/// What a job with a given `config` would run, resolved without queueing it.
#[derive(Debug, serde::Serialize, ToSchema)]
pub struct ConfigPlan {
    pub algorithm: Algorithm,
    /// The resolved configuration: every knob with its value, as the job would store it.
    #[schema(value_type = Object)]
    pub config: serde_json::Value,
    pub steps: StepPlan,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(list_algorithms)).routes(routes!(plan_config))
}

/// The algorithms with their labels, colours and every preset's resolved configuration.
#[utoipa::path(get, path = "/v1/algorithms", tag = "algorithms",
    responses((status = 200, description = "Every algorithm", body = AlgorithmList)))]
async fn list_algorithms() -> Json<AlgorithmList> {
    Json(algorithm_list())
}

/// Resolves a job's `config` (a preset and overrides, `{}` for the service preset) without
/// queueing anything: its every knob and the steps the run takes, with the configuration checks
/// and errors of `POST /v1/jobs` (those that need the datasets aside). The dashboard's job form
/// shows the plan from it as the knobs are typed.
#[utoipa::path(post, path = "/v1/algorithms/{name}/plan", tag = "algorithms",
    params(("name" = Algorithm, Path, description = "The algorithm, as a job's `algorithm`")),
    request_body(content = Object, description = "A job's `config`",
        example = json!({"preset": "service", "iterations": 20000})),
    responses(
        (status = 200, body = ConfigPlan),
        (status = 404, description = "No such algorithm", body = ErrorBody),
        (status = 422, description = "A configuration a job would be refused for \
            (`invalid_config`, the message names the key)", body = ErrorBody),
    ))]
async fn plan_config(
    Path(name): Path<String>,
    Json(config): Json<serde_json::Value>,
) -> Result<Json<ConfigPlan>, ApiError> {
    let algorithm: Algorithm = serde_json::from_value(serde_json::Value::String(name.clone()))
        .map_err(|_| ApiError::not_found("algorithm", &name))?;
    let resolved = algo::resolve_config(algorithm, &config)
        .map_err(|e| ApiError::unprocessable("invalid_config", e.message))?;
    Ok(Json(ConfigPlan {
        algorithm,
        steps: StepPlan::of(&resolved),
        config: serde_json::to_value(&resolved).expect("a configuration serialises"),
    }))
}

/// The table behind `/v1/algorithms` (and the dashboard's copy of it).
pub fn algorithm_list() -> AlgorithmList {
    let items = Algorithm::ALL
        .into_iter()
        .map(|algorithm| AlgorithmInfo {
            name: algorithm,
            label: algorithm.spec().label,
            color: algorithm.spec().color,
            needs_non_preferred: algorithm.spec().needs_non_preferred,
            knobs: algorithm.spec().knobs(),
            presets: Preset::ALL
                .into_iter()
                .map(|preset| preset_config(algorithm, preset))
                .collect(),
        })
        .collect();
    AlgorithmList { items }
}

fn preset_config(algorithm: Algorithm, preset: Preset) -> PresetConfig {
    let name = serde_json::to_value(preset).expect("a preset serialises to its name");
    let config = algo::resolve_config(algorithm, &serde_json::json!({ "preset": name }))
        .expect("every preset resolves");
    PresetConfig {
        name: name.as_str().unwrap_or_default().to_owned(),
        config: serde_json::to_value(config).expect("a configuration serialises"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_algorithm_lists_its_three_presets_with_the_preset_knob_values() {
        let list = algorithm_list();
        assert_eq!(list.items.len(), Algorithm::ALL.len());
        let safedice = &list.items[0];
        assert_eq!((safedice.name, safedice.label), (Algorithm::Safedice, "SafeDICE"));
        let names: Vec<_> = safedice.presets.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, ["service", "paper", "authors-code"]);
        let service = &safedice.presets[0].config;
        assert_eq!(service["iterations"], 100_000);
        assert_eq!(service["batch_size"], 512);
        assert_eq!(safedice.presets[1].config["iterations"], 1_000_000);
    }
}
