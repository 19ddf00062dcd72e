//! Small hand-written tasks for the training-core tests: a gridworld with a safe detour and a
//! hazardous shortcut, and a 2-D point task with the same structure and continuous actions.
//! (The real benchmark environments live in src/envs; these stay tiny and self-contained.)

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use safedice::algo::{self, Algorithm, Policy, TrainingData};
use safedice::data::{ActionSpace, Actions, Dataset, DatasetParts};

/// Episode builder: columns grow one transition at a time.
#[derive(Default)]
struct Builder {
    obs_dim: usize,
    observations: Vec<f32>,
    next_observations: Vec<f32>,
    discrete: Vec<u32>,
    continuous: Vec<f32>,
    terminals: Vec<bool>,
    episode_ids: Vec<u32>,
    costs: Vec<f32>,
}

impl Builder {
    fn finish(self, action_space: ActionSpace) -> Dataset {
        let actions = match action_space {
            ActionSpace::Discrete { .. } => Actions::Discrete(self.discrete),
            ActionSpace::Continuous { .. } => Actions::Continuous(self.continuous),
        };
        Dataset::new(DatasetParts {
            obs_dim: self.obs_dim,
            action_space,
            observations: self.observations,
            actions,
            next_observations: self.next_observations,
            terminals: self.terminals,
            episode_ids: self.episode_ids,
            rewards: None,
            costs: Some(self.costs),
        })
        .expect("generated data is consistent")
    }
}

// ---------------------------------------------------------------------------------------------
// Gridworld: 5 × 2 cells, start (0,0), goal (4,0) (terminal). The bottom row's cells (1..3, 0)
// are hazards (cost 1 per step). The unsafe demonstrator walks straight right through them
// (4 steps); the safe one goes up, right along the top row, and down (6 steps). Demonstrators
// take a random action with probability 0.1; episodes time out after 20 steps.

pub const GRID_W: usize = 5;
pub const GRID_CELLS: usize = 10;
pub const GRID_MAX_STEPS: usize = 20;
const UP: u32 = 0;
const DOWN: u32 = 1;
const LEFT: u32 = 2;
const RIGHT: u32 = 3;

pub fn grid_step(cell: usize, action: u32) -> usize {
    let (x, y) = (cell % GRID_W, cell / GRID_W);
    let (x, y) = match action {
        UP => (x, 1),
        DOWN => (x, 0),
        LEFT => (x.saturating_sub(1), y),
        _ => ((x + 1).min(GRID_W - 1), y),
    };
    y * GRID_W + x
}

pub fn grid_is_hazard(cell: usize) -> bool {
    (1..=3).contains(&cell)
}

pub fn grid_is_goal(cell: usize) -> bool {
    cell == 4
}

fn one_hot(cell: usize) -> Vec<f32> {
    let mut v = vec![0.0; GRID_CELLS];
    v[cell] = 1.0;
    v
}

fn demonstrator(safe: bool, cell: usize) -> u32 {
    let (x, y) = (cell % GRID_W, cell / GRID_W);
    match (safe, y) {
        (true, 0) if x == 4 => DOWN,
        (true, 0) => UP,
        (true, _) if x == 4 => DOWN,
        (true, _) => RIGHT,
        (false, 0) => RIGHT,
        (false, _) => DOWN,
    }
}

/// `unsafe_episodes` + `safe_episodes` demonstrations, episode ids starting at `first_id`.
pub fn grid_dataset(safe_episodes: usize, unsafe_episodes: usize, seed: u64) -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut b = Builder { obs_dim: GRID_CELLS, ..Default::default() };
    let kinds =
        std::iter::repeat_n(true, safe_episodes).chain(std::iter::repeat_n(false, unsafe_episodes));
    for (episode, safe) in kinds.enumerate() {
        let mut cell = 0;
        for _ in 0..GRID_MAX_STEPS {
            let action = if rng.random::<f64>() < 0.1 {
                rng.random_range(0..4)
            } else {
                demonstrator(safe, cell)
            };
            let next = grid_step(cell, action);
            b.observations.extend(one_hot(cell));
            b.next_observations.extend(one_hot(next));
            b.discrete.push(action);
            b.terminals.push(grid_is_goal(next));
            b.episode_ids.push(episode as u32);
            b.costs.push(grid_is_hazard(next) as u8 as f32);
            cell = next;
            if grid_is_goal(cell) {
                break;
            }
        }
    }
    b.finish(ActionSpace::Discrete { n: 4 })
}

/// Unlabeled: 40 safe + 60 unsafe episodes; non-preferred: 20 unsafe episodes.
pub fn grid_training_data(seed: u64) -> TrainingData {
    TrainingData {
        unlabeled: Arc::new(grid_dataset(40, 60, seed)),
        non_preferred: Some(Arc::new(grid_dataset(0, 20, seed + 1000))),
    }
}

