//! The measures of `holoface stability`: per run, jitter and agreement with the peer, the switches between
//! remote and local and their jumps against a never-cut run, and what the link cuts did.

use super::*;

/// One aligner's report.
#[derive(Debug, serde::Serialize)]
pub(super) struct Report {
    pub(super) aligner: &'static str,
    pub(super) frames: usize,
    pub(super) faces_found: usize,
    /// Faces found by a fresh detection after the first one (tracking was lost and found again).
    pub(super) redetections: usize,
    pub(super) remote_answers: usize,
    pub(super) raw_jitter49: Option<Summary>,
    pub(super) steadied_jitter49: Option<Summary>,
    pub(super) raw_vs_peer_nme49: Option<Summary>,
    pub(super) steadied_vs_peer_nme49: Option<Summary>,
    pub(super) switches: usize,
    /// Switches into and out of local interludes wholly outside the link cuts, between two remote answers: the
    /// server missed a deadline (the machine's load, not the cut schedule). The rest are the link's own changes
    /// (up at the start, each cut, each return), which the cuts fix on media time, paced input or not.
    pub(super) switches_at_missed_deadlines: usize,
    /// Switches on a frame where the clip itself jumps (the peer's own jump there is over
    /// [`CLIP_EDIT_JUMP`]: an edit or a whip of the head): left out of the largest jumps below.
    pub(super) switches_at_clip_jumps: usize,
    /// The largest jump at a remote/local switch (eye distances), raw and steadied.
    pub(super) largest_switch_jump_raw: Option<f64>,
    pub(super) largest_switch_jump_steadied: Option<f64>,
    /// Each switch measured (not at a clip jump): its frame, the steadied jump, and with a `remote-uncut` run
    /// beside it, that run's steadied jump at the same frame when it did not switch there itself.
    pub(super) switch_jumps: Vec<SwitchJump>,
    /// Over the switches with a `remote-uncut` run beside: the largest and the median excess
    /// ([`SwitchJump::excess`]; eye distances).
    pub(super) largest_switch_excess: Option<f64>,
    pub(super) median_switch_excess: Option<f64>,
    /// The steadied landmarks' jump on every frame (`|p(t) - 2 p(t-1) + p(t-2)|`, eye distances): the measure
    /// of a switch's jump, over the whole clip. (A switch's excess is held to KRFWS's median steadied
    /// `jitter49`, half of this measure's median: an ordinary local frame's motion.)
    pub(super) steadied_jump: Option<Summary>,
    /// The blendshapes against the lips' gap and the eyes' opening measured on the peer's landmarks (ours,
    /// raw, without a peer), after calibration.
    pub(super) expressions: VideoReport,
    /// With `--link-cuts`: the frames inside the cuts that the local aligner answered, and the frames the
    /// server answered.
    pub(super) cuts: Option<CutReport>,
    /// The tracker's time per frame on this thread, ms (for the local aligner: the whole local frame).
    pub(super) ms_per_frame: Option<Summary>,
}

/// One switch's jump beside the motion of a run that did not switch (see [`Report::switch_jumps`]).
#[derive(Debug, serde::Serialize)]
pub(super) struct SwitchJump {
    pub(super) frame: usize,
    pub(super) steadied: Option<f64>,
    pub(super) uncut_steadied: Option<f64>,
    /// What the switching run moves beyond the run that never switched: the larger of the steadied jump minus
    /// the uncut run's, at the switch's frame and at the next (where a blend that starts with a step in speed
    /// shows), over the frames where the uncut run did not switch itself.
    pub(super) excess: Option<f64>,
}

/// One aligner's answers split by who gave them while the link was cut on a schedule.
#[derive(Debug, serde::Serialize)]
pub(super) struct CutReport {
    pub(super) frames_in_cuts: usize,
    /// Frames inside the cuts answered by the local aligner (KRFWS, corrected when adapted).
    pub(super) local_in_cuts: usize,
    /// Of those, the ones whose landmarks were corrected by the adaptation.
    pub(super) corrected_in_cuts: usize,
    /// Pairs learnt when the first cut began.
    pub(super) pairs_at_first_cut: Option<u32>,
    pub(super) local_in_cuts_vs_peer_raw: Option<Summary>,
    pub(super) local_in_cuts_vs_peer_steadied: Option<Summary>,
    pub(super) local_in_cuts_jitter_raw: Option<Summary>,
    pub(super) local_in_cuts_jitter_steadied: Option<Summary>,
    pub(super) remote_vs_peer_raw: Option<Summary>,
    pub(super) remote_vs_peer_steadied: Option<Summary>,
    /// The mean correction's size over the corrected frames (eye distances).
    pub(super) mean_correction: Option<f64>,
}

