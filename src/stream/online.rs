//! Online motion: targets generated cycle by cycle from the arm's current state, toward a
//! goal that may change at any cycle (a retarget), or along a jog's direction while its
//! keep-alives arrive. rsruckig's online update (its `Ruckig::update` from the last state)
//! keeps position, velocity and acceleration continuous and within the limits it is given:
//! each axis' speed and acceleration times the plan's shares, times the speed override.
//!
//! A splice (a preempting FollowJointTrajectory goal, docs/ros2.md) hands over a planned
//! trajectory that starts where the arm held when it was planned: the arm goes on from its
//! present state (position, velocity, acceleration) into the trajectory's `join` sample, by
//! an rsruckig profile that reaches that sample's position and velocity exactly at its time
//! (jerk, acceleration and speed limited), then follows the trajectory's samples at the
//! same time scale as a planned path (the override ramps it). A splice whose profile would
//! need longer than the join's time is refused, and the motion before goes on unchanged.
//!
//! Braking is this module's own: on a stop, a deadman (no keep-alive for `deadman`), a jog
//! key released, an override of 0 % or a joint limit ahead, every axis' velocity is scaled
//! down together by the same share each cycle, at the brake's acceleration, so the arm
//! comes to rest along the line it moved on, never faster than the cycle before.
//!
//! A servo stream (`OnlineCommand::Servo`) is a goal that moves: each target a client sends
//! replaces the last, with the velocity of the last few targets as the target's velocity
//! (so the arm follows a moving target instead of stopping at each one), measured over the
//! times the targets were sent, not the cycles they were seen in: a loaded machine delivers
//! a client's targets in bursts, and a velocity from arrivals then overshoots (the servo
//! excursion of docs/online.md). When no target arrives for `servo_timeout` the arm comes
//! to rest along its path with the brake.
//!
//! A Cartesian jog moves the tool at the jog speed (ISO 10218-1's reduced speed, 250 mm/s,
//! by default) along a direction of the base or the tool frame, its orientation held, by a
//! damped least-squares solve of the rig's Jacobian each cycle; a joint jog moves one axis
//! no faster than puts the tool at that speed. Owns the generation only: the cycle gates
//! and sends each target ([`super::gate`], and [`CellCheck`], the workcell's hook), and
//! the HTTP API validates a goal before it reaches [`OnlineCommands`]. The cycle allocates
//! nothing here: the generator's buffers are made when the stream is prepared.

use super::gate::Sent;
use crate::motion::Trajectory;
use crate::protocol::AxisValues;
use crate::rig::{JointAxis, JointKind, Rig};
use glam::DVec3;
use rsruckig::prelude::{
    ControlInterface, DataArrayOrVec, InputParameter, OutputParameter, Ruckig, RuckigResult,
    Synchronization, ThrowErrorHandler, Trajectory as Profile,
};
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

/// ISO 10218-1 (5.6) limits the tool's speed in reduced-speed (manual) mode to 250 mm/s.
pub const REDUCED_SPEED_M_S: f64 = 0.25;
/// The deadman: a jog whose keep-alives stop for this long brings the arm to rest.
pub const DEADMAN: Duration = Duration::from_millis(200);
/// A servo stream whose targets stop for this long brings the arm to rest: ten periods of
/// a 100 Hz client, so a target or two lost on a busy network does not stop the arm, while
/// a client that went away holds it at rest within this plus the brake's ramp.
pub const SERVO_TIMEOUT: Duration = Duration::from_millis(100);
/// An online session with nothing to do (at rest, no command) ends after this long.
pub const IDLE_END: Duration = Duration::from_secs(5);
/// The share of each axis' acceleration the brake uses: the rest keeps the braking
/// targets clear of the gate's own check by more than rounding (as `brake.rs`).
const BRAKE_SHARE: f64 = 0.95;
/// A jog stops this far (rad, or m for a prismatic axis) before a joint limit, beyond what
/// braking needs: the gate refuses a target past the limit, and the next cycle's motion
/// must fit too.
const LIMIT_MARGIN_RAD: f64 = 0.01;
const LIMIT_MARGIN_M: f64 = 0.0005;
/// Damping of the least-squares solve (m): near a singularity the joint speeds stay
/// bounded and the tool slows down instead.
const DLS_DAMPING: f64 = 0.01;
/// The share of the jog speed a jog aims at: rsruckig follows a target velocity that
/// changes each cycle (a Cartesian jog's joints) with limited jerk, so it may overshoot it by
/// a little; the tool stays under the jog speed.
const TRACKING_SHARE: f64 = 0.95;
/// Within this much room beyond the cell's margin a jog slows down, in proportion to the
/// room left: at 250 mm/s the arm then needs under 0.1 s to brake (its stopping distance
/// is millimetres), so the look-ahead at the margin stops a slow arm, not a fast one.
const JOG_SLOW_ROOM_M: f64 = 0.1;
/// The least share of the jog speed near the cell: the arm still creeps up to the margin's
/// edge, where the look-ahead stops it, instead of slowing without end.
const JOG_CREEP_SHARE: f64 = 0.1;
/// A velocity below this (rad/s or m/s) on every axis is at rest.
const REST_SPEED: f64 = 1e-9;
/// The weight of the newest interval in the servo targets' mean interval (what a late
/// target is measured in): a 100 Hz client lands 2 or 3 cycles of 250 Hz apart; the mean
/// of about ten is within a few percent of its rate.
const SERVO_INTERVAL_WEIGHT: f64 = 0.1;
/// The share of each axis' velocity limit a servo stream's velocity may use: rsruckig
/// refuses a target velocity above its limit, and a target faster than the arm may move is
/// followed at the arm's speed, its position never changed.
const SERVO_VELOCITY_SHARE: f64 = 0.99;
/// How fast (1/s) a servo stream closes the distance to its target, on top of the target's
/// own velocity: the distance falls by this share a second. Tuned on the servo figure
/// (docs/online.md): higher overshoots with rsruckig's jerk-limited response.
const SERVO_GAIN: f64 = 6.0;
/// A servo target arriving more than this many mean intervals after the one before ends a
/// gap: a 100 Hz client lands 2 or 3 cycles of 250 Hz apart (0.8 or 1.2 intervals), one
/// lost on the way makes it 2.
const SERVO_GAP_INTERVALS: f64 = 1.5;
/// How many targets back a servo target's velocity is measured from: four intervals of a
/// 100 Hz client (40 ms), so a burst and the pause after it average out, while the
/// velocity lags the client's by half that.
const SERVO_WINDOW: usize = 4;
/// A servo target older than this many mean intervals is late: the next one did not come
/// when due. The target is then no longer moved on by its velocity, and that velocity's
/// share of the arm's fades to nothing by the stream's timeout, so the arm slows down
/// toward the last target through rsruckig, its acceleration continuous. Braking at once
/// instead (this module's brake, acceleration stepping to 95 % of the limit) was the
/// servo excursion of docs/online.md: on a loaded machine targets are late for a cycle or
/// two every few hundred milliseconds, and each brake left rsruckig to win back its
/// acceleration under the jerk limit, each axis on its own, the tool off the client's
/// path by up to 90 mm.
const SERVO_LATE_INTERVALS: f64 = 2.0;
/// Below this time scale (samples a cycle) a session counts as paused: a splice is refused
/// then, since its profile starts from the present velocity in the path's own time.
const SPLICE_MIN_RATE: f64 = 1e-3;
/// rsruckig's duration may exceed the minimum asked for by rounding: within this (s) the
/// profile still ends at the join's time.
const SPLICE_TIME_SLACK_S: f64 = 1e-9;

