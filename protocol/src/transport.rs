//! Reliable delivery of message blocks over a lossy byte link, as Klipper's
//! host and MCUs do it.
//!
//! - [`Deframer`] turns a byte stream into blocks, resynchronising after
//!   garbage: on any framing error it drops bytes through the next sync byte
//!   (`0x7e`) and continues there.
//! - [`HostLink`] is the sending side: it numbers blocks (4 bits on the wire,
//!   64 bits inside), keeps at most [`MAX_PENDING_BLOCKS`] unacknowledged and
//!   within the MCU's receive window, and retransmits them all after a
//!   timeout estimated from measured round trips (RFC 6298 as Klipper applies
//!   it) or at once on a nak (a repeated ack).
//! - [`McuLink`] is the receiving side: it delivers each in-order block once,
//!   acknowledges it, and answers an out-of-order block with a nak.
//!
//! Acks are blocks whose sequence byte names the next block expected; an
//! empty block (5 bytes) is a pure ack. Times are in microseconds.

use crate::block::{self, BlockError, MAX_LEN, MIN_LEN, SEQ_MASK, SYNC};

/// Most blocks sent and not yet acknowledged.
pub const MAX_PENDING_BLOCKS: usize = 12;
/// Shortest retransmission timeout, µs.
pub const MIN_RTO_US: u32 = 25_000;
/// Longest retransmission timeout, µs.
pub const MAX_RTO_US: u32 = 5_000_000;
/// Receive window assumed when the MCU does not state one, in bytes.
pub const DEFAULT_RECEIVE_WINDOW: usize = 192;

/// What [`Deframer::push`] found.
#[derive(Debug, PartialEq, Eq)]
pub enum Frame<'a> {
    /// A valid block: its sequence number (4 bits) and payload.
    Block {
        /// Sequence number, 0..=15.
        seq: u8,
        /// Payload bytes.
        payload: &'a [u8],
    },
    /// Bytes dropped while resynchronising.
    Garbage(usize),
}

/// Splits a byte stream into blocks. Holds at most one block.
#[derive(Debug, Clone)]
pub struct Deframer {
    buf: [u8; MAX_LEN],
    len: usize,
    need_sync: bool,
}

impl Default for Deframer {
    fn default() -> Self {
        Self::new()
    }
}

impl Deframer {
    /// A deframer expecting a block start.
    pub const fn new() -> Self {
        Self {
            buf: [0; MAX_LEN],
            len: 0,
            need_sync: false,
        }
    }

