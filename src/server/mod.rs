//! `rigbridge serve`: the daemon that stays up. A control API over HTTP + JSON on
//! 127.0.0.1 for one or more cells ([`cell`]: one run settings file each, so one rig with
//! its own twin, job slot and live view): submit a job, status, the cell's latest jobs (a
//! lookup may wait for a job's end), pause/resume, stop (decelerate to standstill), e-stop
//! and reset (clear a latched fault), per cell under `/api/cells/{cell}/`, and for the
//! first cell also without the prefix. One job streams at a time per cell; jobs in
//! different cells run side by side. A cell's twin persists between jobs, so each job starts
//! where the last one left the rig. Like mini-redis, the binary only binds the listener
//! and hands it to [`run`] with a shutdown signal.
//!
//! Access: with a token ([`ServeOptions::token`]) every control route requires
//! `Authorization: Bearer <token>` ([`require_token`]), and the live view's WebSocket the
//! token in the header, a `token` query parameter or a `rigbridge.token.<token>` subprotocol
//! ([`require_live_token`]: browsers cannot set headers on a WebSocket); on a listener that
//! is not loopback a token is mandatory and every `/api` route requires it, status included.
//! The page's static files (`/`, `/live.js`, `/live.css`) hold no state and stay open.
//!
//! The live view (`src/view`): a task samples every cell's streamer state 50 times a second
//! and sends each frame to every page connected to that cell's live route, and the same
//! task feeds the live Foxglove server ([`foxglove`], its own listener, read-only).

mod cell;
mod connections;
mod fjt;
mod foxglove;
mod guard;
mod online;
pub mod ros2;
mod servo;

pub use cell::{CellError, check_cells};
pub use connections::{HEADER_TIMEOUT, IDLE_TIMEOUT, LISTEN_BACKLOG, bind, connection_cap};
pub use foxglove::{
    FOXGLOVE_APP_ORIGINS, FOXGLOVE_BACKLOG, FOXGLOVE_IDLE_TIMEOUT, FOXGLOVE_SUBPROTOCOL,
    MAX_FOXGLOVE_CLIENTS, MAX_FOXGLOVE_MESSAGE_BYTES, SEND_TIMEOUT as FOXGLOVE_SEND_TIMEOUT,
    URDF_URI_PREFIX,
};
pub use guard::{BODY_TIMEOUT, HostCheck, MAX_BODY_BYTES, MAX_LIVE_MESSAGE_BYTES, MAX_LIVE_PAGES};

use crate::clock::{self, Clock, WallClock};
use crate::daemon::config::ExecutorKind;
use crate::daemon::config::{JobConfig, RunSettings};
use crate::daemon::{DaemonError, error_chain};
use crate::stream::{Executor, ExecutorSettings, StreamControl};
use crate::twin::TwinWorld;
use crate::view::page;
use axum::extract::ws::{CloseFrame, Message as WsMessage, WebSocket, WebSocketUpgrade};
use axum::extract::{FromRequestParts, RawPathParams, RawQuery, Request, State};
use axum::http::request::Parts;
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use cell::{Cell, ResetRefused, StartRefused};
use serde::Deserialize;
use std::future::Future;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
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
    /// Host names requests may carry besides IP addresses and `localhost` (`[serve] hosts`):
    /// any other `Host` is refused, so a DNS-rebinding page cannot reach the API.
    pub allowed_hosts: Vec<String>,
    /// Called on each job's own thread before it plans, with the cell's name and the job's
    /// number (a hook for instrumentation). Whatever it does, a panic in it is contained
    /// like any panic of the job: that job fails, the daemon and the other cells go on.
    pub before_job: Option<BeforeJob>,
    /// The live Foxglove server's port on the listener's address (`[serve] foxglove_port`);
    /// 0 turns it off.
    pub foxglove_port: u16,
    /// Whether the Foxglove server may listen off loopback (it is unauthenticated).
    pub foxglove_allow_remote: bool,
    /// `--zenoh-connect`: the Zenoh endpoint every cell joins ROS 2 through, in place of
    /// its `[ros2] zenoh_connect` (docs/ros2.md).
    pub zenoh_connect: Option<String>,
    /// The CPUs the shared executor's threads keep to, one each (`[serve] pin_executor`:
    /// [`crate::daemon::config::ServeConfig::executor_cpus`]); empty leaves them unpinned.
    /// Keeping the process's other threads off them is the caller's part, done before it
    /// starts its runtime (`rigbridge serve` does), since a thread inherits where it may run
    /// from the thread that starts it.
    pub executor_cpus: Vec<usize>,
}

/// See [`ServeOptions::before_job`].
pub type BeforeJob = Arc<dyn Fn(&str, u64) + Send + Sync>;

// A job's panic is contained by unwinding its thread (`cell::contain_panic`); with
// `panic = "abort"` one job's bug would kill every cell.
#[cfg(not(panic = "unwind"))]
compile_error!(
    "rigbridge's daemon needs panic = \"unwind\": it contains a job's panic to that job"
);