/// A frame a Cartesian jog's direction is given in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Frame {
    Base,
    Tool,
}

/// What a jog moves: one joint (`direction` +1 or -1), or the tool along a unit
/// `direction` of `frame`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Jog {
    Joint { axis: usize, direction: f64 },
    Cartesian { frame: Frame, direction: DVec3 },
}

/// An online command, as the API hands it to the cycle.
// Boxing the goal would allocate in the cycle; a command is small enough to copy.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OnlineCommand {
    /// Move to these joint positions (validated within the limits), from wherever the arm
    /// is and however it moves.
    Goal(AxisValues),
    /// Jog, while keep-alives arrive.
    Jog(Jog),
    /// The jog key was released: to rest along the path now.
    Release,
    /// A servo client's newest target (validated within the limits and the cell): follow
    /// it, while targets keep arriving within [`SERVO_TIMEOUT`].
    Servo(ServoTarget),
}

/// One servo target and when it was sent.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServoTarget {
    pub joints: AxisValues,
    /// When the client sent it (s, on any clock of the client's that only goes forward; the
    /// route's arrival time when the client gives none): the target's velocity is measured
    /// over these, so how the targets bunch on the way does not change it.
    pub sent_s: f64,
}

/// The commands waiting for the cycle, and the jog's keep-alives. The API writes here; the
/// cycle takes a command with `try_lock`, never waiting for a writer.
#[derive(Debug, Default)]
pub struct OnlineCommands {
    pending: Mutex<Option<OnlineCommand>>,
    /// Set once a command was given: the session's motion is online from then on.
    given: AtomicBool,
    keepalives: AtomicU64,
    /// The goal the session moves to, kept for a resume after a link loss.
    goal: Mutex<Option<AxisValues>>,
    /// An online session holds at a goal it reached, waiting for more; a planned job whose
    /// goal was changed ends there.
    session: AtomicBool,
    /// A trajectory waiting to be spliced in, and whether one waits (read every cycle
    /// without taking the lock).
    splice: Mutex<Option<Splice>>,
    splice_waiting: AtomicBool,
    /// The cycle's answer to the last splice ([`SpliceAnswer`], as its code) and, for a
    /// profile too long, the seconds it needed.
    splice_answer: AtomicU64,
    splice_needed_s: AtomicU64,
    splice_due_s: AtomicU64,
}

/// A planned trajectory to go on into from the present motion, at its sample `join` (see
/// the module doc). It must start at rest within the limits, validated and checked against
/// the cell as a job's.
#[derive(Debug, Clone)]
pub struct Splice {
    pub trajectory: Arc<Trajectory>,
    /// The sample the arm joins the trajectory at (> 0): reached at its own time from the
    /// splice.
    pub join: usize,
}

/// What the cycle made of a splice.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SpliceAnswer {
    /// Not seen by a cycle yet.
    Waiting,
    /// The arm goes on into it.
    Taken,
    Refused(SpliceRefusal),
}

/// Why a splice was refused: the motion before goes on unchanged.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum SpliceRefusal {
    #[error("the session is stopping")]
    Stopping,
    #[error("the session is paused (or its override is 0 %)")]
    Paused,
    #[error(
        "from the arm's present motion the join needs {needed_s:.3} s within the axes' speed, \
         acceleration and jerk limits, but its point is due in {due_s:.3} s"
    )]
    TooSoon { needed_s: f64, due_s: f64 },
    #[error("no motion within the axes' limits reaches the join from the arm's present motion")]
    NoProfile,
}

const ANSWER_WAITING: u64 = 0;
const ANSWER_TAKEN: u64 = 1;
const ANSWER_STOPPING: u64 = 2;
const ANSWER_PAUSED: u64 = 3;
const ANSWER_TOO_SOON: u64 = 4;
const ANSWER_NO_PROFILE: u64 = 5;

impl OnlineCommands {
    /// Hands `command` to the next cycle (a newer one replaces one not yet taken); a jog
    /// counts as a keep-alive.
    pub fn give(&self, command: OnlineCommand) {
        let mut pending = self.pending.lock().unwrap_or_else(PoisonError::into_inner);
        *pending = Some(command);
        let mut goal = self.goal.lock().unwrap_or_else(PoisonError::into_inner);
        *goal = match command {
            OnlineCommand::Goal(target) => Some(target),
            _ => None,
        };
        self.given.store(true, Ordering::SeqCst);
        self.keep_alive();
    }

    /// The jog goes on for another [`DEADMAN`].
    pub fn keep_alive(&self) {
        self.keepalives.fetch_add(1, Ordering::SeqCst);
    }

    /// Marks an online session: a goal reached is held, not the end (see [`IDLE_END`]).
    pub fn open_session(&self) {
        self.session.store(true, Ordering::SeqCst);
    }

    /// Whether the session moves online (a command was given).
    pub fn given(&self) -> bool {
        self.given.load(Ordering::SeqCst)
    }

