//! Generated gridworlds of the robustness suite: a random walled grid with hazard cells, a start
//! and a goal. Reaching the goal pays 1 and either ends the episode (terminal goal) or sends the
//! agent back to the start (continuing: the return counts goals reached before the horizon).
//! Every step that ends on a hazard cell costs 1. With probability `slip` the executed action is
//! a uniformly random one.
//!
//! The two demonstrators follow shortest routes to the goal under different step prices
//! (Dijkstra over the cells, recomputed from any cell, so both are Markov policies of the
//! one-hot observation): the preferred one pays 1 per step plus 10 per hazard cell entered, so it
//! walks around hazards; the non-preferred one pays 1 per step but only 0.8 on a hazard cell, so
//! among routes of about the same length it takes the one through hazards. Both take a random
//! action with probability `demo_epsilon`.

use std::collections::BinaryHeap;
use std::sync::Arc;

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::data::{ActionSpace, Actions};
use crate::envs::{Action, Demonstrator, Env, EpisodeRng, Step};

/// (row, col) moves of the actions up, right, down, left.
const MOVES: [(isize, isize); 4] = [(-1, 0), (0, 1), (1, 0), (0, -1)];
const WALL: u8 = b'#';
const HAZARD: u8 = b'$';

/// A generated grid, as the report shows it: one string per row, `#` wall, `$` hazard, `.`
/// free, `S` start, `G` goal.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GridParams {
    pub map: Vec<String>,
    pub terminal_goal: bool,
    pub slip: f64,
    pub demo_epsilon: f64,
    pub horizon: usize,
}

/// The parsed map: free cells, their observation index and the demonstrators' distance fields.
#[derive(Debug)]
pub struct Layout {
    height: usize,
    width: usize,
    cells: Vec<u8>,
    index: Vec<Option<usize>>,
    free: Vec<usize>,
    start: usize,
    goal: usize,
}

impl Layout {
    pub fn parse(map: &[String]) -> Layout {
        let height = map.len();
        let width = map[0].len();
        let mut cells: Vec<u8> = map.iter().flat_map(|r| r.bytes()).collect();
        let start = cells.iter().position(|&c| c == b'S').expect("a start cell");
        let goal = cells.iter().position(|&c| c == b'G').expect("a goal cell");
        cells[start] = b'.';
        cells[goal] = b'.';
        let mut index = vec![None; cells.len()];
        let mut free = Vec::new();
        for (i, &c) in cells.iter().enumerate() {
            if c != WALL {
                index[i] = Some(free.len());
                free.push(i);
            }
        }
        Layout { height, width, cells, index, free, start, goal }
    }

    pub fn n_free(&self) -> usize {
        self.free.len()
    }

    fn is_hazard(&self, cell: usize) -> bool {
        self.cells[cell] == HAZARD
    }

    /// The cell `action` leads to from `cell` (unchanged into a wall or off the grid).
    fn moved(&self, cell: usize, action: usize) -> usize {
        let (r, c) = (cell / self.width, cell % self.width);
        let (dr, dc) = MOVES[action];
        let (nr, nc) = (r.wrapping_add_signed(dr), c.wrapping_add_signed(dc));
        if nr < self.height && nc < self.width && self.cells[nr * self.width + nc] != WALL {
            nr * self.width + nc
        } else {
            cell
        }
    }

    /// Cheapest price from every cell to the goal when entering a cell costs `price(cell)`.
    fn distances(&self, price: impl Fn(usize) -> f64) -> Vec<f64> {
        let mut dist = vec![f64::INFINITY; self.cells.len()];
        let mut heap = BinaryHeap::new();
        dist[self.goal] = 0.0;
        // Max-heap on negated fixed-point prices: deterministic, no float ordering issues.
        heap.push((0i64, self.goal));
        while let Some((neg, cell)) = heap.pop() {
            let d = -neg as f64 / 1000.0;
            if d > dist[cell] + 1e-9 {
                continue;
            }
            for a in 0..MOVES.len() {
                let prev = self.moved(cell, a);
                // `prev` reaches `cell` by the opposite move when the grid is symmetric; check it.
                if prev == cell || self.moved(prev, (a + 2) % 4) != cell {
                    continue;
                }
                let nd = d + price(cell);
                if nd + 1e-9 < dist[prev] {
                    dist[prev] = nd;
                    heap.push((-(nd * 1000.0).round() as i64, prev));
                }
            }
        }
        dist
    }

