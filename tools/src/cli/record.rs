//! `holoface record`: writes a recorded stream (`.hfrec`, the protocol's format) from any frame source.

use holoface_models::crop::CROP_SIDE;
use holoface_sources::output::Output;
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args as ClapArgs, ValueEnum};
use holoface_protocol::CropEncoding;
use holoface_protocol::recording::{
    CameraIntrinsics, FramePayload, FrameRecord, RecordingHeader, RecordingWriter,
};

use holoface_process::stop::Stop;
use holoface_sources::{FrameSource, OwnedFrame};

/// How full frames are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum FrameEncoding {
    /// Uncompressed gray8.
    Raw,
    /// Lossless PNG.
    Png,
}

/// Arguments of `holoface record`.
#[derive(Debug, ClapArgs)]
pub struct Args {
    /// The frames.
    #[command(flatten)]
    pub input: crate::args::SourceArgs,
    /// Output `.hfrec` file.
    #[arg(long)]
    pub out: PathBuf,
    /// Frame storage.
    #[arg(long, value_enum, default_value = "png")]
    pub encoding: FrameEncoding,
    /// Record the crops the client would send instead of full frames, in this wire encoding (`raw`, `png`,
    /// `jpeg:Q`): the tracker runs locally (detector, KRFWS) and each frame's 112x112 crop is stored with
    /// its crop-to-image similarity. Frames without a face are skipped. The load tester replays these.
    #[arg(long)]
    pub crops: Option<holoface_runtime::CropCodec>,
    /// CANDIDE-3 model.
    #[command(flatten)]
    pub candide: crate::args::CandideArg,
    /// Runtime assets (for `--crops`).
    #[command(flatten)]
    pub runtime: crate::args::RuntimeArgs,
}

/// Cuts the client's crop of each frame by running the tracker locally.
struct CropCutter {
    codec: holoface_runtime::CropCodec,
    tracker: holoface_runtime::FaceTracker,
    mean: [holoface_models::geometry::Point2; 68],
    crop: holoface_models::crop::Crop112,
}

impl CropCutter {
    fn new(codec: holoface_runtime::CropCodec, args: &Args) -> anyhow::Result<Self> {
        let mean = holoface_models::shape::dan_mean_shape();
        Ok(Self {
            codec,
            // The local tracker an app runs (KRFWS).
            tracker: crate::args::tracker(args.runtime.tracker_options(&args.candide, Default::default()))?,
            mean,
            crop: holoface_models::crop::Crop112::default(),
        })
    }

    /// The crop payload of `f`, or `None` when no face is tracked.
    fn cut(&mut self, f: &OwnedFrame) -> anyhow::Result<Option<FramePayload>> {
        let frame = f.view();
        let step = self.tracker.process_step(&frame)?;
        let Some(first) = step.first_candidate() else {
            return Ok(None);
        };
        let sim = holoface_runtime::align::crop_from_image(&first.init, &self.mean)?;
        holoface_models::crop::crop_bilinear(&frame.image, &sim, &mut self.crop)?;
        let back = sim.inverse().context("degenerate crop similarity")?;
        let crop =
            holoface_runtime::crop_codec::encode(self.codec, self.crop.as_slice(), CROP_SIDE, CROP_SIDE)?;
        Ok(Some(FramePayload::Crop {
            image_from_crop: [back.a as f32, back.b as f32, back.tx as f32, back.ty as f32],
            crop,
        }))
    }
}

/// The whole frame as a record, its pixels raw or PNG.
fn full_frame(f: &OwnedFrame, encoding: FrameEncoding) -> anyhow::Result<FrameRecord> {
    let (w, h) = (f.image.width() as u32, f.image.height() as u32);
    let (encoding, data) = match encoding {
        FrameEncoding::Raw => (CropEncoding::Raw, f.image.as_bytes().to_vec()),
        FrameEncoding::Png => {
            let mut png = Vec::new();
            let enc = image::codecs::png::PngEncoder::new(&mut png);
            image::ImageEncoder::write_image(enc, f.image.as_bytes(), w, h, image::ExtendedColorType::L8)?;
            (CropEncoding::Png, png)
        }
    };
    Ok(FrameRecord {
        timestamp_us: f.timestamp_us,
        camera_to_world: f.world_from_camera.to_row_major_4x4(),
        payload: FramePayload::FullFrame {
            width: w,
            height: h,
            encoding,
            data: data.into(),
        },
        ground_truth: f
            .ground_truth
            .as_ref()
            .map(|g| g.iter().map(|p| [p.x, p.y]).collect()),
        face_present: None,
    })
}

