//! The live Foxglove server (`docs/foxglove.md`): Foxglove's WebSocket protocol, subprotocol
//! `foxglove.websocket.v1` (<https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md>),
//! on its own listener and read-only. Per cell it advertises `/tf`, `/joint_states` and
//! `/scene` (prefixed `/<cell>` when the daemon runs several), fed by the live view's frame
//! task from each cell's hub, never by the streaming cycle, and it serves each cell's URDF
//! through `fetchAsset` as `package://rigbridge/<cell>.urdf`. Like the HTTP API it refuses a
//! `Host` it does not answer to and a browser page of another site (`Origin`: only the
//! Foxglove app's own origins, [`FOXGLOVE_APP_ORIGINS`], and `[serve] foxglove_origins` pass).
//! A client with no subscription is idle: closed after [`FOXGLOVE_IDLE_TIMEOUT`], and when
//! every place is taken a newcomer takes the place of the longest idle. Owns the protocol,
//! the channels, the subscriptions and the clients' places; it must not control a cell.

use super::guard::{HostCheck, origin_allowed, require_known_host, shorten};
use super::{Daemon, connections};
use crate::clock::{self, Clock};
use crate::log::{RobotDescription, RobotMessages, timestamp};
use crate::scene::SceneView;
use crate::scene::foxglove::{closest_update, full_update, paint_update};
use crate::view::{LiveHub, SceneChange, SceneCursor};
use axum::extract::ws::{CloseFrame, Message as WsMessage, WebSocket, WebSocketUpgrade};
use axum::extract::{Request, State};
use axum::http::{StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use base64::Engine;
use foxglove::Encode;
use foxglove::messages::{FrameTransforms, JointStates, SceneUpdate};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::sync::{Notify, broadcast, watch};

/// The ws-protocol version served (the Foxglove app offers it, with newer ones).
pub const FOXGLOVE_SUBPROTOCOL: &str = "foxglove.websocket.v1";
/// Where `fetchAsset` finds a cell's URDF: `package://rigbridge/<cell>.urdf`.
pub const URDF_URI_PREFIX: &str = "package://rigbridge/";
/// Largest message a client may send: a subscribe to every channel of many cells fits in
/// a few hundred bytes; anything larger closes the connection (1009).
pub const MAX_FOXGLOVE_MESSAGE_BYTES: usize = 16 * 1024;
/// Most Foxglove clients at once: each costs a socket and a place in the message backlog.
/// When all are taken, a newcomer takes the place of the client idle longest (none idle:
/// 503).
pub const MAX_FOXGLOVE_CLIENTS: usize = 16;
/// How long a client may stay with no subscription before it is closed: it receives
/// nothing, yet keeps the feed encoding every message at 50 Hz and holds a place. The
/// Foxglove app subscribes to what its panels show as soon as it has the advertisement;
/// 30 s leaves a person time to add a first panel to an empty layout. A subscribed client
/// is never idle (one that stops reading is dropped by [`SEND_TIMEOUT`]).
pub const FOXGLOVE_IDLE_TIMEOUT: Duration = Duration::from_secs(30);
/// The origins the Foxglove app's WebSocket handshakes carry (`docs/foxglove.md` cites
/// each): the web app, at `app.foxglove.dev` and formerly `studio.foxglove.dev`, and the
/// desktop app, whose pages are `file://` URLs. A client that sends no `Origin` (not a
/// browser) passes as it does on the HTTP API.
pub const FOXGLOVE_APP_ORIGINS: [&str; 3] = [
    "https://app.foxglove.dev",
    "https://studio.foxglove.dev",
    "file://",
];
/// Messages a slow client may fall behind (all channels, all cells: at 50 Hz and three
/// channels a cell, about a second for two cells) before it skips to the present; the
/// backlog is shared, so memory stays bounded whatever the clients do.
pub const FOXGLOVE_BACKLOG: usize = 256;
/// A client whose socket takes longer than this to take one message is dropped.
pub const SEND_TIMEOUT: Duration = Duration::from_secs(2);
const SERVER_NAME: &str = "rigbridge";
/// The scene is looked at every 10th tick (5 Hz at the view's 50): paint in one batch per
/// 0.2 s, and a new job's scene within 0.2 s.
const SCENE_EVERY_TICKS: u64 = 10;
/// ws-protocol's status levels and binary opcodes (spec: Status, Message Data, Fetch Asset
/// Response).
const STATUS_WARNING: u8 = 1;
const STATUS_ERROR: u8 = 2;
const OP_MESSAGE_DATA: u8 = 1;
const OP_FETCH_ASSET_RESPONSE: u8 = 4;
/// RFC 6455 7.4.1: 1009, a message too big to process.
const CLOSE_MESSAGE_TOO_BIG: u16 = 1009;
/// RFC 6455 7.4.1: 1000, a normal closure (idle, or its place given to a newcomer); the
/// reason says which.
const CLOSE_NORMAL: u16 = 1000;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    Tf,
    JointStates,
    Scene,
    Program,
}

