//! A fallback that learned from the server (issue 55): while remote answers arrive, the local aligner also
//! runs on some of those frames and each tracked face learns a correction of the local answer towards the
//! remote one ([`holoface_models::adapt::PersonCorrection`]), from the mean offset and, per point, what the
//! local aligner saw there ([`Aligner::appearance`]); when the link drops, the local answers of that face are
//! corrected (each corrected answer also asks the local aligner what it sees at it: KRFWS, 0.07 ms). A face that is lost takes its correction with it: a new face (a new id) starts
//! from nothing. Nothing runs on the server.
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
    /// Measured on the development clips (BENCHMARKS.md, "A fallback that learned from the server").
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
                    if due {
                        let mine = local.align(image, &face.init)?;
                        let look = if mine.accepted && state.correction.wants_appearance() {
                            local.appearance(image, &mine.landmarks)
                        } else {
                            None
                        };
                        // The size reported is the correction without the appearance's part: solving those
                        // regressions at every pair would cost more than the pair.
                        if mine.accepted
                            && state
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
                    let look = if state.correction.wants_appearance() {
                        local.appearance(image, &answer.landmarks)
                    } else {
                        None
                    };
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
