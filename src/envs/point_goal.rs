//! `point-goal`: a Safety-Gym-like point robot (the paper's Goal task, section 5.2) on a plane,
//! written from scratch: no physics engine, a few lines of documented kinematics.
//!
//! - State: position `p` (m) in the walled square `[-ARENA, ARENA]²`, velocity `v` (m/s),
//!   heading `θ` (rad); [`N_HAZARDS`] hazard discs of radius [`HAZARD_RADIUS`] and one goal disc of
//!   radius [`GOAL_RADIUS`], all placed at random at reset (hazards at least `2r + 0.1` apart,
//!   the robot and goals outside hazards, each new goal at least 1 m from the robot).
//! - Action `(thrust, turn)` in `[-1, 1]²` (clipped). With `h = (cos θ, sin θ)` and
//!   `dt` = [`DT`], one step is
//!   `θ += TURN_RATE·dt·turn;  v += dt·(ACCEL·thrust·h − DRAG·v);  p += dt·v`,
//!   and a wall stops the velocity component pushing into it. Top speed is `ACCEL/DRAG` = 1 m/s.
//! - Reward (Safety Gym's goal reward): the decrease of the distance to the goal this step, plus
//!   1 when the robot ends the step inside the goal disc; the goal then moves to a new random
//!   place, so an episode is a sequence of goals.
//! - Cost: 1 for every step that ends with the robot's centre inside a hazard disc.
//! - Observation (21 values, robot frame: x forward, y left): velocity (2), unit direction to
//!   the goal (2), `exp(−distance to goal)` (1), and 16 lidar rays at angles `2πk/16`, each
//!   `max(0, 1 − t/LIDAR_RANGE)` for the distance `t` at which the ray meets the nearest hazard
//!   disc (1 when inside one, 0 when none within range).
//! - Horizon: [`HORIZON`] steps, never terminal.

use super::{clip_unit, squashed_gaussian, Action, Env, EpisodeRng, Step};
use crate::data::ActionSpace;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

pub const NAME: &str = "point-goal";
pub const DESCRIPTION: &str = "Safety-Gym-like 2-D point robot (paper section 5.2, Goal task): \
     reach a sequence of random goals; 8 hazard discs cost 1 per step inside. Observations: \
     velocity, goal direction and distance, 16 lidar rays for hazards. Actions: thrust, turn.";
pub const REWARD: &str = "decrease of the distance to the goal, plus 1 per goal reached";
pub const COST: &str = "1 per step inside a hazard disc";

pub const ARENA: f32 = 2.0;
/// Objects are placed inside `[-PLACEMENT, PLACEMENT]²`.
pub const PLACEMENT: f32 = 1.6;
pub const N_HAZARDS: usize = 8;
pub const HAZARD_RADIUS: f32 = 0.25;
pub const GOAL_RADIUS: f32 = 0.3;
pub const DT: f32 = 0.05;
pub const ACCEL: f32 = 4.0;
pub const DRAG: f32 = 4.0;
pub const TURN_RATE: f32 = 3.0;
pub const LIDAR_BINS: usize = 16;
pub const LIDAR_RANGE: f32 = 1.5;
pub const HORIZON: usize = 300;
pub const OBS_DIM: usize = 5 + LIDAR_BINS;

/// Offsets of the observation's parts.
pub const OBS_VELOCITY: usize = 0;
pub const OBS_GOAL_DIR: usize = 2;
pub const OBS_GOAL_DIST: usize = 4;
pub const OBS_LIDAR: usize = 5;

type Vec2 = [f32; 2];

fn sub(a: Vec2, b: Vec2) -> Vec2 {
    [a[0] - b[0], a[1] - b[1]]
}

fn norm(a: Vec2) -> f32 {
    a[0].hypot(a[1])
}

/// `a` expressed in a frame rotated by `angle` (world → robot frame when `angle` = θ).
fn to_frame(a: Vec2, angle: f32) -> Vec2 {
    let (s, c) = angle.sin_cos();
    [c * a[0] + s * a[1], -s * a[0] + c * a[1]]
}

