//! Strings a peer sent (a client's name, a server's Goaway or error text, a model version), made safe to
//! write into a log line or an error message: every control or other non-printing character (newline,
//! carriage return, the ESC that starts an ANSI sequence, bidirectional overrides) and every quote or
//! backslash is escaped the way Rust escapes it (`\n`, `\u{1b}`, `\"`), and at most [`MAX_SHOWN_CHARS`]
//! characters are shown. So a peer can neither forge a log line nor recolour a terminal, and a log line
//! stays bounded whatever a peer sends.

use std::fmt;

/// The most characters of one untrusted string shown (the protocol's longest name); a longer one ends in `…`.
pub const MAX_SHOWN_CHARS: usize = 128;

/// Shows `s` escaped and bounded (see the module docs); `Display` only, never allocates.
pub fn untrusted(s: &str) -> Untrusted<'_> {
    Untrusted(s)
}

/// A peer's string as [`untrusted`] shows it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Untrusted<'a>(&'a str);

impl fmt::Display for Untrusted<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut chars = self.0.chars();
        for c in chars.by_ref().take(MAX_SHOWN_CHARS) {
            if c == '\'' {
                f.write_str("'")?;
            } else {
                fmt::Display::fmt(&c.escape_debug(), f)?;
            }
        }
        if chars.next().is_some() {
            f.write_str("…")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_forged_log_line_stays_on_one_escaped_line() {
        let name = "headset\n2026-12-02T12:00:00Z  INFO shutdown complete\x1b[31m\r\u{202e}";
        let shown = untrusted(name).to_string();
        assert!(!shown.contains(['\n', '\r', '\x1b', '\u{202e}']), "{shown}");
        assert_eq!(
            shown,
            "headset\\n2026-12-02T12:00:00Z  INFO shutdown complete\\u{1b}[31m\\r\\u{202e}"
        );
    }

    #[test]
    fn ordinary_names_are_unchanged_and_long_ones_bounded() {
        assert_eq!(untrusted("holoface-demo").to_string(), "holoface-demo");
        assert_eq!(untrusted("café 'x'").to_string(), "café 'x'");
        assert_eq!(untrusted("a\"b\\c").to_string(), "a\\\"b\\\\c");
        let long = "x".repeat(1000);
        let shown = untrusted(&long).to_string();
        assert_eq!(shown.chars().count(), MAX_SHOWN_CHARS + 1);
        assert!(shown.ends_with('…'));
        assert_eq!(
            untrusted(&"y".repeat(MAX_SHOWN_CHARS)).to_string(),
            "y".repeat(MAX_SHOWN_CHARS)
        );
    }
}
