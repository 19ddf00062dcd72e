//! One spec per algorithm: what the rest of the service knows about it, in one place. The API
//! name and the paper's label, its accent colour, whether it needs D^N, the knobs the
//! dashboard's job form offers, and how to start or resume a run. `/v1/algorithms` (and through
//! it the OpenAPI example, the dashboard's form and colours) and [`super::build_trainer`] read
//! this table; nothing outside `algo/` matches on an algorithm to learn these.
//!
//! To add an algorithm: its module beside the others (a [`Trainer`], its `step_flops`, its
//! `memory`, and its `config.rs` with presets and checks), its variant of [`Algorithm`] and its
//! line in `hyperparams.rs`'s `algorithm_configs!`, its entry in [`SPECS`] below and its keys in
//! the CreateJob doc (docs/architecture.md, "Recipes").

use serde::Serialize;

use super::flops::StepShape;
use super::memory::{Footprint, MemoryShape};
use super::{
    bc, dexperts, dwbc, ppl, safedice, Algorithm, ResolvedConfig, TrainError, Trainer, TrainingData,
};

/// Starts a run of one algorithm.
pub type Build = fn(&ResolvedConfig, &TrainingData) -> Result<Box<dyn Trainer>, TrainError>;
/// Resumes a run of one algorithm from the bytes of its [`Trainer::checkpoint`].
pub type Resume = fn(&ResolvedConfig, &TrainingData, &[u8]) -> Result<Box<dyn Trainer>, TrainError>;

/// One policy-learning step of an algorithm, as the speed benchmark measures it.
#[derive(Clone, Copy)]
pub struct StepCost {
    /// What the step trains, in a few words.
    pub label: &'static str,
    /// Its FLOPs (matrix products) for networks of a shape.
    pub flops: fn(&StepShape) -> u64,
}

/// Everything about one algorithm that is not its training code or its configuration.
pub struct AlgorithmSpec {
    pub algorithm: Algorithm,
    /// The API's name (`algorithm` of a job).
    pub name: &'static str,
    /// The name as the paper writes it.
    pub label: &'static str,
    /// Its accent colour in charts and the dashboard (CSS hex).
    pub color: &'static str,
    /// Whether a run needs the labeled non-preferred dataset D^N.
    pub needs_non_preferred: bool,
    /// The job form's knobs of its own, after [`COMMON_KNOBS`].
    pub own_knobs: &'static [Knob],
    /// Its policy-learning step (SafeDICE's main-loop iteration).
    pub step: StepCost,
    /// Its share of a run's peak memory (its networks, step buffers and data of its own), which
    /// [`super::memory::estimate_job_memory`] adds to the datasets'.
    pub memory: fn(&MemoryShape) -> Footprint,
    pub build: Build,
    pub resume: Resume,
}

/// A configuration key the dashboard's job form offers as a field.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, utoipa::ToSchema)]
pub struct Knob {
    /// The configuration key.
    #[schema(example = "iterations")]
    pub key: &'static str,
    #[schema(example = "Iterations")]
    pub label: &'static str,
    /// How the field's text is read.
    #[serde(rename = "type")]
    pub kind: KnobKind,
    /// For the length of a pretraining phase: the phase's name. Its value follows the
    /// iterations unless set, so a form shows the rule rather than the preset's number.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schema(example = json!(null))]
    pub pretraining: Option<&'static str>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum KnobKind {
    Int,
    Float,
    /// Comma-separated integers (`hidden_sizes`).
    List,
}

const fn knob(key: &'static str, label: &'static str, kind: KnobKind) -> Knob {
    Knob { key, label, kind, pretraining: None }
}

/// The knobs every algorithm has.
pub const COMMON_KNOBS: [Knob; 5] = [
    knob("iterations", "Iterations", KnobKind::Int),
    knob("seed", "Seed", KnobKind::Int),
    knob("batch_size", "Batch size", KnobKind::Int),
    knob("hidden_sizes", "Hidden sizes", KnobKind::List),
    knob("lr_actor", "Actor learning rate", KnobKind::Float),
];