/// Distance along the unit ray `dir` from the origin to the disc at `centre` (relative to the
/// ray's origin), 0 when the origin is inside, None when the ray misses it.
pub(crate) fn ray_disc(centre: Vec2, radius: f32, dir: Vec2) -> Option<f32> {
    let dist2 = centre[0] * centre[0] + centre[1] * centre[1];
    if dist2 <= radius * radius {
        return Some(0.0);
    }
    let along = centre[0] * dir[0] + centre[1] * dir[1];
    let perp2 = dist2 - along * along;
    if along <= 0.0 || perp2 > radius * radius {
        return None;
    }
    Some(along - (radius * radius - perp2).sqrt())
}

/// The layout knobs the robustness suite varies (`envs::suite`); `point-goal` itself is
/// [`Params::STANDARD`].
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Params {
    pub n_hazards: usize,
    pub hazard_radius: f32,
    pub horizon: usize,
}

impl Params {
    pub const STANDARD: Params =
        Params { n_hazards: N_HAZARDS, hazard_radius: HAZARD_RADIUS, horizon: HORIZON };
}

#[derive(Clone, Debug, PartialEq)]
pub struct PointState {
    pub pos: Vec2,
    pub vel: Vec2,
    pub heading: f32,
    pub goal: Vec2,
    pub hazards: Vec<Vec2>,
}

pub struct PointGoal {
    params: Params,
    rng: EpisodeRng,
    state: PointState,
    last_goal_dist: f32,
    t: usize,
    done: bool,
}

impl PointGoal {
    pub fn new(seed: u64) -> PointGoal {
        PointGoal::with_params(seed, Params::STANDARD)
    }

    /// A point-goal arena with other hazards or another horizon (the robustness suite).
    pub fn with_params(seed: u64, params: Params) -> PointGoal {
        let state = PointState {
            pos: [0.0; 2],
            vel: [0.0; 2],
            heading: 0.0,
            goal: [1.0, 0.0],
            hazards: vec![],
        };
        PointGoal {
            params,
            rng: EpisodeRng::new(seed),
            state,
            last_goal_dist: 1.0,
            t: 0,
            done: true,
        }
    }

    pub fn state(&self) -> &PointState {
        &self.state
    }

    /// Replaces the state (tests and illustrations set up hand-checked situations).
    pub fn set_state(&mut self, state: PointState) -> Vec<f32> {
        self.last_goal_dist = norm(sub(state.goal, state.pos));
        self.state = state;
        self.observe()
    }

    fn in_hazard(&self, p: Vec2, margin: f32) -> bool {
        let radius = self.params.hazard_radius;
        self.state.hazards.iter().any(|&h| norm(sub(p, h)) < radius + margin)
    }

    fn uniform_point(rng: &mut ChaCha8Rng) -> Vec2 {
        [rng.random_range(-PLACEMENT..PLACEMENT), rng.random_range(-PLACEMENT..PLACEMENT)]
    }

    /// Rejection-samples a point satisfying `ok`; after many failures the last draw is kept
    /// (a layout that crowded never occurs with these sizes, but sampling must terminate).
    fn sample_point(&mut self, ok: impl Fn(&Self, Vec2) -> bool) -> Vec2 {
        let mut p = Self::uniform_point(&mut self.rng.rng);
        for _ in 0..1000 {
            if ok(self, p) {
                break;
            }
            p = Self::uniform_point(&mut self.rng.rng);
        }
        p
    }

    fn place_goal(&mut self) {
        let robot = self.state.pos;
        self.state.goal = self.sample_point(|env, g| {
            !env.in_hazard(g, GOAL_RADIUS + 0.05) && norm(sub(g, robot)) >= 1.0
        });
        self.last_goal_dist = norm(sub(self.state.goal, self.state.pos));
    }

    fn lidar(&self) -> [f32; LIDAR_BINS] {
        let mut readings = [0.0f32; LIDAR_BINS];
        for (k, reading) in readings.iter_mut().enumerate() {
            let angle = self.state.heading + std::f32::consts::TAU * k as f32 / LIDAR_BINS as f32;
            let dir = [angle.cos(), angle.sin()];
            for &h in &self.state.hazards {
                if let Some(t) = ray_disc(sub(h, self.state.pos), self.params.hazard_radius, dir) {
                    *reading = reading.max((1.0 - t / LIDAR_RANGE).max(0.0));
                }
            }
        }
        readings
    }