/// The summary of `values` over the frames where `keep` holds.
pub(super) fn over(values: &[Option<f64>], keep: impl Fn(usize) -> bool) -> Option<Summary> {
    let kept: Vec<Option<f64>> = values
        .iter()
        .enumerate()
        .map(|(t, v)| v.filter(|_| keep(t)))
        .collect();
    summarise(&kept)
}

pub(super) fn cut_report(r: &Run, peer: Option<&[Landmarks]>, in_cut: &[bool]) -> CutReport {
    let cut = |t: usize| in_cut.get(t).copied().unwrap_or(false);
    let local = |t: usize| cut(t) && r.by[t] == Some(AnsweredBy::Krfws);
    let remote = |t: usize| r.by[t] == Some(AnsweredBy::RemoteDan);
    let vs_peer =
        |lm: &[Landmarks], keep: &dyn Fn(usize) -> bool| peer.and_then(|p| over(&agreement(lm, p), keep));
    let corrected: Vec<f64> = (0..r.adapt.len())
        .filter(|&t| local(t))
        .filter_map(|t| {
            r.adapt[t]
                .filter(|a| a.corrected)
                .map(|a| f64::from(a.correction))
        })
        .collect();
    CutReport {
        frames_in_cuts: (0..r.by.len()).filter(|&t| cut(t)).count(),
        local_in_cuts: (0..r.by.len()).filter(|&t| local(t)).count(),
        corrected_in_cuts: corrected.len(),
        pairs_at_first_cut: in_cut
            .iter()
            .position(|&c| c)
            .and_then(|t| r.adapt[..t].iter().rev().find_map(|a| a.map(|a| a.pairs))),
        local_in_cuts_vs_peer_raw: vs_peer(&r.raw, &local),
        local_in_cuts_vs_peer_steadied: vs_peer(&r.steady, &local),
        local_in_cuts_jitter_raw: over(&jitter49(&r.raw), local),
        local_in_cuts_jitter_steadied: over(&jitter49(&r.steady), local),
        remote_vs_peer_raw: vs_peer(&r.raw, &remote),
        remote_vs_peer_steadied: vs_peer(&r.steady, &remote),
        mean_correction: (!corrected.is_empty())
            .then(|| corrected.iter().sum::<f64>() / corrected.len() as f64),
    }
}

/// The peer's own jump (eye distances) above which a frame is a jump of the clip itself (an edit, a whip of the
/// head): on the development clips dlib's jumps pass it on a few per cent of the frames, at the clips' edits and
/// fast turns (up to 24 %), where every tracker jumps whoever answers.
pub(super) const CLIP_EDIT_JUMP: f64 = 0.05;

/// Whether a different aligner answered frame `t` than frame `t - 1` (both answered).
pub(super) fn switched(by: &[Option<AnsweredBy>], t: usize) -> bool {
    t > 0 && matches!((by.get(t - 1), by.get(t)), (Some(Some(a)), Some(Some(b))) if a != b)
}

/// The switches into and out of local interludes that lie wholly outside the link cuts (`in_cut`; none when
/// there are no cuts) with a remote answer on each side: two per interlude.
pub(super) fn missed_deadline_switches(by: &[Option<AnsweredBy>], in_cut: Option<&[bool]>) -> usize {
    let remote = |t: usize| by.get(t) == Some(&Some(AnsweredBy::RemoteDan));
    let local = |t: usize| matches!(by.get(t), Some(Some(a)) if *a != AnsweredBy::RemoteDan);
    let cut = |t: usize| in_cut.and_then(|c| c.get(t)).copied().unwrap_or(false);
    let mut switches = 0;
    let mut t = 1;
    while t < by.len() {
        if local(t) && remote(t - 1) {
            let end = (t..by.len()).find(|&k| !local(k)).unwrap_or(by.len());
            if remote(end) && !(t..end).any(cut) {
                switches += 2;
            }
            t = end;
        } else {
            t += 1;
        }
    }
    switches
}

