//! A shadow's comparison with the version that answered (docs/shadow.md): sums per minute that
//! every serving process adds to, so a fleet's nodes make one series.

use chrono::{DateTime, Utc};

/// Which comparison a count belongs to.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ComparisonKey {
    pub model: String,
    /// The model's creation stamp as stored: a model deleted and created again under its name
    /// has another, so counts still in flight for the deleted one are not added to the new one.
    pub model_created: String,
    pub alias: String,
    /// The version that answered the request.
    pub production_version: u32,
    /// The shadow's version, run beside it.
    pub shadow_version: u32,
}

/// Sums over the requests of one minute; the means are sum / count.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ComparisonCounts {
    /// Requests drawn for the shadow: compared, skipped or failed.
    pub requests: u64,
    /// Drawn but not run: the shadow's queue was full, or its policy not loaded.
    pub skipped: u64,
    /// Run, but the shadow gave no comparable answer (an error, or actions of another shape).
    pub failed: u64,
    /// Observations compared.
    pub observations: u64,
    /// The shadow's compute time, nanoseconds.
    pub shadow_ns: u64,
    /// Discrete actions: observations where the two versions chose differently.
    pub disagreements: u64,
    /// Continuous actions: the L2 distance between the two actions, per observation.
    pub l2_sum: f64,
    pub l2_max: f64,
    /// Continuous actions: the largest absolute difference of one coordinate, per observation.
    pub max_abs_sum: f64,
    pub max_abs_max: f64,
    /// The shadow's `non_preferred_log_ratio` of its own actions (SafeDICE shadows).
    pub shadow_log_ratio_sum: f64,
    pub shadow_log_ratio_n: u64,
    /// The answering version's `non_preferred_log_ratio` of its actions (SafeDICE versions).
    pub production_log_ratio_sum: f64,
    pub production_log_ratio_n: u64,
    /// The shadow's `out_of_support` of the observations (SafeDICE shadows).
    pub out_of_support_sum: f64,
    pub out_of_support_n: u64,
}

impl ComparisonCounts {
    /// Adds `other`'s counts (sums add, maxima take the larger).
    pub fn merge(&mut self, other: &ComparisonCounts) {
        self.requests += other.requests;
        self.skipped += other.skipped;
        self.failed += other.failed;
        self.observations += other.observations;
        self.shadow_ns += other.shadow_ns;
        self.disagreements += other.disagreements;
        self.l2_sum += other.l2_sum;
        self.l2_max = self.l2_max.max(other.l2_max);
        self.max_abs_sum += other.max_abs_sum;
        self.max_abs_max = self.max_abs_max.max(other.max_abs_max);
        self.shadow_log_ratio_sum += other.shadow_log_ratio_sum;
        self.shadow_log_ratio_n += other.shadow_log_ratio_n;
        self.production_log_ratio_sum += other.production_log_ratio_sum;
        self.production_log_ratio_n += other.production_log_ratio_n;
        self.out_of_support_sum += other.out_of_support_sum;
        self.out_of_support_n += other.out_of_support_n;
    }
}

/// One minute of a comparison.
#[derive(Clone, Debug, PartialEq)]
pub struct ComparisonPoint {
    /// The minute's start.
    pub minute: DateTime<Utc>,
    pub counts: ComparisonCounts,
}

/// A comparison's minutes, oldest first.
#[derive(Clone, Debug, PartialEq)]
pub struct ComparisonSeries {
    pub key: ComparisonKey,
    pub points: Vec<ComparisonPoint>,
}
