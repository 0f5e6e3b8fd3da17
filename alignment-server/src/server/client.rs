//! The per-connection task: handshake, welcome, the frame loop and the graceful drain.

use std::sync::Arc;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bytes::BytesMut;
use holoface_protocol::{
    ClientHello, CloseCode, CropEncoding, Goaway, Message, ReplyChannel, ServerWelcome, decode_framed,
    encode_framed,
};
use quinn::{Connection, Incoming, RecvStream, SendStream, VarInt};
use tokio::sync::watch;
use tokio::task::{JoinHandle, JoinSet};
use tracing::{debug, info};

use super::admission::PendingSlot;
use super::auth::{authorize, read_hello};
use super::fault::{ConnectionEnd, Fault, close_conn};
use super::frame_stream::{ConnCtx, frame_task};
use super::rate_limit::RateLimit;
use super::reply::{CLOSE_GRACE, max_reply_len, reply_sink};
use super::scheduler::SchedMsg;
use super::{Shared, code};
use crate::batcher::ClientId;

/// Decrements a gauge when dropped.
struct GaugeGuard<'a>(&'a AtomicI64);

impl<'a> GaugeGuard<'a> {
    fn new(g: &'a AtomicI64) -> Self {
        g.fetch_add(1, Ordering::Relaxed);
        Self(g)
    }
}

impl Drop for GaugeGuard<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

/// One connection from its first packet: the TLS handshake and the hello run inside the pending budget
/// (`slot`, bounded by the hello timeout and evictable by newer attempts); only an authenticated client takes a
/// client slot.
pub(super) async fn connection(incoming: Incoming, slot: PendingSlot, shared: Arc<Shared>) {
    let remote = incoming.remote_address();
    let tls = async {
        match incoming.accept() {
            Ok(connecting) => connecting.await,
            Err(e) => Err(e),
        }
    };
    let conn = tokio::select! {
        r = tokio::time::timeout(shared.settings.hello_timeout, tls) => match r {
            Ok(Ok(c)) => c,
            Ok(Err(e)) => {
                debug!(%remote, %e, "handshake failed");
                return;
            }
            Err(_) => {
                debug!(%remote, "TLS handshake not finished within the hello timeout; dropped");
                return;
            }
        },
        () = slot.evicted() => {
            debug!(%remote, "half-open connection evicted for a newer one (pending budget full)");
            return;
        }
    };
    let metrics = &shared.metrics;
    metrics.connections_total.fetch_add(1, Ordering::Relaxed);
    let client = shared.next_client.fetch_add(1, Ordering::Relaxed);
    let end = serve_connection(&conn, client, &shared, slot).await;
    let _ = shared.sched.try_send(SchedMsg::Disconnect(client));
    match end {
        ConnectionEnd::Gone(why) => debug!(client, %remote, why, "client gone"),
        ConnectionEnd::Shutdown => {
            metrics.count_close(CloseCode::ShuttingDown);
            close_conn(&conn, CloseCode::ShuttingDown, CloseCode::ShuttingDown.reason());
            // Let the CONNECTION_CLOSE go out before the endpoint is closed.
            let _ = tokio::time::timeout(Duration::from_millis(200), conn.closed()).await;
        }
        ConnectionEnd::Fault(f) => {
            metrics.count_close(f.code);
            shared.log_fault(client, remote, &f);
            close_conn(&conn, f.code, &f.detail);
        }
    }
}

/// After the Goaway, frame streams that arrive this long are still served (they were sent before the client
/// could see it); later ones are refused.
const GOAWAY_GRACE: Duration = Duration::from_millis(200);

/// How often each connection's RTT and loss are sampled into the metrics.
const STATS_PERIOD: Duration = Duration::from_secs(5);

