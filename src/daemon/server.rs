//! `rigbridge serve`: the daemon that stays up. A control API over HTTP + JSON on
//! 127.0.0.1: submit a job, status, pause/resume, stop (decelerate to standstill) and
//! e-stop. One job streams at a time; the twin persists between jobs, so each job starts
//! where the last one left the arm. Like mini-redis, the binary only binds the listener
//! and hands it to [`run`] with a shutdown signal.
//!
//! Access: with a token ([`ServeOptions::token`]) every control route requires
//! `Authorization: Bearer <token>` ([`require_token`]), and the live view's WebSocket the
//! token in the header, a `token` query parameter or a `rigbridge.token.<token>` subprotocol
//! ([`require_live_token`]: browsers cannot set headers on a WebSocket); on a listener that
//! is not loopback a token is mandatory and every `/api` route requires it, status included.
//! The page's static files (`/`, `/live.js`, `/live.css`) hold no state and stay open.
//!
//! The live view (`src/view`): a task samples the streamer's latest state 50 times a second
//! and sends each frame to every page connected to `/api/live`.

use super::config::{JobConfig, RunSettings};
use super::{DaemonError, RunReport, plan_for, stream_planned_with, twin_settings};
use crate::clock::{Clock, VirtualClock, WallClock};
use crate::link::LoopbackLink;
use crate::stream::StreamControl;
use crate::twin::{SharedWorld, Twin, TwinWorld};
use crate::view::{
    ArmScene, JobView, LiveHub, LiveSample, LiveScene, LiveSink, LiveSlot, ToolTrace, page,
};
use axum::extract::ws::{Message as WsMessage, WebSocket, WebSocketUpgrade};
use axum::extract::{Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use std::future::Future;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{broadcast, watch};

/// Frames per second sent to the live view: above the 30 a page needs to look smooth, a
/// fifth of the 250 Hz stream.
pub const LIVE_FRAME_RATE_HZ: f64 = 50.0;
/// The WebSocket subprotocol of `/api/live`; a page may offer its token as a second one,
/// `rigbridge.token.<token>`.
pub const LIVE_PROTOCOL: &str = "rigbridge.live";
const TOKEN_PROTOCOL_PREFIX: &str = "rigbridge.token.";

/// Where each job's MCAP log goes, which clock jobs run on, and the bearer token the API
/// requires (mandatory when the listener is not on a loopback address).
#[derive(Clone)]
pub struct ServeOptions {
    pub runs_dir: PathBuf,
    pub virtual_clock: bool,
    pub token: Option<String>,
}

/// Never prints the token itself.
impl std::fmt::Debug for ServeOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServeOptions")
            .field("runs_dir", &self.runs_dir)
            .field("virtual_clock", &self.virtual_clock)
            .field("token", &self.token.as_ref().map(|_| "<redacted>"))
            .finish()
    }
}

/// The state of [`require_token`]: the token requests must carry, if any.
#[derive(Clone)]
pub struct TokenCheck {
    token: Option<Arc<[u8]>>,
}

impl TokenCheck {
    /// `None` lets every request through.
    pub fn new(token: Option<&str>) -> Self {
        TokenCheck {
            token: token.map(|t| Arc::from(t.as_bytes())),
        }
    }

    /// Whether `request` may pass: always without a token, else only with
    /// `Authorization: Bearer <token>` (the scheme's case is free), compared in constant time.
    pub fn allows(&self, headers: &axum::http::HeaderMap) -> bool {
        let Some(expected) = &self.token else {
            return true;
        };
        let Some(value) = headers.get(header::AUTHORIZATION) else {
            return false;
        };
        let value = value.as_bytes();
        let Some((scheme, presented)) = value.split_at_checked(7) else {
            return false;
        };
        scheme.eq_ignore_ascii_case(b"bearer ") && constant_time_eq(presented, expected)
    }