/// `/program`'s JSON schema (a cell with parts): the program's step and the twin's parts,
/// as a live frame's `program` (docs/live-view.md, "Programs"; docs/foxglove.md).
const PROGRAM_SCHEMA: &str = r#"{"title": "rigbridge.Program", "type": "object",
 "properties": {
  "step": {"type": ["object", "null"], "description": "the step the last streamed cycle is in",
   "properties": {"index": {"type": "integer"}, "step": {"type": "string"}, "what": {"type": "string"},
    "repeat": {"type": ["string", "null"]}, "pass": {"type": ["integer", "null"]},
    "target": {"type": ["string", "null"]}, "text": {"type": "string"}}},
  "parts": {"type": "array", "description": "each part's solid pose in the rig's base frame",
   "items": {"type": "object", "properties": {"position": {"type": "array", "items": {"type": "number"}},
    "orientation": {"type": "array", "items": {"type": "number"}}}}},
  "judgement": {"type": ["object", "null"], "description": "the twin's judgement so far, as the run report's parts"}}}"#;
/// `/program` goes out when it changes, and at least this often (ticks of the frame task,
/// about a second) for a client that subscribed since.
const PROGRAM_EVERY_TICKS: u64 = 50;

/// One advertised channel.
struct Channel {
    id: u32,
    cell: usize,
    kind: Kind,
    topic: String,
    schema_name: String,
    /// The schema's `FileDescriptorSet`, base64 (the spec's encoding for protobuf); for a
    /// JSON channel, its JSON schema as text.
    schema: String,
    /// `protobuf`, or `json` for `/program`.
    encoding: &'static str,
}

/// What one cell publishes, and how far it has followed its hub's scene.
struct CellFeed {
    messages: RobotMessages,
    tf: Option<u32>,
    joints: u32,
    scene: u32,
    /// `/program`, for a cell with parts.
    program: Option<u32>,
    /// The `/program` message sent last.
    program_sent: Option<String>,
    frame_id: String,
    /// The tf frame id of each frame of the rig (its collision bodies ride on them); empty
    /// for a rig without `/tf`.
    body_frames: Vec<String>,
    cursor: SceneCursor,
    /// The scene as of its last change: its walls (paint sits in front of them), its solids
    /// and bodies (the closest pair's mark redraws two of them).
    walls: SceneView,
    /// The closest pair last marked.
    closest: Option<crate::scene::ClosestView>,
    batches: u64,
    /// Calls of [`FoxgloveFeed::publish`].
    ticks: u64,
    urdf: Option<String>,
}

/// One message for the subscribers of `channel`.
#[derive(Debug)]
struct Outgoing {
    channel: u32,
    time_ns: u64,
    payload: Vec<u8>,
}

/// The channels, each cell's state, and the broadcast every client follows.
pub struct FoxgloveFeed {
    channels: Vec<Channel>,
    cells: Vec<Mutex<CellFeed>>,
    names: Vec<String>,
    sender: broadcast::Sender<Arc<Outgoing>>,
    seats: Arc<Seats>,
}

/// Why `fetchAsset` found nothing (its text goes back to the client).
#[derive(Debug, thiserror::Error)]
enum AssetError {
    #[error("no asset {0}: this server has {URDF_URI_PREFIX}<cell>.urdf")]
    Unknown(String),
    #[error("no cell named {name}: this server runs {cells}")]
    NoCell { name: String, cells: String },
    #[error("cell {0} has no URDF (its rig is not one serial chain)")]
    NoUrdf(String),
}

