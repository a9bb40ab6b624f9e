//! The daemon and the twin as separate processes over a real TCP socket on 127.0.0.1:
//! a whole job, a twin killed and restarted mid-job, a daemon killed mid-job, and garbage.

use crate::common;

use common::cli::{assert_succeeded, read_json, rigbridge};
use common::runlog::assert_resumes_in_step_after_link_loss;
use common::twin::{TwinProcess, listen_command, start_listening};
use common::{irb120, repo_path, wait_for_logged_commands, wait_for_logged_event};
use rigbridge::log::read_log;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::Duration;

const PERIOD: f64 = 0.004;
/// A second of the default job's motion at 250 Hz: a job this far in is mid-motion.
const MID_JOB_COMMANDS: usize = 250;
/// Longer than any of these waits takes on a loaded machine.
const WAIT: Duration = Duration::from_secs(30);

fn start_twin(listen: &str) -> TwinProcess {
    start_twin_under(listen, None)
}

/// A twin whose environment's RUST_LOG is `rust_log` (or unset).
fn start_twin_under(listen: &str, rust_log: Option<&str>) -> TwinProcess {
    let mut command = listen_command(listen);
    match rust_log {
        Some(directives) => command.env("RUST_LOG", directives),
        None => command.env_remove("RUST_LOG"),
    };
    start_listening(&mut command)
}

fn scratch(name: &str) -> PathBuf {
    common::scratch_file("tcp", name)
}

fn spawn_run(link: &str, log: &Path, report: &Path) -> Child {
    common::cli::spawn_run(&["--link", link], log, report)
}

/// [`spawn_run`] waited for; it must succeed.
fn run_to_end(link: &str, log: &Path, report: &Path) {
    let output = spawn_run(link, log, report).wait_with_output().unwrap();
    assert_succeeded(&output);
}

/// A megabyte of xorshift noise from `seed`: garbage for either end of the link.
fn noise(seed: u64) -> Vec<u8> {
    let mut state = seed;
    let mut noise = Vec::with_capacity(1 << 20);
    while noise.len() < 1 << 20 {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        noise.extend_from_slice(&state.to_le_bytes());
    }
    noise
}

/// The bridge's Hello for the IRB 120 at 250 Hz as a frame on the wire.
fn hello_frame() -> Vec<u8> {
    let mut hello = vec![0];
    let message = rigbridge::protocol::Message::Hello(rigbridge::link::bridge_hello(
        &irb120(),
        std::time::Duration::from_secs_f64(PERIOD),
        25,
    ));
    rigbridge::protocol::encode_frame(&message, &mut hello).unwrap();
    hello
}

#[test]
fn a_job_over_tcp_loses_no_frame_and_stays_within_limits() {
    if !common::in_full_tier("tcp::a_job_over_tcp_loses_no_frame_and_stays_within_limits") {
        return;
    }
    let twin = start_twin("tcp://127.0.0.1:0");
    let (log, json) = (scratch("whole.mcap"), scratch("whole.json"));
    run_to_end(&twin.address, &log, &json);
    let report = read_json(&json);
    assert_eq!(report["outcome"], "completed");
    // No frame lost either way: no gap or repeat in the echoed sequence, no CRC error.
    // (A feedback later than half a cycle on this shared machine counts as a timeout,
    // not a loss: it is used the next cycle.)
    // A stall of the host (listed in the report's `interruptions`) resumes from a hold, discarding the
    // targets queued behind its Stop: the one run where the echo may jump.
    let resumed = report["interruptions"]
        .as_array()
        .is_some_and(|stalls| !stalls.is_empty());
    assert!(resumed || report["gaps"] == 0, "{report}");
    // A repeated echo is a duplicated frame or a controller cycle with no new target (a
    // late bridge cycle lets the twin tick on its own clock): v2 Feedback cannot tell them
    // apart (protocol 6.3), so the count is the host's scheduling, printed, not judged.
    println!(
        "tcp: {} repeated echoes, {} missed cycles in {} cycles",
        report["duplicates"], report["missed_cycles"], report["cycles"]
    );
    assert_eq!(report["crc_errors"], 0);
    assert_eq!(report["limit_violations"], 0, "{report}");
    println!("tcp: {} late feedbacks", report["feedback_timeouts"]);
    let run = read_log(&log).unwrap();
    let seqs: Vec<u32> = run.commands.iter().map(|c| c.seq).collect();
    assert!(seqs.windows(2).all(|w| w[1] == w[0] + 1));
}

