//! The Foxglove-native part of a run log (`docs/foxglove.md`): `/tf` as protobuf
//! `foxglove.FrameTransforms` from forward kinematics of the controller's actual positions,
//! `/joint_states` as `foxglove.JointStates`, the rig's URDF as the attachment
//! `robot_description.urdf`, so Foxglove's 3D panel draws the robot moving, and the world
//! around it (paint room, branches) as `foxglove.SceneUpdate` on `/scene`. Message types and
//! schemas come from the `foxglove` crate (Foxglove SDK). Runs on the recorder's writer
//! thread only: the streaming cycle never encodes protobuf. Owns these channels and the
//! per-link transforms; it must not touch the JSON channels replay reads, nor the rig.

use super::LogError;
use crate::cell::Cell;
use crate::cell::urdf::cell_to_urdf;
use crate::rig::{Joint, Rig, UrdfTree, generated_link_names, origin_from_xyz_rpy};
use crate::scene::foxglove::{closest_update, full_update, paint_update, vector};
use crate::scene::{ClosestView, PaintQuad, SceneView};
use foxglove::Encode;
use foxglove::messages::{
    FrameTransform, FrameTransforms, JointState, JointStates, Quaternion, SceneUpdate, Timestamp,
};
use glam::{DAffine3, DQuat, DVec3};
use mcap::records::MessageHeader;
use mcap::{Attachment, Writer};
use std::borrow::Cow;
use std::collections::BTreeMap;
use std::io::{Seek, Write};
use std::sync::{Arc, Mutex, PoisonError};

/// Foxglove's conventional transform topic.
pub const TF_TOPIC: &str = "/tf";
pub const JOINT_STATES_TOPIC: &str = "/joint_states";
/// The world around the rig (`foxglove.SceneUpdate`): walls, branches, paint.
pub const SCENE_TOPIC: &str = "/scene";
/// How often (job time) a log writes the whole scene again, paint included, so a player
/// that seeks finds it within 10 s; paint in between goes in as it is added. Each repeat
/// holds all paint so far (about 200 bytes a quad, a quad a 0.25 m of stroke): a longer
/// period would leave the scene missing longer after a seek, a shorter one grow the log.
pub const SCENE_REPEAT_S: f64 = 10.0;
/// The attachment name Foxglove's URDF layer is pointed at (`docs/foxglove.md`).
pub const URDF_ATTACHMENT: &str = "robot_description.urdf";
const URDF_MEDIA_TYPE: &str = "application/xml";
const PROTOBUF: &str = "protobuf";

/// Decimation step of `/tf` and `/joint_states`, in job time: at most one message per
/// 16 ms. At the default 250 Hz that is every 4th cycle (62.5 Hz), at 1 kHz every 16th;
/// above the 50 Hz a smooth 3D view needs, with margin, at a quarter of the JSON states'
/// size. Streams slower than 62.5 Hz get every cycle.
pub const TF_PERIOD_S: f64 = 0.016;
/// Job times are sums of float periods: a step 1e-15 s short must still count as due.
const TIME_SLACK_S: f64 = 1e-9;
/// A URDF given for a rig must reproduce its forward kinematics to this (rounding only).
const FK_AGREEMENT_M: f64 = 1e-9;

/// How one link sits on its parent.
#[derive(Debug, Clone, PartialEq)]
enum Motion {
    /// A fixed joint of the URDF, or the rig's tool transform.
    Fixed(DAffine3),
    /// The rig's joint `index`, with the origin the URDF gives it (before any folding).
    Joint { index: usize, joint: Joint },
}

#[derive(Debug, Clone, PartialEq)]
struct Segment {
    parent: String,
    child: String,
    motion: Motion,
}

/// A rig's URDF and its chain of links, base frame to tool frame, then the fixed links hung
/// on it (tool, cell objects): what `/tf` is computed from.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotDescription {
    urdf: String,
    joint_names: Vec<String>,
    segments: Vec<Segment>,
    /// How many of `segments` are the chain, base frame to tool frame.
    chain: usize,
}