    /// Feeds bytes; calls `on_frame` for each block or run of garbage.
    pub fn push(&mut self, bytes: &[u8], mut on_frame: impl FnMut(Frame<'_>)) {
        for &byte in bytes {
            self.push_byte(byte, &mut on_frame);
        }
    }

    fn push_byte(&mut self, byte: u8, on_frame: &mut impl FnMut(Frame<'_>)) {
        if self.need_sync {
            if byte == SYNC {
                self.need_sync = false;
            }
            on_frame(Frame::Garbage(1));
            return;
        }
        // `check` leaves less than a block buffered, so there is room.
        if let Some(slot) = self.buf.get_mut(self.len) {
            *slot = byte;
            self.len += 1;
        }
        self.check(on_frame);
    }

    /// The bytes buffered.
    fn buffered(&self) -> &[u8] {
        self.buf.get(..self.len).unwrap_or_default()
    }

    /// Examines the buffered bytes after each arrival: every complete
    /// block among them goes out at once (after a resynchronisation the
    /// buffer may hold several, and the last of them must not wait for
    /// the next byte from the peer, which may never come).
    fn check(&mut self, on_frame: &mut impl FnMut(Frame<'_>)) {
        loop {
            match block::parse(self.buffered()) {
                Ok(found) => {
                    let n = found.wire_len();
                    on_frame(Frame::Block {
                        seq: found.seq,
                        payload: found.payload,
                    });
                    self.buf.copy_within(n..self.len, 0);
                    self.len -= n;
                    if self.len == 0 {
                        return;
                    }
                    continue;
                }
                Err(BlockError::Incomplete) => {
                    // The sequence byte is checked as soon as it arrives.
                    if self.len < 2 || self.buf[1] & !SEQ_MASK == block::SEQ_DEST {
                        return;
                    }
                }
                Err(_) => {}
            }
            // Framing error: drop through the first sync byte in the buffer
            // (a lone sync before a block, as retransmissions send, costs one
            // byte), then look at what remains.
            match self.buffered().iter().position(|&b| b == SYNC) {
                Some(at) => {
                    on_frame(Frame::Garbage(at + 1));
                    self.buf.copy_within(at + 1..self.len, 0);
                    self.len -= at + 1;
                    if self.len == 0 {
                        return;
                    }
                }
                None => {
                    on_frame(Frame::Garbage(self.len));
                    self.len = 0;
                    self.need_sync = true;
                    return;
                }
            }
        }
    }
}

/// Why [`HostLink::send`] refused a payload.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SendError {
    /// Too many blocks or bytes await acknowledgement; retry after acks.
    WindowFull,
    /// The payload does not fit one block.
    TooLarge,
}

/// The host side of a link: sequencing, flow control and retransmission.
#[derive(Debug, Clone)]
pub struct HostLink {
    /// Sequence number of the next block to send.
    send_seq: u64,
    /// Sequence number the peer expects next (everything below is acked).
    receive_seq: u64,
    /// Highest sequence number carried by an empty (ack) block so far.
    last_ack_seq: u64,
    /// Naks at or below this sequence number are ignored.
    ignore_nak_seq: u64,
    /// `send_seq` at the last retransmission.
    retransmit_seq: u64,
    /// Block whose ack will give an RTT sample (0: none pending).
    rtt_sample_seq: u64,
    srtt_us: u32,
    rttvar_us: u32,
    rto_us: u32,
    /// The timeout the round-trip estimate gives, before any backoff, µs.
    base_rto_us: u32,
    /// A nak behind a retransmission may still cut the timeout short
    /// (once per acknowledgement that makes progress).
    early_retry: bool,
    /// Unacknowledged blocks, oldest first, with their send times; each
    /// block is as long as its first byte says (see [`framed`]).
    sent: heapless::Deque<([u8; MAX_LEN], u64), MAX_PENDING_BLOCKS>,
    sent_bytes: usize,
    last_ack_bytes: usize,
    receive_window: usize,
    /// When to retransmit, µs (None: nothing outstanding).
    retransmit_at: Option<u64>,
    deframer: Deframer,
    /// Counters for diagnostics.
    pub stats: LinkStats,
}

/// Byte and event counters of a link.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Bytes written, retransmissions included.
    pub bytes_written: u64,
    /// Bytes written again by retransmissions.
    pub bytes_retransmitted: u64,
    /// Bytes dropped while resynchronising.
    pub bytes_invalid: u64,
    /// Retransmissions after a timeout.
    pub timeouts: u32,
    /// Retransmissions after a nak.
    pub naks: u32,
}

impl Default for HostLink {
    fn default() -> Self {
        Self::new(DEFAULT_RECEIVE_WINDOW)
    }
}

impl HostLink {
    /// A fresh link; `receive_window` is the MCU's receive buffer in bytes.
    pub fn new(receive_window: usize) -> Self {
        Self {
            send_seq: 1,
            receive_seq: 1,
            last_ack_seq: 0,
            ignore_nak_seq: 0,
            retransmit_seq: 0,
            rtt_sample_seq: 0,
            srtt_us: 0,
            rttvar_us: 0,
            rto_us: MIN_RTO_US,
            base_rto_us: MIN_RTO_US,
            early_retry: true,
            sent: heapless::Deque::new(),
            sent_bytes: 0,
            last_ack_bytes: 0,
            receive_window,
            retransmit_at: None,
            deframer: Deframer::new(),
            stats: LinkStats::default(),
        }
    }

    /// Current retransmission timeout, µs.
    pub fn rto_us(&self) -> u32 {
        self.rto_us
    }

    /// Blocks sent and not yet acknowledged.
    pub fn unacknowledged(&self) -> usize {
        self.sent.len()
    }

    /// True if a block of `payload_len` bytes may be sent now.
    pub fn can_send(&self, payload_len: usize) -> bool {
        if self.sent.is_full() {
            return false;
        }
        let mut in_flight = self.sent_bytes + payload_len + MIN_LEN;
        if self.last_ack_seq < self.receive_seq {
            in_flight += self.last_ack_bytes;
        }
        self.sent.is_empty() || in_flight <= self.receive_window
    }

