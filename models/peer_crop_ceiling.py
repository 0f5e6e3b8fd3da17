"""The crop ceiling (issue 52): how precisely dlib's shipped 68-point predictor reads the very crop a headset sends.

    .venv/bin/python models/peer_crop_ceiling.py --data ../shared/data/faces68/train --split validation

For every face of the split, the crop is made as the headset makes it: a similarity from the face's 51 inner
points onto the DAN mean shape's (the tracker's placement; models/dan/geometry.py, the Python twin of
models/src/crop.rs), 112 x 112, bilinear, then JPEG q75 (the wire's encoding). Rows:
* `full`: dlib on the full photograph from its own detector (peer_dlib.py's detector row);
* `crop`: dlib on the crop, upscaled x4 (bicubic), from its own detector run on the crop;
* `crop-tracker`: the crop placed as a tracker would, off by 5 % in scale and rotation and 2.8 px in shift
  (signs drawn per face, seeded);
* `crop-q95`: as `crop` with JPEG q95.
Where dlib's detector finds no face on a crop, the predictor starts from the box of the DAN mean shape in the
crop (counted in `fallback`). Answers are mapped back to the photograph and scored as `holoface eval` scores:
mean point error over 68 and 49 points divided by the outer-eye-corner distance.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import sys

import numpy as np
from PIL import Image

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "dan"))
import geometry as g  # noqa: E402
from peer_dlib import P49, iou, nme, summary  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
UP = 4


def jpeg(crop: np.ndarray, quality: int) -> np.ndarray:
    buf = io.BytesIO()
    Image.fromarray(crop).save(buf, format="JPEG", quality=quality)
    return np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("L"))


def on_crop(dlib, detector, predictor, crop: np.ndarray, fallback_box) -> tuple[np.ndarray, bool]:
    """dlib's 68 points in crop pixels, and whether its detector found the face."""
    big = np.asarray(Image.fromarray(crop).resize((crop.shape[1] * UP, crop.shape[0] * UP), Image.BICUBIC))
    box = tuple(v * UP for v in fallback_box)
    dets = [(r.left(), r.top(), r.right(), r.bottom()) for r in detector(big, 0)]
    dets = [d for d in dets if iou(d, box) > 0.2]
    found = bool(dets)
    c = max(dets, key=lambda d: iou(d, box)) if found else box
    shape = predictor(big, dlib.rectangle(*(int(round(v)) for v in c)))
    pts = np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64)
    # dlib's pixel centres are integers, as ours: upscaled pixel centre k sits at (k + 0.5) / UP - 0.5.
    return (pts + 0.5) / UP - 0.5, found


def perturb(sim: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The crop placement a tracker makes: scale and rotation off by 5 %, centre off by 2.8 crop pixels."""
    ds = 1.0 + 0.05 * rng.choice([-1.0, 1.0])
    da = 0.05 * rng.choice([-1.0, 1.0])
    ang = rng.uniform(0, 2 * math.pi)
    c = g.CROP / 2.0
    # About the crop centre: rotate and scale, then shift.
    a, b = ds * math.cos(da), ds * math.sin(da)
    tx = c - (a * c - b * c) + 2.8 * math.cos(ang)
    ty = c - (b * c + a * c) + 2.8 * math.sin(ang)
    return g.compose(np.array([a, b, tx, ty]), sim)


def main() -> None:
    import importlib.util

    import dlib

    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or spec.origin is None:
        raise SystemExit("face_recognition_models is not installed (make venv-peer)")
    model = os.path.join(os.path.dirname(spec.origin), "models", "shape_predictor_68_face_landmarks.dat")
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", choices=["validation"], default="validation")
    ap.add_argument("--out", default=os.path.join(REPO, "runs", "crop-ceiling.json"))
    ap.add_argument("--seed", type=int, default=52)
    args = ap.parse_args()

    predictor = dlib.shape_predictor(model)
    detector = dlib.get_frontal_face_detector()
    canon = np.loadtxt(os.path.join(REPO, "models", "assets", "mean_shape_68.txt"), comments="#")
    fallback = (*canon.min(axis=0), *canon.max(axis=0))
    names = g.read_split(os.path.join(REPO, "models", "splits", "val.txt"))
    rng = np.random.default_rng(args.seed)
    rows = {k: {"e68": [], "e49": [], "fallback": 0} for k in ("full", "crop", "crop-tracker", "crop-q95")}
    for n in names:
        img = np.asarray(Image.open(os.path.join(args.data, n + ".jpg")).convert("L"))
        gt = g.read_pts(os.path.join(args.data, n + ".pts"))
        box = (gt[:, 0].min(), gt[:, 1].min(), gt[:, 0].max(), gt[:, 1].max())
        dets = [(r.left(), r.top(), r.right(), r.bottom()) for r in detector(img, 1)]
        dets = [d for d in dets if iou(d, box) > 0.2]
        if dets:
            c = max(dets, key=lambda d: iou(d, box))
            shape = predictor(img, dlib.rectangle(*(int(v) for v in c)))
            pred = np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64)
            rows["full"]["e68"].append(nme(pred, gt, list(range(68))))
            rows["full"]["e49"].append(nme(pred, gt, P49))
        else:
            rows["full"]["e68"].append(float("inf"))
            rows["full"]["e49"].append(float("inf"))
        sim = g.best_fit(gt[17:], canon[17:])
        placed = {"crop": (sim, 75), "crop-tracker": (perturb(sim, rng), 75), "crop-q95": (sim, 95)}
        for key, (s, q) in placed.items():
            crop = jpeg(g.warp_crop(img, s), q)
            pts, found = on_crop(dlib, detector, predictor, crop, fallback)
            pred = g.apply(g.invert(s), pts)
            rows[key]["e68"].append(nme(pred, gt, list(range(68))))
            rows[key]["e49"].append(nme(pred, gt, P49))
            rows[key]["fallback"] += int(not found)
    report = {}
    for key, r in rows.items():
        s68, s49 = summary(r["e68"]), summary(r["e49"])
        # The worst fifth: the mean over the 20 % of faces with the largest NME68 (not eval's yaw-ranked hardest fifth).
        e = np.sort(np.asarray(r["e68"]))
        hard = float(np.mean(e[-max(1, len(e) // 5):]))
        report[key] = {"faces": len(names), "nme68": s68, "nme49": s49, "worst_fifth_nme68": hard,
                       "fallback": r["fallback"]}
        print(f"dlib on {key:<13} faces={len(names)} NME68={100 * s68['mean']:.2f}% NME49={100 * s49['mean']:.2f}% "
              f"fail68={100 * s68['failure_rate']:.2f}% worst-fifth NME68={100 * hard:.2f}% "
              f"no-detection={r['fallback']}")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=2)


if __name__ == "__main__":
    main()
