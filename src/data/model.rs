//! The in-memory dataset model shared by parsers, the environments' data generators and the
//! training core: one struct of columns (row-major flat vectors), never per-transition objects.

use serde::{Deserialize, Serialize};

/// The action space of a dataset, as the API reports it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ActionSpace {
    /// A box `[low, high]^dim`; policies act in `[-1, 1]^dim` and are rescaled to this box.
    Continuous { dim: usize, low: Vec<f32>, high: Vec<f32> },
    /// `n` actions numbered `0..n`.
    Discrete { n: usize },
}

impl ActionSpace {
    /// Width of one action row in [`Actions`]: `dim` for continuous, 1 for discrete.
    pub fn width(&self) -> usize {
        match self {
            ActionSpace::Continuous { dim, .. } => *dim,
            ActionSpace::Discrete { .. } => 1,
        }
    }

    /// Width of the action as a network input: `dim`, or `n` for a one-hot discrete action.
    pub fn input_width(&self) -> usize {
        match self {
            ActionSpace::Continuous { dim, .. } => *dim,
            ActionSpace::Discrete { n } => *n,
        }
    }

    /// The box of a continuous dataset, inferred from its actions: `[-1, 1]` per dimension when
    /// every action lies inside it (the convention of D4RL/DSRL data), the observed per-dimension
    /// min/max otherwise (a constant dimension gets a unit-wide box so rescaling stays finite).
    pub fn infer_continuous(actions: &[f32], dim: usize) -> ActionSpace {
        let mut low = vec![f32::INFINITY; dim];
        let mut high = vec![f32::NEG_INFINITY; dim];
        for row in actions.chunks_exact(dim) {
            for (j, &a) in row.iter().enumerate() {
                low[j] = low[j].min(a);
                high[j] = high[j].max(a);
            }
        }
        let inside_unit_box = low.iter().all(|&l| l >= -1.0) && high.iter().all(|&h| h <= 1.0);
        if inside_unit_box {
            return ActionSpace::Continuous { dim, low: vec![-1.0; dim], high: vec![1.0; dim] };
        }
        for j in 0..dim {
            if high[j] - low[j] < 1e-6 {
                // Half a unit each side; from 2^24 on that is below the spacing of f32 and
                // would leave the box empty (0/0 when rescaling), so widen by the value's own
                // precision there, staying finite.
                let pad = 0.5f32.max(low[j].abs().max(high[j].abs()) * f32::EPSILON);
                low[j] = (low[j] - pad).max(f32::MIN);
                high[j] = (high[j] + pad).min(f32::MAX);
            }
        }
        ActionSpace::Continuous { dim, low, high }
    }

    /// Whether two spaces can be trained together (same kind and size; boxes may differ, the
    /// trainer uses the unlabeled dataset's box).
    pub fn compatible_with(&self, other: &ActionSpace) -> bool {
        match (self, other) {
            (ActionSpace::Continuous { dim: a, .. }, ActionSpace::Continuous { dim: b, .. }) => {
                a == b
            }
            (ActionSpace::Discrete { n: a }, ActionSpace::Discrete { n: b }) => a == b,
            _ => false,
        }
    }
}

/// The action column.
#[derive(Clone, Debug, PartialEq)]
pub enum Actions {
    /// `N × dim`, row-major, in the dataset's original units.
    Continuous(Vec<f32>),
    /// `N` action indices.
    Discrete(Vec<u32>),
}

/// The columns of a dataset before they are checked: what parsers and generators assemble,
/// and what [`Dataset::new`] turns into a [`Dataset`] once the columns agree.
#[derive(Clone, Debug, PartialEq)]
pub struct DatasetParts {
    pub obs_dim: usize,
    pub action_space: ActionSpace,
    /// `N × obs_dim`, row-major.
    pub observations: Vec<f32>,
    pub actions: Actions,
    /// `N × obs_dim`, row-major.
    pub next_observations: Vec<f32>,
    /// True where the transition ends its episode in a terminal state (not a time-out).
    pub terminals: Vec<bool>,
    /// Episode id of each transition; equal ids are contiguous.
    pub episode_ids: Vec<u32>,
    /// Per-transition rewards, kept for reporting only.
    pub rewards: Option<Vec<f32>>,
    /// Per-transition costs, kept for reporting only.
    pub costs: Option<Vec<f32>>,
}

/// A dataset of transitions, stored as columns. Episodes are contiguous runs of equal
/// `episode_ids`; the first transition of each episode gives the initial-state set p0.
///
/// Valid by construction: the only way to build one is [`Dataset::new`], which checks that
/// the columns agree (non-empty, matching lengths, finite values, contiguous episodes, actions
/// inside the action space), so code holding a `Dataset` need not check it again.
#[derive(Clone, Debug, PartialEq)]
pub struct Dataset {
    parts: DatasetParts,
    /// What the parser noticed and the user should know (a missing column derived, rows
    /// dropped, no episode ends marked); reported with the dataset, never an error.
    warnings: Vec<String>,
}