    /// Whether a WebSocket request may pass: like [`TokenCheck::allows`], or with the token
    /// as the query parameter `token` (percent-encoded) or as a `rigbridge.token.<token>`
    /// value of `Sec-WebSocket-Protocol`.
    pub fn allows_websocket(&self, request: &Request) -> bool {
        let Some(expected) = &self.token else {
            return true;
        };
        if self.allows(request.headers()) {
            return true;
        }
        let in_query = request.uri().query().is_some_and(|query| {
            query
                .split('&')
                .filter_map(|pair| pair.strip_prefix("token="))
                .any(|value| percent_decode(value).is_some_and(|t| constant_time_eq(&t, expected)))
        });
        let in_protocol = request
            .headers()
            .get_all(header::SEC_WEBSOCKET_PROTOCOL)
            .iter()
            .filter_map(|value| value.to_str().ok())
            .flat_map(|value| value.split(','))
            .filter_map(|protocol| protocol.trim().strip_prefix(TOKEN_PROTOCOL_PREFIX))
            .any(|token| constant_time_eq(token.as_bytes(), expected));
        in_query || in_protocol
    }
}

/// `%XX` escapes and `+` decoded; `None` for a broken escape.
fn percent_decode(text: &str) -> Option<Vec<u8>> {
    let mut out = Vec::with_capacity(text.len());
    let mut bytes = text.bytes();
    while let Some(byte) = bytes.next() {
        out.push(match byte {
            b'%' => {
                let high = char::from(bytes.next()?).to_digit(16)?;
                let low = char::from(bytes.next()?).to_digit(16)?;
                u8::try_from(high * 16 + low).ok()?
            }
            b'+' => b' ',
            other => other,
        });
    }
    Some(out)
}

/// Equality whose time depends only on the lengths, not on where the bytes differ.
fn constant_time_eq(presented: &[u8], expected: &[u8]) -> bool {
    if expected.is_empty() {
        return false;
    }
    let mut diff = u8::from(presented.len() != expected.len());
    for (i, byte) in presented.iter().enumerate() {
        diff |= byte ^ expected[i % expected.len()];
    }
    std::hint::black_box(diff) == 0
}

/// The access check as axum middleware, reusable on any route (the control routes, a
/// future `/ws`): `route_layer(axum::middleware::from_fn_with_state(check, require_token))`.
/// Refuses a request without the right bearer token with 401 and a JSON error.
pub async fn require_token(
    State(check): State<TokenCheck>,
    request: Request,
    next: Next,
) -> Response {
    if check.allows(request.headers()) {
        return next.run(request).await;
    }
    let mut response = error(
        StatusCode::UNAUTHORIZED,
        "missing or wrong token: send `Authorization: Bearer <token>`",
    );
    response
        .headers_mut()
        .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
    response
}

/// The access check of the live view's WebSocket ([`TokenCheck::allows_websocket`]).
pub async fn require_live_token(
    State(check): State<TokenCheck>,
    request: Request,
    next: Next,
) -> Response {
    if check.allows_websocket(&request) {
        return next.run(request).await;
    }
    let mut response = error(
        StatusCode::UNAUTHORIZED,
        "missing or wrong token: send it as `?token=<token>`, as the WebSocket subprotocol \
         `rigbridge.token.<token>` or in `Authorization: Bearer <token>`",
    );
    response
        .headers_mut()
        .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
    response
}

/// Refuses control requests a browser sends on behalf of another site: a page open in a
/// local browser could otherwise POST to 127.0.0.1 and move the arm. Browsers send
/// `Origin` on every cross-origin POST; it must name the host the request went to.
/// Requests without `Origin` (curl, scripts, tests) pass.
pub async fn require_same_origin(request: Request, next: Next) -> Response {
    let headers = request.headers();
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
    let origin = headers.get(header::ORIGIN).and_then(|o| o.to_str().ok());
    let same = match origin {
        None => true,
        Some(origin) => {
            let origin_host = origin.split_once("://").map_or(origin, |(_, rest)| rest);
            host.is_some_and(|host| host == origin_host)
        }
    };
    if same {
        next.run(request).await
    } else {
        error(
            StatusCode::FORBIDDEN,
            "cross-origin request refused: control requests must come from this server's own page",
        )
    }
}

