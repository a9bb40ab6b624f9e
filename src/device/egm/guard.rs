//! What the EGM link takes from the network: one robot, its messages in order, and feedback
//! the arm could have reached. EGM is plain UDP with nothing in a message that says who sent
//! it (docs/egm.md), so the link binds a session to one source and judges every datagram
//! before it may move anything:
//!
//! - **The lock.** The source address and port of the first well-formed EgmRobot (or the one
//!   named by `egm://ADDR:PORT?robot=HOST:PORT`) is the robot. Datagrams from any other source
//!   are dropped and counted; a well-formed EgmRobot from another source is a second robot,
//!   an error unless the robot was named. An unnamed lock is released after the robot has
//!   been silent for [`LOCK_RELEASE`] (a restarted controller may send from a new port).
//! - **Order.** Within an EGM run, header seqno, header tm and feedBack.time must each
//!   advance; a message that repeats or goes back is a replay, dropped and counted. A run
//!   starts at the lock, and again at seqno 0 (abb_libegm takes seqno 0 as a session's first
//!   message) when the robot's clock (feedBack.time) has advanced: a replayed first message
//!   has not.
//! - **Reach.** Feedback further from the last accepted feedback than each axis' max speed
//!   allows in the time since (plus [`JUMP_SLACK`]) is a jump: dropped, counted, never
//!   adopted; the link then stops the job.
//!
//! Pure judgement on (source, message, feedback, arrival time): it owns no socket and must
//! not decide what is sent.

use crate::device::egm::wire::EgmRobot;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// An unnamed lock ends after the robot has been silent this long: ten times the link's own
/// patience for a silent robot (0.1 s), so a dropped message or a stalled host never frees
/// it, while a controller that restarted (and may send from another port) is met again.
pub const LOCK_RELEASE: Duration = Duration::from_secs(1);
/// Time added to the time between two robot messages before the reach check: the earlier of
/// the two may have reached us up to a cycle late and the later one on time (the robot
/// sampled them a cycle apart all the same), and a host that stalled reads several queued
/// messages at once. One 4 ms EGM cycle at the robot's speeds is 1 deg on the IRB 120's
/// first axis: far below the jump a forgery needs to move the arm somewhere else.
pub const JUMP_SLACK: Duration = Duration::from_millis(4);
/// A second robot that has sent nothing for this long is gone: a later one is a new report.
pub const INTRUDER_MEMORY: Duration = LOCK_RELEASE;

/// What the guard made of one datagram.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// The robot's next message: answer it and take its feedback. `new_run`: it starts an
    /// EGM run (the lock's first message, or seqno 0).
    Accept { new_run: bool },
    /// From another source: dropped. `second_robot`: a well-formed EgmRobot from a robot
    /// that was not reported yet (the words say which); only when the lock was not named.
    Foreign { second_robot: Option<String> },
    /// Not an EgmRobot this link can use, from the robot's source or before any lock.
    Malformed,
    /// Repeats or goes back in seqno or robot time: dropped.
    Replay,
    /// Feedback the arm cannot have reached: dropped, and the words say which axis.
    Jump(String),
}

/// The counts of what the guard dropped.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GuardCounters {
    /// Datagrams from a source other than the robot.
    pub foreign: u64,
    /// Messages from the robot that repeated or went back.
    pub replays: u64,
    /// Feedback further than the arm can move.
    pub jumps: u64,
    /// Second robots reported (each one once while it keeps sending).
    pub second_robots: u64,
}

/// The last accepted message's place in its run.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Order {
    seqno: u32,
    tm: Option<u32>,
    /// feedBack.time, microseconds since 1970.
    time_us: Option<u64>,
}

/// A second robot, as long as it keeps sending.
#[derive(Debug, Clone, Copy)]
struct Intruder {
    from: SocketAddr,
    last_seen: Instant,
}

pub struct RobotGuard {
    named: Option<SocketAddr>,
    locked: Option<SocketAddr>,
    /// When the robot last sent a well-formed EgmRobot (accepted or not).
    heard: Option<Instant>,
    order: Option<Order>,
    /// The last feedback accepted (rig axes, rad or m) and when it arrived.
    accepted: Option<(Vec<f64>, Instant)>,
    intruder: Option<Intruder>,
    /// Each rig axis' max speed (rad/s, m/s) and name.
    max_speeds: Vec<f64>,
    names: Vec<String>,
    pub counters: GuardCounters,
}

impl RobotGuard {
    /// A guard for axes `names` moving at most `max_speeds`; `named` is the robot given by
    /// `?robot=` (the only source ever taken), else the first to send is.
    pub fn new(named: Option<SocketAddr>, names: Vec<String>, max_speeds: Vec<f64>) -> Self {
        Self {
            named,
            locked: named,
            heard: None,
            order: None,
            accepted: None,
            intruder: None,
            max_speeds,
            names,
            counters: GuardCounters::default(),
        }
    }

