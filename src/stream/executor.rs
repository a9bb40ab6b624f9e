//! The shared executor: the cycles of many streams (one per cell of `serve`) on a small
//! fixed pool of real-time threads, each driven by one timer, instead of a thread per stream
//! that sleeps and spins before every deadline of its own. Streams that share a period are
//! grouped on a common grid of deadlines, in a few slots spread over the period, so one
//! wake serves a slot's streams and the slots' work does not pile up at one instant.
//!
//! Ordering, so that one stream's overrun never delays another's safety gate: at every wake
//! the first halves of all due cycles run (stall check, gate, send), then the second halves
//! (feedback, following checks, sink) one at a time, each time after any first half that
//! fell due meanwhile. A cycle whose work (both halves) exceeds its budget, a tenth of its
//! period, is counted (`overruns`, in its report and its cell's status); after three such
//! cycles in a row the stream is handed back to the thread that submitted it, which runs
//! the rest of it on its own clock-driven loop: its neighbours keep their deadlines.
//!
//! A worker sleeps until a spin before its next deadline, then spins; the spin follows how
//! late this machine's timer ends its sleeps (the 99th percentile of the last 2,000), within
//! 10 to 150 us. Its threads keep to the CPUs the settings give, if any.
//!
//! The executor owns the timing of the cycles it runs, never what a cycle does: that is the
//! stream's ([`CycleTask`]). Between submission and end it neither allocates nor blocks in a
//! cycle (a submission waits in a queue the worker only `try_lock`s).

use super::StreamError;
use super::raise_priority;
use crate::clock::{Clock, WallClock};
use std::any::Any;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::{JoinHandle, Thread};
use std::time::Duration;

/// A cycle's work (both halves) beyond this share of its period is an overrun: at a tenth,
/// the jitter its neighbours may see, it would already spend their whole margin.
const OVERRUN_SHARE: f64 = 0.1;
/// Overruns in a row that hand a stream back: one is a hiccup (a page fault, a lock a
/// reader held) that a thread of its own would suffer as well; three are a slow stream.
const OVERRUNS_TO_HAND_BACK: u32 = 3;
/// Slots a period is split into at most, and their least spacing: streams of one slot wake
/// together; more slots spread the work, fewer cost fewer wakes.
const MAX_SLOTS: u32 = 16;
const MIN_SLOT_SPACING: Duration = Duration::from_micros(250);
/// A slot takes streams while their measured work stays within this share of the period
/// (half the 10 % jitter target: the rest is for the wake itself).
const SLOT_SHARE: f64 = 0.05;
/// The work of one cycle assumed before any was measured (a loopback cycle takes a few us).
const FIRST_COST: Duration = Duration::from_micros(10);
/// Weight of the newest measurement in the running mean of a cycle's work.
const COST_WEIGHT: f64 = 1.0 / 64.0;
/// How long an idle worker sleeps between looks at its queue (a submission wakes it anyway).
const IDLE_WAIT: Duration = Duration::from_millis(100);
/// How often a waiting submitter checks that the worker is still alive.
const SUBMITTER_CHECK: Duration = Duration::from_millis(100);
/// A new stream's first deadline lies at least this far ahead, so its first wake is on time.
const FIRST_LEAD: Duration = Duration::from_micros(500);
/// Streams a worker keeps room for before it must grow its list (registration only).
const EXPECTED_STREAMS: usize = 256;

/// One stream's cycle, split in the two halves the executor orders (see the module doc).
pub trait CycleTask: Send {
    fn period(&self) -> Duration;
    /// The wake `late` after the deadline, events, the gate and the send; true once ended.
    fn send_half(&mut self, late: Duration) -> bool;
    /// The feedback of what was sent, the following checks; true once ended.
    fn receive_half(&mut self) -> bool;
    /// Counts an overrun of the cycle's work budget.
    fn overran(&mut self);
}

/// How a stream left the executor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Handback {
    Ended,
    /// It overran its budget: the caller runs it on from `next_deadline` (executor clock).
    Evicted {
        next_deadline: Duration,
    },
}

/// How many threads, how long they spin before a deadline at first, and where they run.
#[derive(Debug, Clone, PartialEq)]
pub struct ExecutorSettings {
    pub threads: usize,
    /// The last stretch before a deadline is spun rather than slept, to begin with: a
    /// real-time thread with no timer slack wakes within tens of microseconds, so less than
    /// the 150 us a thread per stream spins at normal priority. Each worker then sets its
    /// spin from how late its own sleeps end (see [`WakeLateness`]).
    pub spin: Duration,
    /// The CPUs the workers keep to, one each in order (`realtime::reserved_cpus`); empty
    /// leaves them where the scheduler puts them. Keeping the process's other threads off
    /// these CPUs is the caller's part.
    pub cpus: Vec<usize>,
}

