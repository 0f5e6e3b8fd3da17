"""The second per-frame peer of `holoface stability`: MediaPipe Face Mesh (the legacy `mp.solutions.face_mesh`
solution) on every frame of a video, in video mode with its own tracking, as an app would run it.

    .venv-mediapipe/bin/python models/peer_video_mediapipe.py --video .data/video/examples/media/cap12_edit.webm \
        --out runs/stability/cap12_edit.mediapipe.tsv

mediapipe 0.10.21 requires numpy<2 and protobuf<5, which .venv's pins exclude, so it has its own venv
(`make venv-mediapipe`, models/dan/requirements-peer-mediapipe.txt); the face-mesh model ships inside the wheel.

Frames come from models/peer_video_dlib.py's decoder (ffmpeg `-f rawvideo -pix_fmt gray`, presentation order), so
both peers see the same luma; each gray frame is repeated into the three channels of MediaPipe's RGB input.
`FaceMesh(static_image_mode=False, max_num_faces=1, refine_landmarks=False)` with the default confidences (0.5):
its detector runs until it has a face, then it tracks from the previous frame's landmarks.

The 468-point mesh becomes the 68 iBUG points by `landmark_points_68` of ByteDance's LatentSync (Apache-2.0),
github.com/bytedance/LatentSync latentsync/utils/image_processor.py at bf00e0954b4734900b85bfc41f4dc8a0bdd44cfb,
the table most public mesh-to-68 code uses. Mesh indices name the subject's own sides; the table puts the
subject's right (mesh 33, the right outer eye corner) at iBUG 36, image left, as iBUG does. Its jaw points 0-16
are approximate: the mesh has no jaw contour, only the nearest vertices of its face oval. The 49 inner points
(17-67 less 60 and 64) are what `holoface stability` compares (NME49). x, y are the mesh's normalised
coordinates times the frame width and height.

Output as peer_video_dlib.py: one line per frame, `index` then 136 numbers (x0 y0 x1 y1 ...) in image pixels,
or `index -` when MediaPipe has no face, written to `<out>.tmp` and renamed when complete. The process is pinned
to one core (its graph's threads too; ffmpeg is started before and stays free), and the time of
`face_mesh.process` alone (no decoding) goes to stderr and, with the counts, to `<out>.json`.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from peer_video_dlib import gray_frames, peer_args

MAPPING_SOURCE = ("github.com/bytedance/LatentSync latentsync/utils/image_processor.py "
                  "@bf00e0954b4734900b85bfc41f4dc8a0bdd44cfb landmark_points_68")
MESH_TO_IBUG68 = [
    162, 234, 93, 58, 172, 136, 149, 148, 152, 377, 378, 365, 397, 288, 323, 454, 389,  # 0-16 jaw (approximate)
    71, 63, 105, 66, 107, 336, 296, 334, 293, 301,  # 17-26 brows
    168, 197, 5, 4, 75, 97, 2, 326, 305,  # 27-35 nose
    33, 160, 158, 133, 153, 144, 362, 385, 387, 263, 373, 380,  # 36-47 eyes
    61, 39, 37, 0, 267, 269, 291, 405, 314, 17, 84, 181,  # 48-59 outer lips
    78, 82, 13, 312, 308, 317, 14, 87,  # 60-67 inner lips
]
assert len(MESH_TO_IBUG68) == 68


def main() -> None:
    args = peer_args(__doc__)
    import mediapipe as mp

    tmp = args.out + ".tmp"
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    core = min(os.sched_getaffinity(0))
    mesh = None
    ms: list[float] = []
    n, found = 0, 0
    with open(tmp, "w") as f:
        for gray in gray_frames(args.video, args.max_frames):
            if mesh is None:  # after ffmpeg has started, so only this process and its graph share the core
                os.sched_setaffinity(0, {core})
                mesh = mp.solutions.face_mesh.FaceMesh(static_image_mode=False, max_num_faces=1,
                                                       refine_landmarks=False)
            h, w = gray.shape
            rgb = np.repeat(gray[:, :, None], 3, axis=2)
            t0 = time.perf_counter()
            res = mesh.process(rgb)
            ms.append(1e3 * (time.perf_counter() - t0))
            if not res.multi_face_landmarks:
                f.write(f"{n} -\n")
            else:
                lm = res.multi_face_landmarks[0].landmark
                f.write(f"{n} " + " ".join(f"{lm[i].x * w:.2f} {lm[i].y * h:.2f}" for i in MESH_TO_IBUG68) + "\n")
                found += 1
            n += 1
    if mesh is not None:
        mesh.close()
    os.replace(tmp, args.out)
    t = np.array(ms or [np.nan])
    stats = {"mean": float(t.mean()), "p50": float(np.percentile(t, 50)), "p95": float(np.percentile(t, 95))}
    with open(args.out + ".json", "w") as f:
        json.dump({"video": args.video, "frames": n, "faces": found, "ms_per_frame": stats, "cores": 1,
                   "mediapipe": mp.__version__, "mapping": MAPPING_SOURCE}, f, indent=1)
        f.write("\n")
    print(f"{args.video}: {n} frames, MediaPipe found a face in {found}; face_mesh.process on one core "
          f"{stats['mean']:.2f} ms mean, {stats['p50']:.2f} p50, {stats['p95']:.2f} p95 -> {args.out}",
          file=sys.stderr)

if __name__ == "__main__":
    main()