/// Serves one accepted connection: the hello and its checks, the welcome,
/// then frames until the client leaves, misbehaves or the server stops.
async fn serve_connection(
    conn: &Connection,
    client: ClientId,
    shared: &Arc<Shared>,
    slot: PendingSlot,
) -> ConnectionEnd {
    let settings = &shared.settings;
    let mut stop = shared.stop.clone();
    // 1. The control stream and the hello, within the hello timeout (evictable while unauthenticated).
    let (mut ctl_send, mut ctl_recv, hello) = match handshake(conn, shared, &mut stop, &slot).await {
        Ok(v) => v,
        Err(end) => return end,
    };
    // Authenticated: leave the pending budget for a client slot.
    let Some(_permit) = slot.promote() else {
        shared.metrics.rejected_overloaded.fetch_add(1, Ordering::Relaxed);
        // Logged (within the misbehaving-client log's bounds) as the close.
        return Fault::new(
            CloseCode::Overloaded,
            format!("client cap reached ({} clients)", settings.max_clients),
        )
        .into();
    };
    let _gauge = GaugeGuard::new(&shared.metrics.connected_clients);

    // 2. Welcome.
    let (reply_channel, max_in_flight) = match send_welcome(conn, client, shared, &hello, &mut ctl_send).await
    {
        Ok(v) => v,
        Err(end) => return end,
    };
    let (sink, writer) = reply_sink(conn, reply_channel, max_in_flight);
    let ctx = Arc::new(ConnCtx {
        client,
        shared: Arc::clone(shared),
        sink,
        newest: std::sync::Mutex::new(super::frame_stream::NewestFrames::default()),
        read_timeout: settings.hello_timeout.max(settings.max_frame_age),
        version: hello.version,
    });

    // 3. Frames until the client leaves, misbehaves, or the server stops.
    let mut frames: JoinSet<Result<(), Fault>> = JoinSet::new();
    let end = frame_loop(conn, &ctx, &mut ctl_recv, &mut frames, &mut stop).await;

    match end {
        ConnectionEnd::Shutdown => {
            drain_on_shutdown(conn, &mut ctl_send, &mut frames, ctx, writer).await;
            ConnectionEnd::Shutdown
        }
        other => {
            frames.abort_all();
            if let Some(w) = writer {
                w.abort();
            }
            other
        }
    }
}

/// Accepts the control stream and reads the `ClientHello` within the hello
/// timeout (or until the server stops), then checks version and token.
async fn handshake(
    conn: &Connection,
    shared: &Shared,
    stop: &mut watch::Receiver<bool>,
    slot: &PendingSlot,
) -> Result<(SendStream, RecvStream, ClientHello), ConnectionEnd> {
    let settings = &shared.settings;
    let handshake = async {
        let (send, mut recv) = conn
            .accept_bi()
            .await
            .map_err(|e| ConnectionEnd::Gone(e.to_string()))?;
        let hello = read_hello(&mut recv).await?;
        Ok::<_, ConnectionEnd>((send, recv, hello))
    };
    let (ctl_send, ctl_recv, hello) = tokio::select! {
        r = tokio::time::timeout(settings.hello_timeout, handshake) => match r {
            Ok(Ok(v)) => v,
            Ok(Err(end)) => return Err(end),
            Err(_) => {
                let f = Fault::new(CloseCode::ProtocolViolation, "no ClientHello before the hello timeout");
                return Err(f.into());
            }
        },
        () = super::lifecycle::stopped(stop) => return Err(ConnectionEnd::Shutdown),
        () = slot.evicted() => {
            let f = Fault::new(CloseCode::Overloaded, "evicted: too many connections without a hello");
            return Err(f.into());
        }
    };
    authorize(&hello, settings, &shared.metrics)?;
    Ok((ctl_send, ctl_recv, hello))
}