    /// The goal the session was moving to, if it was (a jog has none).
    pub fn goal(&self) -> Option<AxisValues> {
        *self.goal.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Hands `splice` to the next cycle (replacing one not yet taken); its answer is then
    /// [`SpliceAnswer::Waiting`] until a cycle decides.
    pub fn splice(&self, splice: Splice) {
        let mut slot = self.splice.lock().unwrap_or_else(PoisonError::into_inner);
        self.splice_answer.store(ANSWER_WAITING, Ordering::SeqCst);
        *slot = Some(splice);
        self.splice_waiting.store(true, Ordering::SeqCst);
    }

    /// Takes back a splice no cycle has seen; false when one took it already (its answer
    /// then comes).
    pub fn withdraw_splice(&self) -> bool {
        let mut slot = self.splice.lock().unwrap_or_else(PoisonError::into_inner);
        self.splice_waiting.store(false, Ordering::SeqCst);
        slot.take().is_some()
    }

    /// The cycle's answer to the last splice.
    pub fn splice_answer(&self) -> SpliceAnswer {
        match self.splice_answer.load(Ordering::SeqCst) {
            ANSWER_TAKEN => SpliceAnswer::Taken,
            ANSWER_STOPPING => SpliceAnswer::Refused(SpliceRefusal::Stopping),
            ANSWER_PAUSED => SpliceAnswer::Refused(SpliceRefusal::Paused),
            ANSWER_TOO_SOON => SpliceAnswer::Refused(SpliceRefusal::TooSoon {
                needed_s: f64::from_bits(self.splice_needed_s.load(Ordering::SeqCst)),
                due_s: f64::from_bits(self.splice_due_s.load(Ordering::SeqCst)),
            }),
            ANSWER_NO_PROFILE => SpliceAnswer::Refused(SpliceRefusal::NoProfile),
            _ => SpliceAnswer::Waiting,
        }
    }

    pub(super) fn splice_waiting(&self) -> bool {
        self.splice_waiting.load(Ordering::SeqCst)
    }

    /// The waiting splice, unless the API holds its lock this very moment (then next cycle).
    fn take_splice(&self) -> Option<Splice> {
        let mut slot = self.splice.try_lock().ok()?;
        self.splice_waiting.store(false, Ordering::SeqCst);
        slot.take()
    }

    fn answer_splice(&self, answer: Result<(), SpliceRefusal>) {
        let code = match answer {
            Ok(()) => {
                // From here the session's motion is online: a resume after a link loss
                // does not go back to the planned path.
                *self.goal.lock().unwrap_or_else(PoisonError::into_inner) = None;
                self.given.store(true, Ordering::SeqCst);
                ANSWER_TAKEN
            }
            Err(SpliceRefusal::Stopping) => ANSWER_STOPPING,
            Err(SpliceRefusal::Paused) => ANSWER_PAUSED,
            Err(SpliceRefusal::TooSoon { needed_s, due_s }) => {
                self.splice_needed_s
                    .store(needed_s.to_bits(), Ordering::SeqCst);
                self.splice_due_s.store(due_s.to_bits(), Ordering::SeqCst);
                ANSWER_TOO_SOON
            }
            Err(SpliceRefusal::NoProfile) => ANSWER_NO_PROFILE,
        };
        self.splice_answer.store(code, Ordering::SeqCst);
    }

    fn take(&self) -> Option<OnlineCommand> {
        self.pending.try_lock().ok()?.take()
    }

    fn keepalive_count(&self) -> u64 {
        self.keepalives.load(Ordering::SeqCst)
    }
}

/// The workcell's hook: every online target (jog, retarget) passes it after the gate's
/// limits; the workcell's collision model (src/cell/, issue 27) implements it. A refusal
/// brings the arm to rest along its path instead of the target.
pub trait CellCheck: Send + Sync + std::fmt::Debug {
    /// Whether the arm may move from `from` to `to` (one cycle's step, checked
    /// continuously) without coming closer to anything than the cell's margin.
    fn admits(&self, from: &[f64], to: &[f64]) -> bool;

    /// How much clearer than the margin the arm is at `at` (m; negative inside it), for a
    /// jog to slow down as it nears the cell; `None` without a model.
    fn room_m(&self, _at: &[f64]) -> Option<f64> {
        None
    }
}

/// No workcell model: every target within the limits is admitted.
#[derive(Debug)]
pub struct NoCell;

impl CellCheck for NoCell {
    fn admits(&self, _: &[f64], _: &[f64]) -> bool {
        true
    }
}

/// How online motion may use the rig.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OnlineSettings {
    /// The tool's jog speed (m/s).
    pub jog_speed_m_s: f64,
    pub deadman: Duration,
    /// A servo stream with no target for this long brings the arm to rest.
    pub servo_timeout: Duration,
    /// An online session at rest with nothing to do ends after this long.
    pub idle_end: Duration,
    /// Shares of each axis' speed and acceleration a goal or a jog may use (the plan's).
    pub speed_scale: f64,
    pub accel_scale: f64,
    /// Max jerk = max acceleration x this (1/s), as the planner's.
    pub jerk_per_accel_s: f64,
}

impl Default for OnlineSettings {
    fn default() -> Self {
        Self {
            jog_speed_m_s: REDUCED_SPEED_M_S,
            deadman: DEADMAN,
            servo_timeout: SERVO_TIMEOUT,
            idle_end: IDLE_END,
            speed_scale: 0.9,
            accel_scale: 0.8,
            jerk_per_accel_s: 10.0,
        }
    }
}

/// What the generator does this cycle.
// As `OnlineCommand`: no allocation in the cycle.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Copy, PartialEq)]
enum Intent {
    Idle,
    Goal(AxisValues),
    Jog(Jog),
    /// A servo target and its velocity (from the last few targets).
    Servo {
        target: AxisValues,
        velocity: AxisValues,
    },
    /// A spliced trajectory: the profile into it until sample `join`, then its samples; `at`
    /// the place (samples from the splice), `rate` the time scale (samples a cycle).
    Follow {
        join: usize,
        at: f64,
        rate: f64,
    },
}

