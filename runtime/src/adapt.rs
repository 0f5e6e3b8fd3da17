//! A fallback that learned from the server (issue 55): while remote answers arrive, the local aligner also
//! runs on some of those frames and each tracked face learns a correction of the local answer towards the
//! remote one ([`holoface_models::adapt::PersonCorrection`]), from the mean offset and, per point, what the
//! local aligner saw there ([`Aligner::appearance`]); when the link drops, the local answers of that face are
//! corrected (each corrected answer also asks the local aligner what it sees at it: KRFWS, 0.07 ms). A face
//! that is lost takes its correction with it: a new face (a new id) starts from nothing. Nothing runs on
//! the server.
//!
//! [`LocalAdaptation::update`] is called by the remote aligner ([`crate::link::LinkedAligner`]) after every
//! frame; with the local aligner alone nothing is ever learnt, so nothing changes.

use std::collections::HashMap;

use holoface_models::adapt::{AdaptParams, Learnt, PersonCorrection};
use holoface_models::image::GrayView;

use crate::align::{AdaptState, AlignError, Aligner, Alignment, AnsweredBy, Candidate, InitSource};

/// Settings of the adaptation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptOptions {
    /// The local aligner runs beside every this many remote answers of a face (1: every one) to learn a
    /// pair; each run costs one tracked local alignment (KRFWS: 0.3 ms when it runs often, about 0.65 ms run
    /// this rarely, its model out of the caches), and, when the correction uses the answers' appearance, its
    /// HOG at the answer (0.07 ms) and the pair's sums (0.014 ms; BENCHMARKS.md).
    pub learn_every: u32,
    /// A face's first this many remote answers each get a local run beside them (a link that drops early
    /// still leaves a correction), then every `learn_every`-th. 60 (two seconds at 30 fps): the
    /// appearance's 36 values per point need more pairs than a mean offset.
    pub warm_pairs: u32,
    /// The correction's settings.
    pub params: AdaptParams,
}

impl Default for AdaptOptions {
    /// Measured on the development clips (docs/experiments/fallback-adaptation.md).
    fn default() -> Self {
        Self {
            learn_every: crate::defaults::ADAPT_LEARN_EVERY,
            warm_pairs: 60,
            params: AdaptParams::default(),
        }
    }
}

struct Face {
    correction: PersonCorrection,
    remote_answers: u32,
    last_size: f32,
}

/// Every tracked face's correction (see the module docs).
pub struct LocalAdaptation {
    opts: AdaptOptions,
    faces: HashMap<u32, Face>,
}

impl std::fmt::Debug for LocalAdaptation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LocalAdaptation")
            .field("faces", &self.faces.len())
            .finish_non_exhaustive()
    }
}

impl LocalAdaptation {
    /// Nothing learnt yet.
    pub fn new(opts: AdaptOptions) -> Self {
        Self {
            opts,
            faces: HashMap::new(),
        }
    }

