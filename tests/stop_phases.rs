//! Stop and e-stop at every point of a job's life (issue 26, docs/faults.md): 100 stops at
//! seeded random instants across the star (the default job), paint and gait jobs, and 30
//! e-stops, each checked from the twin's side. A link between the bridge and the in-process
//! twin forwards what the bridge sends and records every target the twin receives, with
//! when; it can keep the controller away at the start (the link is down), make it slow to
//! hold (its feedback does not come), and lose the link mid-job (for a resume). It pulls
//! the stop itself at the chosen instant of the chosen phase, from the bridge's own thread
//! outside its cycle's send; the planning phase, which touches no link, is stopped from a
//! thread that watches for it.
//!
//! What must hold once the request is acknowledged: at rest (waiting for the controller or
//! the hold, planning, or moving nothing yet) no target at all reaches the twin; moving,
//! only a ramp whose speed (the fastest axis' share of its speed limit, from the position
//! steps the twin receives) never rises and that ends at rest within what braking needs.
//! After an e-stop no target at all.

use crate::common;

use rand::{Rng, RngExt};
use rigbridge::clock::{Clock, VirtualClock, WallClock};
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::{DaemonError, RunReport, loopback_twin, plan_for, stream_planned};
use rigbridge::link::{Link, LinkCounters, LinkError, LinkEvent, LoopbackLink};
use rigbridge::protocol::{Command, Feedback, Hello};
use rigbridge::stream::{Outcome, Phase, StreamControl};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const STOPS: usize = 100;
const ESTOPS: usize = 30;
/// Every this many cases run on the wall clock (the rest on the virtual one, which runs a
/// job as fast as the machine can).
const WALL_EVERY: usize = 12;
/// A wall-clock case stops within this many cycles of its phase's start: a few seconds.
const WALL_CYCLES: u64 = 600;
/// Steps compared with this relative slack: one rounding of the interpolation.
const SPEED_SLACK: f64 = 1e-6;
/// The brake may take this much longer than the fastest stop of each axis alone (a path
/// that curves while braking), plus a few cycles.
const BRAKING_FACTOR: f64 = 2.0;
const BRAKING_EXTRA_CYCLES: f64 = 5.0;

const PHASES: [Phase; 5] = [
    Phase::WaitingForController,
    Phase::WaitingForHold,
    Phase::Planning,
    Phase::Resuming,
    Phase::Streaming,
];

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Request {
    Stop,
    EStop,
}

/// One case: where and how to pull the request, and the faults that make the phase long.
#[derive(Clone, Copy, Debug)]
struct Case {
    phase: Phase,
    /// Calls (of `is_up` or `receive`) into the phase before the request.
    after_calls: u64,
    request: Request,
    /// `is_up` calls the link stays down at the start.
    down_at_start: u64,
    /// `receive` calls the controller does not answer after the link is up.
    silent_at_start: u64,
    /// Targets after which the link is lost (for a resume), for `loss_calls` `is_up` calls.
    loss_after_targets: Option<u64>,
    loss_calls: u64,
    wall: bool,
}

/// What the twin received, and when the request was acknowledged.
#[derive(Default)]
struct Seen {
    /// Every target forwarded to the twin: when, and its positions.
    targets: Vec<(Instant, Vec<f64>)>,
    /// When the request returned, and the phase it answered.
    acknowledged: Option<(Instant, Phase)>,
}

/// The link between the bridge and the twin (see the module doc).
struct Watched {
    inner: LoopbackLink,
    control: Arc<StreamControl>,
    case: Case,
    seen: Arc<Mutex<Seen>>,
    is_up_calls: std::cell::Cell<u64>,
    down_until: std::cell::Cell<u64>,
    silent_receives: u64,
    /// Calls so far in each phase (by its place in [`PHASES`]), over all its entries.
    calls_in_phase: std::cell::Cell<[u64; 5]>,
    /// Whether the case's phase was entered: a request not pulled in it (a phase shorter
    /// than the case's count) is pulled at the first call after it.
    entered: std::cell::Cell<bool>,
    lost: bool,
}

