//! DAN in-process, the tools' aligner (`holoface eval`, `track --aligner dan`, `tracking-losses`): the crop the
//! headset would send, one ONNX Runtime call, the landmarks mapped back. A headset never runs DAN itself (it
//! asks the alignment server), so this lives here and not in the runtime.

use holoface_inference::{
    BatchTensor, CascadeEngine, EngineError, InferenceEngine, LandmarkOut, LoadedCascade, OnnxEngine,
    OnnxOptions,
};
use holoface_models::crop::{CROP_SIDE, CROP_SIZE, Crop112, crop_bilinear};
use holoface_models::geometry::Point2;
use holoface_models::image::GrayView;
use holoface_runtime::align::{
    AlignError, Aligner, Alignment, Candidate, Neighbours, crop_from_image, landmarks_from_crop,
};

/// DAN alone, in this process (`engine`: CPU, batch 1).
pub fn dan_alone(engine: &OnnxOptions) -> Result<DanAligner<OnnxEngine>, EngineError> {
    DanAligner::new(OnnxEngine::load(engine)?).map_err(|e| EngineError::BadOutput(e.to_string()))
}

/// The alignment server's pipeline in this process: the crop through the wire's default encoding (JPEG q75)
/// and back, DAN, then the refinement cascade at `refiner` ([`CascadeEngine`], the type the server's engine
/// threads run). The errors name the files (the front end names its settings: `EngineError::given_by`).
pub fn server_pipeline(
    engine: &OnnxOptions,
    refiner: &std::path::Path,
) -> Result<DanAligner<CascadeEngine<OnnxEngine>>, EngineError> {
    let refiner = LoadedCascade::load(refiner)?;
    let dan = OnnxEngine::load(engine)?;
    let mut aligner = DanAligner::new(CascadeEngine::new(dan, refiner)?)
        .map_err(|e| EngineError::BadOutput(e.to_string()))?;
    aligner.set_wire_codec(Some(holoface_runtime::CropCodec::default()));
    Ok(aligner)
}

/// DAN in-process: similarity crop onto the model's mean shape, one ONNX Runtime call, inverse map.
#[derive(Debug)]
pub struct DanAligner<E> {
    engine: E,
    canonical: [Point2; 68],
    threshold: f32,
    crop: Crop112,
    batch: BatchTensor,
    out: Vec<LandmarkOut>,
    wire: Option<holoface_runtime::CropCodec>,
    wire_bytes: (u64, u64),
}

impl<E: InferenceEngine> DanAligner<E> {
    /// Wraps an engine; the canonical shape and threshold come from the model's metadata.
    pub fn new(engine: E) -> Result<Self, AlignError> {
        let info = engine.info();
        if info.landmark_count != 68 || info.crop_size != CROP_SIZE || info.mean_shape.len() != 68 {
            return Err(AlignError::BadOutput(format!(
                "model has {} landmarks on a {} px crop; the client needs 68 on {CROP_SIZE}",
                info.landmark_count, info.crop_size
            )));
        }
        let canonical = std::array::from_fn(|i| Point2::new(info.mean_shape[i][0], info.mean_shape[i][1]));
        let threshold = info.face_threshold;
        Ok(Self {
            engine,
            canonical,
            threshold,
            crop: Crop112::default(),
            batch: BatchTensor::new(1, CROP_SIZE * CROP_SIZE),
            out: vec![LandmarkOut::default()],
            wire: None,
            wire_bytes: (0, 0),
        })
    }

    /// As the tracker's aligner (`FaceTracker::with_aligner`).
    pub fn boxed(self) -> Box<dyn Aligner + Send>
    where
        E: Send + 'static,
    {
        Box::new(self)
    }

    /// The face-probability threshold in use.
    pub fn threshold(&self) -> f32 {
        self.threshold
    }

    /// Overrides the face-probability threshold.
    pub fn set_threshold(&mut self, t: f32) {
        self.threshold = t;
    }

    /// Passes every crop through `codec` (encode, then decode as the server does) before inference, to
    /// measure the accuracy cost of a wire encoding in-process; `None` (the default) feeds the crop as is.
    pub fn set_wire_codec(&mut self, codec: Option<holoface_runtime::CropCodec>) {
        self.wire = codec;
    }

    /// Mean size of the frame requests the wire codec produced (bytes), if any crop went through it.
    pub fn mean_request_bytes(&self) -> Option<f64> {
        (self.wire_bytes.1 > 0).then(|| self.wire_bytes.0 as f64 / self.wire_bytes.1 as f64)
    }
}

impl<E: InferenceEngine> Aligner for DanAligner<E> {
    fn name(&self) -> &'static str {
        "dan"
    }

    fn align(&mut self, image: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
        self.align_among(image, init, None)
    }

    /// One face after another, each crop with the other faces blanked out ([`Neighbours`]).
    fn align_faces(
        &mut self,
        image: &GrayView<'_>,
        faces: &[Candidate],
    ) -> Result<Vec<Alignment>, AlignError> {
        (0..faces.len())
            .map(|i| self.align_among(image, &faces[i].init, Neighbours::of(faces, i).as_ref()))
            .collect()
    }
}

impl<E: InferenceEngine> DanAligner<E> {
    /// One face: its crop (the other faces blanked out of it when `neighbours` says where they are), one
    /// inference, the landmarks mapped back.
    fn align_among(
        &mut self,
        image: &GrayView<'_>,
        init: &[Point2; 68],
        neighbours: Option<&Neighbours>,
    ) -> Result<Alignment, AlignError> {
        let sim = crop_from_image(init, &self.canonical)?;
        crop_bilinear(image, &sim, &mut self.crop)?;
        if let Some(n) = neighbours {
            n.blank(&mut self.crop, &sim);
        }
        self.batch.clear();
        match self.wire {
            None => self.batch.push(self.crop.as_slice())?,
            Some(codec) => {
                let bad = |e: image::ImageError| AlignError::BadOutput(format!("crop codec {codec}: {e}"));
                let crop =
                    holoface_runtime::crop_codec::encode(codec, self.crop.as_slice(), CROP_SIDE, CROP_SIDE)
                        .map_err(bad)?;
                let req = holoface_protocol::FrameRequest {
                    track_id: 0,
                    frame_id: 0,
                    captured_at_us: 0,
                    deadline_ms: 0,
                    crop,
                };
                let decoded = holoface_inference::decode_crop(&req.crop)
                    .map_err(|e| AlignError::BadOutput(format!("crop codec {codec}: {e}")))?;
                self.wire_bytes.0 += holoface_protocol::Message::FrameRequest(req).encoded_len() as u64;
                self.wire_bytes.1 += 1;
                self.batch.push(&decoded)?;
            }
        }
        self.engine.infer(&self.batch, &mut self.out)?;
        let out = self
            .out
            .first()
            .ok_or_else(|| AlignError::BadOutput("no output".into()))?;
        landmarks_from_crop(&out.landmarks, out.face_prob, &sim, self.threshold)
    }
}