    /// The greedy action of a distance field from `cell` (lowest index among ties).
    fn greedy(&self, dist: &[f64], price: &impl Fn(usize) -> f64, cell: usize) -> usize {
        let value = |a: usize| {
            let next = self.moved(cell, a);
            if next == cell {
                f64::INFINITY
            } else {
                price(next) + dist[next]
            }
        };
        (0..MOVES.len()).min_by(|&a, &b| value(a).total_cmp(&value(b))).unwrap_or(0)
    }

    /// The route a demonstrator takes without noise: (steps, hazard cells entered), or None when
    /// the goal is unreachable.
    fn route(&self, preferred: bool) -> Option<(usize, usize)> {
        let price = route_price(self, preferred);
        let dist = self.distances(&price);
        if !dist[self.start].is_finite() {
            return None;
        }
        let (mut cell, mut steps, mut hazards) = (self.start, 0, 0);
        while cell != self.goal && steps <= self.cells.len() {
            cell = self.moved(cell, self.greedy(&dist, &price, cell));
            steps += 1;
            hazards += usize::from(self.is_hazard(cell));
        }
        (cell == self.goal).then_some((steps, hazards))
    }
}

fn route_price(layout: &Layout, preferred: bool) -> impl Fn(usize) -> f64 + '_ {
    move |cell| match (layout.is_hazard(cell), preferred) {
        (false, _) => 1.0,
        (true, true) => 11.0,
        (true, false) => 0.8,
    }
}

/// Draws a grid whose two demonstrator routes differ: the non-preferred one crosses at least two
/// hazard cells, the preferred one fewer, and it is at most 30% longer (so the two returns are
/// about equal). Rejection-samples with `rng`; None after many failures.
pub fn generate_map(rng: &mut ChaCha8Rng) -> Option<Vec<String>> {
    for _ in 0..2000 {
        let (h, w) = (rng.random_range(5..=9usize), rng.random_range(5..=9usize));
        let (height, width) = (h + 2, w + 2);
        let mut cells = vec![b'.'; height * width];
        for r in 0..height {
            for c in 0..width {
                if r == 0 || c == 0 || r == height - 1 || c == width - 1 {
                    cells[r * width + c] = WALL;
                }
            }
        }
        let wall_density = rng.random_range(0.0..0.15);
        let interior = |r: usize, c: usize| r * width + c;
        for r in 1..height - 1 {
            for c in 1..width - 1 {
                if rng.random_bool(wall_density) {
                    cells[interior(r, c)] = WALL;
                }
            }
        }
        for _ in 0..rng.random_range(1..=3) {
            let (ph, pw) = (rng.random_range(1..=3usize), rng.random_range(1..=3usize));
            let (r0, c0) = (rng.random_range(1..=h), rng.random_range(1..=w));
            for r in r0..(r0 + ph).min(height - 1) {
                for c in c0..(c0 + pw).min(width - 1) {
                    cells[interior(r, c)] = HAZARD;
                }
            }
        }
        // Start near one corner, goal near the opposite one.
        let start = interior(rng.random_range(1..=2), rng.random_range(1..=2));
        let goal =
            interior(height - 1 - rng.random_range(1..=2), width - 1 - rng.random_range(1..=2));
        cells[start] = b'S';
        cells[goal] = b'G';
        let map: Vec<String> =
            cells.chunks(width).map(|row| String::from_utf8_lossy(row).into_owned()).collect();
        let layout = Layout::parse(&map);
        let (Some(safe), Some(unsafe_)) = (layout.route(true), layout.route(false)) else {
            continue;
        };
        if unsafe_.1 >= 2 && safe.1 < unsafe_.1 && safe.0 * 10 <= unsafe_.0 * 13 {
            return Some(map);
        }
    }
    None
}

pub struct Grid {
    layout: Arc<Layout>,
    params: Arc<GridParams>,
    rng: EpisodeRng,
    cell: usize,
    t: usize,
    done: bool,
}