impl Default for ExecutorSettings {
    fn default() -> Self {
        ExecutorSettings {
            threads: 1,
            spin: Duration::from_micros(50),
            cpus: Vec::new(),
        }
    }
}

/// The spin covers this share of a worker's timed sleeps: how late they end is the
/// machine's (tens of microseconds in this VM, whose halted CPU the host must wake; a few
/// on bare metal with a real-time kernel), and a wake later than the spin is jitter for
/// every stream of its slot.
const SPIN_COVERS: f64 = 0.99;
/// Added to that quantile: the bins' width, and the first half of the slot's first stream.
const SPIN_MARGIN: Duration = Duration::from_micros(10);
/// The spin's bounds: below the floor a sleep's end is never that early anyway; above the
/// ceiling (a thread per stream's spin) spinning costs more CPU than the rare late wake it
/// would save, and such wakes are the machine's stalls, not its timer.
const MIN_SPIN: Duration = Duration::from_micros(10);
const MAX_SPIN: Duration = Duration::from_micros(150);
/// Sleeps per estimate: at 1 kHz two seconds, enough for the 20 latest to set a 99 % quantile.
const WAKES_PER_ESTIMATE: u32 = 2000;
const WAKE_BIN: Duration = Duration::from_micros(5);
/// Bins up to the ceiling, the last one holding every later wake.
const WAKE_BINS: usize = (MAX_SPIN.as_micros() / WAKE_BIN.as_micros()) as usize + 1;

const RUNNING: u8 = 0;
const ENDED: u8 = 1;
const EVICTED: u8 = 2;
const PANICKED: u8 = 3;

/// Where a worker tells the submitter how its stream left.
struct Handoff {
    state: AtomicU8,
    next_deadline_ns: AtomicU64,
    panic: Mutex<Option<Box<dyn Any + Send>>>,
    submitter: Thread,
}

impl Handoff {
    fn settle(&self, state: u8) {
        self.state.store(state, Ordering::Release);
        self.submitter.unpark();
    }
}

