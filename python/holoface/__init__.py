"""HoloFace: real-time face tracking for AR headsets.

Per frame: detect (or track from the previous frame, compensating headset motion), align 68 landmarks with
the local KRFWS or a remote DAN alignment server over QUIC (KRFWS answers when the link is down), fit
CANDIDE-3 for the head pose and expression, predict the pose ahead and denoise it.

    import holoface
    tracker = holoface.FaceTracker()
    result = tracker.process(gray_uint8_image, timestamp_us)
    if result.face is not None:
        print(result.face.landmarks.shape, result.face.world_pose[:3, 3])

Assets: a TrackerOptions field, else its environment variable (ORT_DYLIB_PATH, HOLOFACE_DETECTOR_MODEL,
HOLOFACE_KRFWS_MODEL, HOLOFACE_CANDIDE), else what the installed package has: ONNX Runtime from the pinned
onnxruntime package, the detector and the KRFWS model from the wheel's package data, and CANDIDE-3 from the
user's data folder (data_dir()), where install_candide(path) puts a copy of the user's candide3.wfm (it is
free for research use and not redistributed with holoface).
"""

from ._holoface import (
    BLENDSHAPE_NAMES,
    AssetError,
    Face,
    FaceResult,
    FaceTracker,
    FrameSource,
    HoloFaceError,
    ProcessingError,
    SourceError,
    SourceFrame,
    TrackerOptions,
    __version__,
    data_dir,
    install_candide,
    read_gray,
)

__all__ = [
    "BLENDSHAPE_NAMES",
    "AssetError",
    "Face",
    "FaceResult",
    "FaceTracker",
    "FrameSource",
    "HoloFaceError",
    "ProcessingError",
    "SourceError",
    "SourceFrame",
    "TrackerOptions",
    "__version__",
    "data_dir",
    "install_candide",
    "read_gray",
]