/// A cell as the feed sees it: its name, rig and URDF (`None` for a rig without one serial
/// chain, the sloth: it gets no `/tf`).
pub struct FeedCell<'a> {
    pub name: &'a str,
    pub rig: &'a crate::rig::Rig,
    pub robot: Option<Arc<RobotDescription>>,
    /// Whether the cell has parts: it then publishes `/program`.
    pub program: bool,
}

impl FoxgloveFeed {
    pub fn new(cells: &[FeedCell<'_>]) -> Self {
        let prefix = |name: &str| {
            if cells.len() > 1 {
                format!("/{name}")
            } else {
                String::new()
            }
        };
        let mut channels = Vec::new();
        let mut add = |cell: usize, kind: Kind, topic: String, schema: Option<foxglove::Schema>| {
            let id = u32::try_from(channels.len() + 1).unwrap_or(u32::MAX);
            let schema =
                schema.unwrap_or_else(|| foxglove::Schema::new("", "protobuf", Vec::new()));
            let (schema_name, schema, encoding) = match kind {
                Kind::Program => (
                    "rigbridge.Program".to_owned(),
                    PROGRAM_SCHEMA.to_owned(),
                    "json",
                ),
                _ => (
                    schema.name,
                    base64::engine::general_purpose::STANDARD.encode(&schema.data),
                    "protobuf",
                ),
            };
            channels.push(Channel {
                id,
                cell,
                kind,
                topic,
                schema_name,
                schema,
                encoding,
            });
            id
        };
        let mut feeds = Vec::new();
        for (index, cell) in cells.iter().enumerate() {
            let p = prefix(cell.name);
            let tf = cell.robot.as_ref().map(|_| {
                add(
                    index,
                    Kind::Tf,
                    format!("{p}/tf"),
                    FrameTransforms::get_schema(),
                )
            });
            let joints = add(
                index,
                Kind::JointStates,
                format!("{p}/joint_states"),
                JointStates::get_schema(),
            );
            let scene = add(
                index,
                Kind::Scene,
                format!("{p}/scene"),
                SceneUpdate::get_schema(),
            );
            let program = cell
                .program
                .then(|| add(index, Kind::Program, format!("{p}/program"), None));
            let names: Vec<String> = cell.rig.joint_names().map(str::to_owned).collect();
            feeds.push(Mutex::new(CellFeed {
                messages: RobotMessages::new(cell.robot.clone(), &names),
                tf,
                joints,
                scene,
                program,
                program_sent: None,
                frame_id: cell.rig.base_frame.clone(),
                body_frames: cell
                    .robot
                    .as_ref()
                    .map(|robot| robot.rig_frames())
                    .unwrap_or_default(),
                cursor: SceneCursor::default(),
                walls: SceneView::default(),
                closest: None,
                batches: 0,
                ticks: 0,
                urdf: cell.robot.as_ref().map(|r| r.urdf().to_owned()),
            }));
        }
        let (sender, _) = broadcast::channel(FOXGLOVE_BACKLOG);
        FoxgloveFeed {
            channels,
            cells: feeds,
            names: cells.iter().map(|c| c.name.to_owned()).collect(),
            sender,
            seats: Arc::default(),
        }
    }

    /// Publishes cell `index`'s latest state from its hub: `/tf` and `/joint_states` of the
    /// actual positions in the hub's slot, and what changed in its scene. Called by the
    /// live view's frame task after the hub's tick; encodes nothing while no client is
    /// connected (the scene cursor still follows, so a client starts from the present).
    pub fn publish(&self, index: usize, hub: &LiveHub) {
        let Some(feed) = self.cells.get(index) else {
            return;
        };
        let mut feed = feed.lock().unwrap_or_else(PoisonError::into_inner);
        feed.ticks += 1;
        // Paint goes out in batches: fewer, larger scene entities for the 3D panel.
        let change = (feed.ticks % SCENE_EVERY_TICKS == 1)
            .then(|| hub.scene_since(&mut feed.cursor))
            .flatten();
        if let Some(SceneChange::New(view)) = &change {
            feed.walls.clone_from(view);
            feed.walls.paint.clear();
            // A new scene has no mark: the closest pair is marked again if it still is.
            feed.closest = None;
        }
        // The mark changes with the pair or its status only (not with every distance).
        let closest = hub.closest();
        let marked = |c: &Option<crate::scene::ClosestView>| {
            c.as_ref()
                .map(|c| (c.a.clone(), c.b.clone(), c.status.clone()))
        };
        let mark = (marked(&closest) != marked(&feed.closest)).then(|| {
            feed.closest = closest;
            closest_update(
                &feed.walls,
                feed.closest.as_ref(),
                &feed.frame_id,
                &feed.body_frames,
                timestamp(unix_ns()),
            )
        });
        if self.sender.receiver_count() == 0 {
            return;
        }
        let now = unix_ns();
        let sample = hub.slot().latest();
        let feed = &mut *feed;
        if feed.messages.fill(now, sample.actual.as_slice(), None) {
            if let (Some(channel), Some(tf)) = (feed.tf, feed.messages.tf()) {
                self.send(channel, now, tf);
            }
            self.send(feed.joints, now, feed.messages.joint_states());
        }
        let update = match change {
            Some(SceneChange::New(view)) => Some(full_update(
                &view,
                &feed.frame_id,
                &feed.body_frames,
                timestamp(now),
            )),
            Some(SceneChange::Paint(fresh)) => {
                feed.batches += 1;
                paint_update(
                    &feed.walls,
                    &fresh,
                    feed.batches,
                    &feed.frame_id,
                    timestamp(now),
                )
            }
            None => None,
        };
        if let Some(update) = update {
            self.send(feed.scene, now, &update);
        }
        if let Some(mark) = mark {
            self.send(feed.scene, now, &mark);
        }
        if let Some(channel) = feed.program {
            self.publish_program(feed, channel, hub, now);
        }
    }

    /// `/program` as JSON when it changed since the last one sent, or a second has passed.
    fn publish_program(&self, feed: &mut CellFeed, channel: u32, hub: &LiveHub, now: u64) {
        let Some(program) = hub.program_now() else {
            return;
        };
        let text = serde_json::to_string(&program).unwrap_or_default();
        let due = feed.ticks % PROGRAM_EVERY_TICKS == 1;
        if !due && feed.program_sent.as_deref() == Some(text.as_str()) {
            return;
        }
        let _ = self.sender.send(Arc::new(Outgoing {
            channel,
            time_ns: now,
            payload: text.clone().into_bytes(),
        }));
        feed.program_sent = Some(text);
        // The parts where they are now, in `/scene`.
        let states: Vec<&str> = program
            .judgement
            .as_ref()
            .map(|j| j.per_part.iter().map(|p| p.state).collect())
            .unwrap_or_default();
        let parts = crate::scene::foxglove::parts_update(
            hub.part_solids(),
            &program.parts,
            &states,
            &feed.frame_id,
            timestamp(now),
        );
        self.send(feed.scene, now, &parts);
    }

    fn send(&self, channel: u32, time_ns: u64, message: &impl Encode) {
        let mut payload = Vec::with_capacity(message.encoded_len().unwrap_or(256));
        if message.encode(&mut payload).is_ok() {
            let _ = self.sender.send(Arc::new(Outgoing {
                channel,
                time_ns,
                payload,
            }));
        }
    }

    fn server_info(&self) -> String {
        serde_json::json!({
            "op": "serverInfo",
            "name": SERVER_NAME,
            "capabilities": ["assets"],
            "metadata": { "cells": self.names.join(",") },
            "sessionId": unix_ns().to_string(),
        })
        .to_string()
    }

    fn advertise(&self) -> String {
        let channels: Vec<_> = self
            .channels
            .iter()
            .map(|c| {
                serde_json::json!({
                    "id": c.id,
                    "topic": c.topic,
                    "encoding": c.encoding,
                    "schemaName": c.schema_name,
                    "schema": c.schema,
                    "schemaEncoding": if c.encoding == "json" { "jsonschema" } else { "protobuf" },
                })
            })
            .collect();
        serde_json::json!({ "op": "advertise", "channels": channels }).to_string()
    }

    /// The URDF at `uri`, or why there is none.
    fn asset(&self, uri: &str) -> Result<Vec<u8>, AssetError> {
        let name = uri
            .strip_prefix(URDF_URI_PREFIX)
            .and_then(|file| file.strip_suffix(".urdf"))
            .ok_or_else(|| AssetError::Unknown(uri.to_owned()))?;
        let index =
            self.names
                .iter()
                .position(|n| n == name)
                .ok_or_else(|| AssetError::NoCell {
                    name: name.to_owned(),
                    cells: self.names.join(", "),
                })?;
        let feed = self.cells[index]
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        feed.urdf
            .as_ref()
            .map(|u| u.as_bytes().to_vec())
            .ok_or_else(|| AssetError::NoUrdf(name.to_owned()))
    }

    /// The whole scene of `channel`'s cell now, for a client that just subscribed to it
    /// or skipped ahead.
    fn scene_now(&self, channel: &Channel, hub: &LiveHub) -> Option<Vec<u8>> {
        let Some(SceneChange::New(view)) = hub.scene_since(&mut SceneCursor::default()) else {
            return None;
        };
        let feed = self.cells[channel.cell]
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let mut update = full_update(
            &view,
            &feed.frame_id,
            &feed.body_frames,
            timestamp(unix_ns()),
        );
        // The mark of the closest pair, as the others have it.
        let mark = closest_update(
            &view,
            feed.closest.as_ref(),
            &feed.frame_id,
            &feed.body_frames,
            timestamp(unix_ns()),
        );
        update.entities.extend(mark.entities);
        let mut payload = Vec::new();
        update.encode(&mut payload).ok()?;
        Some(payload)
    }
}

/// Nanoseconds since the Unix epoch: live messages carry wall time, as Foxglove expects of a
/// live source.
fn unix_ns() -> u64 {
    u64::try_from(clock::real().unix_time().as_nanos()).unwrap_or(u64::MAX)
}

/// The connected clients' places: each with when it went idle (`None` while it has a
/// subscription) and how to tell it to go.
#[derive(Default)]
struct Seats {
    next: AtomicU64,
    open: Mutex<BTreeMap<u64, SeatEntry>>,
}

struct SeatEntry {
    idle_since: Option<Duration>,
    evict: Arc<Notify>,
}

impl Seats {
    fn open(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, SeatEntry>> {
        self.open.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A place for a newcomer (idle from now until it subscribes): a free one, else the
    /// place of the client idle longest, which is told to go; `None` when every client is
    /// subscribed.
    fn take(self: &Arc<Self>) -> Option<Seat> {
        let mut open = self.open();
        if open.len() >= MAX_FOXGLOVE_CLIENTS {
            let (_, victim) = open
                .iter()
                .filter_map(|(id, seat)| seat.idle_since.map(|since| (since, *id)))
                .min()?;
            if let Some(seat) = open.remove(&victim) {
                seat.evict.notify_one();
            }
        }
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let evicted = Arc::new(Notify::new());
        open.insert(
            id,
            SeatEntry {
                idle_since: Some(clock::real().now()),
                evict: evicted.clone(),
            },
        );
        Some(Seat {
            id,
            seats: self.clone(),
            evicted,
        })
    }
}

/// One client's place; given back when dropped.
struct Seat {
    id: u64,
    seats: Arc<Seats>,
    /// Notified when a newcomer took the place.
    evicted: Arc<Notify>,
}

impl Seat {
    fn set_idle_since(&self, since: Option<Duration>) {
        if let Some(seat) = self.seats.open().get_mut(&self.id) {
            seat.idle_since = since;
        }
    }
}

impl Drop for Seat {
    fn drop(&mut self) {
        self.seats.open().remove(&self.id);
    }
}

/// Serves ws-protocol on `listener` until `stopping` turns true, behind the HTTP API's
/// `Host` check (`hosts`) and the origin check ([`require_app_origin`]).
pub(super) async fn serve(
    listener: tokio::net::TcpListener,
    daemon: Arc<Daemon>,
    hosts: HostCheck,
    stopping: watch::Receiver<bool>,
) {
    let origins: Vec<String> = FOXGLOVE_APP_ORIGINS
        .iter()
        .map(|o| (*o).to_owned())
        .chain(
            daemon.cells[0]
                .settings()
                .config
                .serve
                .foxglove_origins
                .iter()
                .cloned(),
        )
        .collect();
    let app = axum::Router::new()
        .route("/", axum::routing::get(upgrade))
        .layer(axum::middleware::from_fn_with_state(
            Arc::<[String]>::from(origins),
            require_app_origin,
        ))
        .layer(axum::middleware::from_fn_with_state(
            hosts,
            require_known_host,
        ))
        .with_state(daemon);
    connections::serve(listener, app, MAX_FOXGLOVE_CLIENTS * 2, stopping).await;
}

/// Refuses a handshake whose `Origin` is neither absent, this server, nor one of `origins`
/// with 403, before any message: a page of another site in a local browser must not read
/// the rigs' state.
async fn require_app_origin(
    State(origins): State<Arc<[String]>>,
    request: Request,
    next: Next,
) -> Response {
    if origin_allowed(request.headers(), &origins) {
        return next.run(request).await;
    }
    let origin = request
        .headers()
        .get(header::ORIGIN)
        .map(|o| shorten(&String::from_utf8_lossy(o.as_bytes())))
        .unwrap_or_default();
    super::error(
        StatusCode::FORBIDDEN,
        format!(
            "cross-origin WebSocket refused: origin {origin} is not the Foxglove app's ({}); \
             add it to [serve] foxglove_origins to let it in",
            origins.join(", ")
        ),
    )
}

async fn upgrade(State(daemon): State<Arc<Daemon>>, upgrade: WebSocketUpgrade) -> Response {
    let Some(seat) = daemon.foxglove.seats.take() else {
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("{MAX_FOXGLOVE_CLIENTS} Foxglove clients are connected and subscribed already"),
        )
            .into_response();
    };
    upgrade
        .max_message_size(MAX_FOXGLOVE_MESSAGE_BYTES)
        .max_frame_size(MAX_FOXGLOVE_MESSAGE_BYTES)
        .protocols([FOXGLOVE_SUBPROTOCOL])
        .on_upgrade(move |socket| async move {
            // A client that offered no subprotocol we speak gets none back: the spec says
            // the connection must not go on.
            if socket.protocol().is_some() {
                Client::new(socket, daemon, seat).run().await;
            }
        })
}

/// A client's message, by its `op` (spec: Subscribe, Unsubscribe, Fetch asset); any other
/// op is answered with a status.
#[derive(Deserialize)]
#[serde(tag = "op", rename_all = "camelCase")]
enum ClientOp {
    Subscribe {
        subscriptions: Vec<Subscription>,
    },
    Unsubscribe {
        #[serde(rename = "subscriptionIds")]
        subscription_ids: Vec<u32>,
    },
    FetchAsset {
        uri: String,
        #[serde(rename = "requestId")]
        request_id: u32,
    },
    #[serde(other)]
    Other,
}

#[derive(Deserialize)]
struct Subscription {
    id: u32,
    #[serde(rename = "channelId")]
    channel_id: u32,
}

/// Why a connection ends.
struct Gone;

struct Client {
    socket: WebSocket,
    daemon: Arc<Daemon>,
    seat: Seat,
    /// Since when the client has had no subscription and sent nothing; `None` while it has
    /// a subscription.
    idle_since: Option<Duration>,
    /// channel id -> subscription id: one subscription per channel, so at most as many
    /// entries as channels.
    subscriptions: BTreeMap<u32, u32>,
}

impl Client {
    fn new(socket: WebSocket, daemon: Arc<Daemon>, seat: Seat) -> Self {
        Client {
            socket,
            daemon,
            seat,
            idle_since: Some(clock::real().now()),
            subscriptions: BTreeMap::new(),
        }
    }