/// Where the servo stream's targets arrived: the last one, its cycle, the mean interval
/// between arrivals (s) once there were two, and the ones before (when each was sent, and
/// the target, newest first; `held` of them are real).
#[derive(Debug, Clone, Copy)]
struct ServoArrivals {
    last: ServoTarget,
    cycle: u64,
    interval: Option<f64>,
    earlier: [ServoTarget; SERVO_WINDOW],
    held: usize,
}

/// The brake's progress: the velocity it started from and the share of it left.
#[derive(Debug, Clone, Copy)]
struct Brake {
    from: AxisValues,
    share: f64,
    step: f64,
}

/// One cycle's result.
#[derive(Debug, Clone, Copy)]
pub(super) struct Step {
    pub positions: AxisValues,
    pub velocities: AxisValues,
    /// The arm moves (or will: the target differs from the last).
    pub moving: bool,
    /// A goal was reached, or an idle session's time is up: the stream may end.
    pub finished: bool,
}

/// The generator (see the module doc), made when the stream is prepared.
pub(super) struct Online {
    dof: usize,
    dt: f64,
    settings: OnlineSettings,
    otg: Ruckig<0, ThrowErrorHandler>,
    input: InputParameter<0>,
    output: OutputParameter<0>,
    engaged: bool,
    intent: Intent,
    brake: Option<Brake>,
    position: AxisValues,
    velocity: AxisValues,
    acceleration: AxisValues,
    /// Cycles so far, the stream's own time.
    cycle: u64,
    keepalives: u64,
    keepalive_cycle: u64,
    rest_since: Option<u64>,
    servo: Option<ServoArrivals>,
    /// Where the joint axes are this cycle (kept: no allocation in the cycle).
    axes: Vec<JointAxis>,
    /// The spliced trajectory, the profile into it and that profile's input (made when the
    /// stream is prepared); how fast the time scale may change (samples a cycle, a cycle).
    follow: Option<Arc<Trajectory>>,
    profile: Profile<0>,
    profile_input: InputParameter<0>,
    scale_step: f64,
}

impl Online {
    /// `scale_step`: how much the time scale of a spliced trajectory may change a cycle (a
    /// planned path's, see `stream::slowdown_rate`).
    pub(super) fn new(
        rig: &Rig,
        period: Duration,
        settings: OnlineSettings,
        scale_step: f64,
    ) -> Self {
        let dof = rig.dof();
        let dt = period.as_secs_f64();
        let mut input = InputParameter::new(Some(dof));
        input.synchronization = Synchronization::Time;
        let mut lower = DataArrayOrVec::new(Some(dof), 0.0);
        let mut upper = DataArrayOrVec::new(Some(dof), 0.0);
        for (axis, joint) in rig.joints.iter().enumerate() {
            let limits = joint.limits;
            let acceleration = settings.accel_scale * limits.max_acceleration;
            input.max_acceleration[axis] = acceleration;
            input.max_jerk[axis] = settings.jerk_per_accel_s * acceleration;
            lower[axis] = limits.lower;
            upper[axis] = limits.upper;
        }
        input.min_position = Some(lower);
        input.max_position = Some(upper);
        let mut profile_input = input.clone();
        profile_input.control_interface = ControlInterface::Position;
        Self {
            dof,
            dt,
            settings,
            otg: Ruckig::new(Some(dof), dt),
            input,
            output: OutputParameter::new(Some(dof)),
            engaged: false,
            intent: Intent::Idle,
            brake: None,
            position: AxisValues::zeros(dof),
            velocity: AxisValues::zeros(dof),
            acceleration: AxisValues::zeros(dof),
            cycle: 0,
            keepalives: 0,
            keepalive_cycle: 0,
            rest_since: None,
            servo: None,
            axes: Vec::with_capacity(dof),
            follow: None,
            profile: Profile::new(Some(dof)),
            profile_input,
            scale_step,
        }
    }

    pub(super) fn engaged(&self) -> bool {
        self.engaged
    }

    /// Takes over from the last target sent (its acceleration from the two before): the
    /// online motion starts from the state the arm is commanded in.
    pub(super) fn engage(&mut self, sent: &Sent, previous_velocity: Option<AxisValues>) {
        self.engaged = true;
        if let Some((positions, velocities)) = sent.previous {
            self.position = positions;
            self.velocity = velocities;
            if let Some(before) = previous_velocity {
                for axis in 0..self.dof {
                    self.acceleration.as_mut_slice()[axis] =
                        (velocities.as_slice()[axis] - before.as_slice()[axis]) / self.dt;
                }
            }
        }
    }

    /// Starts from rest at `positions` (nothing sent yet in this stream).
    pub(super) fn start_at(&mut self, positions: &[f64]) {
        self.position.as_mut_slice().copy_from_slice(positions);
    }

    /// A planned path that was engaged only to try a splice, which was refused: the path
    /// goes on as before (nothing of the online state was sent).
    pub(super) fn disengage(&mut self) {
        self.engaged = false;
    }

    /// Takes the waiting splice, if one waits, and goes on into it when a profile from the
    /// present state (moving at `rate` samples a cycle of its path, 1 for online motion)
    /// reaches its join in time; answers either way. True when it was taken.
    pub(super) fn try_splice(
        &mut self,
        rig: &Rig,
        commands: &OnlineCommands,
        rate: f64,
        stopping: bool,
    ) -> bool {
        let Some(splice) = commands.take_splice() else {
            return false;
        };
        let answer = if stopping {
            Err(SpliceRefusal::Stopping)
        } else if rate < SPLICE_MIN_RATE {
            Err(SpliceRefusal::Paused)
        } else {
            self.profile_into(rig, &splice, rate)
        };
        let taken = answer.is_ok();
        if taken {
            self.intent = Intent::Follow {
                join: splice.join,
                at: 0.0,
                rate,
            };
            self.brake = None;
            // The trajectory before stays alive with whoever spliced it: no free here.
            self.follow = Some(splice.trajectory);
        }
        commands.answer_splice(answer);
        taken
    }