#[test]
fn a_restarted_twin_is_rejoined_from_its_actual_position() {
    if !common::in_full_tier("tcp::a_restarted_twin_is_rejoined_from_its_actual_position") {
        return;
    }
    // The restarted twin comes back at its initial position, and the way back to the path
    // is a joint move from there: in the shipped cell it may pass the star's wall within the
    // margin, and is then refused before motion like any path that does. This test
    // is about the link, so the bridge's and both twins' cell is the floor alone.
    let config = settings_on_the_floor();
    let twin_on_the_floor = |listen: &str| {
        let mut command = listen_command(listen);
        command.arg("--config").arg(&config).env_remove("RUST_LOG");
        start_listening(&mut command)
    };
    let first = twin_on_the_floor("tcp://127.0.0.1:0");
    let address = first.address.clone();
    let (log, json) = (scratch("restart.mcap"), scratch("restart.json"));
    let daemon = common::cli::spawn_run(
        &["--link", &address, "--config", config.to_str().unwrap()],
        &log,
        &json,
    );
    wait_for_logged_commands(&log, MID_JOB_COMMANDS, WAIT);
    drop(first);
    // Back only once the daemon has seen it go.
    wait_for_logged_event(&log, "link_lost", WAIT);
    let _second = twin_on_the_floor(address.trim_start_matches("tcp://"));
    assert_succeeded(&daemon.wait_with_output().unwrap());
    let report = read_json(&json);
    assert_eq!(report["outcome"], "completed", "{report}");
    assert!(report["reconnects"].as_u64().unwrap() >= 1, "{report}");

    let run = read_log(&log).unwrap();
    let seqs: Vec<u32> = run.commands.iter().map(|c| c.seq).collect();
    assert!(
        seqs.windows(2).all(|w| w[1] == w[0] + 1),
        "one unbroken sequence across the restart"
    );
    assert_resumes_in_step_after_link_loss(&run, &irb120(), PERIOD);
}

