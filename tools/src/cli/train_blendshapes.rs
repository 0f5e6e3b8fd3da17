//! `holoface train-blendshapes`: learns how head turns move each landmark in the blendshapes' face frame
//! (`holoface_models::blendshapes::PoseTerms`) from the training split's annotations and their mirror images,
//! each face's turn from CANDIDE-3 fitted to its annotation, and writes `models/assets/blendshape_pose.txt`.

use std::path::PathBuf;

use anyhow::Context;
use holoface_models::blendshapes::{HeadTurn, fit_pose_terms};
use holoface_models::camera::Intrinsics;
use holoface_models::candide::{FitOptions, fit};
use holoface_models::geometry::{Point2, Rect};
use holoface_models::shape::mirror68;

use holoface_harness::data::{Split, faces68_or, list_folder};

/// Arguments of `holoface train-blendshapes`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Annotated face folder (`NAME.pts` beside each image); default `$HOLOFACE_DATA/faces68/train`. Only
    /// the training split is read (the validation split is never trained on).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// The terms' text file.
    #[arg(long, default_value = "models/assets/blendshape_pose.txt")]
    pub out: PathBuf,
    /// CANDIDE-3 model (each face's turn comes from its fit to the annotation).
    #[command(flatten)]
    pub candide: crate::args::CandideArg,
}

/// A still's camera: unknown, so a long lens (focal length 10 face widths) centred on the face: close to
/// the orthographic view a 300-W photograph's face mostly is.
fn still_camera(lm: &[Point2; 68]) -> Option<Intrinsics> {
    let b = Rect::bounding(lm)?;
    let f = 10.0 * f64::from((b.x1 - b.x0).max(b.y1 - b.y0));
    let (cx, cy) = (f64::from(0.5 * (b.x0 + b.x1)), f64::from(0.5 * (b.y0 + b.y1)));
    Some(Intrinsics::new(f, f, cx, cy))
}

/// Runs `holoface train-blendshapes`.
pub fn run(args: Args) -> anyhow::Result<()> {
    let data = faces68_or(args.data.as_deref());
    let model = args.candide.load()?;
    let entries = list_folder(&data, Split::Train, true)?;
    let faces: Vec<[Point2; 68]> = entries.iter().filter_map(|e| e.landmarks).collect();
    let opts = FitOptions {
        max_iterations: 30,
        ..FitOptions::default()
    };
    let mut shapes = Vec::with_capacity(2 * faces.len());
    let mut unfitted = 0usize;
    for f in &faces {
        for lm in [*f, mirror68(f, 0)] {
            let fitted = still_camera(&lm).and_then(|k| fit(&model, &k, &lm, None, &opts).ok());
            match fitted {
                Some(r) => shapes.push((lm, HeadTurn::from_pose(r.rotation, r.translation))),
                None => unfitted += 1,
            }
        }
    }
    let terms = fit_pose_terms(&shapes).context("too few usable annotated faces to fit the pose terms")?;
    let comment = format!(
        "How head turns move each landmark in the blendshapes' face frame (holoface_models::blendshapes::PoseTerms).\n\
         Fitted by `holoface train-blendshapes` on {} training faces of faces68/train (validation split\n\
         excluded) and their mirror images: {} shapes ({unfitted} without a CANDIDE-3 fit left out), each\n\
         face's turn from CANDIDE-3 fitted to its annotation. Statistics our code produced; no one's landmarks.",
        faces.len(),
        shapes.len()
    );
    crate::cli::write_atomic(&args.out, terms.to_text(&comment))?;
    crate::say!(
        "{} faces, {} shapes with a fit ({unfitted} without): wrote {}",
        faces.len(),
        shapes.len(),
        args.out.display()
    );
    Ok(())
}
