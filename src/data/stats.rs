//! Per-episode summaries reported with a dataset: episode lengths always, episode returns and
//! costs (sums over the episode) when the dataset has rewards / costs.

use serde::{Deserialize, Serialize};

use super::model::Dataset;

/// Summary of one per-episode quantity. `std` is the population standard deviation (ddof 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Summary {
    pub count: usize,
    pub mean: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
}

impl Summary {
    /// `None` for an empty sample.
    pub fn of(values: &[f64]) -> Option<Summary> {
        if values.is_empty() {
            return None;
        }
        let count = values.len();
        let mean = values.iter().sum::<f64>() / count as f64;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / count as f64;
        Some(Summary {
            count,
            mean,
            std: var.sqrt(),
            min: values.iter().copied().fold(f64::INFINITY, f64::min),
            max: values.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        })
    }
}

/// Statistics of a dataset, as the dataset resource reports them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct DatasetStats {
    pub transitions: usize,
    pub episodes: usize,
    /// Episodes whose last transition is terminal (the rest ended by a time limit or the data).
    pub terminal_episodes: usize,
    /// Episode lengths in transitions.
    pub episode_length: Summary,
    /// Sum of rewards per episode; absent when the dataset has no rewards.
    pub episode_return: Option<Summary>,
    /// Sum of costs per episode; absent when the dataset has no costs.
    pub episode_cost: Option<Summary>,
}

/// Computes [`DatasetStats`]; sums are accumulated in f64. An empty dataset (which no parser
/// returns) reports zero counts and zero summaries.
pub fn stats(d: &Dataset) -> DatasetStats {
    let ranges = d.episode_ranges();
    let lengths: Vec<f64> = ranges.iter().map(|r| r.len() as f64).collect();
    let sums = |column: Option<&[f32]>| {
        column.and_then(|v| {
            let totals: Vec<f64> =
                ranges.iter().map(|r| v[r.clone()].iter().map(|&x| x as f64).sum()).collect();
            Summary::of(&totals)
        })
    };
    DatasetStats {
        transitions: d.len(),
        episodes: ranges.len(),
        terminal_episodes: ranges.iter().filter(|r| d.terminals()[r.end - 1]).count(),
        episode_length: Summary::of(&lengths).unwrap_or(Summary {
            count: 0,
            mean: 0.0,
            std: 0.0,
            min: 0.0,
            max: 0.0,
        }),
        episode_return: sums(d.rewards()),
        episode_cost: sums(d.costs()),
    }
}