/// config/rigbridge.toml (the star job) with the floor alone for its cell.
fn settings_on_the_floor() -> PathBuf {
    let shipped = std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap();
    let absolute = |name: &str| format!("\"{}\"", repo_path(&format!("config/{name}")).display());
    let text = shipped
        .replace("\"irb120.toml\"", &absolute("irb120.toml"))
        .replace("\"cell-star.toml\"", &absolute("cell-floor.toml"));
    assert!(
        text.contains("cell-floor.toml"),
        "the shipped settings name their cell"
    );
    let path = scratch("floor-only.toml");
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn a_killed_daemon_leaves_the_twin_holding_within_two_cycles() {
    if !common::in_full_tier("tcp::a_killed_daemon_leaves_the_twin_holding_within_two_cycles") {
        return;
    }
    let twin = start_twin("tcp://127.0.0.1:0");
    let (log, json) = (scratch("killed.mcap"), scratch("killed.json"));
    let mut daemon = spawn_run(&twin.address, &log, &json);
    wait_for_logged_commands(&log, MID_JOB_COMMANDS, WAIT);
    daemon.kill().unwrap();
    daemon.wait().unwrap();
    let mut lost = None;
    let mut holding = None;
    while let Ok(line) = twin.lines.recv_timeout(Duration::from_secs(2)) {
        let cycle = |l: &str| {
            l.split("at cycle ")
                .nth(1)
                .and_then(|r| r.split_whitespace().next())
                .and_then(|c| c.parse::<u64>().ok())
        };
        if line.starts_with("link lost") {
            lost = cycle(&line);
        }
        if line.starts_with("status holding") && lost.is_some() {
            holding = cycle(&line);
            break;
        }
        if line.starts_with("link lost") && line.ends_with("holding") {
            holding = lost;
        }
    }
    let (lost, holding) = (
        lost.expect("the twin saw the link go"),
        holding.expect("and held"),
    );
    assert!(
        holding - lost <= 2,
        "held {} cycles after the loss",
        holding - lost
    );
}

#[test]
fn a_megabyte_of_garbage_moves_nothing_and_crashes_nothing() {
    if !common::in_full_tier("tcp::a_megabyte_of_garbage_moves_nothing_and_crashes_nothing") {
        return;
    }
    let twin = start_twin("tcp://127.0.0.1:0");
    let address = twin.address.trim_start_matches("tcp://").to_string();
    let noise = noise(0x2545_f491_4f6c_dd1d);
    let mut socket = std::net::TcpStream::connect(&address).unwrap();
    socket
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    // The twin answers with Feedback only once a Hello opened the session
    // (docs/protocol.md 6.1); the garbage follows the Hello.
    let hello = hello_frame();
    socket.write_all(&hello).unwrap();
    let reader = {
        let mut socket = socket.try_clone().unwrap();
        std::thread::spawn(move || read_until_answered_twice(&mut socket))
    };
    socket.write_all(&noise).unwrap();
    // A second Hello behind the garbage: its answer shows the twin has read all of it.
    socket.write_all(&hello).unwrap();
    let received = reader.join().unwrap();
    socket.shutdown(std::net::Shutdown::Both).unwrap();
    let mut decoder = rigbridge::protocol::FrameDecoder::default();
    decoder.push(&received);
    let initial: Vec<f64> = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]
        .iter()
        .map(|d: &f64| d.to_radians())
        .collect();
    let (mut feedbacks, mut answers, mut feedbacks_after_garbage) = (0, 0, 0);
    while let Some(message) = decoder.next_message() {
        if matches!(&message, rigbridge::protocol::Message::Hello(h) if h.answer) {
            answers += 1;
        }
        if let rigbridge::protocol::Message::Feedback(feedback) = message {
            feedbacks += 1;
            if answers >= 2 {
                feedbacks_after_garbage += 1;
            }
            for (q, start) in feedback.positions.as_slice().iter().zip(&initial) {
                // Positions travel as whole micro-radians.
                assert!((q - start).abs() <= 0.5e-6, "garbage moved the twin");
            }
        }
    }
    assert!(feedbacks > 0, "the twin kept answering");
    assert!(
        answers >= 2 && feedbacks_after_garbage > 0,
        "the twin answered a Hello after the garbage and went on: {answers} answers, {feedbacks_after_garbage} feedbacks after"
    );
    // And the twin still serves a real job afterwards.
    let (log, json) = (scratch("after-garbage.mcap"), scratch("after-garbage.json"));
    run_to_end(&twin.address, &log, &json);
}

/// What the twin sends until it has answered a second Hello and sent a Feedback after it
/// (or the stream ends or stays silent past the socket's timeout).
fn read_until_answered_twice(socket: &mut std::net::TcpStream) -> Vec<u8> {
    let mut received = Vec::new();
    let mut decoder = rigbridge::protocol::FrameDecoder::default();
    let (mut answers, mut feedbacks_after) = (0, 0);
    let mut buffer = [0u8; 65536];
    while answers < 2 || feedbacks_after == 0 {
        let n = match socket.read(&mut buffer) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        received.extend_from_slice(&buffer[..n]);
        decoder.push(&buffer[..n]);
        while let Some(message) = decoder.next_message() {
            match message {
                rigbridge::protocol::Message::Hello(h) if h.answer => answers += 1,
                rigbridge::protocol::Message::Feedback(_) if answers >= 2 => feedbacks_after += 1,
                _ => {}
            }
        }
    }
    received
}

