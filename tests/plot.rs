//! `rigbridge log plot`: record a run against the twin, draw it, and check the PNG decodes,
//! has the requested size and is not blank; and that the log holds per-cycle jitter (on
//! the commands, `docs/logs.md` "Versions").

use crate::common;

use rigbridge::log::read_log;
use std::path::PathBuf;

fn scratch(name: &str) -> PathBuf {
    common::scratch_file("plot", name)
}

fn rigbridge(args: &[&str]) -> std::process::Output {
    let output = common::cli::rigbridge().args(args).output().unwrap();
    assert!(
        output.status.success(),
        "rigbridge {args:?} failed: {}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

#[test]
fn plots_a_recorded_run_to_a_png_of_the_requested_size() {
    let log = scratch("run.mcap");
    let png_path = scratch("run.png");
    rigbridge(&["run", "--clock", "virtual", "--log", log.to_str().unwrap()]);

    // Format 2: each command holds the lateness of the wake that sent it; states none.
    let run = read_log(&log).unwrap();
    assert!(!run.commands.is_empty() && !run.states.is_empty());
    assert!(
        run.commands
            .iter()
            .all(|c| c.late_us.is_some_and(|v| v >= 0.0))
    );
    assert!(run.states.iter().all(|s| s.late_us.is_none()));

    rigbridge(&[
        "log",
        "plot",
        log.to_str().unwrap(),
        "-o",
        png_path.to_str().unwrap(),
        "--width",
        "1000",
        "--height",
        "750",
    ]);

    let bytes = std::fs::read(&png_path).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes))
        .read_info()
        .unwrap();
    let mut pixels = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut pixels).unwrap();
    assert_eq!((info.width, info.height), (1000, 750));
    let pixels = &pixels[..info.buffer_size()];

    // Not blank: the pixel values vary, and a fair share of them is not background white.
    let n = pixels.len() as f64;
    let mean = pixels.iter().map(|&p| f64::from(p)).sum::<f64>() / n;
    let variance = pixels
        .iter()
        .map(|&p| (f64::from(p) - mean).powi(2))
        .sum::<f64>()
        / n;
    assert!(variance > 100.0, "pixel variance {variance}");
    let inked = pixels.iter().filter(|&&p| p < 200).count();
    assert!(inked as f64 > 0.01 * n, "{inked} of {n} values are ink");
}

#[test]
fn refuses_a_missing_log() {
    let output = common::cli::rigbridge()
        .args(["log", "plot", "/nonexistent/run.mcap", "-o"])
        .arg(scratch("missing.png"))
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("cannot read"));
}
