//! One frame's step, written once: [`TrackerSession::prepare_faces`] -> an [`Aligner`] per face ->
//! [`TrackerSession::complete_faces`], timed per step ([`step_faces`]). A one-face caller reads the first
//! candidate, alignment and face of the one [`StepFrame`].
//! [`crate::tracker::FaceTracker`], the FFI and every command-line tool that tracks frames go through these;
//! they differ only in which aligner they pass and what they do with the result.
//!
//! The session itself stays clock-free; this module reads the monotonic clock only to report [`Timings`].

use std::time::{Duration, Instant};

use crate::align::{AlignError, Aligner, Alignment};
use crate::detect::DetectError;
use crate::frame::Frame;
use crate::session::{Candidate, SessionFrame, TrackerSession};

/// Time spent per step of one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Timings {
    /// Detection or motion-compensated initialisation.
    pub prepare: Duration,
    /// The aligner (remote round trip or local).
    pub align: Duration,
    /// Verification, CANDIDE fit, world pose, filters, attributes.
    pub complete: Duration,
}

/// Why a frame could not be processed (a "no face" is not an error: it is a [`SessionFrame`] without faces).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StepError {
    /// Face detection failed.
    #[error(transparent)]
    Detect(#[from] DetectError),
    /// Alignment failed.
    #[error(transparent)]
    Align(#[from] AlignError),
}

/// The frame step's result: one frame through the loop, every face (the session's [`SessionFrame`] and what
/// the step saw on the way).
#[derive(Clone, Debug, PartialEq)]
pub struct StepFrame {
    /// What the session prepared: one candidate per tracked face and new detection (empty: "no face").
    pub candidates: Vec<Candidate>,
    /// What the aligner answered, per candidate.
    pub alignments: Vec<Option<Alignment>>,
    /// Whether the detector ran on this frame.
    pub detected: bool,
    /// The frame's faces.
    pub faces: SessionFrame,
    /// Time per step (align: all faces together).
    pub timings: Timings,
}

impl StepFrame {
    /// The first candidate (the oldest track, or the first detection), if any.
    pub fn first_candidate(&self) -> Option<&Candidate> {
        self.candidates.first()
    }

    /// What the aligner answered for the first candidate.
    pub fn first_alignment(&self) -> Option<Alignment> {
        self.alignments.first().copied().flatten()
    }
}

/// Runs one frame with every tracked face: prepare, align each candidate with `aligner` (its detection
/// variant for new detections), complete.
pub fn step_faces<A: Aligner + ?Sized>(
    session: &mut TrackerSession,
    aligner: &mut A,
    frame: &Frame<'_>,
) -> Result<StepFrame, StepError> {
    let t0 = Instant::now();
    let runs = session.detector_runs();
    let candidates = session.prepare_faces(frame)?;
    let detected = session.detector_runs() != runs;
    let t1 = Instant::now();
    let alignments: Vec<Option<Alignment>> = aligner
        .align_faces(&frame.image, &candidates)?
        .into_iter()
        .map(Some)
        .collect();
    let t2 = Instant::now();
    let faces = session.complete_faces(frame, &alignments);
    Ok(StepFrame {
        candidates,
        alignments,
        detected,
        faces,
        timings: Timings {
            prepare: t1 - t0,
            align: t2 - t1,
            complete: t2.elapsed(),
        },
    })
}
