//! Builds the column [`Dataset`] from the row-per-transition formats (JSONL, CSV), enforcing
//! everything that must hold *across* rows with the line number of the offending row: equal
//! dimensions, one kind of action, contiguous episodes, terminals only at episode ends, rewards
//! and costs on all rows or none, and `next_obs` filled from the next row of the same episode.
//!
//! Rule for a missing `next_obs` on the last row of an episode: a terminal row gets its own `obs`
//! (the successor of a terminal state is never bootstrapped from, so any finite value is
//! equivalent); a non-terminal row is rejected, since its successor is unknown and silently
//! dropping the row would change the data behind the user's back.

use std::collections::HashSet;

use super::error::ParseError;
use super::model::{ActionSpace, Actions, Dataset, DatasetParts};

/// Discrete actions are one-hot encoded for the networks, so `n` must stay reasonable.
pub const MAX_DISCRETE_ACTIONS: u64 = 65_536;

/// One transition as a row-format parser read it (borrowed from the parser's buffers).
pub struct Row<'a> {
    pub episode: u32,
    pub obs: &'a [f32],
    pub action: RowAction<'a>,
    pub next_obs: Option<&'a [f32]>,
    pub terminal: bool,
    pub reward: Option<f32>,
    pub cost: Option<f32>,
}

pub enum RowAction<'a> {
    Continuous(&'a [f32]),
    Discrete(u64),
}

#[derive(Clone, Copy, PartialEq)]
enum ActionKind {
    Continuous(usize),
    Discrete,
}

/// The open episode: id, line of its first row, and the last row's line and terminal flag.
struct OpenEpisode {
    id: u32,
    last_line: usize,
    last_terminal: bool,
}

/// Accumulates rows into columns; `finish` returns the checked dataset.
pub struct RowAssembler {
    first_line: usize,
    obs_dim: Option<usize>,
    action_kind: Option<ActionKind>,
    observations: Vec<f32>,
    continuous_actions: Vec<f32>,
    discrete_actions: Vec<u32>,
    next_observations: Vec<f32>,
    terminals: Vec<bool>,
    episode_ids: Vec<u32>,
    rewards: Option<Vec<f32>>,
    costs: Option<Vec<f32>>,
    /// Row index and line of the previous row when it had no `next_obs` (filled by this row).
    pending_next: Option<(usize, usize)>,
    open: Option<OpenEpisode>,
    closed_episodes: HashSet<u32>,
}

impl RowAssembler {
    pub fn new() -> Self {
        RowAssembler {
            first_line: 0,
            obs_dim: None,
            action_kind: None,
            observations: Vec::new(),
            continuous_actions: Vec::new(),
            discrete_actions: Vec::new(),
            next_observations: Vec::new(),
            terminals: Vec::new(),
            episode_ids: Vec::new(),
            rewards: None,
            costs: None,
            pending_next: None,
            open: None,
            closed_episodes: HashSet::new(),
        }
    }

    pub fn len(&self) -> usize {
        self.terminals.len()
    }

    /// Appends the row read at `line` (1-based, as an editor shows it).
    pub fn push(&mut self, line: usize, row: Row<'_>) -> Result<(), ParseError> {
        let first = self.len() == 0;
        if first {
            self.first_line = line;
        }
        let at = |msg: String| ParseError::invalid(format!("line {line}: {msg}"));
        let obs_dim = self.check_obs(line, row.obs)?;
        self.check_action(line, &row.action)?;
        if let Some(next) = row.next_obs {
            check_vector(line, "next_obs", next, obs_dim)?;
        }
        self.track_episode(line, row.episode)?;
        self.check_optional(line, first, "reward", row.reward, |s| &mut s.rewards)?;
        self.check_optional(line, first, "cost", row.cost, |s| &mut s.costs)?;

        let index = self.len();
        if let Some((pending, _)) = self.pending_next.take() {
            self.next_observations[pending * obs_dim..(pending + 1) * obs_dim]
                .copy_from_slice(row.obs);
        }
        self.observations.extend_from_slice(row.obs);
        match row.next_obs {
            Some(next) => self.next_observations.extend_from_slice(next),
            None => {
                // Placeholder, overwritten by the next row of this episode or when it closes.
                self.next_observations.extend(std::iter::repeat_n(0.0, obs_dim));
                self.pending_next = Some((index, line));
            }
        }
        match row.action {
            RowAction::Continuous(a) => self.continuous_actions.extend_from_slice(a),
            RowAction::Discrete(a) => {
                if a >= MAX_DISCRETE_ACTIONS {
                    return Err(at(format!(
                        "discrete action {a} is too large: actions must be numbered \
                         0..{MAX_DISCRETE_ACTIONS}"
                    )));
                }
                self.discrete_actions.push(a as u32)
            }
        }
        self.terminals.push(row.terminal);
        self.episode_ids.push(row.episode);
        if let Some(open) = &mut self.open {
            open.last_line = line;
            open.last_terminal = row.terminal;
        }
        Ok(())
    }

    fn check_obs(&mut self, line: usize, obs: &[f32]) -> Result<usize, ParseError> {
        if obs.is_empty() {
            return Err(ParseError::invalid(format!("line {line}: `obs` is empty")));
        }
        let dim = *self.obs_dim.get_or_insert(obs.len());
        check_vector(line, "obs", obs, dim)?;
        Ok(dim)
    }

