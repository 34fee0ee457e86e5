//! The TMC2208/TMC2209 single-wire UART, bit-banged from a timer
//! interrupt as Klipper's MCU does it (its `tmcuart`): the request's bits
//! are driven on the pin at the bit rate, then the pin is released and
//! the line sampled for the reply.
//!
//! [`SoftUart`] is the interrupt's state: [`SoftUart::start`] takes a
//! request, and each timer event ([`SoftUart::on_event`]) says what to do
//! with the pin and when the next event is due, relative to when this one
//! was due (so the bit clock does not drift with interrupt latency). The
//! reply is sampled [`OVERSAMPLE`] times per bit; [`SoftUart::reply`]
//! finds each byte's start bit among the samples and reads its bits near
//! their middle, so every byte resynchronises on its own start bit (a
//! driver up to 2 % off our bit rate is read right; a TMC2209 takes its
//! bit rate from our request's sync nibble).
//!
//! A TMC2209 takes the bit rate from the request's sync nibble, latency
//! and all; as Klipper's MCU does, the bits after it go at the bit time
//! the driver will have measured, and the reply is read at it.
//!
//! An event that runs later than its tolerance (another interrupt held it
//! off: a quarter bit while sending, half a sample while receiving) fails
//! the exchange ([`Failure::Late`]): the bits it drove or read could be
//! wrong, so the caller tries again, as after any failed exchange. The
//! exchange still runs its course, as Klipper's MCU never cuts one short:
//! the request goes out whole (a request cut short could leave the
//! driver's receiver mid-datagram, for the next one to complete), and the
//! line stays released for the whole reply (driving it then would fight
//! the driver's output).
//!
//! Line levels: `true` is high. The line idles high (driven high between
//! exchanges, as Klipper leaves it); a byte is a low start bit, 8 data
//! bits least significant first, and a high stop bit.

/// Bit times of one byte on the wire: start bit, 8 data bits, stop bit.
pub const FRAME_BITS: usize = 10;
/// Samples per bit while receiving.
pub const OVERSAMPLE: u32 = 4;
/// Longest request and longest reply, bytes (a register write datagram;
/// a read's reply).
pub const MAX_BYTES: usize = 8;
/// Bit times between the end of the request and the first sample: the
/// line is left to the driver (Klipper waits as long; the driver answers
/// after its SENDDELAY, 8 bit times by default).
pub const TURNAROUND_BITS: u32 = 4;
/// Bit times the reply's first start bit is looked for after that, at
/// most (Klipper's wait).
pub const REPLY_WAIT_BITS: u32 = 64;
/// A request's first byte's low nibble: the sync nibble the driver
/// measures the bit rate on.
const SYNC: u8 = 0x05;
/// The sync nibble's last falling edge, bits after its start bit's.
const SYNC_END: u16 = 4;
/// Bit times recorded after the reply's first start bit beyond its
/// bytes' length: room for a driver a little slower than us, or a pause
/// between its bytes.
const SLACK_BITS: usize = 4;
/// Bit times recorded of a reply of `rx_len` bytes, from its first start
/// bit.
const fn recorded_bits(rx_len: usize) -> usize {
    rx_len * FRAME_BITS + SLACK_BITS
}
/// Samples recorded of the longest reply.
const MAX_SAMPLES: usize = recorded_bits(MAX_BYTES) * OVERSAMPLE as usize;

/// The line's level during bit time `bit` of `bytes` sent back to back:
/// each byte's start bit (low), its 8 data bits least significant first,
/// its stop bit (high); high (idle) past the last.
pub fn wire_level(bytes: &[u8], bit: usize) -> bool {
    match (bytes.get(bit / FRAME_BITS), bit % FRAME_BITS) {
        (None, _) | (_, 9) => true,
        (_, 0) => false,
        (Some(byte), k) => byte >> (k - 1) & 1 != 0,
    }
}

/// Why an exchange failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    /// A request or reply longer than [`MAX_BYTES`], or a bit time too
    /// short to sample.
    TooLong,
    /// An event ran later than its tolerance; nothing it did is trusted.
    Late,
    /// No start bit within [`REPLY_WAIT_BITS`] (no driver answered), or
    /// the line never idled high first.
    NoReply,
    /// A byte of the reply lacks its start or stop bit, or the reply
    /// ended early.
    Framing,
    /// The exchange is not over (or was never started).
    Busy,
}

