//! The live view end to end in a real browser: `rigbridge serve` (the built binary, wall
//! clock, 250 Hz) and headless Chromium driven over WebDriver (Debian's `chromium` and
//! `chromium-driver`; `scripts/test.sh` installs them). The page must draw its first frame
//! within 1 s of loading, start a job from its button, redraw the canvas as the twin moves,
//! update its status numbers, receive frames while streaming and draw at least half of them
//! (the rates themselves are reported, not judged: they are the machine's load), and log no
//! error. Chromium runs in chromedriver's process group, killed whole however the test ends.
//! The daemon runs three cells: the arm (its star job), the painter in a generated room
//! (streamed at 250 Hz) and the sloth on its branch. The page shows the first; its cell
//! selector switches to the others, whose jobs it starts from the page and watches. Saves a
//! screenshot of each to `target/e2e/`: `live-view.png` (the star), `live-view-room.png`
//! (walls, openings, arm and paint) and `live-view-sloth.png`.
//!
//! Without Chromium the test fails, unless `RIGBRIDGE_SKIP_BROWSER=1`, when it says why it
//! skips. `RIGBRIDGE_CHROMIUM` and `RIGBRIDGE_CHROMEDRIVER` override the binaries' paths.
//! Traffic only ever goes to 127.0.0.1.

use crate::common;

use common::group::{GONE_WITHIN, ProcessGroup, live_members};
use common::repo_path;
use common::serve::{Served, serve_command, start_serve};
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Exactly the flags this machine's closed network needs (plus a fresh profile).
const CHROMIUM_FLAGS: [&str; 7] = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
];

/// Redraws of the still twin that must all give one picture (the daemon sends 50 frames
/// a second, each one redrawn).
const AT_REST_REDRAWS: u64 = 10;
/// The page rates its frames and messages each second: two of them, with room for a
/// loaded machine.
const RATE_WAIT: Duration = Duration::from_secs(5);
/// The page's second, less the jitter of its timer (a few ms either way; 50 to spare): a
/// figure rated this long after another covers the second between them.
const RATED_SECOND_MS: f64 = 950.0;

fn binary(variable: &str, default: &str) -> PathBuf {
    std::env::var_os(variable).map_or_else(|| PathBuf::from(default), PathBuf::from)
}

/// The painting cell for the daemon in `dir`: `config/paint-run.toml` streamed at 250 Hz
/// (the rate the live view must keep up with), beside copies of the files it names (a job's
/// files must lie in its config's directory).
fn painting_cell(dir: &Path) -> PathBuf {
    let shipped = std::fs::read_to_string(repo_path("config/paint-run.toml")).unwrap();
    assert!(
        shipped.contains("rate_hz = 100.0"),
        "config/paint-run.toml streams at 100 Hz"
    );
    for name in ["painter.toml", "paint.toml", "cell-painter.toml"] {
        std::fs::copy(repo_path(&format!("config/{name}")), dir.join(name)).unwrap();
    }
    let file = dir.join("paint-250hz.toml");
    std::fs::write(&file, shipped.replace("rate_hz = 100.0", "rate_hz = 250.0")).unwrap();
    file
}

