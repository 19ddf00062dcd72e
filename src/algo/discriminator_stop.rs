//! Early stopping of SafeDICE's discriminator (Eq. 9) on held-out data: the option that lets the
//! data, not a step count, decide how long the discriminator trains.
//!
//! A fixed number of discriminator steps is a hyperparameter in disguise: the more often each
//! labeled non-preferred sample is seen, the more the discriminator memorises D^N instead of
//! learning what sets non-preferred behaviour apart, and how many steps that takes depends on
//! |D^N|. Here a fifth of the episodes of D^N and of D^U (rows, where a set has fewer than five
//! episodes) is held out; the discriminator trains on the rest, its Eq. 9 classification loss on
//! the held-out rows is measured every [`EarlyStop::every`] steps, and the weights of the best
//! measurement are kept. Training stops once it has gone as long without improving as it took to
//! reach the best (and at least a tenth of the step budget); the rest of the phase's steps do
//! nothing, so a run's step count, progress and checkpoints do not depend on where it stopped.
//! Eq. 15 and Eq. 10 then read the kept discriminator on all of D^U.

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Share of episodes (or rows) held out.
pub const HOLDOUT_SHARE: f64 = 0.2;
/// Held-out rows scored per set at most (a fixed random subset beyond that).
pub const MAX_VALIDATION_ROWS: usize = 4096;
/// Measurements over the whole step budget.
pub const MEASUREMENTS: u64 = 200;

/// Training and held-out rows of one dataset.
#[derive(Clone, Debug, PartialEq)]
pub struct Holdout {
    pub train: Vec<u32>,
    pub validation: Vec<u32>,
}

impl Holdout {
    /// Holds out [`HOLDOUT_SHARE`] of the episodes of a dataset with rows labelled by
    /// `episode_ids` (of rows, with fewer than five episodes), at least one row or episode on
    /// each side; `seed` fixes the choice. None when the dataset has a single row.
    pub fn split(episode_ids: &[u32], seed: u64) -> Option<Holdout> {
        if episode_ids.len() < 2 {
            return None;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut episodes: Vec<u32> = episode_ids.to_vec();
        episodes.sort_unstable();
        episodes.dedup();
        let by_row = episodes.len() < 5;
        let units: Vec<u32> =
            if by_row { (0..episode_ids.len() as u32).collect() } else { episodes };
        let mut shuffled = units.clone();
        shuffled.shuffle(&mut rng);
        let held =
            ((units.len() as f64 * HOLDOUT_SHARE).round() as usize).clamp(1, units.len() - 1);
        let mut is_held = std::collections::HashSet::new();
        is_held.extend(shuffled[..held].iter().copied());
        let (mut train, mut validation) = (Vec::new(), Vec::new());
        for (row, &episode) in episode_ids.iter().enumerate() {
            let unit = if by_row { row as u32 } else { episode };
            if is_held.contains(&unit) {
                validation.push(row as u32);
            } else {
                train.push(row as u32);
            }
        }
        if validation.len() > MAX_VALIDATION_ROWS {
            validation.shuffle(&mut rng);
            validation.truncate(MAX_VALIDATION_ROWS);
            validation.sort_unstable();
        }
        Some(Holdout { train, validation })
    }
}

/// What a measurement of the held-out loss decided.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Decision {
    /// A new best: keep these weights.
    Improved,
    Continue,
    /// Stop training the discriminator (the best weights stay).
    Stop,
}

/// The stopping rule's state; its fields are what a checkpoint must carry.
#[derive(Clone, Debug, PartialEq)]
pub struct EarlyStop {
    /// Steps between measurements.
    pub every: u64,
    /// At least this many steps before stopping.
    pub min_steps: u64,
    pub best_loss: f64,
    pub best_step: u64,
    /// The step training stopped at, if it has.
    pub stopped_at: Option<u64>,
}

impl EarlyStop {
    /// The rule for a budget of `budget` discriminator steps.
    pub fn new(budget: u64) -> EarlyStop {
        EarlyStop {
            every: (budget / MEASUREMENTS).max(1),
            min_steps: (budget / 10).max(1),
            best_loss: f64::INFINITY,
            best_step: 0,
            stopped_at: None,
        }
    }

    /// Whether the held-out loss is measured after step `step` (1-based count of steps done).
    pub fn measures_at(&self, step: u64) -> bool {
        self.stopped_at.is_none() && step.is_multiple_of(self.every)
    }