/// What the interrupt does to the pin at an event.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pin {
    /// Drive the line to this level (a single wire: as an output).
    Drive(bool),
    /// Let go of the line (a single wire: an input, with its pull-up if
    /// configured) for the driver to answer on.
    Release,
    /// Leave it as it is.
    Keep,
}

/// One timer event's outcome.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Event {
    /// What to do with the pin now.
    pub pin: Pin,
    /// When the next event is due, ticks after this one was due; None:
    /// the exchange is over (see [`SoftUart::outcome`]).
    pub next: Option<u32>,
}

/// Where an exchange stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Sending: bit `pos` of the request (counting start and stop bits)
    /// is the next to drive.
    Sending { pos: u16 },
    /// The last stop bit has lasted its bit time: release the line.
    Sent,
    /// Looking for the reply's first start bit: `samples` taken so far;
    /// `idle`: the line has read high.
    Waiting { samples: u16, idle: bool },
    /// Recording the reply: `samples` recorded so far.
    Reading { samples: u16 },
    /// Over.
    Done(Result<(), Failure>),
}

/// One exchange on a TMC UART: the request, then the reply's samples.
#[derive(Debug, Clone)]
pub struct SoftUart {
    phase: Phase,
    /// The request's bytes.
    tx: [u8; MAX_BYTES],
    tx_len: u8,
    /// Bytes of the reply expected (0: a write, no reply).
    rx_len: u8,
    /// One bit time, ticks (a multiple of [`OVERSAMPLE`] is exact); after
    /// the sync nibble, the time the driver measured.
    bit_ticks: u32,
    /// How late the first event began, ticks.
    first_late: u32,
    /// An event of this exchange began later than its tolerance.
    late: bool,
    /// The reply's line levels from its first start bit on, one bit per
    /// sample.
    samples: [u8; MAX_SAMPLES.div_ceil(8)],
}

impl Default for SoftUart {
    fn default() -> Self {
        Self::new()
    }
}

impl SoftUart {
    /// No exchange yet.
    pub const fn new() -> Self {
        Self {
            phase: Phase::Done(Err(Failure::Busy)),
            tx: [0; MAX_BYTES],
            tx_len: 0,
            rx_len: 0,
            bit_ticks: 0,
            first_late: 0,
            late: false,
            samples: [0; MAX_SAMPLES.div_ceil(8)],
        }
    }

    /// Starts an exchange: `tx` sent at one bit per `bit_ticks` ticks,
    /// then `rx_len` bytes of reply read (0: none). The first event (the
    /// first start bit) is due whenever the caller arms its timer.
    pub fn start(&mut self, tx: &[u8], rx_len: usize, bit_ticks: u32) -> Result<(), Failure> {
        if tx.len() > MAX_BYTES || rx_len > MAX_BYTES || bit_ticks < OVERSAMPLE {
            return Err(Failure::TooLong);
        }
        self.tx[..tx.len()].copy_from_slice(tx);
        self.tx_len = tx.len() as u8;
        self.rx_len = rx_len as u8;
        self.bit_ticks = bit_ticks;
        self.samples.fill(0);
        self.late = false;
        self.phase = Phase::Sending { pos: 0 };
        Ok(())
    }

    /// The longest an exchange of `tx_len` bytes out and `rx_len` back can
    /// last, bit times (from its first event to its last).
    pub const fn longest_bits(tx_len: usize, rx_len: usize) -> u32 {
        let send = (tx_len * FRAME_BITS) as u32;
        if rx_len == 0 {
            return send;
        }
        send + TURNAROUND_BITS + REPLY_WAIT_BITS + recorded_bits(rx_len) as u32
    }

