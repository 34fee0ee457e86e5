//! The MCU side of the protocol: the dictionary this firmware describes
//! itself with, `identify` answering, and command dispatch.
//!
//! The dictionary is compiled from `base-dictionary.txt` by the build script
//! ([`DICTIONARY_JSON`], and [`DICTIONARY_ZLIB`] as served to hosts).
//! [`Dispatcher::dispatch`] runs every command of a received block: it
//! answers `identify` itself and hands the others to a [`Handler`], whose
//! responses it encodes into the reply payload.

use crate::codec::{Arg, DecodeError, Decoded, EncodeError, Encoder};
use crate::dictionary::{Dictionary, Kind};
use crate::identify;

/// The MCU role's data dictionary (JSON).
pub const DICTIONARY_JSON: &str = include_str!(concat!(env!("OUT_DIR"), "/dictionary.json"));
/// The same, zlib-compressed, as `identify` serves it.
pub const DICTIONARY_ZLIB: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/dictionary.zlib"));

/// Why a received block could not be run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DispatchError<'d> {
    /// The bytes are not a valid message (Klipper: "Command parser error").
    Decode(DecodeError),
    /// The message is a response, which an MCU never receives.
    NotACommand(i32),
    /// A response could not be encoded (too large for the reply).
    Encode(EncodeError<'d>),
    /// The handler refused the command.
    Handler(&'static str),
}

impl core::fmt::Display for DispatchError<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Decode(e) => write!(f, "command parser error: {e}"),
            Self::NotACommand(id) => write!(f, "message {id} is not a command"),
            Self::Encode(e) => write!(f, "response: {e}"),
            Self::Handler(reason) => f.write_str(reason),
        }
    }
}

impl<'d> From<EncodeError<'d>> for DispatchError<'d> {
    fn from(e: EncodeError<'d>) -> Self {
        Self::Encode(e)
    }
}

/// Responses being collected for one reply block.
pub struct Responses<'d, 'o> {
    dict: &'d Dictionary<'d>,
    out: &'o mut [u8],
    len: usize,
}

impl<'d> Responses<'d, '_> {
    /// Appends the response `name` with `args` in format order.
    pub fn send(&mut self, name: &'d str, args: &[Arg<'_>]) -> Result<(), EncodeError<'d>> {
        let encoder = Encoder::new(self.dict, name)?;
        self.len += encoder.encode(args, &mut self.out[self.len..])?;
        Ok(())
    }
}

/// The commands an MCU role implements beyond `identify`.
pub trait Handler {
    /// Runs one command; responses go to `reply`.
    fn command<'d>(
        &mut self,
        command: &Decoded<'_, '_, '_>,
        reply: &mut Responses<'d, '_>,
    ) -> Result<(), DispatchError<'d>>;
}

/// Decodes received blocks and runs their commands.
pub struct Dispatcher<'d> {
    dict: &'d Dictionary<'d>,
    identify: identify::Server,
}

impl<'d> Dispatcher<'d> {
    /// A dispatcher for `dict`, serving `compressed` (its zlib form) to
    /// `identify`.
    pub fn new(dict: &'d Dictionary<'d>, compressed: &'static [u8]) -> Self {
        Self {
            dict,
            identify: identify::Server::new(compressed),
        }
    }

    /// Runs every command in `payload`; writes the responses into `out` and
    /// returns their length. Stops at the first error (the MCU then shuts
    /// down, as Klipper's does).
    pub fn dispatch(
        &self,
        mut payload: &[u8],
        handler: &mut impl Handler,
        out: &mut [u8],
    ) -> Result<usize, DispatchError<'d>> {
        let mut reply = Responses {
            dict: self.dict,
            out,
            len: 0,
        };
        while !payload.is_empty() {
            let (command, used) = self.dict.decode(payload).map_err(DispatchError::Decode)?;
            payload = &payload[used..];
            if command.message.kind != Kind::Command {
                return Err(DispatchError::NotACommand(command.message.id));
            }
            if command.message.name() == "identify" {
                let offset = command.int("offset").unwrap_or(0);
                let count = command.int("count").unwrap_or(0);
                let chunk = self.identify.chunk(offset as u32, count as u8);
                reply.send("identify_response", &[Arg::Int(offset), Arg::Bytes(chunk)])?;
            } else {
                handler.command(&command, &mut reply)?;
            }
        }
        Ok(reply.len)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::dictionary::Dictionary;
    use std::string::ToString;

