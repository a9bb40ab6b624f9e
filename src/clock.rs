//! Time, handed in: every stage that needs "now" or a wait gets a [`Clock`]. The wall clock
//! serves real runs; the virtual clock runs exactly the same cycles without waiting, so a
//! job of hours of arm time finishes in seconds and tests are deterministic.
//!
//! The one time type inside the library is `Duration`: a timestamp is the time since its
//! clock started (`Clock::now`), a calendar stamp the time since the Unix epoch
//! (`Clock::unix_time`). Only this module reads the system's clocks (`Instant::now`,
//! `SystemTime::now`; tests/time.rs checks it); f64 seconds appear only at the edges that
//! write them (files, JSON, the wire, the page).

use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

pub trait Clock: Send + Sync {
    /// Time since the clock started.
    fn now(&self) -> Duration;
    /// Returns once `now() >= deadline`.
    fn sleep_until(&self, deadline: Duration);
    /// True for clocks that do not follow real time.
    fn is_virtual(&self) -> bool;
    /// Time since the Unix epoch, for stamps a reader takes as calendar time (ROS 2 headers,
    /// Foxglove log times, run file names). Not monotonic: the system may set its clock back.
    /// A clock paced by a device still lives in the system's calendar, hence the default.
    fn unix_time(&self) -> Duration {
        system_unix_time()
    }
}

/// The system's calendar time; before the epoch (a clock set wrong) reads as the epoch.
fn system_unix_time() -> Duration {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or(Duration::ZERO)
}

/// The process's real-time clock, started on first use: the one origin for real-time
/// deadlines and stamps that are no job's time (I/O timeouts, idle timers, a link's
/// session), so such stamps taken in two places compare.
pub fn real() -> &'static WallClock {
    static REAL: OnceLock<WallClock> = OnceLock::new();
    REAL.get_or_init(WallClock::new)
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

    /// Simulated time's calendar starts at the epoch, so a stamp in a test is exact.
    fn unix_time(&self) -> Duration {
        self.now()
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
    fn virtual_calendar_time_is_virtual_time_and_the_real_clock_is_one_clock() {
        let clock = VirtualClock::new();
        clock.advance(Duration::from_secs(7));
        assert_eq!(clock.unix_time(), Duration::from_secs(7));
        assert!(std::ptr::eq(real(), real()));
        let earlier = real().now();
        assert!(real().now() >= earlier);
        // 2020-01-01 in Unix seconds: any real calendar reads later than that.
        assert!(real().unix_time() > Duration::from_secs(1_577_836_800));
    }

    #[test]
    fn wall_clock_waits_at_least_until_the_deadline() {
        let clock = WallClock::new();
        let deadline = clock.now() + Duration::from_millis(2);
        clock.sleep_until(deadline);
        assert!(clock.now() >= deadline);
    }
}