    /// The timer event: `line` is the line's level read as the event
    /// began, `late` how many ticks after its due time it began.
    pub fn on_event(&mut self, line: bool, late: u32) -> Event {
        let sample_ticks = self.bit_ticks / OVERSAMPLE;
        match self.phase {
            Phase::Sending { pos } => {
                self.late |= late > self.bit_ticks / 4;
                let level = self.tx_bit(pos);
                // The driver measures our bit time on the sync nibble,
                // from the first start bit's falling edge to the one 4
                // bits later, latencies included: from there on, bits go
                // at the time it measured, on its grid.
                let mut shift = 0;
                if pos == 0 {
                    self.first_late = late;
                } else if pos == SYNC_END && self.tx[0] & 0x0f == SYNC {
                    shift = late.wrapping_sub(self.first_late) as i32;
                    let measured = i64::from(self.bit_ticks) + i64::from(shift) / 4;
                    self.bit_ticks = measured.clamp(1, i64::from(u32::MAX)) as u32;
                }
                // The next change of level, or the end of the last bit.
                let total = self.tx_bits();
                let mut next = pos + 1;
                while next < total && self.tx_bit(next) == level {
                    next += 1;
                }
                self.phase = if next < total {
                    Phase::Sending { pos: next }
                } else {
                    Phase::Sent
                };
                let next_due = u32::from(next - pos) * self.bit_ticks;
                Event {
                    pin: Pin::Drive(level),
                    next: Some(next_due.wrapping_add_signed(shift)),
                }
            }
            Phase::Sent if self.rx_len == 0 => self.finish(Ok(())),
            Phase::Sent => {
                self.phase = Phase::Waiting {
                    samples: 0,
                    idle: false,
                };
                Event {
                    pin: Pin::Release,
                    next: Some(TURNAROUND_BITS * self.bit_ticks),
                }
            }
            Phase::Waiting { samples, idle } => {
                self.late |= late > sample_ticks / 2;
                if !line && idle {
                    self.record(0, line);
                    self.phase = Phase::Reading { samples: 1 };
                } else if u32::from(samples) + 1 >= REPLY_WAIT_BITS * OVERSAMPLE {
                    return self.finish(Err(Failure::NoReply));
                } else {
                    self.phase = Phase::Waiting {
                        samples: samples + 1,
                        idle: idle || line,
                    };
                }
                Event {
                    pin: Pin::Keep,
                    next: Some(sample_ticks),
                }
            }
            Phase::Reading { samples } => {
                self.late |= late > sample_ticks / 2;
                self.record(usize::from(samples), line);
                if usize::from(samples) + 1 >= self.recorded_samples() {
                    return self.finish(Ok(()));
                }
                self.phase = Phase::Reading {
                    samples: samples + 1,
                };
                Event {
                    pin: Pin::Keep,
                    next: Some(sample_ticks),
                }
            }
            Phase::Done(_) => Event {
                pin: Pin::Keep,
                next: None,
            },
        }
    }

    /// Ends the exchange now (the caller gave up waiting): the line back
    /// to idle high, to be driven by the caller.
    pub fn abort(&mut self) {
        if !matches!(self.phase, Phase::Done(_)) {
            self.phase = Phase::Done(Err(Failure::Late));
        }
    }

    /// How the exchange ended; [`Failure::Busy`] while it runs.
    pub fn outcome(&self) -> Result<(), Failure> {
        match self.phase {
            Phase::Done(result) => result,
            _ => Err(Failure::Busy),
        }
    }

    /// The reply's bytes into `out` (as many as the exchange asked for),
    /// read from the samples once the exchange is over.
    pub fn reply(&self, out: &mut [u8]) -> Result<(), Failure> {
        self.outcome()?;
        let out = out
            .get_mut(..usize::from(self.rx_len))
            .ok_or(Failure::TooLong)?;
        let recorded = self.recorded_samples();
        let per_bit = OVERSAMPLE as usize;
        // The first sample is the first start bit's first low reading.
        let mut edge = 0;
        for byte in out.iter_mut() {
            // The edge lies within the sample period before `edge`: a
            // bit's middle is about `per_bit / 2` samples after the start
            // of its period, read at the later of the two nearest samples.
            let at = |bit: usize| edge + bit * per_bit + per_bit / 2;
            let level = |bit: usize| {
                let i = at(bit);
                (i < recorded).then(|| self.sample(i))
            };
            if level(0) != Some(false) || level(FRAME_BITS - 1) != Some(true) {
                return Err(Failure::Framing);
            }
            *byte = (0..8).fold(0u8, |b, k| b | u8::from(level(k + 1) == Some(true)) << k);
            // The next start bit: the first low sample after this stop
            // bit's middle.
            edge = (at(FRAME_BITS - 1) + 1..recorded)
                .find(|&i| !self.sample(i))
                .unwrap_or(recorded);
        }
        Ok(())
    }

    /// Ends the exchange with `result` ([`Failure::Late`] instead if an
    /// event ran late: whatever it saw is not trusted), the line driven
    /// idle high.
    fn finish(&mut self, result: Result<(), Failure>) -> Event {
        let result = if self.late {
            Err(Failure::Late)
        } else {
            result
        };
        self.phase = Phase::Done(result);
        Event {
            pin: Pin::Drive(true),
            next: None,
        }
    }

