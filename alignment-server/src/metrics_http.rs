//! The internal HTTP listener: `GET /metrics` (Prometheus text) and
//! `GET /health` (200 when ready, 503 otherwise), on a loopback or
//! private-network address only, off by default.
//!
//! It is a deliberately tiny HTTP/1.1 responder: one request per connection,
//! a 4 KiB request limit and a 2 s read timeout, so a misbehaving scraper
//! cannot hold resources.

use std::net::IpAddr;
#[cfg(test)]
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;
use tracing::debug;

use crate::metrics::Metrics;

const MAX_REQUEST: usize = 4096;
const READ_TIMEOUT: Duration = Duration::from_secs(2);

/// `true` for loopback, RFC 1918 / unique-local and link-local addresses.
pub fn is_internal_addr(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(v4) => v4.is_loopback() || v4.is_private() || v4.is_link_local(),
        IpAddr::V6(v6) => {
            v6.is_loopback() || (v6.segments()[0] & 0xfe00) == 0xfc00 || (v6.segments()[0] & 0xffc0) == 0xfe80
        }
    }
}

/// Serves `/metrics` and `/health` until `shutdown` turns `true`.
pub async fn serve(listener: TcpListener, metrics: Arc<Metrics>, mut shutdown: watch::Receiver<bool>) {
    loop {
        tokio::select! {
            () = crate::server::lifecycle::stopped(&mut shutdown) => return,
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    let metrics = Arc::clone(&metrics);
                    tokio::spawn(async move {
                        if let Err(e) = respond(stream, &metrics).await {
                            debug!(%peer, %e, "internal listener request failed");
                        }
                    });
                }
                Err(e) => {
                    debug!(%e, "internal listener accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            }
        }
    }
}

async fn respond(mut stream: TcpStream, metrics: &Metrics) -> std::io::Result<()> {
    let mut buf = vec![0_u8; MAX_REQUEST];
    let mut len = 0;
    let head_done = |b: &[u8]| b.windows(4).any(|w| w == b"\r\n\r\n") || b.windows(2).any(|w| w == b"\n\n");
    while !head_done(buf.get(..len).unwrap_or_default()) {
        let Some(rest) = buf.get_mut(len..) else { break };
        if rest.is_empty() {
            break;
        }
        let n = match tokio::time::timeout(READ_TIMEOUT, stream.read(rest)).await {
            Ok(r) => r?,
            Err(_) => return Ok(()),
        };
        if n == 0 {
            break;
        }
        len += n;
    }
    let head = String::from_utf8_lossy(buf.get(..len).unwrap_or_default());
    let mut parts = head.split_whitespace();
    let (method, path) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""));
    let (status, ctype, body) = match (method, path) {
        ("GET", "/metrics") => ("200 OK", "text/plain; version=0.0.4", metrics.render()),
        ("GET", "/health") if metrics.healthy() => ("200 OK", "text/plain", "ok\n".to_owned()),
        ("GET", "/health") => ("503 Service Unavailable", "text/plain", "not ready\n".to_owned()),
        ("GET", _) => ("404 Not Found", "text/plain", "not found\n".to_owned()),
        _ => (
            "405 Method Not Allowed",
            "text/plain",
            "method not allowed\n".to_owned(),
        ),
    };
    let response = format!(
        "HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(response.as_bytes()).await?;
    stream.shutdown().await
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::Ordering;

    async fn get(addr: SocketAddr, path: &str) -> String {
        let mut s = TcpStream::connect(addr).await.unwrap();
        s.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes())
            .await
            .unwrap();
        let mut out = String::new();
        s.read_to_string(&mut out).await.unwrap();
        out
    }

    #[tokio::test]
    async fn serves_metrics_and_health() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let metrics = Arc::new(Metrics::new(8));
        let (tx, rx) = watch::channel(false);
        let task = tokio::spawn(serve(listener, Arc::clone(&metrics), rx));
        assert!(get(addr, "/health").await.starts_with("HTTP/1.1 503"));
        metrics.ready.store(true, Ordering::Relaxed);
        assert!(get(addr, "/health").await.starts_with("HTTP/1.1 200"));
        let m = get(addr, "/metrics").await;
        assert!(m.starts_with("HTTP/1.1 200") && m.contains("holoface_connected_clients 0"));
        assert!(get(addr, "/nope").await.starts_with("HTTP/1.1 404"));
        tx.send(true).unwrap();
        task.await.unwrap();
    }

    #[test]
    fn internal_addresses() {
        for ok in ["127.0.0.1", "10.1.2.3", "192.168.0.1", "::1", "fd00::1"] {
            assert!(is_internal_addr(ok.parse().unwrap()), "{ok}");
        }
        for bad in ["0.0.0.0", "8.8.8.8", "::", "2001:db8::1"] {
            assert!(!is_internal_addr(bad.parse().unwrap()), "{bad}");
        }
    }
}
