//! `rigbridge reset` against `rigbridge twin --listen` over TCP: after an e-stop the twin
//! refuses jobs; a reset clears it (exit 0, the controller's words), a second one finds
//! nothing latched, and a job then completes.

use crate::common;

use common::cli::rigbridge;
use common::repo_path;
use common::twin::{listen_command, start_listening};
use rigbridge::daemon::config::load_run_settings;
use rigbridge::device::LinkSpec;
use rigbridge::protocol::{Command as Wire, ControllerStatus, Fault};
use std::process::Output;
use std::time::{Duration, Instant};

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn shown(output: &Output) -> String {
    format!("{}{}", text(&output.stdout), text(&output.stderr))
}

/// E-stops the twin at `address` as a bridge would, and waits until it reports the latch.
fn estop(address: &str) {
    let settings = load_run_settings(&repo_path("config/rigbridge.toml")).unwrap();
    let spec: LinkSpec = address.parse().unwrap();
    let mut link = rigbridge::daemon::open_link(&spec, &settings).unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut sent = false;
    loop {
        assert!(
            Instant::now() < deadline,
            "the twin never latched the e-stop"
        );
        if link.is_up() && link.controller_hello().is_some() && !sent {
            link.send(&Wire::EStop).unwrap();
            sent = true;
        } else {
            link.send(&Wire::Heartbeat).unwrap();
        }
        if let Some(feedback) = link.receive(Duration::from_millis(20)).unwrap()
            && feedback.status == ControllerStatus::Fault(Fault::EStop)
        {
            return;
        }
    }
}

fn short_job_config() -> std::path::PathBuf {
    let original = common::with_absolute_cell(
        &std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap(),
    );
    let job = original.find("[job]").unwrap();
    let edited = format!(
        "{}[job]\nkind = \"move_joints\"\ntargets_deg = [[10.0, 0.0, 0.0, 0.0, 30.0, 0.0]]\n",
        &original[..job]
    );
    let path = repo_path("config").join(format!(".test-reset-{}.toml", std::process::id()));
    std::fs::write(&path, edited).unwrap();
    path
}

fn run_job(address: &str, config: &std::path::Path) -> Output {
    let log = std::env::temp_dir().join(format!(
        "rigbridge-reset-{}-{}.mcap",
        std::process::id(),
        Instant::now().elapsed().as_nanos()
    ));
    let _ = std::fs::remove_file(&log);
    rigbridge()
        .args(["run", "--link", address, "--config"])
        .arg(config)
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap()
}

#[test]
fn reset_clears_an_e_stopped_twin_and_a_job_then_completes() {
    let twin = start_listening(&mut listen_command("tcp://127.0.0.1:0"));
    let address = twin.address.clone();
    let config = short_job_config();
    estop(&address);
    let refused = run_job(&address, &config);
    assert!(!refused.status.success(), "{}", shown(&refused));
    assert!(shown(&refused).contains("e-stop"), "{}", shown(&refused));

    let reset = rigbridge()
        .args(["reset", "--link", &address])
        .output()
        .unwrap();
    assert_eq!(reset.status.code(), Some(0), "{}", shown(&reset));
    let said = text(&reset.stdout);
    assert!(
        said.contains("cleared (e-stop)") && said.contains("holding"),
        "{said}"
    );

    let again = rigbridge()
        .args(["reset", "--link", &address])
        .output()
        .unwrap();
    assert_eq!(again.status.code(), Some(0), "{}", shown(&again));
    assert!(
        text(&again.stdout).contains("no fault latched"),
        "{}",
        shown(&again)
    );

    let job = run_job(&address, &config);
    std::fs::remove_file(&config).unwrap();
    assert!(job.status.success(), "{}", shown(&job));
    assert!(
        text(&job.stdout).contains(": completed after"),
        "{}",
        shown(&job)
    );
}