#[test]
fn a_controller_sending_garbage_gets_no_motion_and_no_crash() {
    if !common::in_full_tier("tcp::a_controller_sending_garbage_gets_no_motion_and_no_crash") {
        return;
    }
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let address = listener.local_addr().unwrap();
    let server = std::thread::spawn(move || {
        let (mut socket, _) = listener.accept().unwrap();
        let _ = socket.write_all(&noise(0x9e37_79b9_7f4a_7c15));
        let mut received = Vec::new();
        let _ = socket.read_to_end(&mut received);
        received
    });
    let (log, json) = (
        scratch("garbage-daemon.mcap"),
        scratch("garbage-daemon.json"),
    );
    let output = spawn_run(&format!("tcp://{address}"), &log, &json)
        .wait_with_output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("did not answer the bridge's Hello"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(
        !log.exists(),
        "nothing was streamed, so nothing was recorded"
    );
    // What the bridge sent: its Hello and heartbeats, never a target.
    let sent = server.join().unwrap();
    let mut decoder = rigbridge::protocol::FrameDecoder::default();
    decoder.push(&sent);
    while let Some(message) = decoder.next_message() {
        assert!(
            matches!(
                message,
                rigbridge::protocol::Message::Command(rigbridge::protocol::Command::Heartbeat)
                    | rigbridge::protocol::Message::Hello(_)
            ),
            "{message:?}"
        );
    }
}

#[test]
fn a_twin_that_never_comes_back_aborts_the_job_with_a_message() {
    if !common::in_full_tier("tcp::a_twin_that_never_comes_back_aborts_the_job_with_a_message") {
        return;
    }
    let config = repo_path("config").join(format!(".test-{}-reconnect.toml", std::process::id()));
    let original = common::with_absolute_cell(
        &std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap(),
    );
    std::fs::write(
        &config,
        original.replace(
            "link = \"loopback\"",
            "link = \"loopback\"\nreconnect_timeout_s = 1.0",
        ),
    )
    .unwrap();
    let twin = start_twin("tcp://127.0.0.1:0");
    let (log, json) = (scratch("abort.mcap"), scratch("abort.json"));
    let daemon = common::cli::spawn_run(
        &[
            "--config",
            config.to_str().unwrap(),
            "--link",
            &twin.address,
        ],
        &log,
        &json,
    );
    wait_for_logged_commands(&log, MID_JOB_COMMANDS, WAIT);
    let address = twin.address.trim_start_matches("tcp://").to_string();
    drop(twin);
    let output = daemon.wait_with_output().unwrap();
    std::fs::remove_file(&config).unwrap();
    assert_eq!(
        output.status.code(),
        Some(3),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report = read_json(&json);
    assert_eq!(report["outcome"], "link_lost", "{report}");
    // Nothing listens where the twin was: the bridge's reconnects are refused, and the
    // fault says so, naming the address (a silent controller would be another message).
    let fault = report["fault"].as_str().unwrap();
    assert!(
        fault.contains(&format!("connection refused at {address}")) && fault.contains("aborted"),
        "{fault}"
    );
    assert!(!fault.contains("Hello"), "{fault}");
    assert!(
        !read_log(&log).unwrap().truncated,
        "the log is closed properly"
    );
}

/// Nothing listens at the address: the run ends saying the connection was refused there,
/// not that a controller kept silent.
#[test]
fn a_refused_connection_is_named_with_its_address() {
    if !common::in_full_tier("tcp::a_refused_connection_is_named_with_its_address") {
        return;
    }
    let address = {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        listener.local_addr().unwrap()
    };
    let (log, json) = (scratch("refused.mcap"), scratch("refused.json"));
    let output = spawn_run(&format!("tcp://{address}"), &log, &json)
        .wait_with_output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    println!("{}", stderr.trim());
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains(&format!("connection refused at {address}")),
        "{stderr}"
    );
    assert!(!stderr.contains("Hello"), "{stderr}");
}

#[test]
fn a_second_bridge_is_refused_with_a_reason_while_one_is_connected() {
    if !common::in_full_tier("tcp::a_second_bridge_is_refused_with_a_reason_while_one_is_connected")
    {
        return;
    }
    let twin = start_twin("tcp://127.0.0.1:0");
    let address = twin.address.trim_start_matches("tcp://").to_string();
    let first = std::net::TcpStream::connect(&address).unwrap();
    (&first).write_all(&hello_frame()).unwrap();
    // Wait until the twin has taken the first one.
    let connected = twin
        .lines
        .recv_timeout(Duration::from_secs(5))
        .expect("the twin reports the first connection");
    assert!(connected.starts_with("connected"), "{connected}");
    let mut second = std::net::TcpStream::connect(&address).unwrap();
    second
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut received = Vec::new();
    second.read_to_end(&mut received).unwrap();
    let mut decoder = rigbridge::protocol::FrameDecoder::default();
    decoder.push(&received);
    let Some(rigbridge::protocol::Message::Fault(notice)) = decoder.next_message() else {
        panic!("the second bridge got no Fault notice: {received:?}");
    };
    assert_eq!(notice.fault, rigbridge::protocol::Fault::Busy);
    assert!(notice.text.contains("another bridge"), "{}", notice.text);
    drop(first);
}

#[test]
fn a_virtual_clock_over_a_real_link_is_refused() {
    if !common::in_full_tier("tcp::a_virtual_clock_over_a_real_link_is_refused") {
        return;
    }
    let output = rigbridge()
        .args(["run", "--clock", "virtual", "--link", "tcp://127.0.0.1:9"])
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("--clock virtual needs the loopback twin"),
        "{stderr}"
    );
}

