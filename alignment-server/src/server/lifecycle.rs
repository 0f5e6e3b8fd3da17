//! Process lifecycle: telling systemd the server is ready, the signals that stop it, and the stop switch
//! every task of the server waits on ([`stopped`]).

use tokio::sync::watch;
use tracing::warn;

/// Resolves once `stop` is (or becomes) `true`, or its sender is gone: the shutdown wait of the accept loop,
/// every connection, the scheduler and the metrics listener.
pub(crate) async fn stopped(stop: &mut watch::Receiver<bool>) {
    let _ = stop.wait_for(|s| *s).await;
}

/// Tells systemd (`Type=notify` units) that the server is ready: `READY=1` on `$NOTIFY_SOCKET`, if set.
/// Without systemd this does nothing; a failure is logged, never fatal.
pub(super) fn notify_systemd_ready() {
    if let Some(path) = std::env::var_os("NOTIFY_SOCKET") {
        notify_ready_at(&path);
    }
}

/// Sends `READY=1` to the notify socket at `path` (`@name` = abstract namespace).
fn notify_ready_at(path: &std::ffi::OsStr) {
    let sent = std::os::unix::net::UnixDatagram::unbound().and_then(|sock| {
        let bytes = std::os::unix::ffi::OsStrExt::as_bytes(path);
        match bytes.strip_prefix(b"@") {
            // Abstract socket namespace (Linux).
            Some(name) => {
                use std::os::linux::net::SocketAddrExt;
                let addr = std::os::unix::net::SocketAddr::from_abstract_name(name)?;
                sock.send_to_addr(b"READY=1", &addr)
            }
            None => sock.send_to(b"READY=1", path),
        }
    });
    if let Err(e) = sent {
        warn!(error = %e, "could not notify systemd of readiness");
    }
}

/// Resolves on SIGINT (Ctrl-C) or SIGTERM: the production shutdown trigger.
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(e) => {
                warn!(%e, "cannot listen for SIGTERM; only Ctrl-C stops the server");
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

#[cfg(test)]
mod notify_tests {
    use super::notify_ready_at;

    #[test]
    fn readiness_goes_to_the_notify_socket() {
        let dir = std::env::temp_dir().join(format!("holoface-notify-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("notify.sock");
        let sock = std::os::unix::net::UnixDatagram::bind(&path).unwrap();
        notify_ready_at(path.as_os_str());
        let mut buf = [0u8; 32];
        sock.set_read_timeout(Some(std::time::Duration::from_secs(1)))
            .unwrap();
        let n = sock.recv(&mut buf).unwrap();
        assert_eq!(&buf[..n], b"READY=1");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