    /// Takes the held-out loss measured after `step` steps.
    pub fn observe(&mut self, step: u64, loss: f64) -> Decision {
        if loss < self.best_loss {
            self.best_loss = loss;
            self.best_step = step;
            return Decision::Improved;
        }
        let patience = self.best_step.max(self.min_steps);
        if step - self.best_step >= patience {
            self.stopped_at = Some(step);
            Decision::Stop
        } else {
            Decision::Continue
        }
    }

    /// The state as checkpoint scalars. Before the first measurement the best loss is infinite, which a checkpoint's JSON header
    /// cannot hold (it would read back as `null`): it is left out, and [`Self::restore`] keeps
    /// the fresh state's infinity.
    pub fn to_scalars(&self) -> Vec<(&'static str, f64)> {
        [
            ("discriminator_best_loss", self.best_loss),
            ("discriminator_best_step", self.best_step as f64),
            ("discriminator_stopped_at", self.stopped_at.map_or(-1.0, |s| s as f64)),
        ]
        .into_iter()
        .filter(|(_, value)| value.is_finite())
        .collect()
    }

    /// Restores the state from checkpoint scalars (absent keys leave the fresh state).
    pub fn restore(&mut self, scalars: &std::collections::BTreeMap<String, f64>) {
        if let Some(&loss) = scalars.get("discriminator_best_loss") {
            self.best_loss = loss;
        }
        if let Some(&step) = scalars.get("discriminator_best_step") {
            self.best_step = step as u64;
        }
        if let Some(&stopped) = scalars.get("discriminator_stopped_at") {
            self.stopped_at = (stopped >= 0.0).then_some(stopped as u64);
        }
    }
}

