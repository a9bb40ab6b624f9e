//! Fixed-size histograms for per-cycle timing: allocated once before streaming, so the
//! cycle records jitter and latency without allocating.

/// Values below this get a bin of 1 us each: every cycle's jitter and latency that
/// matters to a percentile (a tenth of a 1 kHz cycle is 100 us, a 250 Hz cycle 4,000 us).
const FINE_CEILING_US: usize = 5_000;
/// Above [`FINE_CEILING_US`], bins this wide: a stall's length to a tenth of a millisecond.
const COARSE_BIN_US: usize = 100;

/// Counts of microsecond values: 1 us bins up to [`FINE_CEILING_US`], then
/// [`COARSE_BIN_US`] bins up to a ceiling, each standing for its upper edge; larger values
/// share the last bin (and are counted as the ceiling in the percentiles, a lower bound). Small enough (about 48 KB at a
/// 100 ms ceiling, not 800 KB of 1 us bins) to be written through when made, so a cycle
/// later than any before never takes a page fault on a fresh bin: a fault waits for the
/// process's memory map, which another thread may be changing.
#[derive(Debug, Clone)]
pub struct MicrosHistogram {
    bins: Vec<u64>,
    ceiling_us: usize,
    count: u64,
    max_us: f64,
}

impl MicrosHistogram {
    pub fn new(ceiling_us: usize) -> Self {
        let fine = ceiling_us.min(FINE_CEILING_US);
        let coarse = ceiling_us
            .saturating_sub(FINE_CEILING_US)
            .div_ceil(COARSE_BIN_US);
        let len = fine + 1 + coarse;
        // Zeroed memory may come as pages the kernel maps on first touch, and a compiler
        // may drop plain zero writes to it: `black_box` makes each write one it must do.
        let mut bins = vec![0; len];
        for bin in &mut bins {
            *bin = std::hint::black_box(0);
        }
        Self {
            bins,
            ceiling_us,
            count: 0,
            max_us: 0.0,
        }
    }

    /// The bin of a value (us), and the value a bin stands for: its own microsecond, or a
    /// coarse bin's upper edge (so a percentile never understates a late cycle).
    fn bin_of(&self, micros: f64) -> usize {
        let us = (micros.max(0.0).round() as usize).min(self.ceiling_us);
        if us <= FINE_CEILING_US {
            us
        } else {
            FINE_CEILING_US + (us - FINE_CEILING_US).div_ceil(COARSE_BIN_US)
        }
        .min(self.bins.len() - 1)
    }

    fn value_of(&self, bin: usize) -> f64 {
        if bin <= FINE_CEILING_US {
            bin as f64
        } else {
            let value = FINE_CEILING_US + (bin - FINE_CEILING_US) * COARSE_BIN_US;
            value.min(self.ceiling_us) as f64
        }
    }

    pub fn record(&mut self, micros: f64) {
        let bin = self.bin_of(micros);
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
        for (bin, n) in self.bins.iter().enumerate() {
            seen += n;
            if seen >= wanted {
                return self.value_of(bin);
            }
        }
        self.value_of(self.bins.len() - 1)
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

    #[test]
    fn late_values_share_coarse_bins_up_to_the_ceiling() {
        let mut histogram = MicrosHistogram::new(100_000);
        // Fine to 5 ms: every microsecond its own bin.
        histogram.record(4_999.0);
        assert_eq!(histogram.percentile(1.0), 4_999.0);
        histogram.record(5_000.0);
        assert_eq!(histogram.percentile(1.0), 5_000.0);
        // Then 100 us bins, each standing for its upper edge: 5,001..=5,100 is one bin.
        histogram.record(5_001.0);
        assert_eq!(histogram.percentile(1.0), 5_100.0);
        histogram.record(12_345.0);
        assert_eq!(histogram.percentile(1.0), 12_400.0);
        histogram.record(250_000.0);
        assert_eq!(histogram.percentile(1.0), 100_000.0);
        assert_eq!(histogram.percentile(0.2), 4_999.0);
        assert_eq!(histogram.count(), 5);
        // About 48 KB, against 800 KB of 1 us bins to 100 ms.
        assert_eq!(histogram.bins.len(), 5_001 + 950);
    }
}