    /// Frames `payload` as the next block, remembers it for retransmission
    /// and returns the bytes to write.
    pub fn send(&mut self, payload: &[u8], now_us: u64) -> Result<&[u8], SendError> {
        if payload.len() > block::MAX_PAYLOAD {
            return Err(SendError::TooLarge);
        }
        if !self.can_send(payload.len()) {
            return Err(SendError::WindowFull);
        }
        let mut frame = [0u8; MAX_LEN];
        let n = block::encode(self.send_seq as u8, payload, &mut frame)
            .map_err(|_| SendError::TooLarge)?;
        let first = self.sent.is_empty();
        self.sent
            .push_back((frame, now_us))
            .map_err(|_| SendError::WindowFull)?;
        if first {
            self.retransmit_at = Some(now_us.saturating_add(u64::from(self.rto_us)));
        }
        if self.rtt_sample_seq == 0 {
            self.rtt_sample_seq = self.send_seq;
        }
        self.send_seq += 1;
        self.sent_bytes += n;
        self.stats.bytes_written += n as u64;
        Ok(self.sent.back().map_or(&[], |(f, _)| framed(f)))
    }

    /// Feeds bytes from the MCU; calls `on_payload` with the payload of each
    /// data block (responses), in arrival order.
    pub fn receive(&mut self, bytes: &[u8], now_us: u64, mut on_payload: impl FnMut(&[u8])) {
        self.receive_dyn(bytes, now_us, &mut on_payload);
    }

    /// [`Self::receive`]'s body, compiled once for every caller's
    /// `on_payload` (the deframer and the ack handling are not small).
    fn receive_dyn(&mut self, bytes: &[u8], now_us: u64, on_payload: &mut dyn FnMut(&[u8])) {
        let mut deframer = core::mem::take(&mut self.deframer);
        deframer.push(bytes, |frame| match frame {
            Frame::Garbage(n) => self.stats.bytes_invalid += n as u64,
            Frame::Block { seq, payload } => {
                if self.handle_block(seq, payload.is_empty(), now_us) && !payload.is_empty() {
                    on_payload(payload);
                }
            }
        });
        self.deframer = deframer;
    }

    /// Applies a block's acknowledgement; false if the block is bogus.
    fn handle_block(&mut self, wire_seq: u8, is_ack_only: bool, now_us: u64) -> bool {
        let delta = u64::from(wire_seq.wrapping_sub(self.receive_seq as u8) & SEQ_MASK);
        let rseq = self.receive_seq + delta;
        if rseq != self.receive_seq {
            if rseq > self.send_seq && !self.connecting() {
                // Acknowledges a block never sent: not from this connection.
                return false;
            }
            self.acknowledge(rseq, now_us);
        }
        if is_ack_only {
            if self.last_ack_seq < rseq {
                self.last_ack_seq = rseq;
            } else if rseq > self.ignore_nak_seq && !self.sent.is_empty() {
                // A repeated ack is a nak: retransmit now.
                self.retransmit_at = Some(0);
            } else if !self.sent.is_empty() && self.early_retry {
                // A nak behind a retransmission: the peer may be answering
                // blocks it had already (its acks will follow within a
                // round trip), or a retransmitted block was lost again.
                // klippy waits out its whole timeout; here the timeout is
                // cut to a round trip, which the acks of the first case
                // put off again; once until the peer takes a block (the
                // retransmission itself may take longer than a round trip
                // on the wire, and its naks must not retrigger it).
                self.early_retry = false;
                let soon = now_us.saturating_add(u64::from(self.nak_hold_off_us()));
                self.retransmit_at = self.retransmit_at.map(|at| at.min(soon));
            }
        }
        true
    }

    /// How long a nak that may come from a retransmission's duplicates
    /// waits for acks before it counts, µs: the smoothed round trip (it
    /// includes the blocks' time on the wire), at least a millisecond.
    fn nak_hold_off_us(&self) -> u32 {
        // (Not `clamp`, which would bring a panic path for a timeout
        // below a millisecond, which MIN_RTO_US rules out.)
        (self.srtt_us / 8 * 8).max(1_000).min(self.rto_us)
    }

    /// True until the MCU has acknowledged anything: its sequence number
    /// is not known yet. A Klipper MCU starts expecting block 0 and keeps
    /// its count across host connections, so its first ack (or nak) may
    /// name any block; the link adopts it, as klippy's serial queue does.
    fn connecting(&self) -> bool {
        self.receive_seq == 1
    }

