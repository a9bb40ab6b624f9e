//! Serial link (`serialport`): a writer thread frames commands onto the line and keeps the
//! session of `docs/protocol.md` 6 ([`BridgeSession`]: `0x00` and Hello on every open,
//! nothing streamed before the controller's answer, Heartbeats, silence as link loss); a
//! reader thread decodes what comes back. Device, baud, parity, stop bits and flow control
//! come from the link address and the config. A port that disappears (or a controller that
//! goes silent) is reopened with backoff; commands queued meanwhile are dropped, never sent
//! late.

use crate::link::{BridgeSession, ChannelLink, Due, IoEnds, LinkShared, Outgoing};
use crate::protocol::codec::{FrameDecoder, Message, encode_frame};
use crate::protocol::{Command, Hello};
use crate::transport::{Backoff, SerialSettings};
use serialport::SerialPort;
use std::io::ErrorKind;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Starts the I/O threads and returns the link; it opens the port in the background.
/// `hello` is the bridge's, sent on every open.
pub fn connect_serial(settings: SerialSettings, hello: Hello) -> std::io::Result<ChannelLink> {
    let description = format!("serial://{}?baud={}", settings.path, settings.baud);
    let (link, ends, session) = ChannelLink::pair(description, hello);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    crate::link::spawn_io_thread("rigbridge-serial", move || {
        runtime.block_on(keep_open(settings, ends, session))
    })?;
    Ok(link)
}

/// What the reader thread shares with the writer: the session, and answers to send.
struct Shared {
    session: Mutex<BridgeSession>,
    answers: tokio::sync::mpsc::Sender<Outgoing>,
}

async fn keep_open(settings: SerialSettings, mut ends: IoEnds, session: BridgeSession) {
    let mut backoff = Backoff::default();
    let mut sessions = 0u64;
    let (answer_tx, mut answers) = tokio::sync::mpsc::channel(4);
    let shared = Arc::new(Shared {
        session: Mutex::new(session),
        answers: answer_tx,
    });
    while !ends.shared.closed.load(Ordering::SeqCst) {
        let port = match settings.open() {
            Ok(port) => port,
            Err(e) => {
                ends.shared.set_problem(Some(settings.open_failure(&e)));
                tokio::time::sleep(backoff.next_wait()).await;
                continue;
            }
        };
        if sessions > 0 {
            LinkShared::count(&ends.shared.reconnects);
        }
        sessions += 1;
        backoff.reset();
        ends.shared.set_problem(None);
        while ends.commands.try_recv().is_ok() {}
        while answers.try_recv().is_ok() {}
        let Ok(reader) = port.try_clone() else {
            continue;
        };
        ends.shared.connected.store(true, Ordering::SeqCst);
        let reading = {
            let (shared, ends) = (shared.clone(), reader_ends(&ends));
            std::thread::spawn(move || read_messages(reader, &shared, &ends))
        };
        let ended_by_bridge = write_commands(port, &mut ends, &shared, &mut answers).await;
        ends.shared.connected.store(false, Ordering::SeqCst);
        if let Ok(mut session) = shared.session.lock() {
            session.closed(&ends.shared);
        }
        let _ = reading.join();
        if ended_by_bridge {
            return;
        }
    }
}

/// The reader's copy of the ends (it needs no commands and no I/O requests).
fn reader_ends(ends: &IoEnds) -> IoEnds {
    let (_, commands) = tokio::sync::mpsc::channel(1);
    let (_, io_requests) = tokio::sync::mpsc::channel(1);
    IoEnds {
        commands,
        feedback: ends.feedback.clone(),
        events: ends.events.clone(),
        io_requests,
        io_states: ends.io_states.clone(),
        shared: ends.shared.clone(),
    }
}

fn encoded(message: &Message, opening: bool, frame: &mut Vec<u8>, ends: &IoEnds) -> bool {
    frame.clear();
    if opening {
        frame.push(0);
    }
    match encode_frame(message, frame) {
        Ok(()) => true,
        Err(error) => {
            ends.encode_failed(error);
            false
        }
    }
}

fn message_for(what: Outgoing, shared: &Shared) -> Option<Message> {
    match what {
        Outgoing::Hello => Some(shared.session.lock().ok()?.hello_message()),
        Outgoing::Heartbeat => Some(Message::Command(Command::Heartbeat)),
    }
}

/// The writer's side of one open port. True when the bridge closed the link.
async fn write_commands(
    mut port: Box<dyn SerialPort>,
    ends: &mut IoEnds,
    shared: &Shared,
    answers: &mut tokio::sync::mpsc::Receiver<Outgoing>,
) -> bool {
    let mut frame = Vec::with_capacity(1024);
    let (opening, period) = match shared.session.lock() {
        Ok(mut session) => (
            session.opened(Instant::now(), &ends.shared),
            session.period(),
        ),
        Err(_) => return true,
    };
    let mut pending = message_for(opening, shared).map(|m| (m, true));
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        if let Some((message, opening)) = pending.take()
            && encoded(&message, opening, &mut frame, ends)
        {
            if port.write_all(&frame).is_err() {
                return false;
            }
            LinkShared::count(&ends.shared.frames_sent);
            if let Ok(mut session) = shared.session.lock() {
                session.sent(Instant::now());
            }
        }
        if !ends.shared.connected.load(Ordering::SeqCst) {
            return false;
        }
        tokio::select! {
            command = ends.commands.recv() => {
                let Some(command) = command else { return true };
                let allowed = shared
                    .session
                    .lock()
                    .is_ok_and(|s| s.may_send(&command, &ends.shared));
                if allowed {
                    pending = Some((Message::Command(command), false));
                } else {
                    LinkShared::count(&ends.shared.dropped_commands);
                }
            }
            request = ends.io_requests.recv() => {
                let Some(request) = request else { return true };
                let allowed = shared.session.lock().is_ok_and(|s| s.may_send_io());
                if allowed {
                    pending = Some((Message::Io(request), false));
                } else {
                    LinkShared::count(&ends.shared.dropped_commands);
                }
            }
            Some(answer) = answers.recv() => pending = message_for(answer, shared).map(|m| (m, false)),
            _ = tick.tick() => {
                let due = shared.session.lock().map_or(Due::Lost, |mut s| s.due(Instant::now()));
                match due {
                    Due::Nothing => {}
                    Due::Lost => return false,
                    Due::Send(what) => pending = message_for(what, shared).map(|m| (m, false)),
                }
            }
            _ = ends.shared.restart.notified() => return false,
        }
    }
}

fn read_messages(mut port: Box<dyn SerialPort>, shared: &Shared, ends: &IoEnds) {
    let mut decoder = FrameDecoder::default();
    let mut buffer = [0u8; 4096];
    while !ends.shared.closed.load(Ordering::SeqCst) && ends.shared.connected.load(Ordering::SeqCst)
    {
        match port.read(&mut buffer) {
            Ok(0) => {}
            Ok(n) => decoder.push(&buffer[..n]),
            Err(e) if e.kind() == ErrorKind::TimedOut => continue,
            Err(_) => {
                ends.shared.connected.store(false, Ordering::SeqCst);
                return;
            }
        }
        while let Some(message) = decoder.next_message() {
            LinkShared::count(&ends.shared.frames_received);
            let answer = shared
                .session
                .lock()
                .ok()
                .and_then(|mut s| s.received(message, Instant::now(), ends));
            if let Some(answer) = answer {
                let _ = shared.answers.try_send(answer);
            }
        }
        ends.shared
            .crc_errors
            .store(decoder.counters().crc_errors, Ordering::Relaxed);
    }
}
