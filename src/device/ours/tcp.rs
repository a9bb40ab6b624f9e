//! TCP client link (tokio): connects to a controller, keeps the session of
//! `docs/protocol.md` 6 ([`BridgeSession`]: `0x00` and Hello on every connect, nothing
//! streamed before the controller's answer, Heartbeats, silence as link loss), frames
//! commands with the wire codec, decodes feedback, and on any loss reconnects with
//! exponential backoff. Stale commands queued while down are discarded, never sent late.
//! Runs on its own thread with a current-thread runtime; the cycle only touches the
//! channels of [`ChannelLink`].

use crate::link::{BridgeSession, ChannelLink, Due, IoEnds, LinkShared, Outgoing};
use crate::protocol::Hello;
use crate::protocol::codec::{FrameDecoder, Message, encode_frame};
use crate::transport::{BACKOFF_INITIAL, BACKOFF_MAX, Backoff};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

#[derive(Debug, Clone, PartialEq)]
pub struct TcpSettings {
    /// `host:port`.
    pub address: String,
    pub backoff_initial: Duration,
    pub backoff_max: Duration,
}

impl TcpSettings {
    pub fn new(address: impl Into<String>) -> Self {
        Self {
            address: address.into(),
            backoff_initial: BACKOFF_INITIAL,
            backoff_max: BACKOFF_MAX,
        }
    }
}

/// Starts the I/O thread and returns the link at once; it connects in the background.
/// `hello` is the bridge's, sent on every connect.
pub fn connect_tcp(settings: TcpSettings, hello: Hello) -> std::io::Result<ChannelLink> {
    let (link, ends, session) = ChannelLink::pair(format!("tcp://{}", settings.address), hello);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    crate::link::spawn_io_thread("rigbridge-tcp", move || {
        runtime.block_on(keep_connected(settings, ends, session))
    })?;
    Ok(link)
}

async fn keep_connected(settings: TcpSettings, mut ends: IoEnds, mut bridge: BridgeSession) {
    let mut backoff = Backoff::between(settings.backoff_initial, settings.backoff_max);
    let mut sessions = 0u64;
    // Whether a connection opened and closed while no controller had ever answered the
    // Hello on this link: a later refusal then says so too, since that is the first fault
    // (a controller that did answer once and went away is plainly refused).
    let mut unanswered = false;
    while !ends.shared.closed.load(Ordering::SeqCst) {
        match TcpStream::connect(&settings.address).await {
            Ok(stream) => {
                if sessions > 0 {
                    LinkShared::count(&ends.shared.reconnects);
                }
                sessions += 1;
                backoff.reset();
                ends.shared.set_problem(None);
                let _ = stream.set_nodelay(true);
                while ends.commands.try_recv().is_ok() {}
                ends.shared.connected.store(true, Ordering::SeqCst);
                let ended_by_bridge = session(stream, &mut ends, &mut bridge).await;
                unanswered = ends.shared.sessions.load(Ordering::SeqCst) == 0;
                bridge.closed(&ends.shared);
                ends.shared.connected.store(false, Ordering::SeqCst);
                if ended_by_bridge {
                    return;
                }
            }
            Err(e) => {
                let failure = connect_failure(&settings.address, &e);
                let problem = if unanswered {
                    format!(
                        "the controller at {} did not answer the bridge's Hello before the \
                         connection closed; reconnecting: {failure}",
                        settings.address
                    )
                } else {
                    failure
                };
                ends.shared.set_problem(Some(problem));
                tokio::time::sleep(backoff.next_wait()).await;
            }
        }
    }
}

/// Why a connection to `address` failed: a refusal (nothing listens there) in those words,
/// anything else with the system's.
fn connect_failure(address: &str, error: &std::io::Error) -> String {
    match error.kind() {
        std::io::ErrorKind::ConnectionRefused => format!("connection refused at {address}"),
        _ => format!("cannot connect to {address}: {error}"),
    }
}

