//! Glass-to-trajectory latencies in constant memory: a live stream runs for weeks, and a
//! list of every latency (8 bytes a sample) grew without bound (found by the one-hour soak:
//! 12 KiB a minute at 30 samples a second).

/// Smallest latency told apart, seconds: shorter ones count in the first bucket.
const SMALLEST_S: f64 = 1e-4;
/// Each bucket is this much wider than the one before: percentiles within 1 %.
const GROWTH: f64 = 1.02;
/// Buckets from 0.1 ms to about 1000 s; longer latencies count in the last.
const BUCKETS: usize = 820;

/// A histogram of latencies on a logarithmic scale.
#[derive(Clone, Debug)]
pub struct LatencyHistogram {
    counts: Vec<u64>,
    total: u64,
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        Self { counts: vec![0; BUCKETS], total: 0 }
    }
}

impl LatencyHistogram {
    /// Counts one latency, seconds (a negative or non-finite one counts as the smallest).
    pub fn add(&mut self, seconds: f64) {
        let bucket = if seconds.is_finite() && seconds > SMALLEST_S {
            ((seconds / SMALLEST_S).ln() / GROWTH.ln()).ceil() as usize
        } else {
            0
        };
        self.counts[bucket.min(BUCKETS - 1)] += 1;
        self.total += 1;
    }

    /// Latencies counted.
    pub fn len(&self) -> u64 {
        self.total
    }

    /// Whether nothing was counted.
    pub fn is_empty(&self) -> bool {
        self.total == 0
    }

    /// The `p` quantile (0 to 1), seconds, within 1 % of the value the sorted latencies give
    /// (the geometric middle of its bucket); 0 when empty.
    pub fn percentile(&self, p: f64) -> f64 {
        if self.total == 0 {
            return 0.0;
        }
        // The same rank as the sorted list's nearest-rank percentile.
        let rank = ((self.total - 1) as f64 * p.clamp(0.0, 1.0)).round() as u64;
        let mut seen = 0u64;
        for (bucket, &count) in self.counts.iter().enumerate() {
            seen += count;
            if seen > rank {
                if bucket == 0 {
                    return SMALLEST_S;
                }
                return SMALLEST_S * GROWTH.powf(bucket as f64 - 0.5);
            }
        }
        SMALLEST_S * GROWTH.powi(BUCKETS as i32 - 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn sorted_percentile(values: &[f64], p: f64) -> f64 {
        let mut v = values.to_vec();
        v.sort_by(f64::total_cmp);
        v[((v.len() as f64 - 1.0) * p).round() as usize]
    }

    proptest! {
        #[test]
        fn percentiles_are_within_one_percent_of_the_sorted_latencies(
            values in prop::collection::vec(1e-3f64..100.0, 1..400),
            p in 0.0f64..=1.0,
        ) {
            let mut histogram = LatencyHistogram::default();
            for &v in &values {
                histogram.add(v);
            }
            let exact = sorted_percentile(&values, p);
            let estimate = histogram.percentile(p);
            prop_assert!((estimate / exact - 1.0).abs() <= 0.0101, "{estimate} for {exact}");
            prop_assert_eq!(histogram.len(), values.len() as u64);
        }
    }

    #[test]
    fn memory_does_not_grow_with_the_samples_and_odd_values_are_counted_at_the_ends() {
        let mut histogram = LatencyHistogram::default();
        let capacity = histogram.counts.capacity();
        for k in 0..1_000_000u32 {
            histogram.add(0.05 + f64::from(k % 100) * 1e-3);
        }
        assert_eq!(histogram.counts.capacity(), capacity);
        assert!((histogram.percentile(0.5) / 0.1 - 1.0).abs() < 0.011, "{}", histogram.percentile(0.5));
        let mut odd = LatencyHistogram::default();
        odd.add(f64::NAN);
        odd.add(-1.0);
        odd.add(1e9);
        assert_eq!(odd.percentile(0.0), SMALLEST_S);
        assert!(odd.percentile(1.0) > 900.0);
        assert_eq!(LatencyHistogram::default().percentile(0.5), 0.0);
    }
}
