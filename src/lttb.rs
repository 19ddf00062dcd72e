//! Largest-Triangle-Three-Buckets downsampling (Steinarsson, "Downsampling Time Series for
//! Visual Representation", 2013): picks `threshold` of a series' points so that its chart keeps
//! its shape. The first and the last point always stay; the others are split into
//! `threshold - 2` buckets of consecutive points, and each bucket keeps the one point that spans
//! the largest triangle with the point kept before it and the mean of the next bucket. Unlike
//! bucket means it keeps real points, so a one-step spike in a long run (a loss blowing up)
//! stays on the chart at its true height.
//!
//! Written here rather than taken from a crate: the `lttb` crate (0.2, last release 2020)
//! returns copies of the points, and the metrics endpoint needs the indices of the kept rows
//! (each carries its step and time).

/// The indices (ascending) of the points of `(x, y)` that LTTB keeps: all of them when there
/// are at most `threshold`, else `threshold` of them (at least the first and the last).
pub fn lttb_indices(x: &[f64], y: &[f64], threshold: usize) -> Vec<usize> {
    assert_eq!(x.len(), y.len(), "x and y of one series");
    let n = x.len();
    if n <= threshold.max(2) {
        return (0..n).collect();
    }
    if threshold <= 2 {
        return vec![0, n - 1];
    }
    let buckets = threshold - 2;
    // Bucket i covers the inner points [bound(i), bound(i + 1)); the last ends at n - 1.
    let bound = |i: usize| 1 + i * (n - 2) / buckets;
    let mut kept = Vec::with_capacity(threshold);
    kept.push(0);
    let mut previous = 0;
    for bucket in 0..buckets {
        let (start, end) = (bound(bucket), bound(bucket + 1));
        let (next_start, next_end) =
            if bucket + 1 < buckets { (end, bound(bucket + 2)) } else { (n - 1, n) };
        let count = (next_end - next_start) as f64;
        let mean_x = x[next_start..next_end].iter().sum::<f64>() / count;
        let mean_y = y[next_start..next_end].iter().sum::<f64>() / count;
        let (ax, ay) = (x[previous], y[previous]);
        // Twice the triangle's area; the factor does not change which point is largest.
        let area = |i: usize| ((ax - mean_x) * (y[i] - ay) - (ax - x[i]) * (mean_y - ay)).abs();
        let chosen = (start..end)
            .max_by(|&i, &j| area(i).total_cmp(&area(j)).then(j.cmp(&i)))
            .expect("a bucket holds at least one point");
        kept.push(chosen);
        previous = chosen;
    }
    kept.push(n - 1);
    kept
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn short_series_are_kept_whole() {
        assert_eq!(lttb_indices(&[0.0, 1.0, 2.0], &[1.0, 2.0, 3.0], 3), [0, 1, 2]);
        assert_eq!(lttb_indices(&[], &[], 5), Vec::<usize>::new());
        assert_eq!(lttb_indices(&[0.0], &[7.0], 2), [0]);
    }

    #[test]
    fn two_points_are_the_first_and_the_last() {
        let x: Vec<f64> = (0..10).map(f64::from).collect();
        assert_eq!(lttb_indices(&x, &x, 2), [0, 9]);
    }

    #[test]
    fn a_one_point_spike_survives_where_bucket_means_would_flatten_it() {
        // 10,000 steps of a flat loss with one step at 50: 100 kept points. A bucket of 100
        // points averaged would report 1.49; LTTB keeps the spike itself.
        let x: Vec<f64> = (0..10_000).map(f64::from).collect();
        let mut y = vec![1.0; 10_000];
        y[4_321] = 50.0;
        let kept = lttb_indices(&x, &y, 100);
        assert_eq!(kept.len(), 100);
        assert!(kept.contains(&4_321), "{kept:?}");
    }

    #[test]
    fn each_bucket_keeps_its_largest_triangle() {
        // Worked by hand: points (0,0) (1,0) (2,3) (3,0) (4,1) (5,0), threshold 4 → buckets
        // {1,2} and {3,4}. Bucket 1 with a=(0,0), next mean (3.5,0.5): areas 0.5 (i=1), 9.5
        // (i=2) → 2. Bucket 2 with a=(2,3), next = last (5,0): areas |(2-5)(0-3)-(2-3)(0-3)| = 6
        // (i=3) and |(2-5)(1-3)-(2-4)(0-3)| = 0 (i=4) → 3.
        let x = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0];
        let y = [0.0, 0.0, 3.0, 0.0, 1.0, 0.0];
        assert_eq!(lttb_indices(&x, &y, 4), [0, 2, 3, 5]);
    }

    proptest! {
        #[test]
        fn keeps_a_subsequence_of_the_asked_size_with_both_ends(
            y in proptest::collection::vec(-1e6f64..1e6, 0..400),
            threshold in 2usize..60,
        ) {
            let x: Vec<f64> = (0..y.len()).map(|i| i as f64 * 3.0).collect();
            let kept = lttb_indices(&x, &y, threshold);
            prop_assert_eq!(kept.len(), y.len().min(threshold));
            prop_assert!(kept.windows(2).all(|w| w[0] < w[1]));
            if !y.is_empty() {
                prop_assert_eq!(kept[0], 0);
                prop_assert_eq!(*kept.last().unwrap(), y.len() - 1);
            }
        }
    }
}
