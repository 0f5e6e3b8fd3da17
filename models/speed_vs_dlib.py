"""KRFWS vs dlib's 68-point shape predictor: time per face on the same faces, one thread, in one run.

    .venv/bin/python models/speed_vs_dlib.py --data ../shared/data/faces68/train     (make speed-vs-dlib)

Both start from the same ground-truth box of each of the 101 validation faces and run their full predictor
on the full grey frame: KRFWS = mean shape fitted to the box, 3 cascade stages and the failure score
(`holoface eval --init gt-box --aligner krfws --krfws-starts 1`, a release build); dlib =
`shape_predictor(img, rect)` (PyPI dlib-bin, the C++ predictor; Python overhead per call is about a
microsecond). Rounds alternate (ours, dlib, ours, dlib, ...) so drift of a shared machine hits both; each
round times `--repeat` passes over all faces. Reports the median round of each and their ratio.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np
from PIL import Image

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "dan"))
import geometry as g  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=10, help="passes over the faces per round")
    ap.add_argument("--holoface", default=os.path.join(REPO, "target", "release", "holoface"))
    ap.add_argument("--out", default=os.path.join(REPO, "runs", "speed-vs-dlib.json"))
    args = ap.parse_args()

    import dlib

    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or spec.origin is None:
        raise SystemExit("face_recognition_models is not installed (make venv-peer)")
    predictor = dlib.shape_predictor(
        os.path.join(os.path.dirname(spec.origin), "models", "shape_predictor_68_face_landmarks.dat"))
    names = g.read_split(os.path.join(REPO, "models", "splits", "val.txt"))
    faces = []
    for n in names:
        img = np.asarray(Image.open(os.path.join(args.data, n + ".jpg")).convert("L"))
        gt = g.read_pts(os.path.join(args.data, n + ".pts"))
        rect = dlib.rectangle(int(round(gt[:, 0].min())), int(round(gt[:, 1].min())),
                              int(round(gt[:, 0].max())), int(round(gt[:, 1].max())))
        faces.append((img, rect))

    def dlib_round() -> float:
        for img, rect in faces[:10]:  # warm-up
            predictor(img, rect)
        t0 = time.perf_counter()
        for _ in range(args.repeat):
            for img, rect in faces:
                predictor(img, rect)
        return 1e3 * (time.perf_counter() - t0) / (args.repeat * len(faces))

    tmp = os.path.join(REPO, "target", "speed-vs-dlib.json")

    def ours_round() -> tuple[float, float]:
        cmd = [args.holoface, "eval", "--data", args.data, "--split", "validation", "--init", "gt-box",
               "--aligner", "krfws", "--krfws-starts", "1", "--repeat", str(args.repeat), "--out", tmp,
               "--plot", tmp + ".png", "--log", "warn"]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        with open(tmp, encoding="utf-8") as f:
            rep = json.load(f)[0]
        return rep["ms_per_face"], rep["nme49"]["mean"]

    ours, theirs, nme = [], [], None
    for r in range(args.rounds):
        ms, nme = ours_round()
        ours.append(ms)
        theirs.append(dlib_round())
        print(f"round {r + 1}: KRFWS {ours[-1]:.3f} ms/face, dlib {theirs[-1]:.3f} ms/face", flush=True)
    a, b = statistics.median(ours), statistics.median(theirs)
    report = {"faces": len(faces), "rounds": args.rounds, "passes_per_round": args.repeat,
              "krfws_ms_per_face": a, "dlib_ms_per_face": b, "krfws_faces_per_s": 1e3 / a,
              "dlib_faces_per_s": 1e3 / b, "dlib_over_krfws": b / a, "krfws_nme49_gt_box_single_start": nme,
              "rounds_ms": {"krfws": ours, "dlib": theirs}}
    print(f"median: KRFWS {a:.3f} ms/face ({1e3 / a:.0f} faces/s), dlib {b:.3f} ms/face ({1e3 / b:.0f} faces/s); "
          f"KRFWS is {b / a:.2f}x dlib's speed")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=2)


if __name__ == "__main__":
    main()