    /// Drops blocks below `rseq` and updates the round-trip estimate. An
    /// ack past every block sent (only while [`Self::connecting`]) makes
    /// `rseq` the next block to send; the blocks sent before were not
    /// taken and are dropped, so their senders must retry.
    fn acknowledge(&mut self, rseq: u64, now_us: u64) {
        let mut acked_sent_at = None;
        while self.receive_seq < rseq {
            let Some((frame, sent_at)) = self.sent.pop_front() else {
                self.send_seq = rseq;
                break;
            };
            let len = framed(&frame).len();
            self.sent_bytes -= len;
            self.last_ack_bytes = len;
            self.receive_seq += 1;
            acked_sent_at = Some(sent_at);
        }
        self.receive_seq = rseq;
        if acked_sent_at.is_some() {
            // The peer takes blocks again: a timeout's backoff ends. (klippy
            // keeps it until a round trip can be timed, which under steady
            // damage never comes: blocks sent after a retransmission that
            // lost one are answered by naks it ignores, so each timeout
            // doubles the last, to seconds, and steps arrive too late.)
            self.rto_us = self.base_rto_us;
            self.early_retry = true;
        }
        if self.rtt_sample_seq != 0 && rseq > self.rtt_sample_seq {
            if let Some(sent_at) = acked_sent_at {
                self.sample_rtt(now_us.saturating_sub(sent_at));
            }
            self.rtt_sample_seq = 0;
        }
        self.retransmit_at =
            (!self.sent.is_empty()).then(|| now_us.saturating_add(u64::from(self.rto_us)));
    }

    /// RFC 6298 smoothing; the first sample starts high (x10), as Klipper does.
    fn sample_rtt(&mut self, rtt_us: u64) {
        let d = u32::try_from(rtt_us).unwrap_or(u32::MAX);
        if self.srtt_us == 0 {
            self.rttvar_us = d / 2;
            self.srtt_us = d.saturating_mul(10);
        } else {
            self.rttvar_us =
                ((3 * u64::from(self.rttvar_us) + u64::from(self.srtt_us.abs_diff(d))) / 4) as u32;
            self.srtt_us = ((7 * u64::from(self.srtt_us) + u64::from(d)) / 8) as u32;
        }
        let rttvar4 = self.rttvar_us.saturating_mul(4).max(1_000);
        self.base_rto_us = self
            .srtt_us
            .saturating_add(rttvar4)
            .clamp(MIN_RTO_US, MAX_RTO_US);
        self.rto_us = self.base_rto_us;
    }

    /// If a retransmission is due, writes a sync byte and every
    /// unacknowledged block into `out` and returns the length written.
    /// `out` needs `1 + MAX_PENDING_BLOCKS * MAX_LEN` bytes at most.
    pub fn poll(&mut self, now_us: u64, out: &mut [u8]) -> Option<usize> {
        let due = self.retransmit_at?;
        if now_us < due || self.sent.is_empty() {
            return None;
        }
        let mut n = 0;
        let mut put = |bytes: &[u8]| {
            let dest = out.get_mut(n..n + bytes.len())?;
            dest.copy_from_slice(bytes);
            n += bytes.len();
            Some(())
        };
        put(&[SYNC])?;
        for (frame, _) in &self.sent {
            put(framed(frame))?;
        }
        if due == 0 {
            // After a nak: a second nak for this retransmission is honoured,
            // a third is not.
            self.stats.naks += 1;
            self.ignore_nak_seq = if self.receive_seq < self.retransmit_seq {
                self.retransmit_seq
            } else {
                self.receive_seq
            };
        } else {
            self.stats.timeouts += 1;
            self.rto_us = self.rto_us.saturating_mul(2).min(MAX_RTO_US);
            self.ignore_nak_seq = self.send_seq;
        }
        self.retransmit_seq = self.send_seq;
        self.rtt_sample_seq = 0;
        self.stats.bytes_written += n as u64;
        self.stats.bytes_retransmitted += n as u64;
        self.retransmit_at = Some(now_us.saturating_add(u64::from(self.rto_us)));
        Some(n)
    }
}

/// The block stored in `frame` (its length is its first byte).
fn framed(frame: &[u8; MAX_LEN]) -> &[u8] {
    frame.get(..usize::from(frame[0])).unwrap_or(frame)
}

/// The MCU side of a link: in-order delivery, acks and naks.
#[derive(Debug, Clone)]
pub struct McuLink {
    /// Sequence number of the next block expected (4 bits).
    next_seq: u8,
    deframer: Deframer,
}

impl Default for McuLink {
    fn default() -> Self {
        Self::new()
    }
}

/// What an [`McuLink`] must answer after receiving bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reply {
    /// Nothing (only garbage or nothing complete arrived).
    None,
    /// Acknowledge: send a block (empty, or carrying responses) with this
    /// sequence number.
    Ack(u8),
}

