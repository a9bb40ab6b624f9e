//! The shared half of the links that master a bus of devices from their own I/O thread
//! (the Dynamixel link's servos, the CANopen link's drives): the streamer's side of the
//! link (a bounded command queue, feedback handed over under a condition variable, events,
//! sessions and their adoption, the latched fault, the refusal of a target outside a
//! device's range) and the thread's loop that opens the bus, sets the devices up and runs
//! their cycles, again after every loss. Each protocol is one [`Device`]: how its bus
//! opens, how its devices are set up and how one cycle goes.
//!
//! It owns the queue, the session count and the hand-over; it must not know a protocol's
//! bytes or set-up (its `Device` does), nor plan or check speeds (the streamer's gate does).

use crate::device::dynamixel::wire::AxisTicks;
use crate::link::{Link, LinkCounters, LinkError, LinkEvent};
use crate::protocol::codec::{EncodeError, FaultReport};
use crate::protocol::{AxisValues, Command, ControllerStatus, Fault, Feedback, MAX_AXES};
use crate::transport::Backoff;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// How often the I/O thread wakes without commands to notice the link was dropped.
const POLL: Duration = Duration::from_millis(50);
/// Commands waiting for the bus: the streamer sends one a cycle and waits for its answer.
const QUEUE_CAPACITY: usize = 16;

/// One target per axis in the devices' own units (ticks, counts).
pub type Units = [i32; MAX_AXES];

/// What a queued command does on the bus.
#[derive(Debug, Clone, Copy)]
pub enum Job {
    /// Write these targets, then run a cycle; the target's seq.
    Targets(u32, Units),
    /// A cycle that writes nothing; true for Stop (the devices hold their targets).
    Cycle { holding: bool },
    /// Stop every device where it is, and latch the e-stop.
    EStop,
    /// Clear a latched fault if the devices report none.
    Reset,
}

/// Why a set-up or a cycle could not go on.
#[derive(Debug)]
pub enum BusError {
    /// The transport failed or a device did not answer: reopen and set up again.
    Lost(String),
    /// A device refused or reported an error: latch a fault on this axis.
    Drive { axis: usize, text: String },
}

/// What the streamer's side and the I/O thread share, under one lock.
pub struct State {
    pub queue: VecDeque<Job>,
    pub up: bool,
    pub sessions: u64,
    adopted: u64,
    pub feedback: Option<Feedback>,
    generation: u64,
    pub events: VecDeque<LinkEvent>,
    pub counters: LinkCounters,
    pub latched: Option<Fault>,
    /// Each axis' target range in device units, known once its device is set up.
    ranges: Vec<(i64, i64)>,
    restart: bool,
    /// Why the last open or set-up failed, for people reading a timeout.
    problem: Option<String>,
}

/// A bus of devices, one per axis, driven from the link's I/O thread.
pub trait Device: Send + Sync + Sized + 'static {
    /// The bus as one session holds it: its port or socket, and what it heard.
    type Bus;
    /// What a set-up hands the cycles: each axis' target range and present position.
    type Start;
    /// The protocol as messages name it.
    const NAME: &'static str;
    /// What a target's value is called on the wire, and the range it must fit.
    const TARGET_FIELD: &'static str;
    const TARGET_RANGE: &'static str;

    /// Each axis' map between radians and device units, in axis order.
    fn axes(&self) -> &[AxisTicks];
    fn open(&self) -> Result<Self::Bus, BusError>;
    /// Sets the devices up, from whatever state they are in.
    fn set_up(&self, bus: &mut Self::Bus, hub: &Hub<Self>) -> Result<Self::Start, BusError>;
    /// Begins the session ([`Hub::begin_session`]) and runs cycles until loss, a Reset that
    /// needs a new set-up, or the link is dropped.
    fn run(&self, bus: &mut Self::Bus, hub: &Hub<Self>, start: Self::Start);
    /// How many targets before the one a cycle's feedback echoes its positions were
    /// measured against ([`Link::measured_cycles_behind`]).
    const MEASURED_CYCLES_BEHIND: u32 = 0;
    /// Latches `fault` with `text` (every one, by default).
    fn latch(hub: &Hub<Self>, fault: Fault, text: &str) {
        hub.latch(fault, text);
    }
}

/// The shared state, the two wake-ups and the device.
pub struct Hub<D> {
    state: Mutex<State>,
    /// Feedback arrived (for the streamer).
    feedback: Condvar,
    /// A command arrived (for the I/O thread).
    command: Condvar,
    closed: AtomicBool,
    pub device: D,
}

