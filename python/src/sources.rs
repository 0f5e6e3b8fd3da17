//! Frame sources for Python: image folders, videos and recordings read by `holoface-sources` (the decoders
//! `holoface track` uses), and one image read as gray.

use super::*;

/// A frame read from a source: `image` uint8 (height, width), `timestamp_us`, `intrinsics` (fx, fy, cx, cy),
/// `camera_to_world` float64 4x4, `index`.
#[pyclass(module = "holoface", name = "SourceFrame", frozen, get_all)]
#[derive(Debug)]
pub(crate) struct PySourceFrame {
    /// Frame number in the source.
    index: usize,
    /// Timestamp, microseconds.
    timestamp_us: u64,
    /// uint8 [height, width].
    image: Py<PyArray2<u8>>,
    /// (fx, fy, cx, cy) in pixels.
    intrinsics: (f64, f64, f64, f64),
    /// float64 [4, 4]: the headset camera's pose (identity without a pose sidecar).
    camera_to_world: Py<PyArray2<f64>>,
}

fn source_frame_to_py(py: Python<'_>, f: OwnedFrame) -> PyResult<PySourceFrame> {
    let (w, h) = (f.image.width(), f.image.height());
    let image = Array2::from_shape_vec((h, w), f.image.view().data().to_vec())
        .map_err(|e| SourceError::new_err(format!("frame {}: {e}", f.index)))?;
    let p = f.world_from_camera.to_row_major_4x4();
    let m = Array2::from_shape_fn((4, 4), |(i, j)| f64::from(p[i * 4 + j]));
    let k = f.intrinsics;
    Ok(PySourceFrame {
        index: f.index,
        timestamp_us: f.timestamp_us,
        image: image.into_pyarray(py).unbind(),
        intrinsics: (k.fx, k.fy, k.cx, k.cy),
        camera_to_world: m.into_pyarray(py).unbind(),
    })
}

/// Frames of an image folder (name order, `fps` apart), an MP4/H.264 video, a YUV4MPEG2 stream (`.y4m`) or a
/// `.hfrec` recording, read
/// with the same code as `holoface track --source`; iterate it for `SourceFrame`s.
#[pyclass(module = "holoface", name = "FrameSource", unsendable)]
pub(crate) struct PyFrameSource {
    inner: Box<dyn FrameSource>,
}

impl std::fmt::Debug for PyFrameSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameSource").finish_non_exhaustive()
    }
}

#[pymethods]
impl PyFrameSource {
    #[new]
    #[pyo3(signature = (path, fps = 30.0, poses = None))]
    fn new(path: PathBuf, fps: f64, poses: Option<PathBuf>) -> PyResult<Self> {
        let inner = holoface_sources::source::open_source(&path, fps, poses.as_deref())
            .map_err(|e| SourceError::new_err(format!("{e:#}")))?;
        Ok(Self { inner })
    }

    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__(&mut self, py: Python<'_>) -> PyResult<Option<PySourceFrame>> {
        match self.inner.next_frame() {
            Ok(Some(f)) => source_frame_to_py(py, f).map(Some),
            Ok(None) => Ok(None),
            Err(e) => Err(SourceError::new_err(format!("{e:#}"))),
        }
    }
}

/// Reads an image file (PNG or JPEG) as uint8 grayscale, with the decoder `holoface track` uses; a truncated
/// or corrupt file raises `SourceError` naming it.
#[pyfunction]
pub(crate) fn read_gray(py: Python<'_>, path: PathBuf) -> PyResult<Py<PyArray2<u8>>> {
    let img = py
        .detach(|| holoface_sources::images::read_gray(&path))
        .map_err(|e| SourceError::new_err(format!("{e:#}")))?;
    let a = Array2::from_shape_vec((img.height(), img.width()), img.view().data().to_vec())
        .map_err(|e| SourceError::new_err(format!("{}: {e}", path.display())))?;
    Ok(a.into_pyarray(py).unbind())
}