/// Picks the encoding, reply channel and in-flight limit, writes the framed
/// `ServerWelcome` on the control stream and logs the new client.
async fn send_welcome(
    conn: &Connection,
    client: ClientId,
    shared: &Shared,
    hello: &ClientHello,
    ctl_send: &mut SendStream,
) -> Result<(ReplyChannel, u16), ConnectionEnd> {
    let settings = &shared.settings;
    let encoding = hello.encodings.first().copied().unwrap_or(CropEncoding::Raw);
    let reply_channel = match (settings.reply_channel, conn.max_datagram_size()) {
        (ReplyChannel::Datagram, Some(max)) if max >= 1200.min(max_reply_len(&shared.model)) => {
            ReplyChannel::Datagram
        }
        _ => ReplyChannel::Stream,
    };
    let max_in_flight = hello.max_in_flight.clamp(1, settings.max_in_flight);
    conn.set_max_concurrent_uni_streams(VarInt::from(u32::from(max_in_flight)));
    let model = &shared.model;
    let welcome = Message::ServerWelcome(ServerWelcome {
        // Served at the client's version (authorize checked it is one we speak).
        version: hello.version,
        model_id: model.name.clone(),
        // The release and the precision serving it ("0.4.0+int8"): all a client sees of the choice.
        model_version: format!("{}+{}", model.version, model.precision),
        landmark_count: u16::try_from(model.landmark_count).unwrap_or(u16::MAX),
        crop_size: u16::try_from(model.crop_size).unwrap_or(u16::MAX),
        mean_shape: model.mean_shape.clone(),
        face_threshold: model.face_threshold,
        encoding,
        reply_channel,
        max_in_flight,
        max_frame_age_ms: u32::try_from(settings.max_frame_age.as_millis()).unwrap_or(u32::MAX),
    });
    let mut buf = BytesMut::new();
    if let Err(e) = encode_framed(&welcome, &mut buf) {
        return Err(Fault::new(CloseCode::Internal, format!("welcome does not encode: {e}")).into());
    }
    if let Err(e) = ctl_send.write_all(&buf).await {
        return Err(ConnectionEnd::Gone(e.to_string()));
    }
    info!(
        client,
        remote = %conn.remote_address(),
        // The name is the client's own text: escaped and bounded so it cannot forge a log line.
        name = %holoface_protocol::untrusted(&hello.client_name),
        ?encoding,
        ?reply_channel,
        max_in_flight,
        "client connected"
    );
    Ok((reply_channel, max_in_flight))
}

/// Accepts frame streams, samples the path statistics and watches the control
/// stream and datagrams until the client leaves, misbehaves or the server stops.
async fn frame_loop(
    conn: &Connection,
    ctx: &Arc<ConnCtx>,
    ctl_recv: &mut RecvStream,
    frames: &mut JoinSet<Result<(), Fault>>,
    stop: &mut watch::Receiver<bool>,
) -> ConnectionEnd {
    let shared = &ctx.shared;
    let settings = &shared.settings;
    let mut rate = RateLimit::new(settings.max_frame_rate, Instant::now());
    let mut stats_tick = tokio::time::interval(STATS_PERIOD);
    let mut lost_reported = 0_u64;
    let mut ctl_buf = BytesMut::new();
    let mut ctl_open = true;
    loop {
        tokio::select! {
            () = super::lifecycle::stopped(stop) => break ConnectionEnd::Shutdown,
            _ = stats_tick.tick() => {
                let path = conn.stats().path;
                shared.metrics.client_rtt_us.observe_duration(path.rtt);
                let lost = path.lost_packets;
                shared
                    .metrics
                    .client_lost_packets
                    .fetch_add(lost.saturating_sub(lost_reported), Ordering::Relaxed);
                lost_reported = lost;
            },
            stream = conn.accept_uni() => match stream {
                Ok(recv) => {
                    if !rate.take(Instant::now()) {
                        break Fault::new(
                            CloseCode::Overloaded,
                            format!("frame rate above {} per second", settings.max_frame_rate),
                        )
                        .into();
                    }
                    frames.spawn(frame_task(recv, Arc::clone(ctx)));
                }
                Err(e) => break ConnectionEnd::Gone(e.to_string()),
            },
            datagram = conn.read_datagram() => match datagram {
                Ok(bytes) => {
                    break match Message::decode(bytes) {
                        Err(e) => Fault::decode(&e).into(),
                        Ok(m) => Fault::new(
                            CloseCode::ProtocolViolation,
                            format!("clients must not send datagrams (got tag {})", m.tag()),
                        )
                        .into(),
                    };
                }
                Err(e) => break ConnectionEnd::Gone(e.to_string()),
            },
            chunk = ctl_recv.read_chunk(4096, true), if ctl_open => match chunk {
                Ok(Some(c)) => {
                    ctl_buf.extend_from_slice(&c.bytes);
                    match decode_framed(&mut ctl_buf) {
                        Ok(None) => {}
                        Ok(Some(Message::Error(e))) => {
                            break ConnectionEnd::Gone(format!(
                                "client error {}: {}",
                                e.code,
                                holoface_protocol::untrusted(&e.text)
                            ));
                        }
                        Ok(Some(m)) => {
                            break Fault::new(
                                CloseCode::ProtocolViolation,
                                format!("unexpected message (tag {}) on the control stream", m.tag()),
                            )
                            .into();
                        }
                        Err(e) => break Fault::decode(&e).into(),
                    }
                }
                Ok(None) => ctl_open = false,
                Err(e) => break ConnectionEnd::Gone(e.to_string()),
            },
            Some(joined) = frames.join_next(), if !frames.is_empty() => match joined {
                Ok(Ok(())) => {}
                Ok(Err(fault)) => break fault.into(),
                Err(e) => break Fault::new(CloseCode::Internal, format!("frame task failed: {e}")).into(),
            },
        }
    }
}