impl RobotDescription {
    /// The URDF of the rig in its cell ([`cell_to_urdf`], what `rigbridge config urdf`
    /// writes): links named by [`generated_link_names`], the rig's own joint transforms, then
    /// its tool transform; then every fixed link besides (the tool at its TCP, the cell's
    /// objects, extra bodies), each with a frame of its own in `/tf`.
    pub fn generated(rig: &Rig, cell: &Cell) -> Self {
        let links = generated_link_names(rig);
        let parents = std::iter::once(&rig.base_frame).chain(links.iter());
        let mut segments: Vec<Segment> = rig
            .joints
            .iter()
            .zip(parents.zip(&links))
            .enumerate()
            .map(|(index, (joint, (parent, child)))| Segment {
                parent: parent.clone(),
                child: child.clone(),
                motion: Motion::Joint {
                    index,
                    joint: joint.clone(),
                },
            })
            .collect();
        segments.push(Segment {
            parent: links.last().unwrap_or(&rig.base_frame).clone(),
            child: rig.tool_frame.clone(),
            motion: Motion::Fixed(rig.tool),
        });
        let chain = segments.len();
        let export = cell_to_urdf(rig, cell);
        segments.extend(export.fixed.into_iter().map(|link| Segment {
            parent: link.parent,
            child: link.name,
            motion: Motion::Fixed(link.origin),
        }));
        Self {
            urdf: export.text,
            joint_names: rig.joint_names().map(str::to_owned).collect(),
            segments,
            chain,
        }
    }

    /// A URDF file the rig was loaded from: its links, fixed ones included, along the chain
    /// `rig_from_urdf` took. Refused unless its actuated joints are the rig's, in order, and
    /// it gives the rig's forward kinematics.
    pub fn from_urdf(rig: &Rig, urdf: String) -> Result<Self, LogError> {
        let bad = |reason: String| LogError::Setup(format!("URDF for rig {}: {reason}", rig.name));
        let file = std::path::Path::new(&rig.name);
        crate::rig::check_urdf_size(&urdf, file).map_err(|e| bad(e.to_string()))?;
        let robot = urdf_rs::read_from_string(&urdf).map_err(|e| bad(e.to_string()))?;
        let tree = UrdfTree::new(&robot, file).map_err(|e| bad(e.to_string()))?;
        let mut segments = Vec::new();
        let mut actuated = rig.joints.iter().enumerate();
        let chain = tree.path_to(&rig.tool_frame).ok_or_else(|| {
            bad(format!(
                "no chain from {} to {}",
                tree.root(),
                rig.tool_frame
            ))
        })?;
        for urdf_joint in chain {
            let origin = origin_from_xyz_rpy(
                DVec3::from_array(*urdf_joint.origin.xyz),
                DVec3::from_array(*urdf_joint.origin.rpy),
            );
            let motion = if urdf_joint.joint_type == urdf_rs::JointType::Fixed {
                Motion::Fixed(origin)
            } else {
                match actuated.next() {
                    Some((index, joint)) if joint.name == urdf_joint.name => Motion::Joint {
                        index,
                        joint: Joint {
                            origin,
                            ..joint.clone()
                        },
                    },
                    _ => return Err(bad(format!("joint {} is not the rig's", urdf_joint.name))),
                }
            };
            segments.push(Segment {
                parent: urdf_joint.parent.link.clone(),
                child: urdf_joint.child.link.clone(),
                motion,
            });
        }
        let description = Self {
            urdf,
            joint_names: rig.joint_names().map(str::to_owned).collect(),
            chain: segments.len(),
            segments,
        };
        description
            .check_against(rig)
            .map_err(|e| bad(e.to_string()))?;
        Ok(description)
    }

    /// The URDF text, as attached to the log.
    pub fn urdf(&self) -> &str {
        &self.urdf
    }

    /// `(parent, child)` frame ids, base frame first, tool frame at the chain's end, then
    /// the fixed links hung on it.
    pub fn frames(&self) -> impl Iterator<Item = (&str, &str)> {
        self.segments
            .iter()
            .map(|s| (s.parent.as_str(), s.child.as_str()))
    }