    /// The profile from the present state into `splice`'s join, in the path's own time
    /// (the present velocity over `rate`, so that sampled at `rate` it starts at the
    /// present velocity), ending at the join's time from now.
    fn profile_into(&mut self, rig: &Rig, splice: &Splice, rate: f64) -> Result<(), SpliceRefusal> {
        let trajectory = &splice.trajectory;
        let join = splice.join.min(trajectory.len() - 1);
        let due_s = join as f64 * self.dt;
        let (position, velocity) = trajectory.sample(join);
        let input = &mut self.profile_input;
        for (axis, joint) in rig.joints.iter().enumerate() {
            let limits = joint.limits;
            input.current_position[axis] = self.position.as_slice()[axis];
            input.current_velocity[axis] = self.velocity.as_slice()[axis] / rate;
            input.current_acceleration[axis] = self.acceleration.as_slice()[axis] / (rate * rate);
            input.target_position[axis] = position[axis];
            input.target_velocity[axis] = velocity[axis];
            input.target_acceleration[axis] = 0.0;
            // The planned share of the speed, or the trajectory's own speed at the join
            // when it is faster (within the limit: the trajectory was validated).
            input.max_velocity[axis] = (self.settings.speed_scale * limits.max_speed)
                .max(velocity[axis].abs())
                .min(limits.max_speed);
        }
        input.minimum_duration = Some(due_s);
        let calculated = self.otg.calculate(&self.profile_input, &mut self.profile);
        let needed_s = self.profile.get_duration();
        match calculated {
            Ok(RuckigResult::Working | RuckigResult::Finished) => {}
            _ => return Err(SpliceRefusal::NoProfile),
        }
        if needed_s > due_s + SPLICE_TIME_SLACK_S {
            return Err(SpliceRefusal::TooSoon { needed_s, due_s });
        }
        Ok(())
    }

    /// The next target: from the commands, the stop and the override (0..=1).
    pub(super) fn step(
        &mut self,
        rig: &Rig,
        commands: &OnlineCommands,
        stopping: bool,
        speed: f64,
        cell: &dyn CellCheck,
    ) -> Step {
        self.cycle += 1;
        self.take(commands);
        if commands.splice_waiting() {
            let rate = match self.intent {
                Intent::Follow { rate, .. } => rate,
                _ => 1.0,
            };
            self.try_splice(rig, commands, rate, stopping);
        }
        let deadman = matches!(self.intent, Intent::Jog(_))
            && (self.cycle - self.keepalive_cycle) as f64 * self.dt
                > self.settings.deadman.as_secs_f64();
        let servo_timeout = matches!(self.intent, Intent::Servo { .. })
            && (self.cycle - self.keepalive_cycle) as f64 * self.dt
                > self.settings.servo_timeout.as_secs_f64();
        if deadman || servo_timeout {
            self.intent = Intent::Idle;
        }
        // A spliced trajectory pauses as a planned path does, its time scale ramped to 0.
        let follows = matches!(self.intent, Intent::Follow { .. });
        let brake = stopping || (speed <= 0.0 && !follows) || self.intent == Intent::Idle;
        let braked = brake || !self.generate(rig, speed, cell);
        if braked {
            self.brake_step(rig);
        }
        let moving = !self.at_rest();
        if moving || !matches!(self.intent, Intent::Idle) {
            self.rest_since = None;
        } else {
            self.rest_since.get_or_insert(self.cycle);
        }
        let reached = match self.intent {
            Intent::Goal(goal) => !braked && !moving && self.at(&goal),
            Intent::Follow { at, .. } => !braked && !moving && self.at_end(at),
            _ => false,
        };
        if reached && commands.session.load(Ordering::SeqCst) {
            self.intent = Intent::Idle;
        }
        let finished = match self.intent {
            Intent::Goal(_) | Intent::Follow { .. } => reached,
            Intent::Idle => self.rest_since.is_some_and(|since| {
                (self.cycle - since) as f64 * self.dt >= self.settings.idle_end.as_secs_f64()
            }),
            Intent::Jog(_) | Intent::Servo { .. } => false,
        };
        Step {
            positions: self.position,
            velocities: self.velocity,
            moving,
            finished,
        }
    }

    fn take(&mut self, commands: &OnlineCommands) {
        let count = commands.keepalive_count();
        if count != self.keepalives {
            self.keepalives = count;
            self.keepalive_cycle = self.cycle;
        }
        match commands.take() {
            Some(OnlineCommand::Goal(goal)) => self.intent = Intent::Goal(goal),
            Some(OnlineCommand::Jog(jog)) => self.intent = Intent::Jog(jog),
            Some(OnlineCommand::Release) => self.intent = Intent::Idle,
            Some(OnlineCommand::Servo(target)) => self.follow(target),
            None => {}
        }
        if !matches!(self.intent, Intent::Servo { .. }) {
            self.servo = None;
        }
    }

    /// How far (s) the servo target is moved on by its velocity, and the share of that
    /// velocity the arm is given: its age and 1 while it is on time; once it is late (see
    /// [`SERVO_LATE_INTERVALS`]) the lateness bound and a share falling to 0 at the
    /// timeout.
    fn servo_horizon(&self) -> (f64, f64) {
        let Some(arrivals) = self.servo else {
            return (0.0, 0.0);
        };
        let age = (self.cycle - arrivals.cycle) as f64 * self.dt;
        let Some(mean) = arrivals.interval else {
            return (age, 1.0);
        };
        let late = SERVO_LATE_INTERVALS * mean;
        if age <= late {
            return (age, 1.0);
        }
        let timeout = self.settings.servo_timeout.as_secs_f64();
        let share = if timeout > late {
            ((timeout - age) / (timeout - late)).clamp(0.0, 1.0)
        } else {
            0.0
        };
        (late, share)
    }

