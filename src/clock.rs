//! Time, handed in: every stage that needs "now" or a wait gets a [`Clock`]. The wall clock
//! serves real runs; the virtual clock runs exactly the same cycles without waiting, so a
//! job of hours of arm time finishes in seconds and tests are deterministic.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

pub trait Clock: Send + Sync {
    /// Time since the clock started.
    fn now(&self) -> Duration;
    /// Returns once `now() >= deadline`.
    fn sleep_until(&self, deadline: Duration);
    /// True for clocks that do not follow real time.
    fn is_virtual(&self) -> bool;
}

/// Real time. Sleeps most of a wait and spins the last stretch: the kernel's timer slack
/// alone gives jitter of 50-100 us on a loaded 2-core machine, too much at 1 kHz.
#[derive(Debug, Clone)]
pub struct WallClock {
    start: Instant,
    spin: Duration,
}

impl WallClock {
    pub fn new() -> Self {
        Self {
            start: Instant::now(),
            spin: Duration::from_micros(150),
        }
    }
}

impl Default for WallClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for WallClock {
    fn now(&self) -> Duration {
        self.start.elapsed()
    }

    fn sleep_until(&self, deadline: Duration) {
        let now = self.now();
        if deadline > now + self.spin {
            std::thread::sleep(deadline - now - self.spin);
        }
        while self.now() < deadline {
            std::hint::spin_loop();
        }
    }

    fn is_virtual(&self) -> bool {
        false
    }
}

/// Simulated time: a wait jumps straight to its deadline.
#[derive(Debug, Default)]
pub struct VirtualClock {
    nanos: AtomicU64,
}

impl VirtualClock {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn advance(&self, by: Duration) {
        self.nanos.fetch_add(duration_nanos(by), Ordering::SeqCst);
    }
}

fn duration_nanos(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

impl Clock for VirtualClock {
    fn now(&self) -> Duration {
        Duration::from_nanos(self.nanos.load(Ordering::SeqCst))
    }

    fn sleep_until(&self, deadline: Duration) {
        self.nanos
            .fetch_max(duration_nanos(deadline), Ordering::SeqCst);
    }

    fn is_virtual(&self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn virtual_clock_jumps_to_deadlines_and_never_goes_back() {
        let clock = VirtualClock::new();
        clock.sleep_until(Duration::from_secs(3600));
        assert_eq!(clock.now(), Duration::from_secs(3600));
        clock.sleep_until(Duration::from_secs(10));
        assert_eq!(clock.now(), Duration::from_secs(3600));
        clock.advance(Duration::from_millis(4));
        assert_eq!(clock.now(), Duration::from_millis(3_600_004));
    }

    #[test]
    fn wall_clock_waits_at_least_until_the_deadline() {
        let clock = WallClock::new();
        let deadline = clock.now() + Duration::from_millis(2);
        clock.sleep_until(deadline);
        assert!(clock.now() >= deadline);
    }
}