/// Never prints the token itself.
impl std::fmt::Debug for ServeOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServeOptions")
            .field("runs_dir", &self.runs_dir)
            .field("virtual_clock", &self.virtual_clock)
            .field("token", &self.token.as_ref().map(|_| "<redacted>"))
            .field("allowed_hosts", &self.allowed_hosts)
            .field("before_job", &self.before_job.as_ref().map(|_| "<hook>"))
            .field("foxglove_port", &self.foxglove_port)
            .field("foxglove_allow_remote", &self.foxglove_allow_remote)
            .field("zenoh_connect", &self.zenoh_connect)
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
            form_urlencoded::parse(query.as_bytes())
                .any(|(key, value)| key == "token" && constant_time_eq(value.as_bytes(), expected))
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
    if guard::origin_allowed(request.headers(), &[]) {
        next.run(request).await
    } else {
        error(
            StatusCode::FORBIDDEN,
            "cross-origin request refused: control requests must come from this server's own page",
        )
    }
}

/// What every request handler shares: the cells, in the order of their files (the first
/// answers the routes without a cell name), and the daemon's options.
struct Daemon {
    cells: Vec<Arc<Cell>>,
    options: ServeOptions,
    /// Job numbers, daemon-wide: each job's log is `job-<id>.mcap` in the runs directory,
    /// whichever cell ran it.
    next_id: AtomicU64,
    /// Turns true when the server stops: live connections close.
    stopping: watch::Receiver<bool>,
    /// Open live pages, at most [`MAX_LIVE_PAGES`].
    live_pages: Arc<tokio::sync::Semaphore>,
    /// What the live Foxglove server publishes (fed even when it is off: cheap without
    /// clients).
    foxglove: foxglove::FoxgloveFeed,
}

impl Daemon {
    fn cell(&self, name: &str) -> Option<&Arc<Cell>> {
        self.cells.iter().find(|cell| cell.name() == name)
    }

    /// The next job number whose log name is free: numbering starts past the logs already
    /// in the runs directory, and skips any that appeared since (another daemon there).
    fn next_job_id(&self) -> u64 {
        loop {
            let id = self.next_id.fetch_add(1, Ordering::Relaxed);
            if !self.options.runs_dir.join(cell::job_log_name(id)).exists() {
                return id;
            }
        }
    }
}

/// The cell a request is about: the `{cell}` of `/api/cells/{cell}/...`, or the first cell
/// for the routes without one (`/api/jobs`, `/api/status`, ...). An unknown name is 404.
struct CellRef(Arc<Cell>);

impl FromRequestParts<Arc<Daemon>> for CellRef {
    type Rejection = Response;

    async fn from_request_parts(
        parts: &mut Parts,
        daemon: &Arc<Daemon>,
    ) -> Result<Self, Self::Rejection> {
        let params = RawPathParams::from_request_parts(parts, daemon)
            .await
            .map_err(IntoResponse::into_response)?;
        let Some((_, name)) = params.iter().find(|(key, _)| *key == "cell") else {
            return Ok(CellRef(daemon.cells[0].clone()));
        };
        match daemon.cell(name) {
            Some(cell) => Ok(CellRef(cell.clone())),
            None => {
                let known: Vec<&str> = daemon.cells.iter().map(|c| c.name()).collect();
                Err(error(
                    StatusCode::NOT_FOUND,
                    format!("no cell named `{name}`: this daemon runs {known:?}"),
                ))
            }
        }
    }
}

/// The only body `POST .../jobs` takes besides an empty one (the cell's configured job):
/// one of `job` and `toml`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct JobRequest {
    /// A job like config's `[job]`.
    job: Option<JobConfig>,
    /// The same job as TOML text (the live page's pasted job): a run settings file's `[job]`
    /// table, or its keys alone.
    toml: Option<String>,
}

fn error(status: StatusCode, message: impl std::fmt::Display) -> Response {
    (
        status,
        Json(serde_json::json!({ "error": message.to_string() })),
    )
        .into_response()
}

