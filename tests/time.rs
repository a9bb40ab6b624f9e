//! One time type inside the library (issue 31, item 3), read from the source as
//! tests/layers.rs reads it: nothing under `src/` reads the system's clocks but
//! `src/clock.rs` (`Instant::now`, `SystemTime::now`, an `Instant`'s `elapsed`), and no
//! library struct keeps a timestamp as f64 seconds (a `pub` field named `t`, `at_s`,
//! `*_at_s` or `start_s`) outside the edges that write seconds for a reader.
//!
//! A file is read up to its `#[cfg(test)]` module only for the second check; the first reads
//! all of it (a test that reads the clock is as untestable as the code it tests). Comments
//! are left out of both.

use crate::common;
use std::path::{Path, PathBuf};

/// The one module that reads the system's clocks.
const CLOCK_MODULE: &str = "clock.rs";

/// Files that still read the system's clocks, for now: the device protocols' links, wires and
/// twin sides, which another change (issue 31 item 1, "devices") moves into one folder per
/// device and routes through `clock::real()` / the `Clock` trait as it moves them. Remove an
/// entry once its file reads no clock; the list must only shrink.
const NOT_YET_ROUTED: &[&str] = &[
    // Where the "devices" change moves the files below (src/device/<protocol>/).
    "device/",
    "protocol/",
    "link/",
    "transport/",
    "twin/can_port.rs",
    "twin/canopen.rs",
    "twin/dynamixel.rs",
    "twin/egm.rs",
    "twin/serial_port.rs",
    "twin/server.rs",
    "cli/twin.rs",
    "cli/canopen.rs",
    "cli/dynamixel.rs",
];

/// What reads a system clock.
const CLOCK_READS: &[&str] = &["Instant::now", "SystemTime::now", ".elapsed()"];

/// Edges: modules whose structs hold seconds because a reader outside the library wants
/// seconds, each with the reader.
const EDGE_MODULES: &[(&str, &str)] = &[
    ("cli/", "the command line prints seconds"),
    (
        "view/",
        "the live page draws seconds (its JSON frames and samples)",
    ),
    (
        "log/wire.rs",
        "the log file's JSON records carry `t` in seconds",
    ),
    (
        "job/follow_trajectory.rs",
        "a trajectory CSV file's rows carry their time in seconds",
    ),
];

/// Structs that derive `Serialize` are JSON reports (an HTTP answer, a `--json` report, a log
/// event's detail): their `*_s` fields are the JSON's, an edge like the files above.
const SERIALIZED: &str = "Serialize";

/// Timestamps still kept as f64 seconds, for now (issue 31 item 3's remainder), each with
/// why it is not a `Duration` yet. The list must only shrink: a name no longer found fails.
const NOT_YET_DURATION: &[(&str, &str)] = &[(
    "cell/path.rs: PathCollision.t",
    "found by bisecting between two samples in f64 arithmetic; its one reader writes it to JSON",
)];

fn src_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// Each file under `src/` as (its path under `src/`, with `/` separators; its text).
fn sources() -> Vec<(String, String)> {
    let src = src_dir();
    common::rust_files(&src)
        .into_iter()
        .map(|file| {
            let relative = file.strip_prefix(&src).unwrap();
            let name = relative
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect::<Vec<_>>()
                .join("/");
            (name, std::fs::read_to_string(&file).unwrap())
        })
        .collect()
}

/// A line without its `//` comment (a `//` inside a string cuts the line short: that can
/// hide nothing this test looks for that the compiler would see).
fn code(line: &str) -> &str {
    line.split("//").next().unwrap_or("")
}

fn clock_reads(name: &str, text: &str) -> Vec<String> {
    let mut found = Vec::new();
    for (number, line) in text.lines().enumerate() {
        for read in CLOCK_READS {
            if code(line).contains(read) {
                found.push(format!("src/{name}:{}: {read}", number + 1));
            }
        }
    }
    found
}

#[test]
fn only_the_clock_module_reads_the_system_clocks() {
    let mut offences = Vec::new();
    let mut clock_module_reads = 0;
    for (name, text) in sources() {
        let reads = clock_reads(&name, &text);
        if name == CLOCK_MODULE {
            clock_module_reads = reads.len();
        } else if !NOT_YET_ROUTED.iter().any(|p| name.starts_with(p)) {
            offences.extend(reads);
        }
    }
    // The clock module itself is read the same way: the check sees a clock read where one is.
    assert!(
        clock_module_reads >= 2,
        "src/{CLOCK_MODULE} should read Instant::now and SystemTime::now; found {clock_module_reads}"
    );
    assert!(
        offences.is_empty(),
        "{} clock read(s) outside src/{CLOCK_MODULE} (use the Clock trait, or clock::real()):\n{}",
        offences.len(),
        offences.join("\n")
    );
}