    fn observe(&self) -> Vec<f32> {
        let s = &self.state;
        let to_goal = sub(s.goal, s.pos);
        let dist = norm(to_goal);
        let dir = to_frame(to_goal, s.heading);
        let dir = if dist > 0.0 { [dir[0] / dist, dir[1] / dist] } else { [1.0, 0.0] };
        let vel = to_frame(s.vel, s.heading);
        let mut obs = Vec::with_capacity(OBS_DIM);
        obs.extend_from_slice(&vel);
        obs.extend_from_slice(&dir);
        obs.push((-dist).exp());
        obs.extend_from_slice(&self.lidar());
        obs
    }
}

impl Env for PointGoal {
    fn name(&self) -> &'static str {
        NAME
    }

    fn obs_dim(&self) -> usize {
        OBS_DIM
    }

    fn action_space(&self) -> ActionSpace {
        ActionSpace::Continuous { dim: 2, low: vec![-1.0; 2], high: vec![1.0; 2] }
    }

    fn horizon(&self) -> usize {
        self.params.horizon
    }

    fn reset(&mut self, seed: Option<u64>) -> Vec<f32> {
        self.rng.begin(seed);
        self.state.hazards.clear();
        for _ in 0..self.params.n_hazards {
            let h = self.sample_point(|env, h| !env.in_hazard(h, env.params.hazard_radius + 0.1));
            self.state.hazards.push(h);
        }
        self.state.pos = self.sample_point(|env, p| !env.in_hazard(p, 0.1));
        self.state.vel = [0.0; 2];
        self.state.heading = self.rng.rng.random_range(-std::f32::consts::PI..std::f32::consts::PI);
        self.place_goal();
        self.t = 0;
        self.done = false;
        self.observe()
    }

    fn step(&mut self, action: Action<'_>) -> Step {
        assert!(!self.done, "step after the end of the episode");
        let Action::Continuous(a) = action else { panic!("point-goal takes a continuous action") };
        assert_eq!(a.len(), 2, "point-goal actions are (thrust, turn)");
        let (thrust, turn) = (clip_unit(a[0]), clip_unit(a[1]));
        let s = &mut self.state;
        s.heading += TURN_RATE * DT * turn;
        s.heading = (s.heading + std::f32::consts::PI).rem_euclid(std::f32::consts::TAU)
            - std::f32::consts::PI;
        let h = [s.heading.cos(), s.heading.sin()];
        for (i, h) in h.into_iter().enumerate() {
            s.vel[i] += DT * (ACCEL * thrust * h - DRAG * s.vel[i]);
            s.pos[i] += DT * s.vel[i];
            if s.pos[i].abs() > ARENA {
                s.pos[i] = s.pos[i].clamp(-ARENA, ARENA);
                s.vel[i] = 0.0;
            }
        }
        let dist = norm(sub(s.goal, s.pos));
        let mut reward = self.last_goal_dist - dist;
        self.last_goal_dist = dist;
        if dist < GOAL_RADIUS {
            reward += 1.0;
            self.place_goal();
        }
        let cost = if self.in_hazard(self.state.pos, 0.0) { 1.0 } else { 0.0 };
        self.t += 1;
        let truncated = self.t >= self.params.horizon;
        self.done = truncated;
        Step { obs: self.observe(), reward, cost, terminal: false, truncated }
    }
}

/// Std of the Gaussian noise of the demonstrators' actions, before the tanh
/// ([`super::squashed_gaussian`]).
const DEMO_NOISE: f32 = 0.25;
/// Pre-tanh mean per unit of the steering command: thrust `DEMO_GAIN · top_thrust · cos⁺` and
/// turn `DEMO_GAIN · angle`, so a full command gives `tanh(3)` ≈ 0.995.
const DEMO_GAIN: f32 = 3.0;

/// Weight of a hazard's push in [`Avoidance::Field`] at zero distance, against the goal's pull
/// of 1.
const FIELD_GAIN: f32 = 2.0;