    /// Whether each link of [`Self::frames`] is fixed to its parent (a fixed joint, the tool
    /// transform, a cell object): ROS 2 sends those once, on `/tf_static`.
    pub fn fixed(&self) -> impl Iterator<Item = bool> + '_ {
        self.segments
            .iter()
            .map(|s| matches!(s.motion, Motion::Fixed(_)))
    }

    /// The tf frame id of each frame of the rig: its base (before joint 1), then the frame
    /// after each joint (the child link of that joint): where its collision bodies ride.
    pub fn rig_frames(&self) -> Vec<String> {
        let base = self.segments.first().map(|s| s.parent.clone());
        base.into_iter()
            .chain(self.segments.iter().filter_map(|s| match s.motion {
                Motion::Joint { .. } => Some(s.child.clone()),
                Motion::Fixed(_) => None,
            }))
            .collect()
    }

    /// Each link's transform from its parent at `positions`, in [`Self::frames`] order
    /// (the chain's, composed, give the rig's tool frame). `None` when the count is wrong.
    pub fn link_transforms<'a>(
        &'a self,
        positions: &'a [f64],
    ) -> Option<impl Iterator<Item = DAffine3> + 'a> {
        (positions.len() == self.joint_names.len()).then(|| {
            self.segments.iter().map(|segment| match &segment.motion {
                Motion::Fixed(transform) => *transform,
                Motion::Joint { index, joint } => joint.transform(positions[*index]),
            })
        })
    }

    fn check_against(&self, rig: &Rig) -> Result<(), DescriptionMismatch> {
        let chain = &self.segments[..self.chain];
        if chain.last().map(|s| s.child.as_str()) != Some(rig.tool_frame.as_str()) {
            return Err(DescriptionMismatch::End(rig.tool_frame.clone()));
        }
        let used = self
            .segments
            .iter()
            .filter(|s| matches!(s.motion, Motion::Joint { .. }))
            .count();
        if used != rig.dof() {
            return Err(DescriptionMismatch::Axes {
                used,
                dof: rig.dof(),
            });
        }
        // Mid-range positions: every axis away from zero, so every origin and axis counts.
        let probe: Vec<f64> = rig
            .joints
            .iter()
            .map(|j| 0.37 * j.limits.lower + 0.63 * j.limits.upper)
            .collect();
        let composed = self.link_transforms(&probe).map(|links| {
            links
                .take(self.chain)
                .fold(DAffine3::IDENTITY, |frame, link| frame * link)
        });
        let expected = rig.forward(&probe)?;
        match composed {
            Some(tool)
                if (tool.translation - expected.translation).length() <= FK_AGREEMENT_M
                    && tool.matrix3.abs_diff_eq(expected.matrix3, FK_AGREEMENT_M) =>
            {
                Ok(())
            }
            _ => Err(DescriptionMismatch::Kinematics),
        }
    }
}

/// Why a robot description is not the rig's.
#[derive(Debug, thiserror::Error)]
enum DescriptionMismatch {
    #[error("the chain does not end at {0}")]
    End(String),
    #[error("{used} actuated joints for {dof} axes")]
    Axes { used: usize, dof: usize },
    #[error(transparent)]
    Dof(#[from] crate::rig::DofMismatch),
    #[error("its links do not compose to the rig's forward kinematics")]
    Kinematics,
}

/// `/tf` and `/joint_states` for one set of positions, refilled in place (the run log's
/// writer thread and the live Foxglove server each keep one).
pub struct RobotMessages {
    robot: Option<Arc<RobotDescription>>,
    tf: FrameTransforms,
    joints: JointStates,
}

impl RobotMessages {
    /// `/tf` needs the rig's links (`robot`); `/joint_states` only its joint names.
    pub fn new(robot: Option<Arc<RobotDescription>>, joint_names: &[String]) -> Self {
        let tf = FrameTransforms {
            transforms: robot
                .iter()
                .flat_map(|robot| robot.frames())
                .map(|(parent, child)| FrameTransform {
                    parent_frame_id: parent.to_owned(),
                    child_frame_id: child.to_owned(),
                    ..FrameTransform::default()
                })
                .collect(),
        };
        let joints = JointStates {
            timestamp: None,
            joints: joint_names
                .iter()
                .map(|name| JointState {
                    name: name.clone(),
                    ..JointState::default()
                })
                .collect(),
        };
        Self { robot, tf, joints }
    }