    fn check_action(&mut self, line: usize, action: &RowAction<'_>) -> Result<(), ParseError> {
        let kind = match action {
            RowAction::Continuous([]) => {
                return Err(ParseError::invalid(format!("line {line}: `action` is empty")))
            }
            RowAction::Continuous(a) => ActionKind::Continuous(a.len()),
            RowAction::Discrete(_) => ActionKind::Discrete,
        };
        let expected = *self.action_kind.get_or_insert(kind);
        let first_line = self.first_line;
        match (expected, kind, action) {
            (ActionKind::Continuous(dim), ActionKind::Continuous(_), RowAction::Continuous(a)) => {
                check_vector(line, "action", a, dim)
            }
            (ActionKind::Discrete, ActionKind::Discrete, _) => Ok(()),
            (ActionKind::Discrete, _, _) => Err(ParseError::invalid(format!(
                "line {line}: continuous action (a list) but line {first_line} has a discrete \
                 action (an integer); mixed discrete and continuous actions are not allowed"
            ))),
            _ => Err(ParseError::invalid(format!(
                "line {line}: discrete action (an integer) but line {first_line} has a \
                 continuous action (a list); mixed discrete and continuous actions are not \
                 allowed (write a 1-dimensional continuous action as [x])"
            ))),
        }
    }

    /// Enforces contiguous episodes and terminals only at episode ends.
    fn track_episode(&mut self, line: usize, episode: u32) -> Result<(), ParseError> {
        if let Some(open) = &self.open {
            if open.id == episode {
                if open.last_terminal {
                    return Err(ParseError::invalid(format!(
                        "line {line}: episode {episode} continues after its terminal \
                         transition on line {}; a terminal transition must be the last of its \
                         episode",
                        open.last_line
                    )));
                }
                return Ok(());
            }
            self.close_episode()?;
        }
        if !self.closed_episodes.insert(episode) {
            return Err(ParseError::invalid(format!(
                "line {line}: episode {episode} reappears after other episodes; episodes must \
                 be contiguous (sort the rows by episode, keeping each episode's order)"
            )));
        }
        self.open = Some(OpenEpisode { id: episode, last_line: line, last_terminal: false });
        Ok(())
    }

    /// Resolves a missing `next_obs` on the last row of the open episode (see the module docs).
    fn close_episode(&mut self) -> Result<(), ParseError> {
        let Some(open) = self.open.take() else { return Ok(()) };
        let Some((index, line)) = self.pending_next.take() else { return Ok(()) };
        if !open.last_terminal {
            return Err(ParseError::invalid(format!(
                "line {line}: the last transition of episode {} has no `next_obs` and is not \
                 terminal, so its next observation is unknown; add `next_obs`, mark it \
                 `terminal` if the episode really ended there, or drop the row",
                open.id
            )));
        }
        let dim = self.obs_dim.unwrap_or(0);
        let (obs, next) = (&self.observations, &mut self.next_observations);
        next[index * dim..(index + 1) * dim].copy_from_slice(&obs[index * dim..(index + 1) * dim]);
        Ok(())
    }

    /// `reward` / `cost`: present on every row or on none; finite.
    fn check_optional(
        &mut self,
        line: usize,
        first: bool,
        name: &str,
        value: Option<f32>,
        column: impl Fn(&mut Self) -> &mut Option<Vec<f32>>,
    ) -> Result<(), ParseError> {
        let first_line = self.first_line;
        let col = column(self);
        if first {
            *col = value.map(|_| Vec::new());
        }
        match (col, value) {
            (Some(values), Some(v)) if v.is_finite() => {
                values.push(v);
                Ok(())
            }
            (Some(_), Some(v)) => Err(ParseError::invalid(format!(
                "line {line}: `{name}` is {v}, not a finite number"
            ))),
            (None, None) => Ok(()),
            (Some(_), None) => Err(ParseError::invalid(format!(
                "line {line}: `{name}` is missing but line {first_line} has one; give \
                 `{name}` on every row or on none"
            ))),
            (None, Some(_)) => Err(ParseError::invalid(format!(
                "line {line}: `{name}` is given but line {first_line} has none; give \
                 `{name}` on every row or on none"
            ))),
        }
    }

    /// Closes the last episode, and builds the dataset through [`Dataset::new`].
    pub fn finish(mut self) -> Result<Dataset, ParseError> {
        if self.len() == 0 {
            return Err(ParseError::empty("the file holds no transitions"));
        }
        self.close_episode()?;
        let (actions, action_space) = match self.action_kind {
            Some(ActionKind::Continuous(dim)) => {
                let space = ActionSpace::infer_continuous(&self.continuous_actions, dim);
                (Actions::Continuous(self.continuous_actions), space)
            }
            _ => {
                let n = self.discrete_actions.iter().max().map_or(1, |&m| m as usize + 1);
                (Actions::Discrete(self.discrete_actions), ActionSpace::Discrete { n })
            }
        };
        Ok(Dataset::new(DatasetParts {
            obs_dim: self.obs_dim.unwrap_or(0),
            action_space,
            observations: self.observations,
            actions,
            next_observations: self.next_observations,
            terminals: self.terminals,
            episode_ids: self.episode_ids,
            rewards: self.rewards,
            costs: self.costs,
        })?)
    }
}

/// Length and finiteness of one vector field, named by line and field.
fn check_vector(line: usize, name: &str, values: &[f32], dim: usize) -> Result<(), ParseError> {
    if values.len() != dim {
        return Err(ParseError::invalid(format!(
            "line {line}: `{name}` has {} values, expected {dim} like the first row \
             (ragged dimensions)",
            values.len()
        )));
    }
    if let Some(j) = values.iter().position(|v| !v.is_finite()) {
        return Err(ParseError::invalid(format!(
            "line {line}: `{name}`[{j}] is {}, not a finite number (NaN and Inf are rejected)",
            values[j]
        )));
    }
    Ok(())
}
