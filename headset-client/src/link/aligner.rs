//! [`LinkedAligner`]: remote DAN first, the local aligner on the same frame when the remote cannot answer.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use holoface_models::crop::{Crop112, crop_bilinear};
use holoface_models::geometry::Point2;
use holoface_models::image::GrayView;
use holoface_protocol::{FrameRequest, ReplyOutcome, ServerWelcome};

use super::policy::{FallbackPolicy, Mode, PolicyConfig, Route};
use super::{CropCodec, LinkEvent, RemoteLink, WaitError};
use crate::align::{AlignError, Aligner, Alignment, AnsweredBy, crop_from_image, landmarks_from_crop};

/// Settings of the linked aligner.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LinkOptions {
    /// How long a frame waits for the server before the local aligner answers it.
    pub deadline: Duration,
    /// Crop encoding we prefer (the server's choice wins; the JPEG quality is ours).
    pub codec: CropCodec,
    /// When to fall back and when to return.
    pub policy: PolicyConfig,
}

impl Default for LinkOptions {
    fn default() -> Self {
        Self {
            // One frame interval at 30 fps: a missed frame is still answered (deadline + local aligner)
            // well within two intervals.
            deadline: Duration::from_millis(33),
            codec: CropCodec::default(),
            policy: PolicyConfig::default(),
        }
    }
}

/// What happened on the link for the last frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct FrameReport {
    /// Which aligner produced the answer.
    pub answered_by: Option<AnsweredBy>,
    /// The policy's mode after this frame.
    pub mode: Option<Mode>,
    /// The frame went to the server and missed (deadline, drop or link down), so the local aligner answered.
    pub fell_back: bool,
    /// Round trip of the remote answer, microseconds.
    pub remote_rtt_us: Option<u64>,
    /// HoloFace message bytes sent for this frame (the crop or the probe).
    pub sent_bytes: usize,
}

/// Remote DAN over [`RemoteLink`] with a local aligner for fallback; see [`super::policy`].
pub struct LinkedAligner<L> {
    link: RemoteLink,
    local: L,
    policy: FallbackPolicy,
    opts: LinkOptions,
    epoch: Instant,
    next_id: u64,
    crop: Crop112,
    canonical: Option<(Arc<ServerWelcome>, [Point2; 68])>,
    probes: VecDeque<(u64, Instant)>,
    report: FrameReport,
}

impl<L> std::fmt::Debug for LinkedAligner<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LinkedAligner")
            .field("link", &self.link)
            .field("mode", &self.policy.mode())
            .finish_non_exhaustive()
    }
}

impl<L: Aligner> LinkedAligner<L> {
    /// Wraps a started link and the local aligner.
    pub fn new(link: RemoteLink, local: L, opts: LinkOptions) -> Self {
        Self {
            link,
            local,
            policy: FallbackPolicy::new(opts.policy),
            opts,
            epoch: Instant::now(),
            next_id: 1,
            crop: Crop112::default(),
            canonical: None,
            probes: VecDeque::new(),
            report: FrameReport::default(),
        }
    }

    /// The link (status, counters).
    pub fn link(&self) -> &RemoteLink {
        &self.link
    }

    /// The fallback policy (mode, switch count).
    pub fn policy(&self) -> &FallbackPolicy {
        &self.policy
    }

    /// What happened on the link for the last frame.
    pub fn last_report(&self) -> FrameReport {
        self.report
    }

    fn canonical(&mut self, welcome: &Arc<ServerWelcome>) -> Option<[Point2; 68]> {
        if let Some((w, c)) = &self.canonical
            && Arc::ptr_eq(w, welcome)
        {
            return Some(*c);
        }
        if welcome.mean_shape.len() != 68 || welcome.crop_size != 112 {
            return None;
        }
        let c = std::array::from_fn(|i| Point2::new(welcome.mean_shape[i][0], welcome.mean_shape[i][1]));
        self.canonical = Some((Arc::clone(welcome), c));
        Some(c)
    }

    /// Cuts and encodes the crop and queues it; the similarity and frame id, or `None` when the crop
    /// cannot be made (then the frame is simply aligned locally).
    fn send_crop(
        &mut self,
        image: &GrayView<'_>,
        init: &[Point2; 68],
        welcome: &Arc<ServerWelcome>,
    ) -> Option<(holoface_models::geometry::Similarity2, u64)> {
        let canonical = self.canonical(welcome)?;
        let sim = crop_from_image(init, &canonical).ok()?;
        crop_bilinear(image, &sim, &mut self.crop).ok()?;
        let crop = self
            .opts
            .codec
            .for_encoding(welcome.encoding)
            .encode(self.crop.as_slice(), 112, 112)
            .ok()?;
        let id = self.next_id;
        self.next_id += 1;
        let req = FrameRequest {
            frame_id: id,
            captured_at_us: self.epoch.elapsed().as_micros() as u64,
            deadline_ms: u16::try_from(self.opts.deadline.as_millis()).unwrap_or(u16::MAX),
            crop,
        };
        self.report.sent_bytes = holoface_protocol::Message::FrameRequest(req.clone()).encoded_len();
        self.link.send(req).ok()?;
        Some((sim, id))
    }