    /// Refills both messages for `positions` (and `velocities`, where known) stamped
    /// `stamp_ns`; `false`, leaving them as they were, when a position is not finite or
    /// their count is not the rig's: no transform can be drawn from them.
    pub fn fill(&mut self, stamp_ns: u64, positions: &[f64], velocities: Option<&[f64]>) -> bool {
        if positions.len() != self.joints.joints.len() || !positions.iter().all(|q| q.is_finite()) {
            return false;
        }
        let stamp = timestamp(stamp_ns);
        if let Some(links) = self
            .robot
            .as_ref()
            .and_then(|r| r.link_transforms(positions))
        {
            for (message, link) in self.tf.transforms.iter_mut().zip(links) {
                let (_, rotation, translation) = link.to_scale_rotation_translation();
                message.timestamp = Some(stamp);
                message.translation = Some(vector(translation));
                message.rotation = Some(quaternion(rotation));
            }
        }
        self.joints.timestamp = Some(stamp);
        for (i, (joint, q)) in self.joints.joints.iter_mut().zip(positions).enumerate() {
            joint.position = Some(*q);
            joint.velocity = velocities
                .and_then(|v| v.get(i))
                .filter(|v| v.is_finite())
                .copied();
        }
        true
    }

    /// `/tf`, for a rig with links.
    pub fn tf(&self) -> Option<&FrameTransforms> {
        self.robot.as_ref().map(|_| &self.tf)
    }

    pub fn joint_states(&self) -> &JointStates {
        &self.joints
    }
}

/// A world drawn in the log as `foxglove.SceneUpdate` on [`SCENE_TOPIC`] (the paint room,
/// the sloth's branches): the writer thread feeds it every measured state, in job time, so
/// the paint it reports is the paint at that state.
pub trait LoggedScene: Send {
    /// The actual positions of one state.
    fn observe(&mut self, actual: &[f64]);
    /// The static geometry.
    fn scene(&self) -> SceneView;
    /// Paint added since the previous call.
    fn drain_paint(&mut self) -> Vec<PaintQuad>;
    /// The cell's closest pair at the last observed state, when within the margin.
    fn closest(&mut self) -> Option<ClosestView> {
        None
    }
}

/// The recorder's handle on a [`LoggedScene`] (the writer thread takes it), and the frame
/// its coordinates are in.
#[derive(Clone)]
pub struct SceneSource {
    scene: Arc<Mutex<Option<Box<dyn LoggedScene>>>>,
    frame_id: String,
}

impl SceneSource {
    pub fn new(scene: Box<dyn LoggedScene>, frame_id: &str) -> Self {
        Self {
            scene: Arc::new(Mutex::new(Some(scene))),
            frame_id: frame_id.to_owned(),
        }
    }

    fn take(&self) -> Option<(Box<dyn LoggedScene>, String)> {
        let scene = self
            .scene
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take()?;
        Some((scene, self.frame_id.clone()))
    }
}

impl std::fmt::Debug for SceneSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SceneSource")
    }
}

/// The same source, not merely an equal one.
impl PartialEq for SceneSource {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.scene, &other.scene)
    }
}

/// The log's scene channel and what it has written of the scene.
struct SceneLog {
    channel: u16,
    scene: Box<dyn LoggedScene>,
    view: SceneView,
    frame_id: String,
    /// The tf frame id of each frame of the rig, where its collision bodies ride.
    body_frames: Vec<String>,
    /// The closest pair marked last (pair and status).
    marked: Option<(String, String, String)>,
    /// When the static scene was last written (job time), and paint batches so far.
    last_full_t: Option<f64>,
    batches: u64,
}

/// The writer thread's Foxglove channels and the messages it refills for each state.
pub(super) struct FoxgloveLog {
    robot: Option<(RobotMessages, u16, u16)>,
    scene: Option<SceneLog>,
    last_t: Option<f64>,
    sequence: u32,
    buffer: Vec<u8>,
}