    /// After a message from the client: idle from now if it has no subscription.
    fn note_activity(&mut self) {
        self.idle_since = self.subscriptions.is_empty().then(|| clock::real().now());
        self.seat.set_idle_since(self.idle_since);
    }

    async fn close(&mut self, reason: String) -> Result<(), Gone> {
        let close = CloseFrame {
            code: CLOSE_NORMAL,
            reason: reason.into(),
        };
        let _ = self.send(WsMessage::Close(Some(close))).await;
        Err(Gone)
    }

    async fn run(mut self) {
        let feed = &self.daemon.foxglove;
        let mut messages = feed.sender.subscribe();
        let mut stopping = self.daemon.stopping.clone();
        let hello = [feed.server_info(), feed.advertise()];
        for text in hello {
            if self.send(WsMessage::Text(text.into())).await.is_err() {
                return;
            }
        }
        let evicted = self.seat.evicted.clone();
        loop {
            let idle_until = self.idle_since.map(|since| since + FOXGLOVE_IDLE_TIMEOUT);
            let step = tokio::select! {
                message = messages.recv() => self.forward(message).await,
                incoming = self.socket.recv() => self.receive(incoming).await,
                () = sleep_until(idle_until) => {
                    let reason = format!(
                        "idle: no subscription for {} s",
                        FOXGLOVE_IDLE_TIMEOUT.as_secs()
                    );
                    self.close(reason).await
                }
                () = evicted.notified() => {
                    self.close("idle: a new client took this place".into()).await
                }
                _ = stopping.changed() => {
                    let _ = self.send(WsMessage::Close(None)).await;
                    Err(Gone)
                }
            };
            if step.is_err() {
                return;
            }
        }
    }

