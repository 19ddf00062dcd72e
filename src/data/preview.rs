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

/// The per-transition columns an episode summary reads: a preview of many episodes needs these
/// (9-13 bytes a transition) without the observations and actions.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EpisodeColumns {
    pub episode_ids: Vec<u32>,
    pub terminals: Vec<bool>,
    pub rewards: Option<Vec<f32>>,
    pub costs: Option<Vec<f32>>,
}

impl EpisodeColumns {
    /// The columns of a whole dataset.
    pub fn of(d: &Dataset) -> EpisodeColumns {
        EpisodeColumns {
            episode_ids: d.episode_ids().to_vec(),
            terminals: d.terminals().to_vec(),
            rewards: d.rewards().map(<[f32]>::to_vec),
            costs: d.costs().map(<[f32]>::to_vec),
        }
    }

    /// Each episode's rows: runs of one episode id, as [`Dataset::episode_ranges`].
    fn episode_ranges(&self) -> Vec<std::ops::Range<usize>> {
        let ids = &self.episode_ids;
        let mut ranges = Vec::new();
        let mut start = 0;
        for i in 1..=ids.len() {
            if i == ids.len() || ids[i] != ids[start] {
                ranges.push(start..i);
                start = i;
            }
        }
        ranges
    }
}

/// The first `rows` transitions of `d` and its first `episodes` episodes.
pub fn preview(d: &Dataset, rows: usize, episodes: usize) -> DatasetPreview {
    preview_parts(d, rows, &EpisodeColumns::of(d), episodes)
}

/// A preview from the dataset's first rows (`head`, at least `rows` of them or all) and the
/// episode columns of at least its first `episodes` episodes (or all): what a preview of a
/// stored dataset reads instead of the whole file.
pub fn preview_parts(
    head: &Dataset,
    rows: usize,
    columns: &EpisodeColumns,
    episodes: usize,
) -> DatasetPreview {
    let ranges = columns.episode_ranges();
    let episode_of = |i: usize| ranges.partition_point(|r| r.end <= i);
    let sum = |column: Option<&Vec<f32>>, r: &std::ops::Range<usize>| {
        column.map(|c| c[r.clone()].iter().map(|&v| f64::from(v)).sum())
    };
    let transitions = (0..rows.min(head.len()))
        .map(|i| TransitionRow {
            index: i,
            episode: episode_of(i),
            obs: head.obs(i).to_vec(),
            action: action_json(head.actions(), head.action_space().width(), i),
            reward: head.rewards().map(|r| r[i]),
            cost: head.costs().map(|c| c[i]),
            terminal: head.terminals()[i],
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
            episode_return: sum(columns.rewards.as_ref(), r),
            cost: sum(columns.costs.as_ref(), r),
            terminal: columns.terminals[r.end - 1],
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