impl FoxgloveLog {
    /// Adds the schemas, the channels and the URDF attachment of what there is: `/tf` and
    /// `/joint_states` for a rig with links, `/scene` for a world. `None` for neither.
    pub(super) fn open<W: Write + Seek>(
        writer: &mut Writer<W>,
        robot: Option<Arc<RobotDescription>>,
        scene: Option<&SceneSource>,
    ) -> Result<Option<Self>, LogError> {
        let body_frames = robot
            .as_ref()
            .map(|robot| robot.rig_frames())
            .unwrap_or_default();
        let robot = match robot {
            Some(robot) => {
                let tf_channel = add_channel::<FrameTransforms, W>(writer, TF_TOPIC)?;
                let joints_channel = add_channel::<JointStates, W>(writer, JOINT_STATES_TOPIC)?;
                writer.attach(&Attachment {
                    log_time: 0,
                    create_time: 0,
                    name: URDF_ATTACHMENT.to_owned(),
                    media_type: URDF_MEDIA_TYPE.to_owned(),
                    data: Cow::Borrowed(robot.urdf.as_bytes()),
                })?;
                let names = robot.joint_names.clone();
                let messages = RobotMessages::new(Some(robot), &names);
                Some((messages, tf_channel, joints_channel))
            }
            None => None,
        };
        let scene = match scene.and_then(SceneSource::take) {
            Some((scene, frame_id)) => Some(SceneLog {
                channel: add_channel::<SceneUpdate, W>(writer, SCENE_TOPIC)?,
                view: scene.scene(),
                scene,
                frame_id,
                body_frames,
                marked: None,
                last_full_t: None,
                batches: 0,
            }),
            None => None,
        };
        Ok((robot.is_some() || scene.is_some()).then(|| Self {
            robot,
            scene,
            last_t: None,
            sequence: 0,
            buffer: Vec::with_capacity(2048),
        }))
    }

    /// Feeds the scene one measured state, and writes `/tf`, `/joint_states` and new paint
    /// when due ([`TF_PERIOD_S`]); the static scene goes in at the first state and again
    /// every [`SCENE_REPEAT_S`], so a player that seeks finds it. Returns the message
    /// bytes written.
    pub(super) fn state<W: Write + Seek>(
        &mut self,
        writer: &mut Writer<W>,
        t: f64,
        log_time: u64,
        positions: &[f64],
        velocities: &[f64],
    ) -> Result<usize, LogError> {
        if !positions.iter().all(|q| q.is_finite()) {
            return Ok(0);
        }
        if let Some(scene) = &mut self.scene {
            scene.scene.observe(positions);
        }
        let due = self
            .last_t
            // Time going back (a log restarted at 0) starts the decimation afresh.
            .is_none_or(|last| t - last >= TF_PERIOD_S - TIME_SLACK_S || t < last);
        if !due {
            return Ok(0);
        }
        self.last_t = Some(t);
        let mut bytes = 0;
        if let Some((messages, tf_channel, joints_channel)) = &mut self.robot
            && messages.fill(log_time, positions, Some(velocities))
            && let Some(tf) = messages.tf()
        {
            for (channel, message) in [
                (*tf_channel, tf as &dyn Protobuf),
                (*joints_channel, messages.joint_states()),
            ] {
                bytes += write(
                    writer,
                    &mut self.buffer,
                    channel,
                    self.sequence,
                    log_time,
                    message,
                )?;
            }
        }
        if let Some(scene) = &mut self.scene {
            let stamp = timestamp(log_time);
            let fresh = scene.scene.drain_paint();
            scene.view.paint.extend_from_slice(&fresh);
            let repeat = scene
                .last_full_t
                .is_none_or(|last| t - last >= SCENE_REPEAT_S || t < last);
            let update = if repeat {
                scene.last_full_t = Some(t);
                scene.batches = 0;
                Some(full_update(
                    &scene.view,
                    &scene.frame_id,
                    &scene.body_frames,
                    stamp,
                ))
            } else {
                scene.batches += 1;
                paint_update(&scene.view, &fresh, scene.batches, &scene.frame_id, stamp)
            };
            let closest = scene.scene.closest();
            let marked = closest
                .as_ref()
                .map(|c| (c.a.clone(), c.b.clone(), c.status.clone()));
            // Marked again after a full update (which deleted every entity) or on a change.
            let mark = (repeat || marked != scene.marked).then(|| {
                scene.marked = marked;
                closest_update(
                    &scene.view,
                    closest.as_ref(),
                    &scene.frame_id,
                    &scene.body_frames,
                    stamp,
                )
            });
            for update in update.into_iter().chain(mark) {
                bytes += write(
                    writer,
                    &mut self.buffer,
                    scene.channel,
                    self.sequence,
                    log_time,
                    &update,
                )?;
            }
        }
        self.sequence = self.sequence.wrapping_add(1);
        Ok(bytes)
    }
}