/// True for a field name that holds a timestamp in seconds.
fn is_timestamp_name(name: &str) -> bool {
    name == "t" || name == "at_s" || name.ends_with("_at_s") || name == "start_s"
}

/// `pub t: f64,` (any `pub(..)`, `Option<f64>` too) -> the field's name.
fn f64_timestamp_field(line: &str) -> Option<&str> {
    let line = code(line).trim();
    let rest = line.strip_prefix("pub")?;
    let rest = match rest.strip_prefix('(') {
        Some(scoped) => scoped.split_once(')')?.1,
        None => rest,
    };
    let (name, ty) = rest.trim().split_once(':')?;
    let ty = ty.trim().trim_end_matches(',');
    let seconds = ty == "f64" || ty == "Option<f64>";
    (seconds && is_timestamp_name(name.trim())).then_some(name.trim())
}

/// The library part of a file: up to its `#[cfg(test)]` module.
fn library_part(text: &str) -> &str {
    text.split("#[cfg(test)]").next().unwrap_or(text)
}

/// Each f64 timestamp field of a non-serialized struct, as "file: Struct.field".
fn f64_timestamps(name: &str, text: &str) -> Vec<String> {
    let mut found = Vec::new();
    let mut derives = String::new();
    let mut current: Option<(String, bool)> = None;
    for line in library_part(text).lines() {
        let trimmed = code(line).trim();
        if trimmed.starts_with("#[derive(") {
            derives.push_str(trimmed);
        } else if let Some(rest) = trimmed
            .strip_prefix("pub struct ")
            .or_else(|| trimmed.strip_prefix("struct "))
            .or_else(|| trimmed.strip_prefix("pub(crate) struct "))
            .or_else(|| trimmed.strip_prefix("pub(super) struct "))
        {
            let struct_name: String = rest
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            current = Some((struct_name, derives.contains(SERIALIZED)));
            derives.clear();
        } else if !trimmed.starts_with("#[") && !trimmed.is_empty() {
            // Any other line ends what the derives above it belonged to.
            derives.clear();
        }
        let Some(field) = f64_timestamp_field(line) else {
            continue;
        };
        match &current {
            Some((_, true)) => {}
            Some((struct_name, false)) => found.push(format!("{name}: {struct_name}.{field}")),
            None => found.push(format!("{name}: ?.{field}")),
        }
    }
    found
}

#[test]
fn no_library_struct_keeps_a_timestamp_as_f64_seconds() {
    let mut offences = Vec::new();
    let mut still_allowed = Vec::new();
    for (name, text) in sources() {
        if EDGE_MODULES.iter().any(|(edge, _)| name.starts_with(edge)) {
            continue;
        }
        for field in f64_timestamps(&name, &text) {
            if NOT_YET_DURATION.iter().any(|(f, _)| *f == field) {
                still_allowed.push(field);
            } else {
                offences.push(field);
            }
        }
    }
    assert!(
        offences.is_empty(),
        "{} timestamp field(s) in f64 seconds inside the library (make them Duration; \
         convert to seconds where they are written):\n{}",
        offences.len(),
        offences.join("\n")
    );
    let gone: Vec<_> = NOT_YET_DURATION
        .iter()
        .map(|(f, _)| *f)
        .filter(|f| !still_allowed.iter().any(|a| a == f))
        .collect();
    assert!(
        gone.is_empty(),
        "NOT_YET_DURATION names fields that are no longer f64 seconds (take them off): {}",
        gone.join(", ")
    );
}

#[test]
fn the_checks_see_what_they_look_for() {
    let reads = clock_reads("x.rs", "let a = Instant::now(); // SystemTime::now\n");
    assert_eq!(reads, ["src/x.rs:1: Instant::now"]);
    let text = "#[derive(Debug, Clone)]\npub struct Target {\n    pub seq: u32,\n    \
                pub t: f64,\n    pub(crate) picked_at_s: Option<f64>,\n}\n\
                #[derive(Serialize)]\npub struct Report {\n    pub at_s: f64,\n}\n";
    assert_eq!(
        f64_timestamps("x.rs", text),
        ["x.rs: Target.t", "x.rs: Target.picked_at_s"]
    );
    assert_eq!(f64_timestamp_field("    pub t: Duration,"), None);
    assert_eq!(f64_timestamp_field("    pub period_s: f64,"), None);
}