    async fn send(&mut self, message: WsMessage) -> Result<(), Gone> {
        match tokio::time::timeout(SEND_TIMEOUT, self.socket.send(message)).await {
            Ok(Ok(())) => Ok(()),
            _ => Err(Gone),
        }
    }

    async fn forward(
        &mut self,
        message: Result<Arc<Outgoing>, broadcast::error::RecvError>,
    ) -> Result<(), Gone> {
        match message {
            Ok(out) => match self.subscriptions.get(&out.channel) {
                Some(&subscription) => {
                    let data = message_data(subscription, out.time_ns, &out.payload);
                    self.send(WsMessage::Binary(data.into())).await
                }
                None => Ok(()),
            },
            // Skipped ahead: the paint in between is lost, so the scene is sent whole.
            Err(broadcast::error::RecvError::Lagged(_)) => self.resend_scenes().await,
            Err(broadcast::error::RecvError::Closed) => Err(Gone),
        }
    }

    async fn resend_scenes(&mut self) -> Result<(), Gone> {
        let scenes: Vec<(u32, u32)> = self
            .subscriptions
            .iter()
            .map(|(channel, subscription)| (*channel, *subscription))
            .collect();
        for (channel, subscription) in scenes {
            self.send_scene(channel, subscription).await?;
        }
        Ok(())
    }