/// The table, in [`Algorithm::ALL`]'s order (a test holds them together).
pub const SPECS: [AlgorithmSpec; 5] = [
    AlgorithmSpec {
        algorithm: Algorithm::Safedice,
        name: "safedice",
        label: "SafeDICE",
        color: "#2563eb",
        needs_non_preferred: true,
        own_knobs: &[
            Knob {
                pretraining: Some("discriminator pretraining"),
                ..knob("discriminator_iterations", "Discriminator iterations", KnobKind::Int)
            },
            knob("gamma", "Discount γ", KnobKind::Float),
        ],
        step: StepCost {
            label: "main loop (nu on s,s',s0 + nu GP + policy)",
            flops: safedice::step_flops,
        },
        memory: safedice::memory,
        build: |c, d| Ok(Box::new(safedice::SafediceTrainer::new(c, d)?)),
        resume: |c, d, b| Ok(Box::new(safedice::SafediceTrainer::resume(c, d, b)?)),
    },
    AlgorithmSpec {
        algorithm: Algorithm::Bc,
        name: "bc",
        label: "BC",
        color: "#6b7280",
        needs_non_preferred: false,
        own_knobs: &[],
        step: StepCost { label: "BC step", flops: bc::step_flops },
        memory: bc::memory,
        build: |c, d| Ok(Box::new(bc::BcTrainer::new(c, d)?)),
        resume: |c, d, b| Ok(Box::new(bc::BcTrainer::resume(c, d, b)?)),
    },
    AlgorithmSpec {
        algorithm: Algorithm::Dwbc,
        name: "dwbc",
        label: "DWBC",
        color: "#d97706",
        needs_non_preferred: true,
        own_knobs: &[knob("eta", "η (DWBC)", KnobKind::Float)],
        step: StepCost {
            label: "DWBC step (discriminator with GP + policy)",
            flops: dwbc::step_flops,
        },
        memory: dwbc::memory,
        build: |c, d| Ok(Box::new(dwbc::DwbcTrainer::new(c, d)?)),
        resume: |c, d, b| Ok(Box::new(dwbc::DwbcTrainer::resume(c, d, b)?)),
    },
    AlgorithmSpec {
        algorithm: Algorithm::Ppl,
        name: "ppl",
        label: "PPL",
        color: "#059669",
        needs_non_preferred: true,
        own_knobs: &[Knob {
            pretraining: Some("reward-model pretraining"),
            ..knob("reward_model_iterations", "Reward-model iterations", KnobKind::Int)
        }],
        step: StepCost { label: "PPL policy step (reward model frozen)", flops: ppl::step_flops },
        memory: ppl::memory,
        build: |c, d| Ok(Box::new(ppl::PplTrainer::new(c, d)?)),
        resume: |c, d, b| Ok(Box::new(ppl::PplTrainer::resume(c, d, b)?)),
    },
    AlgorithmSpec {
        algorithm: Algorithm::Dexperts,
        name: "dexperts",
        label: "DExperts",
        color: "#7c3aed",
        needs_non_preferred: true,
        own_knobs: &[knob("alpha", "α (DExperts)", KnobKind::Float)],
        step: StepCost {
            label: "DExperts step (both experts / Eq. 45)",
            flops: dexperts::step_flops,
        },
        memory: dexperts::memory,
        build: |c, d| Ok(Box::new(dexperts::DexpertsTrainer::new(c, d)?)),
        resume: |c, d, b| Ok(Box::new(dexperts::DexpertsTrainer::resume(c, d, b)?)),
    },
];

impl AlgorithmSpec {
    /// The job form's knobs: the common ones, then its own.
    pub fn knobs(&self) -> Vec<Knob> {
        COMMON_KNOBS.iter().chain(self.own_knobs).copied().collect()
    }

    /// The name of its phase before policy learning, if it has one.
    pub fn pretraining_phase(&self) -> Option<&'static str> {
        self.own_knobs.iter().find_map(|knob| knob.pretraining)
    }
}

/// The steps a run of a resolved configuration takes, as progress and metrics count them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, utoipa::ToSchema)]
pub struct StepPlan {
    /// Steps of the phase before policy learning (0 for the algorithms without one).
    #[schema(example = 10_000)]
    pub pretraining_steps: u64,
    /// That phase's name; null for the algorithms without one.
    #[schema(example = "discriminator pretraining")]
    pub pretraining_phase: Option<&'static str>,
    /// Policy iterations, after the pretraining phase.
    #[schema(example = 100_000)]
    pub iterations: u64,
    /// Every step of the run: a job's `progress.total`.
    #[schema(example = 110_000)]
    pub total_steps: u64,
}

