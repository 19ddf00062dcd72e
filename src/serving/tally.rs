//! The safety scores a named model's versions served on this process, counted in fixed bins
//! (docs/safety-scores.md): what the model page charts and `/v2/models/{name}/stats` reports
//! beside Triton's request counts.

use std::sync::atomic::{AtomicU64, Ordering};

/// Upper bin edges of `non_preferred_log_ratio` (a value equal to an edge counts in the bin
/// above it): 0 is where an action looks as much like the unsafe demonstrations as like the
/// data; ±1, ±2, ±4 are e, e², e⁴ times more (or less) alike.
pub const LOG_RATIO_EDGES: [f32; 7] = [-4.0, -2.0, -1.0, 0.0, 1.0, 2.0, 4.0];
/// Upper bin edges of `out_of_support`: 1 is the data's own 99th percentile.
pub const SUPPORT_EDGES: [f32; 5] = [0.25, 0.5, 1.0, 2.0, 4.0];

/// Counts of the served scores, one more bin than edges each (a NaN would count in the last).
#[derive(Debug, Default)]
pub struct SafetyTally {
    log_ratio: [AtomicU64; LOG_RATIO_EDGES.len() + 1],
    out_of_support: [AtomicU64; SUPPORT_EDGES.len() + 1],
}

/// One score's counts as read: `counts[i]` below `edges[i]` and at or above `edges[i - 1]`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, utoipa::ToSchema)]
pub struct ScoreCounts {
    pub edges: Vec<f32>,
    pub counts: Vec<u64>,
}

impl ScoreCounts {
    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }
}

impl SafetyTally {
    pub fn record_log_ratios(&self, values: &[f32]) {
        count(&self.log_ratio, &LOG_RATIO_EDGES, values);
    }

    pub fn record_support(&self, values: &[f32]) {
        count(&self.out_of_support, &SUPPORT_EDGES, values);
    }

    /// `(non_preferred_log_ratio, out_of_support)` counts.
    pub fn read(&self) -> (ScoreCounts, ScoreCounts) {
        (read(&self.log_ratio, &LOG_RATIO_EDGES), read(&self.out_of_support, &SUPPORT_EDGES))
    }
}

fn count(bins: &[AtomicU64], edges: &[f32], values: &[f32]) {
    for value in values {
        let bin = edges.partition_point(|edge| edge <= value);
        let bin = if value.is_nan() { edges.len() } else { bin };
        bins[bin].fetch_add(1, Ordering::Relaxed);
    }
}

fn read(bins: &[AtomicU64], edges: &[f32]) -> ScoreCounts {
    ScoreCounts {
        edges: edges.to_vec(),
        counts: bins.iter().map(|b| b.load(Ordering::Relaxed)).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_fall_in_the_bin_below_their_upper_edge() {
        let tally = SafetyTally::default();
        tally.record_log_ratios(&[-9.0, -4.0, -0.5, 0.0, 0.5, 3.0, 4.0, 100.0, f32::NAN]);
        tally.record_support(&[0.0, 0.25, 0.99, 1.0, 7.0]);
        let (log_ratio, support) = tally.read();
        assert_eq!(log_ratio.counts, [1, 1, 0, 1, 2, 0, 1, 3]);
        assert_eq!(support.counts, [1, 1, 1, 1, 0, 1]);
        assert_eq!((log_ratio.total(), support.total()), (9, 5));
    }
}
