//! The record channel between the streaming cycle and the log's writer thread: a
//! preallocated single-producer single-consumer ring (`rtrb`) of 64-bit words, each
//! [`LogRecord`] packed into only as many words as its axes need. A `LogRecord` is sized for
//! [`MAX_AXES`] (about 530 bytes); a six-axis record packs into 16 words (128 bytes), so the
//! same seconds of buffer take a quarter of the memory (issue 18: many cells, one daemon).
//! Owns the packing and the ring's ends; must not encode, write files or wait: pushing never
//! allocates, never locks and never blocks.

use super::recorder::LogRecord;
use crate::protocol::{AxisValues, MAX_AXES};
use rtrb::{Consumer, Producer, RingBuffer};

/// Words before a record's values: kind and seq, t, late_us, and the two value counts.
const HEADER_WORDS: usize = 4;
/// The longest record: a header and both value lists at [`MAX_AXES`].
const MAX_WORDS: usize = HEADER_WORDS + 2 * MAX_AXES;
/// Marks a state in the first word (above the 32 bits of seq).
const STATE_FLAG: u64 = 1 << 32;

/// Words a record of `axes` values per list takes.
pub(super) fn words_per_record(axes: usize) -> usize {
    HEADER_WORDS + 2 * axes.min(MAX_AXES)
}

/// A ring of `records` records of `axes` values per list, its pages written once so the
/// cycle never faults one in (a first touch waits for the memory map whenever another
/// thread changes it: milliseconds late on a loaded machine).
pub(super) fn ring(records: usize, axes: usize) -> (RecordSender, RecordReceiver) {
    let words = records.saturating_mul(words_per_record(axes));
    let (mut producer, mut consumer) = RingBuffer::<u64>::new(words);
    // write_chunk writes every slot (with 0) before handing them out.
    if let Ok(chunk) = producer.write_chunk(words) {
        chunk.commit_all();
    }
    if let Ok(chunk) = consumer.read_chunk(words) {
        chunk.commit_all();
    }
    (RecordSender(producer), RecordReceiver(consumer))
}

/// The cycle's end of the ring.
pub(super) struct RecordSender(Producer<u64>);

impl RecordSender {
    /// Queues `record` whole, or not at all when the ring has no room for it or the writer
    /// thread is gone (then nothing would ever take it: the caller counts it as dropped).
    pub(super) fn try_send(&mut self, record: &LogRecord) -> bool {
        if self.is_closed() {
            return false;
        }
        let mut words = [0u64; MAX_WORDS];
        let used = pack(record, &mut words);
        self.0.push_entire_slice(&words[..used]).is_ok()
    }

    /// The writer thread is gone: nothing sent now would ever be written.
    pub(super) fn is_closed(&self) -> bool {
        self.0.is_abandoned()
    }
}

/// Why the writer thread found no record in the ring.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum NoRecord {
    Empty,
    /// The sender is gone and everything it sent has been taken.
    Closed,
}

/// The writer thread's end of the ring.
pub(super) struct RecordReceiver(Consumer<u64>);

impl RecordReceiver {
    pub(super) fn try_recv(&mut self) -> Result<LogRecord, NoRecord> {
        // Asked before looking: a sender that was gone before the look had sent all it did.
        let abandoned = self.0.is_abandoned();
        let mut words = [0u64; MAX_WORDS];
        if self.0.pop_entire_slice(&mut words[..HEADER_WORDS]).is_err() {
            return Err(if abandoned {
                NoRecord::Closed
            } else {
                NoRecord::Empty
            });
        }
        let values = value_counts(&words);
        let end = HEADER_WORDS + values.0 + values.1;
        // A record goes in whole (one commit), so the rest of it is there.
        if self
            .0
            .pop_entire_slice(&mut words[HEADER_WORDS..end])
            .is_err()
        {
            return Err(NoRecord::Empty);
        }
        Ok(unpack(&words[..end]))
    }
}