/// `rigbridge serve` on a free port of 127.0.0.1 with the arm's cell, `painting` and the
/// sloth's; returns it and its page's address.
fn start_server(runs: &Path, painting: &Path) -> (Served, String) {
    let daemon = start_serve(
        serve_command(runs)
            .args(["--clock", "wall"])
            .args(["--config", "config/rigbridge.toml", "--config"])
            .arg(painting)
            .args(["--config", "config/gait-run.toml"])
            .stderr(Stdio::null()),
    );
    let url = format!("http://{}/", daemon.address);
    assert!(url.starts_with("http://127.0.0.1:"), "{url}");
    (daemon, url)
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// One plain HTTP/1.1 request to chromedriver; the JSON body of its answer.
fn driver_request(port: u16, method: &str, path: &str, body: &str) -> Option<Value> {
    let mut stream = TcpStream::connect(("127.0.0.1", port)).ok()?;
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .ok()?;
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .ok()?;
    // chromedriver keeps the connection open: read the head, then Content-Length bytes.
    let mut reader = BufReader::new(stream);
    let mut length = 0;
    loop {
        let mut line = String::new();
        reader.read_line(&mut line).ok()?;
        let line = line.trim_end();
        if line.is_empty() {
            break;
        }
        if let Some((name, value)) = line.split_once(':')
            && name.eq_ignore_ascii_case("content-length")
        {
            length = value.trim().parse().ok()?;
        }
    }
    let mut body = vec![0; length];
    reader.read_exact(&mut body).ok()?;
    serde_json::from_slice(&body).ok()
}

/// chromedriver on a free port, leading a process group of its own: the Chromium it starts
/// and the renderers Chromium forks stay in that group, all killed when the test lets go of
/// it, however the test ends.
fn start_chromedriver(driver: &Path) -> (ProcessGroup, u16) {
    let port = free_port();
    let running = ProcessGroup::spawn(
        Command::new(driver)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null()),
    )
    .unwrap_or_else(|e| panic!("cannot start {}: {e}", driver.display()));
    let deadline = Instant::now() + Duration::from_secs(20);
    while driver_request(port, "GET", "/status", "").is_none_or(|s| s["value"]["ready"] != true) {
        assert!(Instant::now() < deadline, "chromedriver never got ready");
        std::thread::sleep(Duration::from_millis(100));
    }
    (running, port)
}

async fn eval(client: &Client, script: &str) -> Value {
    client
        .execute(script, Vec::new())
        .await
        .unwrap_or_else(|e| panic!("script failed: {script}: {e}"))
}

/// A hash of the canvas' pixels as PNG (FNV-1a over its data URL), computed in the page.
async fn canvas_hash(client: &Client) -> String {
    let hash = eval(
        client,
        "const s = document.getElementById('view').toDataURL('image/png');
         let h = 0x811c9dc5;
         for (let i = 0; i < s.length; i++) { h ^= s.charCodeAt(i); h = Math.imul(h, 0x01000193) >>> 0; }
         return h.toString(16) + ':' + s.length;",
    )
    .await;
    hash.as_str().unwrap().to_string()
}

async fn text_of(client: &Client, id: &str) -> String {
    client
        .find(Locator::Id(id))
        .await
        .unwrap()
        .text()
        .await
        .unwrap()
}

async fn health(client: &Client) -> Value {
    eval(client, "return window.rigbridgeView;").await
}

