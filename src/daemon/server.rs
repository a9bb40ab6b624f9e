//! `rigbridge serve`: the daemon that stays up. A control API over HTTP + JSON on
//! 127.0.0.1: submit a job, status, pause/resume, stop (decelerate to standstill) and
//! e-stop. One job streams at a time; the twin persists between jobs, so each job starts
//! where the last one left the arm. Like mini-redis, the binary only binds the listener
//! and hands it to [`run`] with a shutdown signal.
//!
//! Access: with a token ([`ServeOptions::token`]) every control route requires
//! `Authorization: Bearer <token>` ([`require_token`]); on a listener that is not loopback a
//! token is mandatory and every route requires it, status included.

use super::config::{JobConfig, RunSettings};
use super::{DaemonError, RunReport, loopback_twin, plan_for, stream_planned};
use crate::clock::{Clock, VirtualClock, WallClock};
use crate::link::LoopbackLink;
use crate::stream::StreamControl;
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
    let auth = axum::middleware::from_fn_with_state(check, require_token);
    let link = loopback_twin(&settings)?;
    std::fs::create_dir_all(&options.runs_dir).map_err(crate::link::LinkError::Io)?;
    let shared = Arc::new(Shared {
        settings,
        options,
        link: Arc::new(Mutex::new(link)),
        job: Mutex::new(None),
        last: Arc::new(Mutex::new(None)),
        next_id: Mutex::new(1),
    });
    // Everything that moves the arm goes here (a future `/ws` too): always behind the check.
    let control = Router::new()
        .route("/api/jobs", post(submit))
        .route("/api/pause", post(pause))
        .route("/api/resume", post(resume))
        .route("/api/stop", post(stop))
        .route("/api/estop", post(estop))
        .route_layer(auth.clone())
        .route_layer(axum::middleware::from_fn(require_same_origin));
    let read = Router::new()
        .route("/", get(index))
        .route("/api/status", get(status));
    let app = read.merge(control).with_state(shared.clone());
    // Off loopback the arm's state is sensitive too: every request needs the token.
    let app = if exposed { app.layer(auth) } else { app };
    axum::serve(listener, app)
        .with_graceful_shutdown(shutdown)
        .await
        .map_err(crate::link::LinkError::Io)?;
    let active = shared.job.lock().map(|mut job| job.take()).unwrap_or(None);
    if let Some(job) = active {
        job.control.stop();
        let _ = tokio::task::spawn_blocking(move || job.handle.join()).await;
    }
    Ok(())
}

async fn index() -> impl IntoResponse {
    (
        [("content-type", "text/plain; charset=utf-8")],
        "rigbridge control API: GET /api/status; POST /api/jobs {\"job\": {...}} (optional), /api/pause, /api/resume, /api/stop, /api/estop\n",
    )
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
            stream_planned(
                &shared.settings,
                &plan,
                &mut *link,
                clock.as_ref(),
                Some(&log),
                &control,
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
