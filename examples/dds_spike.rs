//! Spike: JointState on /joint_states over DDS, loopback only (not to keep).
use ros2_client::{
    Context, MessageTypeName, Name, NodeName, NodeOptions, QosProfile,
    qos::{Durability, History, WhenFull},
};
use rustdds::DomainParticipantBuilder;
use serde::Serialize;
use std::net::{IpAddr, Ipv4Addr};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

#[derive(Serialize)]
struct Time { sec: i32, nanosec: u32 }
#[derive(Serialize)]
struct Header { stamp: Time, frame_id: String }
#[derive(Serialize)]
struct JointState { header: Header, name: Vec<String>, position: Vec<f64>, velocity: Vec<f64>, effort: Vec<f64> }

fn main() {
    let dp = DomainParticipantBuilder::new(0)
        .with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)])
        .build()
        .unwrap();
    let ctx = Context::from_domain_participant(dp).unwrap();
    let mut node = ctx.new_node(NodeName::new("/", "rigbridge").unwrap(), NodeOptions::new().enable_rosout(false)).unwrap();
    let qos = QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 });
    let topic = node.create_topic(&Name::new("/", "joint_states").unwrap(), MessageTypeName::new("sensor_msgs", "JointState"), &qos).unwrap();
    let p = node.create_publisher::<JointState>(&topic, None).unwrap();
    let spinner = node.spinner().unwrap();
    std::thread::spawn(move || tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap().block_on(spinner.spin()));
    for i in 0..1000 {
        let now = SystemTime::now().duration_since(UNIX_EPOCH).unwrap();
        let m = JointState { header: Header { stamp: Time { sec: now.as_secs() as i32, nanosec: now.subsec_nanos() }, frame_id: String::new() },
          name: vec!["joint_1".into()], position: vec![i as f64], velocity: vec![], effort: vec![] };
        let _ = p.publish(m);
        std::thread::sleep(Duration::from_millis(10));
    }
}
