//! Serial link (`serialport`): a writer thread frames commands onto the line, a reader
//! thread decodes feedback off it. Device, baud, parity, stop bits and flow control come
//! from the link address and the config. A port that disappears is reopened with backoff;
//! commands queued meanwhile are dropped, never sent late.

use super::{ChannelLink, IoEnds, LinkShared};
use crate::protocol::codec::{FrameDecoder, Message, encode_frame};
use serialport::{DataBits, FlowControl, Parity, SerialPort, StopBits};
use std::io::ErrorKind;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

#[derive(Debug, Clone, PartialEq)]
pub struct SerialSettings {
    pub path: String,
    pub baud: u32,
    pub parity: Parity,
    pub stop_bits: StopBits,
    pub flow_control: FlowControl,
}

impl SerialSettings {
    /// 8N1, no flow control.
    pub fn new(path: impl Into<String>, baud: u32) -> Self {
        Self {
            path: path.into(),
            baud,
            parity: Parity::None,
            stop_bits: StopBits::One,
            flow_control: FlowControl::None,
        }
    }

    pub fn open(&self) -> serialport::Result<Box<dyn SerialPort>> {
        serialport::new(&self.path, self.baud)
            .data_bits(DataBits::Eight)
            .parity(self.parity)
            .stop_bits(self.stop_bits)
            .flow_control(self.flow_control)
            .timeout(READ_TIMEOUT)
            .open()
    }
}

/// How long a read waits before the reader checks whether the link was closed.
const READ_TIMEOUT: Duration = Duration::from_millis(20);
const BACKOFF_INITIAL: Duration = Duration::from_millis(10);
const BACKOFF_MAX: Duration = Duration::from_secs(1);

/// Starts the I/O threads and returns the link; it opens the port in the background.
pub fn connect_serial(settings: SerialSettings) -> std::io::Result<ChannelLink> {
    let description = format!("serial://{}?baud={}", settings.path, settings.baud);
    let (link, ends) = ChannelLink::pair(description);
    std::thread::Builder::new()
        .name("rigbridge-serial".into())
        .spawn(move || keep_open(settings, ends))?;
    Ok(link)
}

fn keep_open(settings: SerialSettings, mut ends: IoEnds) {
    let mut backoff = BACKOFF_INITIAL;
    let mut sessions = 0u64;
    while !ends.shared.closed.load(Ordering::SeqCst) {
        let port = match settings.open() {
            Ok(port) => port,
            Err(_) => {
                std::thread::sleep(backoff);
                backoff = (backoff * 2).min(BACKOFF_MAX);
                continue;
            }
        };
        if sessions > 0 {
            LinkShared::count(&ends.shared.reconnects);
        }
        sessions += 1;
        backoff = BACKOFF_INITIAL;
        while ends.commands.try_recv().is_ok() {}
        let Ok(reader) = port.try_clone() else {
            continue;
        };
        ends.shared.connected.store(true, Ordering::SeqCst);
        let shared = ends.shared.clone();
        let feedback = ends.feedback.clone();
        let reading = std::thread::spawn(move || read_feedback(reader, &shared, &feedback));
        let ended_by_bridge = write_commands(port, &mut ends);
        ends.shared.connected.store(false, Ordering::SeqCst);
        let _ = reading.join();
        if ended_by_bridge {
            return;
        }
    }
}

/// Writes until the line fails (false) or the bridge closes the link (true).
fn write_commands(mut port: Box<dyn SerialPort>, ends: &mut IoEnds) -> bool {
    let mut frame = Vec::with_capacity(1024);
    while let Some(command) = ends.commands.blocking_recv() {
        frame.clear();
        if encode_frame(&Message::Command(command), &mut frame).is_err() {
            continue;
        }
        if port.write_all(&frame).is_err() {
            return false;
        }
        LinkShared::count(&ends.shared.frames_sent);
        if !ends.shared.connected.load(Ordering::SeqCst) {
            return false;
        }
    }
    true
}

fn read_feedback(
    mut port: Box<dyn SerialPort>,
    shared: &Arc<LinkShared>,
    feedback: &std::sync::mpsc::SyncSender<crate::protocol::Feedback>,
) {
    let mut decoder = FrameDecoder::default();
    let mut buffer = [0u8; 4096];
    let mut last_seq: Option<u32> = None;
    while !shared.closed.load(Ordering::SeqCst) {
        match port.read(&mut buffer) {
            Ok(0) => {}
            Ok(n) => decoder.push(&buffer[..n]),
            Err(e) if e.kind() == ErrorKind::TimedOut => continue,
            Err(_) => {
                shared.connected.store(false, Ordering::SeqCst);
                return;
            }
        }
        while let Some(message) = decoder.next_message() {
            if let Message::Feedback(answer) = message {
                shared.note_feedback(&mut last_seq, &answer);
                let _ = feedback.try_send(answer);
            }
        }
        shared
            .crc_errors
            .store(decoder.counters().crc_errors, Ordering::Relaxed);
    }
}
