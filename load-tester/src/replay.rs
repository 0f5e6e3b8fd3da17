//! The recorded streams a headset replays: the crops of a `.hfrec` and when each is due.

use std::path::Path;
use std::time::Duration;

use anyhow::{Context, bail};
use holoface_protocol::Crop;
use holoface_protocol::recording::{FramePayload, RecordingReader};

/// One recorded frame to replay.
#[derive(Clone)]
pub(crate) struct ReplayFrame {
    /// When the frame is due, from the start of the loop.
    pub(crate) offset: Duration,
    /// The recorded crop.
    pub(crate) crop: Crop,
}

/// The frames of one recorded stream of crops (at their recorded timing, or at `fps`) and the length of
/// one loop over them.
pub(crate) fn read_stream(path: &Path, fps: Option<f64>) -> anyhow::Result<(Vec<ReplayFrame>, Duration)> {
    let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut reader = RecordingReader::new(std::io::BufReader::new(file))
        .with_context(|| format!("reading {}", path.display()))?;
    let mut frames = Vec::new();
    let mut first = None;
    while let Some(r) = reader
        .next_record()
        .with_context(|| format!("reading {}", path.display()))?
    {
        let FramePayload::Crop { crop, .. } = r.payload else {
            bail!(
                "{} holds full frames; record crops with `holoface record --crops jpeg:75`",
                path.display()
            );
        };
        let t0 = *first.get_or_insert(r.timestamp_us);
        let offset = match fps {
            Some(f) => Duration::from_secs_f64(frames.len() as f64 / f),
            None => Duration::from_micros(r.timestamp_us.saturating_sub(t0)),
        };
        frames.push(ReplayFrame { offset, crop });
    }
    if frames.is_empty() {
        bail!("{} holds no frames", path.display());
    }
    // The stream loops: one mean frame interval after its last frame comes its first again.
    let n = frames.len() as u32;
    let last = frames.last().map_or(Duration::ZERO, |f| f.offset);
    let step = match fps {
        Some(f) => Duration::from_secs_f64(1.0 / f),
        None if n > 1 => last / (n - 1),
        None => Duration::from_secs_f64(1.0 / 30.0),
    };
    let period = last + step;
    if period.is_zero() {
        bail!(
            "{}: every frame has the same timestamp, so the stream has no timing; give --fps",
            path.display()
        );
    }
    Ok((frames, period))
}
