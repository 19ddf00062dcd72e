//! The robustness suite: many small generated tasks on which defaults are chosen, so that no
//! default is fitted to the environments the project reports on (`safedice bench --suite
//! robustness`; docs/algorithm.md, "How defaults are chosen").
//!
//! Each task is drawn from its own seed: a family with random parameters (a gridworld with
//! random walls and hazards, terminal or continuing; point navigation among random hazards; the
//! long-horizon `pace` task whose demonstrators differ in most states), the share of
//! non-preferred episodes in D^U (0.2-0.8), the size of D^N (5-80 episodes, log-uniform), the
//! size of D^U and observation noise. The seeds of the development split and the test split are
//! disjoint ranges, so a default chosen on one says nothing about the other until it is run.

pub mod grid;
pub mod pace;

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::Distribution;
use serde::{Deserialize, Serialize};

use super::point_goal::{self, Avoidance, PointGoal, Steering};
use super::{derive_seed, Action, Demonstrator, Env, Profile, Step, Task};
use crate::data::ActionSpace;

/// Which half of the suite: defaults are chosen on `dev` only; `test` is reported once.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    Dev,
    Test,
}

impl Split {
    /// First task seed of the split; task `i` is drawn from `first_seed + i`.
    pub fn first_seed(self) -> u64 {
        match self {
            Split::Dev => 1_000_000,
            Split::Test => 2_000_000,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Split::Dev => "dev",
            Split::Test => "test",
        }
    }

    /// The most tasks a run may draw from the split. The test split is its fixed
    /// [`TASKS_PER_SPLIT`] tasks, reported as a whole; the development split can be extended
    /// (tasks 24 and on, seeds still a million below the test split's) to study a family on
    /// more draws than the standard split holds, e.g. tasks near the edge of what a
    /// discriminator can separate.
    pub fn max_tasks(self) -> usize {
        match self {
            Split::Dev => EXTENDED_DEV_TASKS,
            Split::Test => TASKS_PER_SPLIT,
        }
    }
}

/// Tasks per split in the standard suite (the one every default is chosen and reported on).
pub const TASKS_PER_SPLIT: usize = 24;

/// The most development tasks a study may draw (`--tasks` on the development split alone).
pub const EXTENDED_DEV_TASKS: usize = 96;

/// A family and its drawn parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "family", rename_all = "snake_case")]
pub enum Family {
    Grid(grid::GridParams),
    Nav { layout: point_goal::Params, demo_noise: f32 },
    Pace(pace::PaceParams),
}

impl Family {
    pub fn name(&self) -> &'static str {
        match self {
            Family::Grid(g) if g.terminal_goal => "grid",
            Family::Grid(_) => "grid-continuing",
            Family::Nav { .. } => "nav",
            Family::Pace(_) => "pace",
        }
    }
}

/// One generated task: the environment, its data sizes and its observation noise.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TaskSpec {
    /// `dev-07-nav`: split, index, family.
    pub id: String,
    pub split: Split,
    pub index: usize,
    pub seed: u64,
    pub family: Family,
    /// Std of the Gaussian noise added to every observation value (the demonstrators see it too).
    pub obs_noise: f32,
    pub preferred_episodes: usize,
    pub non_preferred_episodes: usize,
    pub labeled_episodes: usize,
}

impl TaskSpec {
    /// Task `index` of `split`.
    pub fn draw(split: Split, index: usize) -> TaskSpec {
        let seed = split.first_seed() + index as u64;
        let mut rng = ChaCha8Rng::seed_from_u64(derive_seed(seed, SUITE_STREAM, 0));
        // Families in turn, so each split holds all of them in equal numbers.
        let (family, unlabeled) = match index % 4 {
            0 | 1 => {
                let map = grid::generate_map(&mut rng).expect("grids of these sizes are found");
                let terminal_goal = index.is_multiple_of(4);
                let params = grid::GridParams {
                    horizon: if terminal_goal { 100 } else { rng.random_range(100..=200) },
                    map,
                    terminal_goal,
                    slip: rng.random_range(0.0..0.15),
                    demo_epsilon: rng.random_range(0.05..0.2),
                };
                let episodes = if terminal_goal { rng.random_range(200..=400) } else { 100 };
                (Family::Grid(params), episodes)
            }
            2 => {
                let layout = point_goal::Params {
                    n_hazards: rng.random_range(3..=8),
                    hazard_radius: rng.random_range(0.15..0.3),
                    horizon: rng.random_range(100..=200),
                };
                let demo_noise = rng.random_range(0.15..0.35);
                (Family::Nav { layout, demo_noise }, rng.random_range(100..=200))
            }
            _ => (Family::Pace(pace::PaceParams::draw(&mut rng)), rng.random_range(60..=120)),
        };
        let share: f64 = rng.random_range(0.2..0.8);
        let non_preferred = ((unlabeled as f64 * share).round() as usize).clamp(1, unlabeled - 1);
        // |D^N| log-uniform over 5-80 episodes (the paper's Figure 8 range).
        let labeled = (5f64.ln() + rng.random::<f64>() * (80f64.ln() - 5f64.ln())).exp().round();
        let obs_noise = if rng.random_bool(0.5) { 0.0 } else { rng.random_range(0.0..0.1) };
        TaskSpec {
            id: format!("{}-{index:02}-{}", split.as_str(), family.name()),
            split,
            index,
            seed,
            family,
            obs_noise,
            preferred_episodes: unlabeled - non_preferred,
            non_preferred_episodes: non_preferred,
            labeled_episodes: labeled as usize,
        }
    }

