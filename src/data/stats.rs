//! Per-episode summaries reported with a dataset: episode lengths always, episode returns and
//! costs (sums over the episode) when the dataset has rewards / costs.

use serde::{Deserialize, Serialize};

use super::model::{Actions, Dataset};

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
    /// What the upload's parser noticed and you should know, e.g. `next_observations` derived
    /// from the next row and the transitions that had none dropped, no episode ends marked, or
    /// groups of an HDF5 file not read. Empty when there is nothing to say.
    #[serde(default)]
    pub warnings: Vec<String>,
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
        warnings: d.warnings().to_vec(),
    }
}

/// Per-dimension (min, max, mean, std) of a row-major `rows × width` column.
fn column_ranges(values: &[f32], width: usize) -> Vec<(f64, f64, f64, f64)> {
    (0..width)
        .map(|j| {
            let column: Vec<f64> =
                values.iter().skip(j).step_by(width).map(|&v| v as f64).collect();
            let summary = Summary::of(&column).expect("datasets are not empty");
            (summary.min, summary.max, summary.mean, summary.std)
        })
        .collect()
}

/// Root-mean-square of the values.
fn rms(values: &[f32]) -> f64 {
    let sum: f64 = values.iter().map(|&v| f64::from(v) * f64::from(v)).sum();
    (sum / values.len().max(1) as f64).sqrt()
}

/// Where D^N does not look like the same kind of data as D^U: actions outside D^U's range (the
/// policy acts in D^U's box) or observations on another scale (a unit or normalisation that
/// differs between the two files). Each is a warning for the job's log, never an error: the
/// discriminator would separate such data by its scale rather than by what was unsafe in it.
pub fn disagreements(unlabeled: &Dataset, non_preferred: &Dataset) -> Vec<String> {
    let mut warnings = Vec::new();
    if let (Actions::Continuous(u), Actions::Continuous(n)) =
        (unlabeled.actions(), non_preferred.actions())
    {
        let width = unlabeled.action_space().width();
        let (u, n) = (column_ranges(u, width), column_ranges(n, width));
        let outside = u.iter().zip(&n).enumerate().find(|(_, (u, n))| {
            let slack = 0.1 * (u.1 - u.0).max(1e-6);
            n.0 < u.0 - slack || n.1 > u.1 + slack
        });
        if let Some((j, (u, n))) = outside {
            warnings.push(format!(
                "D^N's actions span [{:.3}, {:.3}] in dimension {j} where D^U's span [{:.3}, \
                 {:.3}]: the policy acts within D^U's range, so check both files use the same \
                 action units",
                n.0, n.1, u.0, u.1
            ));
        }
    }
    // The whole observation's scale, not each dimension's: a feature that one set never varies
    // (a cell of a one-hot grid D^N never visits) is data, while a unit or a normalisation
    // that differs between the files moves every dimension at once.
    let (u, n) = (rms(unlabeled.observations()), rms(non_preferred.observations()));
    if u > 0.0 && n > 0.0 && !(0.1..=10.0).contains(&(n / u)) {
        warnings.push(format!(
            "D^N's observations have a root-mean-square of {n:.4} where D^U's have {u:.4} ({:.1}x): \
             check both files are on the same scale (the same units, the same normalisation)",
            n / u
        ));
    }
    warnings
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::model::{ActionSpace, DatasetParts};

    fn dataset(observations: Vec<f32>, actions: Vec<f32>) -> Dataset {
        let n = actions.len();
        Dataset::new(DatasetParts {
            obs_dim: 1,
            action_space: ActionSpace::infer_continuous(&actions, 1),
            next_observations: observations.clone(),
            observations,
            actions: Actions::Continuous(actions),
            terminals: vec![false; n],
            episode_ids: vec![0; n],
            rewards: None,
            costs: None,
        })
        .unwrap()
    }

    #[test]
    fn data_on_another_scale_or_action_range_is_named() {
        let u = dataset(vec![0.0, 1.0, 2.0, 3.0], vec![-1.0, -0.5, 0.5, 1.0]);
        assert!(disagreements(&u, &dataset(vec![0.5, 1.5, 2.5], vec![-0.9, 0.0, 0.9])).is_empty());
        let wide = disagreements(&u, &dataset(vec![0.5, 1.5, 2.5], vec![-3.0, 0.0, 3.0]));
        assert_eq!(wide.len(), 1);
        assert!(wide[0].starts_with("D^N's actions span [-3.000, 3.000] in dimension 0"));
        let scaled = disagreements(&u, &dataset(vec![0.0, 100.0, 200.0], vec![-1.0, 0.0, 1.0]));
        assert_eq!(scaled.len(), 1);
        // sqrt((0 + 1e4 + 4e4) / 3) against sqrt((0 + 1 + 4 + 9) / 4).
        assert!(
            scaled[0].starts_with("D^N's observations have a root-mean-square of 129.0994"),
            "{scaled:?}"
        );
        // A dimension D^N never varies (a one-hot cell it never visits) is not a scale.
        let one_hot = |cells: &[usize]| {
            let observations = cells
                .iter()
                .flat_map(|&c| (0..3).map(move |j| f32::from(u8::from(j == c))))
                .collect();
            Dataset::new(DatasetParts {
                obs_dim: 3,
                action_space: ActionSpace::Discrete { n: 2 },
                next_observations: vec![0.0; cells.len() * 3],
                observations,
                actions: Actions::Discrete(vec![0; cells.len()]),
                terminals: vec![false; cells.len()],
                episode_ids: vec![0; cells.len()],
                rewards: None,
                costs: None,
            })
            .unwrap()
        };
        assert!(disagreements(&one_hot(&[0, 1, 2, 1]), &one_hot(&[0, 1, 1])).is_empty());
    }
}
