//! A hardware serial link's pure parts, for a USART driven from its
//! interrupt (the board's link to secondary MCUs): the byte rings between
//! the interrupt and thread code, and the baud-rate divisor.
//!
//! - [`ByteRing`]: a bounded single-producer single-consumer ring of
//!   bytes, lock-free (one side may be an interrupt, the other thread
//!   code); bytes leave in the order they came, none is overwritten.
//! - [`RxRing`]: the receive side: a [`ByteRing`] whose producer counts
//!   every byte it had no room for (dropped, never reordered).
//! - [`divisor`]: a USART's BRR value for a baud rate from its kernel
//!   clock, as RM0468's USART chapter ("USART baud rate generation") computes it,
//!   with the rate it makes and its error.

use core::cell::UnsafeCell;
use core::sync::atomic::{AtomicU32, AtomicUsize, Ordering};

/// A bounded ring of `N` bytes for one producer and one consumer.
///
/// Invariants: `head` and `tail` count bytes pushed and popped (wrapping);
/// `head - tail` (wrapping) is the number of bytes held, at most `N`;
/// only the producer stores `head`, only the consumer stores `tail`; the
/// byte at `i % N` is written before `head` passes `i` (Release) and read
/// after the consumer saw it pass (Acquire). `N` is a power of two, so the
/// counters' wrap does not break `% N`.
pub struct ByteRing<const N: usize> {
    buf: UnsafeCell<[u8; N]>,
    head: AtomicUsize,
    tail: AtomicUsize,
}

// SAFETY: the producer writes only the slots between `head` and
// `tail + N`, the consumer reads only those between `tail` and `head`;
// each publishes with a Release store the other reads with Acquire. The
// caller keeps to one producer and one consumer (documented on each
// method).
unsafe impl<const N: usize> Sync for ByteRing<N> {}

impl<const N: usize> Default for ByteRing<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> ByteRing<N> {
    const POWER_OF_TWO: () = assert!(N.is_power_of_two(), "ring length is a power of two");

    /// An empty ring (all zero: may live in zeroed memory).
    pub const fn new() -> Self {
        let () = Self::POWER_OF_TWO;
        Self {
            buf: UnsafeCell::new([0; N]),
            head: AtomicUsize::new(0),
            tail: AtomicUsize::new(0),
        }
    }

    /// Bytes held now.
    pub fn len(&self) -> usize {
        let head = self.head.load(Ordering::Acquire);
        head.wrapping_sub(self.tail.load(Ordering::Acquire))
    }

    /// True if no byte is held.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// True if no byte more fits.
    pub fn is_full(&self) -> bool {
        self.len() >= N
    }

    /// Producer side: appends `byte`; false (and nothing stored) if the
    /// ring is full.
    #[inline]
    pub fn push(&self, byte: u8) -> bool {
        let head = self.head.load(Ordering::Relaxed);
        if head.wrapping_sub(self.tail.load(Ordering::Acquire)) >= N {
            return false;
        }
        // SAFETY: slot `head % N` is not between `tail` and `head`, so the
        // consumer does not read it until `head` is published below.
        unsafe { (*self.buf.get())[head % N] = byte };
        self.head.store(head.wrapping_add(1), Ordering::Release);
        true
    }

    /// Producer side: appends as many of `bytes` as fit, in order; how
    /// many.
    pub fn push_slice(&self, bytes: &[u8]) -> usize {
        bytes.iter().take_while(|&&b| self.push(b)).count()
    }

    /// Consumer side: the oldest byte, if any.
    #[inline]
    pub fn pop(&self) -> Option<u8> {
        let tail = self.tail.load(Ordering::Relaxed);
        if self.head.load(Ordering::Acquire) == tail {
            return None;
        }
        // SAFETY: slot `tail % N` lies between `tail` and `head`: the
        // producer wrote it before publishing `head` and leaves it alone
        // until `tail` passes it below.
        let byte = unsafe { (*self.buf.get())[tail % N] };
        self.tail.store(tail.wrapping_add(1), Ordering::Release);
        Some(byte)
    }

    /// Consumer side: moves the oldest bytes into `out`, as many as are
    /// held and fit; how many.
    pub fn pop_into(&self, out: &mut [u8]) -> usize {
        let mut n = 0;
        for slot in out.iter_mut() {
            match self.pop() {
                Some(b) => *slot = b,
                None => break,
            }
            n += 1;
        }
        n
    }

    /// Consumer side: drops every byte held (a link opened again starts
    /// with nothing old).
    pub fn clear(&self) {
        self.tail
            .store(self.head.load(Ordering::Acquire), Ordering::Release);
    }
}