impl Watched {
    /// Counts a call into the current phase and pulls the request at the chosen one.
    fn tick(&self) {
        let phase = self.control.phase();
        let mut calls = self.calls_in_phase.get();
        // Holding, stopping and ended follow a case's phase: its request was pulled.
        let Some(index) = PHASES.iter().position(|p| *p == phase) else {
            if self.entered.get() || phase == Phase::Holding {
                pull(&self.control, self.case.request, &self.seen);
            }
            return;
        };
        calls[index] += 1;
        self.calls_in_phase.set(calls);
        if phase == self.case.phase {
            self.entered.set(true);
            if calls[index] >= self.case.after_calls {
                pull(&self.control, self.case.request, &self.seen);
            }
        } else if self.entered.get() {
            pull(&self.control, self.case.request, &self.seen);
        }
    }

    fn down(&self) -> bool {
        self.is_up_calls.get() < self.down_until.get()
    }
}

fn pull(control: &StreamControl, request: Request, seen: &Mutex<Seen>) {
    let mut seen = seen.lock().unwrap();
    if seen.acknowledged.is_some() {
        return;
    }
    let phase = match request {
        Request::Stop => control.request_stop(),
        Request::EStop => control.request_estop(),
    };
    seen.acknowledged = Some((Instant::now(), phase));
}

