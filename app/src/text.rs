//! Bounded message texts: errors that may borrow the line they describe
//! are formatted into owned, fixed-size strings, cut if too long.

use core::fmt::{Display, Write};

/// An error message, owned and bounded; longer messages are cut.
pub type ErrorText = heapless::String<96>;

/// Formats `e` as an [`ErrorText`], cutting what does not fit.
#[inline(never)]
pub fn error_text(e: &dyn Display) -> ErrorText {
    cut_text(e)
}

/// Formats `e` into a string of at most `N` bytes, cutting what does not
/// fit (at a character boundary).
pub fn cut_text<const N: usize>(e: &(impl Display + ?Sized)) -> heapless::String<N> {
    struct Cut<const N: usize>(heapless::String<N>);
    impl<const N: usize> Write for Cut<N> {
        fn write_str(&mut self, s: &str) -> core::fmt::Result {
            for c in s.chars() {
                if self.0.push(c).is_err() {
                    break;
                }
            }
            Ok(())
        }
    }
    let mut cut = Cut(heapless::String::new());
    let _ = write!(cut, "{e}");
    cut.0
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    #[test]
    fn long_error_texts_are_cut_not_lost() {
        let long = "x".repeat(500);
        assert_eq!(error_text(&long).len(), 96);
        let accented = "é".repeat(60);
        assert_eq!(error_text(&accented).chars().count(), 48);
    }
}