    /// Books a link event against the outstanding probes.
    fn on_event(
        policy: &mut FallbackPolicy,
        probes: &mut VecDeque<(u64, Instant)>,
        deadline: Duration,
        ev: LinkEvent,
    ) {
        match ev {
            LinkEvent::Reply(r, at) => {
                if let Some(i) = probes.iter().position(|(id, _)| *id == r.frame_id) {
                    let (_, sent) = probes.remove(i).unwrap_or((0, at));
                    let timely = at.saturating_duration_since(sent) <= deadline;
                    if timely && matches!(r.outcome, ReplyOutcome::Landmarks { .. }) {
                        policy.on_answer(at);
                    } else {
                        policy.on_miss(at);
                    }
                }
                // Otherwise: a late reply to a frame already answered locally; ignore it.
            }
            LinkEvent::Down(at, _) => {
                probes.clear();
                policy.on_link_down(at);
            }
        }
    }

    fn settle_probes(&mut self, now: Instant) {
        let (policy, probes, deadline) = (&mut self.policy, &mut self.probes, self.opts.deadline);
        self.link.drain(|ev| Self::on_event(policy, probes, deadline, ev));
        while let Some(&(_, sent)) = self.probes.front() {
            if now.saturating_duration_since(sent) <= self.opts.deadline {
                break;
            }
            self.probes.pop_front();
            self.policy.on_miss(now);
        }
    }

    fn local(&mut self, image: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
        let a = self.local.align(image, init)?;
        self.report.answered_by = Some(a.answered_by);
        Ok(a)
    }
}

impl<L: Aligner> Aligner for LinkedAligner<L> {
    fn name(&self) -> &'static str {
        "dan-remote+local"
    }

    fn align(&mut self, image: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
        let now = Instant::now();
        self.report = FrameReport::default();
        self.settle_probes(now);
        let status = self.link.status();
        let welcome = status.welcome().cloned();
        let result = match (self.policy.route(now, welcome.is_some()), welcome) {
            (Route::Remote, Some(welcome)) => match self.send_crop(image, init, &welcome) {
                Some((sim, id)) => {
                    let (policy, probes, deadline) = (&mut self.policy, &mut self.probes, self.opts.deadline);
                    let waited = self.link.wait_reply(id, now + deadline, |ev| {
                        Self::on_event(policy, probes, deadline, ev)
                    });
                    let remote = match waited {
                        Ok((r, at)) => match r.outcome {
                            ReplyOutcome::Landmarks {
                                landmarks, face_prob, ..
                            } => {
                                self.policy.on_answer(at);
                                self.report.remote_rtt_us =
                                    Some(at.saturating_duration_since(now).as_micros() as u64);
                                landmarks_from_crop(&landmarks, face_prob, &sim, welcome.face_threshold).ok()
                            }
                            ReplyOutcome::Dropped { .. } => {
                                self.policy.on_miss(at);
                                None
                            }
                        },
                        Err(WaitError::Deadline | WaitError::Stopped) => {
                            self.policy.on_miss(Instant::now());
                            None
                        }
                        // The policy already saw the Down event.
                        Err(WaitError::Down(_)) => None,
                    };
                    match remote {
                        Some(mut a) => {
                            a.answered_by = AnsweredBy::RemoteDan;
                            self.report.answered_by = Some(AnsweredBy::RemoteDan);
                            Ok(a)
                        }
                        None => {
                            self.report.fell_back = true;
                            self.local(image, init)
                        }
                    }
                }
                None => self.local(image, init),
            },
            (Route::Local { probe: true }, Some(welcome)) => {
                // At most `max_in_flight` probes outstanding: a server slower than the frame rate would
                // otherwise see each probe superseded by the next and never look healthy.
                if self.probes.len() < usize::from(welcome.max_in_flight.max(1))
                    && let Some((_, id)) = self.send_crop(image, init, &welcome)
                {
                    self.probes.push_back((id, now));
                }
                self.local(image, init)
            }
            _ => self.local(image, init),
        };
        self.report.mode = Some(self.policy.mode());
        result
    }
}
