//! Runs KRFWS's single-start alignment `N` times on one annotated face through one instruction-set path, so
//! that an instruction counter can compare the paths where no clock can: under `qemu-aarch64`, which gives no
//! timing, `-one-insn-per-tb -d exec,nochain` logs one line per executed instruction (instructions per face,
//! NEON against the portable kernels; not measured: docs/experiments/arm64.md).
//!
//! ```sh
//! cargo run --release -p holoface-models --example krfws_paths -- FACE.jpg FACE.pts neon|avx512|avx2|baseline N
//! ```
//! Prints the path that ran, the failure score and the NME49 of the answer (the same on every path).

use holoface_models::geometry::Rect;
use holoface_models::image::GrayImage;
use holoface_models::isa::Isa;
use holoface_models::krfws::{Krfws, KrfwsScratch, N_POINTS, nme49_inner};
use holoface_models::shape::parse_pts68;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [image, pts, path, n] = args.as_slice() else {
        return Err("usage: krfws_paths FACE.jpg FACE.pts neon|avx512|avx2|baseline N".into());
    };
    let isa = match path.as_str() {
        "neon" => Isa::Neon,
        "avx512" => Isa::Avx512,
        "avx2" => Isa::Avx2,
        "baseline" => Isa::Baseline,
        other => return Err(format!("unknown path {other}").into()),
    };
    let n: usize = n.parse()?;
    let model = Krfws::from_bytes(&std::fs::read(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/krfws.bin"),
    )?)?;
    let photo = image::open(image)?.into_luma8();
    let (w, h) = (photo.width() as usize, photo.height() as usize);
    let image = GrayImage::from_vec(photo.into_raw(), w, h)?;
    let gt = parse_pts68(&std::fs::read_to_string(pts)?)?;
    let init = model.init_from_box(&Rect::bounding(&gt).ok_or("empty annotation")?);
    let mut scratch = KrfwsScratch::new();
    let mut out = [holoface_models::geometry::Point2::default(); N_POINTS];
    let mut score = f32::NAN;
    for _ in 0..n {
        score = model.align_on(isa, &image.view(), &init, &mut scratch, &mut out);
    }
    println!(
        "{n} alignments asked of the {isa:?} kernels (a path this CPU lacks runs the baseline; this CPU's best: \
         {:?}): score {score:.6}, NME49 {:.6}",
        holoface_models::isa::detected(),
        nme49_inner(&out, &gt)
    );
    Ok(())
}
