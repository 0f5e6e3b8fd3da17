//! Sending frame replies: one datagram each, or framed on one server-opened reply stream.

use std::time::Duration;

use bytes::{Bytes, BytesMut};
use holoface_inference::ModelInfo;
use holoface_protocol::{FrameReply, Message, ReplyChannel, encode_framed};
use quinn::{Connection, SendStream};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tracing::{debug, warn};

/// How long a draining connection waits for the peer to acknowledge its last data.
pub(super) const CLOSE_GRACE: Duration = Duration::from_secs(1);

#[derive(Debug, Clone)]
pub(super) enum ReplySink {
    Datagram(Connection),
    Stream(mpsc::Sender<Bytes>),
}

impl ReplySink {
    pub(super) fn send(&self, reply: FrameReply) {
        let msg = Message::FrameReply(reply);
        match self {
            Self::Datagram(conn) => match msg.to_bytes() {
                Ok(bytes) => {
                    if let Err(e) = conn.send_datagram(bytes) {
                        debug!(%e, "reply datagram not sent");
                    }
                }
                Err(e) => warn!(%e, "reply does not encode"),
            },
            Self::Stream(tx) => {
                let mut buf = BytesMut::new();
                match encode_framed(&msg, &mut buf) {
                    Ok(()) => {
                        if tx.try_send(buf.freeze()).is_err() {
                            debug!("reply stream backlog full: reply dropped");
                        }
                    }
                    Err(e) => warn!(%e, "reply does not encode"),
                }
            }
        }
    }
}

/// The sink for the reply channel the welcome announced, and the reply-stream
/// writer task when replies go on a stream.
pub(super) fn reply_sink(
    conn: &Connection,
    reply_channel: ReplyChannel,
    max_in_flight: u16,
) -> (ReplySink, Option<JoinHandle<()>>) {
    match reply_channel {
        ReplyChannel::Datagram => (ReplySink::Datagram(conn.clone()), None),
        ReplyChannel::Stream => {
            let (tx, rx) = mpsc::channel(usize::from(max_in_flight) * 4 + 4);
            (
                ReplySink::Stream(tx),
                Some(tokio::spawn(reply_writer(conn.clone(), rx))),
            )
        }
    }
}

async fn reply_writer(conn: Connection, mut rx: mpsc::Receiver<Bytes>) {
    let mut stream: Option<SendStream> = None;
    while let Some(bytes) = rx.recv().await {
        if stream.is_none() {
            match conn.open_uni().await {
                Ok(s) => stream = Some(s),
                Err(e) => {
                    debug!(%e, "cannot open the reply stream");
                    return;
                }
            }
        }
        if let Some(s) = stream.as_mut()
            && let Err(e) = s.write_all(&bytes).await
        {
            debug!(%e, "reply stream write failed");
            return;
        }
    }
    if let Some(mut s) = stream
        && s.finish().is_ok()
    {
        let _ = tokio::time::timeout(CLOSE_GRACE, s.stopped()).await;
    }
}

pub(super) fn max_reply_len(model: &ModelInfo) -> usize {
    // tag + frame_id + outcome + count + points + prob + queue + infer
    1 + 8 + 1 + 2 + 8 * model.landmark_count + 4 + 4 + 4
}
