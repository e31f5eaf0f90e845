//! Latency samples and their summary (nearest-rank percentiles), plus a log-scale histogram for
//! the plot.

use serde::{Deserialize, Serialize};

/// Summary of a set of latency samples, in microseconds.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// Samples taken.
    pub n: usize,
    /// Median.
    pub p50_us: f64,
    /// 99th percentile.
    pub p99_us: f64,
    /// Largest sample.
    pub max_us: f64,
    /// Smallest sample.
    pub min_us: f64,
    /// Every sample, sorted (kept for the distribution plot).
    pub samples_us: Vec<f64>,
}

/// Nearest-rank percentile `p` (0–100) of sorted samples; 0 for no samples.
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let rank = (p / 100.0 * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

impl Summary {
    /// Summarises `samples` (any order; non-finite values are dropped).
    pub fn of(mut samples: Vec<f64>) -> Summary {
        samples.retain(|v| v.is_finite());
        samples.sort_by(f64::total_cmp);
        Summary {
            n: samples.len(),
            p50_us: percentile(&samples, 50.0),
            p99_us: percentile(&samples, 99.0),
            max_us: samples.last().copied().unwrap_or(0.0),
            min_us: samples.first().copied().unwrap_or(0.0),
            samples_us: samples,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 50.0), 50.0);
        assert_eq!(percentile(&v, 99.0), 99.0);
        assert_eq!(percentile(&v, 100.0), 100.0);
        assert_eq!(percentile(&[7.0], 99.0), 7.0);
        assert_eq!(percentile(&[], 50.0), 0.0);
    }

    #[test]
    fn summary_sorts_and_drops_nan() {
        let s = Summary::of(vec![3.0, f64::NAN, 1.0, 2.0]);
        assert_eq!(s.n, 3);
        assert_eq!(s.samples_us, vec![1.0, 2.0, 3.0]);
        assert_eq!((s.min_us, s.p50_us, s.max_us), (1.0, 2.0, 3.0));
    }
}