    /// After `answers` (one per face of `faces`, in order) were produced for a frame: each tracked face the
    /// server answered learns a pair when due (`local` runs from the same start), each one the local
    /// aligner answered is corrected once the face has learnt enough, and every answer of a tracked face
    /// carries the face's [`AdaptState`]. Faces no longer tracked are forgotten.
    pub fn update<A: Aligner + ?Sized>(
        &mut self,
        local: &mut A,
        image: &GrayView<'_>,
        faces: &[Candidate],
        answers: &mut [Alignment],
    ) -> Result<(), AlignError> {
        self.faces
            .retain(|id, _| faces.iter().any(|c| c.track == Some(*id)));
        for (face, answer) in faces.iter().zip(answers.iter_mut()) {
            // A new detection has no id yet: its first pair comes on its next frame.
            let (Some(id), InitSource::Tracking) = (face.track, face.source) else {
                continue;
            };
            let params = self.opts.params;
            let state = self.faces.entry(id).or_insert_with(|| Face {
                correction: PersonCorrection::new(params),
                remote_answers: 0,
                last_size: 0.0,
            });
            let mut corrected = false;
            match answer.answered_by {
                AnsweredBy::RemoteDan if answer.accepted => {
                    let due = state.remote_answers < self.opts.warm_pairs
                        || state.remote_answers.is_multiple_of(self.opts.learn_every.max(1));
                    state.remote_answers = state.remote_answers.wrapping_add(1);
                    let mine = due.then(|| local.align(image, &face.init)).transpose()?;
                    if let Some(mine) = mine.filter(|m| m.accepted) {
                        let wanted = state.correction.wants_appearance();
                        let look = wanted.then(|| local.appearance(image, &mine.landmarks)).flatten();
                        // The size reported is the correction without the appearance's part: solving those
                        // regressions at every pair would cost more than the pair.
                        if state
                            .correction
                            .learn(&mine.landmarks, &answer.landmarks, look.as_deref())
                            == Learnt::Yes
                            && let Some((_, size)) = state.correction.correct(&mine.landmarks, None)
                        {
                            state.last_size = size;
                        }
                    }
                }
                AnsweredBy::Krfws => {
                    // Only a correction that can correct asks what the local aligner saw (with no link ever
                    // up, nothing is learnt and nothing more runs).
                    let wanted = state.correction.ready() && state.correction.wants_appearance();
                    let look = wanted
                        .then(|| local.appearance(image, &answer.landmarks))
                        .flatten();
                    if let Some((fixed, size)) = state.correction.correct(&answer.landmarks, look.as_deref())
                    {
                        answer.landmarks = fixed;
                        state.last_size = size;
                        corrected = true;
                    }
                }
                _ => {}
            }
            answer.adaptation = Some(AdaptState {
                pairs: state.correction.pairs(),
                corrected,
                correction: state.last_size,
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use holoface_models::adapt::{APPEARANCE, Appearance};
    use holoface_models::geometry::Point2;
    use holoface_models::shape::dan_mean_shape;

    use super::*;
    use crate::align::{Confidence, LandmarkSet};

    /// A local aligner that answers its start and counts how often it is asked what it sees.
    #[derive(Default)]
    struct Seeing {
        looks: usize,
    }

    impl Aligner for Seeing {
        fn name(&self) -> &'static str {
            "seeing"
        }
        fn align(&mut self, _: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
            Ok(answer(init, AnsweredBy::Krfws))
        }
        fn appearance(&mut self, _: &GrayView<'_>, _: &[Point2; 68]) -> Option<Box<Appearance>> {
            self.looks += 1;
            Some(Box::new([[0.5; APPEARANCE]; 51]))
        }
    }

    fn answer(landmarks: &[Point2; 68], answered_by: AnsweredBy) -> Alignment {
        Alignment {
            landmarks: *landmarks,
            set: LandmarkSet::Ibug68,
            confidence: Confidence::FaceProbability(1.0),
            accepted: true,
            answered_by,
            adaptation: None,
        }
    }

    #[test]
    fn what_the_local_aligner_sees_is_asked_only_when_it_is_learnt_or_can_correct() {
        let pixels = vec![0u8; 64 * 64];
        let image = GrayView::new(&pixels, 64, 64, 64).unwrap();
        let init = dan_mean_shape();
        let face = [Candidate {
            track: Some(1),
            init,
            source: InitSource::Tracking,
        }];
        let mut local = Seeing::default();
        let mut adapt = LocalAdaptation::new(AdaptOptions::default());
        // No link yet: local answers, nothing learnt, nothing asked.
        for _ in 0..5 {
            let mut out = vec![answer(&init, AnsweredBy::Krfws)];
            adapt.update(&mut local, &image, &face, &mut out).unwrap();
            assert!(!out[0].adaptation.unwrap().corrected);
        }
        assert_eq!(local.looks, 0);
        // The server answers (a shifted shape): each warm pair's local answer is looked at.
        let remote = init.map(|p| Point2::new(p.x + 0.5, p.y));
        for _ in 0..12 {
            let mut out = vec![answer(&remote, AnsweredBy::RemoteDan)];
            adapt.update(&mut local, &image, &face, &mut out).unwrap();
        }
        assert_eq!(local.looks, 12);
        // The link drops: each corrected answer is looked at once.
        let mut out = vec![answer(&init, AnsweredBy::Krfws)];
        adapt.update(&mut local, &image, &face, &mut out).unwrap();
        assert!(out[0].adaptation.unwrap().corrected);
        assert_eq!(local.looks, 13);
    }
}
