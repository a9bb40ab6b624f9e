//! Arbitrary bytes into the protocol's receivers: the byte-stream `FrameDecoder` (in
//! pieces of an arbitrary size) and classic and FD `CanAssembler`s (the same bytes read as
//! frames). Nothing may panic; every message that comes out must re-encode and decode to
//! itself, and every body the decoder accepts must be the canonical encoding of its message.

#![no_main]

use libfuzzer_sys::fuzz_target;
use rigbridge::protocol::can::{CanAssembler, CanMapping, CanPayload, CanSender};
use rigbridge::protocol::codec::{cobs_decode, decode_body, encode_body, encode_frame};
use rigbridge::protocol::{FrameDecoder, Message};

const BASE_ID: u16 = 0x100;

fuzz_target!(|data: &[u8]| {
    let Some((&piece, stream)) = data.split_first() else {
        return;
    };
    byte_stream(stream, usize::from(piece).max(1));
    canonical_bodies(stream);
    for fd in [false, true] {
        can_frames(stream, fd);
    }
});

fn byte_stream(stream: &[u8], piece: usize) {
    let mut decoder = FrameDecoder::new();
    for chunk in stream.chunks(piece) {
        decoder.push(chunk);
        while let Some(message) = decoder.next_message() {
            round_trips(&message);
        }
    }
}

/// Every accepted body re-encodes to exactly its own bytes.
fn canonical_bodies(stream: &[u8]) {
    let mut body = Vec::new();
    let mut again = Vec::new();
    for frame in stream.split(|&b| b == 0) {
        body.clear();
        if cobs_decode(frame, &mut body).is_err() {
            continue;
        }
        if let Ok(message) = decode_body(&body) {
            again.clear();
            encode_body(&message, &mut again).expect("a decoded message encodes");
            assert_eq!(again, body, "accepted body is not canonical");
        }
    }
}

/// The bytes as CAN frames: offset from the base (u8), then a length byte (bit 7 flips the
/// frame's FD flag against the mapping's, the rest is the length, cut at 64), then data.
fn can_frames(mut rest: &[u8], fd: bool) {
    let mapping = CanMapping::new(BASE_ID, fd, CanSender::Bridge).expect("valid base");
    let mut assembler = CanAssembler::new(mapping);
    while let [offset, shape, tail @ ..] = rest {
        let len = usize::from(shape & 0x7F).min(64);
        let take = len.min(tail.len());
        let mut frame = CanPayload::new(
            u32::from(BASE_ID) + u32::from(*offset),
            &tail[..take],
            fd ^ (shape & 0x80 != 0),
        );
        // Any length byte at all, valid for the bus or not.
        frame.len = len as u8;
        rest = &tail[take..];
        if let Some(message) = assembler.push(&frame) {
            round_trips(&message);
        }
    }
}

fn round_trips(message: &Message) {
    let mut frame = Vec::new();
    encode_frame(message, &mut frame).expect("a decoded message encodes");
    let mut decoder = FrameDecoder::new();
    decoder.push(&frame);
    assert_eq!(decoder.next_message().as_ref(), Some(message));
}