/// Eq. 9's classification loss, `−mean log σ(c_N) − mean log(1 − σ(c_U))`, from logits, in the
/// numerically stable softplus form: `log(1 + e^{−c})` and `log(1 + e^{c})`.
pub fn classification_loss(logits_n: &[f32], logits_u: &[f32]) -> f64 {
    let softplus = |x: f64| x.max(0.0) + (-x.abs()).exp().ln_1p();
    let mean = |v: &[f32], f: &dyn Fn(f64) -> f64| {
        v.iter().map(|&c| f(c as f64)).sum::<f64>() / v.len().max(1) as f64
    };
    mean(logits_n, &|c| softplus(-c)) + mean(logits_u, &|c| softplus(c))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn holdout_keeps_episodes_whole_and_is_seeded() {
        let ids: Vec<u32> = (0..10).flat_map(|e| std::iter::repeat_n(e, 7)).collect();
        let h = Holdout::split(&ids, 3).unwrap();
        assert_eq!(h, Holdout::split(&ids, 3).unwrap());
        assert_eq!(h.validation.len(), 2 * 7, "two of ten episodes");
        assert_eq!(h.train.len() + h.validation.len(), ids.len());
        let held: std::collections::HashSet<u32> =
            h.validation.iter().map(|&r| ids[r as usize]).collect();
        assert!(h.train.iter().all(|&r| !held.contains(&ids[r as usize])), "no episode split");
    }

    #[test]
    fn few_episodes_hold_out_rows_and_one_row_holds_out_nothing() {
        let ids = vec![0u32; 10];
        let h = Holdout::split(&ids, 1).unwrap();
        assert_eq!((h.train.len(), h.validation.len()), (8, 2));
        assert_eq!(Holdout::split(&[0], 1), None);
    }

    #[test]
    fn stops_after_as_long_without_improvement_as_it_took_to_improve() {
        let mut s = EarlyStop::new(2000);
        assert_eq!((s.every, s.min_steps), (10, 200));
        assert_eq!(s.observe(10, 1.0), Decision::Improved);
        assert_eq!(s.observe(300, 0.5), Decision::Improved);
        assert_eq!(s.observe(590, 0.6), Decision::Continue);
        assert_eq!(s.observe(600, 0.6), Decision::Stop, "300 steps without improving");
        assert_eq!(s.stopped_at, Some(600));
        assert!(!s.measures_at(610));
        let mut back = EarlyStop::new(2000);
        back.restore(&s.to_scalars().iter().map(|(k, v)| (k.to_string(), *v)).collect());
        assert_eq!(back, s);
        // Before any measurement (a checkpoint at the start of cross-fitting's second half).
        let fresh = EarlyStop::new(2000);
        assert!(fresh.to_scalars().iter().all(|(_, v)| v.is_finite()), "JSON has no infinity");
        let mut back = EarlyStop::new(2000);
        back.restore(&fresh.to_scalars().iter().map(|(k, v)| (k.to_string(), *v)).collect());
        assert_eq!(back, fresh);
    }

    /// D^U and D^N drawn from the same distribution (nothing to learn): every gain on the
    /// training rows is memorisation, so the held-out loss turns up early.
    fn indistinguishable_task(seed: u64) -> crate::algo::TrainingData {
        use crate::data::{ActionSpace, Actions, Dataset, DatasetParts};
        use rand::Rng;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut set = |episodes: usize| {
            let n = episodes * 5;
            let mut draw =
                |k: usize| -> Vec<f32> { (0..k).map(|_| rng.random_range(-1.0..1.0)).collect() };
            let observations = draw(n * 4);
            let next_observations = draw(n * 4);
            let actions = draw(n);
            Dataset::new(DatasetParts {
                obs_dim: 4,
                action_space: ActionSpace::Continuous { dim: 1, low: vec![-1.0], high: vec![1.0] },
                observations,
                actions: Actions::Continuous(actions),
                next_observations,
                terminals: vec![false; n],
                episode_ids: (0..n).map(|i| (i / 5) as u32).collect(),
                rewards: None,
                costs: None,
            })
            .unwrap()
        };
        let unlabeled = std::sync::Arc::new(set(20));
        let non_preferred = Some(std::sync::Arc::new(set(10)));
        crate::algo::TrainingData { unlabeled, non_preferred }
    }

    fn early_stopping_config() -> crate::algo::ResolvedConfig {
        crate::algo::resolve_config(
            crate::algo::Algorithm::Safedice,
            &serde_json::json!({
                "seed": 1, "batch_size": 16, "hidden_sizes": [32, 32], "iterations": 4,
                "discriminator_iterations": 2000, "lr_discriminator": 0.003,
                "discriminator_early_stopping": true,
            }),
        )
        .unwrap()
    }

    fn run_to_end(t: &mut crate::algo::safedice::SafediceTrainer) {
        use crate::algo::Trainer;
        while !t.is_finished() {
            t.step(false).unwrap();
        }
    }

    #[test]
    fn trainer_stops_on_memorisation_and_keeps_the_phase_length() {
        use crate::algo::safedice::SafediceTrainer;
        use crate::algo::Trainer;
        let data = indistinguishable_task(5);
        let mut t = SafediceTrainer::new(&early_stopping_config(), &data).unwrap();
        let mut last = std::collections::BTreeMap::new();
        let mut final_step = std::collections::BTreeMap::new();
        while t.progress().phase == "discriminator" {
            final_step = t.step(true).unwrap().into_iter().collect();
            last.extend(final_step.clone());
        }
        assert_eq!(t.progress().step, 2000, "the phase keeps its length");
        let (best, stopped) = (last["discriminator_best_step"], last["discriminator_stopped_at"]);
        assert!(best > 0.0 && best < 1000.0, "the best held-out loss came early ({best})");
        assert!(stopped > best && stopped < 2000.0, "stopped at {stopped}, best at {best}");
        // The phase's last step, trained or not, names the stop: the value a job's page shows.
        assert_eq!(final_step.get("discriminator_stopped_at"), Some(&stopped));
        assert!(t.alpha_hat().is_some_and(f64::is_finite));
    }

    #[test]
    fn a_resume_mid_phase_is_bitwise_the_run_that_was_not_stopped() {
        use crate::algo::safedice::SafediceTrainer;
        use crate::algo::Trainer;
        let data = indistinguishable_task(5);
        let config = early_stopping_config();
        let mut straight = SafediceTrainer::new(&config, &data).unwrap();
        run_to_end(&mut straight);
        for cut in [150, 1200] {
            let mut first = SafediceTrainer::new(&config, &data).unwrap();
            while first.progress().step < cut {
                first.step(false).unwrap();
            }
            let bytes = first.checkpoint().unwrap();
            let mut resumed = SafediceTrainer::resume(&config, &data, &bytes).unwrap();
            run_to_end(&mut resumed);
            assert_eq!(resumed.alpha_hat(), straight.alpha_hat(), "cut at {cut}");
            assert_eq!(
                resumed.export_policy().unwrap().weights,
                straight.export_policy().unwrap().weights,
                "cut at {cut}"
            );
        }
    }

    #[test]
    fn classification_loss_matches_the_closed_form() {
        // σ(0) = 1/2 on both sides: 2 ln 2.
        assert!((classification_loss(&[0.0], &[0.0]) - 2.0 * 2f64.ln()).abs() < 1e-12);
        // Logit 2 on D^N: ln(1 + e^-2); logit -1 on D^U: ln(1 + e^-1).
        let want = (1.0 + (-2f64).exp()).ln() + (1.0 + (-1f64).exp()).ln();
        assert!((classification_loss(&[2.0], &[-1.0]) - want).abs() < 1e-9);
    }
}
