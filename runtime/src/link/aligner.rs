//! [`LinkedAligner`]: remote DAN first, the local aligner on the same frame when the remote cannot answer.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use holoface_models::crop::{CROP_SIDE, CROP_SIZE, Crop112, crop_bilinear};
use holoface_models::geometry::Point2;
use holoface_models::image::GrayView;
use holoface_protocol::{FrameRequest, ReplyOutcome, ServerWelcome};

use super::policy::{FallbackPolicy, Mode, PolicyConfig, Route};
use super::{Clock, CropCodec, Link, LinkEvent, RemoteLink, SystemClock};
use crate::adapt::{AdaptOptions, LocalAdaptation};
use crate::align::{
    AlignError, Aligner, Alignment, AnsweredBy, Candidate, InitSource, Neighbours, align_from,
    crop_from_image, landmarks_from_crop,
};

/// Settings of the linked aligner.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinkOptions {
    /// How long a frame waits for the server before the local aligner answers it.
    pub deadline: Duration,
    /// Crop encoding we prefer (the server's choice wins; the JPEG quality is ours).
    pub codec: CropCodec,
    /// When to fall back and when to return.
    pub policy: PolicyConfig,
    /// The local aligner's per-person adaptation to the remote answers ([`crate::adapt`]); `None`: off.
    pub adapt: Option<AdaptOptions>,
}

impl Default for LinkOptions {
    fn default() -> Self {
        Self {
            deadline: Duration::from_millis(crate::defaults::DEADLINE_MS),
            codec: CropCodec::default(),
            policy: PolicyConfig::default(),
            adapt: crate::defaults::ADAPT.then(AdaptOptions::default),
        }
    }
}

/// The link's result for the last frame: what happened on it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct LinkReport {
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
    /// The link's state when the frame was routed (why it was answered locally, when it was).
    pub link: Option<super::LinkState>,
}

/// Remote DAN over a [`Link`] (in the headset: [`RemoteLink`]) with a local aligner `A` for fallback; see
/// [`super::policy`]. Time comes from the clock `C`, so the whole fallback behaviour runs on made-up instants
/// in tests.
pub struct LinkedAligner<A, K = RemoteLink, C = SystemClock> {
    link: K,
    clock: C,
    local: A,
    policy: FallbackPolicy,
    opts: LinkOptions,
    epoch: Instant,
    next_id: u64,
    crop: Crop112,
    canonical: Option<(Arc<ServerWelcome>, [Point2; 68])>,
    probes: VecDeque<Probe>,
    report: LinkReport,
    adapt: Option<LocalAdaptation>,
}

impl<A, K: std::fmt::Debug, C> std::fmt::Debug for LinkedAligner<A, K, C> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LinkedAligner")
            .field("link", &self.link)
            .field("mode", &self.policy.mode())
            .finish_non_exhaustive()
    }
}

impl<A: Aligner> LinkedAligner<A> {
    /// Wraps a started link and the local aligner; the system clock.
    pub fn new(link: RemoteLink, local: A, opts: LinkOptions) -> Self {
        Self::with_clock(link, local, opts, SystemClock)
    }
}

impl<A: Aligner, K: Link, C: Clock> LinkedAligner<A, K, C> {
    /// Wraps any link and clock.
    pub fn with_clock(link: K, local: A, opts: LinkOptions, clock: C) -> Self {
        let epoch = clock.now();
        Self {
            link,
            clock,
            local,
            policy: FallbackPolicy::new(opts.policy),
            opts,
            epoch,
            next_id: 1,
            crop: Crop112::default(),
            canonical: None,
            probes: VecDeque::new(),
            report: LinkReport::default(),
            adapt: opts.adapt.map(LocalAdaptation::new),
        }
    }

    /// The link (status, counters).
    pub fn link(&self) -> &K {
        &self.link
    }

    /// The fallback policy (mode, switch count).
    pub fn policy(&self) -> &FallbackPolicy {
        &self.policy
    }

    /// The link's result for the last frame: what happened on it.
    pub fn last_report(&self) -> LinkReport {
        self.report
    }

    fn canonical(&mut self, welcome: &Arc<ServerWelcome>) -> Option<[Point2; 68]> {
        if let Some((w, c)) = &self.canonical
            && Arc::ptr_eq(w, welcome)
        {
            return Some(*c);
        }
        if welcome.mean_shape.len() != 68 || usize::from(welcome.crop_size) != CROP_SIZE {
            return None;
        }
        let c = std::array::from_fn(|i| Point2::new(welcome.mean_shape[i][0], welcome.mean_shape[i][1]));
        self.canonical = Some((Arc::clone(welcome), c));
        Some(c)
    }