/// The link the streamer holds: one per bus, its I/O thread joined when dropped.
pub struct DeviceLink<D> {
    hub: Arc<Hub<D>>,
    seen: u64,
    description: String,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// `ids` as a link address lists them: `1,2,3`.
pub fn id_list(ids: &[u8]) -> String {
    ids.iter().map(u8::to_string).collect::<Vec<_>>().join(",")
}

/// Starts the I/O thread `thread`, which opens the bus and sets the devices up in the
/// background (and again after every loss).
pub fn start<D: Device>(
    device: D,
    description: String,
    thread: &str,
) -> Result<DeviceLink<D>, LinkError> {
    let hub = Arc::new(Hub {
        state: Mutex::new(State {
            queue: VecDeque::with_capacity(QUEUE_CAPACITY),
            up: false,
            sessions: 0,
            adopted: 0,
            feedback: None,
            generation: 0,
            events: VecDeque::new(),
            counters: LinkCounters::default(),
            latched: None,
            ranges: Vec::new(),
            restart: false,
            problem: None,
        }),
        feedback: Condvar::new(),
        command: Condvar::new(),
        closed: AtomicBool::new(false),
        device,
    });
    let io = hub.clone();
    let thread = crate::link::spawn_io_thread(thread, move || keep_open(&io))?;
    Ok(DeviceLink {
        hub,
        seen: 0,
        description,
        thread: Some(thread),
    })
}

/// Opens, sets up and runs the bus until the link is dropped, again after every loss.
fn keep_open<D: Device>(hub: &Hub<D>) {
    let mut backoff = Backoff::default();
    while !hub.closed() {
        let mut bus = match hub.device.open() {
            Ok(bus) => bus,
            Err(BusError::Lost(problem) | BusError::Drive { text: problem, .. }) => {
                hub.lock().problem = Some(problem);
                std::thread::sleep(backoff.next_wait());
                continue;
            }
        };
        match hub.device.set_up(&mut bus, hub) {
            Ok(start) => {
                backoff.reset();
                hub.device.run(&mut bus, hub, start);
            }
            Err(BusError::Drive { axis, text }) => {
                D::latch(hub, Fault::Drive { axis: axis as u8 }, &text);
                hub.lock().problem = Some(text);
                hub.wait_for_reset();
            }
            Err(BusError::Lost(problem)) => {
                hub.lock().problem = Some(problem);
                std::thread::sleep(backoff.next_wait());
            }
        }
        let mut state = hub.lock();
        state.up = false;
        state.queue.clear();
    }
}

/// The link was dropped or asked to restart: the cycles end.
#[derive(Debug)]
pub struct Stopped;

impl<D: Device> Hub<D> {
    pub fn lock(&self) -> MutexGuard<'_, State> {
        // A panicking holder leaves plain data behind: keep using it.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub fn closed(&self) -> bool {
        self.closed.load(Ordering::SeqCst)
    }

    /// Publishes a new session: each axis' target range, and the first feedback at the
    /// devices' `present` units: holding, or the fault `fault` names (latched before any
    /// feedback may say holding).
    pub fn begin_session(
        &self,
        ranges: Vec<(i64, i64)>,
        present: &[i32],
        fault: Option<(usize, String)>,
    ) {
        let positions = self.radians(present);
        let mut state = self.lock();
        state.ranges = ranges;
        state.up = true;
        state.sessions += 1;
        state.counters.reconnects = state.sessions - 1;
        state.latched = None;
        state.restart = false;
        state.queue.clear();
        state.problem = None;
        let status = match fault {
            Some((axis, text)) => {
                let fault = Fault::Drive { axis: axis as u8 };
                state.latched = Some(fault);
                state
                    .events
                    .push_back(LinkEvent::Fault(FaultReport { fault, text }));
                ControllerStatus::Fault(fault)
            }
            None => ControllerStatus::Holding,
        };
        self.publish(
            &mut state,
            Feedback {
                seq: 0,
                positions,
                status,
            },
        );
    }

    /// A cycle's feedback: the devices at `units`, echoing `seq`; its status the latched
    /// fault, else holding when `at_rest` (holding, and on the targets last written).
    pub fn publish_cycle(&self, seq: u32, units: &[i32], at_rest: bool) {
        let positions = self.radians(units);
        let mut state = self.lock();
        let status = match state.latched {
            Some(fault) => ControllerStatus::Fault(fault),
            None if at_rest => ControllerStatus::Holding,
            None => ControllerStatus::Ok,
        };
        self.publish(
            &mut state,
            Feedback {
                seq,
                positions,
                status,
            },
        );
    }

    fn publish(&self, state: &mut State, feedback: Feedback) {
        state.feedback = Some(feedback);
        state.generation += 1;
        self.feedback.notify_all();
    }

    fn radians(&self, units: &[i32]) -> AxisValues {
        let values: Vec<f64> = self
            .device
            .axes()
            .iter()
            .zip(units)
            .map(|(axis, &u)| axis.radians(i64::from(u)))
            .collect();
        AxisValues::from_slice(&values).unwrap_or(AxisValues::zeros(0))
    }

    /// Latches `fault` with `text`, as an event the streamer reads with its words.
    pub fn latch(&self, fault: Fault, text: &str) {
        let mut state = self.lock();
        state.latched = Some(fault);
        state.events.push_back(LinkEvent::Fault(FaultReport {
            fault,
            text: text.to_string(),
        }));
    }