    /// The robot the session is bound to, once there is one.
    pub fn robot(&self) -> Option<SocketAddr> {
        self.locked
    }

    /// The report of a second robot that still sends (heard within [`INTRUDER_MEMORY`]).
    pub fn second_robot_words(&self, now: Instant) -> Option<String> {
        self.intruder
            .filter(|i| now.saturating_duration_since(i.last_seen) < INTRUDER_MEMORY)
            .map(|i| self.second_robot_text(i.from))
    }

    fn second_robot_text(&self, from: SocketAddr) -> String {
        let robot = self.locked.map_or("none".to_string(), |r| r.to_string());
        format!(
            "a second robot at {from} sends EgmRobot messages to this sensor port, which is bound to the robot at {robot}: which one is ours is ambiguous (name it with egm://ADDR:PORT?robot=HOST:PORT)"
        )
    }

    /// Judges one datagram from `from` that arrived at `arrived`: `message` when it decoded
    /// as an EgmRobot with this rig's axes, `feedback` its positions (rad, m).
    pub fn judge(
        &mut self,
        from: SocketAddr,
        message: Option<(&EgmRobot, &[f64])>,
        arrived: Instant,
    ) -> Verdict {
        self.release_if_silent(arrived);
        if self.locked.is_some_and(|robot| robot != from) {
            self.counters.foreign += 1;
            let second_robot = message.and_then(|_| self.second_robot(from, arrived));
            return Verdict::Foreign { second_robot };
        }
        let Some((robot, feedback)) = message else {
            return Verdict::Malformed;
        };
        let Some(order) = order_of(robot) else {
            return Verdict::Malformed;
        };
        self.locked = Some(from);
        self.heard = Some(arrived);
        let Some(new_run) = self.in_order(&order) else {
            self.counters.replays += 1;
            return Verdict::Replay;
        };
        if let Some(words) = self.jump(feedback, arrived) {
            self.counters.jumps += 1;
            return Verdict::Jump(words);
        }
        self.order = Some(order);
        self.accepted = Some((feedback.to_vec(), arrived));
        Verdict::Accept { new_run }
    }

    /// After [`LOCK_RELEASE`] of silence a run's order starts anew, and an unnamed lock is
    /// free for whoever sends first.
    fn release_if_silent(&mut self, now: Instant) {
        if self
            .heard
            .is_some_and(|t| now.saturating_duration_since(t) >= LOCK_RELEASE)
        {
            self.heard = None;
            self.order = None;
            if self.named.is_none() {
                self.locked = None;
            }
        }
    }

    /// Notes a well-formed EgmRobot from `from`, not the robot: the words of a report when
    /// it is a second robot not reported yet (never for a named lock: it is just dropped).
    fn second_robot(&mut self, from: SocketAddr, now: Instant) -> Option<String> {
        if self.named.is_some() {
            return None;
        }
        let known = self.second_robot_words(now).is_some();
        self.intruder = Some(Intruder {
            from,
            last_seen: now,
        });
        if known {
            return None;
        }
        self.counters.second_robots += 1;
        Some(self.second_robot_text(from))
    }

    /// `Some(new_run)` when `order` follows the run (or starts one), `None` for a replay.
    fn in_order(&self, order: &Order) -> Option<bool> {
        let Some(last) = self.order else {
            return Some(true);
        };
        let clock_advanced = advanced_u64(last.time_us, order.time_us);
        if order.seqno == 0 {
            // A new EGM run (abb_libegm: seqno 0 is a session's first message); a replayed
            // first message shows an old robot time. tm may restart with the run.
            return (clock_advanced != Some(false)).then_some(true);
        }
        let seqno_advanced = newer_u32(last.seqno, order.seqno);
        let tm_advanced = match (last.tm, order.tm) {
            (Some(a), Some(b)) => newer_u32(a, b),
            _ => true,
        };
        (seqno_advanced && tm_advanced && clock_advanced != Some(false)).then_some(false)
    }

    /// The words for feedback no axis could have reached since the last accepted one.
    fn jump(&self, feedback: &[f64], arrived: Instant) -> Option<String> {
        let (last, at) = self.accepted.as_ref()?;
        let window = arrived.saturating_duration_since(*at) + JUMP_SLACK;
        let seconds = window.as_secs_f64();
        for (axis, ((now, before), max_speed)) in
            feedback.iter().zip(last).zip(&self.max_speeds).enumerate()
        {
            let moved = (now - before).abs();
            let reach = max_speed * seconds;
            if moved > reach {
                let name = self.names.get(axis).map_or("?", String::as_str);
                return Some(format!(
                    "robot feedback of {name} jumped {moved:.4} (rad or m) in {:.1} ms, further than its max speed {max_speed:.3} allows ({reach:.4}): not adopted, the job stops",
                    seconds * 1e3
                ));
            }
        }
        None
    }
}

