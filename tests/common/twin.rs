//! `rigbridge twin` as a test's child process: its stdout's lines on a channel (the first
//! says where it serves), a `--listen` twin on a free port of 127.0.0.1 started and its
//! address read, stopped with SIGTERM for its exit summary, and killed and reaped when the
//! test lets go of it. Owns the process only: the callers judge what it says.

use super::cli::rigbridge;
use std::io::{BufRead, BufReader, Read};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

/// How long a twin may take to print where it listens: far beyond its start on a loaded
/// machine, only to fail rather than hang.
const ADDRESS_WITHIN: Duration = Duration::from_secs(10);

/// How long a twin may take to exit after SIGTERM: it brings its axes to rest and prints its
/// summary first.
const EXIT_WITHIN: Duration = Duration::from_secs(10);

/// A started `rigbridge twin --listen`, killed and reaped when dropped.
pub struct TwinProcess {
    pub child: Child,
    /// Where it listens, `tcp://HOST:PORT`, as it printed it.
    pub address: String,
    /// The lines it printed after its address.
    pub lines: Receiver<String>,
}

impl Drop for TwinProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The lines `stdout` prints, sent on a channel by a thread of their own until it ends or
/// the receiver is dropped.
pub fn lines_of(stdout: impl Read + Send + 'static) -> Receiver<String> {
    let (tx, lines) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    lines
}

/// `rigbridge twin --listen LISTEN` from the repository root, its stderr discarded; the
/// caller may add arguments (`--config`) and environment.
pub fn listen_command(listen: &str) -> Command {
    let mut command = rigbridge();
    command
        .args(["twin", "--listen", listen])
        .stderr(Stdio::null());
    command
}

/// Starts `command` (from [`listen_command`]) and waits for the address it prints first,
/// which must be on 127.0.0.1.
pub fn start_listening(command: &mut Command) -> TwinProcess {
    let mut child = command.stdout(Stdio::piped()).spawn().unwrap();
    let lines = lines_of(child.stdout.take().unwrap());
    let address = lines
        .recv_timeout(ADDRESS_WITHIN)
        .expect("the twin prints its address");
    assert!(address.starts_with("tcp://127.0.0.1:"), "{address}");
    TwinProcess {
        child,
        address,
        lines,
    }
}

/// Stops the twin `child` (SIGTERM, as a user would) and returns its exit summary, which it
/// prints on stderr (piped by the caller).
pub fn stop_for_summary(child: &mut Child) -> String {
    // SAFETY: kill(2) on our own child's pid.
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
    let deadline = Instant::now() + EXIT_WITHIN;
    while child.try_wait().unwrap().is_none() {
        assert!(Instant::now() < deadline, "the twin ignored SIGTERM");
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut summary = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut summary)
        .unwrap();
    summary
}
