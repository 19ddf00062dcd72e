//! Built-in safety benchmarks: environments modelled on the paper's experiments (section 5 and
//! Appendix G), scripted demonstrators that produce preferred and non-preferred data, the
//! paper's evaluation metrics, and the data generator behind `safedice datagen`.
//!
//! Every environment is deterministic given a seed: [`Env::reset`] with `Some(seed)` draws the
//! initial state and every later random event (slips, goal placements) of that episode from
//! `seed` alone, so an episode can be replayed exactly.

pub mod cartpole_slider;
pub mod datagen;
pub mod demonstrators;
pub mod metrics;
pub mod point_goal;
pub mod rollout;
pub mod six_rooms;
pub mod suite;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::Distribution;
use serde::Serialize;

use crate::data::ActionSpace;

pub use datagen::{
    generate, generate_task, write_generated, DatagenError, DatagenSpec, Generated, GroupProfile,
    Manifest,
};
pub use demonstrators::{demonstrator, Demonstrator, Profile};
pub use metrics::{
    compute_metrics, cvar_cost, evaluate, evaluate_task, reference_stats, task_reference_stats,
    CvarCost, EvalError, EvalReport, Metrics, ReferenceStats,
};
pub use rollout::{demonstration_dataset, EpisodeOutcome, RolloutError};

/// Where episodes come from: a way to make fresh copies of an environment, and its two scripted
/// demonstrators. The registry's environments are one kind ([`Registered`]); the generated tasks
/// of the robustness suite ([`suite`]) are another. Rollouts, data generation and evaluation
/// take a `Task`, so every kind is generated and scored by the same code.
pub trait Task: Sync {
    /// The name results are reported under (the registry name, or a suite task's id).
    fn name(&self) -> String;
    /// A fresh environment; episodes are reset with explicit seeds.
    fn make(&self) -> Box<dyn Env>;
    /// The `profile` demonstrator.
    fn demonstrator(&self, profile: Profile) -> Box<dyn Demonstrator>;
}

