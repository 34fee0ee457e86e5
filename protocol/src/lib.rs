//! The Klipper wire protocol, as spoken between a Klipper host and a Klipper MCU.
//!
//! onechip speaks it in both directions: as the host towards secondary boards
//! running stock Klipper firmware, and as an MCU towards a normal Klipper host.
//!
//! Layers, bottom up:
//! - [`vlq`]: Klipper's variable-length integer encoding of command arguments;
//! - [`crc`]: the CRC16 that closes every message block;
//! - [`block`]: message-block framing (length, sequence, payload, CRC, sync);
//! - [`transport`]: reliable delivery (sequence numbers, acks and naks,
//!   retransmission, flow control, resynchronisation);
//! - [`json`] and [`dictionary`]: the data dictionary of commands,
//!   responses, enumerations and constants;
//! - [`codec`]: messages to and from bytes and Klipper's text form;
//! - [`identify`]: fetching a dictionary from an MCU, inflated by
//!   [`inflate`];
//! - [`mcu`]: the MCU side (our own dictionary, identify, dispatch).
//!
//! Everything here is `no_std` and allocation-free.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod block;
pub mod codec;
pub mod crc;
pub mod dictionary;
pub mod identify;
pub mod inflate;
pub mod json;
pub mod mcu;
pub mod transport;
pub mod vlq;
