//! The alignment server in this process, on loopback: what the demo and `multi-face --aligner remote`
//! talk to over real QUIC.

use std::net::SocketAddr;

use holoface_alignment_server::Fingerprint;

use crate::args::RuntimeArgs;

/// A running in-process server; [`LoopbackServer::stop`] shuts it down gracefully.
#[derive(Debug)]
pub struct LoopbackServer {
    rt: tokio::runtime::Runtime,
    /// Where it listens.
    pub addr: SocketAddr,
    /// Its certificate's fingerprint (what a client pins).
    pub fingerprint: Fingerprint,
    /// The access token it accepts (random per run).
    pub token: String,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Result<(), holoface_alignment_server::ServerError>>,
}

impl LoopbackServer {
    /// Binds a server with the runtime's DAN model and ONNX Runtime, `threads` intra-op threads, and
    /// `tweak` applied to its loopback settings.
    pub fn start(
        runtime: &RuntimeArgs,
        threads: usize,
        tweak: impl FnOnce(&mut holoface_alignment_server::config::Settings),
    ) -> anyhow::Result<Self> {
        let token = format!("loopback-{:016x}", {
            use std::hash::{BuildHasher, Hasher};
            std::collections::hash_map::RandomState::new()
                .build_hasher()
                .finish()
        });
        let mut settings = holoface_alignment_server::config::Settings::for_loopback(
            &token,
            runtime.dan_model.clone(),
            Some(runtime.refine_model.clone()),
            runtime.ort_dylib(),
        )?;
        settings.engine.intra_threads = threads;
        tweak(&mut settings);
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()?;
        let server = rt.block_on(holoface_alignment_server::AlignmentServer::bind(settings))?;
        let (addr, fingerprint) = (server.local_addr()?, server.fingerprint());
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = rt.spawn(server.run(async move {
            let _ = stopped.await;
        }));
        Ok(Self {
            rt,
            addr,
            fingerprint,
            token,
            stop,
            task,
        })
    }

    /// The runtime the server runs on (for helpers such as the demo's relay).
    pub fn runtime(&self) -> &tokio::runtime::Runtime {
        &self.rt
    }

    /// Stops the server and waits for it; a failure is printed, not returned (the run's results stand).
    pub fn stop(self) {
        let _ = self.stop.send(());
        match self.rt.block_on(self.task) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => tracing::error!(error = %e, "the loopback server stopped with an error"),
            Err(e) => tracing::error!(error = %e, "the loopback server's task failed"),
        }
    }
}