/// Serves the control API for `cells` (one per run settings file, checked with
/// [`check_cells`]) on `listener` until `shutdown` completes; then stops every job
/// (decelerating along its path) and waits for them. Refuses a listener that is not on a
/// loopback address unless `options.token` is set.
pub async fn run(
    listener: tokio::net::TcpListener,
    cells: Vec<RunSettings>,
    options: ServeOptions,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServeError> {
    check_cells(&cells)?;
    Ok(serve_cells(listener, cells, options, shutdown).await?)
}

/// Why `rigbridge serve` stopped or never started: its cells clash, or the daemon refused.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(transparent)]
    Cells(#[from] CellError),
    #[error(transparent)]
    Daemon(#[from] DaemonError),
}

/// [`run`] once the cells are known not to clash.
async fn serve_cells(
    listener: tokio::net::TcpListener,
    cells: Vec<RunSettings>,
    options: ServeOptions,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), DaemonError> {
    let local = listener.local_addr().map_err(crate::link::LinkError::Io)?;
    let exposed = refuse_unguarded(local, &options)?;
    let foxglove_listener = bind_foxglove(local.ip(), &options)?;
    let robots = cells
        .iter()
        .map(crate::daemon::robot_description)
        .collect::<Result<Vec<_>, _>>()?;
    let cells = start_cells(cells, &options)?;
    let (stop_live, stopping) = watch::channel(false);
    let first_id = cell::first_job_id(&options.runs_dir);
    let hosts = HostCheck::new(local, &options.allowed_hosts);
    let daemon = Arc::new(Daemon {
        foxglove: foxglove_feed(&cells, robots),
        cells,
        options,
        next_id: AtomicU64::new(first_id),
        stopping: stopping.clone(),
        live_pages: Arc::new(tokio::sync::Semaphore::new(MAX_LIVE_PAGES)),
    });
    let app = routes(&daemon, exposed)
        .layer(axum::middleware::from_fn_with_state(
            hosts.clone(),
            guard::require_known_host,
        ))
        .layer(axum::extract::DefaultBodyLimit::max(MAX_BODY_BYTES))
        .with_state(daemon.clone());
    let ros2 = start_ros2(&daemon).await?;
    let frames = tokio::spawn(send_frames(daemon.clone()));
    let foxglove = foxglove_listener.map(|listener| {
        let serve = foxglove::serve(listener, daemon.clone(), hosts.clone(), stopping.clone());
        tokio::spawn(serve)
    });
    tokio::spawn(async move {
        shutdown.await;
        let _ = stop_live.send(true);
    });
    connections::serve(listener, app, connection_cap(), stopping).await;
    frames.abort();
    if let Some(foxglove) = foxglove {
        let _ = foxglove.await;
    }
    stop_cells(daemon, ros2).await;
    Ok(())
}

/// Whether `local` is off loopback (exposed); refused there without a token.
fn refuse_unguarded(
    local: std::net::SocketAddr,
    options: &ServeOptions,
) -> Result<bool, DaemonError> {
    let exposed = !local.ip().is_loopback();
    if exposed && options.token.is_none() {
        return Err(DaemonError::Unavailable(format!(
            "refusing to serve on {local} without a token: a non-loopback address needs \
             RIGBRIDGE_TOKEN or [serve] token"
        )));
    }
    Ok(exposed)
}

/// A cell for each settings file, on the shared executor when one is asked for, each with
/// its control journal open in the runs directory.
fn start_cells(
    cells: Vec<RunSettings>,
    options: &ServeOptions,
) -> Result<Vec<Arc<Cell>>, DaemonError> {
    std::fs::create_dir_all(&options.runs_dir).map_err(crate::link::LinkError::Io)?;
    let executor = shared_executor(&cells[0], options)?;
    let cells = cells
        .into_iter()
        .map(|settings| Cell::new(settings, executor.clone()).map(Arc::new))
        .collect::<Result<Vec<_>, _>>()?;
    for cell in &cells {
        let journal = cell.open_journal(&options.runs_dir)?;
        tracing::info!(
            cell = %cell.name(),
            "cell {}: control actions logged to {}",
            cell.name(),
            journal.display()
        );
    }
    Ok(cells)
}

/// What the live Foxglove server publishes of `cells`, with their robot descriptions.
fn foxglove_feed(
    cells: &[Arc<Cell>],
    robots: Vec<Option<Arc<crate::log::RobotDescription>>>,
) -> foxglove::FoxgloveFeed {
    let feed_cells: Vec<_> = cells
        .iter()
        .zip(robots)
        .map(|(cell, robot)| foxglove::FeedCell {
            name: cell.name(),
            rig: &cell.settings().rig,
            robot,
            program: !cell.settings().cell.parts.is_empty(),
        })
        .collect();
    foxglove::FoxgloveFeed::new(&feed_cells)
}

/// The cells' ROS 2 nodes, started off the async threads (they connect to Zenoh).
async fn start_ros2(daemon: &Arc<Daemon>) -> Result<Vec<crate::ros2::RigNode>, DaemonError> {
    let daemon = daemon.clone();
    tokio::task::spawn_blocking(move || ros2_nodes(&daemon))
        .await
        .map_err(|e| DaemonError::Unavailable(format!("starting the ROS 2 nodes: {e}")))?
}

/// Takes the cells out of the ROS 2 graph, stops every job and closes the journals.
async fn stop_cells(daemon: Arc<Daemon>, ros2: Vec<crate::ros2::RigNode>) {
    let _ = tokio::task::spawn_blocking(move || {
        // Out of the graph first: no trajectory starts a job while the cells stop.
        drop(ros2);
        for cell in &daemon.cells {
            cell.stop_and_wait();
            cell.close_journal();
        }
    })
    .await;
}

/// The live Foxglove server's listener on the API's address, unless `foxglove_port` is 0;
/// refused off loopback without `foxglove_allow_remote` (it is unauthenticated).
fn bind_foxglove(
    ip: std::net::IpAddr,
    options: &ServeOptions,
) -> Result<Option<tokio::net::TcpListener>, DaemonError> {
    let port = options.foxglove_port;
    if port == 0 {
        return Ok(None);
    }
    if let Some(problem) =
        crate::daemon::config::foxglove_bind_problem(ip, port, options.foxglove_allow_remote)
    {
        return Err(DaemonError::Unavailable(format!(
            "refusing to serve: {problem}"
        )));
    }
    let address = std::net::SocketAddr::new(ip, port);
    let listener = bind(address).map_err(|e| {
        DaemonError::Unavailable(format!(
            "cannot listen for Foxglove on {address}: {e}; choose another [serve] \
             foxglove_port (--foxglove-port), or 0 to turn it off"
        ))
    })?;
    tracing::info!("foxglove: ws://{address} ({FOXGLOVE_SUBPROTOCOL}, read-only)");
    Ok(Some(listener))
}

/// The executor the first file's `[serve] executor` asks for: `None` for a thread per
/// cell, and under a virtual clock (its cycles do not wait, so nothing needs sharing).
fn shared_executor(
    first: &RunSettings,
    options: &ServeOptions,
) -> Result<Option<Arc<Executor>>, DaemonError> {
    let serve = &first.config.serve;
    if options.virtual_clock || serve.executor != ExecutorKind::Shared {
        return Ok(None);
    }
    let settings = ExecutorSettings {
        threads: serve.executor_threads,
        cpus: options.executor_cpus.clone(),
        ..ExecutorSettings::default()
    };
    let executor = Executor::new(settings).map_err(crate::link::LinkError::Io)?;
    let realtime = executor.realtime_threads();
    if realtime < executor.threads() {
        tracing::warn!(
            "note: the shared executor streams at normal priority on {} of its {} threads \
             (SCHED_FIFO needs root or CAP_SYS_NICE)",
            executor.threads() - realtime,
            executor.threads()
        );
    }
    Ok(Some(Arc::new(executor)))
}

/// The ROS 2 node of every cell whose settings have `[ros2]` (or with `--zenoh-connect`):
/// its joint states from the cell's live slot, its trajectories as jobs, and over DDS its
/// FollowJointTrajectory goals.
fn ros2_nodes(daemon: &Arc<Daemon>) -> Result<Vec<crate::ros2::RigNode>, DaemonError> {
    let mut nodes = Vec::new();
    for cell in &daemon.cells {
        let settings = cell.settings();
        let endpoint = daemon.options.zenoh_connect.as_deref();
        let Some(ros2) = settings.config.ros2.settings(endpoint) else {
            continue;
        };
        // Off: no subscription at all, so nothing any peer sends can reach a job.
        let handler = ros2.accept_motion.then(|| {
            let (daemon, cell) = (daemon.clone(), cell.clone());
            let mut refusals = ros2::Refusals::new(Box::new(crate::clock::WallClock::new()));
            let servo = servo::zenoh_handler(daemon.clone(), cell.clone());
            crate::ros2::Motion {
                trajectories: Box::new(move |message| {
                    take_trajectory(&daemon, &cell, &mut refusals, message)
                }),
                servo,
            }
        });
        // Over DDS, the FollowJointTrajectory action too, under the same consent.
        let dds = matches!(ros2.middleware, crate::ros2::Middleware::Dds { .. });
        let goals = (ros2.accept_motion && dds).then(|| {
            let server = crate::ros2::fjt::ServerSettings {
                joints: settings.rig.joint_names().map(String::from).collect(),
                tolerances: ros2.tolerances,
                max_points: settings.config.limits.max_job_points,
            };
            let runner = fjt::CellGoals::new(daemon.clone(), cell.clone());
            crate::ros2::fjt::Goals::new(server, Box::new(runner))
        });
        // Zenoh's and RustDDS's own runtimes must not be entered from the server's: a
        // thread of its own.
        let rig = crate::ros2::PublishedRig {
            name: cell.name().to_string(),
            joints: settings.rig.joint_names().map(String::from).collect(),
            robot: Arc::new(crate::log::RobotDescription::generated(
                &settings.rig,
                &settings.cell,
            )),
            mount: settings.cell.mount,
        };
        let (slot, known) = (cell.hub().slot().clone(), cell.streams_to_twin());
        let middleware = ros2.middleware.to_string();
        let motion = motion_from_ros2(&ros2);
        let motion_unauthenticated = ros2.accept_motion && ros2.login.is_none();
        let node = std::thread::spawn(move || {
            crate::ros2::start_node(&ros2, rig, slot, known, handler, goals)
        })
        .join()
        .map_err(|_| DaemonError::Unavailable("the ROS 2 node's start panicked".into()))?
        .map_err(|e| {
            DaemonError::Unavailable(format!("cell {}: ROS 2: {}", cell.name(), error_chain(&e)))
        })?;
        tracing::info!(
            cell = %cell.name(),
            "cell {}: ROS 2 node /{}/{} on {} (joint states on {})",
            cell.name(),
            cell.name(),
            crate::ros2::graph::NODE_NAME,
            middleware,
            node.joint_states_at(cell.name())
        );
        if motion_unauthenticated {
            tracing::warn!(cell = %cell.name(), "cell {}: ROS 2: {motion}", cell.name());
        }
        cell.log_ros2("ros2_motion", None, motion.to_string());
        nodes.push(node);
    }
    Ok(nodes)
}

/// Whether and how a cell takes motion from ROS 2, as its status and journal say it.
fn motion_from_ros2(ros2: &crate::ros2::Ros2Settings) -> &'static str {
    let dds = matches!(ros2.middleware, crate::ros2::Middleware::Dds { .. });
    match (ros2.accept_motion, &ros2.login) {
        (false, _) if dds => {
            "off: JointTrajectory is not subscribed to and FollowJointTrajectory is not \
             served ([ros2] accept_motion = false); joint states are published"
        }
        (true, _) if dds => {
            "on WITHOUT AUTHENTICATION over DDS ([ros2] allow_unauthenticated_motion): \
             JointTrajectory and FollowJointTrajectory goals from anyone on the DDS \
             discovery range move the arm"
        }
        (false, _) => {
            "off: JointTrajectory is not subscribed to ([ros2] accept_motion = false); \
             joint states are published"
        }
        (true, Some(_)) => {
            "on: JointTrajectory taken as jobs, from a Zenoh session logged in with \
             [ros2] user and password_file"
        }
        (true, None) => {
            "on WITHOUT AUTHENTICATION ([ros2] allow_unauthenticated_motion): anyone who \
             reaches the Zenoh network can move the arm"
        }
    }
}

/// A JointTrajectory received for `cell`: a job like any other, or a refusal counted in
/// `refusals` and logged with its reason (on stderr, in the cell's events and journal) at
/// most once an interval.
fn take_trajectory(
    daemon: &Daemon,
    cell: &Arc<Cell>,
    refusals: &mut ros2::Refusals,
    message: Result<crate::ros2::messages::JointTrajectory, crate::ros2::messages::CdrError>,
) {
    const REFUSED: &str = cell::ROS2_REFUSED;
    // Counted always, logged at most once an interval (a flood of bad messages).
    let mut refuse = |job: Option<u64>, reason: String| {
        if let Some(text) = refusals.refuse(&reason) {
            cell.log_ros2(REFUSED, job, text);
        }
    };
    let job = message
        .map_err(|e| error_chain(&e))
        .and_then(|message| {
            ros2::trajectory_job(&message, &cell.settings().rig).map_err(|e| e.to_string())
        })
        .and_then(|job| cell.validate(job).map_err(|e| e.to_string()));
    let job = match job {
        Ok(job) => job,
        Err(reason) => return refuse(None, reason),
    };
    let id = daemon.next_job_id();
    let started = match cell.start(id, job, &daemon.options) {
        Ok(started) => started,
        Err(refused) => return refuse(None, start_refusal(cell, refused)),
    };
    match started.planned.blocking_recv() {
        Ok(Ok(())) => cell.log_ros2("ros2_trajectory_started", Some(id), "streaming".into()),
        Ok(Err(message)) => {
            cell.reap(id);
            refuse(Some(id), message.to_string());
        }
        Err(_) => refuse(Some(id), "the job thread ended before planning".into()),
    }
}

/// Every route, each cell's under `/api/cells/{cell}/` and the first cell's also without
/// the prefix, with the access checks ([`require_token`], [`require_live_token`],
/// [`require_same_origin`]) layered once per group.
fn routes(daemon: &Arc<Daemon>, exposed: bool) -> Router<Arc<Daemon>> {
    let check = TokenCheck::new(daemon.options.token.as_deref());
    let auth = axum::middleware::from_fn_with_state(check.clone(), require_token);
    let live_auth = axum::middleware::from_fn_with_state(check, require_live_token);
    let same_origin = axum::middleware::from_fn(require_same_origin);
    // Everything that moves a rig goes here: always behind the check.
    let mut control = Router::new();
    for prefix in ["/api", "/api/cells/{cell}"] {
        control = control
            .route(&format!("{prefix}/jobs"), post(submit))
            .route(&format!("{prefix}/pause"), post(pause))
            .route(&format!("{prefix}/resume"), post(resume))
            .route(&format!("{prefix}/stop"), post(stop))
            .route(&format!("{prefix}/estop"), post(estop))
            .route(&format!("{prefix}/reset"), post(reset))
            .route(&format!("{prefix}/speed"), post(online::speed))
            .route(&format!("{prefix}/jog"), post(online::jog))
            .route(&format!("{prefix}/goal"), post(online::goal));
    }
    let control = control
        .route_layer(axum::middleware::from_fn(guard::require_json))
        .route_layer(auth.clone())
        .route_layer(same_origin.clone());
    // A rig's state, live, and the servo stream that moves it: as guarded as control (a
    // browser cannot send the header on a WebSocket; the token may come in the query).
    let live = Router::new()
        .route("/api/live", get(live))
        .route("/api/cells/{cell}/live", get(live))
        .route("/api/servo", get(servo::servo))
        .route("/api/cells/{cell}/servo", get(servo::servo))
        .route_layer(live_auth)
        .route_layer(same_origin);
    // Reading a cell's state moves nothing. `GET .../jobs` shares its path with `POST`
    // above: axum merges the two, each method behind its own group's checks.
    let mut status = Router::new()
        .route("/api/cells", get(list_cells))
        .route("/api/schema", get(schema));
    for prefix in ["/api", "/api/cells/{cell}"] {
        status = status
            .route(&format!("{prefix}/status"), get(status_of))
            .route(&format!("{prefix}/jobs"), get(list_jobs))
            .route(&format!("{prefix}/jobs/{{id}}"), get(job));
    }
    // Off loopback the rigs' state is sensitive too.
    let status = if exposed {
        status.route_layer(auth)
    } else {
        status
    };
    let assets = Router::new()
        .route("/", get(index))
        .route("/live.js", get(live_js))
        .route("/live.css", get(live_css));
    assets.merge(status).merge(control).merge(live)
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

/// The twin's world for the job at hand, swapped when a job starts.
struct JobWorld(Option<Box<dyn TwinWorld>>);

impl TwinWorld for JobWorld {
    fn observe(&mut self, actual: &[f64]) {
        if let Some(world) = self.0.as_mut() {
            world.observe(actual);
        }
    }
}

/// The live view's frame task: samples every cell's streamer state at
/// [`LIVE_FRAME_RATE_HZ`] in real time (whatever clock jobs run on: a person watches it) and
/// sends each cell's pages its frame, and the Foxglove clients the same state.
async fn send_frames(daemon: Arc<Daemon>) {
    let clock = WallClock::new();
    let mut ticks = tokio::time::interval(Duration::from_secs_f64(1.0 / LIVE_FRAME_RATE_HZ));
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut reported = vec![false; daemon.cells.len()];
    loop {
        ticks.tick().await;
        for (index, (cell, reported)) in daemon.cells.iter().zip(&mut reported).enumerate() {
            // One cell's broken scene must not freeze every cell's view.
            let tick = || {
                cell.hub().tick(clock.now(), cell.job_view());
                daemon.foxglove.publish(index, cell.hub());
            };
            if std::panic::catch_unwind(std::panic::AssertUnwindSafe(tick)).is_err()
                && !std::mem::replace(reported, true)
            {
                tracing::error!(
                    cell = %cell.name(),
                    "cell {}: its live view failed; other cells go on",
                    cell.name()
                );
            }
        }
    }
}

async fn live(
    State(daemon): State<Arc<Daemon>>,
    CellRef(cell): CellRef,
    upgrade: WebSocketUpgrade,
) -> Response {
    let Ok(page) = daemon.live_pages.clone().try_acquire_owned() else {
        return error(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("{MAX_LIVE_PAGES} live pages are open already: close one"),
        );
    };
    let stopping = daemon.stopping.clone();
    // A page sends nothing but a close: a small message cap bounds what a client can make
    // the server buffer.
    upgrade
        .max_message_size(MAX_LIVE_MESSAGE_BYTES)
        .max_frame_size(MAX_LIVE_MESSAGE_BYTES)
        .protocols([LIVE_PROTOCOL])
        .on_upgrade(move |socket| async move {
            serve_live(socket, cell, stopping).await;
            drop(page);
        })
}

/// One page: the cell's scene, then every frame until the page goes or the server stops. A
/// page that falls behind skips to the present and gets the scene again (paint included).
async fn serve_live(mut socket: WebSocket, cell: Arc<Cell>, mut stopping: watch::Receiver<bool>) {
    let (scene, mut frames) = cell.hub().subscribe();
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
                    Err(broadcast::error::RecvError::Lagged(_)) => cell.hub().scene_now(),
                    Err(broadcast::error::RecvError::Closed) => return,
                };
                if socket.send(WsMessage::Text((&*text).into())).await.is_err() {
                    return;
                }
            }
            incoming = socket.recv() => match incoming {
                Some(Err(e)) if is_too_big(&e) => {
                    let close = CloseFrame {
                        code: CLOSE_MESSAGE_TOO_BIG,
                        reason: format!(
                            "a message to the live view is at most {MAX_LIVE_MESSAGE_BYTES} bytes"
                        )
                        .into(),
                    };
                    let _ = socket.send(WsMessage::Close(Some(close))).await;
                    return;
                }
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

/// RFC 6455 7.4.1: "1009 indicates that an endpoint is terminating the connection because
/// it has received a message that is too big for it to process".
const CLOSE_MESSAGE_TOO_BIG: u16 = 1009;

/// Whether a WebSocket read failed on [`MAX_LIVE_MESSAGE_BYTES`] (a frame, or the frames
/// of an unfinished message together).
fn is_too_big(error: &axum::Error) -> bool {
    std::error::Error::source(error)
        .and_then(|inner| inner.downcast_ref::<tungstenite::Error>())
        .is_some_and(|e| matches!(e, tungstenite::Error::Capacity(_)))
}

async fn list_cells(State(daemon): State<Arc<Daemon>>) -> Response {
    let cells: Vec<_> = daemon.cells.iter().map(|cell| cell.summary()).collect();
    Json(serde_json::json!({ "cells": cells })).into_response()
}

async fn status_of(CellRef(cell): CellRef) -> Response {
    Json(cell.status()).into_response()
}

/// The longest `wait_s` of `GET .../jobs/{id}`: half of nginx's default
/// `proxy_read_timeout` of 60 s (<https://nginx.org/en/docs/http/ngx_http_proxy_module.html#proxy_read_timeout>),
/// so a wait behind a reverse proxy left at its defaults is answered before the proxy gives
/// up on it.
pub const MAX_JOB_WAIT_S: f64 = 30.0;

/// `GET .../jobs`: the cell's remembered jobs (at most [`cell::KEPT_JOBS`]), newest first.
async fn list_jobs(CellRef(cell): CellRef) -> Response {
    let jobs = match settled(&cell, |cell| cell.jobs()).await {
        Ok(Ok(jobs)) => jobs,
        Ok(Err(e)) => return job_unshown(&cell, e),
        Err(refusal) => return refusal,
    };
    Json(serde_json::json!({ "cell": cell.name(), "jobs": jobs })).into_response()
}

/// `GET .../jobs/{id}[?wait_s=S]`: one job of the cell, 404 naming the id when the cell
/// never ran it or forgot it. With `wait_s` the answer waits, up to S seconds (at most
/// [`MAX_JOB_WAIT_S`]), for a running job to end: a client chaining jobs learns of each
/// end as it happens, without polling. A job answered as ended has freed its cell.
async fn job(CellRef(cell): CellRef, params: RawPathParams, query: RawQuery) -> Response {
    let id = params
        .iter()
        .find(|(key, _)| *key == "id")
        .map_or("", |(_, id)| id);
    let Ok(number) = id.parse::<u64>() else {
        return error(
            StatusCode::NOT_FOUND,
            format!(
                "no job `{}` in cell `{}`: a job's id is the number `POST .../jobs` answered",
                guard::shorten(id),
                cell.name()
            ),
        );
    };
    let wait = match wait_of(query.0.as_deref()) {
        Ok(wait) => wait,
        Err(refused) => return error(StatusCode::BAD_REQUEST, refused),
    };
    // Subscribed before the first look: an end between the look and the wait still wakes.
    let mut ends = cell.job_ends();
    let deadline = clock::real().now() + wait;
    loop {
        let entry = match settled(&cell, move |cell| cell.job_entry(number)).await {
            Ok(entry) => entry,
            Err(refusal) => return refusal,
        };
        let entry = match entry {
            None => {
                return error(
                    StatusCode::NOT_FOUND,
                    format!(
                        "no job {number} in cell `{}`: it never ran there, or it is older than \
                         the {} jobs a cell remembers",
                        cell.name(),
                        cell::KEPT_JOBS
                    ),
                );
            }
            Some(Err(e)) => return job_unshown(&cell, e),
            Some(Ok(entry)) => entry,
        };
        if !entry.running {
            return Json(entry.json).into_response();
        }
        let left = deadline.saturating_sub(clock::real().now());
        match tokio::time::timeout(left, ends.changed()).await {
            Ok(Ok(())) => {}
            // The wait is over (or the cell is gone): the job as it stands.
            Ok(Err(_)) | Err(_) => return Json(entry.json).into_response(),
        }
    }
}

/// `what` of `cell`, asked once the cell's slot is free of a job whose end is recorded
/// ([`Cell::settle`]: a join, so off the async threads).
async fn settled<T: Send + 'static>(
    cell: &Arc<Cell>,
    what: impl FnOnce(&Cell) -> T + Send + 'static,
) -> Result<T, Response> {
    let cell = cell.clone();
    tokio::task::spawn_blocking(move || {
        cell.settle();
        what(&cell)
    })
    .await
    .map_err(|_| {
        error(
            StatusCode::INTERNAL_SERVER_ERROR,
            "reading the cell's jobs failed unexpectedly",
        )
    })
}

/// A job record that would not turn into JSON.
fn job_unshown(cell: &Cell, e: serde_json::Error) -> Response {
    error(
        StatusCode::INTERNAL_SERVER_ERROR,
        format!("cannot show the jobs of cell `{}`: {e}", cell.name()),
    )
}

/// Why a job lookup's query is refused: the parameter or the value, shortened.
#[derive(Debug, thiserror::Error)]
enum WaitRefused {
    #[error("unknown query parameter `{0}`: a job lookup takes only `wait_s`")]
    UnknownParameter(String),
    #[error("wait_s = `{0}` is not a number of seconds in 0..={MAX_JOB_WAIT_S}")]
    BadSeconds(String),
}

/// The wait a job lookup's query asks for: `wait_s`, seconds in 0..=[`MAX_JOB_WAIT_S`];
/// none without it. Anything else in the query is refused, naming it.
fn wait_of(query: Option<&str>) -> Result<Duration, WaitRefused> {
    let mut wait = Duration::ZERO;
    for (key, value) in form_urlencoded::parse(query.unwrap_or("").as_bytes()) {
        if key != "wait_s" {
            return Err(WaitRefused::UnknownParameter(guard::shorten(&key)));
        }
        wait = value
            .parse::<f64>()
            .ok()
            .filter(|s| (0.0..=MAX_JOB_WAIT_S).contains(s))
            .map(Duration::from_secs_f64)
            .ok_or_else(|| WaitRefused::BadSeconds(guard::shorten(&value)))?;
    }
    Ok(wait)
}

/// `GET /api/schema`: the JSON Schema of `POST .../jobs`'s body.
async fn schema() -> Response {
    Json(crate::job::request_schema()).into_response()
}

async fn submit(
    State(daemon): State<Arc<Daemon>>,
    CellRef(cell): CellRef,
    request: Request,
) -> Response {
    let body = match guard::read_body(request).await {
        Ok(body) => body,
        Err(refused) => return refused,
    };
    let job = if body.is_empty() {
        cell.configured_job()
    } else {
        let parsed = serde_json::from_slice(&body)
            .map_err(|e| guard::shorten(&e.to_string()))
            .and_then(|request| requested_job(request).map_err(|e| e.to_string()));
        let job = match parsed {
            Ok(job) => job,
            Err(why) => {
                let reason = format!(
                    "job request is not valid: {why}; send {{\"job\": {{\"kind\": ...}}}} \
                     or {{\"toml\": \"[job] ...\"}} (GET /api/schema) or an empty body for \
                     the cell's job"
                );
                cell.log_refusal(cell::JOB_REFUSED, None, reason.clone());
                return error(StatusCode::BAD_REQUEST, reason);
            }
        };
        match cell.validate(job) {
            Ok(job) => job,
            Err(refused) => {
                cell.log_refusal(cell::JOB_REFUSED, None, refused.to_string());
                return error(StatusCode::UNPROCESSABLE_ENTITY, refused);
            }
        }
    };
    let id = daemon.next_job_id();
    let started = match cell.start(id, job, &daemon.options) {
        Ok(started) => started,
        Err(refused) => return start_refused(&cell, refused),
    };
    match started.planned.await {
        Ok(Ok(())) => (
            StatusCode::ACCEPTED,
            Json(serde_json::json!({
                "id": started.id,
                "job": started.name,
                "cell": cell.name(),
            })),
        )
            .into_response(),
        Ok(Err(message)) => {
            // The refused job's thread is ending: once the refusal is answered the cell must
            // take the next job, not answer "busy".
            let id = started.id;
            let logged = cell.clone();
            let _ = tokio::task::spawn_blocking(move || cell.reap(id)).await;
            logged.log_refusal(cell::JOB_REFUSED, Some(id), message.to_string());
            error(StatusCode::UNPROCESSABLE_ENTITY, message)
        }
        Err(_) => error(
            StatusCode::INTERNAL_SERVER_ERROR,
            "the job thread ended before planning",
        ),
    }
}

/// Why a job request's body names no job.
#[derive(Debug, thiserror::Error)]
enum RequestedJobError {
    /// Its TOML, with the line and column of the error.
    #[error(transparent)]
    Pasted(#[from] crate::job::PastedJobError),
    #[error("both `job` and `toml` given: send one")]
    Both,
    #[error("neither `job` nor `toml` given")]
    Neither,
}

/// The job of a request: its `job`, or its `toml` parsed (one of the two).
fn requested_job(request: JobRequest) -> Result<JobConfig, RequestedJobError> {
    match (request.job, request.toml) {
        (Some(job), None) => Ok(job),
        (None, Some(text)) => Ok(crate::job::job_from_toml(&text)?),
        (Some(_), Some(_)) => Err(RequestedJobError::Both),
        (None, None) => Err(RequestedJobError::Neither),
    }
}

/// The answer to a job the cell would not start.
fn start_refused(cell: &Cell, refused: StartRefused) -> Response {
    let status = match refused {
        StartRefused::Poisoned => StatusCode::INTERNAL_SERVER_ERROR,
        StartRefused::Spawn(_) => StatusCode::SERVICE_UNAVAILABLE,
        StartRefused::Busy | StartRefused::Faulted(_) => StatusCode::CONFLICT,
    };
    error(status, start_refusal(cell, refused))
}

/// Why the cell did not start a job, in words.
fn start_refusal(cell: &Cell, refused: StartRefused) -> String {
    match refused {
        StartRefused::Busy => format!(
            "a job is already running in cell `{}`: stop it or wait",
            cell.name()
        ),
        StartRefused::Poisoned => "state lock poisoned".to_string(),
        StartRefused::Spawn(e) => format!(
            "cell `{}` cannot start the job's thread ({e}): try again later",
            cell.name()
        ),
        StartRefused::Faulted(fault) => format!(
            "the controller of cell `{0}` has a latched fault ({fault}): reset it first \
             (POST /api/cells/{0}/reset) once its cause is gone",
            cell.name()
        ),
    }
}

fn with_control(cell: &Cell, what: &'static str, act: impl Fn(&StreamControl)) -> Response {
    match cell.control(what, act) {
        Some(id) => Json(serde_json::json!({ "id": id })).into_response(),
        None => error(StatusCode::CONFLICT, "no job is running"),
    }
}

async fn pause(CellRef(cell): CellRef) -> Response {
    with_control(&cell, "pause", StreamControl::pause)
}

async fn resume(CellRef(cell): CellRef) -> Response {
    with_control(&cell, "resume", StreamControl::resume)
}

/// A stop or e-stop: 200 with the job's number and the phase it was in when the request
/// was acknowledged (`planning`, `waiting_for_controller`, `waiting_for_hold`, `resuming`,
/// `streaming`); from then on nothing that moves the arm is sent but a braking ramp when it
/// was moving.
fn with_halt(
    cell: &Cell,
    what: &'static str,
    request: impl Fn(&StreamControl) -> crate::stream::Phase,
) -> Response {
    match cell.halt(what, request) {
        Some((id, phase)) => Json(serde_json::json!({ "id": id, "phase": phase })).into_response(),
        None => error(StatusCode::CONFLICT, "no job is running"),
    }
}

async fn stop(CellRef(cell): CellRef) -> Response {
    with_halt(&cell, "stop", StreamControl::request_stop)
}

async fn estop(CellRef(cell): CellRef) -> Response {
    with_halt(&cell, "estop", StreamControl::request_estop)
}

/// `POST .../reset`: asks the cell's controller to clear its latched fault (docs/protocol.md
/// 6.7), when no job runs. 200 with the controller's state once it reports none; 409 when
/// a job runs or the controller keeps its fault (its words); 503 when it cannot be asked.
async fn reset(CellRef(cell): CellRef) -> Response {
    let name = cell.name().to_string();
    let outcome = match tokio::task::spawn_blocking(move || cell.reset()).await {
        Ok(outcome) => outcome,
        Err(_) => {
            return error(
                StatusCode::INTERNAL_SERVER_ERROR,
                "the reset failed unexpectedly",
            );
        }
    };
    match outcome {
        Ok(outcome) if outcome.is_clear() => {
            let result = match outcome {
                crate::daemon::reset::ResetOutcome::Cleared { .. } => "cleared",
                _ => "nothing_latched",
            };
            Json(serde_json::json!({ "result": result, "message": outcome.to_string() }))
                .into_response()
        }
        Ok(kept) => error(StatusCode::CONFLICT, kept),
        Err(ResetRefused::Busy) => error(
            StatusCode::CONFLICT,
            format!("a job is running in cell `{name}`: stop it before a reset"),
        ),
        Err(ResetRefused::Failed(why)) => error(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("cannot reset the controller of cell `{name}`: {why}"),
        ),
    }
}
