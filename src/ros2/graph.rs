//! Names on the wire as rmw_zenoh writes them (ros2/rmw_zenoh, `docs/design.md` and
//! `rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`; docs/ros2.md): a topic's key expression
//! `<domain>/<topic without its leading slash>/<DDS type>/<RIHS01 hash>`, the liveliness
//! tokens `@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/
//! <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]` (a `/` inside a name becomes `%`), the
//! entity's gid (XXH3-128 of its token) and the attachment every sample carries.
//!
//! Owns these names and bytes; it must not open a session or know about the daemon.

use thiserror::Error;

/// The liveliness tokens' admin space.
const ADMIN_SPACE: &str = "@ros2_lv";
/// What stands for `/` inside one key segment.
const SLASH_REPLACEMENT: char = '%';
/// The QoS segment of a token for ROS 2's default publisher and subscription profile
/// (reliable, volatile, keep last 10): rmw_zenoh writes only what differs from its own
/// default (keep last 42), so only the depth.
pub const DEFAULT_QOS: &str = "::,10:,:,:,,";
/// The node every rig's entities hang from, in the rig's namespace.
pub const NODE_NAME: &str = "rigbridge";

/// The DDS type names rmw_zenoh puts in key expressions and tokens.
pub const JOINT_STATE_DDS: &str = "sensor_msgs::msg::dds_::JointState_";
pub const JOINT_TRAJECTORY_DDS: &str = "trajectory_msgs::msg::dds_::JointTrajectory_";

/// A rig name that cannot be a ROS 2 namespace.
#[derive(Debug, Error)]
#[error(
    "rig name `{0}` cannot be a ROS 2 namespace: it must start with a letter and hold only \
     letters, digits and underscores"
)]
pub struct BadNamespace(pub String);

/// The rig's name, checked as one ROS 2 name token (so that `/<rig>/joint_states` is a valid
/// topic and a valid key expression).
pub fn check_namespace(rig: &str) -> Result<(), BadNamespace> {
    let mut chars = rig.chars();
    let first_ok = chars.next().is_some_and(|c| c.is_ascii_alphabetic());
    if first_ok && chars.all(|c| c.is_ascii_alphanumeric() || c == '_') {
        Ok(())
    } else {
        Err(BadNamespace(rig.to_string()))
    }
}

fn mangle(name: &str) -> String {
    name.replace('/', &SLASH_REPLACEMENT.to_string())
}

/// Where one ROS 2 node of rigbridge lives: its domain, its Zenoh session's id, its
/// namespace (`/<rig>`).
#[derive(Debug, Clone)]
pub struct NodeNames {
    pub domain_id: u32,
    /// The Zenoh session id as Zenoh prints it (lowercase hex).
    pub session_id: String,
    /// `/<rig>`.
    pub namespace: String,
    /// The node's own entity id; entities number on from it.
    pub node_id: u32,
}

/// A topic of a node: the name, the DDS type and its hash.
#[derive(Debug, Clone, Copy)]
pub struct TopicType {
    pub dds_type: &'static str,
    pub hash: &'static str,
}

impl NodeNames {
    pub fn new(domain_id: u32, session_id: String, rig: &str) -> Self {
        NodeNames {
            domain_id,
            session_id,
            namespace: format!("/{rig}"),
            node_id: 0,
        }
    }

    /// `/<rig>/<name>`.
    pub fn topic(&self, name: &str) -> String {
        format!("{}/{name}", self.namespace)
    }

    /// The key expression samples of `topic` travel on.
    pub fn topic_key(&self, topic: &str, kind: TopicType) -> String {
        format!(
            "{}/{}/{}/{}",
            self.domain_id,
            topic.trim_matches('/'),
            kind.dds_type,
            kind.hash
        )
    }

    /// The liveliness token of the node itself.
    pub fn node_token(&self) -> String {
        self.token_prefix(self.node_id, "NN")
    }

    /// The liveliness token of a publisher (`MP`) or subscription (`MS`) with id `entity`.
    pub fn topic_token(&self, entity: u32, kind: &str, topic: &str, ty: TopicType) -> String {
        format!(
            "{}/{}/{}/{}/{DEFAULT_QOS}",
            self.token_prefix(entity, kind),
            mangle(topic),
            mangle(ty.dds_type),
            ty.hash
        )
    }

