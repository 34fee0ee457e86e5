//! MCU pin names as printer.cfg writes them (`PF13`, `!PF14`, `^PG6`):
//! GPIO port and number, and whether the signal is inverted (`!`) or
//! wants a pull-up (`^`).

use core::fmt;

/// A GPIO pin of an STM32 (ports A to K, pins 0 to 15).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PinName {
    /// Port: 0 for A, 1 for B, ...
    pub port: u8,
    /// Pin number within the port.
    pub number: u8,
    /// The signal is active low (`!`).
    pub inverted: bool,
    /// A pull-up is wanted (`^`).
    pub pull_up: bool,
}

/// A pin name that is not an STM32 GPIO.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BadPin<'a>(pub &'a str);

impl fmt::Display for BadPin<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "unknown pin '{}' (expected a name like PF13, !PF14 or ^PG6)",
            self.0
        )
    }
}

/// Parses a pin name from printer.cfg.
pub fn parse(text: &str) -> Result<PinName, BadPin<'_>> {
    let (mut inverted, mut pull_up) = (false, false);
    let mut rest = text.trim();
    loop {
        if let Some(r) = rest.strip_prefix('!') {
            inverted = true;
            rest = r.trim_start();
        } else if let Some(r) = rest.strip_prefix('^') {
            pull_up = true;
            rest = r.trim_start();
        } else {
            break;
        }
    }
    let bad = || BadPin(text);
    let digits = rest.strip_prefix(['P', 'p']).ok_or_else(bad)?;
    let mut chars = digits.chars();
    let letter = chars.next().ok_or_else(bad)?.to_ascii_uppercase();
    if !('A'..='K').contains(&letter) {
        return Err(bad());
    }
    let number: u8 = chars.as_str().parse().map_err(|_| bad())?;
    if number > 15 {
        return Err(bad());
    }
    Ok(PinName {
        port: letter as u8 - b'A',
        number,
        inverted,
        pull_up,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn klipper_pin_names_parse() {
        assert_eq!(
            parse("PF13"),
            Ok(PinName {
                port: 5,
                number: 13,
                inverted: false,
                pull_up: false
            })
        );
        let enable = parse("!PF14").expect("valid");
        assert!(enable.inverted && enable.port == 5 && enable.number == 14);
        let endstop = parse("^!PG6").expect("valid");
        assert!(endstop.inverted && endstop.pull_up && endstop.port == 6);
        assert_eq!(parse(" pa0 ").map(|p| (p.port, p.number)), Ok((0, 0)));
    }

    #[test]
    fn other_names_are_errors() {
        for bad in ["", "F13", "PZ1", "PF16", "PF", "PF1x", "ar13", "!"] {
            assert_eq!(parse(bad), Err(BadPin(bad)), "{bad}");
        }
    }
}