#[test]
fn serve_refuses_a_virtual_clock_for_a_cell_on_a_real_link() {
    if !common::in_full_tier("tcp::serve_refuses_a_virtual_clock_for_a_cell_on_a_real_link") {
        return;
    }
    let dir = std::env::temp_dir().join(format!("rigbridge-serve-virtual-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let settings = common::shipped_settings_text()
        .replace("link = \"loopback\"", "link = \"tcp://127.0.0.1:9\"");
    let file = dir.join("cell.toml");
    std::fs::write(&file, settings).unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args([
            "serve",
            "--clock",
            "virtual",
            "--port",
            "0",
            "--foxglove-port",
            "0",
            "--config",
        ])
        .arg(&file)
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("--clock virtual needs the loopback twin")
            && stderr.contains("tcp://127.0.0.1:9"),
        "{stderr}"
    );
}

/// The twin's events are its stdout's plain lines, which scripts wait on, whatever RUST_LOG
/// asks of the diagnostics.
#[test]
fn the_twin_prints_its_events_plainly_even_under_rust_log() {
    if !common::in_full_tier("tcp::the_twin_prints_its_events_plainly_even_under_rust_log") {
        return;
    }
    let twin = start_twin_under("tcp://127.0.0.1:0", Some("trace"));
    let peer = std::net::TcpStream::connect(twin.address.trim_start_matches("tcp://")).unwrap();
    let connected = twin
        .lines
        .recv_timeout(WAIT)
        .expect("the twin saw the peer");
    let cycle = connected.strip_prefix("connected at cycle ");
    assert!(
        cycle.is_some_and(|c| c.parse::<u64>().is_ok()),
        "{connected}"
    );
    drop(peer);
    // A loaded machine may let the watchdog see the silence first: plain lines too.
    loop {
        let line = twin
            .lines
            .recv_timeout(WAIT)
            .expect("the twin saw the peer go");
        if let Some(rest) = line.strip_prefix("link lost at cycle ") {
            let cycle = rest.split_once(' ').map(|(cycle, _)| cycle);
            assert!(cycle.is_some_and(|c| c.parse::<u64>().is_ok()), "{line}");
            assert!(line.ends_with("): holding"), "{line}");
            break;
        }
        assert!(
            line.starts_with("silent for ") || line.starts_with("status holding at cycle "),
            "{line}"
        );
    }
}

/// A controller that stalls (SIGSTOP of the twin process for 3 s, within the 5 s
/// reconnect timeout) and comes back: the bridge's old connection, which it closed when the
/// controller went silent, is still queued in the stopped twin behind the bridge's new
/// one. The twin must take the new one (its peer closed the old), and the job resumes and
/// completes rather than ending `faulted: busy with another bridge`.
#[test]
fn a_controller_stalled_for_three_seconds_is_resumed_when_it_comes_back() {
    if !common::in_full_tier(
        "tcp::a_controller_stalled_for_three_seconds_is_resumed_when_it_comes_back",
    ) {
        return;
    }
    let twin = start_twin("tcp://127.0.0.1:0");
    let (log, json) = (scratch("stalled.mcap"), scratch("stalled.json"));
    let daemon = spawn_run(&twin.address, &log, &json);
    wait_for_logged_commands(&log, MID_JOB_COMMANDS, WAIT);
    let pid = twin.child.id() as libc::pid_t;
    // SAFETY: kill(2) on our own child's pid.
    unsafe { libc::kill(pid, libc::SIGSTOP) };
    std::thread::sleep(Duration::from_secs(3));
    // SAFETY: as above.
    unsafe { libc::kill(pid, libc::SIGCONT) };
    let output = daemon.wait_with_output().unwrap();
    let report = read_json(&json);
    assert_succeeded(&output);
    assert_eq!(report["outcome"], "completed", "{report}");
    let run = read_log(&log).unwrap();
    assert!(
        run.events.iter().any(|e| e.kind == "resumed"),
        "a resume event in the log: {:?}",
        run.events.iter().map(|e| &e.kind).collect::<Vec<_>>()
    );
    assert_resumes_in_step_after_link_loss(&run, &irb120(), PERIOD);
}