/// The receive side of a link: a ring its interrupt fills, counting the
/// bytes that did not fit.
///
/// A byte that arrives while the ring is full is dropped (the ones held
/// stay, in order) and counted: Klipper's transport sees a bad block and
/// has it sent again, as after a damaged byte on the wire.
pub struct RxRing<const N: usize> {
    ring: ByteRing<N>,
    dropped: AtomicU32,
}

impl<const N: usize> Default for RxRing<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> RxRing<N> {
    /// An empty ring, nothing dropped.
    pub const fn new() -> Self {
        Self {
            ring: ByteRing::new(),
            dropped: AtomicU32::new(0),
        }
    }

    /// Producer side (the receive interrupt): keeps `byte`, or counts it
    /// dropped if the ring is full.
    #[inline]
    pub fn receive(&self, byte: u8) {
        if !self.ring.push(byte) {
            // Only the producer adds: a load and a store suffice (no
            // read-modify-write, which an M7 does have, but Relaxed
            // ordering is all this needs).
            let n = self.dropped.load(Ordering::Relaxed);
            self.dropped.store(n.wrapping_add(1), Ordering::Relaxed);
        }
    }

    /// Consumer side: the bytes received, oldest first, as many as fit in
    /// `out`; how many.
    pub fn read(&self, out: &mut [u8]) -> usize {
        self.ring.pop_into(out)
    }

    /// True if a byte waits.
    pub fn has_data(&self) -> bool {
        !self.ring.is_empty()
    }

    /// Consumer side: forgets every byte held.
    pub fn clear(&self) {
        self.ring.clear();
    }

    /// Bytes dropped for want of room, since the start (wrapping).
    pub fn dropped(&self) -> u32 {
        self.dropped.load(Ordering::Relaxed)
    }
}

/// A baud rate a USART can make: its BRR register value and the rate it
/// gives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Divisor {
    /// BRR's value (RM0468, "USART baud rate generation": with 16× oversampling BRR =
    /// USARTDIV; with 8×, BRR[15:4] = USARTDIV[15:4] and BRR[2:0] =
    /// USARTDIV[3:0] >> 1).
    pub brr: u16,
    /// True for 8× oversampling (CR1.OVER8), used only when 16× cannot
    /// reach the rate.
    pub over8: bool,
    /// The rate the divisor makes, bit/s (rounded down).
    pub actual_baud: u32,
    /// `(actual - asked) / asked`, parts per million (signed).
    pub error_ppm: i32,
}

/// Why a rate cannot be made.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BaudError {
    /// Zero, or above the kernel clock / 8 (the fastest a USART goes).
    OutOfRange,
    /// The nearest divisor is off by more than [`MAX_ERROR_PPM`]: the
    /// rate the divisor makes, bit/s.
    TooFar(u32),
}

/// The largest rate error accepted, ppm (1 %): a receiver at 16×
/// oversampling tolerates about 3.75 % in all (RM0468, "Tolerance of
/// the USART receiver to clock deviation"), which both ends' errors
/// share.
pub const MAX_ERROR_PPM: i32 = 10_000;

/// The BRR value for `baud` bit/s from a kernel clock of `kernel_hz` (the
/// USART's prescaler at 1): 16× oversampling (the more noise-tolerant) with
/// USARTDIV = round(kernel / baud), at least 16 (BRR must be ≥ 16);
/// 8× if 16× cannot go that fast.
pub fn divisor(kernel_hz: u32, baud: u32) -> Result<Divisor, BaudError> {
    if baud == 0 || u64::from(baud) * 8 > u64::from(kernel_hz) {
        return Err(BaudError::OutOfRange);
    }
    let (k, b) = (u64::from(kernel_hz), u64::from(baud));
    let div16 = (k + b / 2) / b;
    let (brr, over8, actual) = if (16..=0xffff).contains(&div16) {
        (div16 as u16, false, k / div16)
    } else if div16 > 0xffff {
        return Err(BaudError::OutOfRange);
    } else {
        // USARTDIV = 2 × kernel / baud, at least 16.
        let div8 = ((2 * k + b / 2) / b).max(16);
        let brr = (div8 & !0xf) | ((div8 & 0xf) >> 1);
        (brr as u16, true, 2 * k / div8)
    };
    let error_ppm = ((actual as i64 - b as i64) * 1_000_000 / b as i64) as i32;
    let found = Divisor {
        brr,
        over8,
        actual_baud: actual as u32,
        error_ppm,
    };
    if error_ppm.abs() > MAX_ERROR_PPM {
        return Err(BaudError::TooFar(found.actual_baud));
    }
    Ok(found)
}