    /// The whole scene to a subscriber of `channel`, if it is a scene channel.
    async fn send_scene(&mut self, channel: u32, subscription: u32) -> Result<(), Gone> {
        let feed = &self.daemon.foxglove;
        let payload = feed
            .channels
            .iter()
            .find(|c| c.id == channel && c.kind == Kind::Scene)
            .and_then(|c| feed.scene_now(c, self.daemon.cells.get(c.cell)?.hub()));
        match payload {
            Some(payload) => {
                let data = message_data(subscription, unix_ns(), &payload);
                self.send(WsMessage::Binary(data.into())).await
            }
            None => Ok(()),
        }
    }

    async fn receive(
        &mut self,
        incoming: Option<Result<WsMessage, axum::Error>>,
    ) -> Result<(), Gone> {
        match incoming {
            Some(Ok(WsMessage::Text(text))) => {
                let handled = self.handle(text.as_str()).await;
                self.note_activity();
                handled
            }
            Some(Ok(WsMessage::Binary(_))) => {
                self.note_activity();
                self.status(
                    STATUS_ERROR,
                    "this server is read-only: clients cannot publish",
                )
                .await
            }
            Some(Ok(_)) => Ok(()),
            Some(Err(e)) if super::is_too_big(&e) => {
                let close = CloseFrame {
                    code: CLOSE_MESSAGE_TOO_BIG,
                    reason: format!("a message is at most {MAX_FOXGLOVE_MESSAGE_BYTES} bytes")
                        .into(),
                };
                let _ = self.send(WsMessage::Close(Some(close))).await;
                Err(Gone)
            }
            None | Some(Err(_)) => Err(Gone),
        }
    }