/// A message's seqno, tm and robot time; `None` without a seqno (nothing to order it by).
fn order_of(robot: &EgmRobot) -> Option<Order> {
    let header = robot.header.as_ref()?;
    let time_us = robot
        .feed_back
        .as_ref()
        .and_then(|f| f.time.as_ref())
        .map(|t| t.sec.saturating_mul(1_000_000).saturating_add(t.usec));
    Some(Order {
        seqno: header.seqno?,
        tm: header.tm,
        time_us,
    })
}

/// `b` comes after `a` in a wrapping 32-bit count (seqno, and tm in ms, both wrap).
fn newer_u32(a: u32, b: u32) -> bool {
    let d = b.wrapping_sub(a);
    d != 0 && d < 1 << 31
}

/// Whether robot time `b` is later than `a`; `None` unless both are known.
fn advanced_u64(a: Option<u64>, b: Option<u64>) -> Option<bool> {
    Some(b? > a?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::egm::wire::{EgmClock, EgmFeedBack, EgmHeader};

    fn message(seqno: u32, tm: u32, time_us: u64) -> EgmRobot {
        EgmRobot {
            header: Some(EgmHeader {
                seqno: Some(seqno),
                tm: Some(tm),
                mtype: None,
            }),
            feed_back: Some(EgmFeedBack {
                joints: None,
                cartesian: None,
                external_joints: None,
                time: Some(EgmClock {
                    sec: time_us / 1_000_000,
                    usec: time_us % 1_000_000,
                }),
            }),
            planned: None,
            motor_state: None,
            mci_state: None,
            mci_convergence_met: None,
            rapid_exec_state: None,
            utilization_rate: None,
        }
    }

    fn guard(named: Option<SocketAddr>) -> RobotGuard {
        // One axis at 250 deg/s, as the IRB 120's first.
        RobotGuard::new(named, vec!["joint_1".into()], vec![250f64.to_radians()])
    }

    const ROBOT: &str = "10.0.0.2:6511";
    const OTHER: &str = "10.0.0.9:6511";
    const CYCLE: Duration = Duration::from_millis(4);

    fn addr(text: &str) -> SocketAddr {
        text.parse().expect("an address")
    }

    #[test]
    fn the_first_source_is_the_robot_and_another_is_a_second_robot_reported_once() {
        let mut guard = guard(None);
        let t0 = Instant::now();
        let first = message(1, 4, 1_000_000);
        let verdict = guard.judge(addr(ROBOT), Some((&first, &[0.0])), t0);
        assert_eq!(verdict, Verdict::Accept { new_run: true });
        assert_eq!(guard.robot(), Some(addr(ROBOT)));
        let forged = message(2, 8, 1_004_000);
        let Verdict::Foreign {
            second_robot: Some(words),
        } = guard.judge(addr(OTHER), Some((&forged, &[0.0])), t0 + CYCLE)
        else {
            panic!("a second robot");
        };
        assert!(words.contains(OTHER) && words.contains(ROBOT), "{words}");
        // Still sending: counted, not reported again; garbage from it is foreign too.
        let again = guard.judge(addr(OTHER), Some((&forged, &[0.0])), t0 + 2 * CYCLE);
        assert_eq!(again, Verdict::Foreign { second_robot: None });
        let garbage = guard.judge(addr(OTHER), None, t0 + 2 * CYCLE);
        assert_eq!(garbage, Verdict::Foreign { second_robot: None });
        assert_eq!(guard.counters.foreign, 3);
        assert_eq!(guard.counters.second_robots, 1);
    }

    #[test]
    fn a_named_robot_is_the_only_source_and_an_intruder_is_only_counted() {
        let mut guard = guard(Some(addr(ROBOT)));
        let t0 = Instant::now();
        let forged = message(1, 4, 1_000_000);
        let verdict = guard.judge(addr(OTHER), Some((&forged, &[0.0])), t0);
        assert_eq!(verdict, Verdict::Foreign { second_robot: None });
        let real = message(7, 4, 1_000_000);
        let verdict = guard.judge(addr(ROBOT), Some((&real, &[0.0])), t0);
        assert_eq!(verdict, Verdict::Accept { new_run: true });
        assert_eq!(guard.counters.second_robots, 0);
        // Named: kept after any silence.
        let later = t0 + LOCK_RELEASE * 3;
        let verdict = guard.judge(addr(OTHER), Some((&forged, &[0.0])), later);
        assert_eq!(verdict, Verdict::Foreign { second_robot: None });
    }

    #[test]
    fn a_repeated_or_older_seqno_tm_or_robot_time_is_a_replay() {
        let mut guard = guard(None);
        let t0 = Instant::now();
        let robot = addr(ROBOT);
        let accept = |g: &mut RobotGuard, m: &EgmRobot, t| g.judge(robot, Some((m, &[0.0])), t);
        assert!(matches!(
            accept(&mut guard, &message(10, 40, 1_000_000), t0),
            Verdict::Accept { .. }
        ));
        for (seqno, tm, time) in [
            (10, 44, 1_004_000), // seqno repeats
            (9, 44, 1_004_000),  // seqno goes back
            (11, 40, 1_004_000), // tm repeats
            (11, 44, 1_000_000), // robot time repeats
            (11, 44, 999_000),   // robot time goes back
        ] {
            let verdict = accept(&mut guard, &message(seqno, tm, time), t0 + CYCLE);
            assert_eq!(verdict, Verdict::Replay, "{seqno} {tm} {time}");
        }
        assert_eq!(guard.counters.replays, 5);
        let next = accept(&mut guard, &message(11, 44, 1_004_000), t0 + CYCLE);
        assert_eq!(next, Verdict::Accept { new_run: false });
    }

    #[test]
    fn seqno_zero_with_a_later_robot_time_starts_a_run_and_a_replayed_one_does_not() {
        let mut guard = guard(None);
        let t0 = Instant::now();
        let robot = addr(ROBOT);
        let first = message(0, 0, 5_000_000);
        guard.judge(robot, Some((&first, &[0.0])), t0);
        let running = message(500, 2000, 7_000_000);
        guard.judge(robot, Some((&running, &[0.0])), t0 + CYCLE);
        // The old first message again: its robot time went back.
        let replayed = guard.judge(robot, Some((&first, &[0.0])), t0 + 2 * CYCLE);
        assert_eq!(replayed, Verdict::Replay);
        // EGM started again: seqno and tm restart, the robot's clock goes on.
        let restart = message(0, 0, 7_004_000);
        let verdict = guard.judge(robot, Some((&restart, &[0.0])), t0 + 2 * CYCLE);
        assert_eq!(verdict, Verdict::Accept { new_run: true });
        let next = guard.judge(
            robot,
            Some((&message(1, 4, 7_008_000), &[0.0])),
            t0 + 3 * CYCLE,
        );
        assert_eq!(next, Verdict::Accept { new_run: false });
    }

    #[test]
    fn feedback_beyond_the_axis_reach_since_the_last_is_a_jump_never_adopted() {
        let mut guard = guard(None);
        let t0 = Instant::now();
        let robot = addr(ROBOT);
        let start = 2.9f64.to_radians();
        guard.judge(robot, Some((&message(1, 4, 1_000_000), &[start])), t0);
        // 90 deg one cycle later: 250 deg/s reaches 2 deg in a cycle and the slack.
        let far = [90f64.to_radians()];
        let Verdict::Jump(words) =
            guard.judge(robot, Some((&message(2, 8, 1_004_000), &far)), t0 + CYCLE)
        else {
            panic!("a jump");
        };
        assert!(words.contains("joint_1"), "{words}");
        // Not adopted: the next real message is judged against the last accepted one.
        let near = [start + 0.9f64.to_radians()];
        let verdict = guard.judge(robot, Some((&message(2, 8, 1_004_000), &near)), t0 + CYCLE);
        assert_eq!(verdict, Verdict::Accept { new_run: false });
        // Within reach only in time: 87 deg needs 0.35 s at 250 deg/s.
        let later = t0 + Duration::from_millis(400);
        let verdict = guard.judge(robot, Some((&message(3, 400, 1_400_000), &far)), later);
        assert_eq!(verdict, Verdict::Accept { new_run: false });
        assert_eq!(guard.counters.jumps, 1);
    }

    #[test]
    fn an_unnamed_lock_is_released_after_silence() {
        let mut guard = guard(None);
        let t0 = Instant::now();
        guard.judge(addr(ROBOT), Some((&message(5, 4, 1_000_000), &[0.0])), t0);
        let later = t0 + LOCK_RELEASE;
        let verdict = guard.judge(addr(OTHER), Some((&message(1, 4, 900_000), &[0.0])), later);
        assert_eq!(verdict, Verdict::Accept { new_run: true });
        assert_eq!(guard.robot(), Some(addr(OTHER)));
    }
}
