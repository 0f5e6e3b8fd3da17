//! A real alignment server in its own process, for fault tests that kill it (SIGKILL) and restart it on
//! the same port with the same certificate.
//!
//! `holoface-e2e-server <listen> <cert.pem> <key.pem>` prints `ready <addr> <fingerprint>` on stdout when
//! it accepts connections, and exits when stdin closes (so a crashed test leaves no orphan).

use std::io::{BufRead, Write};
use std::net::SocketAddr;

use holoface_alignment_server::AlignmentServer;
use holoface_alignment_server::config::TlsSource;
use holoface_tests::loopback_settings;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [listen, cert, key] = args.as_slice() else {
        anyhow::bail!("usage: holoface-e2e-server <listen addr> <cert.pem> <key.pem>");
    };
    let mut settings = loopback_settings();
    settings.listen = listen.parse::<SocketAddr>()?;
    settings.tls = TlsSource::Files {
        cert: cert.into(),
        key: key.into(),
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    rt.block_on(async move {
        let server = AlignmentServer::bind(settings).await?;
        let addr = server.local_addr()?;
        let mut out = std::io::stdout();
        writeln!(out, "ready {addr} {}", server.fingerprint())?;
        out.flush()?;
        let stdin_closed = async {
            let _ = tokio::task::spawn_blocking(|| {
                let mut line = String::new();
                let mut stdin = std::io::stdin().lock();
                while stdin.read_line(&mut line).map(|n| n > 0).unwrap_or(false) {
                    line.clear();
                }
            })
            .await;
        };
        server.run(stdin_closed).await?;
        anyhow::Ok(())
    })
}