/// A submitted stream, borrowed from its submitter's stack for as long as it runs here.
struct TaskPtr(*mut (dyn CycleTask + 'static));

// SAFETY: the pointee is a `CycleTask`, so `Send`; the submitter does not touch it while
// the executor holds this pointer (it waits until the handoff settles), so access is unique.
unsafe impl Send for TaskPtr {}

struct Entry {
    task: TaskPtr,
    handoff: Arc<Handoff>,
    period: Duration,
    budget: Duration,
    slot: u32,
    deadline: Duration,
    /// The first half ran this cycle; the second is due.
    sent: bool,
    work: Duration,
    /// Overruns in a row, up to this cycle.
    overruns: u32,
    /// The handoff is settled: the task is the submitter's again and must not be touched
    /// (kept here too, so scans need not read the shared state).
    done: bool,
}

impl Entry {
    fn settle(&mut self, state: u8) {
        self.done = true;
        self.handoff.settle(state);
    }
}

/// A worker's side shared with submitters.
struct Inbox {
    queue: Mutex<Vec<Entry>>,
    thread: Mutex<Option<Thread>>,
    streams: AtomicUsize,
    alive: AtomicBool,
    stop: AtomicBool,
}

impl Inbox {
    fn wake(&self) {
        if let Some(thread) = &*self.thread.lock().unwrap_or_else(PoisonError::into_inner) {
            thread.unpark();
        }
    }
}

pub struct Executor {
    clock: Arc<WallClock>,
    inboxes: Vec<Arc<Inbox>>,
    workers: Vec<JoinHandle<()>>,
    realtime: Arc<AtomicUsize>,
}

impl Executor {
    /// Starts `settings.threads` worker threads (at least one); returns once each has asked
    /// for its priority.
    pub fn new(settings: ExecutorSettings) -> std::io::Result<Executor> {
        let clock = Arc::new(WallClock::new());
        let realtime = Arc::new(AtomicUsize::new(0));
        let (started_tx, started) = std::sync::mpsc::channel::<()>();
        let mut inboxes = Vec::new();
        let mut workers = Vec::new();
        for index in 0..settings.threads.max(1) {
            let inbox = Arc::new(Inbox {
                queue: Mutex::new(Vec::with_capacity(EXPECTED_STREAMS)),
                thread: Mutex::new(None),
                streams: AtomicUsize::new(0),
                alive: AtomicBool::new(true),
                stop: AtomicBool::new(false),
            });
            let worker = Worker {
                inbox: inbox.clone(),
                clock: clock.clone(),
                spin: settings.spin,
                wakes: WakeLateness::default(),
                cost: FIRST_COST,
            };
            let cpu = settings.cpus.get(index).copied();
            let realtime = realtime.clone();
            let started_tx = started_tx.clone();
            let handle = std::thread::Builder::new()
                .name(format!("rigbridge-executor-{index}"))
                .spawn(move || {
                    if raise_priority(crate::realtime::CYCLE_PRIORITY).is_ok() {
                        realtime.fetch_add(1, Ordering::SeqCst);
                    }
                    if let Some(cpu) = cpu {
                        // Unpinned, the worker still runs; only its wakes are less sure.
                        let _ = crate::realtime::pin_to(cpu);
                    }
                    no_timer_slack();
                    let _ = started_tx.send(());
                    worker.run();
                })?;
            *inbox.thread.lock().unwrap_or_else(PoisonError::into_inner) =
                Some(handle.thread().clone());
            inboxes.push(inbox);
            workers.push(handle);
        }
        for _ in 0..workers.len() {
            let _ = started.recv();
        }
        Ok(Executor {
            clock,
            inboxes,
            workers,
            realtime,
        })
    }

    /// The clock the executor's deadlines are on.
    pub fn clock(&self) -> &WallClock {
        &self.clock
    }

    pub fn threads(&self) -> usize {
        self.workers.len()
    }

    /// How many worker threads got real-time priority (SCHED_FIFO needs CAP_SYS_NICE).
    pub fn realtime_threads(&self) -> usize {
        self.realtime.load(Ordering::SeqCst)
    }

    /// Runs `task`'s cycles on the least loaded worker until it ends or is handed back;
    /// the calling thread waits meanwhile. A panic in the task is resumed here.
    pub fn run(&self, task: &mut (dyn CycleTask + '_)) -> Result<Handback, StreamError> {
        let Some(inbox) = self
            .inboxes
            .iter()
            .min_by_key(|inbox| inbox.streams.load(Ordering::SeqCst))
        else {
            return Err(StreamError::ExecutorStopped);
        };
        let period = task.period();
        let handoff = Arc::new(Handoff {
            state: AtomicU8::new(RUNNING),
            next_deadline_ns: AtomicU64::new(0),
            panic: Mutex::new(None),
            submitter: std::thread::current(),
        });
        let pointer: *mut (dyn CycleTask + '_) = task;
        // SAFETY: only the lifetime is erased. This function does not return before the
        // worker settles the handoff, after which the worker never touches the task again
        // (or before the worker is gone, which ends its use of it just as well); nothing in
        // the wait below can unwind.
        let pointer: *mut (dyn CycleTask + 'static) = unsafe { std::mem::transmute(pointer) };
        inbox.streams.fetch_add(1, Ordering::SeqCst);
        inbox
            .queue
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(Entry {
                task: TaskPtr(pointer),
                handoff: handoff.clone(),
                period,
                budget: period.mul_f64(OVERRUN_SHARE),
                slot: 0,
                deadline: Duration::ZERO,
                sent: false,
                work: Duration::ZERO,
                overruns: 0,
                done: false,
            });
        inbox.wake();
        loop {
            match handoff.state.load(Ordering::Acquire) {
                RUNNING if inbox.alive.load(Ordering::SeqCst) => {
                    std::thread::park_timeout(SUBMITTER_CHECK);
                }
                RUNNING => return Err(StreamError::ExecutorStopped),
                ENDED => return Ok(Handback::Ended),
                EVICTED => {
                    let ns = handoff.next_deadline_ns.load(Ordering::SeqCst);
                    return Ok(Handback::Evicted {
                        next_deadline: Duration::from_nanos(ns),
                    });
                }
                _ => {
                    let payload = handoff
                        .panic
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .take();
                    std::panic::resume_unwind(
                        payload.unwrap_or_else(|| Box::new("a stream panicked")),
                    );
                }
            }
        }
    }
}

/// Stops the workers once every stream they run has ended.
impl Drop for Executor {
    fn drop(&mut self) {
        for inbox in &self.inboxes {
            inbox.stop.store(true, Ordering::SeqCst);
            inbox.wake();
        }
        for worker in self.workers.drain(..) {
            let _ = worker.join();
        }
    }
}

/// A real-time thread gets no timer slack anyway; a normal one would wake up to 50 us late.
fn no_timer_slack() {
    // SAFETY: PR_SET_TIMERSLACK takes one integer argument and changes only this thread.
    unsafe {
        let slack_ns: libc::c_ulong = 1;
        libc::prctl(libc::PR_SET_TIMERSLACK, slack_ns);
    }
}

/// Marks the worker gone however it ends, so no submitter waits for it forever.
struct Alive(Arc<Inbox>);

impl Drop for Alive {
    fn drop(&mut self) {
        self.0.alive.store(false, Ordering::SeqCst);
    }
}

struct Worker {
    inbox: Arc<Inbox>,
    clock: Arc<WallClock>,
    spin: Duration,
    wakes: WakeLateness,
    /// Running mean of one cycle's work, for filling slots.
    cost: Duration,
}

impl Worker {
    fn run(mut self) {
        let _alive = Alive(self.inbox.clone());
        let mut entries: Vec<Entry> = Vec::with_capacity(EXPECTED_STREAMS);
        loop {
            self.adopt(&mut entries);
            if entries.is_empty() {
                if self.inbox.stop.load(Ordering::SeqCst) && self.queue_empty() {
                    return;
                }
                std::thread::park_timeout(IDLE_WAIT);
                continue;
            }
            let ran = self.first_halves(&mut entries) | self.one_second_half(&mut entries);
            self.release_ended(&mut entries);
            if !ran {
                self.wait_for_next(&entries);
            }
        }
    }

    fn queue_empty(&self) -> bool {
        self.inbox
            .queue
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .is_empty()
    }

    /// Takes the submitted streams, if the queue is free this instant, and gives each its
    /// slot and first deadline.
    fn adopt(&mut self, entries: &mut Vec<Entry>) {
        let Ok(mut queue) = self.inbox.queue.try_lock() else {
            return;
        };
        for mut entry in queue.drain(..) {
            let slots = slots_per_period(entry.period);
            entry.slot = self.choose_slot(entries, entry.period, slots);
            let offset = entry.period / slots * entry.slot;
            entry.deadline = first_deadline(self.clock.now() + FIRST_LEAD, entry.period, offset);
            entries.push(entry);
        }
    }

    /// The first slot of the period with room for one more stream's measured work, else
    /// the emptiest: a slot is woken once for all its streams.
    fn choose_slot(&self, entries: &[Entry], period: Duration, slots: u32) -> u32 {
        let mut count = [0u32; MAX_SLOTS as usize];
        for entry in entries.iter().filter(|e| e.period == period) {
            count[entry.slot as usize] += 1;
        }
        let room = (period.mul_f64(SLOT_SHARE).as_nanos() / self.cost.as_nanos().max(1)).max(1);
        let used = &count[..slots as usize];
        (0..slots)
            .find(|&slot| u128::from(used[slot as usize]) < room)
            .or_else(|| (0..slots).min_by_key(|&slot| used[slot as usize]))
            .unwrap_or(0)
    }

    /// The first half of every cycle due when the pass starts, in the order the streams
    /// came; each one's lateness is read as it starts.
    fn first_halves(&mut self, entries: &mut [Entry]) -> bool {
        let mut ran = false;
        let due = self.clock.now();
        for entry in entries.iter_mut() {
            if entry.sent || entry.done || entry.deadline > due {
                continue;
            }
            ran = true;
            let start = self.clock.now();
            let late = start.saturating_sub(entry.deadline);
            let ended = guarded(entry, |task| task.send_half(late));
            entry.work = self.clock.now().saturating_sub(start);
            entry.sent = true;
            if ended && !entry.done {
                entry.settle(ENDED);
            }
        }
        ran
    }

    /// The second half of the earliest sent cycle; then its budget is judged.
    fn one_second_half(&mut self, entries: &mut [Entry]) -> bool {
        let Some(entry) = entries
            .iter_mut()
            .filter(|e| e.sent && !e.done)
            .min_by_key(|e| e.deadline)
        else {
            return false;
        };
        let start = self.clock.now();
        let ended = guarded(entry, |task| task.receive_half());
        entry.work += self.clock.now().saturating_sub(start);
        entry.sent = false;
        entry.deadline += entry.period;
        self.cost = self.cost.mul_f64(1.0 - COST_WEIGHT) + entry.work.mul_f64(COST_WEIGHT);
        if entry.done {
            return true;
        }
        if ended {
            entry.settle(ENDED);
        } else if entry.work <= entry.budget {
            entry.overruns = 0;
        } else {
            entry.overruns += 1;
            guarded(entry, |task| {
                task.overran();
                false
            });
            if !entry.done && entry.overruns >= OVERRUNS_TO_HAND_BACK {
                let ns = u64::try_from(entry.deadline.as_nanos()).unwrap_or(u64::MAX);
                entry.handoff.next_deadline_ns.store(ns, Ordering::SeqCst);
                entry.settle(EVICTED);
            }
        }
        true
    }

    /// Drops the entries whose stream has left; their submitters were told.
    fn release_ended(&self, entries: &mut Vec<Entry>) {
        let before = entries.len();
        entries.retain(|entry| !entry.done);
        let gone = before - entries.len();
        if gone > 0 {
            self.inbox.streams.fetch_sub(gone, Ordering::SeqCst);
        }
    }

    /// Sleeps to the spin margin before the next deadline, then spins to it. A submission
    /// unparks the thread early; the loop then looks again. A sleep that ran its course
    /// tells how late this machine's timer wakes the thread, which sets the spin.
    fn wait_for_next(&mut self, entries: &[Entry]) {
        let Some(next) = entries.iter().map(|e| e.deadline).min() else {
            return;
        };
        let now = self.clock.now();
        if next > now + self.spin {
            let wake = next - self.spin;
            std::thread::park_timeout(wake - now);
            let woke = self.clock.now();
            if woke >= wake
                && let Some(spin) = self.wakes.record(woke - wake)
            {
                self.spin = spin;
            }
            return;
        }
        while self.clock.now() < next {
            std::hint::spin_loop();
        }
    }
}

/// How late a worker's timed sleeps end, over the last [`WAKES_PER_ESTIMATE`] of them, in
/// [`WAKE_BIN`] bins; every so many, the spin that covers [`SPIN_COVERS`] of them.
struct WakeLateness {
    bins: [u32; WAKE_BINS],
    wakes: u32,
}

impl Default for WakeLateness {
    fn default() -> Self {
        WakeLateness {
            bins: [0; WAKE_BINS],
            wakes: 0,
        }
    }
}

impl WakeLateness {
    /// Counts one sleep that ended `late` after it was due; once the estimate is complete,
    /// the new spin (and the count starts over, so the spin follows the machine's load).
    fn record(&mut self, late: Duration) -> Option<Duration> {
        let bin = usize::try_from(late.as_nanos() / WAKE_BIN.as_nanos()).unwrap_or(usize::MAX);
        self.bins[bin.min(WAKE_BINS - 1)] += 1;
        self.wakes += 1;
        if self.wakes < WAKES_PER_ESTIMATE {
            return None;
        }
        let covered = (f64::from(self.wakes) * SPIN_COVERS).ceil() as u32;
        let mut seen = 0;
        let mut quantile = MAX_SPIN;
        for (index, count) in self.bins.iter().enumerate() {
            seen += count;
            if seen >= covered {
                // The bin's upper edge: every wake counted in it was at most that late.
                quantile = WAKE_BIN * (index as u32 + 1);
                break;
            }
        }
        *self = WakeLateness::default();
        Some((quantile + SPIN_MARGIN).clamp(MIN_SPIN, MAX_SPIN))
    }
}

/// Runs `work` on the entry's task; a panic settles the handoff with it, for the submitter
/// to resume, and counts as the end of the stream here.
fn guarded(entry: &mut Entry, work: impl FnOnce(&mut dyn CycleTask) -> bool) -> bool {
    // SAFETY: the submitter waits, without touching the task, until the handoff settles;
    // it has not (callers skip `done` entries), so this is the only access.
    let task = unsafe { &mut *entry.task.0 };
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| work(task))) {
        Ok(ended) => ended,
        Err(payload) => {
            *entry
                .handoff
                .panic
                .lock()
                .unwrap_or_else(PoisonError::into_inner) = Some(payload);
            entry.settle(PANICKED);
            false
        }
    }
}

fn slots_per_period(period: Duration) -> u32 {
    let fit = period.as_nanos() / MIN_SLOT_SPACING.as_nanos();
    u32::try_from(fit).unwrap_or(MAX_SLOTS).clamp(1, MAX_SLOTS)
}

/// The first deadline at or after `earliest` on the grid `k x period + offset`: streams of
/// one period share the grid whenever they start.
fn first_deadline(earliest: Duration, period: Duration, offset: Duration) -> Duration {
    let period_ns = period.as_nanos().max(1);
    let from = earliest.saturating_sub(offset).as_nanos();
    let k = from.div_ceil(period_ns);
    let ns = u64::try_from(k * period_ns).unwrap_or(u64::MAX);
    Duration::from_nanos(ns) + offset
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deadlines_of_a_period_share_one_grid() {
        let period = Duration::from_millis(4);
        let offset = Duration::from_micros(500);
        let first = first_deadline(Duration::from_micros(9_100), period, offset);
        assert_eq!(first, Duration::from_micros(12_500));
        let on_grid = first_deadline(Duration::from_micros(8_500), period, offset);
        assert_eq!(on_grid, Duration::from_micros(8_500));
    }

    /// Feeds `late` wakes: most at `usual`, the rest (`rare` of them) at `outlier`.
    fn estimate(usual: Duration, outlier: Duration, rare: u32) -> Option<Duration> {
        let mut wakes = WakeLateness::default();
        let mut spin = None;
        for k in 0..WAKES_PER_ESTIMATE {
            let late = if k < rare { outlier } else { usual };
            spin = wakes.record(late);
            assert!(
                spin.is_none() || k == WAKES_PER_ESTIMATE - 1,
                "an estimate before the count was complete, at wake {k}"
            );
        }
        spin
    }

    #[test]
    fn the_spin_covers_the_latest_but_one_percent_of_wakes() {
        let us = Duration::from_micros;
        // 1 % at 300 us: the spin covers the other 99 %, 42 us (the 40-45 us bin) + 10 us.
        assert_eq!(estimate(us(42), us(300), 20), Some(us(55)));
        // 2 % that late: the quantile is among them, beyond the ceiling.
        assert_eq!(estimate(us(42), us(300), 40), Some(MAX_SPIN));
        // A machine that wakes on time: the floor.
        assert_eq!(estimate(us(0), us(0), 0), Some(us(15)));
    }

    #[test]
    fn the_estimate_starts_over() {
        let mut wakes = WakeLateness::default();
        for _ in 0..WAKES_PER_ESTIMATE {
            wakes.record(Duration::from_micros(140));
        }
        assert_eq!(wakes.wakes, 0);
        assert!(wakes.bins.iter().all(|&count| count == 0));
    }

    /// The CPUs each of this process' executor workers may run on, as /proc lists them.
    fn workers_cpus() -> Vec<String> {
        let tasks = std::fs::read_dir("/proc/self/task").expect("/proc/self/task is readable");
        tasks
            .filter_map(|task| {
                let path = task.ok()?.path();
                let comm = std::fs::read_to_string(path.join("comm")).ok()?;
                // Thread names are cut to 15 bytes: "rigbridge-execu".
                if !comm.starts_with("rigbridge-execu") {
                    return None;
                }
                let status = std::fs::read_to_string(path.join("status")).ok()?;
                status
                    .lines()
                    .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))
                    .map(|list| list.trim().to_string())
            })
            .collect()
    }

    #[test]
    fn a_worker_keeps_to_the_cpu_it_is_given() {
        let Some(cpu) = crate::realtime::streaming_cpu() else {
            eprintln!("skipped: this machine lets the test run on one CPU only");
            return;
        };
        let pinned = cpu.to_string();
        let executor = Executor::new(ExecutorSettings {
            cpus: vec![cpu],
            ..ExecutorSettings::default()
        })
        .expect("the executor starts on the streaming CPU");
        assert!(
            workers_cpus().contains(&pinned),
            "no worker on CPU {cpu} alone: {:?}",
            workers_cpus()
        );
        drop(executor);
        assert!(
            !workers_cpus().contains(&pinned),
            "the worker outlived its executor"
        );
    }

    #[test]
    fn slots_are_spaced_and_capped() {
        assert_eq!(slots_per_period(Duration::from_millis(4)), 16);
        assert_eq!(slots_per_period(Duration::from_millis(1)), 4);
        assert_eq!(slots_per_period(Duration::from_micros(100)), 1);
        assert_eq!(slots_per_period(Duration::from_secs(1)), 16);
    }
}
