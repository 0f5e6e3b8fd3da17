//! One frame stream: reading the `FrameRequest`, frame-id ordering, crop decoding and submission.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use bytes::Bytes;
use holoface_protocol::limits::MAX_MESSAGE_LEN;
use holoface_protocol::{CloseCode, Crop, DropReason, FrameReply, FrameRequest, Message, ReplyOutcome};
use quinn::{ReadToEndError, RecvStream};
use tokio::sync::{mpsc, oneshot};
use tracing::debug;

use super::Shared;
use super::code;
use super::fault::Fault;
use super::reply::ReplySink;
use super::scheduler::{FrameJob, FrameOutcome, SchedMsg};
use crate::batcher::ClientId;
use crate::batcher::Pending;

/// Per-connection state shared by its frame tasks.
#[derive(Debug)]
pub(super) struct ConnCtx {
    pub(super) client: ClientId,
    pub(super) shared: Arc<Shared>,
    pub(super) sink: ReplySink,
    /// Highest frame id seen per track.
    pub(super) newest: std::sync::Mutex<NewestFrames>,
    pub(super) read_timeout: Duration,
    /// The protocol version this client speaks (replies use only what it decodes).
    pub(super) version: u16,
}

/// Decodes a crop into `size` x `size` gray8 pixels (`None`: another size, or a payload that does not
/// decode within the limits of [`holoface_inference::decode_crop`]).
fn crop_pixels(crop: &Crop, size: usize) -> Option<Bytes> {
    if usize::from(crop.width) != size || usize::from(crop.height) != size {
        return None;
    }
    holoface_inference::decode_crop(crop).ok()
}

pub(super) async fn frame_task(mut recv: RecvStream, ctx: Arc<ConnCtx>) -> Result<(), Fault> {
    let data = match tokio::time::timeout(ctx.read_timeout, recv.read_to_end(MAX_MESSAGE_LEN)).await {
        Err(_) => {
            let _ = recv.stop(code(CloseCode::NoError));
            debug!(client = ctx.client, "frame stream not finished in time: ignored");
            return Ok(());
        }
        Ok(Err(ReadToEndError::TooLong)) => {
            return Err(Fault::new(
                CloseCode::TooLarge,
                format!("frame stream longer than {MAX_MESSAGE_LEN} bytes"),
            ));
        }
        Ok(Err(ReadToEndError::Read(e))) => {
            // Reset by the client (a stale frame it gave up on) or connection loss.
            debug!(client = ctx.client, %e, "frame stream not read");
            return Ok(());
        }
        Ok(Ok(d)) => d,
    };
    let req = match Message::decode(Bytes::from(data)) {
        Ok(Message::FrameRequest(r)) => r,
        Ok(other) => {
            return Err(Fault::new(
                CloseCode::ProtocolViolation,
                format!(
                    "a frame stream must carry a FrameRequest (got tag {})",
                    other.tag()
                ),
            ));
        }
        Err(e) => return Err(Fault::decode(&e)),
    };
    let metrics = &ctx.shared.metrics;
    metrics.frames_received.fetch_add(1, Ordering::Relaxed);
    let (frame_id, track_id) = (req.frame_id, req.track_id);
    if track_id != 0 && ctx.version < 3 {
        return Err(Fault::new(
            CloseCode::ProtocolViolation,
            format!(
                "a track id needs protocol version 3 (this client said {})",
                ctx.version
            ),
        ));
    }
    let outcome = align(&ctx, req).await?;
    let outcome = match outcome {
        FrameOutcome::Landmarks {
            landmarks,
            face_prob,
            queue_us,
            infer_us,
        } => ReplyOutcome::Landmarks {
            landmarks,
            face_prob,
            queue_us,
            infer_us,
        },
        FrameOutcome::Dropped(reason) => ReplyOutcome::Dropped {
            reason: reason.for_version(ctx.version),
        },
    };
    ctx.sink.send(FrameReply {
        frame_id,
        outcome,
        track_id,
    });
    // The stream (and its flow-control credit) is released only now, so a
    // client cannot have more than max_in_flight frames being worked on.
    drop(recv);
    Ok(())
}

/// Where a frame's id stands against the newest id seen for its track on its connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FrameOrder {
    /// Newer than every frame of this track so far (now the newest).
    Newest,
    /// The newest id of this track again: a protocol violation.
    Duplicate,
    /// Older than the track's newest: superseded.
    Older,
}

/// Tracks remembered per connection. A headset tracks a handful of faces and never reuses a retired
/// face's track id soon; beyond this many the track whose newest frame is oldest is forgotten (its next
/// crop, if any, simply counts as newest), so a client cycling through track ids cannot grow server state.
pub(super) const TRACKS_REMEMBERED: usize = 64;

/// The newest frame id of each track of one connection (track 0 is a one-face client's only track).
#[derive(Debug, Default)]
pub(super) struct NewestFrames {
    tracks: Vec<(u16, u64)>,
}

impl NewestFrames {
    /// Classifies `id` of `track` and records it when it is the newest. Every `u64` is a valid id,
    /// `u64::MAX` included. Several tracks may carry the same id (one camera frame, several faces).
    fn order(&mut self, track: u16, id: u64) -> FrameOrder {
        match self.tracks.iter_mut().find(|(t, _)| *t == track) {
            Some((_, prev)) if id == *prev => FrameOrder::Duplicate,
            Some((_, prev)) if id < *prev => FrameOrder::Older,
            Some((_, prev)) => {
                *prev = id;
                FrameOrder::Newest
            }
            None => {
                if self.tracks.len() >= TRACKS_REMEMBERED
                    && let Some(stalest) = self
                        .tracks
                        .iter()
                        .enumerate()
                        .min_by_key(|(_, (_, newest))| *newest)
                        .map(|(i, _)| i)
                {
                    self.tracks.swap_remove(stalest);
                }
                self.tracks.push((track, id));
                FrameOrder::Newest
            }
        }
    }
}