    /// Samples recorded of this exchange's reply.
    fn recorded_samples(&self) -> usize {
        recorded_bits(usize::from(self.rx_len)) * OVERSAMPLE as usize
    }

    /// Bits of the request on the wire.
    fn tx_bits(&self) -> u16 {
        u16::from(self.tx_len) * FRAME_BITS as u16
    }

    /// The level of bit `pos` of the request on the wire.
    fn tx_bit(&self, pos: u16) -> bool {
        wire_level(&self.tx[..usize::from(self.tx_len)], usize::from(pos))
    }

    fn record(&mut self, i: usize, level: bool) {
        if let Some(b) = self.samples.get_mut(i / 8) {
            *b |= u8::from(level) << (i % 8);
        }
    }

    fn sample(&self, i: usize) -> bool {
        self.samples
            .get(i / 8)
            .is_some_and(|b| b >> (i % 8) & 1 != 0)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;
    use std::vec::Vec;

    const BIT: u32 = 6500;

    /// The request's waveform as the events drive it, with no latency:
    /// (time, level) at each event, up to the line's release (a read) or
    /// the end (a write).
    fn drive(uart: &mut SoftUart) -> Vec<(u64, bool)> {
        let (mut t, mut edges) = (0u64, Vec::new());
        loop {
            let e = uart.on_event(true, 0);
            if let Pin::Drive(level) = e.pin {
                edges.push((t, level));
            }
            match e.next {
                Some(d) if matches!(uart.phase, Phase::Sending { .. } | Phase::Sent) => {
                    t += u64::from(d)
                }
                _ => return edges,
            }
        }
    }

    #[test]
    fn a_request_goes_out_least_significant_bit_first_between_start_and_stop_bits() {
        let mut uart = SoftUart::new();
        uart.start(&[0x05, 0xa3], 0, BIT).expect("fits");
        let edges = drive(&mut uart);
        // Reconstruct the level at each bit's middle.
        let level_at = |t: u64| {
            edges
                .iter()
                .rev()
                .find(|(at, _)| *at <= t)
                .expect("driven")
                .1
        };
        let bits: Vec<bool> = (0..20)
            .map(|k| level_at(k * u64::from(BIT) + u64::from(BIT) / 2))
            .collect();
        // 0x05 then 0xa3, least significant bit first, between start and
        // stop bits.
        let expect = [
            [0, 1, 0, 1, 0, 0, 0, 0, 0, 1],
            [0, 1, 1, 0, 0, 0, 1, 0, 1, 1],
        ];
        let expect: Vec<bool> = expect.iter().flatten().map(|&b| b == 1).collect();
        assert_eq!(bits, expect);
        // A write ends driven high, at the end of the last stop bit.
        assert_eq!(uart.outcome(), Ok(()));
        assert_eq!(edges.last(), Some(&(20 * u64::from(BIT), true)));
    }

    /// Feeds the receive phase line levels from `wave(t)` (t in ticks
    /// after the release), with `late` ticks of latency at every event;
    /// fails if the line is driven before the phase ends.
    fn receive(uart: &mut SoftUart, late: u32, wave: impl Fn(u64) -> bool) {
        let mut t = u64::from(TURNAROUND_BITS * uart.bit_ticks);
        loop {
            let e = uart.on_event(wave(t + u64::from(late)), late);
            match e.next {
                Some(d) => t += u64::from(d),
                None => return,
            }
            // The line stays released until the reply's window is over,
            // late events or not.
            assert_eq!(e.pin, Pin::Keep, "the line taken back mid-reply");
        }
    }

    /// The wire levels of `bytes` sent from `start` ticks at `bit` ticks
    /// per bit, high around them.
    fn frames(bytes: &[u8], start: f64, bit: f64) -> impl Fn(u64) -> bool + '_ {
        move |t| {
            let k = (t as f64 - start) / bit;
            k < 0.0 || wire_level(bytes, k as usize)
        }
    }

    fn read(reply: &[u8], delay_bits: f64, bit: f64, late: u32) -> Result<Vec<u8>, Failure> {
        let mut uart = SoftUart::new();
        uart.start(&[0x05, 0x00, 0x06, 0x00], reply.len(), BIT)
            .expect("fits");
        drive(&mut uart);
        assert!(matches!(uart.phase, Phase::Waiting { samples: 0, .. }));
        receive(
            &mut uart,
            late,
            frames(reply, delay_bits * f64::from(BIT), bit),
        );
        let mut out = vec![0; reply.len()];
        uart.reply(&mut out)?;
        Ok(out)
    }

