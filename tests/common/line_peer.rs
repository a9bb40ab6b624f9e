//! A Python peer that speaks in lines on its stdout: "ready" once it listens, then one JSON
//! line of results when it ends (tests/peers/ros2_peer.py, ros2_dds_peer.py). Owns only
//! starting it, reading those two lines and killing it if the test ends first.

use std::io::{BufRead, BufReader};
use std::process::{Child, ChildStdout, Command, Stdio};

/// A started peer that has said "ready".
pub struct LinePeer {
    child: Child,
    stdout: BufReader<ChildStdout>,
}

impl LinePeer {
    /// Starts `command` with its stdout piped and waits for its "ready" line, so that what
    /// the test sends next is heard.
    pub fn start(mut command: Command) -> LinePeer {
        let mut child = command.stdout(Stdio::piped()).spawn().unwrap();
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        let mut line = String::new();
        stdout.read_line(&mut line).unwrap();
        assert_eq!(line.trim(), "ready", "the peer should listen first");
        LinePeer { child, stdout }
    }

    /// Its one JSON line of results, once it has ended well.
    pub fn result(mut self) -> serde_json::Value {
        let mut line = String::new();
        self.stdout.read_line(&mut line).unwrap();
        assert!(self.child.wait().unwrap().success(), "the peer failed");
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("peer said {line:?}: {e}"))
    }
}

impl Drop for LinePeer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