    /// The first `count` tasks of `split`.
    pub fn split(split: Split, count: usize) -> Vec<TaskSpec> {
        (0..count).map(|i| TaskSpec::draw(split, i)).collect()
    }

    /// Non-preferred share of D^U's episodes.
    pub fn mixture_share(&self) -> f64 {
        let total = self.preferred_episodes + self.non_preferred_episodes;
        self.non_preferred_episodes as f64 / total as f64
    }

    /// The task's training length as a multiple of the suite's base iterations: navigation is
    /// the hardest to imitate (BC on the preferred episodes reached about 60% of the
    /// demonstrator's return at the base 5,000 iterations on the development split), `pace` has
    /// the longest episodes.
    pub fn iteration_scale(&self) -> u64 {
        match self.family {
            Family::Grid(_) => 1,
            Family::Pace(_) => 2,
            Family::Nav { .. } => 4,
        }
    }

    /// A short description of the parameters for a report table.
    pub fn describe(&self) -> String {
        match &self.family {
            Family::Grid(g) => format!(
                "{}x{} grid, slip {:.2}, ε {:.2}, horizon {}",
                g.map.len() - 2,
                g.map[0].len() - 2,
                g.slip,
                g.demo_epsilon,
                g.horizon
            ),
            Family::Nav { layout, demo_noise } => format!(
                "{} hazards r {:.2}, noise {:.2}, horizon {}",
                layout.n_hazards, layout.hazard_radius, demo_noise, layout.horizon
            ),
            Family::Pace(p) => format!(
                "{} joints, v* {:.2} ±{:.0}%, period {}, horizon {}",
                p.joints,
                p.target,
                p.amplitude * 100.0,
                p.period,
                p.horizon
            ),
        }
    }

    /// The task, ready to roll out.
    pub fn task(&self) -> SuiteTask {
        let grid = match &self.family {
            Family::Grid(g) => Some((Arc::new(grid::Layout::parse(&g.map)), Arc::new(g.clone()))),
            _ => None,
        };
        SuiteTask { spec: self.clone(), grid }
    }
}

/// Stream of the task draws under a task seed.
const SUITE_STREAM: u64 = 301;
/// Stream of the observation noise under an episode seed.
const NOISE_STREAM: u64 = 302;

/// A [`TaskSpec`] as a [`Task`].
pub struct SuiteTask {
    spec: TaskSpec,
    grid: Option<(Arc<grid::Layout>, Arc<grid::GridParams>)>,
}

impl SuiteTask {
    pub fn spec(&self) -> &TaskSpec {
        &self.spec
    }

    fn bare_env(&self) -> Box<dyn Env> {
        match (&self.spec.family, &self.grid) {
            (Family::Grid(_), Some((layout, params))) => {
                Box::new(grid::Grid::new(layout.clone(), params.clone()))
            }
            (Family::Nav { layout, .. }, _) => Box::new(PointGoal::with_params(0, *layout)),
            (Family::Pace(p), _) => Box::new(pace::Pace::new(*p)),
            (Family::Grid(_), None) => unreachable!("a grid task parses its map"),
        }
    }
}

impl Task for SuiteTask {
    fn name(&self) -> String {
        self.spec.id.clone()
    }

    fn make(&self) -> Box<dyn Env> {
        let env = self.bare_env();
        if self.spec.obs_noise > 0.0 {
            Box::new(NoisyObs { inner: env, std: self.spec.obs_noise, rng: noise_rng(0) })
        } else {
            env
        }
    }

