//! `pace`: the robustness suite's long-horizon task where the two demonstrators differ in most
//! states, as a joint-velocity constraint makes them differ on a walker (the paper's RWRL
//! experiments). `joints` first-order actuated joints move forward: each step
//! `v_i += DT · GAIN · (u_i − v_i)` for the action `u_i ∈ [-1, 1]`; the reward is the mean joint
//! velocity times `DT` (progress), and every step on which some `|v_i|` exceeds `limit` costs 1.
//! Never terminal; the episode is truncated at the horizon.
//!
//! The observation is the joint velocities and a clock `(sin φ, cos φ)` with `φ = 2π t / period`,
//! so a policy that moves in rhythm is Markov in it. Both demonstrators average the same speed
//! `target`, so they collect about the same return: the preferred one holds `target` on every
//! joint, the non-preferred one surges and coasts, `target · (1 + amplitude · sin(φ + offset_i))`,
//! and spends the peaks of each cycle above `limit`.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::data::{ActionSpace, Actions};
use crate::envs::{clip_unit, squashed_gaussian, Action, Demonstrator, Env, EpisodeRng, Step};

pub const DT: f32 = 0.05;
pub const GAIN: f32 = 4.0;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PaceParams {
    pub joints: usize,
    pub target: f32,
    pub amplitude: f32,
    pub limit: f32,
    /// Steps per cycle of the clock.
    pub period: usize,
    pub horizon: usize,
    /// Std of the demonstrators' pre-tanh action noise.
    pub demo_noise: f32,
}

impl PaceParams {
    /// Draws a task: 1-3 joints, target speed 0.3-0.5, surges of ±40-80% whose peaks pass a
    /// limit set halfway up them, cycles of 20-60 steps, 200-400 steps per episode.
    pub fn draw(rng: &mut ChaCha8Rng) -> PaceParams {
        let target = rng.random_range(0.3..0.5);
        let amplitude = rng.random_range(0.4..0.8);
        PaceParams {
            joints: rng.random_range(1..=3),
            target,
            amplitude,
            limit: target * (1.0 + amplitude / 2.0),
            period: rng.random_range(20..=60),
            horizon: rng.random_range(200..=400),
            demo_noise: rng.random_range(0.1..0.3),
        }
    }

    fn obs_dim(&self) -> usize {
        self.joints + 2
    }
}

pub struct Pace {
    params: PaceParams,
    rng: EpisodeRng,
    velocity: Vec<f32>,
    /// Clock phase offset of this episode (random at reset).
    phase0: f32,
    t: usize,
    done: bool,
}

impl Pace {
    pub fn new(params: PaceParams) -> Pace {
        Pace {
            velocity: vec![0.0; params.joints],
            params,
            rng: EpisodeRng::new(0),
            phase0: 0.0,
            t: 0,
            done: true,
        }
    }

    fn observe(&self) -> Vec<f32> {
        let phase = self.phase0 + std::f32::consts::TAU * self.t as f32 / self.params.period as f32;
        let mut obs = self.velocity.clone();
        obs.extend([phase.sin(), phase.cos()]);
        obs
    }
}

impl Env for Pace {
    fn name(&self) -> &'static str {
        "suite-pace"
    }

    fn obs_dim(&self) -> usize {
        self.params.obs_dim()
    }

    fn action_space(&self) -> ActionSpace {
        let dim = self.params.joints;
        ActionSpace::Continuous { dim, low: vec![-1.0; dim], high: vec![1.0; dim] }
    }

    fn horizon(&self) -> usize {
        self.params.horizon
    }

    fn reset(&mut self, seed: Option<u64>) -> Vec<f32> {
        self.rng.begin(seed);
        let top = self.params.target;
        for v in &mut self.velocity {
            *v = self.rng.rng.random_range(0.0..top);
        }
        self.phase0 = self.rng.rng.random_range(0.0..std::f32::consts::TAU);
        self.t = 0;
        self.done = false;
        self.observe()
    }

    fn step(&mut self, action: Action<'_>) -> Step {
        assert!(!self.done, "step after the end of the episode");
        let Action::Continuous(u) = action else { panic!("pace takes a continuous action") };
        assert_eq!(u.len(), self.params.joints, "one action per joint");
        for (v, &u) in self.velocity.iter_mut().zip(u) {
            *v += DT * GAIN * (clip_unit(u) - *v);
        }
        let mean = self.velocity.iter().sum::<f32>() / self.params.joints as f32;
        let over = self.velocity.iter().any(|v| v.abs() > self.params.limit);
        self.t += 1;
        let truncated = self.t >= self.params.horizon;
        self.done = truncated;
        Step {
            obs: self.observe(),
            reward: mean * DT,
            cost: f32::from(u8::from(over)),
            terminal: false,
            truncated,
        }
    }
}

/// The two demonstrators of [`Pace`] (see the module docs).
pub struct Pacer {
    params: PaceParams,
    surge: bool,
}

impl Pacer {
    pub fn new(params: PaceParams, preferred: bool) -> Pacer {
        Pacer { params, surge: !preferred }
    }

    fn act(&self, obs: &[f32], rng: &mut ChaCha8Rng, out: &mut Vec<f32>) {
        let p = &self.params;
        let phase = obs[p.joints].atan2(obs[p.joints + 1]);
        for (i, &v) in obs[..p.joints].iter().enumerate() {
            let offset = std::f32::consts::TAU * i as f32 / p.joints as f32;
            let wanted = if self.surge {
                p.target * (1.0 + p.amplitude * (phase + offset).sin())
            } else {
                p.target
            };
            // Feed-forward to the wanted speed plus a proportional correction, in tanh space.
            let command = (wanted + 0.5 * (wanted - v)).clamp(-0.97, 0.97);
            out.push(squashed_gaussian(command.atanh(), p.demo_noise, rng));
        }
    }
}

impl Demonstrator for Pacer {
    fn obs_dim(&self) -> usize {
        self.params.obs_dim()
    }

    fn act_batch(&self, observations: &[f32], rng: &mut ChaCha8Rng) -> Actions {
        let mut out = Vec::with_capacity(observations.len());
        for obs in observations.chunks_exact(self.params.obs_dim()) {
            self.act(obs, rng, &mut out);
        }
        Actions::Continuous(out)
    }
}