struct ActiveJob {
    id: u64,
    name: String,
    control: Arc<StreamControl>,
    handle: std::thread::JoinHandle<()>,
}

struct Shared {
    settings: RunSettings,
    options: ServeOptions,
    link: Arc<Mutex<LoopbackLink>>,
    job: Mutex<Option<ActiveJob>>,
    last: Arc<Mutex<Option<JobResult>>>,
    next_id: Mutex<u64>,
    hub: LiveHub,
    /// The twin's world for the current job (the twin outlives jobs; its world does not).
    world: SharedWorld<JobWorld>,
    /// Turns true when the server stops: live connections close.
    stopping: watch::Receiver<bool>,
}

#[derive(Debug, Clone, Serialize)]
#[serde(tag = "result", rename_all = "snake_case")]
enum JobResult {
    Finished { id: u64, report: Box<RunReport> },
    Failed { id: u64, error: String },
}

#[derive(Debug, Serialize)]
struct Status {
    state: &'static str,
    job: Option<JobStatus>,
    last: Option<JobResult>,
    actual_deg: Vec<f64>,
}

#[derive(Debug, Serialize)]
struct JobStatus {
    id: u64,
    name: String,
    progress: f64,
    cycles: u64,
    paused: bool,
}

#[derive(Debug, Deserialize)]
struct JobRequest {
    /// A job like config's `[job]`; the configured job when absent.
    job: Option<JobConfig>,
}

fn error(status: StatusCode, message: impl std::fmt::Display) -> Response {
    (
        status,
        Json(serde_json::json!({ "error": message.to_string() })),
    )
        .into_response()
}

/// Serves the control API on `listener` until `shutdown` completes; then stops any job
/// (decelerating along its path) and waits for it. Refuses a listener that is not on a
/// loopback address unless `options.token` is set.
pub async fn run(
    listener: tokio::net::TcpListener,
    settings: RunSettings,
    options: ServeOptions,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), DaemonError> {
    let local = listener.local_addr().map_err(crate::link::LinkError::Io)?;
    let exposed = !local.ip().is_loopback();
    if exposed && options.token.is_none() {
        return Err(DaemonError::Unavailable(format!(
            "refusing to serve on {local} without a token: a non-loopback address needs \
             RIGBRIDGE_TOKEN or [serve] token"
        )));
    }
    let check = TokenCheck::new(options.token.as_deref());
    let auth = axum::middleware::from_fn_with_state(check.clone(), require_token);
    let live_auth = axum::middleware::from_fn_with_state(check, require_live_token);
    let world = Arc::new(Mutex::new(JobWorld(None)));
    let twin = Twin::new(&settings.rig, twin_settings(&settings), &settings.initial())?
        .with_world(Box::new(world.clone()));
    let link = LoopbackLink::new(twin);
    std::fs::create_dir_all(&options.runs_dir).map_err(crate::link::LinkError::Io)?;
    let slot = Arc::new(LiveSlot::new(LiveSample::at_rest(&settings.initial())));
    let (scene, job_world) = scene_for_job(&settings, &settings.config.job);
    if let Ok(mut world) = world.lock() {
        world.0 = job_world;
    }
    let hub = LiveHub::new(
        settings.rig.clone(),
        settings.config.stream.rate_hz,
        LIVE_FRAME_RATE_HZ,
        slot,
        scene,
    );
    let (stop_live, stopping) = watch::channel(false);
    let shared = Arc::new(Shared {
        settings,
        options,
        link: Arc::new(Mutex::new(link)),
        job: Mutex::new(None),
        last: Arc::new(Mutex::new(None)),
        next_id: Mutex::new(1),
        hub,
        world,
        stopping,
    });
    let same_origin = axum::middleware::from_fn(require_same_origin);
    // Everything that moves the arm goes here: always behind the check.
    let control = Router::new()
        .route("/api/jobs", post(submit))
        .route("/api/pause", post(pause))
        .route("/api/resume", post(resume))
        .route("/api/stop", post(stop))
        .route("/api/estop", post(estop))
        .route_layer(auth.clone())
        .route_layer(same_origin.clone());
    // The arm's state, live: as guarded as control (a browser cannot send the header).
    let live = Router::new()
        .route("/api/live", get(live))
        .route_layer(live_auth)
        .route_layer(same_origin);
    let status = Router::new().route("/api/status", get(status));
    // Off loopback the arm's state is sensitive too.
    let status = if exposed {
        status.route_layer(auth)
    } else {
        status
    };
    let assets = Router::new()
        .route("/", get(index))
        .route("/live.js", get(live_js))
        .route("/live.css", get(live_css));
    let app = assets
        .merge(status)
        .merge(control)
        .merge(live)
        .with_state(shared.clone());
    let frames = tokio::spawn(send_frames(shared.clone()));
    let shutdown = async move {
        shutdown.await;
        let _ = stop_live.send(true);
    };
    axum::serve(listener, app)
        .with_graceful_shutdown(shutdown)
        .await
        .map_err(crate::link::LinkError::Io)?;
    frames.abort();
    let active = shared.job.lock().map(|mut job| job.take()).unwrap_or(None);
    if let Some(job) = active {
        job.control.stop();
        let _ = tokio::task::spawn_blocking(move || job.handle.join()).await;
    }
    Ok(())
}