impl Grid {
    pub fn new(layout: Arc<Layout>, params: Arc<GridParams>) -> Grid {
        let cell = layout.start;
        Grid { layout, params, rng: EpisodeRng::new(0), cell, t: 0, done: true }
    }

    fn observe(&self) -> Vec<f32> {
        let mut obs = vec![0.0; self.layout.n_free()];
        obs[self.layout.index[self.cell].expect("the agent is on a free cell")] = 1.0;
        obs
    }
}

impl Env for Grid {
    fn name(&self) -> &'static str {
        "suite-grid"
    }

    fn obs_dim(&self) -> usize {
        self.layout.n_free()
    }

    fn action_space(&self) -> ActionSpace {
        ActionSpace::Discrete { n: MOVES.len() }
    }

    fn horizon(&self) -> usize {
        self.params.horizon
    }

    fn reset(&mut self, seed: Option<u64>) -> Vec<f32> {
        self.rng.begin(seed);
        self.cell = self.layout.start;
        self.t = 0;
        self.done = false;
        self.observe()
    }

    fn step(&mut self, action: Action<'_>) -> Step {
        assert!(!self.done, "step after the end of the episode");
        let Action::Discrete(a) = action else { panic!("a grid takes a discrete action") };
        let mut a = a as usize;
        if self.rng.rng.random_bool(self.params.slip) {
            a = self.rng.rng.random_range(0..MOVES.len());
        }
        self.cell = self.layout.moved(self.cell, a);
        let cost = f32::from(u8::from(self.layout.is_hazard(self.cell)));
        let at_goal = self.cell == self.layout.goal;
        let reward = f32::from(u8::from(at_goal));
        let terminal = at_goal && self.params.terminal_goal;
        if at_goal && !terminal {
            self.cell = self.layout.start;
        }
        self.t += 1;
        let truncated = !terminal && self.t >= self.params.horizon;
        self.done = terminal || truncated;
        Step { obs: self.observe(), reward, cost, terminal, truncated }
    }
}

/// A route follower of [`Layout`] (see the module docs).
pub struct RouteFollower {
    layout: Arc<Layout>,
    /// The greedy action of every free cell.
    actions: Vec<usize>,
    epsilon: f64,
}

impl RouteFollower {
    pub fn new(layout: Arc<Layout>, preferred: bool, epsilon: f64) -> RouteFollower {
        let actions = {
            let price = route_price(&layout, preferred);
            let dist = layout.distances(&price);
            layout.free.iter().map(|&cell| layout.greedy(&dist, &price, cell)).collect()
        };
        RouteFollower { layout, actions, epsilon }
    }
}

impl Demonstrator for RouteFollower {
    fn obs_dim(&self) -> usize {
        self.layout.n_free()
    }

    fn act_batch(&self, observations: &[f32], rng: &mut ChaCha8Rng) -> Actions {
        let rows = observations.chunks_exact(self.layout.n_free());
        Actions::Discrete(
            rows.map(|obs| {
                // The agent's cell is the largest entry (robust to observation noise).
                let i = (0..obs.len()).max_by(|&a, &b| obs[a].total_cmp(&obs[b])).unwrap_or(0);
                if rng.random_bool(self.epsilon) {
                    rng.random_range(0..MOVES.len() as u32)
                } else {
                    self.actions[i] as u32
                }
            })
            .collect(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn generated_maps_separate_the_two_routes() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..20 {
            let map = generate_map(&mut rng).expect("a map");
            let layout = Layout::parse(&map);
            let (safe, unsafe_) = (layout.route(true).unwrap(), layout.route(false).unwrap());
            assert!(unsafe_.1 >= 2 && safe.1 < unsafe_.1, "{map:?}");
            assert!(safe.0 * 10 <= unsafe_.0 * 13, "{map:?}");
        }
    }

    #[test]
    fn hand_made_grid_routes_are_the_expected_ones() {
        // Straight through the hazard row (4 steps, 3 hazards) or around it (6 steps, 0).
        let map: Vec<String> =
            ["#######", "#.....#", "#S$$$G#", "#######"].iter().map(|s| s.to_string()).collect();
        let layout = Layout::parse(&map);
        assert_eq!(layout.route(false), Some((4, 3)));
        assert_eq!(layout.route(true), Some((6, 0)));
    }
}
