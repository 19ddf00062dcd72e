//! Vectorised rollouts: many episodes of one environment advance in lock-step so a policy is
//! queried with a batch of observations per step (one network call for hundreds of episodes),
//! optionally recording the transitions as a [`Dataset`].

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::{derive_seed, Action, Demonstrator, Env, Profile, Registered, Task, UnknownEnv};
use crate::data::{ActionSpace, Actions, Dataset, DatasetParts};

/// Episodes run side by side at most; bounds memory while keeping policy batches large.
pub const WAVE: usize = 500;

/// Undiscounted sums of one episode.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpisodeOutcome {
    pub ret: f64,
    pub cost: f64,
    pub length: usize,
}

/// The transitions of one episode, in the column layout of [`Dataset`].
#[derive(Clone, Debug, Default)]
pub(crate) struct EpisodeRecord {
    observations: Vec<f32>,
    next_observations: Vec<f32>,
    continuous: Vec<f32>,
    discrete: Vec<u32>,
    rewards: Vec<f32>,
    costs: Vec<f32>,
    terminals: Vec<bool>,
}

/// Why a rollout stopped.
#[derive(Debug, thiserror::Error)]
pub enum RolloutError {
    #[error(transparent)]
    UnknownEnv(#[from] UnknownEnv),
    /// The policy failed, or returned actions of the wrong kind, count or value.
    #[error("policy: {0}")]
    Policy(String),
}

/// Checks a policy's answer for `rows` observations against the action space.
fn check_actions(actions: &Actions, rows: usize, space: &ActionSpace) -> Result<(), RolloutError> {
    let bad = |m: String| Err(RolloutError::Policy(m));
    match (actions, space) {
        (Actions::Discrete(a), ActionSpace::Discrete { n }) => {
            if a.len() != rows {
                return bad(format!(
                    "returned {} discrete actions for {rows} observations",
                    a.len()
                ));
            }
            match a.iter().find(|&&x| x as usize >= *n) {
                Some(x) => bad(format!("returned action {x}, outside 0..{n}")),
                None => Ok(()),
            }
        }
        (Actions::Continuous(a), ActionSpace::Continuous { dim, .. }) => {
            if a.len() != rows * dim {
                return bad(format!(
                    "returned {} action values for {rows} observations of action dim {dim}",
                    a.len()
                ));
            }
            if a.iter().any(|x| !x.is_finite()) {
                return bad("returned a non-finite action".to_string());
            }
            Ok(())
        }
        _ => bad("returned actions of the wrong kind for this environment".to_string()),
    }
}

/// Runs one episode per seed (episode `i` is reset with `episode_seeds[i]`), [`WAVE`] at a time,
/// asking `policy` for the actions of all running episodes at once. Returns the outcomes in
/// seed order and, with `record`, every episode's transitions.
pub(crate) fn run_episodes<P>(
    task: &dyn Task,
    episode_seeds: &[u64],
    policy_rng: &mut ChaCha8Rng,
    mut policy: P,
    record: bool,
) -> Result<(Vec<EpisodeOutcome>, Vec<EpisodeRecord>), RolloutError>
where
    P: FnMut(&[f32], &mut ChaCha8Rng) -> Result<Actions, String>,
{
    let probe = task.make();
    let (obs_dim, space) = (probe.obs_dim(), probe.action_space());
    let mut outcomes = Vec::with_capacity(episode_seeds.len());
    let mut records = Vec::new();
    for wave in episode_seeds.chunks(WAVE) {
        let mut envs: Vec<Box<dyn Env>> = wave.iter().map(|_| task.make()).collect();
        let mut obs: Vec<Vec<f32>> =
            envs.iter_mut().zip(wave).map(|(env, &seed)| env.reset(Some(seed))).collect();
        let mut wave_outcomes = vec![EpisodeOutcome { ret: 0.0, cost: 0.0, length: 0 }; wave.len()];
        let mut wave_records = vec![EpisodeRecord::default(); if record { wave.len() } else { 0 }];
        let mut running: Vec<usize> = (0..wave.len()).collect();
        let mut batch = Vec::with_capacity(wave.len() * obs_dim);
        while !running.is_empty() {
            batch.clear();
            for &i in &running {
                batch.extend_from_slice(&obs[i]);
            }
            let actions = policy(&batch, policy_rng).map_err(RolloutError::Policy)?;
            check_actions(&actions, running.len(), &space)?;
            let mut still_running = Vec::with_capacity(running.len());
            for (row, &i) in running.iter().enumerate() {
                let action = match &actions {
                    Actions::Discrete(a) => Action::Discrete(a[row]),
                    Actions::Continuous(a) => {
                        let dim = space.width();
                        Action::Continuous(&a[row * dim..(row + 1) * dim])
                    }
                };
                let step = envs[i].step(action);
                let outcome = &mut wave_outcomes[i];
                outcome.ret += f64::from(step.reward);
                outcome.cost += f64::from(step.cost);
                outcome.length += 1;
                if record {
                    let rec = &mut wave_records[i];
                    rec.observations.extend_from_slice(&obs[i]);
                    rec.next_observations.extend_from_slice(&step.obs);
                    match action {
                        Action::Discrete(a) => rec.discrete.push(a),
                        Action::Continuous(a) => {
                            rec.continuous.extend(a.iter().map(|&x| x.clamp(-1.0, 1.0)))
                        }
                    }
                    rec.rewards.push(step.reward);
                    rec.costs.push(step.cost);
                    rec.terminals.push(step.terminal);
                }
                if !(step.terminal || step.truncated) {
                    still_running.push(i);
                }
                obs[i] = step.obs;
            }
            running = still_running;
        }
        outcomes.extend(wave_outcomes);
        records.extend(wave_records);
    }
    Ok((outcomes, records))
}

/// Concatenates episode records into one dataset; episode `i` of `records` gets id `i`.
///
/// Panics when `records` is empty: a dataset has at least one transition. Recorded episodes are
/// otherwise consistent (non-empty, finite, actions checked against the space as they were taken).
pub(crate) fn assemble(records: &[EpisodeRecord], obs_dim: usize, space: &ActionSpace) -> Dataset {
    let mut d = DatasetParts {
        obs_dim,
        action_space: space.clone(),
        observations: Vec::new(),
        actions: match space {
            ActionSpace::Discrete { .. } => Actions::Discrete(Vec::new()),
            ActionSpace::Continuous { .. } => Actions::Continuous(Vec::new()),
        },
        next_observations: Vec::new(),
        terminals: Vec::new(),
        episode_ids: Vec::new(),
        rewards: Some(Vec::new()),
        costs: Some(Vec::new()),
    };
    for (id, rec) in records.iter().enumerate() {
        d.observations.extend_from_slice(&rec.observations);
        d.next_observations.extend_from_slice(&rec.next_observations);
        match &mut d.actions {
            Actions::Discrete(a) => a.extend_from_slice(&rec.discrete),
            Actions::Continuous(a) => a.extend_from_slice(&rec.continuous),
        }
        d.terminals.extend_from_slice(&rec.terminals);
        d.episode_ids.extend(std::iter::repeat_n(id as u32, rec.terminals.len()));
        d.rewards.as_mut().expect("set above").extend_from_slice(&rec.rewards);
        d.costs.as_mut().expect("set above").extend_from_slice(&rec.costs);
    }
    Dataset::new(d).expect("recorded episodes form a consistent dataset")
}

/// Episodes of the `profile` demonstrator: episode `i` uses the seeds of index `i` of `stream`
/// under `seed`, so the same arguments give the same episodes.
pub(crate) fn demonstration_records(
    task: &dyn Task,
    demo: &dyn Demonstrator,
    episodes: usize,
    seed: u64,
    stream: u64,
    record: bool,
) -> Result<(Vec<EpisodeOutcome>, Vec<EpisodeRecord>), RolloutError> {
    let seeds: Vec<u64> = (0..episodes as u64).map(|i| derive_seed(seed, stream, i)).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(derive_seed(seed, stream, u64::MAX));
    run_episodes(task, &seeds, &mut rng, |obs, rng| Ok(demo.act_batch(obs, rng)), record)
}

/// `episodes` episodes of the `profile` demonstrator of `env_name` as a dataset (rewards and
/// costs included), with their outcomes. `episodes` must be positive (a dataset is not empty).
pub fn demonstration_dataset(
    env_name: &str,
    profile: Profile,
    episodes: usize,
    seed: u64,
) -> Result<(Dataset, Vec<EpisodeOutcome>), RolloutError> {
    let task = Registered::get(env_name)?;
    let demo = task.demonstrator(profile);
    let stream = match profile {
        Profile::Preferred => super::stream::PREFERRED,
        Profile::NonPreferred => super::stream::NON_PREFERRED,
    };
    let (outcomes, records) =
        demonstration_records(&task, demo.as_ref(), episodes, seed, stream, true)?;
    let env = task.make();
    Ok((assemble(&records, env.obs_dim(), &env.action_space()), outcomes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recorded_dataset_is_consistent_and_matches_outcomes() {
        for env in super::super::names() {
            let (d, outcomes) = demonstration_dataset(env, Profile::Preferred, 3, 11).unwrap();
            assert_eq!(d.episodes(), 3);
            for (range, outcome) in d.episode_ranges().into_iter().zip(&outcomes) {
                assert_eq!(range.len(), outcome.length);
                let ret: f64 = d.rewards().unwrap()[range.clone()].iter().map(|&r| r as f64).sum();
                assert!((ret - outcome.ret).abs() < 1e-4, "{env}");
                // Consecutive transitions chain: next_obs of t is obs of t + 1.
                for i in range.start..range.end - 1 {
                    assert_eq!(d.next_obs(i), d.obs(i + 1));
                }
            }
            let again = demonstration_dataset(env, Profile::Preferred, 3, 11).unwrap().0;
            assert_eq!(d, again, "{env}: same seed, same data");
        }
    }

    #[test]
    fn bad_policy_output_is_reported_not_stepped() {
        let seeds = [1, 2];
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let err = run_episodes(
            &Registered::get("six-rooms").unwrap(),
            &seeds,
            &mut rng,
            |_, _| Ok(Actions::Discrete(vec![0, 4])),
            false,
        )
        .unwrap_err();
        assert_eq!(err.to_string(), "policy: returned action 4, outside 0..4");
        let err = run_episodes(
            &Registered::get("cartpole-slider").unwrap(),
            &seeds,
            &mut rng,
            |_, _| Ok(Actions::Continuous(vec![0.0])),
            false,
        )
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "policy: returned 1 action values for 2 observations of action dim 1"
        );
        let err = run_episodes(
            &Registered::get("point-goal").unwrap(),
            &seeds,
            &mut rng,
            |_, _| Ok(Actions::Discrete(vec![0, 0])),
            false,
        )
        .unwrap_err();
        assert!(err.to_string().contains("wrong kind"));
    }

    #[test]
    fn policy_sees_one_batch_of_all_running_episodes() {
        let seeds: Vec<u64> = (0..7).collect();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut sizes = Vec::new();
        let (outcomes, _) = run_episodes(
            &Registered::get("cartpole-slider").unwrap(),
            &seeds,
            &mut rng,
            |obs, _| {
                sizes.push(obs.len() / 5);
                Ok(Actions::Continuous(vec![0.0; obs.len() / 5]))
            },
            false,
        )
        .unwrap();
        assert_eq!(sizes.len(), super::super::cartpole_slider::HORIZON);
        assert!(sizes.iter().all(|&s| s == 7));
        assert!(outcomes.iter().all(|o| o.length == super::super::cartpole_slider::HORIZON));
    }
}