    /// A servo target: its velocity from the targets before it over the time between their
    /// sending; zero for the first of a stream (or after a pause longer than the timeout).
    fn follow(&mut self, target: ServoTarget) {
        let timeout = self.settings.servo_timeout.as_secs_f64();
        let continued = self
            .servo
            .filter(|_| matches!(self.intent, Intent::Servo { .. }));
        let mut velocity = AxisValues::zeros(self.dof);
        let mut arrivals = ServoArrivals {
            last: target,
            cycle: self.cycle,
            interval: None,
            earlier: [target; SERVO_WINDOW],
            held: 0,
        };
        if let Some(before) = continued {
            let since = (self.cycle - before.cycle) as f64 * self.dt;
            if since > 0.0 && since <= timeout {
                // A gap (a target lost or late) says nothing of the client's rate.
                arrivals.interval = Some(match before.interval {
                    Some(mean) if since > SERVO_GAP_INTERVALS * mean => mean,
                    Some(mean) => mean + SERVO_INTERVAL_WEIGHT * (since - mean),
                    None => since,
                });
                arrivals.earlier[0] = before.last;
                arrivals.earlier[1..].copy_from_slice(&before.earlier[..SERVO_WINDOW - 1]);
                arrivals.held = (before.held + 1).min(SERVO_WINDOW);
                // Over the window and the client's own times: two targets seen in
                // consecutive cycles after a pause were still sent an interval apart.
                let oldest = arrivals.earlier[arrivals.held - 1];
                let elapsed = target.sent_s - oldest.sent_s;
                if elapsed > 0.0 {
                    for axis in 0..self.dof {
                        velocity.as_mut_slice()[axis] = (target.joints.as_slice()[axis]
                            - oldest.joints.as_slice()[axis])
                            / elapsed;
                    }
                }
            }
        }
        self.servo = Some(arrivals);
        self.intent = Intent::Servo {
            target: target.joints,
            velocity,
        };
    }

    fn at(&self, goal: &AxisValues) -> bool {
        self.position
            .as_slice()
            .iter()
            .zip(goal.as_slice())
            .all(|(p, g)| (p - g).abs() <= 1e-9)
    }

    /// Whether `at` is the spliced trajectory's last sample.
    fn at_end(&self, at: f64) -> bool {
        self.follow
            .as_ref()
            .is_some_and(|trajectory| at >= (trajectory.len() - 1) as f64)
    }

    fn at_rest(&self) -> bool {
        self.velocity
            .as_slice()
            .iter()
            .all(|v| v.abs() <= REST_SPEED)
    }

    /// One cycle of rsruckig toward the intent; false when it must brake instead (a limit
    /// ahead of a jog, the cell's refusal, or no profile within the limits).
    fn generate(&mut self, rig: &Rig, speed: f64, cell: &dyn CellCheck) -> bool {
        self.brake = None;
        if let Intent::Follow { join, at, rate } = self.intent {
            return self.follow_step(rig, speed, cell, join, at, rate);
        }
        for (axis, joint) in rig.joints.iter().enumerate() {
            self.input.max_velocity[axis] =
                speed * self.settings.speed_scale * joint.limits.max_speed;
            self.input.current_position[axis] = self.position.as_slice()[axis];
            self.input.current_velocity[axis] = self.velocity.as_slice()[axis];
            self.input.current_acceleration[axis] = self.acceleration.as_slice()[axis];
            self.input.target_acceleration[axis] = 0.0;
        }
        // Goals and jogs move every axis in step (a line in joint space, a direction of the
        // tool); a servo target's axes each follow their own target.
        self.input.synchronization = Synchronization::Time;
        match self.intent {
            Intent::Goal(goal) => {
                self.input.control_interface = ControlInterface::Position;
                for axis in 0..self.dof {
                    self.input.target_position[axis] = goal.as_slice()[axis];
                    self.input.target_velocity[axis] = 0.0;
                }
            }
            Intent::Servo { target, velocity } => {
                let wanted = self.servo_velocity(&target, &velocity);
                if !self.clear_of_limits(rig, &wanted) {
                    return false;
                }
                self.input.control_interface = ControlInterface::Velocity;
                self.input.synchronization = Synchronization::None;
                for axis in 0..self.dof {
                    self.input.target_velocity[axis] = wanted.as_slice()[axis];
                }
            }
            Intent::Jog(jog) => {
                let near = jog_share_near_the_cell(cell.room_m(self.position.as_slice()));
                let Some(velocity) = self.jog_velocity(rig, jog, speed * near) else {
                    return false;
                };
                self.input.control_interface = ControlInterface::Velocity;
                for axis in 0..self.dof {
                    self.input.target_velocity[axis] = velocity.as_slice()[axis];
                }
            }
            // Followed above.
            Intent::Idle | Intent::Follow { .. } => return false,
        }
        match self.otg.update(&self.input, &mut self.output) {
            Ok(RuckigResult::Working | RuckigResult::Finished) => {}
            _ => return false,
        }
        if !self.admitted_with_its_stop(rig, cell) {
            return false;
        }
        if let Intent::Jog(_) = self.intent
            && self.tool_too_fast(rig, speed)
        {
            return false;
        }
        for axis in 0..self.dof {
            self.position.as_mut_slice()[axis] = self.output.new_position[axis];
            self.velocity.as_mut_slice()[axis] = self.output.new_velocity[axis];
            self.acceleration.as_mut_slice()[axis] = self.output.new_acceleration[axis];
        }
        true
    }

    /// One cycle along the spliced trajectory: the time scale ramped toward the override
    /// by the planned path's step, the profile into the join before it, the trajectory's
    /// samples after, each step checked against the cell with its stop as every online
    /// step is. A refused step ends the splice: the arm brakes to rest and holds.
    fn follow_step(
        &mut self,
        rig: &Rig,
        speed: f64,
        cell: &dyn CellCheck,
        join: usize,
        at: f64,
        rate: f64,
    ) -> bool {
        // A clone of the handle, not of the samples; the splicer keeps its own.
        let Some(trajectory) = self.follow.clone() else {
            return false;
        };
        let rate = if speed > rate {
            (rate + self.scale_step).min(speed)
        } else {
            (rate - self.scale_step).max(speed)
        };
        let at = (at + rate).min((trajectory.len() - 1) as f64);
        if at < join as f64 {
            self.profile.at_time(
                at * self.dt,
                &mut Some(&mut self.output.new_position),
                &mut Some(&mut self.output.new_velocity),
                &mut None,
                &mut None,
                &mut None,
            );
            for axis in 0..self.dof {
                self.output.new_velocity[axis] *= rate;
            }
        } else {
            let (positions, velocities) = super::brake::sample_at(&trajectory, at, rate);
            for axis in 0..self.dof {
                self.output.new_position[axis] = positions.as_slice()[axis];
                self.output.new_velocity[axis] = velocities.as_slice()[axis];
            }
        }
        if !self.admitted_with_its_stop(rig, cell) {
            self.intent = Intent::Idle;
            return false;
        }
        for axis in 0..self.dof {
            let velocity = self.output.new_velocity[axis];
            self.acceleration.as_mut_slice()[axis] =
                (velocity - self.velocity.as_slice()[axis]) / self.dt;
            self.position.as_mut_slice()[axis] = self.output.new_position[axis];
            self.velocity.as_mut_slice()[axis] = velocity;
        }
        self.intent = Intent::Follow { join, at, rate };
        true
    }

