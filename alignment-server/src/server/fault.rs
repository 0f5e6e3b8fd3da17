//! How a connection ends: the close code and reason the server sends, shared by the handshake, the
//! frame streams and the per-connection task.

use holoface_protocol::{CloseCode, DecodeError};
use quinn::Connection;

use super::code;

/// A connection-ending problem: the close code and a log/close-reason text.
#[derive(Debug)]
pub(super) struct Fault {
    pub(super) code: CloseCode,
    pub(super) detail: String,
}

impl Fault {
    pub(super) fn new(code: CloseCode, detail: impl Into<String>) -> Self {
        Self {
            code,
            detail: detail.into(),
        }
    }

    pub(super) fn decode(e: &DecodeError) -> Self {
        Self::new(e.close_code(), e.to_string())
    }
}

/// How a session ended.
#[derive(Debug)]
pub(super) enum ConnectionEnd {
    /// The peer closed or the connection was lost.
    Gone(String),
    /// The server must close the connection with this code.
    Fault(Fault),
    /// Graceful shutdown completed; close with `ShuttingDown`.
    Shutdown,
}

impl From<Fault> for ConnectionEnd {
    fn from(f: Fault) -> Self {
        Self::Fault(f)
    }
}

pub(super) fn close_conn(conn: &Connection, c: CloseCode, detail: &str) {
    // Keep the reason short: it has to fit in one packet.
    let mut end = detail.len().min(120);
    while !detail.is_char_boundary(end) {
        end -= 1;
    }
    conn.close(code(c), detail.get(..end).unwrap_or_default().as_bytes());
}
