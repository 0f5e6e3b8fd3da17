"""The per-frame peer of `holoface stability`: dlib's shipped 68-point predictor on every frame of a video,
each frame from dlib's own face detector (no tracking, no filtering), as a user of dlib would run it.

    .venv/bin/python models/peer_video_dlib.py --video .data/video/examples/media/cap12_edit.webm \
        --out runs/stability/cap12_edit.dlib.tsv

The video is decoded by ffmpeg (`-f rawvideo -pix_fmt gray`, frames in presentation order, as
`holoface track` reads the same clip through `ffmpeg ... -f yuv4mpegpipe -`). For each frame: dlib's HOG
frontal detector (no upsampling, one 2x upsampling when that finds nothing), the largest detection, the
predictor from that box. One line per frame: `index` then 136 numbers (x0 y0 x1 y1 ...) in image pixels, or
`index -` when dlib found no face. Written to `<out>.tmp` and renamed when complete.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np


def model_path() -> str:
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or spec.origin is None:
        raise SystemExit("face_recognition_models is not installed (make venv-peer)")
    return os.path.join(os.path.dirname(spec.origin), "models", "shape_predictor_68_face_landmarks.dat")


def probe_size(video: str) -> tuple[int, int]:
    out = subprocess.run(
        ["ffprobe", "-v", "error", "-select_streams", "v:0", "-show_entries", "stream=width,height",
         "-of", "json", video],
        check=True, capture_output=True, text=True,
    ).stdout
    s = json.loads(out)["streams"][0]
    w, h = int(s["width"]), int(s["height"])
    if not (0 < w <= 8192 and 0 < h <= 8192):
        raise SystemExit(f"{video}: frame size {w}x{h} outside 1..8192")
    return w, h


def gray_frames(video: str, max_frames: int) -> Iterator[np.ndarray]:
    """The first `max_frames` frames of `video` as (h, w) uint8 luma, decoded by ffmpeg in presentation order."""
    w, h = probe_size(video)
    proc = subprocess.Popen(
        ["ffmpeg", "-v", "error", "-i", video, "-f", "rawvideo", "-pix_fmt", "gray", "-"],
        stdout=subprocess.PIPE,
    )
    assert proc.stdout is not None
    n = 0
    try:
        while n < max_frames:
            buf = proc.stdout.read(w * h)
            if len(buf) < w * h:
                break
            yield np.frombuffer(buf, np.uint8).reshape(h, w)
            n += 1
    finally:
        proc.stdout.close()
        if proc.wait() != 0 and n == 0:
            raise SystemExit(f"ffmpeg could not decode {video}")


def peer_args(doc: str) -> argparse.Namespace:
    """The command line of every per-frame video peer: `--video CLIP --out FILE [--max-frames N]`."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--video", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--max-frames", type=int, default=100_000)
    return ap.parse_args()


def main() -> None:
    args = peer_args(__doc__)
    import dlib

    detector = dlib.get_frontal_face_detector()
    predictor = dlib.shape_predictor(model_path())
    tmp = args.out + ".tmp"
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    t0, n, found = time.time(), 0, 0
    with open(tmp, "w") as f:
        for img in gray_frames(args.video, args.max_frames):
            dets = detector(img, 0)
            if len(dets) == 0:
                dets = detector(img, 1)
            if len(dets) == 0:
                f.write(f"{n} -\n")
            else:
                d = max(dets, key=lambda r: r.width() * r.height())
                s = predictor(img, d)
                pts = " ".join(f"{p.x} {p.y}" for p in s.parts())
                f.write(f"{n} {pts}\n")
                found += 1
            n += 1
    os.replace(tmp, args.out)
    print(f"{args.video}: {n} frames, dlib found a face in {found}, {time.time() - t0:.0f} s -> {args.out}",
          file=sys.stderr)


if __name__ == "__main__":
    main()
