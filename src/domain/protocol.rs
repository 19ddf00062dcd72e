//! An evaluation protocol: what two evaluations must share for their numbers to be compared or
//! averaged. The same policy scored deterministically and with sampled actions, on 50 episodes and
//! on 500, or through the served `act` and through its ONNX export, gives different numbers; a
//! mean over seeds is only a result when every seed was evaluated the same way.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::EvalSpec;

/// How the policy was run in an evaluation's episodes.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize, ToSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum EvalRuntime {
    /// A worker of this service ran it on a built-in environment.
    Builtin,
    /// The user's simulator asked the served policy for each action (`act`, `/v2/.../infer`).
    Act,
    /// The user's simulator ran the policy's ONNX export (e.g. in onnxruntime).
    Onnx,
    /// Some other way, as the recorder said.
    Other,
    /// An evaluation recorded from the user's simulator without saying how (older records).
    Unspecified,
}

impl EvalRuntime {
    pub const ALL: [EvalRuntime; 5] = [
        EvalRuntime::Builtin,
        EvalRuntime::Act,
        EvalRuntime::Onnx,
        EvalRuntime::Other,
        EvalRuntime::Unspecified,
    ];

    /// As stored and shown.
    pub fn as_str(self) -> &'static str {
        match self {
            EvalRuntime::Builtin => "builtin",
            EvalRuntime::Act => "act",
            EvalRuntime::Onnx => "onnx",
            EvalRuntime::Other => "other",
            EvalRuntime::Unspecified => "unspecified",
        }
    }

    /// In words, for labels.
    fn describe(self) -> &'static str {
        match self {
            EvalRuntime::Builtin => "built-in",
            EvalRuntime::Act => "through act",
            EvalRuntime::Onnx => "ONNX export",
            EvalRuntime::Other => "other runtime",
            EvalRuntime::Unspecified => "runtime not recorded",
        }
    }
}

impl std::str::FromStr for EvalRuntime {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        EvalRuntime::ALL
            .into_iter()
            .find(|runtime| runtime.as_str() == s)
            .ok_or_else(|| format!("unknown evaluation runtime {s:?}"))
    }
}

/// What a client recording an evaluation from its own simulator may say about how the policy
/// acted (`builtin` is the service's own).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum RecordedRuntime {
    /// Each action came from the served policy (`act`, `/v2/.../infer`).
    Act,
    /// The policy's ONNX export ran in the simulator's process.
    Onnx,
    /// Some other way.
    Other,
}

impl From<RecordedRuntime> for EvalRuntime {
    fn from(runtime: RecordedRuntime) -> Self {
        match runtime {
            RecordedRuntime::Act => EvalRuntime::Act,
            RecordedRuntime::Onnx => EvalRuntime::Onnx,
            RecordedRuntime::Other => EvalRuntime::Other,
        }
    }
}

/// An evaluation protocol: environment, episodes, seed, deterministic or sampled actions, and the
/// runtime. Results are grouped by it and never averaged across two of them.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, ToSchema)]
pub struct EvalProtocol {
    /// Names the protocol in requests (`?protocol=`): every field, the environment last.
    #[schema(example = "runtime=builtin;actions=sampled;episodes=500;seed=0;env=six-rooms")]
    pub key: String,
    /// In words, e.g. `six-rooms · 500 episodes · seed 0 · sampled · built-in`.
    pub label: String,
    pub env: String,
    pub episodes: usize,
    pub seed: u64,
    pub deterministic: bool,
    pub runtime: EvalRuntime,
}

impl EvalProtocol {
    pub fn new(spec: &EvalSpec, runtime: EvalRuntime) -> EvalProtocol {
        let actions = if spec.deterministic { "deterministic" } else { "sampled" };
        let (env, episodes, seed) = (&spec.env, spec.episodes, spec.seed);
        EvalProtocol {
            // The environment last: an external simulator's name may hold any character but
            // control ones, so every field before it stays unambiguous.
            key: format!(
                "runtime={};actions={actions};episodes={episodes};seed={seed};env={env}",
                runtime.as_str()
            ),
            label: format!(
                "{env} · {episodes} episodes · seed {seed} · {actions} · {}",
                runtime.describe()
            ),
            env: env.clone(),
            episodes,
            seed,
            deterministic: spec.deterministic,
            runtime,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(env: &str, episodes: usize, deterministic: bool) -> EvalSpec {
        EvalSpec { env: env.into(), episodes, seed: 3, deterministic }
    }

    #[test]
    fn every_field_tells_protocols_apart() {
        let base = EvalProtocol::new(&spec("six-rooms", 10, false), EvalRuntime::Builtin);
        assert_eq!(base.key, "runtime=builtin;actions=sampled;episodes=10;seed=3;env=six-rooms");
        assert_eq!(base.label, "six-rooms · 10 episodes · seed 3 · sampled · built-in");
        let others = [
            EvalProtocol::new(&spec("six-rooms", 10, true), EvalRuntime::Builtin),
            EvalProtocol::new(&spec("six-rooms", 11, false), EvalRuntime::Builtin),
            EvalProtocol::new(&spec("point-goal", 10, false), EvalRuntime::Builtin),
            EvalProtocol::new(&spec("six-rooms", 10, false), EvalRuntime::Act),
            EvalProtocol::new(&EvalSpec { seed: 4, ..spec("six-rooms", 10, false) }, base.runtime),
        ];
        for other in others {
            assert_ne!(other.key, base.key);
        }
    }

    #[test]
    fn runtimes_round_trip_through_their_stored_names() {
        for runtime in EvalRuntime::ALL {
            assert_eq!(runtime.as_str().parse::<EvalRuntime>(), Ok(runtime));
            assert_eq!(serde_json::to_value(runtime).unwrap().as_str(), Some(runtime.as_str()));
        }
    }
}