    fn demonstrator(&self, profile: Profile) -> Box<dyn Demonstrator> {
        let preferred = profile == Profile::Preferred;
        match (&self.spec.family, &self.grid) {
            (Family::Grid(g), Some((layout, _))) => {
                Box::new(grid::RouteFollower::new(layout.clone(), preferred, g.demo_epsilon))
            }
            (Family::Nav { demo_noise, .. }, _) => {
                // The field, not point-goal's window rule: BC on the window rule's episodes kept
                // about twice its cost (its heading jumps between rays near a hazard), so every
                // nav task failed the fairness check and measured imitation, not safety
                // (bench/robustness/README.md, "Suite version 2").
                let base = if preferred {
                    Steering { avoidance: Avoidance::Field, ..Steering::preferred() }
                } else {
                    Steering::non_preferred()
                };
                Box::new(Steering { noise: *demo_noise, ..base })
            }
            (Family::Pace(p), _) => Box::new(pace::Pacer::new(*p, preferred)),
            (Family::Grid(_), None) => unreachable!("a grid task parses its map"),
        }
    }
}

fn noise_rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(derive_seed(seed, NOISE_STREAM, 0))
}

/// Adds `N(0, std²)` to every observation value; the noise of an episode follows its seed.
struct NoisyObs {
    inner: Box<dyn Env>,
    std: f32,
    rng: ChaCha8Rng,
}

impl NoisyObs {
    fn noisy(&mut self, mut obs: Vec<f32>) -> Vec<f32> {
        for x in &mut obs {
            let e: f32 = rand_distr::StandardNormal.sample(&mut self.rng);
            *x += self.std * e;
        }
        obs
    }
}

impl Env for NoisyObs {
    fn name(&self) -> &'static str {
        self.inner.name()
    }

    fn obs_dim(&self) -> usize {
        self.inner.obs_dim()
    }

    fn action_space(&self) -> ActionSpace {
        self.inner.action_space()
    }

    fn horizon(&self) -> usize {
        self.inner.horizon()
    }

    fn reset(&mut self, seed: Option<u64>) -> Vec<f32> {
        self.rng = noise_rng(seed.unwrap_or_else(|| self.rng.random()));
        let obs = self.inner.reset(seed);
        self.noisy(obs)
    }

    fn step(&mut self, action: Action<'_>) -> Step {
        let mut step = self.inner.step(action);
        step.obs = self.noisy(std::mem::take(&mut step.obs));
        step
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envs::{generate_task, task_reference_stats, DatagenSpec};

    #[test]
    fn splits_are_disjoint_deterministic_and_cover_every_family() {
        let dev = TaskSpec::split(Split::Dev, TASKS_PER_SPLIT);
        let test = TaskSpec::split(Split::Test, TASKS_PER_SPLIT);
        assert_eq!(dev, TaskSpec::split(Split::Dev, TASKS_PER_SPLIT));
        assert!(dev.iter().all(|d| test.iter().all(|t| t.seed != d.seed)));
        for family in ["grid", "grid-continuing", "nav", "pace"] {
            assert_eq!(dev.iter().filter(|t| t.family.name() == family).count(), 6, "{family}");
        }
        let extended = TaskSpec::split(Split::Dev, Split::Dev.max_tasks());
        assert_eq!(extended[..TASKS_PER_SPLIT], dev[..], "extending keeps the standard tasks");
        assert!(extended.iter().all(|d| d.seed < Split::Test.first_seed()));
        for t in extended.iter().chain(&test) {
            assert!((0.15..=0.85).contains(&t.mixture_share()), "{t:?}");
            assert!((5..=80).contains(&t.labeled_episodes), "{t:?}");
        }
    }

    #[test]
    fn every_family_separates_cost_at_similar_return() {
        for index in 0..4 {
            let spec = TaskSpec::draw(Split::Dev, index);
            let task = spec.task();
            let r = task_reference_stats(&task, 100);
            assert!(r.non_preferred_cost > 1.5 * r.preferred_cost + 0.5, "{}: {r:?}", spec.id);
            // The nav family's preferred demonstrator gives up about a third of its return to
            // keep clear of the hazards (bench/robustness/README.md, "Suite version 2").
            let gap = (r.preferred_return - r.non_preferred_return).abs();
            let larger = r.preferred_return.abs().max(r.non_preferred_return.abs()).max(0.1);
            assert!(gap <= 0.35 * larger, "{}: {r:?}", spec.id);
            let data = DatagenSpec {
                env: spec.id.clone(),
                preferred: 3,
                non_preferred: 2,
                labeled: 1,
                seed: 9,
            };
            let a = generate_task(&task, &data, r.clone()).unwrap();
            let b = generate_task(&task, &data, r).unwrap();
            assert_eq!(a, b, "{}: same seed, same data", spec.id);
            assert_eq!(a.unlabeled.episodes(), 5);
        }
    }
}