    fn token_prefix(&self, entity: u32, kind: &str) -> String {
        // The default enclave is "/", mangled like every name.
        format!(
            "{ADMIN_SPACE}/{}/{}/{}/{entity}/{kind}/{}/{}/{NODE_NAME}",
            self.domain_id,
            self.session_id,
            self.node_id,
            mangle("/"),
            mangle(&self.namespace)
        )
    }
}

/// The gid rmw_zenoh gives an entity: XXH3-128 of its liveliness token, low half first,
/// each half little-endian.
pub fn gid(token: &str) -> [u8; 16] {
    xxhash_rust::xxh3::xxh3_128(token.as_bytes()).to_le_bytes()
}

/// The attachment of every sample rmw_zenoh publishes, in Zenoh's own serialisation
/// (zenoh-ext): three (key, value) pairs in order, a string as its LEB128 length and bytes,
/// an int64 as 8 little-endian bytes, the gid as a length-prefixed byte string.
pub fn attachment(sequence_number: i64, source_timestamp_ns: i64, gid: &[u8; 16]) -> Vec<u8> {
    let mut out = Vec::with_capacity(80);
    put_bytes(&mut out, b"sequence_number");
    out.extend_from_slice(&sequence_number.to_le_bytes());
    put_bytes(&mut out, b"source_timestamp");
    out.extend_from_slice(&source_timestamp_ns.to_le_bytes());
    put_bytes(&mut out, b"source_gid");
    put_bytes(&mut out, gid);
    out
}

fn put_bytes(out: &mut Vec<u8>, bytes: &[u8]) {
    let mut length = bytes.len();
    // LEB128: seven bits a byte, the high bit set on all but the last.
    while length >= 0x80 {
        out.push((length as u8 & 0x7f) | 0x80);
        length >>= 7;
    }
    out.push(length as u8);
    out.extend_from_slice(bytes);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names() -> NodeNames {
        NodeNames::new(0, "4f1c".into(), "irb120")
    }

    const STATE: TopicType = TopicType {
        dds_type: JOINT_STATE_DDS,
        hash: "RIHS01_ab",
    };

    #[test]
    fn keys_and_tokens_follow_rmw_zenoh() {
        let n = names();
        let topic = n.topic("joint_states");
        assert_eq!(topic, "/irb120/joint_states");
        assert_eq!(
            n.topic_key(&topic, STATE),
            "0/irb120/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_ab"
        );
        assert_eq!(n.node_token(), "@ros2_lv/0/4f1c/0/0/NN/%/%irb120/rigbridge");
        assert_eq!(
            n.topic_token(1, "MP", &topic, STATE),
            "@ros2_lv/0/4f1c/0/1/MP/%/%irb120/rigbridge/%irb120%joint_states/\
             sensor_msgs::msg::dds_::JointState_/RIHS01_ab/::,10:,:,:,,"
        );
    }

    #[test]
    fn rig_names_that_are_no_ros_name_are_refused() {
        assert!(check_namespace("irb120").is_ok());
        assert!(check_namespace("cell_2").is_ok());
        for bad in ["", "2cell", "north-east", "a/b", "a*"] {
            assert!(check_namespace(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_attachment_is_three_pairs_in_zenoh_ext_serialisation() {
        let bytes = attachment(7, -2, &[9; 16]);
        let mut expected = vec![15];
        expected.extend_from_slice(b"sequence_number");
        expected.extend_from_slice(&[7, 0, 0, 0, 0, 0, 0, 0]);
        expected.push(16);
        expected.extend_from_slice(b"source_timestamp");
        expected.extend_from_slice(&[0xfe, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff]);
        expected.push(10);
        expected.extend_from_slice(b"source_gid");
        expected.push(16);
        expected.extend_from_slice(&[9; 16]);
        assert_eq!(bytes, expected);
        let mut long = Vec::new();
        put_bytes(&mut long, &[0; 300]);
        assert_eq!(&long[..2], &[0xac, 0x02], "300 = 0b10_0101100");
    }
}