/// Encodes `message` into `buffer` and writes it on `channel`; its size.
fn write<W: Write + Seek>(
    writer: &mut Writer<W>,
    buffer: &mut Vec<u8>,
    channel_id: u16,
    sequence: u32,
    log_time: u64,
    message: &dyn Protobuf,
) -> Result<usize, LogError> {
    buffer.clear();
    message.encode_into(buffer)?;
    let header = MessageHeader {
        channel_id,
        sequence,
        log_time,
        publish_time: log_time,
    };
    writer.write_to_known_channel(&header, buffer)?;
    Ok(buffer.len())
}

/// The two message types, encoded through one loop.
trait Protobuf {
    fn encode_into(&self, buffer: &mut Vec<u8>) -> Result<(), LogError>;
}

impl<T: Encode<Error = prost::EncodeError>> Protobuf for T {
    fn encode_into(&self, buffer: &mut Vec<u8>) -> Result<(), LogError> {
        self.encode(buffer)
            .map_err(|e| LogError::Setup(format!("protobuf encoding: {e}")))
    }
}

fn add_channel<T: Encode, W: Write + Seek>(
    writer: &mut Writer<W>,
    topic: &str,
) -> Result<u16, LogError> {
    let schema = T::get_schema()
        .ok_or_else(|| LogError::Setup(format!("{topic}: the foxglove crate gave no schema")))?;
    let id = writer.add_schema(&schema.name, &schema.encoding, &schema.data)?;
    Ok(writer.add_channel(id, topic, PROTOBUF, &BTreeMap::new())?)
}

/// A Foxglove timestamp of `nanos` since the epoch of the clock in use.
pub fn timestamp(nanos: u64) -> Timestamp {
    const NANOS: u64 = 1_000_000_000;
    // Job times under 136 years fit u32 seconds; saturate beyond, as job_time_ns does.
    let sec = u32::try_from(nanos / NANOS).unwrap_or(u32::MAX);
    Timestamp::new(sec, (nanos % NANOS) as u32)
}

fn quaternion(q: DQuat) -> Quaternion {
    Quaternion {
        x: q.x,
        y: q.y,
        z: q.z,
        w: q.w,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{load_rig, rig_to_urdf};
    use std::path::Path;

    fn irb120() -> Rig {
        load_rig(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/irb120.toml"))
            .expect("the IRB 120 rig loads")
    }

    #[test]
    fn generated_links_compose_to_the_tool_pose() {
        let rig = irb120();
        let robot = RobotDescription::generated(&rig, &Cell::builtin());
        let q = [0.3, -0.4, 0.5, -1.1, 0.7, 2.0];
        // The chain's seven links, base to tool0; the floor hangs on the base after them.
        let tool = robot
            .link_transforms(&q)
            .expect("the IRB 120 takes six positions")
            .take(7)
            .fold(DAffine3::IDENTITY, |a, b| a * b);
        let expected = rig.forward(&q).expect("the IRB 120 takes six positions");
        assert!((tool.translation - expected.translation).length() < 1e-12);
        let frames: Vec<_> = robot.frames().collect();
        assert_eq!(frames.len(), 8);
        assert_eq!(frames[0], ("base_link", "link_1"));
        assert_eq!(frames[6], ("link_6", "tool0"));
        assert_eq!(frames[7], ("base_link", "floor"));
    }

    #[test]
    fn a_urdf_file_keeps_its_fixed_links_and_a_wrong_one_is_refused() {
        let rig = irb120();
        let text = rig_to_urdf(&rig);
        let robot = RobotDescription::from_urdf(&rig, text.clone())
            .expect("the generated URDF matches the rig");
        // The chain's links; the generated description adds the floor after them.
        assert_eq!(
            robot.frames().collect::<Vec<_>>(),
            RobotDescription::generated(&rig, &Cell::builtin())
                .frames()
                .take(7)
                .collect::<Vec<_>>()
        );
        // Joint 2's origin moved (the bodies' solids carry the same numbers before it).
        let at = text
            .find("<joint name=\"joint_2\"")
            .expect("joint 2 is written");
        let (head, tail) = text.split_at(at);
        let moved = format!(
            "{head}{}",
            tail.replacen("xyz=\"0 0 0.29\"", "xyz=\"0 0 0.3\"", 1)
        );
        assert_ne!(moved, text);
        assert!(RobotDescription::from_urdf(&rig, moved).is_err());
    }
}