async fn index() -> impl IntoResponse {
    (
        [("content-type", "text/html; charset=utf-8")],
        page::INDEX_HTML,
    )
}

async fn live_js() -> impl IntoResponse {
    (
        [("content-type", "text/javascript; charset=utf-8")],
        page::LIVE_JS,
    )
}

async fn live_css() -> impl IntoResponse {
    (
        [("content-type", "text/css; charset=utf-8")],
        page::LIVE_CSS,
    )
}

/// What the live view shows for `job`, and the twin's world that measures it: the one place
/// a kind of job chooses its scene. The star: the arm in front of its wall, the tool's trace
/// on the wall as paint.
fn scene_for_job(
    settings: &RunSettings,
    job: &JobConfig,
) -> (Box<dyn LiveScene>, Option<Box<dyn TwinWorld>>) {
    let trace = Arc::new(Mutex::new(ToolTrace::new(settings.rig.clone())));
    let scene = ArmScene::for_job(settings.rig.clone(), job, Some(trace.clone()));
    (Box::new(scene), Some(Box::new(trace)))
}

/// The twin's world for the job at hand, swapped when a job starts.
struct JobWorld(Option<Box<dyn TwinWorld>>);

impl TwinWorld for JobWorld {
    fn observe(&mut self, actual: &[f64]) {
        if let Some(world) = self.0.as_mut() {
            world.observe(actual);
        }
    }
}

/// The live view's frame task: samples the streamer's state at [`LIVE_FRAME_RATE_HZ`] in
/// real time (whatever clock jobs run on: a person watches it) and sends every page the frame.
async fn send_frames(shared: Arc<Shared>) {
    let clock = WallClock::new();
    let mut ticks = tokio::time::interval(Duration::from_secs_f64(1.0 / LIVE_FRAME_RATE_HZ));
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        ticks.tick().await;
        shared.hub.tick(clock.now(), job_view(&shared));
    }
}