impl Link for Watched {
    fn send(&mut self, command: &Command) -> Result<(), LinkError> {
        if self.down() {
            return Ok(());
        }
        if let Command::Target(target) = command {
            let mut seen = self.seen.lock().unwrap();
            seen.targets
                .push((Instant::now(), target.positions.as_slice().to_vec()));
            let count = seen.targets.len() as u64;
            drop(seen);
            if !self.lost && self.case.loss_after_targets == Some(count) {
                self.lost = true;
                self.down_until
                    .set(self.is_up_calls.get() + self.case.loss_calls);
            }
        }
        self.inner.send(command)
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Feedback>, LinkError> {
        self.tick();
        if self.down() {
            return Ok(None);
        }
        if self.silent_receives < self.case.silent_at_start {
            self.silent_receives += 1;
            return Ok(None);
        }
        self.inner.receive(timeout)
    }

    fn counters(&self) -> LinkCounters {
        self.inner.counters()
    }

    fn describe(&self) -> String {
        "watched loopback".into()
    }

    fn is_up(&self) -> bool {
        self.is_up_calls.set(self.is_up_calls.get() + 1);
        self.tick();
        !self.down()
    }

    fn next_event(&mut self) -> Option<LinkEvent> {
        self.inner.next_event()
    }

    fn controller_hello(&self) -> Option<Hello> {
        self.inner.controller_hello()
    }
}

struct Job {
    label: &'static str,
    settings: RunSettings,
    /// Samples of its planned trajectory: where a stop may fall.
    samples: u64,
}

fn job(label: &'static str, file: &str) -> Job {
    let settings = load_run_settings(&common::repo_path(file)).unwrap();
    let mut link = loopback_twin(&settings).unwrap();
    let planned = plan_for(
        &settings,
        &settings.config.job,
        &mut link,
        &VirtualClock::new(),
        &StreamControl::default(),
    )
    .unwrap();
    let samples = planned.trajectory.len() as u64;
    Job {
        label,
        settings,
        samples,
    }
}

/// What became of one case.
struct Ran {
    report: RunReport,
    seen: Seen,
}

fn run_case(job: &Job, case: Case) -> Ran {
    let control = Arc::new(StreamControl::default());
    let seen = Arc::new(Mutex::new(Seen::default()));
    let mut link = Watched {
        inner: loopback_twin(&job.settings).unwrap(),
        control: control.clone(),
        case,
        seen: seen.clone(),
        is_up_calls: std::cell::Cell::new(0),
        down_until: std::cell::Cell::new(case.down_at_start),
        silent_receives: 0,
        calls_in_phase: std::cell::Cell::new([0; 5]),
        entered: std::cell::Cell::new(false),
        lost: false,
    };
    let clock: Box<dyn Clock> = if case.wall {
        Box::new(WallClock::new())
    } else {
        Box::new(VirtualClock::new())
    };
    let planning = Arc::new(AtomicBool::new(true));
    let watcher = (case.phase == Phase::Planning).then(|| {
        let (control, seen, planning) = (control.clone(), seen.clone(), planning.clone());
        std::thread::spawn(move || {
            // Planning may be over before this thread looks: then the stop finds the stream.
            while planning.load(Ordering::SeqCst) {
                if matches!(control.phase(), Phase::Planning | Phase::Streaming) {
                    pull(&control, case.request, &seen);
                    return;
                }
                std::hint::spin_loop();
            }
        })
    });
    let settings = &job.settings;
    let report = match plan_for(
        settings,
        &settings.config.job,
        &mut link,
        clock.as_ref(),
        &control,
    ) {
        Ok(planned) => stream_planned(
            settings,
            &planned,
            &mut link,
            clock.as_ref(),
            None,
            &control,
        )
        .unwrap(),
        Err(DaemonError::Halted(halted)) => {
            halted.report(settings, &settings.config.job.name(), &link, clock.as_ref())
        }
        Err(e) => panic!("{}: {}", job.label, rigbridge::daemon::error_chain(&e)),
    };
    planning.store(false, Ordering::SeqCst);
    if let Some(watcher) = watcher {
        watcher.join().unwrap();
    }
    drop(link);
    let seen = std::mem::take(&mut *seen.lock().unwrap());
    Ran { report, seen }
}

/// The fastest axis' share of its speed limit, moving by `step` in one period.
fn speed(settings: &RunSettings, step: &[f64]) -> f64 {
    let dt = settings.period().as_secs_f64();
    settings
        .rig
        .joints
        .iter()
        .zip(step)
        .map(|(joint, d)| (d / dt).abs() / joint.limits.max_speed)
        .fold(0.0, f64::max)
}

fn step(a: &[f64], b: &[f64]) -> Vec<f64> {
    b.iter().zip(a).map(|(b, a)| b - a).collect()
}

/// The twin's side of one case: what arrived after the acknowledgment. Returns the phase
/// acknowledged and the targets after it.
fn judge(job: &Job, case: &Case, ran: &Ran) -> (Phase, usize) {
    let what = format!("{} {case:?}", job.label);
    let (at, phase) = ran
        .seen
        .acknowledged
        .unwrap_or_else(|| panic!("{what}: the request was never pulled"));
    let report = &ran.report.stream;
    assert_eq!(report.stopped_in, Some(phase), "{what}: the report's phase");
    let split = ran.seen.targets.partition_point(|(t, _)| *t <= at);
    let (before, after) = ran.seen.targets.split_at(split);
    if case.request == Request::EStop {
        assert_eq!(report.outcome, Outcome::EStopped, "{what}");
        assert_eq!(after.len(), 0, "{what}: targets after the e-stop");
        return (phase, 0);
    }
    assert!(
        matches!(report.outcome, Outcome::Stopped | Outcome::Completed),
        "{what}: {:?}",
        report
    );
    let moving = before.len() >= 2;
    if !phase.moves() || before.is_empty() {
        assert_eq!(after.len(), 0, "{what}: targets after a stop at rest");
        return (phase, 0);
    }
    // Moving: each step no faster than the one before, starting with the last before the
    // acknowledgment (from rest, the first target's step from where the twin held).
    let mut last_step = if moving {
        step(&before[before.len() - 2].1, &before[before.len() - 1].1)
    } else {
        vec![0.0; job.settings.rig.dof()]
    };
    let mut previous = before[before.len() - 1].1.clone();
    let first_speed = speed(&job.settings, &last_step);
    for (i, (_, positions)) in after.iter().enumerate() {
        let now = step(&previous, positions);
        let (was, is) = (speed(&job.settings, &last_step), speed(&job.settings, &now));
        assert!(
            is <= was * (1.0 + SPEED_SLACK) + 1e-12,
            "{what}: target {i} after the stop moves at {is:.6} of the speed limit after {was:.6}"
        );
        last_step = now;
        previous = positions.clone();
    }
    // No further than braking needs: each axis' own fastest stop from its speed.
    let dt = job.settings.period().as_secs_f64();
    let first = if moving {
        step(&before[before.len() - 2].1, &before[before.len() - 1].1)
    } else {
        vec![0.0; job.settings.rig.dof()]
    };
    let alone = job
        .settings
        .rig
        .joints
        .iter()
        .zip(&first)
        .map(|(joint, d)| (d / dt).abs() / joint.limits.max_acceleration / dt)
        .fold(0.0, f64::max);
    assert!(
        (after.len() as f64) <= BRAKING_FACTOR * alone + BRAKING_EXTRA_CYCLES,
        "{what}: {} targets after the stop, braking from {first_speed:.4} of the speed limit needs about {alone:.0}",
        after.len()
    );
    (phase, after.len())
}

/// A case for `phase` on `job`, from `rng`.
fn case_for(rng: &mut impl Rng, job: &Job, phase: Phase, request: Request, wall: bool) -> Case {
    let cycles = if wall { WALL_CYCLES } else { job.samples };
    let mut case = Case {
        phase,
        after_calls: 1,
        request,
        down_at_start: 0,
        silent_at_start: 0,
        loss_after_targets: None,
        loss_calls: 0,
        wall,
    };
    match phase {
        Phase::WaitingForController => {
            case.down_at_start = rng.random_range(5..60);
            case.after_calls = rng.random_range(1..case.down_at_start);
        }
        Phase::WaitingForHold => {
            case.silent_at_start = rng.random_range(2..60);
            case.after_calls = rng.random_range(1..case.silent_at_start + 2);
        }
        Phase::Planning => {}
        Phase::Resuming => {
            case.loss_after_targets = Some(rng.random_range(20..cycles.min(2000)));
            case.loss_calls = rng.random_range(3..30);
            // The approach back to the path is short: stop early in it, sometimes first.
            case.after_calls = rng.random_range(1..12);
        }
        Phase::Streaming => {
            // Calls in the streaming phase: about two a cycle.
            case.after_calls = rng.random_range(1..2 * (cycles - 1));
            if rng.random_bool(0.2) {
                case.loss_after_targets = Some(rng.random_range(1..cycles));
                case.loss_calls = rng.random_range(3..30);
            }
        }
        // A case is drawn from PHASES: these three are passed through, never stopped in.
        Phase::Holding | Phase::Stopping | Phase::Ended => {
            unreachable!("{phase} is not among the phases a case is drawn from")
        }
    }
    case
}

#[test]
fn a_stop_or_estop_at_any_point_of_a_job_moves_nothing_but_a_slowing_ramp() {
    if !common::in_full_tier(
        "stop_phases::a_stop_or_estop_at_any_point_of_a_job_moves_nothing_but_a_slowing_ramp",
    ) {
        return;
    }
    let started = Instant::now();
    let jobs = [
        job("star", "config/rigbridge.toml"),
        job("paint", "config/paint-run.toml"),
        job("gait", "config/gait-run.toml"),
    ];
    let mut rng = common::rng(26);
    let mut hit = std::collections::BTreeMap::<&str, usize>::new();
    let mut ramps = Vec::new();
    for i in 0..STOPS + ESTOPS {
        let job = &jobs[i % jobs.len()];
        let request = if i < STOPS {
            Request::Stop
        } else {
            Request::EStop
        };
        let phase = PHASES[rng.random_range(0..PHASES.len())];
        let case = case_for(&mut rng, job, phase, request, i % WALL_EVERY == 0);
        let ran = run_case(job, case);
        let (acknowledged, after) = judge(job, &case, &ran);
        if request == Request::Stop {
            *hit.entry(acknowledged.name()).or_default() += 1;
            if acknowledged.moves() {
                ramps.push(after);
            }
        }
    }
    println!(
        "stop_phases: {STOPS} stops by phase acknowledged {hit:?}, ramps after a moving stop: max {} targets, {ESTOPS} e-stops; {:.1} s",
        ramps.iter().max().unwrap_or(&0),
        started.elapsed().as_secs_f64()
    );
    for phase in PHASES {
        assert!(
            hit.get(phase.name()).is_some_and(|n| *n > 0),
            "no stop acknowledged while {phase}: {hit:?}"
        );
    }
}
