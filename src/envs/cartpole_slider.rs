//! `cartpole-slider`: the RWRL cartpole swing-up (`realworld_swingup`, paper section 5.1) with
//! its slider-position constraint, written from scratch on the textbook cart-pole equations
//! with dm_control's parameters (no physics engine).
//!
//! - State: cart position `x` (m) and velocity, pole angle `θ` (rad, 0 = upright, positive when
//!   the pole leans towards +x) and angular velocity. Cart 1 kg, pole a uniform 0.1 kg rod of
//!   length 1 m (half-length `l` = 0.5), gravity 9.81, force `F = 10·u` N for the action
//!   `u ∈ [-1, 1]` (clipped).
//! - Dynamics (Barto, Sutton & Anderson 1983, frictionless), with `T = M + m`:
//!   `c = (F + m·l·θ̇²·sin θ)/T`, `θ̈ = (g·sin θ − cos θ·c) / (l·(4/3 − m·cos²θ/T))`,
//!   `ẍ = c − m·l·θ̈·cos θ/T`; semi-implicit Euler with `dt` = [`DT`] (velocities first, as
//!   MuJoCo's Euler integrator). Rails stop the cart at `|x|` = [`RAIL`] (its velocity is zeroed).
//! - Reset (swing-up): pole hanging, `θ = π + U(−0.2, 0.2)`, `x ~ U(−0.45, 0.45)` (so a few
//!   episodes start beyond the safety bound: the paper notes cost that no policy can avoid),
//!   velocities `N(0, 0.05²)`.
//! - Reward (dm_control's smooth swing-up reward, in [0, 1] per step):
//!   `upright · centred · small_control · small_velocity` with `upright = (cos θ + 1)/2`,
//!   `centred = (1 + tol(x, 2))/2`, `small_control = (4 + 1 − u²)/5`,
//!   `small_velocity = (1 + tol(θ̇, 5))/2`, where `tol(v, m) = exp(−½·(v·s/m)²)` with
//!   `s = sqrt(−2 ln 0.1)` (dm_control's Gaussian tolerance: 0.1 at the margin).
//! - Cost: 1 per step with `|x|` > [`SLIDER_BOUND`] = safety coefficient 0.2 × 2 m, RWRL's
//!   `slider_pos_constraint` limits for `realworld_swingup`.
//! - Observation (dm_control order): `x, cos θ, sin θ, ẋ, θ̇`.
//! - Horizon: [`HORIZON`] steps (10 s), never terminal.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::{clip_unit, Action, Env, EpisodeRng, Step};
use crate::data::ActionSpace;

pub const NAME: &str = "cartpole-slider";
pub const DESCRIPTION: &str = "RWRL cartpole swing-up with the slider-position constraint \
     (paper section 5.1, safety coefficient 0.2): swing the pole up and balance it; cost while \
     the cart is more than 0.4 m from the centre. Observations: x, cos, sin, x', theta'.";
pub const REWARD: &str =
    "dm_control smooth swing-up reward in [0,1]: upright x centred x small control x small velocity";
pub const COST: &str = "1 per step with |cart position| > 0.4 m";

pub const SAFETY_COEFFICIENT: f32 = 0.2;
pub const SLIDER_BOUND: f32 = SAFETY_COEFFICIENT * 2.0;
pub const DT: f32 = 0.01;
pub const HORIZON: usize = 1000;
pub const RAIL: f32 = 1.8;
const GRAVITY: f32 = 9.81;
const CART_MASS: f32 = 1.0;
const POLE_MASS: f32 = 0.1;
const HALF_LENGTH: f32 = 0.5;
const FORCE: f32 = 10.0;

/// `[x, ẋ, θ, θ̇]`.
pub type State = [f32; 4];

/// Time derivative of the velocities `(ẍ, θ̈)` under force `force`.
fn accelerations(s: &State, force: f32) -> (f32, f32) {
    let total = CART_MASS + POLE_MASS;
    let (sin, cos) = s[2].sin_cos();
    let c = (force + POLE_MASS * HALF_LENGTH * s[3] * s[3] * sin) / total;
    let theta_acc =
        (GRAVITY * sin - cos * c) / (HALF_LENGTH * (4.0 / 3.0 - POLE_MASS * cos * cos / total));
    let x_acc = c - POLE_MASS * HALF_LENGTH * theta_acc * cos / total;
    (x_acc, theta_acc)
}