    async fn handle(&mut self, text: &str) -> Result<(), Gone> {
        let op = match serde_json::from_str::<ClientOp>(text) {
            Ok(op) => op,
            Err(e) => {
                let message = format!(
                    "not a ws-protocol message: {}",
                    super::guard::shorten(&e.to_string())
                );
                return self.status(STATUS_ERROR, &message).await;
            }
        };
        match op {
            ClientOp::Subscribe { subscriptions } => self.subscribe(subscriptions).await,
            ClientOp::Unsubscribe { subscription_ids } => {
                self.subscriptions
                    .retain(|_, subscription| !subscription_ids.contains(subscription));
                Ok(())
            }
            ClientOp::FetchAsset { uri, request_id } => {
                let answer = fetch_asset_response(request_id, self.daemon.foxglove.asset(&uri));
                self.send(WsMessage::Binary(answer.into())).await
            }
            ClientOp::Other => {
                self.status(
                    STATUS_WARNING,
                    "not supported: this read-only server takes subscribe, unsubscribe and fetchAsset",
                )
                .await
            }
        }
    }

    async fn subscribe(&mut self, subscriptions: Vec<Subscription>) -> Result<(), Gone> {
        for Subscription { id, channel_id } in subscriptions {
            let known = self
                .daemon
                .foxglove
                .channels
                .iter()
                .any(|c| c.id == channel_id);
            let problem = if !known {
                Some(format!("no channel {channel_id}"))
            } else if self.subscriptions.values().any(|s| *s == id) {
                Some(format!("subscription id {id} is in use"))
            } else if self.subscriptions.contains_key(&channel_id) {
                Some(format!("channel {channel_id} is subscribed already"))
            } else {
                None
            };
            match problem {
                Some(problem) => self.status(STATUS_ERROR, &problem).await?,
                None => {
                    self.subscriptions.insert(channel_id, id);
                    self.send_scene(channel_id, id).await?;
                }
            }
        }
        Ok(())
    }