/// A built-in environment of the registry, as a [`Task`].
#[derive(Clone, Copy, Debug)]
pub struct Registered(&'static str);

impl Registered {
    /// The registry entry called `name`.
    pub fn get(name: &str) -> Result<Registered, UnknownEnv> {
        REGISTRY
            .iter()
            .find(|e| e.name == name)
            .map(|e| Registered(e.name))
            .ok_or_else(|| UnknownEnv { name: name.to_string() })
    }
}

impl Task for Registered {
    fn name(&self) -> String {
        self.0.to_string()
    }

    fn make(&self) -> Box<dyn Env> {
        make(self.0, 0).expect("a Registered name is in the registry")
    }

    fn demonstrator(&self, profile: Profile) -> Box<dyn Demonstrator> {
        demonstrator(self.0, profile).expect("every registered environment has demonstrators")
    }
}

/// One action handed to [`Env::step`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Action<'a> {
    /// An index in `0..n` of a discrete action space.
    Discrete(u32),
    /// A continuous action; environments clip each component to their box (`[-1, 1]` here).
    Continuous(&'a [f32]),
}

/// What one environment step returns.
#[derive(Clone, Debug, PartialEq)]
pub struct Step {
    pub obs: Vec<f32>,
    pub reward: f32,
    pub cost: f32,
    /// The episode ended in a terminal state (e.g. the goal was reached).
    pub terminal: bool,
    /// The episode hit the horizon without a terminal state (a time-out, not a terminal).
    pub truncated: bool,
}

/// A simulated task with a reward and a safety cost per step.
pub trait Env: Send {
    /// The registry name, e.g. `"point-goal"`.
    fn name(&self) -> &'static str;
    fn obs_dim(&self) -> usize;
    fn action_space(&self) -> ActionSpace;
    /// Steps after which an episode is truncated.
    fn horizon(&self) -> usize;
    /// Starts an episode. `Some(seed)`: the episode is a pure function of `seed`; `None`: the
    /// next seed of the stream the environment was made with (see [`make`]).
    fn reset(&mut self, seed: Option<u64>) -> Vec<f32>;
    /// Advances one step. Panics on an action of the wrong kind or size, or after the episode
    /// ended (callers validate policy output first: see [`rollout`]).
    fn step(&mut self, action: Action<'_>) -> Step;
}

/// How an environment is listed at `GET /v1/envs`.
#[derive(Clone, Debug, PartialEq, Serialize, utoipa::ToSchema)]
pub struct EnvInfo {
    pub name: String,
    pub description: String,
    pub obs_dim: usize,
    pub action_space: ActionSpace,
    /// Maximum steps per episode.
    pub horizon: usize,
    /// What the per-step reward is.
    pub reward: String,
    /// What the per-step cost is.
    pub cost: String,
}

/// A name that is not in the registry.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("unknown environment `{name}` (known: {})", names().join(", "))]
pub struct UnknownEnv {
    pub name: String,
}

struct Entry {
    name: &'static str,
    description: &'static str,
    reward: &'static str,
    cost: &'static str,
    build: fn(u64) -> Box<dyn Env>,
}

const REGISTRY: [Entry; 3] = [
    Entry {
        name: six_rooms::NAME,
        description: six_rooms::DESCRIPTION,
        reward: six_rooms::REWARD,
        cost: six_rooms::COST,
        build: |seed| Box::new(six_rooms::SixRooms::new(seed)),
    },
    Entry {
        name: point_goal::NAME,
        description: point_goal::DESCRIPTION,
        reward: point_goal::REWARD,
        cost: point_goal::COST,
        build: |seed| Box::new(point_goal::PointGoal::new(seed)),
    },
    Entry {
        name: cartpole_slider::NAME,
        description: cartpole_slider::DESCRIPTION,
        reward: cartpole_slider::REWARD,
        cost: cartpole_slider::COST,
        build: |seed| Box::new(cartpole_slider::CartpoleSlider::new(seed)),
    },
];

/// The registry names, in listing order.
pub fn names() -> Vec<&'static str> {
    REGISTRY.iter().map(|e| e.name).collect()
}

/// Every built-in environment with its spaces.
pub fn list() -> Vec<EnvInfo> {
    REGISTRY
        .iter()
        .map(|e| {
            let env = (e.build)(0);
            EnvInfo {
                name: e.name.to_string(),
                description: e.description.to_string(),
                obs_dim: env.obs_dim(),
                action_space: env.action_space(),
                horizon: env.horizon(),
                reward: e.reward.to_string(),
                cost: e.cost.to_string(),
            }
        })
        .collect()
}

/// The listing of one environment.
pub fn info(name: &str) -> Result<EnvInfo, UnknownEnv> {
    list().into_iter().find(|i| i.name == name).ok_or_else(|| UnknownEnv { name: name.into() })
}

/// Why a policy (or the data it is trained on) cannot act in an environment.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SpaceMismatch {
    #[error(transparent)]
    UnknownEnv(#[from] UnknownEnv),
    #[error("{0}")]
    Spaces(String),
}

/// Checks that a policy over `obs_dim` observations and `action_space` actions can act in
/// environment `name`; `whose` names them in the message (e.g. "the policy's"): the same observation width and the same kind of action with the same
/// width. A discrete policy may know fewer actions than the environment (a dataset re-inferred
/// from JSONL or CSV counts only the actions it uses); continuous actions are clipped to the
/// environment's box.
pub fn check_spaces(
    name: &str,
    obs_dim: usize,
    action_space: &ActionSpace,
    whose: &str,
) -> Result<(), SpaceMismatch> {
    let env = info(name)?;
    let mismatch = |what: String| Err(SpaceMismatch::Spaces(format!("{name}: {what}")));
    if env.obs_dim != obs_dim {
        return mismatch(format!(
            "observations have {} values, {whose} have {obs_dim}",
            env.obs_dim
        ));
    }
    match (&env.action_space, action_space) {
        (ActionSpace::Discrete { n: env_n }, ActionSpace::Discrete { n }) if n <= env_n => Ok(()),
        (ActionSpace::Continuous { dim: env_dim, .. }, ActionSpace::Continuous { dim, .. })
            if dim == env_dim =>
        {
            Ok(())
        }
        (expected, got) => mismatch(format!(
            "actions are {}, {whose} are {}",
            describe_space(expected),
            describe_space(got)
        )),
    }
}

fn describe_space(space: &ActionSpace) -> String {
    match space {
        ActionSpace::Discrete { n } => format!("discrete with {n} choices"),
        ActionSpace::Continuous { dim, .. } => format!("continuous with {dim} dimensions"),
    }
}

/// A fresh environment whose `reset(None)` episodes follow the stream seeded by `seed`.
pub fn make(name: &str, seed: u64) -> Result<Box<dyn Env>, UnknownEnv> {
    REGISTRY
        .iter()
        .find(|e| e.name == name)
        .map(|e| (e.build)(seed))
        .ok_or_else(|| UnknownEnv { name: name.to_string() })
}

/// SplitMix64 finaliser: turns related integers (a run seed and an index) into unrelated seeds.
pub(crate) fn mix(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The random streams of one seed, each kept in one place so that no two uses of randomness
/// share a stream by accident (see [`derive_seed`]).
pub(crate) mod stream {
    /// Preferred demonstrations (generated unlabeled data, demonstration datasets).
    pub const PREFERRED: u64 = 1;
    /// Non-preferred demonstrations in the unlabeled data.
    pub const NON_PREFERRED: u64 = 2;
    /// The labeled non-preferred dataset.
    pub const LABELED: u64 = 3;
    /// The order of the generated unlabeled transitions.
    pub const SHUFFLE: u64 = 4;
    /// Initial states of evaluation episodes.
    pub const EVAL: u64 = 101;
    /// Sampled actions of the evaluated policy.
    pub const EVAL_POLICY: u64 = 102;
    /// The demonstrators' reference episodes.
    pub const REFERENCE: u64 = 103;
}

/// The seed of item `index` of the named `stream` of a run seeded with `seed`; streams keep the
/// preferred, non-preferred, labeled and evaluation episodes of one run independent.
pub(crate) fn derive_seed(seed: u64, stream: u64, index: u64) -> u64 {
    mix(mix(mix(seed) ^ stream) ^ index)
}

/// Per-episode randomness shared by the environments: `reset(None)` takes the next seed of a
/// stream fixed at construction, `reset(Some(s))` uses `s`.
#[derive(Clone, Debug)]
pub(crate) struct EpisodeRng {
    stream: ChaCha8Rng,
    /// The current episode's generator.
    pub rng: ChaCha8Rng,
}

impl EpisodeRng {
    pub fn new(seed: u64) -> Self {
        EpisodeRng { stream: ChaCha8Rng::seed_from_u64(seed), rng: ChaCha8Rng::seed_from_u64(0) }
    }

    /// Re-seeds the episode generator for a new episode.
    pub fn begin(&mut self, seed: Option<u64>) {
        let seed = seed.unwrap_or_else(|| self.stream.random());
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }
}

/// One action component of a scripted demonstrator: `tanh(mean + std · ε)`, ε ~ N(0, 1), the
/// tanh-squashed Gaussian the learners' continuous policies are (docs/algorithm.md), so a
/// demonstrator is a policy a learner can represent. Clipping `mean + noise` instead put a large
/// share of the actions exactly on ±1, which a tanh-Gaussian can only fit with a pre-tanh spread
/// wide enough to also flip the action's sign now and then: BC on the preferred episodes alone
/// then had 1.6-6x the preferred demonstrator's cost (bench/README.md, "Environments").
pub(crate) fn squashed_gaussian(mean: f32, std: f32, rng: &mut ChaCha8Rng) -> f32 {
    let noise: f32 = rand_distr::StandardNormal.sample(rng);
    (mean + std * noise).tanh()
}

/// Clips each component to `[-1, 1]`; NaN becomes 0 so a broken policy cannot poison the state.
pub(crate) fn clip_unit(x: f32) -> f32 {
    if x.is_nan() {
        0.0
    } else {
        x.clamp(-1.0, 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registry_lists_and_makes_every_env() {
        let infos = list();
        assert_eq!(
            infos.iter().map(|i| i.name.as_str()).collect::<Vec<_>>(),
            ["six-rooms", "point-goal", "cartpole-slider"]
        );
        for info in &infos {
            let mut env = make(&info.name, 3).unwrap();
            assert_eq!(env.obs_dim(), info.obs_dim);
            assert_eq!(env.reset(Some(1)).len(), info.obs_dim);
        }
        let err = make("walker", 0).err().unwrap();
        assert_eq!(
            err.to_string(),
            "unknown environment `walker` (known: six-rooms, point-goal, cartpole-slider)"
        );
    }

    #[test]
    fn env_info_serialises_with_its_action_space() {
        let json = serde_json::to_value(info("point-goal").unwrap()).unwrap();
        assert_eq!(json["action_space"]["type"], "continuous");
        assert_eq!(json["action_space"]["dim"], 2);
        let json = serde_json::to_value(info("six-rooms").unwrap()).unwrap();
        assert_eq!(json["action_space"], serde_json::json!({"type": "discrete", "n": 4}));
    }

    #[test]
    fn spaces_must_match_the_environment() {
        const P: &str = "the policy's";
        let obs = info("six-rooms").unwrap().obs_dim;
        assert_eq!(check_spaces("six-rooms", obs, &ActionSpace::Discrete { n: 4 }, P), Ok(()));
        assert_eq!(check_spaces("six-rooms", obs, &ActionSpace::Discrete { n: 3 }, P), Ok(()));
        let err = check_spaces("six-rooms", obs, &ActionSpace::Discrete { n: 5 }, P).unwrap_err();
        assert_eq!(
            err.to_string(),
            "six-rooms: actions are discrete with 4 choices, the policy's are discrete with 5 choices"
        );
        let err =
            check_spaces("six-rooms", obs + 1, &ActionSpace::Discrete { n: 4 }, P).unwrap_err();
        assert_eq!(
            err.to_string(),
            format!("six-rooms: observations have {obs} values, the policy's have {}", obs + 1)
        );
        let point = info("point-goal").unwrap();
        let square =
            |dim| ActionSpace::Continuous { dim, low: vec![-1.0; dim], high: vec![1.0; dim] };
        assert_eq!(check_spaces("point-goal", point.obs_dim, &square(2), P), Ok(()));
        assert!(check_spaces("point-goal", point.obs_dim, &square(3), P).is_err());
        assert!(
            check_spaces("point-goal", point.obs_dim, &ActionSpace::Discrete { n: 2 }, P).is_err()
        );
        assert!(matches!(
            check_spaces("walker", 1, &square(1), P),
            Err(SpaceMismatch::UnknownEnv(_))
        ));
    }

    #[test]
    fn derived_seeds_differ_across_streams_and_indices() {
        let a = derive_seed(0, 1, 0);
        assert_ne!(a, derive_seed(0, 1, 1));
        assert_ne!(a, derive_seed(0, 2, 0));
        assert_ne!(a, derive_seed(1, 1, 0));
        assert_eq!(a, derive_seed(0, 1, 0));
    }

    #[test]
    fn reset_with_a_seed_replays_the_episode_and_none_follows_the_stream() {
        for name in names() {
            let mut a = make(name, 7).unwrap();
            let mut b = make(name, 99).unwrap();
            assert_eq!(a.reset(Some(5)), b.reset(Some(5)), "{name}");
            let mut c = make(name, 7).unwrap();
            assert_eq!(a.reset(None), c.reset(None), "{name}");
        }
    }
}