#[cfg(test)]
mod tests {
    use super::*;

    extern crate std;

    #[test]
    fn ring_keeps_order_and_bounds() {
        let ring = ByteRing::<8>::new();
        assert!(ring.is_empty());
        assert_eq!(ring.push_slice(b"0123456789"), 8);
        assert!(ring.is_full());
        assert!(!ring.push(b'x'));
        let mut out = [0u8; 5];
        assert_eq!(ring.pop_into(&mut out), 5);
        assert_eq!(&out, b"01234");
        assert_eq!(ring.push_slice(b"abc"), 3);
        let mut out = [0u8; 16];
        assert_eq!(ring.pop_into(&mut out), 6);
        assert_eq!(&out[..6], b"567abc");
        assert_eq!(ring.pop(), None);
    }

    #[test]
    fn ring_survives_counter_wrap() {
        let ring = ByteRing::<4>::new();
        ring.head.store(usize::MAX - 1, Ordering::Relaxed);
        ring.tail.store(usize::MAX - 1, Ordering::Relaxed);
        for round in 0..10u8 {
            assert_eq!(ring.push_slice(&[round, round + 1, round + 2]), 3);
            assert_eq!(ring.len(), 3);
            let mut out = [0u8; 3];
            assert_eq!(ring.pop_into(&mut out), 3);
            assert_eq!(out, [round, round + 1, round + 2]);
        }
    }

    #[test]
    fn overrun_drops_newest_and_counts() {
        let rx = RxRing::<4>::new();
        for b in b"abcdef" {
            rx.receive(*b);
        }
        assert_eq!(rx.dropped(), 2);
        let mut out = [0u8; 8];
        assert_eq!(rx.read(&mut out), 4);
        assert_eq!(&out[..4], b"abcd", "the held bytes stay, in order");
        rx.receive(b'g');
        assert_eq!(rx.read(&mut out), 1);
        assert_eq!(out[0], b'g');
        assert_eq!(rx.dropped(), 2);
        rx.receive(b'h');
        rx.clear();
        assert!(!rx.has_data());
    }

    #[test]
    fn ring_between_threads() {
        // One producer thread, one consumer: every byte arrives once, in
        // order.
        let ring = std::sync::Arc::new(ByteRing::<16>::new());
        let producer = {
            let ring = ring.clone();
            std::thread::spawn(move || {
                for i in 0..100_000u32 {
                    while !ring.push(i as u8) {
                        std::hint::spin_loop();
                    }
                }
            })
        };
        let mut expect = 0u32;
        while expect < 100_000 {
            if let Some(b) = ring.pop() {
                assert_eq!(b, expect as u8);
                expect += 1;
            }
        }
        producer.join().expect("producer ran");
    }

    #[test]
    fn usart2_at_250000_is_exact() {
        // 130 MHz APB1 clock (the board's clocks.rs), Klipper's default.
        let d = divisor(130_000_000, 250_000).expect("reachable");
        assert_eq!(
            d,
            Divisor {
                brr: 520,
                over8: false,
                actual_baud: 250_000,
                error_ppm: 0
            }
        );
    }

    #[test]
    fn common_rates_and_their_error() {
        let d = divisor(130_000_000, 115_200).expect("reachable");
        assert_eq!((d.brr, d.over8), (1128, false));
        assert_eq!(d.actual_baud, 115_248);
        assert_eq!(d.error_ppm, 416);
        let d = divisor(130_000_000, 1_000_000).expect("reachable");
        assert_eq!((d.brr, d.actual_baud, d.error_ppm), (130, 1_000_000, 0));
        // Beyond kernel / 16: 8× oversampling, BRR's low nibble halved.
        let d = divisor(130_000_000, 10_000_000).expect("reachable");
        assert!(d.over8);
        assert_eq!(d.brr, 0x10 | (0xa >> 1));
        assert_eq!(d.actual_baud, 10_000_000);
    }

    #[test]
    fn unreachable_rates_are_refused() {
        assert_eq!(divisor(130_000_000, 0), Err(BaudError::OutOfRange));
        assert_eq!(divisor(130_000_000, 20_000_000), Err(BaudError::OutOfRange));
        // Below kernel / 65535: BRR does not hold the divisor.
        assert_eq!(divisor(130_000_000, 1_000), Err(BaudError::OutOfRange));
        // 8× at 12 Mbit/s: USARTDIV 21.67 -> 22, 11.8 Mbit/s, 1.5 % off.
        assert_eq!(
            divisor(130_000_000, 12_000_000),
            Err(BaudError::TooFar(11_818_181))
        );
    }
}
