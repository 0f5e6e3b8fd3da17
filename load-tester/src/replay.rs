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
    // A recording whose writer was killed ends inside a record: its whole records are replayed (and the cut named).
    let mut reader = RecordingReader::new(std::io::BufReader::new(file))
        .with_context(|| format!("reading {}", path.display()))?
        .tolerate_cut();
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
    if let Some(cut) = reader.cut() {
        eprintln!("{}", holoface_sources::source::cut_note(path, cut));
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use holoface_protocol::recording::{CameraIntrinsics, FrameRecord, RecordingHeader, RecordingWriter};

    #[test]
    fn a_recording_cut_anywhere_replays_its_whole_records() {
        // What `holoface record` leaves when it is killed: the file ends inside a record.
        let header = RecordingHeader {
            intrinsics: CameraIntrinsics {
                fx: 500.0,
                fy: 500.0,
                cx: 56.0,
                cy: 56.0,
                width: 112,
                height: 112,
            },
            source: "test".into(),
            created_unix_ms: 0,
        };
        let record = |k: u8| FrameRecord {
            timestamp_us: u64::from(k) * 33_333,
            camera_to_world: [
                1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
            ],
            payload: FramePayload::Crop {
                image_from_crop: [1.0, 0.0, 0.0, 0.0],
                crop: Crop::raw(16, 16, vec![k; 16 * 16]),
            },
            ground_truth: None,
            face_present: Some(true),
        };
        // The file with its first n records, for n = 0..=4: `ends[n]` is where record n ends.
        let file_of = |n: u8| {
            let mut w = RecordingWriter::new(Vec::new(), &header).unwrap();
            for k in 0..n {
                w.write_record(&record(k)).unwrap();
            }
            w.finish().unwrap()
        };
        let ends: Vec<usize> = (0..=4).map(|n| file_of(n).len()).collect();
        let file = file_of(4);
        let dir = std::env::temp_dir().join(format!("holoface-replay-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("cut.hfrec");
        // Every cut inside the last two records (and at their ends).
        for cut in ends[2] + 1..=file.len() {
            std::fs::write(&path, &file[..cut]).unwrap();
            let (frames, _) = read_stream(&path, None).unwrap();
            let whole = ends.iter().filter(|&&e| e <= cut).count() - 1;
            assert_eq!(frames.len(), whole, "cut at byte {cut}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