/// dm_control's `tolerance(v, bounds=(0, 0), margin, sigmoid='gaussian', value_at_margin=0.1)`.
fn gaussian_tolerance(v: f32, margin: f32) -> f32 {
    let scale = (-2.0 * 0.1f32.ln()).sqrt();
    (-0.5 * (v / margin * scale).powi(2)).exp()
}

/// The reward of being in `s` after applying action `u`.
pub fn reward(s: &State, u: f32) -> f32 {
    let upright = (s[2].cos() + 1.0) / 2.0;
    let centred = (1.0 + gaussian_tolerance(s[0], 2.0)) / 2.0;
    // Quadratic tolerance with margin 1 and value 0 at the margin: 1 − u² on [−1, 1].
    let small_control = (4.0 + (1.0 - u * u).max(0.0)) / 5.0;
    let small_velocity = (1.0 + gaussian_tolerance(s[3], 5.0)) / 2.0;
    upright * centred * small_control * small_velocity
}

pub fn observation(s: &State) -> Vec<f32> {
    vec![s[0], s[2].cos(), s[2].sin(), s[1], s[3]]
}

pub struct CartpoleSlider {
    rng: EpisodeRng,
    state: State,
    t: usize,
    done: bool,
}

impl CartpoleSlider {
    pub fn new(seed: u64) -> CartpoleSlider {
        CartpoleSlider { rng: EpisodeRng::new(seed), state: [0.0; 4], t: 0, done: true }
    }

    pub fn state(&self) -> State {
        self.state
    }

    /// Replaces the state (tests set up hand-checked situations).
    pub fn set_state(&mut self, state: State) -> Vec<f32> {
        self.state = state;
        observation(&state)
    }
}

impl Env for CartpoleSlider {
    fn name(&self) -> &'static str {
        NAME
    }

    fn obs_dim(&self) -> usize {
        5
    }

    fn action_space(&self) -> ActionSpace {
        ActionSpace::Continuous { dim: 1, low: vec![-1.0], high: vec![1.0] }
    }

    fn horizon(&self) -> usize {
        HORIZON
    }

    fn reset(&mut self, seed: Option<u64>) -> Vec<f32> {
        self.rng.begin(seed);
        let rng = &mut self.rng.rng;
        let jitter = Normal::new(0.0f32, 0.05).expect("valid std");
        self.state = [
            rng.random_range(-0.45..0.45),
            jitter.sample(rng),
            std::f32::consts::PI + rng.random_range(-0.2..0.2),
            jitter.sample(rng),
        ];
        self.t = 0;
        self.done = false;
        observation(&self.state)
    }

    fn step(&mut self, action: Action<'_>) -> Step {
        assert!(!self.done, "step after the end of the episode");
        let Action::Continuous(a) = action else { panic!("cartpole takes a continuous action") };
        assert_eq!(a.len(), 1, "cartpole actions have one component");
        let u = clip_unit(a[0]);
        let s = &mut self.state;
        let (x_acc, theta_acc) = accelerations(s, FORCE * u);
        s[1] += DT * x_acc;
        s[3] += DT * theta_acc;
        s[0] += DT * s[1];
        s[2] += DT * s[3];
        if s[0].abs() > RAIL {
            s[0] = s[0].clamp(-RAIL, RAIL);
            s[1] = 0.0;
        }
        self.t += 1;
        let truncated = self.t >= HORIZON;
        self.done = truncated;
        let s = *s;
        Step {
            obs: observation(&s),
            reward: reward(&s, u),
            cost: if s[0].abs() > SLIDER_BOUND { 1.0 } else { 0.0 },
            terminal: false,
            truncated,
        }
    }
}

