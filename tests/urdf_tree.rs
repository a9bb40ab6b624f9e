//! A URDF is checked as a tree before a rig is built from it (audit finding 7): a joint
//! cycle and a 100,000-joint chain are refused with a clear error in well under a second,
//! never a stack overflow; a link with two parents, a joint naming a missing link, several
//! roots and a chain past the joint cap are refused naming the joint (or link) and the file;
//! a 1,000-joint chain within the caps loads. The refusals are checked through the binary
//! (`rigbridge fk --rig`, its exit status and message) as a user meets them.

use crate::common;

use common::cli::rigbridge;
use rigbridge::rig::{MAX_URDF_BYTES, MAX_URDF_JOINTS, load_rig, rig_from_urdf};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The issue's figure is 1 s; the bound asserted is generous for a loaded CI machine, and
/// the measured time is printed.
const MAX_REFUSAL_TIME: Duration = Duration::from_secs(5);

fn revolute(name: &str, parent: &str, child: &str) -> String {
    format!(
        r#"<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/><axis xyz="0 0 1"/><origin xyz="0 0 0.1" rpy="0 0 0"/><limit lower="-1" upper="1" velocity="1" effort="0"/></joint>"#
    )
}

/// A URDF with `links` and the joints `(name, parent, child)`.
fn urdf(links: &[&str], joints: &[(&str, &str, &str)]) -> String {
    let mut text = String::from(r#"<?xml version="1.0"?><robot name="t">"#);
    for link in links {
        text += &format!(r#"<link name="{link}"/>"#);
    }
    for (name, parent, child) in joints {
        text += &revolute(name, parent, child);
    }
    text + "</robot>"
}

/// A serial chain of `n` revolute joints `j0..`, links `l0..=ln`.
fn chain(n: usize) -> String {
    let mut text = String::from(r#"<?xml version="1.0"?><robot name="chain">"#);
    for i in 0..=n {
        text += &format!(r#"<link name="l{i}"/>"#);
    }
    for i in 0..n {
        text += &revolute(&format!("j{i}"), &format!("l{i}"), &format!("l{}", i + 1));
    }
    text + "</robot>"
}

fn write(name: &str, text: &str) -> PathBuf {
    let path = common::scratch_file("urdf", name);
    std::fs::write(&path, text).unwrap();
    path
}

/// `rigbridge fk --rig PATH` on no rows: its exit code (None when killed by a signal, as a
/// stack overflow's abort is), stderr and how long it took.
fn fk(path: &Path) -> (Option<i32>, String, Duration) {
    let start = Instant::now();
    let output = rigbridge()
        .arg("fk")
        .arg("--rig")
        .arg(path)
        .args(["--input", "/dev/null"])
        .output()
        .unwrap();
    let took = start.elapsed();
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    (output.status.code(), stderr, took)
}

/// The binary refuses `path` in time with exit 1 and a message holding each of `expected`.
fn assert_refused(what: &str, path: &Path, expected: &[&str]) {
    let (code, stderr, took) = fk(path);
    let bytes = std::fs::metadata(path).unwrap().len();
    println!(
        "{what} ({bytes} bytes): refused in {:.3} s, exit {code:?}: {}",
        took.as_secs_f64(),
        stderr.trim()
    );
    assert_eq!(code, Some(1), "{what}: exit 1, not a crash: {stderr}");
    assert!(!stderr.contains("overflow"), "{stderr}");
    assert!(
        stderr.contains(path.file_name().unwrap().to_str().unwrap()),
        "names the file: {stderr}"
    );
    for text in expected {
        assert!(stderr.contains(text), "{what}: `{text}` in: {stderr}");
    }
    assert!(took < MAX_REFUSAL_TIME, "{what}: {took:?}");
}

#[test]
fn a_joint_cycle_is_refused_naming_the_joint() {
    // The audit's shape: root -> a -> b -> a (630 bytes there, about as many here).
    let text = urdf(
        &["root", "a", "b"],
        &[
            ("root_a", "root", "a"),
            ("a_b", "a", "b"),
            ("b_a", "b", "a"),
        ],
    );
    let path = write("cycle.urdf", &text);
    assert_refused(
        "root -> a -> b -> a",
        &path,
        &["joint[name=b_a]", "root_a", "one parent joint"],
    );

    // A cycle with no root at all, and one beside a root: the joint that closes it is named.
    let ring = urdf(&["a", "b"], &[("a_b", "a", "b"), ("b_a", "b", "a")]);
    assert_refused(
        "a -> b -> a",
        &write("ring.urdf", &ring),
        &["joint[name=b_a]", "cycle"],
    );
    let beside = urdf(
        &["root", "x", "a", "b"],
        &[
            ("root_x", "root", "x"),
            ("a_b", "a", "b"),
            ("b_a", "b", "a"),
        ],
    );
    assert_refused(
        "root -> x; a -> b -> a",
        &write("beside.urdf", &beside),
        &["cycle", "b -> a"],
    );
}

#[test]
fn a_chain_of_100_000_joints_is_refused_at_once() {
    let text = chain(100_000);
    assert!(text.len() > MAX_URDF_BYTES);
    let path = write("chain100k.urdf", &text);
    assert_refused(
        "a 100,000-joint chain",
        &path,
        &["(file size)", &format!("at most {MAX_URDF_BYTES} bytes")],
    );
    // The cap holds for URDF text that comes from elsewhere than a file, too.
    let start = Instant::now();
    let error = rig_from_urdf(&text, Path::new("chain100k.urdf"))
        .unwrap_err()
        .to_string();
    println!(
        "rig_from_urdf on the same text: {:.3} s: {error}",
        start.elapsed().as_secs_f64()
    );
    assert!(error.contains("(file size)"), "{error}");
    assert!(start.elapsed() < MAX_REFUSAL_TIME);
}

#[test]
fn a_chain_past_the_joint_cap_is_refused_naming_the_first_joint_past_it() {
    let text = chain(MAX_URDF_JOINTS + 500);
    assert!(
        text.len() <= MAX_URDF_BYTES,
        "under the size cap: {}",
        text.len()
    );
    let path = write("chain-long.urdf", &text);
    let first_past = format!("joint[name=j{MAX_URDF_JOINTS}]");
    assert_refused("a chain past the joint cap", &path, &[&first_past]);
}

#[test]
fn a_deep_chain_within_the_caps_loads() {
    let n = 1000;
    let path = write("chain-1000.urdf", &chain(n));
    let start = Instant::now();
    let rig = load_rig(&path).unwrap_or_else(|e| panic!("{e}"));
    println!(
        "a {n}-joint chain loads in {:.3} s",
        start.elapsed().as_secs_f64()
    );
    assert_eq!(rig.dof(), n);
    assert_eq!(rig.base_frame, "l0");
    assert_eq!(rig.tool_frame, format!("l{n}"));
    // Each joint lifts the next frame 0.1 m along z: at zero the tool is n * 0.1 m up.
    let tool = rig.forward(&vec![0.0; n]).unwrap().translation;
    assert!((tool.z - n as f64 * 0.1).abs() < 1e-9, "{tool}");
}

#[test]
fn a_graph_that_is_no_tree_is_refused_naming_the_joint_and_the_file() {
    let file = Path::new("bad.urdf");
    let cases = [
        (
            "a missing link",
            urdf(
                &["base", "a"],
                &[("base_a", "base", "a"), ("a_c", "a", "c")],
            ),
            vec![
                "bad.urdf",
                "joint[name=a_c].child",
                "= c",
                "no link of that name",
            ],
        ),
        (
            "two parents",
            urdf(
                &["base", "a", "b"],
                &[
                    ("base_a", "base", "a"),
                    ("base_b", "base", "b"),
                    ("a_b", "a", "b"),
                ],
            ),
            vec!["joint[name=a_b].child", "already the child of joint base_b"],
        ),
        (
            "two roots",
            urdf(&["base", "a", "other"], &[("base_a", "base", "a")]),
            vec!["several root links", "base, other"],
        ),
        (
            "a joint declared twice",
            urdf(&["base", "a", "b"], &[("j", "base", "a"), ("j", "a", "b")]),
            vec!["joint[name=j]", "declared twice"],
        ),
    ];
    for (what, text, expected) in cases {
        let error = rig_from_urdf(&text, file).unwrap_err().to_string();
        println!("{what}: {error}");
        for text in expected {
            assert!(error.contains(text), "{what}: `{text}` in: {error}");
        }
    }
}
