//! CAN link (Linux SocketCAN): the bridge's end of the protocol's CAN mapping
//! (`docs/protocol.md`, section 7). Each command goes out as the frames of
//! [`can_frames`]; the controller's frames are rebuilt into feedback by a [`CanAssembler`],
//! which delivers a multi-frame message only when it is complete and its CRC holds.
//!
//! The session of `docs/protocol.md` 6 is the shared [`BridgeSession`]: a Hello on every
//! open, nothing streamed before the controller's answer, Heartbeats, and silence as link
//! loss. CAN has no connection: the link is open while its socket is open on an interface
//! that is up, and up once the controller has answered. When the interface goes down (or
//! away), the I/O thread closes the socket and reopens it with exponential backoff, like
//! the TCP link reconnects; commands queued meanwhile are discarded, never sent late. The
//! thread runs a current-thread tokio runtime that waits on the command channel and the
//! socket at once, so neither direction adds latency.
//!
//! The socket is [`CanBus`] (`transport::can`), shared with the twin's CAN port. Counters
//! are in CAN frames (`frames_sent`, `frames_received`: 8 and 5 a cycle for 6 axes on classic
//! CAN); gaps and duplicates are counted on the sequence numbers the feedback echoes.

use crate::link::{BridgeSession, ChannelLink, Due, IoEnds, LinkShared, Outgoing};
use crate::protocol::{
    CanAssembler, CanMapping, CanPayload, CanSender, Command, Hello, Message, can_frames,
};
use crate::transport::{Backoff, CanBus, SEND_PATIENCE, interface_up};
use std::io::{self, ErrorKind};
use std::ops::ControlFlow;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tokio::io::Interest;
use tokio::io::unix::{AsyncFd, AsyncFdReadyGuard};

/// A session shorter than this does not reset the backoff (an interface that flaps).
const STABLE_SESSION: Duration = Duration::from_secs(1);
/// How often the I/O thread looks at the interface's state and the link's closed flag.
const WATCH_PERIOD: Duration = Duration::from_millis(50);

/// Starts the I/O thread and returns the link. An interface that is missing, not CAN FD
/// for an FD mapping, or on a kernel without SocketCAN is an error now; one that is down
/// is waited for in the background (`is_up` is false until it comes up).
/// `hello` is the bridge's, sent on every open.
pub fn connect_can(interface: &str, mapping: CanMapping, hello: Hello) -> io::Result<ChannelLink> {
    if mapping.sender() != CanSender::Bridge {
        return Err(io::Error::new(
            ErrorKind::InvalidInput,
            "a bridge's CAN link needs a mapping with the bridge as sender",
        ));
    }
    let first = match CanBus::open(interface, &mapping) {
        Ok(bus) => Some(bus),
        Err(e) if e.kind() == ErrorKind::NetworkDown => None,
        Err(e) => return Err(e),
    };
    let (link, ends, session) = ChannelLink::pair(describe(interface, &mapping), hello);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let interface = interface.to_string();
    crate::link::spawn_io_thread("rigbridge-can", move || {
        runtime.block_on(keep_open(interface, mapping, ends, session, first))
    })?;
    Ok(link)
}

fn describe(interface: &str, mapping: &CanMapping) -> String {
    format!(
        "can://{interface} ({}, base {:#x})",
        if mapping.fd() {
            "CAN FD"
        } else {
            "classic CAN"
        },
        mapping.base_id()
    )
}

async fn keep_open(
    interface: String,
    mapping: CanMapping,
    mut ends: IoEnds,
    mut bridge: BridgeSession,
    mut first: Option<CanBus>,
) {
    let mut backoff = Backoff::default();
    let mut sessions = 0u64;
    let mut assembler = CanAssembler::new(mapping);
    while !ends.shared.closed.load(Ordering::SeqCst) {
        let opened = match first.take() {
            Some(bus) => Ok(bus),
            None => CanBus::open(&interface, &mapping),
        };
        if let Ok(bus) = opened {
            if sessions > 0 {
                LinkShared::count(&ends.shared.reconnects);
            }
            sessions += 1;
            while ends.commands.try_recv().is_ok() {}
            assembler.reset();
            let started = Instant::now();
            ends.shared.connected.store(true, Ordering::SeqCst);
            let ended_by_bridge =
                session(bus, &mut ends, &mapping, &mut assembler, &mut bridge).await;
            bridge.closed(&ends.shared);
            ends.shared.connected.store(false, Ordering::SeqCst);
            if ended_by_bridge {
                return;
            }
            if started.elapsed() >= STABLE_SESSION {
                backoff.reset();
            }
        }
        tokio::time::sleep(backoff.next_wait()).await;
    }
}