    async fn status(&mut self, level: u8, message: &str) -> Result<(), Gone> {
        let text = serde_json::json!({ "op": "status", "level": level, "message": message });
        self.send(WsMessage::Text(text.to_string().into())).await
    }
}

/// Completes at `deadline`; never without one.
async fn sleep_until(deadline: Option<Duration>) {
    match deadline {
        Some(deadline) => tokio::time::sleep(deadline.saturating_sub(clock::real().now())).await,
        None => std::future::pending().await,
    }
}

/// Spec, Message Data: opcode 1, subscription id (u32), timestamp (u64 ns), payload; little
/// endian.
fn message_data(subscription: u32, time_ns: u64, payload: &[u8]) -> Vec<u8> {
    let mut data = Vec::with_capacity(13 + payload.len());
    data.push(OP_MESSAGE_DATA);
    data.extend_from_slice(&subscription.to_le_bytes());
    data.extend_from_slice(&time_ns.to_le_bytes());
    data.extend_from_slice(payload);
    data
}

/// Spec, Fetch Asset Response: opcode 4, request id (u32), status (0 ok, 1 error), error
/// length (u32) and text, then the asset's bytes.
fn fetch_asset_response(request_id: u32, asset: Result<Vec<u8>, AssetError>) -> Vec<u8> {
    let (status, error, data) = match asset {
        Ok(data) => (0u8, String::new(), data),
        Err(error) => (1u8, error.to_string(), Vec::new()),
    };
    let mut out = Vec::with_capacity(10 + error.len() + data.len());
    out.push(OP_FETCH_ASSET_RESPONSE);
    out.extend_from_slice(&request_id.to_le_bytes());
    out.push(status);
    out.extend_from_slice(&u32::try_from(error.len()).unwrap_or(u32::MAX).to_le_bytes());
    out.extend_from_slice(error.as_bytes());
    out.extend_from_slice(&data);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binary_messages_follow_the_spec_layout() {
        let data = message_data(7, 0x0102_0304_0506_0708, b"xyz");
        assert_eq!(data[0], 1);
        assert_eq!(&data[1..5], &[7, 0, 0, 0]);
        assert_eq!(&data[5..13], &[8, 7, 6, 5, 4, 3, 2, 1]);
        assert_eq!(&data[13..], b"xyz");
        let ok = fetch_asset_response(3, Ok(b"<robot/>".to_vec()));
        assert_eq!(&ok[..10], &[4, 3, 0, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(&ok[10..], b"<robot/>");
        let refused = fetch_asset_response(3, Err(AssetError::NoUrdf("s".into())));
        let text = b"cell s has no URDF (its rig is not one serial chain)";
        assert_eq!(refused[5], 1);
        assert_eq!(&refused[6..10], &(text.len() as u32).to_le_bytes());
        assert_eq!(&refused[10..], text);
    }

    #[test]
    fn ops_parse_and_others_are_told_apart() {
        let op: ClientOp =
            serde_json::from_str(r#"{"op":"subscribe","subscriptions":[{"id":0,"channelId":3}]}"#)
                .expect("the subscribe op parses");
        assert!(
            matches!(op, ClientOp::Subscribe { subscriptions } if subscriptions[0].channel_id == 3)
        );
        let op: ClientOp = serde_json::from_str(r#"{"op":"advertise","channels":[]}"#)
            .expect("the advertise op parses");
        assert!(matches!(op, ClientOp::Other));
    }
}
