//! The reconnect backoff every side that reopens a transport uses (the bridge's TCP, serial,
//! CAN, Dynamixel and CANopen links, the twin's CAN port): wait, double the wait up to a
//! ceiling, start again from the first wait once a session held.
//!
//! It owns the waits only: it must not sleep, open anything or decide when a session held
//! (its callers do, each on its own clock: a thread, a tokio task or a polled deadline).

use std::time::Duration;

/// The first wait: short, so a peer that was only restarting is met again at once.
pub const BACKOFF_INITIAL: Duration = Duration::from_millis(10);
/// The longest wait: a peer that is away for long is still tried once a second, so it is
/// met within a second of its return.
pub const BACKOFF_MAX: Duration = Duration::from_secs(1);

/// Exponential backoff from an initial wait to a ceiling.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Backoff {
    initial: Duration,
    max: Duration,
    next: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Self::between(BACKOFF_INITIAL, BACKOFF_MAX)
    }
}

impl Backoff {
    /// Waits from `initial`, doubling up to `max`.
    pub fn between(initial: Duration, max: Duration) -> Self {
        Self {
            initial,
            max,
            next: initial,
        }
    }

    /// The wait the next attempt would have, without counting an attempt.
    pub fn wait(&self) -> Duration {
        self.next
    }

    /// The wait before the next attempt; the one after it is twice as long (up to the
    /// ceiling).
    pub fn next_wait(&mut self) -> Duration {
        let wait = self.next;
        self.next = (wait * 2).min(self.max);
        wait
    }

    /// A session held: the next attempt waits the initial time again.
    pub fn reset(&mut self) {
        self.next = self.initial;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn waits_double_up_to_the_ceiling_and_reset_to_the_first() {
        let mut backoff = Backoff::default();
        let waits: Vec<u128> = (0..9).map(|_| backoff.next_wait().as_millis()).collect();
        assert_eq!(waits, [10, 20, 40, 80, 160, 320, 640, 1000, 1000]);
        backoff.reset();
        assert_eq!(backoff.next_wait(), Duration::from_millis(10));
        let mut tcp = Backoff::between(Duration::from_millis(5), Duration::from_millis(12));
        let waits: Vec<u128> = (0..4).map(|_| tcp.next_wait().as_millis()).collect();
        assert_eq!(waits, [5, 10, 12, 12]);
    }
}
