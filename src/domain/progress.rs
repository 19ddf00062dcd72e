//! A job's progress as the API shows it.

use serde::Serialize;
use utoipa::ToSchema;

/// Where a job is: steps done of all phases, the current phase, speed and estimated time left.
#[derive(Clone, Debug, PartialEq, Serialize, ToSchema)]
pub struct JobProgress {
    /// Steps done, every phase included.
    pub step: u64,
    /// Steps of the whole run (e.g. discriminator steps + policy iterations).
    pub total: u64,
    /// `step / total`, 0 to 1.
    pub fraction: f64,
    /// Current phase: `discriminator`, `reward_model` or `policy`; null before the job starts.
    pub phase: Option<String>,
    /// Recent training speed while the job runs; null otherwise.
    pub iterations_per_second: Option<f64>,
    /// Time left at the recent speed while the job runs; null otherwise.
    pub eta_seconds: Option<f64>,
}

impl JobProgress {
    pub fn new(step: u64, total: u64, phase: Option<String>, speed: Option<f64>) -> Self {
        let fraction = if total == 0 { 0.0 } else { (step as f64 / total as f64).min(1.0) };
        let speed = speed.filter(|s| s.is_finite() && *s > 0.0);
        let eta_seconds = speed.map(|s| total.saturating_sub(step) as f64 / s);
        JobProgress { step, total, fraction, phase, iterations_per_second: speed, eta_seconds }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fraction_and_eta_follow_from_step_total_and_speed() {
        let p = JobProgress::new(250, 1000, Some("policy".into()), Some(50.0));
        assert_eq!((p.fraction, p.eta_seconds), (0.25, Some(15.0)));
        let idle = JobProgress::new(0, 1000, None, None);
        assert_eq!((idle.fraction, idle.eta_seconds), (0.0, None));
        assert_eq!(JobProgress::new(0, 10, None, Some(0.0)).iterations_per_second, None);
    }
}