    /// After a fault at set-up: nothing moves until a Reset (or the link is dropped).
    fn wait_for_reset(&self) {
        let mut state = self.lock();
        while !self.closed() {
            if let Some(index) = state.queue.iter().position(|j| matches!(j, Job::Reset)) {
                state.queue.drain(..=index);
                return;
            }
            state.queue.clear();
            state = self
                .command
                .wait_timeout(state, POLL)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    /// The next command; `Ok(None)` once `idle` has passed without one (never when it is
    /// `None`), `Err(Stopped)` when the link was dropped or asked to restart.
    pub fn next_job(&self, idle: Option<Instant>) -> Result<Option<Job>, Stopped> {
        let mut state = self.lock();
        loop {
            if self.closed() || state.restart {
                return Err(Stopped);
            }
            if let Some(job) = state.queue.pop_front() {
                return Ok(Some(job));
            }
            let mut wait = POLL;
            if let Some(idle) = idle {
                let now = Instant::now();
                if now >= idle {
                    return Ok(None);
                }
                wait = wait.min(idle - now);
            }
            state = self
                .command
                .wait_timeout(state, wait)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    /// The targets of `positions` in device units, or the first axis whose value is
    /// outside its device's range (never clamped).
    fn units(&self, state: &State, positions: &[f64]) -> Result<Units, EncodeError> {
        let mut units = [0i32; MAX_AXES];
        for (axis, (map, &rad)) in self.device.axes().iter().zip(positions).enumerate() {
            let unit = map.tick(rad);
            let (low, high) = state.ranges.get(axis).copied().unwrap_or((0, -1));
            if !unit.is_finite() || unit < low as f64 || unit > high as f64 {
                return Err(EncodeError::OutOfRange {
                    field: D::TARGET_FIELD,
                    value: unit,
                    range: D::TARGET_RANGE,
                });
            }
            units[axis] = unit as i32;
        }
        Ok(units)
    }
}

impl<D> Drop for DeviceLink<D> {
    fn drop(&mut self) {
        self.hub.closed.store(true, Ordering::SeqCst);
        self.hub.command.notify_all();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl<D: Device> DeviceLink<D> {
    /// Why the last open or set-up of the bus failed, if one did.
    pub fn problem(&self) -> Option<String> {
        self.hub.lock().problem.clone()
    }

    pub fn device(&self) -> &D {
        &self.hub.device
    }

    fn push(&mut self, job: Job) -> Result<(), LinkError> {
        let mut state = self.hub.lock();
        if state.queue.len() >= QUEUE_CAPACITY {
            return Err(LinkError::Io(std::io::Error::other(format!(
                "{} command queue full: the bus is behind the streamer",
                D::NAME
            ))));
        }
        if matches!(job, Job::EStop | Job::Cycle { holding: true }) {
            // Targets planned before a Stop or EStop are stale: never sent.
            state.queue.retain(|j| !matches!(j, Job::Targets(..)));
        }
        state.queue.push_back(job);
        drop(state);
        self.hub.command.notify_all();
        Ok(())
    }
}

impl<D: Device> Link for DeviceLink<D> {
    fn send(&mut self, command: &Command) -> Result<(), LinkError> {
        match command {
            Command::Target(target) => {
                let state = self.hub.lock();
                // A target for another session (planned before the devices were set up
                // anew), or while a fault is latched, is never written.
                if !state.up || state.sessions != state.adopted || state.latched.is_some() {
                    return Ok(());
                }
                let units = self.hub.units(&state, target.positions.as_slice());
                drop(state);
                match units {
                    Ok(units) => self.push(Job::Targets(target.seq, units)),
                    Err(e) => {
                        self.hub.lock().events.push_back(LinkEvent::EncodeFailed(e));
                        Ok(())
                    }
                }
            }
            Command::Stop => self.push(Job::Cycle { holding: true }),
            Command::EStop => self.push(Job::EStop),
            Command::Reset => self.push(Job::Reset),
            Command::Heartbeat => {
                self.adopt_session();
                self.push(Job::Cycle { holding: false })
            }
        }
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Feedback>, LinkError> {
        let deadline = Instant::now() + timeout;
        let mut state = self.hub.lock();
        loop {
            if state.generation > self.seen {
                self.seen = state.generation;
                return Ok(state.feedback);
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            state = self
                .hub
                .feedback
                .wait_timeout(state, deadline - now)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    fn counters(&self) -> LinkCounters {
        self.hub.lock().counters
    }

    fn describe(&self) -> String {
        self.description.clone()
    }

    fn is_up(&self) -> bool {
        self.hub.lock().up
    }

    fn drain(&mut self) {
        self.seen = self.hub.lock().generation;
    }

    fn next_event(&mut self) -> Option<LinkEvent> {
        self.hub.lock().events.pop_front()
    }

    fn sessions(&self) -> u64 {
        self.hub.lock().sessions
    }

    fn measured_cycles_behind(&self) -> u32 {
        D::MEASURED_CYCLES_BEHIND
    }

    fn down_reason(&self) -> Option<String> {
        self.problem()
    }

    fn restart(&mut self) {
        self.hub.lock().restart = true;
        self.hub.command.notify_all();
    }

    fn adopt_session(&mut self) {
        let mut state = self.hub.lock();
        state.adopted = state.sessions;
    }
}