/// [`Avoidance::Field`]'s heading: the goal's unit pull plus, per lidar ray whose hazard is
/// nearer than `needed`, a push of weight `FIELD_GAIN · (1 − d/needed)²` away from the ray and,
/// in proportion to how much the hazard lies towards the goal, around it on the left.
fn field_heading(goal: f32, needed: f32, lidar: &[f32]) -> f32 {
    let (mut x, mut y) = (goal.cos(), goal.sin());
    for (k, reading) in lidar.iter().enumerate() {
        let hazard_at = (1.0 - reading) * LIDAR_RANGE;
        let inside = ((needed - hazard_at) / needed).max(0.0);
        let push = FIELD_GAIN * inside * inside;
        let (cos, sin) = (ray_angle(k).cos(), ray_angle(k).sin());
        let towards_goal = (cos * goal.cos() + sin * goal.sin()).max(0.0);
        x += push * (-cos - towards_goal * sin);
        y += push * (-sin + towards_goal * cos);
    }
    y.atan2(x)
}

/// Angle of lidar ray `k` in the robot frame.
fn ray_angle(k: usize) -> f32 {
    std::f32::consts::TAU * k as f32 / LIDAR_BINS as f32
}

/// Smallest absolute difference of two angles.
fn angle_gap(a: f32, b: f32) -> f32 {
    let d = (a - b).rem_euclid(std::f32::consts::TAU);
    d.min(std::f32::consts::TAU - d)
}

/// How a [`Steering`] controller treats the hazards its lidar sees.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Avoidance {
    /// Straight for the goal, through hazards.
    None,
    /// The heading closest to the goal whose lidar window is clear (a vector-field-histogram
    /// rule: every ray within `window` of it sees no hazard nearer than `clearance`, or than the
    /// goal). The choice jumps from one ray to the next as the readings change.
    Window,
    /// The goal's direction plus a push from every hazard nearer than `clearance` (or than the
    /// goal), away from it and around it on the left, growing with the square of how far inside
    /// the clearance it is: the heading is a continuous function of the observation.
    Field,
}

/// A steering controller that reads only the observation. It picks a heading, turns towards it
/// and thrusts when roughly facing it. The non-preferred demonstrator heads straight for the
/// goal, through hazards; the preferred one walks around them ([`Avoidance`]). The
/// non-preferred one thrusts a little less (both collect about the same return). Actions are
/// tanh-squashed Gaussians around the command ([`super::squashed_gaussian`]), the learners' own
/// policy class.
pub(crate) struct Steering {
    pub avoidance: Avoidance,
    pub top_thrust: f32,
    /// Half-width (rad) of the lidar window that must be clear around a heading.
    pub window: f32,
    /// Distance (m) a heading must be clear for.
    pub clearance: f32,
    /// Std of the pre-tanh action noise.
    pub noise: f32,
}

impl Steering {
    pub fn preferred() -> Steering {
        Steering {
            avoidance: Avoidance::Window,
            top_thrust: 1.0,
            window: 0.3,
            clearance: 1.0,
            noise: DEMO_NOISE,
        }
    }

    pub fn non_preferred() -> Steering {
        Steering { avoidance: Avoidance::None, top_thrust: 0.8, ..Steering::preferred() }
    }

    /// Desired heading in the robot frame (rad).
    fn heading(&self, obs: &[f32]) -> f32 {
        let goal = obs[OBS_GOAL_DIR + 1].atan2(obs[OBS_GOAL_DIR]);
        let goal_dist = -obs[OBS_GOAL_DIST].max(f32::MIN_POSITIVE).ln();
        let needed = self.clearance.min(goal_dist);
        let lidar = &obs[OBS_LIDAR..OBS_LIDAR + LIDAR_BINS];
        match self.avoidance {
            Avoidance::None => goal,
            Avoidance::Window => self.window_heading(goal, needed, lidar),
            Avoidance::Field => field_heading(goal, needed, lidar),
        }
    }

    fn window_heading(&self, goal: f32, needed: f32, lidar: &[f32]) -> f32 {
        let clear = |heading: f32| {
            (0..LIDAR_BINS).all(|k| {
                let hazard_at = (1.0 - lidar[k]) * LIDAR_RANGE;
                angle_gap(ray_angle(k), heading) > self.window || hazard_at > needed
            })
        };
        let mut candidates: Vec<f32> = (0..LIDAR_BINS).map(ray_angle).collect();
        candidates.sort_by(|a, b| angle_gap(*a, goal).total_cmp(&angle_gap(*b, goal)));
        std::iter::once(goal).chain(candidates).find(|&h| clear(h)).unwrap_or(goal)
    }