    /// Whether the cell admits the generated step and, from its end, the brake that
    /// [`Self::brake_step`] would run next cycle: a refusal must leave the arm room to stop
    /// outside the margin, so the stop is checked before the step is taken, not after.
    /// That brake is a line in joint space (every axis' velocity down by one share a
    /// cycle), over at most `T + dt` at half the speed, `T` the slowest axis' time to rest.
    fn admitted_with_its_stop(&self, rig: &Rig, cell: &dyn CellCheck) -> bool {
        let next: &[f64] = &self.output.new_position;
        if !cell.admits(self.position.as_slice(), next) {
            return false;
        }
        let velocity: &[f64] = &self.output.new_velocity;
        let time_to_rest = rig
            .joints
            .iter()
            .zip(velocity)
            .map(|(joint, v)| v.abs() / (BRAKE_SHARE * joint.limits.max_acceleration))
            .fold(0.0, f64::max);
        if time_to_rest == 0.0 {
            return true;
        }
        let reach = 0.5 * (time_to_rest + self.dt);
        let mut stop = AxisValues::zeros(self.dof);
        for (axis, (p, v)) in next.iter().zip(velocity).enumerate() {
            stop.as_mut_slice()[axis] = p + v * reach;
        }
        cell.admits(next, stop.as_slice())
    }

    /// The velocity that follows a servo target: its own velocity, plus [`SERVO_GAIN`] times
    /// the distance to where it is now (moved on by its velocity since it arrived), each
    /// axis within [`SERVO_VELOCITY_SHARE`] of its limit (all scaled down together); a late
    /// target's as [`Self::servo_horizon`] says.
    fn servo_velocity(&self, target: &AxisValues, velocity: &AxisValues) -> AxisValues {
        let (horizon, share) = self.servo_horizon();
        let mut wanted = AxisValues::zeros(self.dof);
        for axis in 0..self.dof {
            let v = velocity.as_slice()[axis];
            let now = target.as_slice()[axis] + v * horizon;
            wanted.as_mut_slice()[axis] =
                share * v + SERVO_GAIN * (now - self.position.as_slice()[axis]);
        }
        let over = (0..self.dof)
            .map(|axis| {
                wanted.as_slice()[axis].abs()
                    / (SERVO_VELOCITY_SHARE * self.input.max_velocity[axis])
            })
            .fold(1.0, f64::max);
        for v in wanted.as_mut_slice() {
            *v /= over;
        }
        wanted
    }

    /// The joint velocity a jog asks for at `speed` of its own, or None when an axis would
    /// not stop before its limit (the arm brakes).
    fn jog_velocity(&mut self, rig: &Rig, jog: Jog, speed: f64) -> Option<AxisValues> {
        let positions = self.position;
        let tool = rig
            .forward_with_axes(positions.as_slice(), &mut self.axes)
            .ok()?;
        let tcp = tool.translation;
        let jog_speed = speed * self.settings.jog_speed_m_s * TRACKING_SHARE;
        let mut velocity = AxisValues::zeros(self.dof);
        match jog {
            Jog::Joint { axis, direction } => {
                let joint = rig.joints.get(axis)?;
                let lever = match joint.kind {
                    JointKind::Revolute => {
                        let a = self.axes[axis];
                        a.direction.cross(tcp - a.point).length()
                    }
                    JointKind::Prismatic => 1.0,
                };
                let fastest = speed * self.settings.speed_scale * joint.limits.max_speed;
                let along = if lever > 0.0 {
                    (jog_speed / lever).min(fastest)
                } else {
                    fastest
                };
                velocity.as_mut_slice()[axis] = direction.signum() * along;
            }
            Jog::Cartesian { frame, direction } => {
                let direction = match frame {
                    Frame::Base => direction,
                    Frame::Tool => tool.matrix3 * direction,
                };
                self.cartesian(
                    rig,
                    tcp,
                    direction.normalize_or_zero() * jog_speed,
                    &mut velocity,
                );
                let linear = self.tool_speed(rig, tcp, &velocity);
                let share = rig
                    .joints
                    .iter()
                    .zip(velocity.as_slice())
                    .map(|(joint, v)| {
                        v.abs() / (speed * self.settings.speed_scale * joint.limits.max_speed)
                    })
                    .fold(1.0, f64::max)
                    .max(linear / jog_speed);
                for v in velocity.as_mut_slice() {
                    *v /= share;
                }
            }
        }
        self.clear_of_limits(rig, &velocity).then_some(velocity)
    }

    /// The joint velocities moving the tool at `linear` (m/s, base frame) without turning
    /// it: damped least squares on the geometric Jacobian, `J^T (J J^T + l^2 I)^-1 x`.
    fn cartesian(&self, rig: &Rig, tcp: DVec3, linear: DVec3, out: &mut AxisValues) {
        let column = |axis: usize| -> [f64; 6] {
            let a = self.axes[axis];
            match rig.joints[axis].kind {
                JointKind::Revolute => {
                    let v = a.direction.cross(tcp - a.point);
                    let w = a.direction;
                    [v.x, v.y, v.z, w.x, w.y, w.z]
                }
                JointKind::Prismatic => {
                    let v = a.direction;
                    [v.x, v.y, v.z, 0.0, 0.0, 0.0]
                }
            }
        };
        let mut m = [[0.0; 7]; 6];
        for axis in 0..self.dof {
            let c = column(axis);
            for (i, row) in m.iter_mut().enumerate() {
                for j in 0..6 {
                    row[j] += c[i] * c[j];
                }
            }
        }
        let twist = [linear.x, linear.y, linear.z, 0.0, 0.0, 0.0];
        for (i, row) in m.iter_mut().enumerate() {
            row[i] += DLS_DAMPING * DLS_DAMPING;
            row[6] = twist[i];
        }
        let y = solve6(&mut m);
        for axis in 0..self.dof {
            let c = column(axis);
            out.as_mut_slice()[axis] = (0..6).map(|i| c[i] * y[i]).sum();
        }
    }