/// Polls `script` (returning a boolean) until true.
async fn wait_until(client: &Client, what: &str, script: &str, timeout: Duration) {
    let deadline = Instant::now() + timeout;
    while eval(client, script).await != Value::Bool(true) {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The page's clock (`performance.now()`, ms).
async fn page_now(client: &Client) -> f64 {
    eval(client, "return performance.now();")
        .await
        .as_f64()
        .unwrap()
}

/// Waits until the page has drawn `frames` more frames.
async fn redrawn(client: &Client, frames: u64) {
    let drawn = health(client).await["framesDrawn"].as_u64().unwrap();
    wait_until(
        client,
        &format!("{frames} frames drawn after frame {drawn}"),
        &format!(
            "return window.rigbridgeView.framesDrawn >= {};",
            drawn + frames
        ),
        Duration::from_secs(5),
    )
    .await;
}

/// The page's health once the rates it shows (each second, over the one before) are of a
/// second wholly after `since` (page clock, ms), with `rateAt`: when that second ended.
async fn rates_after(client: &Client, since: f64) -> Value {
    let window_start = rated_after(client, since).await;
    next_rates(client, window_start).await
}

/// The page's health once it has rated the second that began at `rated_at` (the end of
/// the one before), with `rateAt`. A second, less its timer's jitter, has passed by then.
async fn next_rates(client: &Client, rated_at: f64) -> Value {
    rated_after(client, rated_at + RATED_SECOND_MS).await;
    eval(
        client,
        "return Object.assign({ rateAt: lastRateAt }, window.rigbridgeView);",
    )
    .await
}

/// Waits until the page has rated a second that ended after `after`; returns when it ended.
async fn rated_after(client: &Client, after: f64) -> f64 {
    let script = format!("return lastRateAt > {after};");
    wait_until(client, "the page's rates", &script, RATE_WAIT).await;
    eval(client, "return lastRateAt;").await.as_f64().unwrap()
}

/// The page keeps up with the frames it receives: in one second it rated, it received
/// frames and drew at least this share of them. A frame is drawn at the next animation frame
/// after it arrives, so two arriving within one animation frame are drawn once; drawing fewer
/// than half would mean the page falls behind the stream. The rates themselves (50 frames/s
/// sent, `LIVE_FRAME_RATE_HZ`) are figures of the machine's load, printed with the report,
/// not judged: both fall together on a loaded machine.
const DRAWN_PER_RECEIVED: f64 = 0.5;

/// Asserts that `figures` (the page's rates over one second while `what` streams) show
/// frames received and drawn, at least [`DRAWN_PER_RECEIVED`] of them.
fn keeps_up(figures: &Value, what: &str) {
    let fps = figures["fps"].as_f64().unwrap();
    let ws_rate = figures["wsRate"].as_f64().unwrap();
    assert!(
        ws_rate > 0.0 && fps >= DRAWN_PER_RECEIVED * ws_rate,
        "frames drawn per frame received while {what} streams: {fps:.1} drawn, {ws_rate:.1} received in one second ({figures})"
    );
}

fn rated_at(figures: &Value) -> f64 {
    figures["rateAt"].as_f64().unwrap()
}

#[test]
fn the_live_view_draws_the_twin_and_runs_a_job_in_headless_chromium() {
    if !common::in_full_tier(
        "live_view::the_live_view_draws_the_twin_and_runs_a_job_in_headless_chromium",
    ) {
        return;
    }
    let chromium = binary("RIGBRIDGE_CHROMIUM", "/usr/bin/chromium");
    let driver = binary("RIGBRIDGE_CHROMEDRIVER", "/usr/bin/chromedriver");
    if !chromium.exists() || !driver.exists() {
        let why = format!(
            "no browser for the live view's end-to-end test: {} or {} is missing \
             (apt-get install -y chromium chromium-driver; scripts/test.sh does it)",
            chromium.display(),
            driver.display()
        );
        if std::env::var("RIGBRIDGE_SKIP_BROWSER").as_deref() == Ok("1") {
            eprintln!("skipping, RIGBRIDGE_SKIP_BROWSER=1: {why}");
            return;
        }
        panic!("{why}; set RIGBRIDGE_SKIP_BROWSER=1 to skip knowingly");
    }
    let scratch = std::env::temp_dir().join(format!("rigbridge-e2e-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&scratch);
    std::fs::create_dir_all(&scratch).unwrap();
    let painting = painting_cell(&scratch);
    let (_server, url) = start_server(&scratch.join("runs"), &painting);
    let (browser, driver_port) = start_chromedriver(&driver);
    let profile = scratch.join("profile");

    let runtime = tokio::runtime::Runtime::new().unwrap();
    let report = runtime.block_on(async {
        let mut args: Vec<String> = CHROMIUM_FLAGS.iter().map(|f| f.to_string()).collect();
        args.push(format!("--user-data-dir={}", profile.display()));
        let capabilities = json!({
            "browserName": "chrome",
            "goog:chromeOptions": { "binary": chromium, "args": args },
            "goog:loggingPrefs": { "browser": "ALL" },
        });
        let Value::Object(capabilities) = capabilities else {
            unreachable!()
        };
        let client = ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
            .capabilities(capabilities)
            .connect(&format!("http://127.0.0.1:{driver_port}"))
            .await
            .expect("a WebDriver session in headless Chromium");
        let session = client.session_id().await.unwrap().unwrap();
        client.set_window_size(1280, 960).await.unwrap();
        let report = exercise_page(&client, &url).await;
        let console = driver_request(
            driver_port,
            "POST",
            &format!("/session/{session}/se/log"),
            r#"{"type":"browser"}"#,
        )
        .expect("chromedriver's browser log");
        client.close().await.unwrap();
        (report, console)
    });
    let (report, console) = report;
    leaves_no_browser_behind(browser, &profile);
    eprintln!("live view: {report}");
    let entries = console["value"].as_array().cloned().unwrap_or_default();
    // The one refusal this test asks for (the pasted job out of range) is a 422 that
    // Chromium logs as a failed load: that entry, and only that one, is expected.
    let asked_refusal = |e: &Value| {
        e["source"] == "network"
            && e["message"]
                .as_str()
                .is_some_and(|m| m.contains("/api/jobs - ") && m.contains("status of 422"))
    };
    let refusals = entries.iter().filter(|e| asked_refusal(e)).count();
    assert_eq!(refusals, 1, "the pasted job's refusal: {entries:#?}");
    let severe: Vec<&Value> = entries
        .iter()
        .filter(|e| e["level"] == "SEVERE" || e["level"] == "WARNING")
        .filter(|e| !asked_refusal(e))
        .collect();
    eprintln!(
        "browser console: {} entries, {} warnings or errors",
        entries.len(),
        severe.len()
    );
    assert!(severe.is_empty(), "browser console: {severe:#?}");
    let _ = std::fs::remove_dir_all(&scratch);
}

/// Lets go of the browser's process group (chromedriver, Chromium and its renderers) and
/// checks that none of them, and nothing naming the run's `profile` directory, still runs.
fn leaves_no_browser_behind(browser: ProcessGroup, profile: &Path) {
    let group = browser.id();
    assert!(
        !live_members(group, Some(profile)).is_empty(),
        "the browser's processes are seen in group {group} before it is let go"
    );
    drop(browser);
    common::wait_until(
        &format!("no process of the browser's group {group} left"),
        GONE_WITHIN,
        || live_members(group, Some(profile)).is_empty().then_some(()),
    );
}

/// The guard the browser runs under, with a stand-in that forks as Chromium does (a child
/// that forks a grandchild of its own): when the test holding it panics, the whole group is
/// gone after the unwind, grandchildren included. Needs no browser: runs in every tier.
#[test]
fn a_panicking_test_leaves_no_process_of_its_browser_group() {
    let group = ProcessGroup::spawn(
        Command::new("sh").args(["-c", "sleep 300 & sh -c 'sleep 300 & wait' & wait"]),
    )
    .expect("sh starts");
    let id = group.id();
    // sh, its sleep, the inner sh and its sleep.
    common::wait_until(
        &format!("four processes in group {id}"),
        GONE_WITHIN,
        || (live_members(id, None).len() >= 4).then_some(()),
    );
    let unwound = std::panic::catch_unwind(std::panic::AssertUnwindSafe(move || {
        let _held = group;
        panic!("the test fails while it holds the browser");
    }));
    assert!(unwound.is_err());
    common::wait_until(
        &format!("no process of group {id} left after the panic"),
        GONE_WITHIN,
        || live_members(id, None).is_empty().then_some(()),
    );
}

/// Loads the page and drives it; returns the figures it measured.
async fn exercise_page(client: &Client, url: &str) -> Value {
    client.goto(url).await.unwrap();
    wait_until(
        client,
        "the first frame",
        "return window.rigbridgeView && window.rigbridgeView.firstFrameMs !== null;",
        Duration::from_secs(5),
    )
    .await;
    let first_frame_ms = health(client).await["firstFrameMs"].as_f64().unwrap();
    assert!(
        first_frame_ms < 1000.0,
        "first frame {first_frame_ms:.0} ms after navigation start"
    );
    assert_eq!(text_of(client, "job-state").await, "idle");
    // At rest the picture holds still: whatever changes later is the twin moving.
    let at_rest = canvas_hash(client).await;
    redrawn(client, AT_REST_REDRAWS).await;
    assert_eq!(
        canvas_hash(client).await,
        at_rest,
        "a still twin draws the same picture"
    );
    let cycles_at_rest = text_of(client, "link-cycles").await;

    click(client, "start").await;
    wait_for_state(client, "running", Duration::from_secs(10)).await;
    let early = rates_after(client, page_now(client).await).await;
    let moving = canvas_hash(client).await;
    let cycles_early: u64 = text_of(client, "link-cycles").await.parse().unwrap();
    let rate_early = text_of(client, "link-rate").await;
    // The next second the page measures.
    let streaming = next_rates(client, rated_at(&early)).await;
    let later = canvas_hash(client).await;
    let cycles_later: u64 = text_of(client, "link-cycles").await.parse().unwrap();
    assert_ne!(moving, at_rest, "the canvas changes as the twin moves");
    assert_ne!(later, moving, "and keeps changing");
    assert_ne!(cycles_at_rest, cycles_early.to_string());
    let rated_s = (rated_at(&streaming) - rated_at(&early)) / 1000.0;
    assert!(
        cycles_later > cycles_early + 150,
        "status numbers update: {cycles_early} -> {cycles_later} cycles in 1 s at 250 Hz (read {rated_s:.2} s apart)"
    );
    for figures in [&early, &streaming] {
        keeps_up(figures, "the star");
    }
    // Half-way through the star: arm, wall and paint in one picture.
    wait_until(
        client,
        "the star half drawn",
        "return document.getElementById('job-progress').value > 0.55;",
        Duration::from_secs(20),
    )
    .await;
    save_screenshot(client, "live-view.png").await;
    let painted: u64 = eval(client, "return window.rigbridgeView.paintQuads;")
        .await
        .as_u64()
        .unwrap();
    assert!(painted > 20, "paint on the wall: {painted} quads");
    for (button, state) in [("pause", "paused"), ("resume", "running")] {
        click(client, button).await;
        wait_for_state(client, state, Duration::from_secs(10)).await;
    }
    wait_until(
        client,
        "the job to end",
        "return document.getElementById('job-state').textContent === 'idle';",
        Duration::from_secs(30),
    )
    .await;
    assert_eq!(text_of(client, "job-last").await, "last job: completed");
    let star_plan = health(client).await;
    assert!(
        star_plan["planPoints"].as_u64().unwrap() > 100
            && star_plan["planTargets"].as_u64().unwrap() > 5,
        "the star's tool path and corners are drawn: {star_plan}"
    );
    let pasted = paste_jobs(client, url).await;
    let room = paint_the_room(client).await;
    let sloth = watch_the_sloth(client).await;
    let end = health(client).await;
    let errors = end["errors"].as_array().unwrap();
    assert!(errors.is_empty(), "errors the page collected: {errors:?}");
    json!({
        "first_frame_ms": first_frame_ms,
        "fps_while_streaming": [early["fps"], streaming["fps"]],
        "ws_messages_per_s": [early["wsRate"], streaming["wsRate"]],
        "rate_shown": rate_early,
        "cycles_in_1s": cycles_later - cycles_early,
        "paint_quads": painted,
        "frames_drawn": end["framesDrawn"],
        "page_errors": errors.len(),
        "star_plan": [star_plan["planPoints"], star_plan["planTargets"]],
        "pasted": pasted,
        "room": room,
        "sloth": sloth,
    })
}

/// Puts `text` in the page's paste box and clicks "Start pasted job".
async fn paste(client: &Client, text: &str) {
    client
        .execute(
            "document.getElementById('paste').value = arguments[0];
             document.getElementById('paste-result').textContent = '';
             document.getElementById('paste-start').click();",
            vec![json!(text)],
        )
        .await
        .unwrap();
}

/// The paste box: a TOML job with a value out of range comes back with the API's refusal
/// (key and value) under the box; a good one starts, its plan (one target) is drawn, and it
/// completes (waited for on the API's `?wait_s=`).
async fn paste_jobs(client: &Client, url: &str) -> Value {
    paste(
        client,
        "[job]\nkind = \"move_joints\"\ntargets_deg = [[0, 130, 0, 0, 30, 0]]\n",
    )
    .await;
    wait_until(
        client,
        "the pasted job's refusal",
        "return document.getElementById('paste-result').textContent.startsWith('422');",
        Duration::from_secs(10),
    )
    .await;
    let refusal = text_of(client, "paste-result").await;
    assert!(
        refusal.starts_with("422: key `job.targets_deg[0][1]` = 130"),
        "{refusal}"
    );
    paste(
        client,
        "[job]\nkind = \"move_joints\"\ntargets_deg = [[20, 10, 0, 0, 30, 0]]\n",
    )
    .await;
    wait_until(
        client,
        "the pasted job to start",
        "return document.getElementById('paste-result').textContent.startsWith('started job');",
        Duration::from_secs(10),
    )
    .await;
    let started = text_of(client, "paste-result").await;
    wait_until(
        client,
        "the pasted job's plan",
        "return window.rigbridgeView.planTargets === 1 && window.rigbridgeView.planPoints > 1;",
        Duration::from_secs(10),
    )
    .await;
    let id: u64 = started
        .trim_start_matches("started job ")
        .split(' ')
        .next()
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{started}"));
    let address = url.trim_start_matches("http://").trim_end_matches('/');
    let (code, entry) =
        common::serve::request_json(address, "GET", &format!("/api/jobs/{id}?wait_s=30"), "", "");
    assert_eq!(code, 200, "{entry}");
    assert_eq!(entry["report"]["outcome"], "completed", "{entry}");
    json!({ "refusal": refusal, "started": started })
}

/// Saves the page as `target/e2e/<name>`.
async fn save_screenshot(client: &Client, name: &str) {
    let screenshot = client.screenshot().await.unwrap();
    let out = repo_path("target/e2e");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join(name), &screenshot).unwrap();
}

async fn click(client: &Client, id: &str) {
    client
        .find(Locator::Id(id))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
}

async fn wait_for_state(client: &Client, state: &str, timeout: Duration) {
    wait_until(
        client,
        &format!("the job state {state}"),
        &format!("return document.getElementById('job-state').textContent === '{state}';"),
        timeout,
    )
    .await;
}

/// Chooses `cell` in the page's selector and waits for its scene (`joints` rows).
async fn choose_cell(client: &Client, cell: &str, joints: usize) {
    wait_until(
        client,
        "the cell selector",
        "return !document.getElementById('cell').hidden;",
        Duration::from_secs(5),
    )
    .await;
    eval(
        client,
        &format!(
            "const select = document.getElementById('cell');
             select.value = '{cell}';
             select.dispatchEvent(new Event('change'));
             return true;"
        ),
    )
    .await;
    wait_until(
        client,
        &format!("the scene of the cell {cell}"),
        &format!(
            "return document.getElementById('rig-name').textContent.startsWith('{cell}') &&
                    document.querySelectorAll('#joints tbody tr').length === {joints};"
        ),
        Duration::from_secs(5),
    )
    .await;
    assert_eq!(text_of(client, "job-state").await, "idle");
}

/// Starts the cell's job from the page; the control line it shows.
async fn start_from_page(client: &Client, cell: &str) -> String {
    click(client, "start").await;
    // The daemon answers once the job is planned (a painting room takes a moment).
    wait_until(
        client,
        "the answer to the job request",
        "return !document.getElementById('control-result').textContent.endsWith('...');",
        Duration::from_secs(20),
    )
    .await;
    wait_for_state(client, "running", Duration::from_secs(20)).await;
    let result = text_of(client, "control-result").await;
    assert!(
        result.starts_with(&format!("/api/cells/{cell}/jobs: 202")),
        "{result}"
    );
    result
}

/// The painter's cell: its room (4 walls) before the job, then the job at 250 Hz with the
/// room view: frame rates while it streams, paint going on, a screenshot, and a stop.
async fn paint_the_room(client: &Client) -> Value {
    choose_cell(client, "painter", 10).await;
    let walls = health(client).await["sceneWalls"].as_u64().unwrap();
    assert_eq!(walls, 4, "the room's walls are in the scene before the job");
    let control = start_from_page(client, "painter").await;
    let early = rates_after(client, page_now(client).await).await;
    let cycles_early: u64 = text_of(client, "link-cycles").await.parse().unwrap();
    let streaming = next_rates(client, rated_at(&early)).await;
    let cycles_later: u64 = text_of(client, "link-cycles").await.parse().unwrap();
    let rated_s = (rated_at(&streaming) - rated_at(&early)) / 1000.0;
    assert!(
        cycles_later > cycles_early + 150,
        "the painter streams at 250 Hz: {cycles_early} -> {cycles_later} cycles in 1 s (read {rated_s:.2} s apart)"
    );
    for figures in [&early, &streaming] {
        keeps_up(figures, "the room view");
    }
    // A few strokes on the first wall: paint between the openings.
    wait_until(
        client,
        "paint on the walls",
        "return window.rigbridgeView.paintQuads >= 60;",
        Duration::from_secs(90),
    )
    .await;
    // The camera turned to face wall 0 (+x, where the painter starts) and brought closer to
    // the painter, as a person would.
    eval(
        client,
        "Object.assign(camera, { yaw: 2.9, pitch: 0.35, distance: 4.5, target: [0.9, -0.6, 1.0] });
         cameraMoved = true; dirty = true; return true;",
    )
    .await;
    redrawn(client, 1).await;
    save_screenshot(client, "live-view-room.png").await;
    let painted = health(client).await["paintQuads"].as_u64().unwrap();
    click(client, "stop").await;
    wait_for_state(client, "idle", Duration::from_secs(20)).await;
    assert_eq!(text_of(client, "job-last").await, "last job: stopped");
    json!({
        "cell": "painter",
        "control": control,
        "walls": walls,
        "fps_while_streaming": [early["fps"], streaming["fps"]],
        "ws_messages_per_s": [early["wsRate"], streaming["wsRate"]],
        "cycles_in_1s": cycles_later - cycles_early,
        "paint_quads": painted,
    })
}

/// The sloth's cell: its branch before the job, then the gait from the page to the end,
/// with a screenshot half-way.
async fn watch_the_sloth(client: &Client) -> Value {
    choose_cell(client, "sloth", 26).await;
    let cylinders = health(client).await["sceneCylinders"].as_u64().unwrap();
    assert!(cylinders >= 1, "the branch is in the scene before the job");
    let at_rest = canvas_hash(client).await;
    let control = start_from_page(client, "sloth").await;
    wait_until(
        client,
        "the gait half-way",
        "return document.getElementById('job-progress').value > 0.5;",
        Duration::from_secs(30),
    )
    .await;
    assert_ne!(
        canvas_hash(client).await,
        at_rest,
        "the sloth moves on the canvas"
    );
    save_screenshot(client, "live-view-sloth.png").await;
    wait_for_state(client, "idle", Duration::from_secs(30)).await;
    assert_eq!(text_of(client, "job-last").await, "last job: completed");
    json!({ "cell": "sloth", "control": control, "cylinders": cylinders })
}