    pub fn act(&self, obs: &[f32], rng: &mut ChaCha8Rng) -> [f32; 2] {
        let heading = self.heading(obs);
        let angle = heading.sin().atan2(heading.cos());
        let thrust = DEMO_GAIN * self.top_thrust * angle.cos().max(0.0);
        let turn = DEMO_GAIN * angle;
        [squashed_gaussian(thrust, self.noise, rng), squashed_gaussian(turn, self.noise, rng)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn open_field(pos: Vec2, goal: Vec2, hazards: Vec<Vec2>) -> (PointGoal, Vec<f32>) {
        let mut env = PointGoal::new(0);
        env.reset(Some(0));
        let obs = env.set_state(PointState { pos, vel: [0.0; 2], heading: 0.0, goal, hazards });
        (env, obs)
    }

    #[test]
    fn one_step_of_thrust_follows_the_documented_kinematics() {
        let (mut env, obs) = open_field([0.0, 0.0], [1.0, 0.0], vec![]);
        assert_eq!(&obs[..5], &[0.0, 0.0, 1.0, 0.0, (-1.0f32).exp()]);
        let step = env.step(Action::Continuous(&[1.0, 0.0]));
        // v = dt·ACCEL = 0.2; p = dt·v = 0.01; reward = 1 − 0.99.
        let s = env.state();
        assert!((s.vel[0] - 0.2).abs() < 1e-6 && (s.pos[0] - 0.01).abs() < 1e-6);
        assert!((step.reward - 0.01).abs() < 1e-6);
        assert_eq!((step.cost, step.terminal, step.truncated), (0.0, false, false));
        assert!((step.obs[OBS_VELOCITY] - 0.2).abs() < 1e-6);

        // Turning left by dt·TURN_RATE = 0.15 rad puts the goal to the robot's right.
        let step = env.step(Action::Continuous(&[0.0, 1.0]));
        assert!((env.state().heading - 0.15).abs() < 1e-6);
        assert!(step.obs[OBS_GOAL_DIR + 1] < 0.0);
        // Out-of-range actions are clipped: thrust 5 acts like thrust 1.
        let (mut a, _) = open_field([0.0, 0.0], [1.0, 0.0], vec![]);
        let (mut b, _) = open_field([0.0, 0.0], [1.0, 0.0], vec![]);
        assert_eq!(
            a.step(Action::Continuous(&[5.0, 0.0])),
            b.step(Action::Continuous(&[1.0, 0.0]))
        );
    }

    #[test]
    fn reaching_a_goal_pays_one_and_places_a_new_goal() {
        let (mut env, _) = open_field([0.0, 0.0], [0.3, 0.0], vec![[-1.0, -1.0]]);
        let step = env.step(Action::Continuous(&[1.0, 0.0]));
        // Distance 0.3 → 0.29 < GOAL_RADIUS: progress 0.01 plus the goal bonus.
        assert!((step.reward - 1.01).abs() < 1e-5, "{}", step.reward);
        let goal = env.state().goal;
        assert_ne!(goal, [0.3, 0.0]);
        assert!(norm(sub(goal, env.state().pos)) >= 1.0);
        assert!(norm(sub(goal, [-1.0, -1.0])) >= HAZARD_RADIUS + GOAL_RADIUS);
    }

    #[test]
    fn cost_is_one_inside_a_hazard_and_lidar_sees_it() {
        let (mut env, obs) = open_field([0.0, 0.0], [1.5, 1.5], vec![[1.0, 0.0]]);
        // Ray 0 points at the hazard: it meets the disc at t = 0.75.
        assert!((obs[OBS_LIDAR] - (1.0 - 0.75 / LIDAR_RANGE)).abs() < 1e-6);
        // The ray at 90° misses it.
        assert_eq!(obs[OBS_LIDAR + LIDAR_BINS / 4], 0.0);
        let (mut inside, obs) = open_field([0.9, 0.0], [-1.5, 1.5], vec![[1.0, 0.0]]);
        assert!(obs[OBS_LIDAR..].iter().all(|&r| r == 1.0), "inside: every ray reads 1");
        assert_eq!(inside.step(Action::Continuous(&[0.0, 0.0])).cost, 1.0);
        assert_eq!(env.step(Action::Continuous(&[0.0, 0.0])).cost, 0.0);
    }

    #[test]
    fn walls_stop_the_robot() {
        let (mut env, _) = open_field([ARENA - 0.001, 0.0], [0.0, 1.0], vec![]);
        env.state.vel = [1.0, 0.0];
        env.step(Action::Continuous(&[1.0, 0.0]));
        assert_eq!(env.state().pos[0], ARENA);
        assert_eq!(env.state().vel[0], 0.0);
    }

    fn lidar_with(hits: &[(usize, f32)]) -> [f32; LIDAR_BINS] {
        let mut lidar = [0.0; LIDAR_BINS];
        for &(k, distance) in hits {
            lidar[k] = 1.0 - distance / LIDAR_RANGE;
        }
        lidar
    }

    #[test]
    fn the_field_heads_for_the_goal_in_the_open_and_around_a_hazard_on_its_way() {
        assert!((field_heading(0.7, 1.0, &lidar_with(&[])) - 0.7).abs() < 1e-6);
        // A hazard beyond the clearance does not push.
        assert!((field_heading(0.0, 1.0, &lidar_with(&[(0, 1.2)]))).abs() < 1e-6);
        // A hazard dead ahead on the way to the goal: pass it on the left.
        let ahead = field_heading(0.0, 1.0, &lidar_with(&[(0, 0.3)]));
        assert!(ahead > 0.5, "{ahead}");
        // A hazard on the right, not towards the goal: turn away from it only.
        let right = field_heading(0.0, 1.0, &lidar_with(&[(LIDAR_BINS * 3 / 4, 0.3)]));
        assert!(right > 0.0 && right < ahead, "{right}");
        // Nearer the goal than the hazard: the hazard stops counting.
        assert!((field_heading(0.0, 0.25, &lidar_with(&[(0, 0.3)]))).abs() < 1e-6);
    }

    #[test]
    fn the_field_heading_is_continuous_in_the_readings() {
        // The window rule jumps by a ray's width as a reading crosses the clearance; the field
        // moves by little when a reading moves by little.
        for distance in [0.2f32, 0.5, 0.9, 0.999] {
            let a = field_heading(0.3, 1.0, &lidar_with(&[(1, distance)]));
            let b = field_heading(0.3, 1.0, &lidar_with(&[(1, distance + 1e-3)]));
            assert!((a - b).abs() < 1e-2, "{distance}: {a} vs {b}");
        }
    }

    #[test]
    fn ray_disc_closed_forms() {
        assert_eq!(ray_disc([2.0, 0.0], 1.0, [1.0, 0.0]), Some(1.0));
        assert_eq!(ray_disc([-2.0, 0.0], 1.0, [1.0, 0.0]), None, "behind");
        assert_eq!(ray_disc([2.0, 1.5], 1.0, [1.0, 0.0]), None, "passes beside");
        let t = ray_disc([2.0, 0.6], 1.0, [1.0, 0.0]).unwrap();
        assert!((t - (2.0 - 0.8)).abs() < 1e-6);
        assert_eq!(ray_disc([0.5, 0.0], 1.0, [0.0, 1.0]), Some(0.0), "inside");
    }

    #[test]
    fn reset_places_objects_as_documented() {
        let mut env = PointGoal::new(3);
        for seed in 0..200 {
            env.reset(Some(seed));
            let s = env.state();
            assert_eq!(s.hazards.len(), N_HAZARDS);
            for (i, a) in s.hazards.iter().enumerate() {
                for b in &s.hazards[i + 1..] {
                    assert!(norm(sub(*a, *b)) >= 2.0 * HAZARD_RADIUS + 0.1);
                }
                assert!(norm(sub(*a, s.pos)) >= HAZARD_RADIUS + 0.1);
            }
            assert!(norm(sub(s.goal, s.pos)) >= 1.0);
        }
    }
}
