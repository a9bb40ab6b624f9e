//! The `fk` and `ik` batch tools, run as a user would, against the reference data.

use crate::common;

use common::cli::assert_succeeded;
use common::{output_with_stdin, reference_path, repo_path};
use std::process::{Command, Output};

fn rigbridge(args: &[&str], stdin: Option<&str>) -> Output {
    output_with_stdin(
        Command::new(env!("CARGO_BIN_EXE_rigbridge"))
            .args(args)
            .current_dir(repo_path("")),
        stdin.unwrap_or(""),
    )
}

fn column(line: &str, index: usize) -> f64 {
    line.split(',').nth(index).unwrap().parse().unwrap()
}

#[test]
fn fk_reproduces_the_reference_poses() {
    let reference = reference_path("irb120_fk.csv");
    let output = rigbridge(&["fk", "--input", reference.to_str().unwrap()], None);
    assert_succeeded(&output);
    let produced = String::from_utf8(output.stdout).unwrap();
    let expected = std::fs::read_to_string(&reference).unwrap();
    let mut rows = 0;
    for (ours, theirs) in produced.lines().skip(1).zip(expected.lines().skip(1)) {
        for i in 0..3 {
            assert!(
                (column(ours, i) - column(theirs, 6 + i)).abs() < 1e-9,
                "{ours} vs {theirs}"
            );
        }
        assert!(ours.ends_with(",ok"));
        rows += 1;
    }
    assert_eq!(rows, 1000);
    assert!(String::from_utf8_lossy(&output.stderr).contains("1000 rows: 1000 ok"));
}

#[test]
fn ik_keeps_going_past_bad_rows_and_reports_them() {
    let rig = common::irb120();
    let row = |q: [f64; 6]| {
        let pose = rig.tool_pose(&q.map(f64::to_radians)).unwrap();
        let (p, o) = (pose.position, pose.orientation);
        format!("{},{},{},{},{},{},{}", p.x, p.y, p.z, o.w, o.x, o.y, o.z)
    };
    let input = format!(
        "x,y,z,qw,qx,qy,qz,comment\n{},start\n5.0,0,0.5,1,0,0,0,far\n0.4,0,abc,1,0,0,0,garbage\n\
         0.4,0,0.5,2,0,0,0,not unit\n{},a degree on\n",
        row([10.0, 20.0, -30.0, 40.0, 50.0, 60.0]),
        row([11.0, 21.0, -29.0, 41.0, 51.0, 61.0]),
    );
    let output = rigbridge(&["ik", "--input", "-", "--output", "-"], Some(&input));
    assert_eq!(
        output.status.code(),
        Some(3),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let text = String::from_utf8(output.stdout).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(
        lines[0],
        "j1,j2,j3,j4,j5,j6,pos_err_m,rot_err_rad,iterations,status"
    );
    let statuses: Vec<&str> = lines[1..]
        .iter()
        .map(|l| l.rsplit(',').next().unwrap().split(':').next().unwrap())
        .collect();
    assert_eq!(
        statuses,
        [
            "ok",
            "out_of_reach",
            "invalid_target",
            "invalid_target",
            "ok"
        ]
    );
    // The last row is seeded by the first (the failures in between leave the seed alone),
    // so it stays on the same branch, a small step away.
    let first: Vec<f64> = (0..6).map(|i| column(lines[1], i)).collect();
    let last: Vec<f64> = (0..6).map(|i| column(lines[5], i)).collect();
    for (a, b) in first.iter().zip(&last) {
        assert!((a - b - -1.0).abs() < 1e-6, "{first:?} -> {last:?}");
    }
    let summary = String::from_utf8_lossy(&output.stderr);
    assert!(summary.contains("5 rows: 2 ok, 3 failed"), "{summary}");
}

#[test]
fn ik_refuses_a_seed_of_the_wrong_length() {
    let output = rigbridge(&["ik", "--seed", "1,2,3"], Some("x,y,z,qw,qx,qy,qz\n"));
    assert_eq!(output.status.code(), Some(2), "a usage error");
    assert!(String::from_utf8_lossy(&output.stderr).contains("--seed has 3 values"));
}

#[test]
fn ik_names_a_missing_column() {
    let output = rigbridge(&["ik"], Some("x,y,qw,qx,qy,qz\n1,2,3,4,5,6\n"));
    assert_eq!(output.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&output.stderr).contains("no column `z`"));
}