fn order_frame(newest: &std::sync::Mutex<NewestFrames>, track: u16, id: u64) -> FrameOrder {
    newest
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .order(track, id)
}

async fn align(ctx: &ConnCtx, req: FrameRequest) -> Result<FrameOutcome, Fault> {
    let metrics = &ctx.shared.metrics;
    let dropped = |reason| {
        metrics.count_drop(reason);
        Ok(FrameOutcome::Dropped(reason))
    };
    match order_frame(&ctx.newest, req.track_id, req.frame_id) {
        FrameOrder::Newest => {}
        FrameOrder::Duplicate => {
            return Err(Fault::new(
                CloseCode::ProtocolViolation,
                format!("duplicate frame_id {} (track {})", req.frame_id, req.track_id),
            ));
        }
        FrameOrder::Older => return dropped(DropReason::Superseded),
    }
    let Some(pixels) = crop_pixels(&req.crop, ctx.shared.model.crop_size) else {
        debug!(client = ctx.client, frame_id = req.frame_id, "bad crop");
        return dropped(DropReason::BadCrop);
    };
    let settings = &ctx.shared.settings;
    let budget = match req.deadline_ms {
        0 => settings.max_frame_age,
        ms => Duration::from_millis(u64::from(ms)).min(settings.max_frame_age),
    };
    let arrived = tokio::time::Instant::now().into_std();
    let (tx, rx) = oneshot::channel();
    let pending = Pending {
        client: ctx.client,
        track: req.track_id,
        frame_id: req.frame_id,
        arrived,
        expires: arrived + budget,
        payload: FrameJob { pixels, reply: tx },
    };
    match ctx.shared.sched.try_send(SchedMsg::Submit(pending)) {
        Ok(()) => {}
        Err(mpsc::error::TrySendError::Full(_)) => return dropped(DropReason::Overloaded),
        Err(mpsc::error::TrySendError::Closed(_)) => return dropped(DropReason::ShuttingDown),
    }
    Ok(rx
        .await
        .unwrap_or(FrameOutcome::Dropped(DropReason::ShuttingDown)))
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use holoface_protocol::CropEncoding;

    use super::*;

    #[test]
    fn frame_ids_order_across_the_whole_u64_range() {
        let n = std::sync::Mutex::new(NewestFrames::default());
        assert_eq!(order_frame(&n, 0, u64::MAX), FrameOrder::Newest);
        // MAX - 1 after MAX is an older frame, not a duplicate.
        assert_eq!(order_frame(&n, 0, u64::MAX - 1), FrameOrder::Older);
        assert_eq!(order_frame(&n, 0, u64::MAX), FrameOrder::Duplicate);
        let n = std::sync::Mutex::new(NewestFrames::default());
        assert_eq!(order_frame(&n, 0, 0), FrameOrder::Newest);
        assert_eq!(order_frame(&n, 0, 0), FrameOrder::Duplicate);
        assert_eq!(order_frame(&n, 0, 5), FrameOrder::Newest);
        assert_eq!(order_frame(&n, 0, 3), FrameOrder::Older);
        assert_eq!(order_frame(&n, 0, 6), FrameOrder::Newest);
    }

    /// The faces of one frame share its id; each track is ordered on its own, and out-of-order arrival
    /// across tracks never supersedes another face's crop.
    #[test]
    fn frame_ids_are_ordered_per_track() {
        let n = std::sync::Mutex::new(NewestFrames::default());
        assert_eq!(order_frame(&n, 2, 10), FrameOrder::Newest);
        assert_eq!(
            order_frame(&n, 1, 10),
            FrameOrder::Newest,
            "same frame, another face"
        );
        assert_eq!(
            order_frame(&n, 3, 9),
            FrameOrder::Newest,
            "an older frame of a new track"
        );
        assert_eq!(order_frame(&n, 1, 10), FrameOrder::Duplicate);
        assert_eq!(order_frame(&n, 2, 9), FrameOrder::Older);
        assert_eq!(order_frame(&n, 3, 11), FrameOrder::Newest);
    }

    /// Cycling through track ids keeps at most TRACKS_REMEMBERED of them; the stalest goes first.
    #[test]
    fn remembered_tracks_are_bounded() {
        let mut n = NewestFrames::default();
        for t in 0..10_000_u16 {
            assert_eq!(n.order(t, u64::from(t) + 100), FrameOrder::Newest);
        }
        assert_eq!(n.tracks.len(), TRACKS_REMEMBERED);
        // The newest tracks are still ordered; the first ones were forgotten.
        assert_eq!(n.order(9_999, 50), FrameOrder::Older);
        assert_eq!(n.order(0, 1), FrameOrder::Newest);
    }

    #[test]
    fn crops_are_checked_and_decoded() {
        let raw = Crop::raw(4, 4, vec![9_u8; 16]);
        assert_eq!(crop_pixels(&raw, 4).unwrap().len(), 16);
        assert!(crop_pixels(&raw, 8).is_none(), "wrong size is a bad crop");
        let mut png = Vec::new();
        image::GrayImage::from_pixel(4, 4, image::Luma([7]))
            .write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let crop = Crop {
            encoding: CropEncoding::Png,
            width: 4,
            height: 4,
            data: png.into(),
        };
        assert_eq!(&crop_pixels(&crop, 4).unwrap()[..], &[7_u8; 16]);
        let garbage = Crop {
            encoding: CropEncoding::Jpeg,
            width: 4,
            height: 4,
            data: Bytes::from_static(b"not a jpeg"),
        };
        assert!(crop_pixels(&garbage, 4).is_none());
    }
}