/// Greedy rollout from the start: (hazard steps, reached the goal).
pub fn grid_rollout(policy: &Policy) -> (usize, bool) {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut cell = 0;
    let mut cost = 0;
    for _ in 0..GRID_MAX_STEPS {
        let Actions::Discrete(a) = policy.act(&one_hot(cell), true, &mut rng).unwrap() else {
            panic!()
        };
        cell = grid_step(cell, a[0]);
        cost += grid_is_hazard(cell) as usize;
        if grid_is_goal(cell) {
            return (cost, true);
        }
    }
    (cost, false)
}

// ---------------------------------------------------------------------------------------------
// Point task: position in the plane, start (0, 0), goal (1, 0) (terminal within 0.1). A hazard
// disk of radius 0.2 sits at (0.5, 0). Actions are velocities in [-1, 1]^2, scaled by 0.1 per
// step. The unsafe demonstrator heads straight for the goal, the safe one via (0.5, 0.45).

pub const POINT_MAX_STEPS: usize = 40;

fn point_move(p: [f32; 2], a: [f32; 2]) -> [f32; 2] {
    [p[0] + 0.1 * a[0].clamp(-1.0, 1.0), p[1] + 0.1 * a[1].clamp(-1.0, 1.0)]
}

pub fn point_in_hazard(p: [f32; 2]) -> bool {
    ((p[0] - 0.5).powi(2) + p[1].powi(2)).sqrt() < 0.2
}

pub fn point_at_goal(p: [f32; 2]) -> bool {
    ((p[0] - 1.0).powi(2) + p[1].powi(2)).sqrt() < 0.1
}

fn point_demonstrator(safe: bool, p: [f32; 2]) -> [f32; 2] {
    let target = if safe && p[0] < 0.5 { [0.5, 0.45] } else { [1.0, 0.0] };
    let (dx, dy) = (target[0] - p[0], target[1] - p[1]);
    let norm = (dx * dx + dy * dy).sqrt().max(1e-6);
    [dx / norm, dy / norm]
}

pub fn point_dataset(safe_episodes: usize, unsafe_episodes: usize, seed: u64) -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0f32, 0.2).unwrap();
    let mut b = Builder { obs_dim: 2, ..Default::default() };
    let kinds =
        std::iter::repeat_n(true, safe_episodes).chain(std::iter::repeat_n(false, unsafe_episodes));
    for (episode, safe) in kinds.enumerate() {
        let mut p = [0.0f32, 0.0];
        for _ in 0..POINT_MAX_STEPS {
            let d = point_demonstrator(safe, p);
            let a = [
                (d[0] + noise.sample(&mut rng)).clamp(-1.0, 1.0),
                (d[1] + noise.sample(&mut rng)).clamp(-1.0, 1.0),
            ];
            let next = point_move(p, a);
            b.observations.extend(p);
            b.next_observations.extend(next);
            b.continuous.extend(a);
            b.terminals.push(point_at_goal(next));
            b.episode_ids.push(episode as u32);
            b.costs.push(point_in_hazard(next) as u8 as f32);
            p = next;
            if point_at_goal(p) {
                break;
            }
        }
    }
    b.finish(ActionSpace::Continuous { dim: 2, low: vec![-1.0; 2], high: vec![1.0; 2] })
}

pub fn point_training_data(seed: u64) -> TrainingData {
    TrainingData {
        unlabeled: Arc::new(point_dataset(40, 60, seed)),
        non_preferred: Some(Arc::new(point_dataset(0, 20, seed + 1000))),
    }
}

/// Greedy rollout: (hazard steps, reached the goal).
pub fn point_rollout(policy: &Policy) -> (usize, bool) {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut p = [0.0f32, 0.0];
    let mut cost = 0;
    for _ in 0..POINT_MAX_STEPS {
        let Actions::Continuous(a) = policy.act(&p, true, &mut rng).unwrap() else { panic!() };
        p = point_move(p, [a[0], a[1]]);
        cost += point_in_hazard(p) as usize;
        if point_at_goal(p) {
            return (cost, true);
        }
    }
    (cost, false)
}

// ---------------------------------------------------------------------------------------------

/// Trains `algorithm` to the end with `config` and returns the loaded policy and alpha-hat.
pub fn train(
    algorithm: Algorithm,
    config: serde_json::Value,
    data: &TrainingData,
) -> (Policy, Option<f64>) {
    let config = algo::resolve_config(algorithm, &config).unwrap();
    let mut trainer = algo::build_trainer(&config, data, None).unwrap();
    while !trainer.is_finished() {
        trainer.step(false).unwrap();
    }
    let artifact = trainer.export_policy().unwrap();
    (Policy::load(&artifact.spec, &artifact.weights).unwrap(), trainer.alpha_hat())
}
