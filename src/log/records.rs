//! The few MCAP records the reader needs (Channel, Message, Metadata, the Chunk header),
//! parsed by hand with every length checked against the bytes actually there. The mcap
//! crate's record parser trusts declared string lengths enough to reserve them up front,
//! which on a damaged file can mean gigabytes; this one cannot over-read or over-allocate.
//! Owns byte layout only (MCAP spec, "Serialization": little-endian integers, uint32-prefixed
//! strings and maps); must not decide what a record means for a run log.

use std::collections::BTreeMap;
use thiserror::Error;

/// An MCAP `map<string, string>` (metadata records, a schema's or channel's metadata).
pub type StringMap = BTreeMap<String, String>;

/// Why a record's bytes do not parse.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum RecordError {
    #[error("{what} record: field of {len} bytes at byte {pos} runs past its end ({total} bytes)")]
    RunsPast {
        what: &'static str,
        len: usize,
        pos: usize,
        total: usize,
    },
    #[error("length {0} does not fit in memory")]
    TooLong(u64),
    #[error("{what} record: a string is not UTF-8")]
    NotUtf8 { what: &'static str },
    #[error("{what} record: a map repeats a key")]
    RepeatedKey { what: &'static str },
}

pub(super) struct Channel {
    pub id: u16,
    pub topic: String,
    pub message_encoding: String,
    pub metadata: StringMap,
}

pub(super) struct Message<'a> {
    pub channel_id: u16,
    pub data: &'a [u8],
}

pub(super) struct Metadata {
    pub name: String,
    pub map: StringMap,
}

pub(super) fn channel(body: &[u8]) -> Result<Channel, RecordError> {
    let mut cursor = Cursor::new(body, "channel");
    let id = cursor.u16()?;
    let _schema_id = cursor.u16()?;
    Ok(Channel {
        id,
        topic: cursor.string()?,
        message_encoding: cursor.string()?,
        metadata: cursor.string_map()?,
    })
}

pub(super) fn message(body: &[u8]) -> Result<Message<'_>, RecordError> {
    let mut cursor = Cursor::new(body, "message");
    let channel_id = cursor.u16()?;
    let _sequence = cursor.u32()?;
    let _log_time = cursor.u64()?;
    let _publish_time = cursor.u64()?;
    Ok(Message {
        channel_id,
        data: cursor.rest(),
    })
}

pub(super) fn metadata(body: &[u8]) -> Result<Metadata, RecordError> {
    let mut cursor = Cursor::new(body, "metadata");
    Ok(Metadata {
        name: cursor.string()?,
        map: cursor.string_map()?,
    })
}

/// The length of a chunk record's body without any padding after its `records` field: the
/// header (times, sizes, CRC, compression) plus `compressed_size` bytes.
pub(super) fn chunk_len_without_padding(body: &[u8]) -> Result<usize, RecordError> {
    let mut cursor = Cursor::new(body, "chunk");
    let _start_time = cursor.u64()?;
    let _end_time = cursor.u64()?;
    let _uncompressed_size = cursor.u64()?;
    let _uncompressed_crc = cursor.u32()?;
    let compression_len = cursor.u32()?;
    cursor.take(usize_of(u64::from(compression_len))?)?;
    let compressed_size = usize_of(cursor.u64()?)?;
    let header_len = cursor.pos;
    cursor.take(compressed_size)?;
    Ok(header_len + compressed_size)
}

fn usize_of(value: u64) -> Result<usize, RecordError> {
    usize::try_from(value).map_err(|_| RecordError::TooLong(value))
}

struct Cursor<'a> {
    bytes: &'a [u8],
    pos: usize,
    what: &'static str,
}

impl<'a> Cursor<'a> {
    fn new(bytes: &'a [u8], what: &'static str) -> Self {
        Self {
            bytes,
            pos: 0,
            what,
        }
    }

    fn take(&mut self, len: usize) -> Result<&'a [u8], RecordError> {
        let end = self
            .pos
            .checked_add(len)
            .filter(|end| *end <= self.bytes.len())
            .ok_or(RecordError::RunsPast {
                what: self.what,
                len,
                pos: self.pos,
                total: self.bytes.len(),
            })?;
        let slice = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(slice)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], RecordError> {
        let mut out = [0; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    fn u16(&mut self) -> Result<u16, RecordError> {
        Ok(u16::from_le_bytes(self.array()?))
    }

    fn u32(&mut self) -> Result<u32, RecordError> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    fn u64(&mut self) -> Result<u64, RecordError> {
        Ok(u64::from_le_bytes(self.array()?))
    }

    fn string(&mut self) -> Result<String, RecordError> {
        let len = usize_of(u64::from(self.u32()?))?;
        let bytes = self.take(len)?;
        String::from_utf8(bytes.to_vec()).map_err(|_| RecordError::NotUtf8 { what: self.what })
    }

    fn string_map(&mut self) -> Result<StringMap, RecordError> {
        let len = usize_of(u64::from(self.u32()?))?;
        let mut entries = Cursor::new(self.take(len)?, self.what);
        let mut map = BTreeMap::new();
        while entries.pos < entries.bytes.len() {
            let key = entries.string()?;
            let value = entries.string()?;
            if map.insert(key, value).is_some() {
                return Err(RecordError::RepeatedKey { what: self.what });
            }
        }
        Ok(map)
    }

    fn rest(&mut self) -> &'a [u8] {
        let rest = &self.bytes[self.pos..];
        self.pos = self.bytes.len();
        rest
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn string(out: &mut Vec<u8>, s: &str) {
        out.extend((s.len() as u32).to_le_bytes());
        out.extend(s.as_bytes());
    }

    #[test]
    fn parses_a_channel_and_rejects_every_shorter_cut() {
        let mut body = Vec::new();
        body.extend(3u16.to_le_bytes());
        body.extend(1u16.to_le_bytes());
        string(&mut body, "/arm/joint_state");
        string(&mut body, "json");
        let mut map = Vec::new();
        string(&mut map, "rig");
        string(&mut map, "arm");
        body.extend((map.len() as u32).to_le_bytes());
        body.extend(&map);
        let parsed = channel(&body).expect("the channel record parses");
        assert_eq!(parsed.id, 3);
        assert_eq!(parsed.topic, "/arm/joint_state");
        assert_eq!(parsed.metadata.get("rig").map(String::as_str), Some("arm"));
        for cut in 0..body.len() {
            assert!(channel(&body[..cut]).is_err(), "cut at {cut}");
        }
    }

    #[test]
    fn a_huge_declared_length_is_an_error_not_an_allocation() {
        let mut body = vec![0u8; 4];
        body.extend(u32::MAX.to_le_bytes());
        body.extend(b"abc");
        assert!(channel(&body).is_err());
        assert!(metadata(&u32::MAX.to_le_bytes()).is_err());
        let mut chunk = vec![0u8; 28];
        chunk.extend(0u32.to_le_bytes());
        chunk.extend(u64::MAX.to_le_bytes());
        assert!(chunk_len_without_padding(&chunk).is_err());
    }
}
