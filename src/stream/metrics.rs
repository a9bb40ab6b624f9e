//! Fixed-size histograms for per-cycle timing: allocated once before streaming, so the
//! cycle records jitter and latency without allocating.

/// Counts of microsecond values in 1 us bins up to a ceiling; larger values share the
/// last bin (and are counted as such in the percentiles, a lower bound).
#[derive(Debug, Clone)]
pub struct MicrosHistogram {
    bins: Vec<u64>,
    count: u64,
    max_us: f64,
}

impl MicrosHistogram {
    pub fn new(ceiling_us: usize) -> Self {
        Self {
            bins: vec![0; ceiling_us + 1],
            count: 0,
            max_us: 0.0,
        }
    }

    pub fn record(&mut self, micros: f64) {
        let bin = (micros.max(0.0).round() as usize).min(self.bins.len() - 1);
        self.bins[bin] += 1;
        self.count += 1;
        self.max_us = self.max_us.max(micros);
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn max_us(&self) -> f64 {
        self.max_us
    }

    /// The smallest bin value at or below which `fraction` of the samples lie (0 if empty).
    pub fn percentile(&self, fraction: f64) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let wanted = (fraction * self.count as f64).ceil().max(1.0) as u64;
        let mut seen = 0;
        for (value, n) in self.bins.iter().enumerate() {
            seen += n;
            if seen >= wanted {
                return value as f64;
            }
        }
        (self.bins.len() - 1) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_of_a_known_spread() {
        let mut histogram = MicrosHistogram::new(1000);
        for v in 1..=100 {
            histogram.record(v as f64);
        }
        assert_eq!(histogram.percentile(0.5), 50.0);
        assert_eq!(histogram.percentile(0.99), 99.0);
        assert_eq!(histogram.percentile(1.0), 100.0);
        histogram.record(5000.0);
        assert_eq!(histogram.percentile(1.0), 1000.0);
        assert_eq!(histogram.max_us(), 5000.0);
    }
}