/// The steadied jump at each of `frames` (switches), beside the `uncut` run's (who answered it, its steadied
/// landmarks) at the same frame where that run did not switch itself.
pub(super) fn switch_jumps(
    frames: &[usize],
    steady: &[Landmarks],
    uncut: Option<(&[Option<AnsweredBy>], &[Landmarks])>,
) -> Vec<SwitchJump> {
    let theirs = |t: usize| {
        uncut
            .filter(|(by, _)| !switched(by, t))
            .and_then(|(_, lm)| jump(lm, t))
    };
    frames
        .iter()
        .map(|&t| SwitchJump {
            frame: t,
            steadied: jump(steady, t),
            uncut_steadied: theirs(t),
            excess: [t, t + 1]
                .into_iter()
                .filter_map(|k| Some(jump(steady, k)? - theirs(k)?))
                .reduce(f64::max),
        })
        .collect()
}

pub(super) fn report(
    r: &Run,
    peer: Option<&[Landmarks]>,
    in_cut: Option<&[bool]>,
    uncut: Option<&Run>,
) -> Report {
    let frames = r.raw.len();
    // Calibration takes the first second (`BlendshapeParams::calibration_s`) of the first track: its frames
    // within that time of the first face, and the frame that completes it.
    let first = r.raw.iter().position(Option::is_some).unwrap_or(0);
    let t0 = r.times_s.get(first).copied().unwrap_or(0.0);
    let calibration_s = BlendshapeParams::default().calibration_s;
    let calibrated_from = first
        + r.times_s[first.min(r.times_s.len())..]
            .iter()
            .take_while(|&&t| t - t0 < calibration_s - 1e-9)
            .count();
    let all_switches = (1..frames).filter(|&t| switched(&r.by, t)).count();
    // A switch is judged by the jump it adds: where the clip itself jumps (the peer's landmarks too), the
    // jump says nothing about the switch.
    let switch_frames: Vec<usize> = (1..frames)
        .filter(|&t| switched(&r.by, t))
        .filter(|&t| peer.and_then(|p| jump(p, t)).is_none_or(|j| j <= CLIP_EDIT_JUMP))
        .collect();
    let largest = |lm: &[Landmarks]| {
        switch_frames
            .iter()
            .filter_map(|&t| jump(lm, t))
            .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))))
    };
    let vs_peer = |lm: &[Landmarks]| peer.and_then(|p| summarise(&agreement(lm, p)));
    let uncut = uncut
        .filter(|u| u.name != r.name)
        .map(|u| (&u.by[..], &u.steady[..]));
    let switch_jumps = switch_jumps(&switch_frames, &r.steady, uncut);
    let excess = summarise(&switch_jumps.iter().map(|j| j.excess).collect::<Vec<_>>());
    Report {
        aligner: r.name,
        frames,
        faces_found: r.raw.iter().filter(|l| l.is_some()).count(),
        redetections: r.detections.saturating_sub(1),
        remote_answers: r.by.iter().filter(|b| **b == Some(AnsweredBy::RemoteDan)).count(),
        raw_jitter49: summarise(&jitter49(&r.raw)),
        steadied_jitter49: summarise(&jitter49(&r.steady)),
        raw_vs_peer_nme49: vs_peer(&r.raw),
        steadied_vs_peer_nme49: vs_peer(&r.steady),
        switches: all_switches,
        switches_at_missed_deadlines: missed_deadline_switches(&r.by, in_cut),
        switches_at_clip_jumps: all_switches - switch_frames.len(),
        largest_switch_jump_raw: largest(&r.raw),
        largest_switch_jump_steadied: largest(&r.steady),
        switch_jumps,
        largest_switch_excess: excess.map(|e| e.max),
        median_switch_excess: excess.map(|e| e.median),
        steadied_jump: summarise(&(0..frames).map(|t| jump(&r.steady, t)).collect::<Vec<_>>()),
        expressions: video_report(
            &r.shapes,
            peer.unwrap_or(&r.raw),
            calibrated_from,
            RestRule::default(),
        ),
        cuts: in_cut.map(|c| cut_report(r, peer, c)),
        ms_per_frame: summarise(&r.ms),
    }
}