/// Writes `record` into `words`; returns how many it took.
fn pack(record: &LogRecord, words: &mut [u64; MAX_WORDS]) -> usize {
    let (first, t, positions, velocities, late_us) = match record {
        LogRecord::Command {
            seq,
            t,
            positions,
            velocities,
            late_us,
        } => (u64::from(*seq), t, positions, velocities, *late_us),
        LogRecord::State {
            seq,
            t,
            positions,
            velocities,
        } => (u64::from(*seq) | STATE_FLAG, t, positions, velocities, 0.0),
    };
    let (p, v) = (positions.as_slice(), velocities.as_slice());
    words[0] = first;
    words[1] = t.to_bits();
    words[2] = u64::from(late_us.to_bits());
    words[3] = (p.len() as u64) << 8 | v.len() as u64;
    let mut end = HEADER_WORDS;
    for value in p.iter().chain(v) {
        words[end] = value.to_bits();
        end += 1;
    }
    end
}

/// The two value counts in a record's header, each capped at [`MAX_AXES`].
fn value_counts(words: &[u64]) -> (usize, usize) {
    let count = |n: u64| ((n & 0xff) as usize).min(MAX_AXES);
    (count(words[3] >> 8), count(words[3]))
}

fn unpack(words: &[u64]) -> LogRecord {
    let seq = (words[0] & u64::from(u32::MAX)) as u32;
    let t = f64::from_bits(words[1]);
    let (p, v) = value_counts(words);
    let values = |from: usize, n: usize| {
        let mut out = AxisValues::zeros(n);
        for (slot, word) in out.as_mut_slice().iter_mut().zip(&words[from..from + n]) {
            *slot = f64::from_bits(*word);
        }
        out
    };
    let positions = values(HEADER_WORDS, p);
    let velocities = values(HEADER_WORDS + p, v);
    if words[0] & STATE_FLAG == 0 {
        LogRecord::Command {
            seq,
            t,
            positions,
            velocities,
            late_us: f32::from_bits(words[2] as u32),
        }
    } else {
        LogRecord::State {
            seq,
            t,
            positions,
            velocities,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values(from: f64, n: usize) -> AxisValues {
        let v: Vec<f64> = (0..n).map(|i| from + i as f64 * 0.25).collect();
        AxisValues::from_slice(&v).expect("at most MAX_AXES values")
    }

    #[test]
    fn records_come_out_bit_for_bit_in_order() {
        let (mut tx, mut rx) = ring(4, 6);
        let command = LogRecord::Command {
            seq: u32::MAX,
            t: -0.0,
            positions: values(f64::NAN, 6),
            velocities: values(1.5, 6),
            late_us: 12.5,
        };
        let state = LogRecord::State {
            seq: 7,
            t: 0.028,
            positions: values(-3.0, MAX_AXES),
            velocities: values(2.0, 0),
        };
        assert!(tx.try_send(&command) && tx.try_send(&state));
        for sent in [command, state] {
            let got = rx.try_recv().expect("a record was sent");
            // NaN != NaN: compare the packed words instead.
            let (mut a, mut b) = ([0; MAX_WORDS], [0; MAX_WORDS]);
            assert_eq!(pack(&sent, &mut a), pack(&got, &mut b));
            assert_eq!(a, b);
        }
        assert_eq!(rx.try_recv().err(), Some(NoRecord::Empty));
        drop(tx);
        assert_eq!(rx.try_recv().err(), Some(NoRecord::Closed));
    }

    #[test]
    fn a_full_ring_refuses_whole_records() {
        let (mut tx, mut rx) = ring(2, 6);
        let record = LogRecord::Command {
            seq: 1,
            t: 0.0,
            positions: values(0.0, 6),
            velocities: values(0.0, 6),
            late_us: 0.0,
        };
        assert!(tx.try_send(&record) && tx.try_send(&record));
        assert!(!tx.try_send(&record));
        assert!(rx.try_recv().is_ok());
        assert!(tx.try_send(&record));
    }
}
