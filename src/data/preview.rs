//! A look at a stored dataset without downloading it: its first transitions and a summary of
//! its first episodes (length, return, cost, how it ended).

use serde::Serialize;
use utoipa::ToSchema;

use super::model::{Actions, Dataset};

/// One transition as the preview shows it.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct TransitionRow {
    /// Row number in the dataset, from 0.
    pub index: usize,
    /// The episode's number in the dataset, from 0 (not the uploaded episode id).
    pub episode: usize,
    pub obs: Vec<f32>,
    /// The action: a vector (continuous) or an index (discrete).
    #[schema(value_type = Value)]
    pub action: serde_json::Value,
    pub reward: Option<f32>,
    pub cost: Option<f32>,
    pub terminal: bool,
}

/// One episode's summary.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct EpisodeSummary {
    /// The episode's number in the dataset, from 0.
    pub episode: usize,
    /// Row of its first transition.
    pub start: usize,
    pub length: usize,
    /// Sum of its rewards, if the dataset has rewards.
    #[serde(rename = "return")]
    pub episode_return: Option<f64>,
    /// Sum of its costs, if the dataset has costs.
    pub cost: Option<f64>,
    /// Whether it ends in a terminal state (else it was cut off).
    pub terminal: bool,
}

/// The first `rows` transitions and the first `episodes` episodes.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct DatasetPreview {
    pub transitions: Vec<TransitionRow>,
    pub episodes: Vec<EpisodeSummary>,
}

pub fn preview(d: &Dataset, rows: usize, episodes: usize) -> DatasetPreview {
    let ranges = d.episode_ranges();
    let episode_of = |i: usize| ranges.partition_point(|r| r.end <= i);
    let sum = |column: Option<&[f32]>, r: &std::ops::Range<usize>| {
        column.map(|c| c[r.clone()].iter().map(|&v| f64::from(v)).sum())
    };
    let transitions = (0..rows.min(d.len()))
        .map(|i| TransitionRow {
            index: i,
            episode: episode_of(i),
            obs: d.obs(i).to_vec(),
            action: action_json(d.actions(), d.action_space().width(), i),
            reward: d.rewards().map(|r| r[i]),
            cost: d.costs().map(|c| c[i]),
            terminal: d.terminals()[i],
        })
        .collect();
    let episodes = ranges
        .iter()
        .take(episodes)
        .enumerate()
        .map(|(episode, r)| EpisodeSummary {
            episode,
            start: r.start,
            length: r.len(),
            episode_return: sum(d.rewards(), r),
            cost: sum(d.costs(), r),
            terminal: d.terminals()[r.end - 1],
        })
        .collect();
    DatasetPreview { transitions, episodes }
}

fn action_json(actions: &Actions, width: usize, i: usize) -> serde_json::Value {
    match actions {
        Actions::Continuous(values) => serde_json::json!(values[i * width..(i + 1) * width]),
        Actions::Discrete(indices) => serde_json::json!(indices[i]),
    }
}
