//! Demonstration data in the paper's setting (section 5): an abundant *unlabeled* set D^U that
//! mixes preferred and non-preferred episodes (shuffled), and a scarce *labeled* set D^N of
//! fresh non-preferred episodes. Behind `safedice datagen`.

use std::io;
use std::path::Path;

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use super::metrics::mean_return_and_cost;
use super::rollout::{assemble, demonstration_records, EpisodeOutcome, RolloutError};
use super::{
    derive_seed, reference_stats, stream, Profile, ReferenceStats, Registered, Task, UnknownEnv,
};
use crate::data::{write_csv, write_jsonl, write_npz, Dataset, Format};

/// What to generate.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DatagenSpec {
    pub env: String,
    /// Preferred episodes in the unlabeled set.
    pub preferred: usize,
    /// Non-preferred episodes in the unlabeled set.
    pub non_preferred: usize,
    /// Episodes in the labeled non-preferred set.
    pub labeled: usize,
    pub seed: u64,
}

/// Mean episode return and cost of a group of generated episodes.
#[derive(Clone, Debug, PartialEq, Serialize, utoipa::ToSchema)]
pub struct GroupProfile {
    pub episodes: usize,
    pub transitions: usize,
    pub mean_return: f64,
    pub mean_cost: f64,
}

impl GroupProfile {
    fn of(outcomes: &[EpisodeOutcome]) -> GroupProfile {
        let (mean_return, mean_cost) = mean_return_and_cost(outcomes);
        GroupProfile {
            episodes: outcomes.len(),
            transitions: outcomes.iter().map(|o| o.length).sum(),
            mean_return,
            mean_cost,
        }
    }
}

/// Written next to the data: how it was made and what it contains.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Manifest {
    pub spec: DatagenSpec,
    /// The unlabeled set's preferred and non-preferred parts, and the labeled set.
    pub unlabeled_preferred: GroupProfile,
    pub unlabeled_non_preferred: GroupProfile,
    pub labeled_non_preferred: GroupProfile,
    /// The environment's reference statistics that evaluation normalises with.
    pub reference: ReferenceStats,
    /// Files written, relative to the output directory (filled in by [`write_generated`]).
    pub files: Vec<String>,
    /// Ground truth for diagnostics only (a learner must not see it): the episode ids of the
    /// unlabeled set that came from the non-preferred demonstrator.
    pub unlabeled_non_preferred_episode_ids: Vec<u32>,
}

/// The generated sets.
#[derive(Clone, Debug, PartialEq)]
pub struct Generated {
    pub unlabeled: Dataset,
    /// None when no labeled episodes were asked for.
    pub labeled_non_preferred: Option<Dataset>,
    pub manifest: Manifest,
}

/// Why nothing was generated.
#[derive(Debug, thiserror::Error)]
pub enum DatagenError {
    #[error(transparent)]
    UnknownEnv(#[from] UnknownEnv),
    #[error("the unlabeled set needs at least one episode (preferred + non-preferred)")]
    NoUnlabeled,
}

impl From<RolloutError> for DatagenError {
    fn from(e: RolloutError) -> Self {
        match e {
            RolloutError::UnknownEnv(e) => DatagenError::UnknownEnv(e),
            RolloutError::Policy(m) => unreachable!("demonstrators act validly: {m}"),
        }
    }
}

/// Generates both sets; the same spec gives the same data.
pub fn generate(spec: &DatagenSpec) -> Result<Generated, DatagenError> {
    let task = Registered::get(&spec.env)?;
    generate_task(&task, spec, reference_stats(&spec.env)?)
}

/// [`generate`] for any [`Task`]; `spec.env` only names it in the manifest, and `reference` is
/// recorded there as the statistics evaluation normalises with.
pub fn generate_task(
    task: &dyn Task,
    spec: &DatagenSpec,
    reference: ReferenceStats,
) -> Result<Generated, DatagenError> {
    if spec.preferred + spec.non_preferred == 0 {
        return Err(DatagenError::NoUnlabeled);
    }
    let env = task.make();
    let (obs_dim, space) = (env.obs_dim(), env.action_space());
    let preferred = task.demonstrator(Profile::Preferred);
    let non_preferred = task.demonstrator(Profile::NonPreferred);
    let run = |demo: &dyn super::Demonstrator, episodes, stream| {
        demonstration_records(task, demo, episodes, spec.seed, stream, true)
    };
    let (p_out, p_rec) = run(preferred.as_ref(), spec.preferred, stream::PREFERRED)?;
    let (n_out, n_rec) = run(non_preferred.as_ref(), spec.non_preferred, stream::NON_PREFERRED)?;
    let (l_out, l_rec) = run(non_preferred.as_ref(), spec.labeled, stream::LABELED)?;

    // Shuffle whole episodes; remember where the non-preferred ones landed.
    let mut order: Vec<(bool, usize)> =
        (0..p_rec.len()).map(|i| (false, i)).chain((0..n_rec.len()).map(|i| (true, i))).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(derive_seed(spec.seed, stream::SHUFFLE, 0)));
    let mixed: Vec<_> =
        order.iter().map(|&(np, i)| if np { n_rec[i].clone() } else { p_rec[i].clone() }).collect();
    let non_preferred_ids =
        order.iter().enumerate().filter(|(_, (np, _))| *np).map(|(id, _)| id as u32).collect();