/// Sends `message` as its CAN frames; false when the bus failed. A message that does not
/// fit the wire is reported and skipped; one the bus has no room for is dropped whole
/// (the controller drops the incomplete one).
fn send_message(bus: &CanBus, message: &Message, mapping: &CanMapping, ends: &IoEnds) -> bool {
    let mut frames: Vec<CanPayload> = Vec::with_capacity(64);
    if let Err(error) = can_frames(message, mapping, &mut frames) {
        ends.encode_failed(error);
        return true;
    }
    for frame in &frames {
        // Blocks this thread for at most SEND_PATIENCE: it has nothing else to do.
        match bus.send_patiently(frame, SEND_PATIENCE) {
            Ok(()) => LinkShared::count(&ends.shared.frames_sent),
            Err(e) if e.kind() == ErrorKind::WouldBlock => {
                LinkShared::count(&ends.shared.dropped_commands);
                break;
            }
            Err(_) => return false,
        }
    }
    true
}

fn outgoing(what: Outgoing, bridge: &BridgeSession) -> Message {
    match what {
        Outgoing::Hello => bridge.hello_message(),
        Outgoing::Heartbeat => Message::Command(Command::Heartbeat),
    }
}

/// [`send_message`], and the session told when it went; false when the bus failed.
fn send_noted(
    bus: &CanBus,
    message: &Message,
    mapping: &CanMapping,
    ends: &IoEnds,
    bridge: &mut BridgeSession,
) -> bool {
    if !send_message(bus, message, mapping, ends) {
        return false;
    }
    bridge.sent(Instant::now());
    true
}

/// A timer that skips the ticks it missed rather than bunching them.
fn skipping_interval(period: Duration) -> tokio::time::Interval {
    let mut interval = tokio::time::interval(period);
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    interval
}

/// Registers the socket with the runtime, for its frames and its errors: the kernel
/// reports an interface going down as a socket error alone.
fn register(bus: CanBus) -> Option<AsyncFd<CanBus>> {
    // SAFETY: the CanBus owns its socket and never replaces it, so its fd stays open and
    // the same for as long as the AsyncFd holds it.
    unsafe { AsyncFd::register_with_interest(bus, Interest::READABLE | Interest::ERROR) }.ok()
}

/// One socket's life. True when the bridge closed the link (stop for good).
async fn session(
    bus: CanBus,
    ends: &mut IoEnds,
    mapping: &CanMapping,
    assembler: &mut CanAssembler,
    bridge: &mut BridgeSession,
) -> bool {
    let interface = bus.interface().to_string();
    let Some(bus) = register(bus) else {
        return false;
    };
    let hello = outgoing(bridge.opened(Instant::now(), &ends.shared), bridge);
    if !send_noted(bus.get_ref(), &hello, mapping, ends, bridge) {
        return false;
    }
    let mut watch = skipping_interval(WATCH_PERIOD);
    let mut tick = skipping_interval(bridge.period());
    loop {
        let next = tokio::select! {
            command = ends.commands.recv() => {
                on_command(bus.get_ref(), command, mapping, ends, bridge)
            }
            request = ends.io_requests.recv() => {
                on_io_request(bus.get_ref(), request, mapping, ends, bridge)
            }
            ready = bus.ready(Interest::READABLE | Interest::ERROR) => match ready {
                Ok(guard) => on_readable(guard, mapping, assembler, ends, bridge),
                Err(_) => ControlFlow::Break(false),
            },
            _ = tick.tick() => on_tick(bus.get_ref(), mapping, ends, bridge),
            _ = watch.tick() => on_watch(&interface, ends),
            _ = ends.shared.restart.notified() => ControlFlow::Break(false),
        };
        if let ControlFlow::Break(ended_by_bridge) = next {
            return ended_by_bridge;
        }
    }
}