/// State-feedback gains `K` (action `u = −K·s`) of the discrete-time LQR for the cart-pole
/// linearised at the upright equilibrium, from iterating the Riccati recursion to convergence.
pub(crate) fn lqr_gains(q: [f32; 4], r: f32) -> [f32; 4] {
    // Linearisation of `accelerations` at θ = θ̇ = 0 in f64 for a well-conditioned recursion.
    let (m, l, g) = (POLE_MASS as f64, HALF_LENGTH as f64, GRAVITY as f64);
    let total = (CART_MASS + POLE_MASS) as f64;
    let d = l * (4.0 / 3.0 - m / total);
    let force = FORCE as f64;
    let (th_theta, th_u) = (g / d, -force / (total * d));
    let (x_theta, x_u) = (-m * l * th_theta / total, force / total - m * l * th_u / total);
    let dt = DT as f64;
    // Semi-implicit Euler as in `step`: velocities first, positions with the new velocities.
    let a = [
        [1.0, dt, dt * dt * x_theta, 0.0],
        [0.0, 1.0, dt * x_theta, 0.0],
        [0.0, 0.0, 1.0 + dt * dt * th_theta, dt],
        [0.0, 0.0, dt * th_theta, 1.0],
    ];
    let b = [dt * dt * x_u, dt * x_u, dt * dt * th_u, dt * th_u];
    let mut p = [[0.0f64; 4]; 4];
    for i in 0..4 {
        p[i][i] = q[i] as f64;
    }
    let mut k = [0.0f64; 4];
    for _ in 0..20_000 {
        // k = (r + bᵀPb)⁻¹ bᵀPA ;  P = Q + AᵀPA − AᵀPb k
        let pb: Vec<f64> = (0..4).map(|i| (0..4).map(|j| p[i][j] * b[j]).sum()).collect();
        let denom = r as f64 + (0..4).map(|i| b[i] * pb[i]).sum::<f64>();
        let pa: Vec<[f64; 4]> = (0..4)
            .map(|i| std::array::from_fn(|j| (0..4).map(|t| p[i][t] * a[t][j]).sum()))
            .collect();
        k = std::array::from_fn(|j| (0..4).map(|i| b[i] * pa[i][j]).sum::<f64>() / denom);
        let mut next = [[0.0f64; 4]; 4];
        for i in 0..4 {
            for j in 0..4 {
                let apa: f64 = (0..4).map(|t| a[t][i] * pa[t][j]).sum();
                let apb: f64 = (0..4).map(|t| a[t][i] * pb[t]).sum();
                next[i][j] = apa - apb * k[j] + if i == j { q[i] as f64 } else { 0.0 };
            }
        }
        p = next;
    }
    k.map(|x| x as f32)
}

/// Energy of the pole relative to resting upright (J): kinetic about the pivot plus potential.
pub(crate) fn pole_energy(cos_theta: f32, theta_dot: f32) -> f32 {
    let inertia = 4.0 / 3.0 * POLE_MASS * HALF_LENGTH * HALF_LENGTH;
    0.5 * inertia * theta_dot * theta_dot + POLE_MASS * GRAVITY * HALF_LENGTH * (cos_theta - 1.0)
}

/// Energy-pumping swing-up (Åström & Furuta) followed by LQR balancing, reading only the
/// observation. The pumping action is limited to `pump_limit`; `centring` is the cart position
/// and velocity feedback added while swinging up. The preferred demonstrator uses it and keeps
/// the cart near the centre (mostly inside the safety bound); the non-preferred one swings up
/// without it and lets the cart run far out. Both balance with the same LQR, which brings the
/// cart back to the centre, so their returns end up close (tuned so; see the tests).
pub(crate) struct SwingUp {
    pump_gain: f32,
    /// Largest pumping action: bounds the cart's excursions while swinging up.
    pump_limit: f32,
    centring: [f32; 2],
    balance: [f32; 4],
    noise: f32,
}

/// |θ| below which the balancing controller takes over.
const CATCH_ANGLE: f32 = 0.35;

impl SwingUp {
    pub fn preferred() -> SwingUp {
        SwingUp { centring: [1.0, 0.6], ..SwingUp::non_preferred() }
    }

    pub fn non_preferred() -> SwingUp {
        SwingUp {
            pump_gain: 30.0,
            pump_limit: 1.0,
            centring: [0.0, 0.0],
            balance: lqr_gains([20.0, 1.0, 20.0, 1.0], 1.0),
            noise: 0.2,
        }
    }