    /// A clock that reads 1000 and counts config queries.
    struct TestMcu {
        configs: u32,
    }

    impl Handler for TestMcu {
        fn command<'d>(
            &mut self,
            command: &Decoded<'_, '_, '_>,
            reply: &mut Responses<'d, '_>,
        ) -> Result<(), DispatchError<'d>> {
            match command.message.name() {
                "get_clock" => reply.send("clock", &[Arg::Int(1000)])?,
                "get_config" => {
                    self.configs += 1;
                    reply.send(
                        "config",
                        &[Arg::Int(0), Arg::Int(0), Arg::Int(0), Arg::Int(0)],
                    )?;
                }
                _ => return Err(DispatchError::Handler("unsupported command")),
            }
            Ok(())
        }
    }

    #[test]
    fn the_built_in_dictionary_parses_and_names_its_window() {
        let dict = Dictionary::parse(DICTIONARY_JSON).expect("valid");
        assert_eq!(dict.constant_int("RECEIVE_WINDOW"), Some(192));
        assert_eq!(dict.by_name("identify").map(|m| m.id), Some(1));
        assert_eq!(dict.by_name("identify_response").map(|m| m.id), Some(0));
    }

    #[test]
    fn dispatch_answers_identify_and_hands_on_other_commands() {
        let dict = Dictionary::parse(DICTIONARY_JSON).expect("valid");
        let dispatcher = Dispatcher::new(&dict, DICTIONARY_ZLIB);
        let mut payload = [0u8; 32];
        let mut n = dict
            .encode_text("identify offset=0 count=8", &mut payload)
            .expect("valid");
        n += dict
            .encode_text("get_clock", &mut payload[n..])
            .expect("valid");
        n += dict
            .encode_text("get_config", &mut payload[n..])
            .expect("valid");
        let mut mcu = TestMcu { configs: 0 };
        let mut out = [0u8; 64];
        let len = dispatcher
            .dispatch(&payload[..n], &mut mcu, &mut out)
            .expect("runs");
        let (first, used) = dict.decode(&out[..len]).expect("identify_response");
        assert_eq!(first.message.name(), "identify_response");
        assert_eq!(
            first.fields[1],
            crate::codec::Field::Bytes(&DICTIONARY_ZLIB[..8])
        );
        let (second, used2) = dict.decode(&out[used..len]).expect("clock");
        assert_eq!(second.to_string(), "clock clock=1000");
        let (third, _) = dict.decode(&out[used + used2..len]).expect("config");
        assert_eq!(third.message.name(), "config");
        assert_eq!(mcu.configs, 1);
    }

    #[test]
    fn bad_commands_are_errors() {
        let dict = Dictionary::parse(DICTIONARY_JSON).expect("valid");
        let dispatcher = Dispatcher::new(&dict, DICTIONARY_ZLIB);
        let mut mcu = TestMcu { configs: 0 };
        let mut out = [0u8; 64];
        let mut payload = [0u8; 16];
        let n = dict
            .encode_text("clock clock=5", &mut payload)
            .expect("encodable");
        assert!(matches!(
            dispatcher.dispatch(&payload[..n], &mut mcu, &mut out),
            Err(DispatchError::NotACommand(_))
        ));
        assert_eq!(
            dispatcher.dispatch(&[90], &mut mcu, &mut out),
            Err(DispatchError::Decode(DecodeError::UnknownId(90)))
        );
        let n = dict
            .encode_text("emergency_stop", &mut payload)
            .expect("encodable");
        assert_eq!(
            dispatcher.dispatch(&payload[..n], &mut mcu, &mut out),
            Err(DispatchError::Handler("unsupported command"))
        );
    }
}