impl McuLink {
    /// A link expecting the host's first block (sequence 1).
    pub const fn new() -> Self {
        Self {
            next_seq: 1,
            deframer: Deframer::new(),
        }
    }

    /// Feeds bytes from the host; calls `on_payload` once per in-order block
    /// and returns what to answer. Out-of-order blocks and garbage are
    /// answered with the expected sequence number, which the host reads as
    /// a nak.
    pub fn receive(&mut self, bytes: &[u8], mut on_payload: impl FnMut(&[u8])) -> Reply {
        let mut reply = Reply::None;
        let next_seq = &mut self.next_seq;
        self.deframer.push(bytes, |frame| match frame {
            Frame::Block { seq, payload } => {
                if seq == *next_seq {
                    *next_seq = (*next_seq + 1) & SEQ_MASK;
                    on_payload(payload);
                }
                reply = Reply::Ack(*next_seq);
            }
            Frame::Garbage(_) => {}
        });
        reply
    }

    /// Frames a reply block carrying `payload` (empty for a pure ack).
    pub fn frame_reply(
        &self,
        payload: &[u8],
        out: &mut [u8; MAX_LEN],
    ) -> Result<usize, block::PayloadTooLarge> {
        block::encode(self.next_seq, payload, out)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;
    use std::vec::Vec;

    fn frames(bytes: &[u8]) -> Vec<Result<(u8, Vec<u8>), usize>> {
        let mut d = Deframer::new();
        let mut out = Vec::new();
        d.push(bytes, |f| match f {
            Frame::Block { seq, payload } => out.push(Ok((seq, payload.to_vec()))),
            Frame::Garbage(n) => out.push(Err(n)),
        });
        out
    }

    fn block_bytes(seq: u8, payload: &[u8]) -> Vec<u8> {
        let mut b = [0u8; MAX_LEN];
        let n = block::encode(seq, payload, &mut b).expect("fits");
        b[..n].to_vec()
    }

    #[test]
    fn deframer_splits_back_to_back_blocks() {
        let mut stream = block_bytes(1, b"ab");
        stream.extend(block_bytes(2, b""));
        stream.extend(block_bytes(3, b"xyz"));
        assert_eq!(
            frames(&stream),
            [
                Ok((1, b"ab".to_vec())),
                Ok((2, Vec::new())),
                Ok((3, b"xyz".to_vec()))
            ]
        );
    }

    #[test]
    fn deframer_skips_a_lone_sync_and_resyncs_after_garbage() {
        let mut stream = vec![SYNC];
        stream.extend(block_bytes(1, b"ab"));
        stream.extend([0x30, 0x31, 0x99, SYNC]);
        stream.extend(block_bytes(2, b"cd"));
        let got = frames(&stream);
        let blocks: Vec<_> = got
            .iter()
            .filter_map(|f| f.as_ref().ok().cloned())
            .collect();
        assert_eq!(blocks, [(1, b"ab".to_vec()), (2, b"cd".to_vec())]);
        let dropped: usize = got.iter().filter_map(|f| f.as_ref().err()).sum();
        assert_eq!(dropped, 5);
    }

    #[test]
    fn blocks_found_behind_a_damaged_length_go_out_without_waiting() {
        // A damaged length byte makes the deframer wait for a long block;
        // the acks behind it are complete once those bytes are in, and
        // all of them must go out then, not one per later byte.
        let mut stream = block_bytes(1, b"");
        stream[0] = MAX_LEN as u8;
        let acks: Vec<u8> = (2..14).flat_map(|seq| block_bytes(seq, b"")).collect();
        stream.extend(&acks);
        let blocks: Vec<u8> = frames(&stream)
            .iter()
            .filter_map(|f| f.as_ref().ok().map(|(seq, _)| *seq))
            .collect();
        assert_eq!(blocks, (2..14).collect::<Vec<u8>>());
    }

    #[test]
    fn deframer_recovers_from_a_corrupted_block() {
        let mut bad = block_bytes(1, b"hello");
        bad[3] ^= 0x40;
        let mut stream = bad.clone();
        stream.extend(block_bytes(2, b"ok"));
        let got = frames(&stream);
        assert_eq!(got.last(), Some(&Ok((2, b"ok".to_vec()))));
        assert!(
            got.iter()
                .all(|f| f.as_ref().map_or(true, |(seq, _)| *seq == 2))
        );
    }

    #[test]
    fn host_waits_for_acks_when_twelve_blocks_are_out() {
        let mut host = HostLink::new(usize::MAX);
        for i in 0..MAX_PENDING_BLOCKS {
            host.send(&[i as u8], 0).expect("room");
        }
        assert_eq!(host.send(b"x", 0), Err(SendError::WindowFull));
        host.receive(&block_bytes(4, b""), 10, |_| {});
        assert_eq!(host.unacknowledged(), MAX_PENDING_BLOCKS - 3);
        host.send(b"x", 10).expect("room after acks");
    }

    #[test]
    fn host_respects_the_receive_window_in_bytes() {
        let mut host = HostLink::new(DEFAULT_RECEIVE_WINDOW);
        let payload = [0u8; block::MAX_PAYLOAD];
        let mut sent = 0;
        while host.send(&payload, 0).is_ok() {
            sent += 1;
        }
        assert_eq!(sent, DEFAULT_RECEIVE_WINDOW / MAX_LEN);
    }

    #[test]
    fn timeout_retransmits_everything_and_doubles_the_rto() {
        let mut host = HostLink::default();
        let first = host.send(b"one", 0).expect("room").to_vec();
        let second = host.send(b"two", 0).expect("room").to_vec();
        let mut out = [0u8; 1 + MAX_PENDING_BLOCKS * MAX_LEN];
        assert_eq!(host.poll(u64::from(MIN_RTO_US) - 1, &mut out), None);
        let n = host.poll(u64::from(MIN_RTO_US), &mut out).expect("due");
        let mut expected = vec![SYNC];
        expected.extend(&first);
        expected.extend(&second);
        assert_eq!(&out[..n], &expected[..]);
        assert_eq!(host.rto_us(), 2 * MIN_RTO_US);
        assert_eq!(host.stats.timeouts, 1);
    }

    #[test]
    fn a_timeouts_backoff_ends_when_the_peer_takes_blocks_again() {
        let mut host = HostLink::default();
        host.send(b"one", 0).expect("room");
        host.send(b"two", 0).expect("room");
        let mut out = [0u8; 1 + MAX_PENDING_BLOCKS * MAX_LEN];
        let mut now = 0;
        for _ in 0..3 {
            now += u64::from(host.rto_us());
            host.poll(now, &mut out).expect("due");
        }
        assert_eq!(host.rto_us(), 8 * MIN_RTO_US);
        // The first block is acknowledged (the second was lost again).
        host.receive(&block_bytes(2, b""), now + 1, |_| {});
        assert_eq!(host.unacknowledged(), 1);
        assert_eq!(host.rto_us(), MIN_RTO_US);
    }

    #[test]
    fn a_nak_behind_a_timeout_retransmits_after_a_round_trip_not_a_timeout() {
        let mut host = HostLink::default();
        for p in [b"a", b"b", b"c"] {
            host.send(p, 0).expect("room");
        }
        let mut out = [0u8; 1 + MAX_PENDING_BLOCKS * MAX_LEN];
        let now = u64::from(MIN_RTO_US);
        host.poll(now, &mut out).expect("timeout");
        // The first block gets through, the second is lost again: an ack,
        // then the peer's nak for the third.
        host.receive(&block_bytes(2, b""), now + 100, |_| {});
        host.receive(&block_bytes(2, b""), now + 200, |_| {});
        assert_eq!(host.poll(now + 200 + 999, &mut out), None);
        assert!(host.poll(now + 200 + 1_000, &mut out).is_some());
    }

    #[test]
    fn a_repeated_ack_is_a_nak_and_retransmits_at_once() {
        let mut host = HostLink::default();
        for p in [b"a", b"b", b"c"] {
            host.send(p, 0).expect("room");
        }
        host.receive(&block_bytes(2, b""), 100, |_| {}); // acks block 1
        let mut out = [0u8; 1 + MAX_PENDING_BLOCKS * MAX_LEN];
        assert_eq!(host.poll(101, &mut out), None);
        host.receive(&block_bytes(2, b""), 102, |_| {}); // same ack again: nak
        assert!(host.poll(103, &mut out).is_some());
        assert_eq!(host.stats.naks, 1);
        // The same nak repeated for the same retransmission is ignored.
        host.receive(&block_bytes(2, b""), 104, |_| {});
        assert_eq!(host.poll(105, &mut out), None);
    }

    #[test]
    fn rto_follows_measured_round_trips() {
        let mut host = HostLink::default();
        for i in 0..20u64 {
            let t = i * 10_000;
            host.send(b"p", t).expect("room");
            host.receive(
                &block_bytes((i + 2) as u8 & SEQ_MASK, b""),
                t + 2_000,
                |_| {},
            );
        }
        // A steady 2 ms round trip converges to the 25 ms floor.
        assert_eq!(host.rto_us(), MIN_RTO_US);
        let mut slow = HostLink::default();
        slow.send(b"p", 0).expect("room");
        slow.receive(&block_bytes(2, b""), 300_000, |_| {});
        // First sample d = 0.3 s: srtt = 10 d = 3 s, rttvar = d / 2, so the
        // timeout is 3 s + 4 x 0.15 s.
        assert_eq!(slow.rto_us(), 3_600_000);
        let mut slower = HostLink::default();
        slower.send(b"p", 0).expect("room");
        slower.receive(&block_bytes(2, b""), 1_000_000, |_| {});
        assert_eq!(slower.rto_us(), MAX_RTO_US);
    }

    #[test]
    fn clock_values_near_the_end_of_time_do_not_overflow() {
        let mut host = HostLink::default();
        host.send(b"a", u64::MAX - 1).expect("room");
        let mut out = [0u8; 1 + MAX_PENDING_BLOCKS * MAX_LEN];
        assert!(host.poll(u64::MAX, &mut out).is_some());
        host.receive(&block_bytes(2, b""), u64::MAX, |_| {});
        assert_eq!(host.unacknowledged(), 0);
    }

    #[test]
    fn acks_for_blocks_never_sent_are_ignored_once_connected() {
        let mut host = HostLink::default();
        host.send(b"a", 0).expect("room");
        host.receive(&block_bytes(2, b""), 1, |_| {});
        host.send(b"b", 2).expect("room");
        host.receive(&block_bytes(9, b""), 3, |_| {});
        assert_eq!(host.unacknowledged(), 1);
    }

    #[test]
    fn the_first_ack_sets_the_sequence_of_a_fresh_or_reused_mcu() {
        // A freshly started Klipper MCU expects block 0 and naks block 1
        // with sequence 0; one still counting from an earlier host naks
        // with its own number. Either way the next block carries it.
        for mcu_expects in [0u8, 5, 15] {
            let mut host = HostLink::default();
            host.send(b"identify", 0).expect("room");
            host.receive(&block_bytes(mcu_expects, b""), 1, |_| {});
            let wire_seq = host.send(b"identify", 2).expect("room")[1] & SEQ_MASK;
            assert_eq!(wire_seq, mcu_expects);
            // The block it acknowledges next is taken as an ack.
            host.receive(&block_bytes((mcu_expects + 1) & SEQ_MASK, b""), 3, |_| {});
            assert_eq!(host.unacknowledged(), 0);
        }
    }

    #[test]
    fn mcu_delivers_in_order_once_and_naks_gaps() {
        let mut mcu = McuLink::new();
        let mut got = Vec::new();
        assert_eq!(
            mcu.receive(&block_bytes(1, b"a"), |p| got.push(p.to_vec())),
            Reply::Ack(2)
        );
        assert_eq!(
            mcu.receive(&block_bytes(3, b"c"), |p| got.push(p.to_vec())),
            Reply::Ack(2)
        );
        assert_eq!(
            mcu.receive(&block_bytes(1, b"a"), |p| got.push(p.to_vec())),
            Reply::Ack(2)
        );
        assert_eq!(
            mcu.receive(&block_bytes(2, b"b"), |p| got.push(p.to_vec())),
            Reply::Ack(3)
        );
        assert_eq!(got, [b"a".to_vec(), b"b".to_vec()]);
    }
}