    #[test]
    fn a_reply_is_read_at_the_drivers_bit_rate_within_two_percent() {
        let reply = [0x05, 0xff, 0x06, 0x40, 0x00, 0x01, 0xc0, 0x5a];
        for rate in [0.98, 0.99, 1.0, 1.01, 1.02] {
            for delay in [8.0, 8.3, 8.61, 24.0] {
                let got = read(&reply, delay, f64::from(BIT) / rate, 0);
                assert_eq!(got, Ok(reply.to_vec()), "rate {rate}, delay {delay} bits");
            }
        }
        // Latency within half a sample is tolerated.
        assert_eq!(
            read(&reply, 8.0, f64::from(BIT), BIT / 9),
            Ok(reply.to_vec())
        );
    }

    #[test]
    fn no_answer_a_broken_frame_and_a_late_event_are_failures() {
        let reply = [0x05, 0xff, 0x06, 0x40];
        // Nothing answers within the wait.
        assert_eq!(read(&reply, 70.0, f64::from(BIT), 0), Err(Failure::NoReply));
        // A line held low (no pull-up, no driver) never idles high.
        let mut uart = SoftUart::new();
        uart.start(&[0x05], 4, BIT).expect("fits");
        drive(&mut uart);
        receive(&mut uart, 0, |_| false);
        assert_eq!(uart.outcome(), Err(Failure::NoReply));
        // A byte with its stop bit low.
        let mut uart = SoftUart::new();
        uart.start(&[0x05], 1, BIT).expect("fits");
        drive(&mut uart);
        receive(&mut uart, 0, |t| t < 8 * u64::from(BIT));
        let mut out = [0];
        assert_eq!(uart.reply(&mut out), Err(Failure::Framing));
        // An event later than half a sample.
        assert_eq!(
            read(&reply, 8.0, f64::from(BIT), BIT / 7),
            Err(Failure::Late)
        );
        // Sending: later than a quarter bit. The request still goes out
        // whole, as without the delay.
        let mut uart = SoftUart::new();
        uart.start(&[0x05, 0xa3], 0, BIT).expect("fits");
        uart.on_event(true, 0);
        uart.on_event(true, BIT / 4 + 1);
        assert_eq!(uart.outcome(), Err(Failure::Busy));
        let mut on_time = SoftUart::new();
        on_time.start(&[0x05, 0xa3], 0, BIT).expect("fits");
        on_time.on_event(true, 0);
        on_time.on_event(true, 0);
        assert_eq!(drive(&mut uart), drive(&mut on_time));
        assert_eq!(uart.outcome(), Err(Failure::Late));
        assert_eq!(on_time.outcome(), Ok(()));
    }

    #[test]
    fn after_the_sync_nibble_bits_go_at_the_time_the_driver_measured() {
        let mut uart = SoftUart::new();
        uart.start(&[0xf5, 0x00], 0, BIT).expect("fits");
        // 0xf5: changes at bits 0..=5; the first edge 100 ticks late, the
        // sync nibble's last falling edge (bit 4) 500: the driver measures
        // (4 × BIT + 400) / 4 = BIT + 100.
        let lates = [100, 100, 100, 100, 500];
        let mut next = 0;
        for late in lates {
            next = uart.on_event(true, late).next.expect("more bits");
        }
        // Bit 5 is due one measured bit after bit 4's actual edge, less
        // the first edge's latency (the grid the driver counts on).
        assert_eq!(next, BIT + 100 + 400);
        assert_eq!(uart.bit_ticks, BIT + 100);
    }

    #[test]
    fn oversized_exchanges_are_refused_and_an_exchange_lasts_at_most_its_longest() {
        let mut uart = SoftUart::new();
        assert_eq!(uart.start(&[0; 9], 0, BIT), Err(Failure::TooLong));
        assert_eq!(uart.start(&[0; 4], 9, BIT), Err(Failure::TooLong));
        assert_eq!(uart.outcome(), Err(Failure::Busy));
        // A reply that never comes: the exchange's length in events.
        uart.start(&[0x55; 4], 8, BIT).expect("fits");
        let mut ticks = 0u64;
        while let Some(d) = uart.on_event(true, 0).next {
            ticks += u64::from(d);
        }
        assert!(ticks <= u64::from(SoftUart::longest_bits(4, 8)) * u64::from(BIT));
    }
}
