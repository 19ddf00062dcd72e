//! Scripted demonstrators: for each environment a *preferred* policy (high return, low cost) and
//! a *non-preferred* one (about the same return, high cost), both stochastic so the data covers
//! more than one path, as the paper's data (Tables 1 and 3). They read only the observation, so
//! each is a Markov policy π(a|s) like the ones a learner can represent.

use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::{cartpole_slider, point_goal, six_rooms, UnknownEnv};
use crate::data::Actions;

/// Which of the two demonstrators.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Profile {
    Preferred,
    NonPreferred,
}

impl Profile {
    pub const ALL: [Profile; 2] = [Profile::Preferred, Profile::NonPreferred];

    pub fn as_str(self) -> &'static str {
        match self {
            Profile::Preferred => "preferred",
            Profile::NonPreferred => "non_preferred",
        }
    }
}

/// A scripted policy acting on a batch of observations (`rows × obs_dim`, row-major).
pub trait Demonstrator: Send + Sync {
    fn obs_dim(&self) -> usize;
    /// One action per row, drawn with `rng`.
    fn act_batch(&self, observations: &[f32], rng: &mut ChaCha8Rng) -> Actions;
}

/// The `profile` demonstrator of environment `env`.
pub fn demonstrator(env: &str, profile: Profile) -> Result<Box<dyn Demonstrator>, UnknownEnv> {
    let preferred = profile == Profile::Preferred;
    Ok(match env {
        six_rooms::NAME => Box::new(six_rooms::RouteFollower::new(preferred)),
        point_goal::NAME => Box::new(if preferred {
            point_goal::Steering::preferred()
        } else {
            point_goal::Steering::non_preferred()
        }),
        cartpole_slider::NAME => Box::new(if preferred {
            cartpole_slider::Balancer::preferred()
        } else {
            cartpole_slider::Balancer::non_preferred()
        }),
        other => return Err(UnknownEnv { name: other.to_string() }),
    })
}

impl Demonstrator for six_rooms::RouteFollower {
    fn obs_dim(&self) -> usize {
        six_rooms::RouteFollower::obs_dim(self)
    }

    fn act_batch(&self, observations: &[f32], rng: &mut ChaCha8Rng) -> Actions {
        let rows = observations.chunks_exact(self.obs_dim());
        Actions::Discrete(rows.map(|obs| self.act(obs, rng)).collect())
    }
}

impl Demonstrator for point_goal::Steering {
    fn obs_dim(&self) -> usize {
        point_goal::OBS_DIM
    }

    fn act_batch(&self, observations: &[f32], rng: &mut ChaCha8Rng) -> Actions {
        let rows = observations.chunks_exact(point_goal::OBS_DIM);
        Actions::Continuous(rows.flat_map(|obs| self.act(obs, rng)).collect())
    }
}

impl Demonstrator for cartpole_slider::Balancer {
    fn obs_dim(&self) -> usize {
        5
    }

    fn act_batch(&self, observations: &[f32], rng: &mut ChaCha8Rng) -> Actions {
        let rows = observations.chunks_exact(5);
        Actions::Continuous(rows.map(|obs| self.act(obs, rng)).collect())
    }
}