    /// Whether rsruckig's next state moves the tool faster than the jog speed (it follows a
    /// Cartesian jog's joint velocities, which change each cycle, with limited jerk): the
    /// arm brakes from the present state instead, and the jog goes on from there.
    fn tool_too_fast(&mut self, rig: &Rig, speed: f64) -> bool {
        let mut next = AxisValues::zeros(self.dof);
        for axis in 0..self.dof {
            next.as_mut_slice()[axis] = self.output.new_velocity[axis];
        }
        let new_position: &[f64] = &self.output.new_position;
        let Ok(tool) = rig.forward_with_axes(new_position, &mut self.axes) else {
            return true;
        };
        self.tool_speed(rig, tool.translation, &next) > speed * self.settings.jog_speed_m_s
    }

    /// The tool's linear speed (m/s) at joint velocities `velocity`.
    fn tool_speed(&self, rig: &Rig, tcp: DVec3, velocity: &AxisValues) -> f64 {
        let mut linear = DVec3::ZERO;
        for (axis, joint) in rig.joints.iter().enumerate() {
            let a = self.axes[axis];
            let v = velocity.as_slice()[axis];
            linear += match joint.kind {
                JointKind::Revolute => a.direction.cross(tcp - a.point) * v,
                JointKind::Prismatic => a.direction * v,
            };
        }
        linear.length()
    }

    /// Whether every axis can still stop before its limit (less the margin), moving at its
    /// present velocity or at `wanted`, whichever is faster, with the brake: all axes slow
    /// down together, so each takes as long as the slowest to stop.
    fn clear_of_limits(&self, rig: &Rig, wanted: &AxisValues) -> bool {
        let fastest = |axis: usize| {
            self.velocity.as_slice()[axis]
                .abs()
                .max(wanted.as_slice()[axis].abs())
        };
        let braking = rig
            .joints
            .iter()
            .enumerate()
            .map(|(axis, joint)| fastest(axis) / (BRAKE_SHARE * joint.limits.max_acceleration))
            .fold(0.0, f64::max);
        rig.joints.iter().enumerate().all(|(axis, joint)| {
            let limits = joint.limits;
            let v = self.velocity.as_slice()[axis];
            let toward = if v != 0.0 { v } else { wanted.as_slice()[axis] };
            if toward == 0.0 {
                return true;
            }
            let margin = match joint.kind {
                JointKind::Revolute => LIMIT_MARGIN_RAD,
                JointKind::Prismatic => LIMIT_MARGIN_M,
            };
            // Braking (half the speed over the brake's time), two more cycles at this
            // speed, and what a cycle's acceleration adds before the brake takes over.
            let needed = fastest(axis) * (0.5 * braking + 2.0 * self.dt)
                + limits.max_acceleration * self.dt * self.dt
                + margin;
            let p = self.position.as_slice()[axis];
            let room = if toward > 0.0 {
                limits.upper - p
            } else {
                p - limits.lower
            };
            room > needed
        })
    }

    /// One braking cycle (see the module doc): every axis' velocity down by the same share.
    fn brake_step(&mut self, rig: &Rig) {
        if self.at_rest() {
            self.brake = None;
            self.velocity = AxisValues::zeros(self.dof);
            self.acceleration = AxisValues::zeros(self.dof);
            return;
        }
        let dt = self.dt;
        let velocity = self.velocity;
        let brake = self.brake.get_or_insert_with(|| {
            let step = rig
                .joints
                .iter()
                .zip(velocity.as_slice())
                .filter(|(_, v)| v.abs() > REST_SPEED)
                .map(|(joint, v)| BRAKE_SHARE * joint.limits.max_acceleration * dt / v.abs())
                .fold(f64::INFINITY, f64::min);
            Brake {
                from: velocity,
                share: 1.0,
                step,
            }
        });
        let before = brake.share;
        brake.share = (brake.share - brake.step).max(0.0);
        let (from, share) = (brake.from, brake.share);
        for axis in 0..self.dof {
            let v0 = from.as_slice()[axis];
            let (was, now) = (before * v0, share * v0);
            // The mean of the two velocities over the cycle: the second difference of the
            // positions is then half the change over two cycles, within the acceleration.
            self.position.as_mut_slice()[axis] += 0.5 * (was + now) * dt;
            self.velocity.as_mut_slice()[axis] = now;
            // The brake is not jerk-limited. Handing its deceleration to rsruckig as the
            // present acceleration, when a command takes over mid-brake, made rsruckig
            // overshoot the other way under its jerk limit (a jog stopped at the cell's
            // margin swung back at 0.8 rad/s); it takes over from the brake's velocity with
            // no acceleration instead, as it does at rest.
            self.acceleration.as_mut_slice()[axis] = 0.0;
        }
        if share == 0.0 {
            self.brake = None;
        }
    }
}

/// The share of the jog speed at `room` beyond the cell's margin (see [`JOG_SLOW_ROOM_M`]).
fn jog_share_near_the_cell(room: Option<f64>) -> f64 {
    room.map_or(1.0, |room| {
        (room / JOG_SLOW_ROOM_M).clamp(JOG_CREEP_SHARE, 1.0)
    })
}

/// Solves the 6x6 system in `m` (its 7th column the right-hand side), with partial
/// pivoting; `m` is positive definite here (damped), so no pivot is zero.
fn solve6(m: &mut [[f64; 7]; 6]) -> [f64; 6] {
    for col in 0..6 {
        let pivot = (col..6)
            .max_by(|a, b| m[*a][col].abs().total_cmp(&m[*b][col].abs()))
            .unwrap_or(col);
        m.swap(col, pivot);
        for row in col + 1..6 {
            let factor = m[row][col] / m[col][col];
            let pivot_row = m[col];
            for (value, pivot) in m[row].iter_mut().zip(pivot_row).skip(col) {
                *value -= factor * pivot;
            }
        }
    }
    let mut x = [0.0; 6];
    for row in (0..6).rev() {
        let tail: f64 = (row + 1..6).map(|k| m[row][k] * x[k]).sum();
        x[row] = (m[row][6] - tail) / m[row][row];
    }
    x
}
