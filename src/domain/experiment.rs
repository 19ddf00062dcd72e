//! Experiments: a grid of algorithms ("arms") × seeds on one pair of datasets, queued as
//! ordinary jobs, whose results are the paper's metrics per arm as mean ± standard error over
//! the seeds (the paper reports every number that way, over 5 runs).

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::ExperimentId;
use crate::algo::Algorithm;

/// Most jobs one experiment may queue (arms × seeds).
pub const MAX_GRID: usize = 100;
/// Most seeds one experiment may list.
pub const MAX_SEEDS: usize = 50;

/// One entry of the grid's algorithm list.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Arm {
    /// How the results name it (default: the algorithm; must differ between arms).
    pub label: Option<String>,
    pub algorithm: Algorithm,
    /// This arm's configuration keys, over the experiment's `config` (the seed is the grid's).
    #[schema(value_type = Option<Object>)]
    pub config: Option<serde_json::Value>,
}

impl Arm {
    pub fn label(&self) -> String {
        self.label.clone().unwrap_or_else(|| self.algorithm.to_string())
    }
}

/// What an experiment runs, as stored.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExperimentSpec {
    pub unlabeled_dataset: String,
    pub non_preferred_dataset: Option<String>,
    pub arms: Vec<Arm>,
    pub seeds: Vec<u64>,
    /// The configuration keys every arm shares (e.g. `iterations`).
    pub config: Option<serde_json::Value>,
    /// The jobs' in-training evaluation, if any.
    pub eval: Option<serde_json::Value>,
    pub tags: Vec<String>,
}

/// A stored experiment.
#[derive(Clone, Debug, PartialEq)]
pub struct ExperimentRecord {
    pub id: ExperimentId,
    pub name: Option<String>,
    pub spec: ExperimentSpec,
    pub created_at: chrono::DateTime<chrono::Utc>,
}

/// The tag every job of an experiment carries (`GET /v1/jobs?tag=` finds them).
pub fn experiment_tag(id: &ExperimentId) -> String {
    format!("experiment={id}")
}

/// A job's configuration in the grid: the experiment's keys, then the arm's, then the seed.
pub fn job_config(
    common: Option<&serde_json::Value>,
    arm: Option<&serde_json::Value>,
    seed: u64,
) -> Result<serde_json::Value, String> {
    let mut merged = serde_json::Map::new();
    for (what, layer) in [("config", common), ("algorithms[].config", arm)] {
        match layer {
            None | Some(serde_json::Value::Null) => {}
            Some(serde_json::Value::Object(keys)) => {
                if keys.contains_key("seed") {
                    return Err(format!("{what}: `seed` is the grid's (use `seeds`)"));
                }
                merged.extend(keys.clone());
            }
            Some(other) => return Err(format!("{what} must be an object, got {other}")),
        }
    }
    merged.insert("seed".into(), seed.into());
    Ok(serde_json::Value::Object(merged))
}

/// Mean and standard error of one metric over seeds, with the values it came from.
#[derive(Clone, Debug, PartialEq, Serialize, ToSchema)]
pub struct Summary {
    pub mean: f64,
    /// Standard error of the mean: sample standard deviation / √n (absent for one value).
    pub se: Option<f64>,
    pub n: usize,
    /// The values it summarises: one per seed whose job has the metric, in the order of the
    /// experiment's `seeds` (the jobs list pairs each value with its seed).
    pub values: Vec<f64>,
}

impl Summary {
    pub fn of(values: Vec<f64>) -> Option<Summary> {
        let n = values.len();
        if n == 0 {
            return None;
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let se = (n > 1).then(|| {
            let variance = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
            (variance / n as f64).sqrt()
        });
        Some(Summary { mean, se, n, values })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn the_standard_error_is_the_sample_deviation_over_root_n() {
        let s = Summary::of(vec![1.0, 2.0, 3.0, 6.0]).unwrap();
        assert_eq!((s.mean, s.n), (3.0, 4));
        // Sample variance (4 + 1 + 0 + 9) / 3 = 14/3; SE = sqrt(14/3 / 4).
        assert!((s.se.unwrap() - (14.0f64 / 12.0).sqrt()).abs() < 1e-12);
        assert_eq!(Summary::of(vec![5.0]).unwrap().se, None);
        assert_eq!(Summary::of(vec![]), None);
    }

    #[test]
    fn a_jobs_config_layers_the_arm_over_the_experiment_and_takes_the_grids_seed() {
        let common = json!({"iterations": 100, "batch_size": 64});
        let arm = json!({"batch_size": 32});
        assert_eq!(
            job_config(Some(&common), Some(&arm), 3).unwrap(),
            json!({"iterations": 100, "batch_size": 32, "seed": 3})
        );
        assert!(job_config(Some(&json!({"seed": 1})), None, 0).unwrap_err().contains("seeds"));
        assert!(job_config(None, Some(&json!([1])), 0).unwrap_err().contains("object"));
    }
}