fn job_view(shared: &Shared) -> JobView {
    let last = shared.last.lock().ok().and_then(|last| {
        last.as_ref().map(|result| match result {
            JobResult::Finished { report, .. } => serde_json::to_value(report.stream.outcome)
                .ok()
                .and_then(|v| v.as_str().map(String::from))
                .unwrap_or_default(),
            JobResult::Failed { error, .. } => format!("failed: {error}"),
        })
    });
    let running = shared.job.lock().ok().and_then(|job| {
        job.as_ref().filter(|j| !j.handle.is_finished()).map(|j| {
            (
                j.id,
                j.name.clone(),
                j.control.progress(),
                j.control.is_paused(),
            )
        })
    });
    match running {
        Some((id, name, progress, paused)) => JobView {
            state: if paused { "paused" } else { "running" },
            id: Some(id),
            name: Some(name),
            progress,
            last,
        },
        None => JobView {
            state: "idle",
            last,
            ..JobView::default()
        },
    }
}

async fn live(State(shared): State<Arc<Shared>>, upgrade: WebSocketUpgrade) -> Response {
    upgrade
        .protocols([LIVE_PROTOCOL])
        .on_upgrade(move |socket| serve_live(socket, shared))
}

/// One page: the scene, then every frame until the page goes or the server stops. A page
/// that falls behind skips to the present and gets the scene again (paint included).
async fn serve_live(mut socket: WebSocket, shared: Arc<Shared>) {
    let (scene, mut frames) = shared.hub.subscribe();
    let mut stopping = shared.stopping.clone();
    if socket
        .send(WsMessage::Text((&*scene).into()))
        .await
        .is_err()
    {
        return;
    }
    loop {
        tokio::select! {
            frame = frames.recv() => {
                let text = match frame {
                    Ok(text) => text,
                    Err(broadcast::error::RecvError::Lagged(_)) => shared.hub.scene_now(),
                    Err(broadcast::error::RecvError::Closed) => return,
                };
                if socket.send(WsMessage::Text((&*text).into())).await.is_err() {
                    return;
                }
            }
            incoming = socket.recv() => match incoming {
                None | Some(Err(_)) | Some(Ok(WsMessage::Close(_))) => return,
                Some(Ok(_)) => {}
            },
            _ = stopping.changed() => {
                let _ = socket.send(WsMessage::Close(None)).await;
                return;
            }
        }
    }
}

fn job_running(shared: &Shared) -> bool {
    shared
        .job
        .lock()
        .map(|job| job.as_ref().is_some_and(|j| !j.handle.is_finished()))
        .unwrap_or(false)
}

async fn status(State(shared): State<Arc<Shared>>) -> Response {
    let job = shared.job.lock().ok().and_then(|job| {
        job.as_ref()
            .filter(|j| !j.handle.is_finished())
            .map(|j| JobStatus {
                id: j.id,
                name: j.name.clone(),
                progress: j.control.progress(),
                cycles: j.control.cycles(),
                paused: j.control.is_paused(),
            })
    });
    let actual_deg = match shared.link.try_lock() {
        Ok(link) => link
            .twin()
            .actual()
            .iter()
            .map(|q| q.to_degrees())
            .collect(),
        Err(_) => Vec::new(),
    };
    let state = match &job {
        Some(j) if j.paused => "paused",
        Some(_) => "running",
        None => "idle",
    };
    let last = shared.last.lock().ok().and_then(|l| l.clone());
    Json(Status {
        state,
        job,
        last,
        actual_deg,
    })
    .into_response()
}

