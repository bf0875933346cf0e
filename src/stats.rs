//! Running statistics for the `leangate-stats` bus message.

/// Per-frame inference times, for the mean and 99th percentile.
#[derive(Debug, Clone, Default)]
pub struct InferenceStats {
    samples_us: Vec<u64>,
    sum_us: u128,
}

impl InferenceStats {
    pub fn record(&mut self, us: u64) {
        self.samples_us.push(us);
        self.sum_us += us as u128;
    }

    pub fn count(&self) -> usize {
        self.samples_us.len()
    }

    /// Mean in microseconds (0 with no sample).
    pub fn mean_us(&self) -> f64 {
        if self.samples_us.is_empty() {
            0.0
        } else {
            self.sum_us as f64 / self.samples_us.len() as f64
        }
    }

    /// Nearest-rank percentile `p` in (0, 100], microseconds (0 with no sample).
    pub fn percentile_us(&self, p: f64) -> u64 {
        if self.samples_us.is_empty() {
            return 0;
        }
        let mut v = self.samples_us.clone();
        let rank = ((p / 100.0) * v.len() as f64).ceil().max(1.0) as usize;
        let idx = rank.min(v.len()) - 1;
        *v.select_nth_unstable(idx).1
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_and_p99() {
        let mut s = InferenceStats::default();
        assert_eq!((s.mean_us(), s.percentile_us(99.0)), (0.0, 0));
        for us in 1..=200u64 {
            s.record(us);
        }
        assert_eq!(s.count(), 200);
        assert!((s.mean_us() - 100.5).abs() < 1e-9);
        assert_eq!(s.percentile_us(99.0), 198);
        assert_eq!(s.percentile_us(100.0), 200);
        assert_eq!(s.percentile_us(50.0), 100);
    }
}