/// The recording's header: the first frame's camera and size, where it came from, when.
fn header(args: &Args, first: &OwnedFrame) -> RecordingHeader {
    let k = first.intrinsics;
    RecordingHeader {
        intrinsics: CameraIntrinsics {
            fx: k.fx as f32,
            fy: k.fy as f32,
            cx: k.cx as f32,
            cy: k.cy as f32,
            width: first.image.width() as u32,
            height: first.image.height() as u32,
        },
        source: format!("holoface record {}", args.input.source.display())
            .chars()
            .take(1000)
            .collect(),
        created_unix_ms: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as u64),
    }
}

/// Runs `holoface record`.
pub fn run(args: Args, stop: &Stop) -> anyhow::Result<()> {
    let mut source = args.input.open()?;
    let Some(first) = source.next_frame()? else {
        bail!("{} holds no frames", args.input.source.display())
    };
    let header = header(&args, &first);
    record(&args, source, first, &header, stop)
}

/// Writes the recording, from its first frame on.
fn record(
    args: &Args,
    mut source: Box<dyn FrameSource>,
    first: OwnedFrame,
    header: &RecordingHeader,
    stop: &Stop,
) -> anyhow::Result<()> {
    // From a live source (`-`) the recording is a journal: written under its real name (or to standard output)
    // and flushed record by record, and a signal ends the run as the stream's end would. From a file it appears
    // at --out only when it is complete: a failed run leaves no file.
    let stdout = args.out == std::path::Path::new("-");
    let live = args.input.is_stdin() || stdout;
    let out = if live {
        stop.stop_gracefully();
        let out = Output::live(&args.out)?;
        if out.is_stdout() {
            crate::cli::stdout_carries_data();
        }
        out
    } else {
        Output::create(&args.out, crate::cli::temporaries())?
    };
    let mut writer = RecordingWriter::new(out, header)?;
    // The next frame, or none once a stop was asked for (a source cut by the same signal is its end).
    let next = |source: &mut Box<dyn FrameSource>| -> anyhow::Result<Option<OwnedFrame>> {
        if stop.requested().is_some() {
            return Ok(None);
        }
        match source.next_frame() {
            Err(_) if stop.requested().is_some() => Ok(None),
            r => Ok(r?),
        }
    };
    let mut cutter = args.crops.map(|c| CropCutter::new(c, args)).transpose()?;
    let mut frame = Some(first);
    let mut count = 0usize;
    while let Some(f) = frame {
        if let Some(cutter) = cutter.as_mut() {
            if let Some(payload) = cutter
                .cut(&f)
                .with_context(|| format!("frame {} of {}", f.index, args.input.source.display()))?
            {
                writer
                    .write_record(&FrameRecord {
                        timestamp_us: f.timestamp_us,
                        camera_to_world: f.world_from_camera.to_row_major_4x4(),
                        payload,
                        ground_truth: None,
                        face_present: Some(true),
                    })
                    .with_context(|| format!("writing frame {}", f.index))?;
                if live {
                    writer.flush()?;
                }
                count += 1;
            }
            frame = next(&mut source)?;
            continue;
        }
        let record = full_frame(&f, args.encoding)?;
        writer
            .write_record(&record)
            .with_context(|| format!("writing frame {}", f.index))?;
        if live {
            writer.flush()?;
        }
        count += 1;
        frame = next(&mut source)?;
    }
    writer
        .finish()
        .with_context(|| format!("finishing {}", args.out.display()))?
        .commit()?;
    let to = if stdout {
        "standard output".to_owned()
    } else {
        args.out.display().to_string()
    };
    match stop.requested() {
        Some(sig) => {
            crate::say!(
                "stopped by {} after {count} frames; kept every one in {to}",
                sig.name()
            );
            std::process::exit(sig.exit_code());
        }
        None => crate::say!("wrote {count} frames to {to}"),
    }
    Ok(())
}
