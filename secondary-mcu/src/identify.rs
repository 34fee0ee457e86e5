//! The first exchange with a secondary MCU: its data dictionary, fetched
//! with `identify` over a fresh link. Sans I/O: the caller writes what
//! [`Identify::poll`] returns and feeds what it reads to
//! [`Identify::receive`]; times are host seconds.

use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;
use onechip_protocol::identify::{CHUNK, Fetcher, IdentifyError, Progress};
use onechip_protocol::transport::HostLink;
use onechip_protocol::vlq;

/// Message id of `identify offset=%u count=%c` in every Klipper dictionary.
const IDENTIFY_ID: i64 = 1;
/// Message id of `identify_response offset=%u data=%.*s`.
const IDENTIFY_RESPONSE_ID: i64 = 0;
/// Seconds without an answer after which a question is asked again: the
/// first one is lost whenever the MCU's block sequence is not the one a
/// new link starts with (klippy retries its commands the same way).
pub const RETRY_TIME: f64 = 0.25;
/// Seconds after a question's acknowledgement without its answer (lost
/// on the way) before it is asked again; doubled at each miss up to
/// [`RETRY_TIME`], as klippy's retried commands wait.
const LOST_ANSWER_RETRY: f64 = 0.010;

/// Host seconds as the link's microseconds. Not inlined: a soft-float
/// conversion, with several callers.
#[inline(never)]
pub(crate) fn micros(now: f64) -> u64 {
    (now.max(0.0) * 1e6) as u64
}

/// A dictionary fetch in progress.
pub struct Identify<'b> {
    link: HostLink,
    fetcher: Fetcher<'b>,
    /// When to ask (again) for the fetcher's offset, host s.
    ask_at: f64,
    /// Offsets asked so far (for diagnostics).
    pub questions: u32,
    /// A question is out and its answer not in.
    waiting: bool,
    /// Wait before asking again once a question is acknowledged without
    /// its answer, s.
    lost_retry: f64,
    /// The MCU's receive buffer, bytes.
    receive_window: usize,
}

impl<'b> Identify<'b> {
    /// Starts fetching into `out` (the inflated JSON; Klipper's are 10–15
    /// KB), over a link to an MCU that buffers `receive_window` bytes,
    /// built in place in `slot`: the fetcher's inflate state is about
    /// 1.6 KB, which a microcontroller's stack should not carry.
    pub fn init_in<'s>(
        slot: &'s mut MaybeUninit<Self>,
        out: &'b mut [u8],
        receive_window: usize,
    ) -> &'s mut Self {
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; each field is written once, in
        // place, before the slot is taken as initialised.
        unsafe {
            addr_of_mut!((*p).link).write(HostLink::new(receive_window));
            Fetcher::init_in(&mut *addr_of_mut!((*p).fetcher).cast(), out);
            addr_of_mut!((*p).ask_at).write(0.0);
            addr_of_mut!((*p).questions).write(0);
            addr_of_mut!((*p).waiting).write(false);
            addr_of_mut!((*p).lost_retry).write(LOST_ANSWER_RETRY);
            addr_of_mut!((*p).receive_window).write(receive_window);
            slot.assume_init_mut()
        }
    }

    /// Writes into `out` what must go to the MCU now (a question, or a
    /// retransmission); returns its length. `out` needs
    /// `1 + MAX_PENDING_BLOCKS × MAX_LEN` bytes.
    pub fn poll(&mut self, now: f64, out: &mut [u8]) -> usize {
        if let Some(n) = self.link.poll(micros(now), out) {
            return n;
        }
        if now < self.ask_at || self.link.unacknowledged() > 0 {
            return 0;
        }
        let mut payload = [0u8; 3 * vlq::MAX_LEN];
        let mut len = 0;
        for value in [
            IDENTIFY_ID,
            i64::from(self.fetcher.offset()),
            i64::from(CHUNK),
        ] {
            if let Some(room) = payload.get_mut(len..).and_then(|r| r.first_chunk_mut()) {
                len += vlq::encode(value, room);
            }
        }
        self.ask_at = now + RETRY_TIME;
        self.questions += 1;
        self.waiting = true;
        match self.link.send(&payload[..len], micros(now)) {
            Ok(block) => {
                let n = block.len().min(out.len());
                out[..n].copy_from_slice(&block[..n]);
                n
            }
            Err(_) => 0,
        }
    }

    /// Takes bytes from the MCU: `Some(length)` of the dictionary text once
    /// it is complete.
    pub fn receive(&mut self, bytes: &[u8], now: f64) -> Result<Option<usize>, IdentifyError> {
        let mut result = Ok(None);
        let fetcher = &mut self.fetcher;
        let ask_at = &mut self.ask_at;
        self.link.receive(bytes, micros(now), |payload| {
            let Some((offset, data)) = identify_response(payload) else {
                return;
            };
            if result != Ok(None) || offset != fetcher.offset() {
                return; // an answer to a question asked twice
            }
            result = match fetcher.on_response(offset, data) {
                Ok(Progress::Done(n)) => Ok(Some(n)),
                Ok(Progress::More) => {
                    *ask_at = now;
                    Ok(None)
                }
                Err(e) => Err(e),
            };
        });
        if *ask_at == now {
            // Answered: the next question goes at once.
            self.waiting = false;
            self.lost_retry = LOST_ANSWER_RETRY;
        } else if self.waiting && self.link.unacknowledged() == 0 {
            // The MCU took the question, and its answer was lost.
            self.waiting = false;
            self.ask_at = self.ask_at.min(now + self.lost_retry);
            self.lost_retry = (2.0 * self.lost_retry).min(RETRY_TIME);
        }
        result
    }

    /// The same fetch from its start, into the same buffer, for a link
    /// opened anew (the old one went before the dictionary was in).
    pub fn restart(&mut self) {
        self.link = HostLink::new(self.receive_window);
        self.fetcher.restart();
        (self.ask_at, self.questions) = (0.0, 0);
        (self.waiting, self.lost_retry) = (false, LOST_ANSWER_RETRY);
    }

    /// Once the dictionary is in: the link to go on with, and the
    /// dictionary's text (the fetch is spent after).
    pub fn finish(&mut self) -> (HostLink, &'b [u8]) {
        let link = core::mem::replace(&mut self.link, HostLink::new(self.receive_window));
        (link, self.fetcher.take_output())
    }
}

/// `(offset, data)` of an `identify_response` payload, if it is one.
fn identify_response(payload: &[u8]) -> Option<(u32, &[u8])> {
    let (id, mut at) = vlq::decode(payload).ok()?;
    if id != IDENTIFY_RESPONSE_ID {
        return None;
    }
    let (offset, n) = vlq::decode(payload.get(at..)?).ok()?;
    at += n;
    let (len, n) = vlq::decode(payload.get(at..)?).ok()?;
    at += n;
    let data = payload.get(at..at + usize::try_from(len).ok()?)?;
    Some((u32::try_from(offset).ok()?, data))
}