/// Why a [`Dataset`] is internally inconsistent.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ModelError {
    #[error("the dataset has no transitions")]
    Empty,
    #[error("column `{column}` has {actual} values, expected {expected}")]
    ColumnLength { column: &'static str, expected: usize, actual: usize },
    #[error("column `{column}` holds a non-finite value at transition {index}")]
    NonFinite { column: &'static str, index: usize },
    #[error("episode {episode} is not contiguous: it reappears at transition {index}")]
    NonContiguousEpisode { episode: u32, index: usize },
    #[error("discrete action {action} at transition {index} is outside 0..{n}")]
    ActionOutOfRange { action: u32, index: usize, n: usize },
    #[error("action space does not match the action column")]
    ActionKind,
}

impl Dataset {
    /// The dataset of these columns, or why they do not agree.
    pub fn new(parts: DatasetParts) -> Result<Dataset, ModelError> {
        let dataset = Dataset { parts, warnings: Vec::new() };
        dataset.check()?;
        Ok(dataset)
    }

    /// The dataset with a warning for its uploader.
    pub fn with_warning(mut self, warning: String) -> Dataset {
        self.warnings.push(warning);
        self
    }

    /// What its parser noticed (see [`Dataset::with_warning`]).
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// The columns, to be reassembled (through [`Dataset::new`] again) or consumed.
    pub fn into_parts(self) -> DatasetParts {
        self.parts
    }

    /// Width of one observation row.
    pub fn obs_dim(&self) -> usize {
        self.parts.obs_dim
    }

    pub fn action_space(&self) -> &ActionSpace {
        &self.parts.action_space
    }

    /// `N × obs_dim`, row-major.
    pub fn observations(&self) -> &[f32] {
        &self.parts.observations
    }

    pub fn actions(&self) -> &Actions {
        &self.parts.actions
    }

    /// `N × obs_dim`, row-major.
    pub fn next_observations(&self) -> &[f32] {
        &self.parts.next_observations
    }

    /// True where the transition ends its episode in a terminal state (not a time-out).
    pub fn terminals(&self) -> &[bool] {
        &self.parts.terminals
    }

    /// Episode id of each transition; equal ids are contiguous.
    pub fn episode_ids(&self) -> &[u32] {
        &self.parts.episode_ids
    }

    /// Per-transition rewards, kept for reporting only.
    pub fn rewards(&self) -> Option<&[f32]> {
        self.parts.rewards.as_deref()
    }

    /// Per-transition costs, kept for reporting only.
    pub fn costs(&self) -> Option<&[f32]> {
        self.parts.costs.as_deref()
    }

    /// Number of transitions.
    pub fn len(&self) -> usize {
        self.parts.terminals.len()
    }

    pub fn is_empty(&self) -> bool {
        self.parts.terminals.is_empty()
    }

    /// Observation row `i`.
    pub fn obs(&self, i: usize) -> &[f32] {
        &self.parts.observations[i * self.parts.obs_dim..(i + 1) * self.parts.obs_dim]
    }

    /// Next-observation row `i`.
    pub fn next_obs(&self, i: usize) -> &[f32] {
        &self.parts.next_observations[i * self.parts.obs_dim..(i + 1) * self.parts.obs_dim]
    }

    /// Half-open index ranges of the episodes, in order.
    pub fn episode_ranges(&self) -> Vec<std::ops::Range<usize>> {
        let mut ranges = Vec::new();
        let mut start = 0;
        for i in 1..=self.len() {
            if i == self.len() || self.parts.episode_ids[i] != self.parts.episode_ids[start] {
                ranges.push(start..i);
                start = i;
            }
        }
        ranges
    }

    /// Index of the first transition of every episode (the initial-state set p0).
    pub fn episode_starts(&self) -> Vec<usize> {
        self.episode_ranges().into_iter().map(|r| r.start).collect()
    }

    /// Number of episodes.
    pub fn episodes(&self) -> usize {
        self.episode_ranges().len()
    }

    /// Checks that the columns agree with each other; [`Dataset::new`] runs it.
    fn check(&self) -> Result<(), ModelError> {
        let n = self.len();
        if n == 0 {
            return Err(ModelError::Empty);
        }
        let expect = |column, expected, actual| {
            if expected == actual {
                Ok(())
            } else {
                Err(ModelError::ColumnLength { column, expected, actual })
            }
        };
        expect("observations", n * self.parts.obs_dim, self.parts.observations.len())?;
        expect("next_observations", n * self.parts.obs_dim, self.parts.next_observations.len())?;
        expect("episode_ids", n, self.parts.episode_ids.len())?;
        match (&self.parts.actions, &self.parts.action_space) {
            (Actions::Continuous(a), ActionSpace::Continuous { dim, .. }) => {
                expect("actions", n * dim, a.len())?;
                check_finite("actions", a, *dim)?;
            }
            (Actions::Discrete(a), ActionSpace::Discrete { n: count }) => {
                expect("actions", n, a.len())?;
                if let Some((index, &action)) =
                    a.iter().enumerate().find(|(_, &x)| x as usize >= *count)
                {
                    return Err(ModelError::ActionOutOfRange { action, index, n: *count });
                }
            }
            _ => return Err(ModelError::ActionKind),
        }
        check_finite("observations", &self.parts.observations, self.parts.obs_dim)?;
        check_finite("next_observations", &self.parts.next_observations, self.parts.obs_dim)?;
        for (column, values) in [("rewards", &self.parts.rewards), ("costs", &self.parts.costs)] {
            if let Some(v) = values {
                expect(column, n, v.len())?;
                check_finite(column, v, 1)?;
            }
        }
        let mut seen = std::collections::HashSet::new();
        for (i, &id) in self.parts.episode_ids.iter().enumerate() {
            let continues = i > 0 && self.parts.episode_ids[i - 1] == id;
            if !continues && !seen.insert(id) {
                return Err(ModelError::NonContiguousEpisode { episode: id, index: i });
            }
        }
        Ok(())
    }
}

fn check_finite(column: &'static str, values: &[f32], width: usize) -> Result<(), ModelError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(pos) => Err(ModelError::NonFinite { column, index: pos / width.max(1) }),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_episodes() -> DatasetParts {
        DatasetParts {
            obs_dim: 1,
            action_space: ActionSpace::Discrete { n: 2 },
            observations: vec![0.0, 1.0, 2.0, 10.0, 11.0],
            actions: Actions::Discrete(vec![0, 1, 1, 0, 0]),
            next_observations: vec![1.0, 2.0, 3.0, 11.0, 12.0],
            terminals: vec![false, false, true, false, false],
            episode_ids: vec![7, 7, 7, 3, 3],
            rewards: None,
            costs: Some(vec![0.0; 5]),
        }
    }

    #[test]
    fn episodes_are_contiguous_runs() {
        let d = Dataset::new(two_episodes()).unwrap();
        assert_eq!(d.episode_ranges(), vec![0..3, 3..5]);
        assert_eq!(d.episode_starts(), vec![0, 3]);
        assert_eq!(d.clone().into_parts(), two_episodes());
    }

    #[test]
    fn new_rejects_reappearing_episode_and_bad_values() {
        let mut d = two_episodes();
        d.episode_ids = vec![7, 7, 3, 7, 3];
        assert_eq!(Dataset::new(d), Err(ModelError::NonContiguousEpisode { episode: 7, index: 3 }));
        let mut d = two_episodes();
        d.next_observations[4] = f32::NAN;
        assert_eq!(
            Dataset::new(d),
            Err(ModelError::NonFinite { column: "next_observations", index: 4 })
        );
        let mut d = two_episodes();
        d.actions = Actions::Discrete(vec![0, 1, 2, 0, 0]);
        assert_eq!(
            Dataset::new(d),
            Err(ModelError::ActionOutOfRange { action: 2, index: 2, n: 2 })
        );
    }

    #[test]
    fn continuous_box_is_unit_when_actions_fit_it() {
        let space = ActionSpace::infer_continuous(&[-1.0, 0.5, 1.0, -0.2], 2);
        assert_eq!(
            space,
            ActionSpace::Continuous { dim: 2, low: vec![-1.0; 2], high: vec![1.0; 2] }
        );
        let space = ActionSpace::infer_continuous(&[-3.0, 2.0, 5.0, 2.0], 2);
        assert_eq!(
            space,
            ActionSpace::Continuous { dim: 2, low: vec![-3.0, 1.5], high: vec![5.0, 2.5] }
        );
    }

    #[test]
    fn a_constant_dimension_gets_a_box_of_positive_width_at_any_magnitude() {
        // Regression: from 2^24 on, value ± 0.5 rounds back to the value, and the box of a
        // constant dimension was empty (the NPZ reader then refused the writer's own file).
        for v in [3.0, 16_777_216.0, -1e30, 3e38, f32::MAX, f32::MIN] {
            let ActionSpace::Continuous { low, high, .. } = ActionSpace::infer_continuous(&[v], 1)
            else {
                unreachable!()
            };
            assert!(low[0] < high[0] && low[0] <= v && v <= high[0], "{v}: [{low:?}, {high:?}]");
            assert!(low[0].is_finite() && high[0].is_finite(), "{v}: [{low:?}, {high:?}]");
        }
    }
}
