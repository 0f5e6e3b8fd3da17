"""HoloFace: real-time face tracking for AR headsets.

Per frame: detect (or track from the previous frame, compensating headset motion), align 68 landmarks with
the local KRFWS or a remote DAN alignment server over QUIC (KRFWS answers when the link is down), fit
CANDIDE-3 for the head pose and expression, predict the pose ahead and denoise it.

    import holoface
    tracker = holoface.FaceTracker()
    result = tracker.process(gray_uint8_image, timestamp_us)
    if result.face is not None:
        print(result.face.landmarks.shape, result.face.world_pose[:3, 3])

Model paths default to the same places as the Rust API (the environment variables ORT_DYLIB_PATH,
HOLOFACE_DETECTOR_MODEL, HOLOFACE_KRFWS_MODEL and HOLOFACE_CANDIDE, then the set-up's paths).
"""

from ._holoface import (
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
    read_gray,
)

__all__ = [
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
    "read_gray",
]