    pub fn act(&self, obs: &[f32], rng: &mut ChaCha8Rng) -> f32 {
        let (x, cos, sin, x_dot, theta_dot) = (obs[0], obs[1], obs[2], obs[3], obs[4]);
        let theta = sin.atan2(cos);
        let u = if theta.abs() < CATCH_ANGLE {
            let s = [x, x_dot, theta, theta_dot];
            -(0..4).map(|i| self.balance[i] * s[i]).sum::<f32>()
        } else {
            // Pushing the cart along −θ̇·cos θ adds energy while the pole is below its target.
            let deficit = -pole_energy(cos, theta_dot);
            let pump =
                (self.pump_gain * deficit).min(self.pump_limit) * (-theta_dot * cos).signum();
            pump - self.centring[0] * x - self.centring[1] * x_dot
        };
        let noise = Normal::new(0.0, self.noise).expect("valid std");
        clip_unit(u + noise.sample(rng))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resting_upright_pays_the_full_reward_and_stays() {
        let mut env = CartpoleSlider::new(0);
        env.reset(Some(0));
        let obs = env.set_state([0.0; 4]);
        assert_eq!(obs, vec![0.0, 1.0, 0.0, 0.0, 0.0]);
        let step = env.step(Action::Continuous(&[0.0]));
        assert_eq!(env.state(), [0.0; 4]);
        assert_eq!((step.reward, step.cost), (1.0, 0.0));
    }

    #[test]
    fn hanging_pole_earns_nothing_and_the_force_moves_the_cart() {
        let mut env = CartpoleSlider::new(0);
        env.reset(Some(0));
        env.set_state([0.0, 0.0, std::f32::consts::PI, 0.0]);
        let step = env.step(Action::Continuous(&[1.0]));
        // Hanging at rest: upright = 0. With θ = π, sin θ ≈ 0: θ̈ = −cos θ·c / (l·(4/3 − m/T))
        // and ẍ = c − m·l·θ̈·cos θ / T with c = 10/1.1.
        assert!(step.reward.abs() < 1e-6);
        let c: f32 = 10.0 / 1.1;
        let theta_acc = c / (0.5 * (4.0 / 3.0 - 0.1 / 1.1));
        let x_acc = c + 0.1 * 0.5 * theta_acc / 1.1;
        let s = env.state();
        assert!((s[1] - DT * x_acc).abs() < 1e-4, "{} vs {}", s[1], DT * x_acc);
        assert!((s[3] - DT * theta_acc).abs() < 1e-3, "{} vs {}", s[3], DT * theta_acc);
        assert!((s[0] - DT * DT * x_acc).abs() < 1e-6);
    }

    #[test]
    fn reward_terms_match_dm_control_tolerances() {
        // At the margin a Gaussian tolerance is 0.1: centred = 0.55, small velocity = 0.55.
        let r = reward(&[2.0, 0.0, 0.0, 5.0], 0.0);
        assert!((r - 0.55 * 0.55).abs() < 1e-5, "{r}");
        // Full control costs a fifth; a horizontal pole earns half.
        let r = reward(&[0.0, 0.0, std::f32::consts::FRAC_PI_2, 0.0], 1.0);
        assert!((r - 0.5 * 0.8).abs() < 1e-5, "{r}");
    }

    #[test]
    fn cost_is_charged_beyond_the_slider_bound() {
        let mut env = CartpoleSlider::new(0);
        env.reset(Some(0));
        env.set_state([0.39, 0.0, 0.0, 0.0]);
        assert_eq!(env.step(Action::Continuous(&[0.0])).cost, 0.0);
        env.set_state([-0.41, 0.0, 0.0, 0.0]);
        assert_eq!(env.step(Action::Continuous(&[0.0])).cost, 1.0);
        assert_eq!(SLIDER_BOUND, 0.4);
    }

    #[test]
    fn rails_stop_the_cart() {
        let mut env = CartpoleSlider::new(0);
        env.reset(Some(0));
        env.set_state([RAIL - 0.001, 1.0, 0.0, 0.0]);
        env.step(Action::Continuous(&[1.0]));
        assert_eq!(env.state()[0], RAIL);
        assert_eq!(env.state()[1], 0.0);
    }

    #[test]
    fn lqr_balances_the_linearised_and_the_nonlinear_pole() {
        let k = lqr_gains([20.0, 1.0, 20.0, 1.0], 1.0);
        let mut env = CartpoleSlider::new(0);
        env.reset(Some(0));
        env.set_state([0.2, 0.0, 0.15, 0.0]);
        for _ in 0..500 {
            let s = env.state();
            let u = -(0..4).map(|i| k[i] * s[i]).sum::<f32>();
            env.step(Action::Continuous(&[u]));
        }
        let s = env.state();
        assert!(s.iter().all(|v| v.abs() < 0.02), "not settled: {s:?}");
    }

    #[test]
    fn energy_is_zero_upright_at_rest_and_minus_mgl2_hanging() {
        assert_eq!(pole_energy(1.0, 0.0), 0.0);
        assert!((pole_energy(-1.0, 0.0) + 2.0 * 0.1 * 9.81 * 0.5).abs() < 1e-6);
    }
}