/// A command from the streamer (`None`: the bridge closed the link): sent when the
/// session admits it, else counted as dropped. Breaks with true when the bridge closed
/// the link, false when the bus failed.
fn on_command(
    bus: &CanBus,
    command: Option<Command>,
    mapping: &CanMapping,
    ends: &IoEnds,
    bridge: &mut BridgeSession,
) -> ControlFlow<bool> {
    let Some(command) = command else {
        return ControlFlow::Break(true);
    };
    if !bridge.may_send(&command, &ends.shared) {
        LinkShared::count(&ends.shared.dropped_commands);
        return ControlFlow::Continue(());
    }
    if !send_noted(bus, &Message::Command(command), mapping, ends, bridge) {
        return ControlFlow::Break(false);
    }
    ControlFlow::Continue(())
}

/// An I/O request from the streamer, sent as its segments once the controller has
/// answered (dropped and counted before). Breaks as [`on_command`] does.
fn on_io_request(
    bus: &CanBus,
    request: Option<crate::protocol::IoMessage>,
    mapping: &CanMapping,
    ends: &IoEnds,
    bridge: &mut BridgeSession,
) -> ControlFlow<bool> {
    let Some(request) = request else {
        return ControlFlow::Break(true);
    };
    if !bridge.may_send_io() {
        LinkShared::count(&ends.shared.dropped_commands);
        return ControlFlow::Continue(());
    }
    if !send_noted(bus, &Message::Io(request), mapping, ends, bridge) {
        return ControlFlow::Break(false);
    }
    ControlFlow::Continue(())
}

/// Every frame waiting: complete messages go to the session, and its answers out.
/// Breaks with false when the bus failed.
fn on_readable(
    mut guard: AsyncFdReadyGuard<'_, CanBus>,
    mapping: &CanMapping,
    assembler: &mut CanAssembler,
    ends: &IoEnds,
    bridge: &mut BridgeSession,
) -> ControlFlow<bool> {
    loop {
        match guard.get_inner().try_receive() {
            Ok(Some(frame)) => {
                LinkShared::count(&ends.shared.frames_received);
                let Some(message) = assembler.push(&frame) else {
                    continue;
                };
                let Some(answer) = bridge.received(message, Instant::now(), ends) else {
                    continue;
                };
                let answer = outgoing(answer, bridge);
                if !send_noted(guard.get_inner(), &answer, mapping, ends, bridge) {
                    return ControlFlow::Break(false);
                }
            }
            Ok(None) => {
                guard.clear_ready();
                break;
            }
            Err(_) => return ControlFlow::Break(false),
        }
    }
    ends.shared
        .crc_errors
        .store(assembler.counters().crc_errors, Ordering::Relaxed);
    ControlFlow::Continue(())
}

/// A cycle's tick: a Hello or Heartbeat when one is due; breaks with false when the
/// controller fell silent (link loss) or the bus failed.
fn on_tick(
    bus: &CanBus,
    mapping: &CanMapping,
    ends: &IoEnds,
    bridge: &mut BridgeSession,
) -> ControlFlow<bool> {
    let what = match bridge.due(Instant::now()) {
        Due::Nothing => return ControlFlow::Continue(()),
        Due::Lost => return ControlFlow::Break(false),
        Due::Send(what) => what,
    };
    if !send_noted(bus, &outgoing(what, bridge), mapping, ends, bridge) {
        return ControlFlow::Break(false);
    }
    ControlFlow::Continue(())
}

/// The periodic look at the link and the interface: breaks with true when the bridge
/// closed the link, false when the interface went down.
fn on_watch(interface: &str, ends: &IoEnds) -> ControlFlow<bool> {
    if ends.shared.closed.load(Ordering::SeqCst) {
        return ControlFlow::Break(true);
    }
    if interface_up(interface) == Some(false) {
        return ControlFlow::Break(false);
    }
    ControlFlow::Continue(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_controller_mapping_is_refused_for_the_bridge() {
        let mapping = CanMapping::new(0x100, false, CanSender::Controller)
            .expect("base ID 0x100 is a valid mapping");
        let hello = crate::protocol::Hello {
            axis_names: vec![],
            lower: vec![],
            upper: vec![],
            max_speed: vec![],
            max_acceleration: vec![],
            cycle_us: 4000,
            watchdog_cycles: 25,
            answer: false,
            version: 2,
        };
        let Err(error) = connect_can("vcan0", mapping, hello) else {
            panic!("a controller-side mapping was accepted");
        };
        assert_eq!(error.kind(), ErrorKind::InvalidInput);
    }
}