    /// Cuts and encodes one face's crop (the frame's other faces blanked out of it, as the in-process
    /// DAN aligner does) and queues it as `frame_id` of `track_id`; the similarity, or `None` when the
    /// crop cannot be made (then that face is simply aligned locally).
    fn send_crop(
        &mut self,
        image: &GrayView<'_>,
        faces: &[Candidate],
        i: usize,
        welcome: &Arc<ServerWelcome>,
        (frame_id, track_id): (u64, u16),
    ) -> Option<holoface_models::geometry::Similarity2> {
        let canonical = self.canonical(welcome)?;
        let sim = crop_from_image(&faces.get(i)?.init, &canonical).ok()?;
        crop_bilinear(image, &sim, &mut self.crop).ok()?;
        if let Some(n) = Neighbours::of(faces, i) {
            n.blank(&mut self.crop, &sim);
        }
        let codec = crate::crop_codec::for_encoding(self.opts.codec, welcome.encoding);
        let crop = crate::crop_codec::encode(codec, self.crop.as_slice(), CROP_SIDE, CROP_SIDE).ok()?;
        let req = FrameRequest {
            track_id,
            frame_id,
            captured_at_us: self.clock.now().saturating_duration_since(self.epoch).as_micros() as u64,
            deadline_ms: u16::try_from(self.opts.deadline.as_millis()).unwrap_or(u16::MAX),
            crop,
        };
        let len = holoface_protocol::Message::FrameRequest(req.clone()).encoded_len();
        self.link.send(req).ok()?;
        self.report.sent_bytes += len;
        Some(sim)
    }

