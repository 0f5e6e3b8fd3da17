"""dlib's 68-point shape predictor on the same faces, for the side-by-side table in BENCHMARKS.md.

    .venv/bin/python models/dan/peer_dlib.py --data ../shared/data/faces68/train --split validation

Two initialisations, matching `holoface eval --init`:
* `detector`: dlib's own HOG frontal face detector (its full single-image pipeline); a face counts as found
  when a detection overlaps the annotated face's box (IoU > 0.2), else it is a failure;
* `gt-box`: the predictor started from the ground-truth landmarks' bounding box (dlib was trained on its
  detector's boxes, which are larger and lower, so this row favours our aligners; it is shown for reference).
Errors use the same definitions as `holoface eval`: mean point error over 68 or the 49-point protocol,
divided by the outer-eye-corner distance (points 36 and 45); AUC@0.08 and failure rate, missing answers
counted as failures. Also prints the predictor's time per face.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
from PIL import Image

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import geometry as g  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
P49 = [i for i in range(17, 68) if i not in (60, 64)]


def nme(pred, gt, idx):
    return float(np.linalg.norm(pred[idx] - gt[idx], axis=1).mean() / np.linalg.norm(gt[36] - gt[45]))


def summary(errors):
    e = np.asarray(errors, dtype=np.float64)
    finite = np.sort(e[np.isfinite(e)])
    total = len(e)
    xs = np.linspace(0, 0.08, 801)
    ced = np.searchsorted(finite, xs, side="right") / total
    auc = float(np.trapezoid(ced, xs) / 0.08)
    return {"mean": float(finite.mean()) if len(finite) else float("nan"), "auc": auc,
            "failure_rate": float(1.0 - np.searchsorted(finite, 0.08, side="right") / total)}


def iou(a, b):
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def main() -> None:
    import importlib.util

    import dlib

    # face_recognition_models imports pkg_resources, which current setuptools no longer ships; the model file
    # is found through the package's location instead of importing it.
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or spec.origin is None:
        raise SystemExit("face_recognition_models is not installed (make venv-peer)")
    model_path = os.path.join(os.path.dirname(spec.origin), "models", "shape_predictor_68_face_landmarks.dat")

    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", choices=["validation", "all"], default="validation")
    ap.add_argument("--out", default=os.path.join(REPO, "runs", "dlib.json"))
    args = ap.parse_args()

    predictor = dlib.shape_predictor(model_path)
    detector = dlib.get_frontal_face_detector()
    names = g.read_split(os.path.join(REPO, "models", "splits", "val.txt")) if args.split == "validation" \
        else g.list_samples(args.data)
    report = {}
    for init in ("detector", "gt-box"):
        e68, e49, t_pred, found = [], [], 0.0, 0
        for n in names:
            img = np.asarray(Image.open(os.path.join(args.data, n + ".jpg")).convert("L"))
            gt = g.read_pts(os.path.join(args.data, n + ".pts"))
            box = (gt[:, 0].min(), gt[:, 1].min(), gt[:, 0].max(), gt[:, 1].max())
            if init == "detector":
                cands = [(r.left(), r.top(), r.right(), r.bottom()) for r in detector(img, 1)]
                cands = [c for c in cands if iou(c, box) > 0.2]
                if not cands:
                    e68.append(float("inf"))
                    e49.append(float("inf"))
                    continue
                c = max(cands, key=lambda c: iou(c, box))
                rect = dlib.rectangle(int(c[0]), int(c[1]), int(c[2]), int(c[3]))
            else:
                rect = dlib.rectangle(int(round(box[0])), int(round(box[1])), int(round(box[2])), int(round(box[3])))
            t0 = time.perf_counter()
            shape = predictor(img, rect)
            t_pred += time.perf_counter() - t0
            found += 1
            pred = np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64)
            e68.append(nme(pred, gt, list(range(68))))
            e49.append(nme(pred, gt, P49))
        s68, s49 = summary(e68), summary(e49)
        report[init] = {"images": len(names), "found": found, "nme68": s68, "nme49": s49,
                        "ms_per_face": 1e3 * t_pred / max(found, 1)}
        print(f"dlib   init={init:<8} images={len(names)} found={found} NME49={100*s49['mean']:.2f}% "
              f"AUC49={100*s49['auc']:.2f} fail49={100*s49['failure_rate']:.2f}% NME68={100*s68['mean']:.2f}% "
              f"AUC68={100*s68['auc']:.2f} fail68={100*s68['failure_rate']:.2f}% "
              f"predictor {1e3*t_pred/max(found,1):.2f} ms/face")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=2)


if __name__ == "__main__":
    main()