async fn submit(State(shared): State<Arc<Shared>>, body: axum::body::Bytes) -> Response {
    if job_running(&shared) {
        return error(
            StatusCode::CONFLICT,
            "a job is already running: stop it or wait",
        );
    }
    let request: JobRequest = if body.iter().all(u8::is_ascii_whitespace) {
        JobRequest { job: None }
    } else {
        match serde_json::from_slice(&body) {
            Ok(request) => request,
            Err(e) => {
                return error(
                    StatusCode::BAD_REQUEST,
                    format!("job request is not valid: {e}"),
                );
            }
        }
    };
    let job = request
        .job
        .unwrap_or_else(|| shared.settings.config.job.clone());
    let id = {
        let Ok(mut next) = shared.next_id.lock() else {
            return error(StatusCode::INTERNAL_SERVER_ERROR, "state lock poisoned");
        };
        *next += 1;
        *next - 1
    };
    let control = Arc::new(StreamControl::default());
    let name = serde_json::to_value(&job)
        .ok()
        .and_then(|v| v.get("kind").and_then(|k| k.as_str().map(String::from)))
        .unwrap_or_else(|| "job".into());
    let (planned_tx, planned_rx) = tokio::sync::oneshot::channel::<Result<(), String>>();
    let handle = spawn_job(shared.clone(), id, job, control.clone(), planned_tx);
    if let Ok(mut slot) = shared.job.lock() {
        *slot = Some(ActiveJob {
            id,
            name: name.clone(),
            control,
            handle,
        });
    }
    match planned_rx.await {
        Ok(Ok(())) => (
            StatusCode::ACCEPTED,
            Json(serde_json::json!({ "id": id, "job": name })),
        )
            .into_response(),
        Ok(Err(message)) => error(StatusCode::UNPROCESSABLE_ENTITY, message),
        Err(_) => error(
            StatusCode::INTERNAL_SERVER_ERROR,
            "the job thread ended before planning",
        ),
    }
}

/// Plans and streams one job on its own thread, reporting through `shared.last`. The
/// submitter learns whether planning succeeded (a bad target is refused before motion).
fn spawn_job(
    shared: Arc<Shared>,
    id: u64,
    job: JobConfig,
    control: Arc<StreamControl>,
    planned: tokio::sync::oneshot::Sender<Result<(), String>>,
) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        let clock: Box<dyn Clock> = if shared.options.virtual_clock {
            Box::new(VirtualClock::new())
        } else {
            Box::new(WallClock::new())
        };
        let log = shared.options.runs_dir.join(format!("job-{id}.mcap"));
        let Ok(mut link) = shared.link.lock() else {
            let _ = planned.send(Err("twin lock poisoned".into()));
            return;
        };
        let plan = plan_for(&shared.settings, &job, &mut *link);
        let _ = planned.send(plan.as_ref().map(|_| ()).map_err(|e| super::error_chain(e)));
        let result = plan.and_then(|plan| {
            let (scene, world) = scene_for_job(&shared.settings, &job);
            // Nothing streams yet: the twin is not observing.
            if let Ok(mut current) = shared.world.lock() {
                current.0 = world;
            }
            shared.hub.set_scene(scene);
            let rate = shared.settings.config.stream.rate_hz.round() as u64;
            let mut live = LiveSink::new(shared.hub.slot(), rate);
            stream_planned_with(
                &shared.settings,
                &plan,
                &mut *link,
                clock.as_ref(),
                Some(&log),
                &control,
                &mut live,
            )
        });
        let outcome = match result {
            Ok(report) => JobResult::Finished {
                id,
                report: Box::new(report),
            },
            Err(e) => JobResult::Failed {
                id,
                error: super::error_chain(&e),
            },
        };
        if let Ok(mut last) = shared.last.lock() {
            *last = Some(outcome);
        }
    })
}

fn with_control(shared: &Shared, act: impl Fn(&StreamControl)) -> Response {
    match shared.job.lock() {
        Ok(job) => match job.as_ref().filter(|j| !j.handle.is_finished()) {
            Some(j) => {
                act(&j.control);
                Json(serde_json::json!({ "id": j.id })).into_response()
            }
            None => error(StatusCode::CONFLICT, "no job is running"),
        },
        Err(_) => error(StatusCode::INTERNAL_SERVER_ERROR, "state lock poisoned"),
    }
}

async fn pause(State(shared): State<Arc<Shared>>) -> Response {
    with_control(&shared, StreamControl::pause)
}

async fn resume(State(shared): State<Arc<Shared>>) -> Response {
    with_control(&shared, StreamControl::resume)
}

async fn stop(State(shared): State<Arc<Shared>>) -> Response {
    with_control(&shared, StreamControl::stop)
}

async fn estop(State(shared): State<Arc<Shared>>) -> Response {
    with_control(&shared, StreamControl::estop)
}