#[test]
fn help_explains_the_commands() {
    let output = rigbridge(&["--help"], None);
    let text = String::from_utf8_lossy(&output.stdout);
    assert!(
        text.contains("fk") && text.contains("ik") && text.contains("degrees"),
        "{text}"
    );
}

/// The subcommands a `--help` text lists under "Commands:" (without `help`).
fn subcommands(help: &str) -> Vec<String> {
    help.split("Commands:")
        .nth(1)
        .map(|section| section.split("\n\n").next().unwrap_or(""))
        .unwrap_or("")
        .lines()
        .filter_map(|line| line.split_whitespace().next())
        .filter(|name| *name != "help")
        .map(str::to_string)
        .collect()
}

/// Every argument and option of a `-h` text that has no description, or only a default:
/// clap puts the description after the name on the same line, or (when names are long) on
/// the next line, indented further.
fn undescribed(help: &str) -> Vec<String> {
    let mut bare = Vec::new();
    for section in ["Arguments:", "Options:"] {
        let Some(body) = help.split(section).nth(1) else {
            continue;
        };
        let lines: Vec<&str> = body.split("\n\n").next().unwrap_or("").lines().collect();
        for (i, line) in lines.iter().enumerate() {
            let indent = line.len() - line.trim_start().len();
            let entry = line.trim();
            if entry.is_empty() || indent > 6 || !entry.starts_with(['-', '<']) {
                continue;
            }
            let same_line = entry
                .split("  ")
                .map(str::trim)
                .filter(|p| !p.is_empty())
                .nth(1);
            let next_line = lines
                .get(i + 1)
                .filter(|next| next.len() - next.trim_start().len() > 6)
                .map(|next| next.trim());
            match same_line.or(next_line) {
                Some(text) if !text.starts_with('[') => {}
                _ => bare.push(entry.to_string()),
            }
        }
    }
    bare
}

/// Issue 32: every command's every argument says what it is, and every command that takes
/// `--link` lists every link form there is (one text, rigbridge::device::link_forms(), from the one list of backends).
#[test]
fn every_argument_is_described_and_every_link_form_listed() {
    let mut commands: Vec<Vec<String>> = subcommands(&String::from_utf8_lossy(
        &rigbridge(&["--help"], None).stdout,
    ))
    .into_iter()
    .map(|c| vec![c])
    .collect();
    let mut checked = 0;
    let mut problems = Vec::new();
    while let Some(command) = commands.pop() {
        let mut args: Vec<&str> = command.iter().map(String::as_str).collect();
        args.push("-h");
        let short = String::from_utf8_lossy(&rigbridge(&args, None).stdout).to_string();
        for nested in subcommands(&short) {
            let mut deeper = command.clone();
            deeper.push(nested);
            commands.push(deeper);
        }
        for bare in undescribed(&short) {
            problems.push(format!(
                "rigbridge {}: `{bare}` has no description",
                command.join(" ")
            ));
        }
        if short.contains("--link") {
            *args.last_mut().unwrap() = "--help";
            let long = String::from_utf8_lossy(&rigbridge(&args, None).stdout).to_string();
            for scheme in [
                "loopback",
                "tcp://",
                "serial://",
                "can://",
                "egm://",
                "dynamixel://",
                "canopen://",
            ] {
                if !long.contains(scheme) {
                    problems.push(format!(
                        "rigbridge {} --help leaves out {scheme}",
                        command.join(" ")
                    ));
                }
            }
        }
        checked += 1;
    }
    assert!(checked >= 10, "only {checked} commands found in --help");
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}