/// Graceful shutdown of one connection: `Goaway`, then answer what is in
/// flight, then finish the control stream.
async fn drain_on_shutdown(
    conn: &Connection,
    ctl_send: &mut SendStream,
    frames: &mut JoinSet<Result<(), Fault>>,
    ctx: Arc<ConnCtx>,
    writer: Option<JoinHandle<()>>,
) {
    // Goaway, then answer what is in flight (the scheduler drains).
    let mut buf = BytesMut::new();
    let goaway = Message::Goaway(Goaway {
        reason: CloseCode::ShuttingDown,
        text: "server shutting down".into(),
    });
    if encode_framed(&goaway, &mut buf).is_ok() {
        let _ = tokio::time::timeout(Duration::from_millis(500), ctl_send.write_all(&buf)).await;
    }
    // The whole drain fits the shutdown timeout: in-flight frames get until two close graces before it, the
    // reply writer and the control stream one grace each.
    let deadline = ctx.shared.settings.shutdown_timeout;
    let frames_until = tokio::time::Instant::now() + deadline.saturating_sub(2 * CLOSE_GRACE);
    // Frame streams the client opened before it saw the Goaway (arriving within `GOAWAY_GRACE`) are still
    // answered: landmarks if batched in time, else Dropped{ShuttingDown} from the draining scheduler. Later
    // ones are refused (`STOP_SENDING` with ShuttingDown) and the client's stream credit goes to zero, so a
    // client that ignores the Goaway cannot keep the drain going.
    conn.set_max_concurrent_uni_streams(VarInt::from_u32(0));
    let serve_until = tokio::time::Instant::now() + GOAWAY_GRACE;
    let refused = AtomicU64::new(0);
    let drain = async {
        loop {
            let serving = tokio::time::Instant::now() < serve_until;
            if !serving && frames.is_empty() {
                break;
            }
            tokio::select! {
                Some(_) = frames.join_next(), if !frames.is_empty() => {}
                stream = conn.accept_uni() => match stream {
                    Ok(recv) if tokio::time::Instant::now() < serve_until => {
                        frames.spawn(frame_task(recv, Arc::clone(&ctx)));
                    }
                    Ok(mut recv) => {
                        let _ = recv.stop(code(CloseCode::ShuttingDown));
                        refused.fetch_add(1, Ordering::Relaxed);
                    }
                    Err(_) => break,
                },
                () = tokio::time::sleep_until(serve_until), if serving => {}
            }
        }
    };
    let _ = tokio::time::timeout_at(frames_until, drain).await;
    let refused = refused.into_inner();
    if refused > 0 {
        debug!(
            client = ctx.client,
            refused, "frame streams refused after the Goaway"
        );
    }
    frames.abort_all();
    drop(ctx);
    if let Some(w) = writer {
        let _ = tokio::time::timeout(CLOSE_GRACE, w).await;
    }
    // Finish the control stream and wait (bounded) for the peer to
    // acknowledge it: the Goaway and the last replies, queued before
    // the FIN, are then on the client's side before the close.
    if ctl_send.finish().is_ok() {
        let _ = tokio::time::timeout(CLOSE_GRACE.min(deadline), ctl_send.stopped()).await;
    }
}
