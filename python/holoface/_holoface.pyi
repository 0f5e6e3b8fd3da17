"""Type stubs of the extension module (python/src/lib.rs)."""

from os import PathLike
from pathlib import Path
from typing import Iterator, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

__version__: str
BLENDSHAPE_NAMES: list[str]
"""ARKit's names of Face.blendshapes' slots ("eyeBlinkLeft", ..., "jawOpen", ...)."""

_Path = Union[str, PathLike[str]]
_Matrix4 = Union[npt.NDArray[np.floating], Sequence[Sequence[float]]]

class HoloFaceError(Exception):
    """Base class of holoface's errors."""

class AssetError(HoloFaceError):
    """A model file or the ONNX Runtime library could not be loaded (the message names it)."""

class ProcessingError(HoloFaceError):
    """Processing a frame failed (detector or aligner error)."""

class SourceError(HoloFaceError):
    """A frame source could not be opened or read (corrupt, truncated or missing file)."""

class TrackerOptions:
    """Tracker options; every field defaults like the Rust API's `TrackerOptions::default()`."""

    mode: str
    """"video" (track between frames; timestamps must increase) or "image" (detect every frame)."""
    server: Optional[str]
    """Alignment server "ip:port"; None = local KRFWS only."""
    fingerprint: Optional[str]
    """SHA-256 of the server certificate (64 hex digits); required with `server`."""
    token: str
    deadline_ms: int
    """Per-frame deadline for the server's answer; KRFWS answers the frame when it is missed."""
    crop_encoding: str
    """"raw", "png", "jpeg" or "jpeg:Q"."""
    adapt: bool
    """With a server: the local aligner learns each person from the server's answers while the link is up and
    corrects its own when the link is down."""
    lookahead_ms: float
    motion_compensation: bool
    max_faces: int
    """Most faces tracked at once (1..=64), each with a stable id."""
    detect_every: int
    """While some but fewer than max_faces faces are tracked, run the detector every this many frames (>= 1)."""
    detect_tiles: Optional[int]
    """Detector tiles per side besides the whole frame (1..=32); None: 1 for one face, 3 for several."""
    steady: bool
    """Steady the landmarks over time (One-Euro in the face's frame); False: landmarks == raw_landmarks."""
    steady_shape_cutoff_hz: float
    """Local aligner's answers: shape cut-off at rest, Hz (the CLI's --steady-shape-cutoff-hz)."""
    steady_shape_beta: float
    steady_rigid_cutoff_hz: float
    steady_rigid_beta: float
    steady_precise_shape_cutoff_hz: float
    """The server's answers: shape cut-off at rest, Hz (the CLI's --steady-precise-shape-cutoff-hz)."""
    steady_precise_shape_beta: float
    steady_precise_rigid_cutoff_hz: float
    steady_precise_rigid_beta: float
    ort_dylib: Optional[str]
    detector_model: Optional[str]
    krfws_model: Optional[str]
    candide: Optional[str]
    def __init__(
        self,
        *,
        mode: str = "video",
        server: Optional[str] = None,
        fingerprint: Optional[str] = None,
        token: str = "",
        deadline_ms: int = 33,
        crop_encoding: str = "jpeg:75",
        adapt: bool = True,
        lookahead_ms: float = 120.0,
        motion_compensation: bool = True,
        max_faces: int = 1,
        detect_every: int = 10,
        detect_tiles: Optional[int] = None,
        steady: bool = True,
        steady_shape_cutoff_hz: float = 1.0,
        steady_shape_beta: float = 10.0,
        steady_rigid_cutoff_hz: float = 3.0,
        steady_rigid_beta: float = 2.0,
        steady_precise_shape_cutoff_hz: float = 3.0,
        steady_precise_shape_beta: float = 10.0,
        steady_precise_rigid_cutoff_hz: float = 20.0,
        steady_precise_rigid_beta: float = 5.0,
        ort_dylib: Optional[_Path] = None,
        detector_model: Optional[_Path] = None,
        krfws_model: Optional[_Path] = None,
        candide: Optional[_Path] = None,
    ) -> None: ...

