"""Track the faces of an image folder, MP4/H.264 video, YUV4MPEG2 (.y4m) stream or .hfrec recording; print one line per frame and
optionally draw the landmarks.

    python python/examples/track.py SOURCE [--draw OUT_DIR] [--server IP:PORT --fingerprint HEX --token T]
"""

import argparse
from pathlib import Path

from PIL import Image, ImageDraw

import holoface


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source", type=Path, help="image folder, .mp4, .y4m or .hfrec")
    ap.add_argument("--fps", type=float, default=30.0, help="frame rate of an image folder")
    ap.add_argument("--draw", type=Path, help="write each frame with its landmarks as PNG here")
    ap.add_argument("--server", help="alignment server ip:port (remote DAN, KRFWS as fallback)")
    ap.add_argument("--fingerprint", help="the server certificate's SHA-256 (printed at its start)")
    ap.add_argument("--token", default="")
    args = ap.parse_args()

    options = holoface.TrackerOptions(server=args.server, fingerprint=args.fingerprint, token=args.token)
    if args.draw:
        args.draw.mkdir(parents=True, exist_ok=True)
    with holoface.FaceTracker(options) as tracker:
        for frame in holoface.FrameSource(args.source, fps=args.fps):
            r = tracker.process(frame.image, frame.timestamp_us, frame.camera_to_world, frame.intrinsics)
            if r.face is None:
                print(f"frame {frame.index}: no face ({r.no_face_reason})")
            else:
                x, y, z = r.face.world_pose[:3, 3]
                print(f"frame {frame.index}: face by {r.face.answered_by}, head at ({x:+.3f}, {y:+.3f}, {z:+.3f}) m"
                      f", smile={r.face.smile}, mouth_open={r.face.mouth_open}")
            if args.draw:
                img = Image.fromarray(frame.image).convert("RGB")
                draw = ImageDraw.Draw(img)
                for face in r.faces:
                    for px, py in face.landmarks:
                        draw.ellipse((px - 1.5, py - 1.5, px + 1.5, py + 1.5), fill=(0, 255, 0))
                img.save(args.draw / f"frame_{frame.index:06d}.png")


if __name__ == "__main__":
    main()
