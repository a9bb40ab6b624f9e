//! TCP client link (tokio): connects to a controller, frames commands with the wire codec,
//! decodes feedback, and on any loss reconnects with exponential backoff. Stale commands
//! queued while down are discarded, never sent late. Runs on its own thread with a
//! current-thread runtime; the cycle only touches the channels of [`ChannelLink`].

use super::{ChannelLink, IoEnds, LinkShared};
use crate::protocol::codec::{FrameDecoder, Message, encode_frame};
use std::sync::atomic::Ordering;
use std::time::Duration;
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
            backoff_initial: Duration::from_millis(10),
            backoff_max: Duration::from_secs(1),
        }
    }
}

/// Starts the I/O thread and returns the link at once; it connects in the background.
pub fn connect_tcp(settings: TcpSettings) -> std::io::Result<ChannelLink> {
    let (link, ends) = ChannelLink::pair(format!("tcp://{}", settings.address));
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    std::thread::Builder::new()
        .name("rigbridge-tcp".into())
        .spawn(move || runtime.block_on(keep_connected(settings, ends)))?;
    Ok(link)
}

async fn keep_connected(settings: TcpSettings, mut ends: IoEnds) {
    let mut backoff = settings.backoff_initial;
    let mut sessions = 0u64;
    while !ends.shared.closed.load(Ordering::SeqCst) {
        match TcpStream::connect(&settings.address).await {
            Ok(stream) => {
                if sessions > 0 {
                    LinkShared::count(&ends.shared.reconnects);
                }
                sessions += 1;
                backoff = settings.backoff_initial;
                let _ = stream.set_nodelay(true);
                while ends.commands.try_recv().is_ok() {}
                ends.shared.connected.store(true, Ordering::SeqCst);
                let ended_by_bridge = session(stream, &mut ends).await;
                ends.shared.connected.store(false, Ordering::SeqCst);
                if ended_by_bridge {
                    return;
                }
            }
            Err(_) => {
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(settings.backoff_max);
            }
        }
    }
}

/// One connection's life. True when the bridge closed the link (stop for good).
async fn session(stream: TcpStream, ends: &mut IoEnds) -> bool {
    let (mut reader, mut writer) = stream.into_split();
    let mut decoder = FrameDecoder::default();
    let mut frame = Vec::with_capacity(1024);
    let mut buffer = [0u8; 4096];
    let mut last_seq = None;
    loop {
        tokio::select! {
            command = ends.commands.recv() => {
                let Some(command) = command else { return true };
                frame.clear();
                if encode_frame(&Message::Command(command), &mut frame).is_err() {
                    continue;
                }
                if writer.write_all(&frame).await.is_err() {
                    return false;
                }
                LinkShared::count(&ends.shared.frames_sent);
            }
            read = reader.read(&mut buffer) => {
                let n = match read {
                    Ok(0) | Err(_) => return false,
                    Ok(n) => n,
                };
                decoder.push(&buffer[..n]);
                while let Some(message) = decoder.next_message() {
                    if let Message::Feedback(feedback) = message {
                        ends.shared.note_feedback(&mut last_seq, &feedback);
                        let _ = ends.feedback.try_send(feedback);
                    }
                }
                ends.shared.crc_errors.store(decoder.counters().crc_errors, Ordering::Relaxed);
            }
        }
    }
}