class Face:
    """One tracked face (see FaceResult)."""

    id: int
    """The track id: the same for as long as the face is tracked, never reused by this tracker."""
    landmarks: npt.NDArray[np.float32]
    """[68, 2] iBUG-68 landmarks in image pixels, steadied over time (what to draw)."""
    raw_landmarks: npt.NDArray[np.float32]
    blendshapes: npt.NDArray[np.float32]
    """float32 [39]: ARKit-named coefficients in [0, 1], in BLENDSHAPE_NAMES order."""
    """[68, 2] the aligner's own landmarks for this frame, unfiltered."""
    landmark_set: str
    """"ibug68" or "inner51" (KRFWS aligns the 51 inner points; the jaw holds the initial shape)."""
    answered_by: str
    """"remote_dan", "krfws" or "local_dan"."""
    init: str
    """"detection" or "tracking"."""
    face_probability: Optional[float]
    predicted_error: Optional[float]
    camera_pose: npt.NDArray[np.float64]
    """[4, 4] head-to-camera (x right, y down, z forward, metres)."""
    fit_rmse_px: float
    world_pose: npt.NDArray[np.float64]
    """[4, 4] head-to-world, in the frame of the camera_to_world poses passed to process()."""
    predicted_position: npt.NDArray[np.float64]
    """[3] world position predicted lookahead_ms ahead, metres."""
    display_pose: npt.NDArray[np.float64]
    """[4, 4] the pose to render: prediction after two-frame denoising."""
    expression_weights: dict[str, float]
    """HoloFace's five expression weights, derived from `blendshapes`, each in [-1, 1]."""
    smile: bool
    brows_raised: bool
    mouth_open: bool
    adapt_pairs: int
    """With a server and `adapt`: pairs of local and server answers learnt for this face (0 otherwise)."""
    adapt_corrected: bool
    """These landmarks are the local aligner's answer corrected by what it learnt from the server."""
    adapt_correction: float
    """The size of this face's correction: mean length over the 51 inner points, in eye distances."""

class FaceResult:
    """One frame's answer: the faces, or why there is none."""

    timestamp_us: int
    faces: list[Face]
    no_face_reason: Optional[str]
    """"not_detected", "rejected", "no_answer" or "fit_failed"; None with a face."""
    answered_by: Optional[str]
    link_state: Optional[str]
    """With a server: "connecting", "up", "retrying", "failed" or "stopped"."""
    link_failure: Optional[str]
    timings: dict[str, float]
    @property
    def face(self) -> Optional[Face]: ...
    @property
    def has_face(self) -> bool: ...

class FaceTracker:
    """Detects, aligns, fits and filters a face frame by frame; the GIL is released while a frame runs."""

    def __init__(self, options: Optional[TrackerOptions] = None) -> None: ...
    def process(
        self,
        image: npt.NDArray[np.uint8],
        timestamp_us: int,
        camera_to_world: Optional[_Matrix4] = None,
        intrinsics: Optional[Tuple[float, float, float, float]] = None,
    ) -> FaceResult:
        """`image`: C-contiguous uint8 (height, width). Raises TypeError/ValueError on bad input."""
    def link_status(self) -> Optional[Tuple[str, Optional[str], Optional[str]]]: ...
    def close(self) -> None: ...
    def __enter__(self) -> "FaceTracker": ...
    def __exit__(self, *args: object) -> None: ...

class SourceFrame:
    index: int
    timestamp_us: int
    image: npt.NDArray[np.uint8]
    intrinsics: Tuple[float, float, float, float]
    camera_to_world: npt.NDArray[np.float64]

class FrameSource:
    """Image folder, MP4/H.264 video, .y4m stream or .hfrec recording, read like `holoface track --source`."""

    def __init__(self, path: _Path, fps: float = 30.0, poses: Optional[_Path] = None) -> None: ...
    def __iter__(self) -> Iterator[SourceFrame]: ...
    def __next__(self) -> SourceFrame: ...

def data_dir() -> Path:
    """The user's holoface data folder: $HOLOFACE_HOME, else $XDG_DATA_HOME/holoface, else ~/.local/share/holoface."""

def install_candide(path: _Path) -> Path:
    """Checks that `path` is a CANDIDE-3 .wfm and copies it into data_dir(); returns where it went."""

def read_gray(path: _Path) -> npt.NDArray[np.uint8]:
    """Reads a PNG or JPEG as uint8 grayscale with the decoder `holoface track` uses."""