    /// Books a link event against the outstanding probes.
    fn on_event(
        policy: &mut FallbackPolicy,
        probes: &mut VecDeque<Probe>,
        deadline: Duration,
        ev: LinkEvent,
    ) {
        match ev {
            LinkEvent::Reply(r, at) => {
                if let Some(i) = probes
                    .iter()
                    .position(|p| p.frame_id == r.frame_id && p.track_id == r.track_id)
                {
                    let sent = probes.remove(i).map_or(at, |p| p.sent);
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
        self.link
            .drain(&mut |ev| Self::on_event(policy, probes, deadline, ev));
        while let Some(p) = self.probes.front() {
            if now.saturating_duration_since(p.sent) <= self.opts.deadline {
                break;
            }
            self.probes.pop_front();
            self.policy.on_miss(now);
        }
    }

    /// The local aligner's answer for one face: after a detection its detection path (KRFWS: several
    /// starts), as a headset without a link would run it; otherwise one tracked alignment.
    fn local(&mut self, image: &GrayView<'_>, face: &Candidate) -> Result<Alignment, AlignError> {
        align_from(&mut self.local, image, &face.init, face.source)
    }

    /// Which track each face's crop travels under: a lone face is track 0 (the version-1/2 message, byte
    /// for byte); with several, a tracked face's id (mod 32767, plus 1) or, for a new detection, 32768 +
    /// its place in the frame. `None` for a face that cannot go remote: a second face to a server older
    /// than version 3 (it orders frames per connection), or an id colliding with another face's.
    fn wire_tracks(faces: &[Candidate], server_version: u16) -> Vec<Option<u16>> {
        if faces.len() == 1 {
            return vec![Some(0)];
        }
        let mut tracks: Vec<Option<u16>> = Vec::with_capacity(faces.len());
        for (i, face) in faces.iter().enumerate() {
            let track = if server_version < 3 {
                (i == 0).then_some(0)
            } else {
                match face.track {
                    Some(id) => u16::try_from(id % 0x7FFF).ok().map(|t| t + 1),
                    None => u16::try_from(i).ok().and_then(|i| 0x8000_u16.checked_add(i)),
                }
            };
            let unique = track.filter(|t| !tracks.contains(&Some(*t)));
            tracks.push(unique);
        }
        tracks
    }

    /// One frame: every face's crop to the server at once when the policy routes there, one wait for all
    /// their replies (until the deadline), and the local aligner for each face the server did not answer
    /// in time, so every face of the frame has an answer.
    fn align_frame(
        &mut self,
        image: &GrayView<'_>,
        faces: &[Candidate],
    ) -> Result<Vec<Alignment>, AlignError> {
        let now = self.clock.now();
        self.report = LinkReport::default();
        self.settle_probes(now);
        let status = self.link.status();
        self.report.link = Some(status.state());
        let welcome = status.welcome().cloned();
        let frame_id = self.next_id;
        self.next_id += 1;
        let mut remote: Vec<Option<Alignment>> = vec![None; faces.len()];
        let mut sent_any = false;
        match (self.policy.route(now, welcome.is_some()), welcome) {
            (Route::Remote, Some(welcome)) => {
                let tracks = Self::wire_tracks(faces, welcome.version);
                // (face index, track, crop similarity, reply)
                let mut sent = Vec::with_capacity(faces.len());
                for (i, track) in tracks.iter().enumerate() {
                    if let Some(track) = *track
                        && let Some(sim) = self.send_crop(image, faces, i, &welcome, (frame_id, track))
                    {
                        sent.push((i, track, sim, None));
                    }
                }
                sent_any = !sent.is_empty();
                if sent_any {
                    self.wait_replies(now, frame_id, &welcome, &mut sent, &mut remote);
                }
            }
            (Route::Local { probe: true }, Some(welcome)) => {
                // At most `max_in_flight` probes outstanding: a server slower than the frame rate would
                // otherwise see each probe superseded by the next and never look healthy.
                let tracks = Self::wire_tracks(faces, welcome.version);
                for (i, track) in tracks.into_iter().enumerate() {
                    if self.probes.len() >= usize::from(welcome.max_in_flight.max(1)) {
                        break;
                    }
                    if let Some(track_id) = track
                        && self
                            .send_crop(image, faces, i, &welcome, (frame_id, track_id))
                            .is_some()
                    {
                        self.probes.push_back(Probe {
                            frame_id,
                            track_id,
                            sent: now,
                        });
                    }
                }
            }
            _ => {}
        }
        let mut out = Vec::with_capacity(faces.len());
        for (face, answer) in faces.iter().zip(remote) {
            match answer {
                Some(a) => out.push(a),
                None => {
                    self.report.fell_back |= sent_any;
                    out.push(self.local(image, face)?);
                }
            }
        }
        if let Some(adapt) = &mut self.adapt {
            adapt.update(&mut self.local, image, faces, &mut out)?;
        }
        self.report.answered_by = out.first().map(|a| a.answered_by);
        self.report.mode = Some(self.policy.mode());
        Ok(out)
    }

    /// Waits once, until the deadline, for the replies to every crop in `sent`; fills `remote` with the
    /// server's answers and tells the policy how the frame went: answered when every face was, else one
    /// miss (a frame that misses counts once, however many faces it has).
    fn wait_replies(
        &mut self,
        now: Instant,
        frame_id: u64,
        welcome: &ServerWelcome,
        sent: &mut [SentCrop],
        remote: &mut [Option<Alignment>],
    ) {
        let deadline = self.opts.deadline;
        let mut waiting = sent.len();
        let mut down = false;
        let (policy, probes) = (&mut self.policy, &mut self.probes);
        let waited = self.link.wait_until(now + deadline, &mut |ev| {
            match ev {
                LinkEvent::Reply(r, at) if r.frame_id == frame_id => {
                    if let Some(slot) = sent.iter_mut().find(|s| s.1 == r.track_id && s.3.is_none()) {
                        slot.3 = Some((r.outcome, at));
                        waiting -= 1;
                    }
                }
                ev @ LinkEvent::Down(..) => {
                    down = true;
                    Self::on_event(policy, probes, deadline, ev);
                }
                ev => Self::on_event(policy, probes, deadline, ev),
            }
            waiting == 0 || down
        });
        let mut last = None;
        let mut all_answered = true;
        for (i, _, sim, reply) in sent.iter_mut() {
            let answer = match reply.take() {
                Some((
                    ReplyOutcome::Landmarks {
                        landmarks, face_prob, ..
                    },
                    at,
                )) => {
                    last = Some(last.map_or(at, |l: Instant| l.max(at)));
                    landmarks_from_crop(&landmarks, face_prob, sim, welcome.face_threshold).ok()
                }
                Some((ReplyOutcome::Dropped { .. }, _)) | None => None,
            };
            all_answered &= answer.is_some();
            remote[*i] = answer.map(|mut a| {
                a.answered_by = AnsweredBy::RemoteDan;
                a
            });
        }
        if let Some(at) = last {
            self.report.remote_rtt_us = Some(at.saturating_duration_since(now).as_micros() as u64);
        }
        match (waited, all_answered) {
            // The policy already saw the Down event.
            _ if down => {}
            (Ok(()), true) => self.policy.on_answer(last.unwrap_or(now)),
            (Ok(()), false) => self.policy.on_miss(last.unwrap_or(now)),
            (Err(_), _) => self.policy.on_miss(self.clock.now()),
        }
    }
}

/// A crop of this frame sent for its answer: (face index, track id, crop similarity, the reply and when
/// it came).
type SentCrop = (
    usize,
    u16,
    holoface_models::geometry::Similarity2,
    Option<(ReplyOutcome, Instant)>,
);

/// A probe crop sent while in Local mode.
#[derive(Clone, Copy, Debug)]
struct Probe {
    frame_id: u64,
    track_id: u16,
    sent: Instant,
}

impl<A: Aligner, K: Link, C: Clock> Aligner for LinkedAligner<A, K, C> {
    fn name(&self) -> &'static str {
        "dan-remote+local"
    }

    fn align(&mut self, image: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
        self.align_one(image, init, InitSource::Tracking)
    }

    /// A detection frame: DAN when the link answers (its crop does not depend on the start), else the local
    /// aligner's detection path, so a headset without a link answers detection frames as a local-only one.
    fn align_detection(
        &mut self,
        image: &GrayView<'_>,
        init: &[Point2; 68],
    ) -> Result<Alignment, AlignError> {
        self.align_one(image, init, InitSource::Detection)
    }

    /// Every face's crop goes out at once (each under its track id) and the frame waits once for all the
    /// replies; each face the server misses is answered by the local aligner.
    fn align_faces(
        &mut self,
        image: &GrayView<'_>,
        faces: &[Candidate],
    ) -> Result<Vec<Alignment>, AlignError> {
        self.align_frame(image, faces)
    }
}

impl<A: Aligner, K: Link, C: Clock> LinkedAligner<A, K, C> {
    fn align_one(
        &mut self,
        image: &GrayView<'_>,
        init: &[Point2; 68],
        source: InitSource,
    ) -> Result<Alignment, AlignError> {
        let face = Candidate {
            track: None,
            init: *init,
            source,
        };
        let mut out = self.align_frame(image, std::slice::from_ref(&face))?;
        out.pop().ok_or(AlignError::DegenerateInit)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::super::WaitError;
    use super::*;
    use crate::adapt::AdaptOptions;
    use crate::align::AdaptState;
    use crate::align::{Confidence, LandmarkSet};

    /// A local aligner that records which path it was asked for.
    #[derive(Default)]
    struct Recorder {
        tracked: usize,
        detection: usize,
    }

    impl Recorder {
        fn answer(init: &[Point2; 68]) -> Alignment {
            Alignment {
                landmarks: *init,
                set: LandmarkSet::Inner51,
                confidence: Confidence::PredictedError(0.01),
                accepted: true,
                answered_by: AnsweredBy::Krfws,
                adaptation: None,
            }
        }
    }

    impl Aligner for Recorder {
        fn name(&self) -> &'static str {
            "recorder"
        }
        fn align(&mut self, _: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
            self.tracked += 1;
            Ok(Self::answer(init))
        }
        fn align_detection(
            &mut self,
            _: &GrayView<'_>,
            init: &[Point2; 68],
        ) -> Result<Alignment, AlignError> {
            self.detection += 1;
            Ok(Self::answer(init))
        }
    }

    /// A made-up clock that only moves when told to.
    struct FakeClock(std::cell::Cell<Instant>);

    impl Clock for FakeClock {
        fn now(&self) -> Instant {
            self.0.get()
        }
    }

    /// How the scripted server answers the next frame it is sent.
    #[derive(Clone, Copy)]
    enum Answer {
        /// Landmarks this long after the frame was sent.
        After(Duration),
        /// No answer.
        Silent,
    }

    /// A link whose server answers from a script, on the shared fake clock: a sent frame's reply becomes
    /// due at send time + its delay; `wait_until` and `drain` hand out the replies that are due.
    struct FakeLink {
        clock: std::rc::Rc<FakeClock>,
        up: Option<Arc<ServerWelcome>>,
        script: std::cell::RefCell<VecDeque<Answer>>,
        /// (frame id, track id, when its reply is due)
        pending: std::cell::RefCell<Vec<(u64, u16, Instant)>>,
        /// Every request sent: (frame id, track id).
        requests: std::cell::RefCell<Vec<(u64, u16)>>,
        /// The last request's crop, decoded.
        last_crop: std::cell::RefCell<Vec<u8>>,
        sent: std::cell::Cell<usize>,
    }

    impl FakeLink {
        fn welcome() -> Arc<ServerWelcome> {
            Arc::new(ServerWelcome {
                version: holoface_protocol::PROTOCOL_VERSION,
                model_id: "fake".into(),
                model_version: "0".into(),
                landmark_count: 68,
                crop_size: 112,
                mean_shape: holoface_models::shape::dan_mean_shape()
                    .iter()
                    .map(|p| [p.x, p.y])
                    .collect(),
                face_threshold: 0.5,
                encoding: holoface_protocol::CropEncoding::Raw,
                reply_channel: holoface_protocol::ReplyChannel::Datagram,
                max_in_flight: 1,
                max_frame_age_ms: 100,
            })
        }

        /// The server's answer: the mean shape in crop pixels (the initial shape, mapped back).
        fn reply(frame_id: u64, track_id: u16) -> holoface_protocol::FrameReply {
            holoface_protocol::FrameReply {
                track_id,
                frame_id,
                outcome: ReplyOutcome::Landmarks {
                    landmarks: holoface_models::shape::dan_mean_shape()
                        .iter()
                        .map(|p| [p.x, p.y])
                        .collect(),
                    face_prob: 0.9,
                    queue_us: 0,
                    infer_us: 0,
                },
            }
        }
    }

    impl Link for FakeLink {
        fn status(&self) -> super::super::LinkInfo {
            match &self.up {
                Some(w) => super::super::LinkInfo::Up(super::super::ServerInfo::new(Arc::clone(w))),
                None => super::super::LinkInfo::Connecting { last_error: None },
            }
        }
        fn send(&self, req: FrameRequest) -> Result<(), WaitError> {
            self.sent.set(self.sent.get() + 1);
            self.requests.borrow_mut().push((req.frame_id, req.track_id));
            *self.last_crop.borrow_mut() = holoface_inference::decode_crop(&req.crop)
                .map(|px| px.to_vec())
                .unwrap_or_default();
            if let Some(Answer::After(d)) = self.script.borrow_mut().pop_front() {
                self.pending
                    .borrow_mut()
                    .push((req.frame_id, req.track_id, self.clock.now() + d));
            }
            Ok(())
        }
        fn wait_until(
            &self,
            deadline: Instant,
            each: &mut dyn FnMut(LinkEvent) -> bool,
        ) -> Result<(), WaitError> {
            loop {
                let next = {
                    let mut pending = self.pending.borrow_mut();
                    let first = pending
                        .iter()
                        .enumerate()
                        .filter(|(_, p)| p.2 <= deadline)
                        .min_by_key(|(_, p)| p.2)
                        .map(|(i, _)| i);
                    first.map(|i| pending.remove(i))
                };
                let Some((id, track, due)) = next else {
                    self.clock.0.set(deadline.max(self.clock.now()));
                    return Err(WaitError::Deadline);
                };
                self.clock.0.set(due.max(self.clock.now()));
                if each(LinkEvent::Reply(Self::reply(id, track), due)) {
                    return Ok(());
                }
            }
        }
        fn drain(&self, each: &mut dyn FnMut(LinkEvent)) {
            let now = self.clock.now();
            let mut pending = self.pending.borrow_mut();
            let (due, later): (Vec<_>, Vec<_>) = pending.iter().partition(|&&(_, _, at)| at <= now);
            *pending = later;
            drop(pending);
            for (id, track, at) in due {
                each(LinkEvent::Reply(Self::reply(id, track), at));
            }
        }
    }

    impl Clock for std::rc::Rc<FakeClock> {
        fn now(&self) -> Instant {
            self.0.get()
        }
    }

    type Linked = LinkedAligner<Recorder, FakeLink, std::rc::Rc<FakeClock>>;

    /// These tests count the local aligner's calls: the adaptation, which calls it too, is off (its own
    /// tests are below).
    fn linked(up: bool, script: &[Answer]) -> (Linked, std::rc::Rc<FakeClock>) {
        let opts = LinkOptions {
            adapt: None,
            ..LinkOptions::default()
        };
        linked_with(Recorder::default(), up, script, opts)
    }

    fn linked_with<A: Aligner>(
        local: A,
        up: bool,
        script: &[Answer],
        opts: LinkOptions,
    ) -> (
        LinkedAligner<A, FakeLink, std::rc::Rc<FakeClock>>,
        std::rc::Rc<FakeClock>,
    ) {
        let clock = std::rc::Rc::new(FakeClock(std::cell::Cell::new(Instant::now())));
        let link = FakeLink {
            clock: std::rc::Rc::clone(&clock),
            up: up.then(FakeLink::welcome),
            script: std::cell::RefCell::new(script.iter().copied().collect()),
            pending: std::cell::RefCell::new(Vec::new()),
            requests: std::cell::RefCell::new(Vec::new()),
            last_crop: std::cell::RefCell::new(Vec::new()),
            sent: std::cell::Cell::new(0),
        };
        (
            LinkedAligner::with_clock(link, local, opts, std::rc::Rc::clone(&clock)),
            clock,
        )
    }

    /// A local aligner with a person-specific error: its answer is the start with the brows 2 px too high
    /// (the fake server answers the start itself; 2 px is within the correction's bound on this face).
    struct HighBrows;

    impl Aligner for HighBrows {
        fn name(&self) -> &'static str {
            "high-brows"
        }
        fn align(&mut self, _: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
            let mut a = Recorder::answer(init);
            for p in &mut a.landmarks[17..27] {
                p.y -= 2.0;
            }
            Ok(a)
        }
    }

    /// The brows' mean height error of an answer against the start, pixels.
    fn brows_off(a: &Alignment, init: &[Point2; 68]) -> f32 {
        (17..27).map(|i| init[i].y - a.landmarks[i].y).sum::<f32>() / 10.0
    }

    /// A tracked face for 110 frames: the server answers the first 80 crops in 5 ms, then nothing. Per
    /// frame: who answered, the brows' error and the adaptation's state.
    fn link_then_outage(opts: LinkOptions, track: u32) -> Vec<(AnsweredBy, f32, Option<AdaptState>)> {
        let (mut a, clock) = linked_with(
            HighBrows,
            true,
            &[Answer::After(Duration::from_millis(5)); 80],
            opts,
        );
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        let face = Candidate {
            track: Some(track),
            init,
            source: InitSource::Tracking,
        };
        (0..110)
            .map(|_| {
                let r = a
                    .align_faces(&image, std::slice::from_ref(&face))
                    .unwrap()
                    .remove(0);
                clock.0.set(clock.now() + FRAME);
                (r.answered_by, brows_off(&r, &init), r.adaptation)
            })
            .collect()
    }

    #[test]
    fn the_local_aligner_learns_the_person_while_the_link_is_up_and_is_corrected_when_it_drops() {
        let frames = link_then_outage(LinkOptions::default(), 7);
        let first_remote = frames.iter().position(|f| f.0 == AnsweredBy::RemoteDan).unwrap();
        let last_remote = frames.iter().rposition(|f| f.0 == AnsweredBy::RemoteDan).unwrap();
        // Before the link is trusted: the local aligner's own answers, nothing learnt yet.
        assert!(
            frames[..first_remote]
                .iter()
                .all(|f| (f.1 - 2.0).abs() < 1e-3 && !f.2.unwrap().corrected)
        );
        // While the server answers: a pair beside every answer until `warm_pairs`, then every
        // `learn_every`-th.
        let learnt = frames[last_remote].2.unwrap().pairs;
        let remote_frames = last_remote + 1 - first_remote;
        let opts = AdaptOptions::default();
        let expected = (0..remote_frames as u32)
            .filter(|k| *k < opts.warm_pairs || k.is_multiple_of(opts.learn_every))
            .count() as u32;
        assert!(
            remote_frames > 40 && learnt == expected,
            "{learnt} pairs from {remote_frames}"
        );
        // The outage: every local answer corrected, the brows back where the server put them.
        let outage = &frames[last_remote + 1..];
        assert!(outage.len() > 20);
        for (by, off, state) in outage {
            assert_eq!(*by, AnsweredBy::Krfws);
            let s = state.unwrap();
            assert!(s.corrected && s.pairs == learnt && s.correction > 0.0, "{s:?}");
            assert!(off.abs() < 0.05, "brows {off} px off after the correction");
        }
    }

    #[test]
    fn without_the_adaptation_the_local_answers_are_the_local_aligners_own() {
        let opts = LinkOptions {
            adapt: None,
            ..LinkOptions::default()
        };
        let frames = link_then_outage(opts, 7);
        assert!(frames.iter().any(|f| f.0 == AnsweredBy::RemoteDan));
        for (by, off, state) in frames {
            assert_eq!(state, None);
            if by == AnsweredBy::Krfws {
                assert!((off - 2.0).abs() < 1e-3);
            }
        }
    }

    #[test]
    fn with_no_link_ever_up_nothing_is_learnt_or_corrected() {
        let (mut a, clock) = linked_with(HighBrows, false, &[], LinkOptions::default());
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        let face = Candidate {
            track: Some(3),
            init,
            source: InitSource::Tracking,
        };
        for _ in 0..50 {
            let r = a.align_faces(&image, &[face]).unwrap().remove(0);
            clock.0.set(clock.now() + FRAME);
            assert_eq!(r.answered_by, AnsweredBy::Krfws);
            assert_eq!(r.adaptation, Some(AdaptState::default()));
            assert!((brows_off(&r, &init) - 2.0).abs() < 1e-3);
        }
    }

    #[test]
    fn a_new_face_starts_from_nothing() {
        let (mut a, clock) = linked_with(
            HighBrows,
            true,
            &[Answer::After(Duration::from_millis(5)); 80],
            LinkOptions::default(),
        );
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        let face = |track| Candidate {
            track: Some(track),
            init,
            source: InitSource::Tracking,
        };
        for _ in 0..100 {
            a.align_faces(&image, &[face(1)]).unwrap();
            clock.0.set(clock.now() + FRAME);
        }
        let before = a.align_faces(&image, &[face(1)]).unwrap().remove(0);
        assert!(before.adaptation.unwrap().corrected);
        // Face 1 lost, face 2 found: its answers are the local aligner's own until it learns.
        let after = a.align_faces(&image, &[face(2)]).unwrap().remove(0);
        assert_eq!(after.answered_by, AnsweredBy::Krfws);
        assert_eq!(after.adaptation.unwrap().pairs, 0);
        assert!((brows_off(&after, &init) - 2.0).abs() < 1e-3);
        // And face 1, should it come back under its old id, has been forgotten too.
        let back = a.align_faces(&image, &[face(1)]).unwrap().remove(0);
        assert_eq!(back.adaptation.unwrap().pairs, 0);
    }

    /// A face-sized initial shape in a 200x200 image.
    fn frame() -> (Vec<u8>, [Point2; 68]) {
        let init = holoface_models::shape::dan_mean_shape().map(|p| Point2::new(p.x + 40.0, p.y + 40.0));
        (vec![100_u8; 200 * 200], init)
    }

    const FRAME: Duration = Duration::from_millis(33);

    /// Frames at 30 fps until the server answers one; how many the local aligner answered before it (each
    /// with a probe to the server).
    fn run_until_remote(
        a: &mut Linked,
        clock: &FakeClock,
        image: &GrayView<'_>,
        init: &[Point2; 68],
    ) -> usize {
        for n in 0..100 {
            let r = a.align(image, init).unwrap();
            clock.0.set(clock.now() + FRAME);
            if r.answered_by == AnsweredBy::RemoteDan {
                assert_eq!(a.policy().mode(), Mode::Remote);
                return n;
            }
            assert_eq!(r.answered_by, AnsweredBy::Krfws, "frame {n} before the switch");
        }
        panic!("never switched to the server");
    }

    #[test]
    fn probes_earn_the_remote_path_and_a_timely_reply_is_the_answer() {
        let (mut a, clock) = linked(true, &[Answer::After(Duration::from_millis(5)); 64]);
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        let n = run_until_remote(&mut a, &clock, &image, &init);
        // Hold-off of 1 s at 33 ms per frame, and at least 10 timely probes: about 31 frames.
        assert!((30..=34).contains(&n), "switched after {n} frames");
        assert_eq!(a.link().sent.get(), n + 1);
        let t0 = clock.now();
        let r = a.align(&image, &init).unwrap();
        assert_eq!(r.answered_by, AnsweredBy::RemoteDan);
        assert_eq!(clock.now() - t0, Duration::from_millis(5));
        let rep = a.last_report();
        assert_eq!(
            (rep.remote_rtt_us, rep.fell_back, rep.mode),
            (Some(5_000), false, Some(Mode::Remote))
        );
        // The server's crop-pixel landmarks are the mean shape: mapped back, they are the initial shape.
        assert!(r.landmarks.iter().zip(&init).all(|(p, q)| p.dist(*q) < 1e-3));
        assert_eq!(a.local.tracked, n);
    }

    #[test]
    fn missed_deadlines_are_answered_locally_and_three_in_a_row_fall_back() {
        let ok = Answer::After(Duration::from_millis(5));
        let late = Answer::After(Duration::from_millis(50));
        let mut script = vec![ok; 40];
        let (mut a, clock) = linked(true, &[]);
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        a.link.script.borrow_mut().extend(script.drain(..));
        let n = run_until_remote(&mut a, &clock, &image, &init);
        a.link.script.borrow_mut().clear();
        a.link
            .script
            .borrow_mut()
            .extend([late, Answer::Silent, late, ok]);
        for i in 0..3 {
            let t0 = clock.now();
            let r = a.align(&image, &init).unwrap();
            assert_eq!(r.answered_by, AnsweredBy::Krfws, "miss {i}");
            assert!(a.last_report().fell_back);
            // Each waited exactly its deadline, then KRFWS answered the same frame.
            assert_eq!(clock.now() - t0, LinkOptions::default().deadline);
            clock.0.set(clock.now() + FRAME);
        }
        assert_eq!(a.policy().mode(), Mode::Local);
        assert_eq!(a.local.tracked, n + 3);
        // Local again: the next frame is answered at once (a probe goes out, nobody waits for it).
        let t0 = clock.now();
        let r = a.align(&image, &init).unwrap();
        assert_eq!(r.answered_by, AnsweredBy::Krfws);
        assert_eq!(clock.now(), t0);
        assert!(!a.last_report().fell_back);
    }

    #[test]
    fn without_a_link_detection_frames_take_the_local_detection_path() {
        let (mut a, _) = linked(false, &[]);
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        let d = a.align_detection(&image, &init).unwrap();
        let t = a.align(&image, &init).unwrap();
        assert_eq!(
            (d.answered_by, t.answered_by),
            (AnsweredBy::Krfws, AnsweredBy::Krfws)
        );
        assert_eq!((a.local.detection, a.local.tracked), (1, 1));
        assert_eq!(a.link().sent.get(), 0);
    }

    #[test]
    fn a_detection_frame_that_misses_falls_back_to_the_detection_path() {
        let (mut a, clock) = linked(true, &[Answer::After(Duration::from_millis(5)); 40]);
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        let n = run_until_remote(&mut a, &clock, &image, &init);
        a.link.script.borrow_mut().clear();
        a.link.script.borrow_mut().push_back(Answer::Silent);
        let r = a.align_detection(&image, &init).unwrap();
        assert_eq!(r.answered_by, AnsweredBy::Krfws);
        assert!(a.last_report().fell_back);
        assert_eq!((a.local.detection, a.local.tracked), (1, n));
    }

    fn three_faces(init: &[Point2; 68]) -> Vec<Candidate> {
        let shifted = |dx: f32| init.map(|p| Point2::new(p.x + dx, p.y));
        vec![
            Candidate {
                track: Some(4),
                init: shifted(-20.0),
                source: InitSource::Tracking,
            },
            Candidate {
                track: Some(9),
                init: shifted(0.0),
                source: InitSource::Tracking,
            },
            Candidate {
                track: None,
                init: shifted(20.0),
                source: InitSource::Detection,
            },
        ]
    }

    /// Three faces in one frame: three crops of one frame id under three tracks, one wait for all of them,
    /// and the face whose reply misses the deadline answered by the local aligner's detection path.
    #[test]
    fn several_faces_go_out_together_and_each_miss_is_answered_locally() {
        let ok = Answer::After(Duration::from_millis(5));
        let (mut a, clock) = linked(true, &[ok; 40]);
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        run_until_remote(&mut a, &clock, &image, &init);
        let faces = three_faces(&init);

        // All three answer (at 5, 7 and 6 ms): the frame waits for the slowest only.
        a.link.script.borrow_mut().clear();
        a.link.script.borrow_mut().extend([
            ok,
            Answer::After(Duration::from_millis(7)),
            Answer::After(Duration::from_millis(6)),
        ]);
        a.link.requests.borrow_mut().clear();
        let (local_before, t0) = ((a.local.tracked, a.local.detection), clock.now());
        let out = a.align_faces(&image, &faces).unwrap();
        assert_eq!(
            clock.now() - t0,
            Duration::from_millis(7),
            "one wait for the three"
        );
        assert!(out.iter().all(|r| r.answered_by == AnsweredBy::RemoteDan));
        for (r, f) in out.iter().zip(&faces) {
            assert!(r.landmarks.iter().zip(&f.init).all(|(p, q)| p.dist(*q) < 1e-3));
        }
        let requests = a.link.requests.borrow().clone();
        let frame_id = requests[0].0;
        assert_eq!(
            requests,
            vec![(frame_id, 5), (frame_id, 10), (frame_id, 0x8002)],
            "one frame id, a track per face"
        );
        assert_eq!((a.local.tracked, a.local.detection), local_before);
        assert_eq!(a.last_report().remote_rtt_us, Some(7_000));
        assert!(!a.last_report().fell_back);

        // The third face's reply never comes: the frame waits its deadline once, the local detection path
        // answers that face, the other two keep the server's answer; the frame counts as one miss.
        clock.0.set(clock.now() + FRAME);
        a.link.script.borrow_mut().extend([ok, ok, Answer::Silent]);
        let t0 = clock.now();
        let out = a.align_faces(&image, &faces).unwrap();
        assert_eq!(clock.now() - t0, LinkOptions::default().deadline);
        let by: Vec<_> = out.iter().map(|r| r.answered_by).collect();
        assert_eq!(
            by,
            vec![AnsweredBy::RemoteDan, AnsweredBy::RemoteDan, AnsweredBy::Krfws]
        );
        assert_eq!(a.local.detection, local_before.1 + 1);
        assert!(a.last_report().fell_back);
        assert_eq!(a.policy().mode(), Mode::Remote, "one miss does not fall back");
    }

    /// With several faces, each crop has the other faces blanked out of it (0, what a crop reads off the
    /// image); a lone face's crop is the image as it is.
    #[test]
    fn a_face_crop_has_the_other_faces_blanked_out() {
        let ok = Answer::After(Duration::from_millis(5));
        let (mut a, clock) = linked(true, &[ok; 40]);
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        run_until_remote(&mut a, &clock, &image, &init);
        let blanked = |crop: &[u8]| crop.iter().filter(|&&p| p == 0).count();
        let lone = a.link.last_crop.borrow().clone();
        assert_eq!(lone.len(), 112 * 112);
        assert_eq!(blanked(&lone), 0, "nothing blanked around a lone face");

        // Two faces 60 px apart: alone, neither crop is blanked; together, the second face's crop has the
        // first (on its left) blanked and its own side untouched.
        let shifted = |dx: f32| init.map(|p| Point2::new(p.x + dx, p.y));
        let faces = [0.0, 60.0].map(|dx| Candidate {
            track: Some(dx as u32),
            init: shifted(dx - 20.0),
            source: InitSource::Tracking,
        });
        a.link.script.borrow_mut().extend([ok, ok]);
        a.align(&image, &faces[0].init).unwrap();
        assert_eq!(blanked(&a.link.last_crop.borrow()), 0);
        a.align_faces(&image, &faces[..1]).unwrap();
        assert_eq!(blanked(&a.link.last_crop.borrow()), 0);
        a.link.script.borrow_mut().extend([ok, ok]);
        let sent = a.link.requests.borrow().len();
        a.align_faces(&image, &faces).unwrap();
        assert_eq!(a.link.requests.borrow().len(), sent + 2);
        let second = a.link.last_crop.borrow().clone();
        let (left, right): (Vec<u8>, Vec<u8>) = second.chunks(112).map(|row| (row[5], row[106])).unzip();
        assert!(
            left.iter().filter(|&&p| p == 0).count() > 50,
            "the neighbour on the left is blanked"
        );
        assert!(right.iter().all(|&p| p == 100), "the face's own side is not");
    }

    /// A server older than version 3 orders frames per connection: only the first face goes to it (as
    /// track 0), the others are aligned locally.
    #[test]
    fn a_version_2_server_gets_one_face_per_frame() {
        let ok = Answer::After(Duration::from_millis(5));
        let (mut a, clock) = linked(true, &[ok; 40]);
        let (pixels, init) = frame();
        let image = GrayView::new(&pixels, 200, 200, 200).unwrap();
        run_until_remote(&mut a, &clock, &image, &init);
        let mut old = (*FakeLink::welcome()).clone();
        old.version = 2;
        a.link.up = Some(Arc::new(old));
        a.link.requests.borrow_mut().clear();
        let out = a.align_faces(&image, &three_faces(&init)).unwrap();
        let by: Vec<_> = out.iter().map(|r| r.answered_by).collect();
        assert_eq!(
            by,
            vec![AnsweredBy::RemoteDan, AnsweredBy::Krfws, AnsweredBy::Krfws]
        );
        let requests = a.link.requests.borrow().clone();
        assert_eq!(requests.len(), 1);
        assert_eq!(requests[0].1, 0);
    }

    /// Wire tracks never collide within a frame, and a lone face is track 0.
    #[test]
    fn wire_tracks_are_unique_per_frame() {
        let init = [Point2::default(); 68];
        let face = |track| Candidate {
            track,
            init,
            source: InitSource::Tracking,
        };
        type L = Linked;
        assert_eq!(L::wire_tracks(&[face(Some(7))], 3), vec![Some(0)]);
        assert_eq!(
            L::wire_tracks(&[face(Some(0)), face(Some(0x7FFF)), face(None)], 3),
            vec![Some(1), None, Some(0x8002)],
            "ids 0 and 32767 map to one track: the second face is aligned locally"
        );
    }
}