/// Encodes `message` into `frame` (cleared first); false when it does not fit the wire,
/// which is reported as an event, and nothing is to be sent.
fn encode(message: &Message, frame: &mut Vec<u8>, ends: &IoEnds) -> bool {
    frame.clear();
    match encode_frame(message, frame) {
        Ok(()) => true,
        Err(error) => {
            ends.encode_failed(error);
            false
        }
    }
}

/// Encodes what the session asks for: the Hello (after a `0x00` on opening) or a Heartbeat.
fn outgoing(what: Outgoing, bridge: &BridgeSession, opening: bool, frame: &mut Vec<u8>) -> bool {
    frame.clear();
    if opening {
        frame.push(0);
    }
    let message = match what {
        Outgoing::Hello => bridge.hello_message(),
        Outgoing::Heartbeat => Message::Command(crate::protocol::Command::Heartbeat),
    };
    encode_frame(&message, frame).is_ok()
}

/// One connection's life. True when the bridge closed the link (stop for good).
async fn session(stream: TcpStream, ends: &mut IoEnds, bridge: &mut BridgeSession) -> bool {
    let (mut reader, mut writer) = stream.into_split();
    let mut decoder = FrameDecoder::default();
    let mut frame = Vec::with_capacity(1024);
    let mut buffer = [0u8; 4096];
    let hello = bridge.opened(Instant::now(), &ends.shared);
    if !outgoing(hello, bridge, true, &mut frame) || writer.write_all(&frame).await.is_err() {
        return false;
    }
    bridge.sent(Instant::now());
    let mut tick = tokio::time::interval(bridge.period());
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            command = ends.commands.recv() => {
                let Some(command) = command else { return true };
                if !bridge.may_send(&command, &ends.shared) {
                    LinkShared::count(&ends.shared.dropped_commands);
                    continue;
                }
                if !encode(&Message::Command(command), &mut frame, ends) {
                    continue;
                }
                if writer.write_all(&frame).await.is_err() {
                    return false;
                }
                bridge.sent(Instant::now());
                LinkShared::count(&ends.shared.frames_sent);
            }
            request = ends.io_requests.recv() => {
                let Some(request) = request else { return true };
                if !bridge.may_send_io() {
                    LinkShared::count(&ends.shared.dropped_commands);
                    continue;
                }
                if !encode(&Message::Io(request), &mut frame, ends) {
                    continue;
                }
                if writer.write_all(&frame).await.is_err() {
                    return false;
                }
                bridge.sent(Instant::now());
                LinkShared::count(&ends.shared.frames_sent);
            }
            read = reader.read(&mut buffer) => {
                let n = match read {
                    Ok(0) | Err(_) => return false,
                    Ok(n) => n,
                };
                decoder.push(&buffer[..n]);
                while let Some(message) = decoder.next_message() {
                    LinkShared::count(&ends.shared.frames_received);
                    let Some(answer) = bridge.received(message, Instant::now(), ends) else {
                        continue;
                    };
                    if !outgoing(answer, bridge, false, &mut frame)
                        || writer.write_all(&frame).await.is_err()
                    {
                        return false;
                    }
                    LinkShared::count(&ends.shared.frames_sent);
                    bridge.sent(Instant::now());
                }
                ends.shared.crc_errors.store(decoder.counters().crc_errors, Ordering::Relaxed);
            }
            _ = tick.tick() => {
                let what = match bridge.due(Instant::now()) {
                    Due::Nothing => continue,
                    Due::Lost => return false,
                    Due::Send(what) => what,
                };
                if !outgoing(what, bridge, false, &mut frame) || writer.write_all(&frame).await.is_err() {
                    return false;
                }
                LinkShared::count(&ends.shared.frames_sent);
                bridge.sent(Instant::now());
            }
            _ = ends.shared.restart.notified() => return false,
        }
    }
}
