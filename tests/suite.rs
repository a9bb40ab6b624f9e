//! The integration tests' one binary, `cargo test --test suite`: each file `tests/X.rs` is
//! its module `X`, so its tests are named `X::name` (`cargo test --test suite paint::` runs
//! `tests/paint.rs`'s). One binary links the library and its dependencies once, where a
//! binary a file linked them some 60 times (docs/testing.md has the figures). Owns the list
//! of modules only; what each tests is in its own file.
//!
//! Cargo.toml turns cargo's discovery of `tests/*.rs` off (`autotests = false`) and names
//! this binary and the files that need a process of their own: `codec` and `stream_alloc`
//! (each installs a counting global allocator), `realtime` (it reads its own process's
//! threads), `can` and `canopen` (scripts/test.sh runs each alone in the SocketCAN VM). A
//! new `tests/*.rs` joins the list below, or Cargo.toml's; `every_test_file_is_built` fails
//! until it does.

mod common;

#[path = "common/flood.rs"]
mod flood;
#[path = "common/free_pairs.rs"]
mod free_pairs;
#[path = "common/in_process.rs"]
mod in_process;
#[path = "common/proxy.rs"]
mod proxy;

#[path = "api_hardening.rs"]
mod api_hardening;
#[path = "batch.rs"]
mod batch;
#[path = "bounds.rs"]
mod bounds;
#[path = "cell_agreement.rs"]
mod cell_agreement;
#[path = "cell_tools.rs"]
mod cell_tools;
#[path = "cell_tunnelling.rs"]
mod cell_tunnelling;
#[path = "cli.rs"]
mod cli;
#[path = "collisions.rs"]
mod collisions;
#[path = "config.rs"]
mod config;
#[path = "conformance.rs"]
mod conformance;
#[path = "contacts.rs"]
mod contacts;
#[path = "daemon.rs"]
mod daemon;
#[path = "dynamixel.rs"]
mod dynamixel;
#[path = "egm.rs"]
mod egm;
#[path = "egm_spoof.rs"]
mod egm_spoof;
#[path = "executor.rs"]
mod executor;
#[path = "faults.rs"]
mod faults;
#[path = "foxglove.rs"]
mod foxglove;
#[path = "foxglove_live.rs"]
mod foxglove_live;
#[path = "free_plan.rs"]
mod free_plan;
#[path = "gait.rs"]
mod gait;
#[path = "gait_forest.rs"]
mod gait_forest;
#[path = "ik_errors.rs"]
mod ik_errors;
#[path = "ik_paths.rs"]
mod ik_paths;
#[path = "ik_round_trip.rs"]
mod ik_round_trip;
#[path = "install.rs"]
mod install;
#[path = "jobs.rs"]
mod jobs;
#[path = "kinematics_reference.rs"]
mod kinematics_reference;
#[path = "layers.rs"]
mod layers;
#[path = "live_plan.rs"]
mod live_plan;
#[path = "live_view.rs"]
mod live_view;
#[path = "log.rs"]
mod log;
#[path = "logfail.rs"]
mod logfail;
#[path = "long_plan.rs"]
mod long_plan;
#[path = "online.rs"]
mod online;
#[path = "paint.rs"]
mod paint;
#[path = "plot.rs"]
mod plot;
#[path = "program.rs"]
mod program;
#[path = "replay.rs"]
mod replay;
#[path = "reset.rs"]
mod reset;
#[path = "ros2.rs"]
mod ros2;
#[path = "ros2_dds.rs"]
mod ros2_dds;
#[path = "serial.rs"]
mod serial;
#[path = "serve.rs"]
mod serve;
#[path = "serve_history.rs"]
mod serve_history;
#[path = "serve_jobs.rs"]
mod serve_jobs;
#[path = "serve_load.rs"]
mod serve_load;
#[path = "servo.rs"]
mod servo;
#[path = "signals.rs"]
mod signals;
#[path = "stalls.rs"]
mod stalls;
#[path = "stop_phases.rs"]
mod stop_phases;
#[path = "stream.rs"]
mod stream;
#[path = "tcp.rs"]
mod tcp;
#[path = "time.rs"]
mod time;
#[path = "trajectory.rs"]
mod trajectory;
#[path = "twin.rs"]
mod twin;
#[path = "urdf_tree.rs"]
mod urdf_tree;
#[path = "validate.rs"]
mod validate;

/// Every `tests/*.rs` is built: a module of this binary (a `#[path]` above) or a `[[test]]`
/// of its own in Cargo.toml. With cargo's discovery off, a file in neither would never run.
#[test]
fn every_test_file_is_built() {
    let tests = common::repo_path("tests");
    let suite = std::fs::read_to_string(tests.join("suite.rs")).unwrap();
    let manifest = std::fs::read_to_string(common::repo_path("Cargo.toml")).unwrap();
    let mut unbuilt = Vec::new();
    for entry in std::fs::read_dir(&tests).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        if !name.ends_with(".rs") || name == "suite.rs" {
            continue;
        }
        let module = format!("#[path = \"{name}\"]");
        let target = format!("path = \"tests/{name}\"");
        if !suite.contains(&module) && !manifest.contains(&target) {
            unbuilt.push(name);
        }
    }
    assert!(
        unbuilt.is_empty(),
        "tests/ files built by no test target (add each to tests/suite.rs, or a [[test]] \
         to Cargo.toml): {}",
        unbuilt.join(", ")
    );
}