    let manifest = Manifest {
        spec: spec.clone(),
        unlabeled_preferred: GroupProfile::of(&p_out),
        unlabeled_non_preferred: GroupProfile::of(&n_out),
        labeled_non_preferred: GroupProfile::of(&l_out),
        unlabeled_non_preferred_episode_ids: non_preferred_ids,
        reference,
        files: Vec::new(),
    };
    Ok(Generated {
        unlabeled: assemble(&mixed, obs_dim, &space),
        labeled_non_preferred: (!l_rec.is_empty()).then(|| assemble(&l_rec, obs_dim, &space)),
        manifest,
    })
}

/// File name of the unlabeled set (plus the format's extension).
pub const UNLABELED_FILE: &str = "unlabeled";
/// File name of the labeled non-preferred set (plus the format's extension).
pub const NON_PREFERRED_FILE: &str = "non_preferred";
pub const MANIFEST_FILE: &str = "manifest.json";

/// Writes both sets in an upload `format` (`npz`, `jsonl` or `csv`) and `manifest.json` into
/// `dir` (created if missing); an empty labeled set is not written. Returns the manifest as
/// written, `files` filled in.
pub fn write_generated(g: &Generated, dir: &Path, format: Format) -> io::Result<Manifest> {
    let writer: fn(&Dataset, &Path) -> io::Result<()> = match format {
        Format::Npz => write_npz,
        Format::Jsonl => write_jsonl,
        Format::Csv => write_csv,
        Format::Hdf5 => {
            return Err(io::Error::new(
                io::ErrorKind::Unsupported,
                "datagen writes npz, jsonl or csv, not hdf5",
            ))
        }
    };
    std::fs::create_dir_all(dir)?;
    let mut manifest = g.manifest.clone();
    let sets = [
        (UNLABELED_FILE, Some(&g.unlabeled)),
        (NON_PREFERRED_FILE, g.labeled_non_preferred.as_ref()),
    ];
    for (stem, data) in sets {
        let Some(data) = data else { continue };
        let name = format!("{stem}.{}", format.as_str());
        writer(data, &dir.join(&name))?;
        manifest.files.push(name);
    }
    manifest.files.push(MANIFEST_FILE.to_string());
    let json = serde_json::to_vec_pretty(&manifest).map_err(io::Error::other)?;
    std::fs::write(dir.join(MANIFEST_FILE), json)?;
    Ok(manifest)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> DatagenSpec {
        DatagenSpec { env: "six-rooms".into(), preferred: 6, non_preferred: 4, labeled: 3, seed: 9 }
    }

    #[test]
    fn sets_have_the_requested_episodes_and_labels_point_at_non_preferred_ones() {
        let g = generate(&spec()).unwrap();
        assert_eq!(g.unlabeled.episodes(), 10);
        assert_eq!(g.labeled_non_preferred.as_ref().unwrap().episodes(), 3);
        let ids = &g.manifest.unlabeled_non_preferred_episode_ids;
        assert_eq!(ids.len(), 4);
        // Non-preferred episodes enter the bottom-left room (cost), preferred ones mostly not:
        // the summed cost of the labeled ids is the unlabeled non-preferred group's total.
        let ranges = g.unlabeled.episode_ranges();
        let costs = g.unlabeled.costs().unwrap();
        let cost_of = |id: usize| ranges[id].clone().map(|i| costs[i] as f64).sum::<f64>();
        let labeled_total: f64 = ids.iter().map(|&id| cost_of(id as usize)).sum();
        let group = &g.manifest.unlabeled_non_preferred;
        assert!((labeled_total - group.mean_cost * group.episodes as f64).abs() < 1e-9);
        assert_eq!(
            g.unlabeled.len(),
            g.manifest.unlabeled_preferred.transitions + group.transitions
        );
    }

    #[test]
    fn same_spec_same_data_and_the_seed_matters() {
        let a = generate(&spec()).unwrap();
        assert_eq!(a, generate(&spec()).unwrap());
        let b = generate(&DatagenSpec { seed: 10, ..spec() }).unwrap();
        assert_ne!(a.unlabeled, b.unlabeled);
    }

    #[test]
    fn labeled_episodes_are_fresh_not_copies_of_unlabeled_ones() {
        let g = generate(&DatagenSpec { env: "point-goal".into(), ..spec() }).unwrap();
        let first_labeled = g.labeled_non_preferred.as_ref().unwrap().obs(0);
        for start in g.unlabeled.episode_starts() {
            assert_ne!(g.unlabeled.obs(start), first_labeled);
        }
    }
}
