//! `rigbridge serve` as a test's child process: the command on a free port of 127.0.0.1,
//! started, its address read from the first line it prints once it listens, and killed
//! when the test lets go of it.

use super::repo_path;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// How long a test waits for an answer: far beyond any request's, only to fail rather than
/// hang.
const ANSWER_WITHIN: Duration = Duration::from_secs(30);

/// A started daemon, killed and reaped when dropped.
pub struct Served {
    pub child: Child,
    /// Where it listens, HOST:PORT, as it printed it.
    pub address: String,
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `command` (the rigbridge binary, or a wrapper that runs it) made `rigbridge serve` on a
/// free port, its jobs' logs in `runs`, from the repository root, and without a token from
/// the environment. The Foxglove server is as the settings and the caller's arguments say.
pub fn serve_args<'a>(command: &'a mut Command, runs: &Path) -> &'a mut Command {
    command
        .args(["serve", "--port", "0", "--runs-dir"])
        .arg(runs)
        .current_dir(repo_path(""))
        .env_remove("RIGBRIDGE_TOKEN")
}

/// [`serve_args`] without the Foxglove server: tests run several daemons at once, and its
/// default port is one.
pub fn serve_command(runs: &Path) -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_rigbridge"));
    serve_args(&mut command, runs).args(["--foxglove-port", "0"]);
    command
}

/// Starts `command` (a `rigbridge serve`; its stderr as the caller set it) and waits for the
/// address it prints as its first line, `http://HOST:PORT/`.
pub fn start_serve(command: &mut Command) -> Served {
    let mut child = command
        .stdout(Stdio::piped())
        .spawn()
        .expect("rigbridge serve starts");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let address = line
        .trim()
        .strip_prefix("http://")
        .and_then(|a| a.strip_suffix('/'))
        .unwrap_or_else(|| panic!("first line should be the address, got {line:?}"))
        .to_string();
    Served { child, address }
}

/// One HTTP/1.1 request with a JSON body to the daemon at `address`, `Connection: close`;
/// `headers` are extra header lines, each ending in `\r\n`. The status code and the body as
/// JSON (null when it is not).
pub fn request_json(
    address: &str,
    method: &str,
    path: &str,
    headers: &str,
    body: &str,
) -> (u16, serde_json::Value) {
    let mut stream = TcpStream::connect(address).unwrap();
    stream.set_read_timeout(Some(ANSWER_WITHIN)).unwrap();
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {address}\r\n{headers}Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let status = response[9..12].parse().unwrap();
    let json = response.split("\r\n\r\n").nth(1).unwrap_or("");
    (status, serde_json::from_str(json).unwrap_or_default())
}

/// One HTTP/1.1 request with no body to the daemon at `address`, `Connection: close`, with
/// exactly the header lines `headers` (each ending in `\r\n`) besides Host and
/// Content-Length: the status code and the whole response, headers included.
pub fn request_bare(
    address: &str,
    method: &str,
    path: &str,
    headers: &str,
    within: Duration,
) -> (u16, String) {
    let mut stream = TcpStream::connect(address).unwrap();
    stream.set_read_timeout(Some(within)).unwrap();
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {address}\r\n{headers}Content-Length: 0\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let status = response[9..12].parse().unwrap();
    (status, response)
}

/// `dir/pan_tilt.toml`: a three-axis rig named `name` (joints `pan`, `tilt`, `elbow`,
/// revolute, +-90 deg), slow enough (60 deg/s) that a job of a few moves lasts seconds.
pub fn write_pan_tilt_rig(dir: &Path, name: &str) {
    let joint = |joint: &str, z: f64, axis: &str| {
        format!(
            "[[joint]]\nname = \"{joint}\"\nkind = \"revolute\"\norigin_xyz_m = [0.0, 0.0, {z}]\n\
             axis = {axis}\nlower_deg = -90.0\nupper_deg = 90.0\nmax_speed_deg_s = 60.0\n\
             max_accel_deg_s2 = 240.0\n\n"
        )
    };
    let rig = format!(
        "name = \"{name}\"\nbase_frame = \"base\"\ntool_frame = \"tool\"\n\n{}{}{}",
        joint("pan", 0.0, "[0.0, 0.0, 1.0]"),
        joint("tilt", 0.3, "[0.0, 1.0, 0.0]"),
        joint("elbow", 0.25, "[0.0, 1.0, 0.0]"),
    );
    std::fs::write(dir.join("pan_tilt.toml"), rig).unwrap();
}