impl StepPlan {
    pub fn of(config: &ResolvedConfig) -> StepPlan {
        let pretraining_steps = config.pretraining_steps();
        StepPlan {
            pretraining_steps,
            pretraining_phase: config.algorithm().spec().pretraining_phase(),
            iterations: config.common.iterations,
            total_steps: config.total_steps(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::resolve_config;

    #[test]
    fn the_table_follows_the_enum_and_its_serde_names() {
        for (spec, algorithm) in SPECS.iter().zip(Algorithm::ALL) {
            assert_eq!(spec.algorithm, algorithm);
            assert_eq!(serde_json::to_value(algorithm).unwrap(), spec.name);
        }
    }

    /// Every knob a form offers is a key of the algorithm's resolved configuration, and every
    /// pretraining knob is the one phase-length key the configuration has.
    #[test]
    fn every_knob_is_a_key_of_the_configuration() {
        for spec in &SPECS {
            let resolved = resolve_config(spec.algorithm, &serde_json::json!({})).unwrap();
            let config = serde_json::to_value(&resolved).unwrap();
            for knob in spec.knobs() {
                assert!(config.get(knob.key).is_some(), "{}: {}", spec.name, knob.key);
            }
            let pretraining = spec.own_knobs.iter().filter(|k| k.pretraining.is_some()).count();
            assert_eq!(pretraining, usize::from(resolved.pretraining_steps() > 0), "{}", spec.name);
        }
    }

    /// Every algorithm counts its step's FLOPs for the speed benchmark: more rows, more work, and
    /// a label of its own.
    #[test]
    fn every_algorithm_counts_its_step() {
        let shape = |batch| StepShape {
            obs_dim: 17,
            act_input: 6,
            policy_output: 12,
            hidden: vec![256, 256],
            batch,
        };
        let mut labels: Vec<&str> = SPECS.iter().map(|s| s.step.label).collect();
        for spec in &SPECS {
            let (small, large) = ((spec.step.flops)(&shape(256)), (spec.step.flops)(&shape(512)));
            assert!(small > 0 && large == 2 * small, "{}: {small} then {large}", spec.name);
        }
        labels.sort_unstable();
        labels.dedup();
        assert_eq!(labels.len(), SPECS.len());
    }

    /// Every algorithm states its memory: its networks include the policy, and its step buffers
    /// grow with the batch.
    #[test]
    fn every_algorithm_estimates_its_memory() {
        use crate::algo::memory::{DataShape, MemoryShape, Network};
        use crate::data::ActionSpace;
        let data = DataShape {
            transitions: 10_000,
            obs_dim: 17,
            action_space: ActionSpace::Continuous {
                dim: 6,
                low: vec![-1.0; 6],
                high: vec![1.0; 6],
            },
            longest_episode: 1_000,
        };
        for spec in &SPECS {
            let footprint = |batch: u64| {
                let config = serde_json::json!({"batch_size": batch});
                let config = resolve_config(spec.algorithm, &config).unwrap();
                let shape = MemoryShape { config: &config, unlabeled: &data, non_preferred: None };
                (spec.memory)(&shape)
            };
            let (small, large) = (footprint(256), footprint(65_536));
            let config = resolve_config(spec.algorithm, &serde_json::json!({})).unwrap();
            let shape = MemoryShape { config: &config, unlabeled: &data, non_preferred: None };
            assert!(small.networks.contains(&Network::policy(&shape)), "{}", spec.name);
            assert!(
                0 < small.step && small.step < large.step,
                "{}: {small:?} {large:?}",
                spec.name
            );
        }
    }

    #[test]
    fn a_step_plan_adds_the_pretraining_phase_to_the_iterations() {
        let safedice = resolve_config(Algorithm::Safedice, &serde_json::json!({"iterations": 300}));
        let plan = StepPlan::of(&safedice.unwrap());
        assert_eq!(plan.pretraining_phase, Some("discriminator pretraining"));
        assert_eq!(plan.pretraining_steps + plan.iterations, plan.total_steps);
        assert_eq!(plan.iterations, 300);
        let bc = StepPlan::of(&resolve_config(Algorithm::Bc, &serde_json::json!({})).unwrap());
        assert_eq!((bc.pretraining_steps, bc.pretraining_phase), (0, None));
        assert_eq!(bc.total_steps, bc.iterations);
    }
}
