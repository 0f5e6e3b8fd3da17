//! The connection handshake's checks: reading the `ClientHello`, then the protocol version and the token.

use std::sync::atomic::Ordering;

use bytes::BytesMut;
use holoface_protocol::{
    ClientHello, CloseCode, MIN_PROTOCOL_VERSION, Message, PROTOCOL_VERSION, decode_framed,
};
use quinn::RecvStream;

use super::fault::{ConnectionEnd, Fault};
use crate::config::Settings;
use crate::metrics::Metrics;

pub(super) async fn read_hello(recv: &mut RecvStream) -> Result<ClientHello, ConnectionEnd> {
    let mut buf = BytesMut::new();
    loop {
        match decode_framed(&mut buf) {
            Ok(Some(Message::ClientHello(h))) => return Ok(h),
            Ok(Some(other)) => {
                return Err(Fault::new(
                    CloseCode::ProtocolViolation,
                    format!("first message must be ClientHello, got tag {}", other.tag()),
                )
                .into());
            }
            Ok(None) => {}
            Err(e) => return Err(Fault::decode(&e).into()),
        }
        match recv.read_chunk(8 * 1024, true).await {
            Ok(Some(chunk)) => buf.extend_from_slice(&chunk.bytes),
            Ok(None) => {
                return Err(Fault::new(
                    CloseCode::ProtocolViolation,
                    "control stream finished before ClientHello",
                )
                .into());
            }
            Err(e) => return Err(ConnectionEnd::Gone(e.to_string())),
        }
    }
}

/// Compares without an early exit on the first differing byte.
fn token_eq(a: &str, b: &str) -> bool {
    a.len() == b.len() && a.bytes().zip(b.bytes()).fold(0_u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

pub(super) fn authorize(hello: &ClientHello, settings: &Settings, metrics: &Metrics) -> Result<(), Fault> {
    if !(MIN_PROTOCOL_VERSION..=PROTOCOL_VERSION).contains(&hello.version) {
        metrics.auth_bad_version.fetch_add(1, Ordering::Relaxed);
        return Err(Fault::new(
            CloseCode::BadVersion,
            format!(
                "protocol version {} not supported (server speaks {MIN_PROTOCOL_VERSION} to {PROTOCOL_VERSION})",
                hello.version
            ),
        ));
    }
    let ok = settings.allow_anonymous
        || settings
            .tokens
            .iter()
            .fold(false, |found, t| found | token_eq(t, &hello.token));
    if !ok {
        metrics.auth_unauthorized.fetch_add(1, Ordering::Relaxed);
        return Err(Fault::new(CloseCode::Unauthorized, "token rejected"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_comparison() {
        assert!(token_eq("abc", "abc"));
        assert!(!token_eq("abc", "abd"));
        assert!(!token_eq("abc", "abcd"));
        assert!(token_eq("", ""));
    }

    fn hello(version: u16, token: &str) -> ClientHello {
        ClientHello {
            version,
            token: token.into(),
            client_name: "t".into(),
            encodings: vec![],
            max_in_flight: 1,
        }
    }

    #[test]
    fn version_is_checked_before_the_token() {
        let settings = Settings::for_loopback("good", "m.onnx".into(), None, "l.so".into()).unwrap();
        let m = Metrics::new(8);
        let f = authorize(&hello(99, "bad"), &settings, &m).unwrap_err();
        assert_eq!(f.code, CloseCode::BadVersion);
        let f = authorize(&hello(PROTOCOL_VERSION, "bad"), &settings, &m).unwrap_err();
        assert_eq!(f.code, CloseCode::Unauthorized);
        authorize(&hello(PROTOCOL_VERSION, "good"), &settings, &m).unwrap();
        assert_eq!(m.auth_bad_version.load(Ordering::Relaxed), 1);
        assert_eq!(m.auth_unauthorized.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn every_version_from_the_oldest_served_to_ours_is_served_and_no_other() {
        let settings = Settings::for_loopback("good", "m.onnx".into(), None, "l.so".into()).unwrap();
        let m = Metrics::new(8);
        for v in MIN_PROTOCOL_VERSION..=PROTOCOL_VERSION {
            authorize(&hello(v, "good"), &settings, &m).unwrap();
        }
        for v in [0, MIN_PROTOCOL_VERSION - 1, PROTOCOL_VERSION + 1, u16::MAX] {
            let f = authorize(&hello(v, "good"), &settings, &m).unwrap_err();
            assert_eq!(f.code, CloseCode::BadVersion, "version {v}");
            assert!(
                f.detail
                    .contains(&format!("{MIN_PROTOCOL_VERSION} to {PROTOCOL_VERSION}")),
                "{}",
                f.detail
            );
        }
    }
}
