"""A reference trainer on our own data (issue 52): dlib's shape-predictor trainer on the crops the server sees.

    .venv/bin/python models/refiner_reference_dlib.py --data ../shared/data/faces68/train --out runs/reference

It answers one question: is the gap between our refinement cascade and dlib's shipped predictor in our trainer
or in our data? dlib's C++ trainer (Kazemi & Sullivan's ensemble of regression trees; Boost licence, the peer
venv's dlib) is trained on exactly our training split (models/splits/val.txt excluded, as every trainer here
does) in crop form: each face (and its mirror) warped into `--placements` 112 x 112 crops placed as a detector
would place them (the mean shape fitted to the face's box, then shifted, rotated and scaled at random; the
spread below), JPEG q75 as on the wire, upscaled x`--up` for dlib's nearest-pixel features. Every crop starts
from the same box, the DAN mean shape's in the crop, as the server's cascade starts from a placed crop.
Validation faces get the same treatment with a fixed seed; errors are scored on the photograph, as `holoface
eval` scores them (NME over 68 and 49 points, outer-eye-corner distance). Options are dlib's, printed in the
report; `--quick` is a smaller run for a first number.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import time

import numpy as np
from PIL import Image

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "dan"))
import data as D  # noqa: E402
import geometry as g  # noqa: E402
from peer_dlib import P49, nme, summary  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def jpeg(crop: np.ndarray, quality: int = 75) -> np.ndarray:
    buf = io.BytesIO()
    Image.fromarray(crop).save(buf, format="JPEG", quality=quality)
    return np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("L"))


def placements(pts: np.ndarray, canon: np.ndarray, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """`n` crop similarities for a face: the mean shape fitted to its box, shifted (4 % of the box), rotated
    (6 degrees) and scaled (5 %), standard deviations."""
    base = g.fit_to_box(canon, D.gt_box(pts))
    out = []
    for _ in range(n):
        init = D.perturb(base, rng, abs(rng.normal(0, 0.04)), rng.normal(0, 6.0), float(np.exp(rng.normal(0, 0.05))))
        out.append(g.best_fit(init, canon))
    return out


def crops(faces, canon, n, up, rng, mirror):
    """(upscaled crops, crop-frame points, similarities, faces) for every placement of every face."""
    imgs, shapes, sims, owners = [], [], [], []
    for f in faces:
        variants = [(f.img, f.pts)]
        if mirror:
            w = f.img.shape[1]
            variants.append((np.ascontiguousarray(f.img[:, ::-1]), g.mirror_points(f.pts, w)))
        for img, pts in variants:
            for s in placements(pts, canon, n, rng):
                c = jpeg(g.warp_crop(img, s))
                big = np.asarray(Image.fromarray(c).resize((c.shape[1] * up, c.shape[0] * up), Image.BILINEAR))
                imgs.append(big)
                shapes.append((g.apply(s, pts) + 0.5) * up - 0.5)
                sims.append(s)
                owners.append(f)
    return imgs, shapes, sims, owners


def main() -> None:
    import dlib

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--out", default=os.path.join(REPO, "runs", "reference"))
    ap.add_argument("--placements", type=int, default=4)
    ap.add_argument("--up", type=int, default=2)
    ap.add_argument("--oversampling", type=int, default=5)
    ap.add_argument("--cascade", type=int, default=10)
    ap.add_argument("--trees", type=int, default=500)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--nu", type=float, default=0.1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="300 faces, 100 trees per stage")
    args = ap.parse_args()

    canon = np.loadtxt(os.path.join(REPO, "models", "assets", "mean_shape_68.txt"), comments="#")
    val = set(g.read_split(os.path.join(REPO, "models", "splits", "val.txt")))
    train_names = [n for n in g.list_samples(args.data) if n not in val]
    if args.quick:
        train_names, args.trees = train_names[:300], 100
    rng = np.random.default_rng(52)
    t0 = time.time()
    imgs, shapes, _, _ = crops(D.load_faces(args.data, train_names), canon, args.placements, args.up, rng, True)
    box = (canon.min(axis=0) + 0.5) * args.up - 0.5, (canon.max(axis=0) + 0.5) * args.up - 0.5
    rect = dlib.rectangle(*(int(round(v)) for v in (*box[0], *box[1])))
    objects = [[dlib.full_object_detection(rect, [dlib.point(int(round(x)), int(round(y))) for x, y in s])]
               for s in shapes]
    opts = dlib.shape_predictor_training_options()
    opts.cascade_depth, opts.num_trees_per_cascade_level, opts.tree_depth = args.cascade, args.trees, args.depth
    opts.nu, opts.oversampling_amount = args.nu, args.oversampling
    opts.num_threads, opts.be_verbose = args.threads, True
    print(f"{len(train_names)} training faces, {len(imgs)} crops; {opts}", flush=True)
    os.makedirs(args.out, exist_ok=True)
    model = os.path.join(args.out, "dlib-on-our-crops.dat")
    t1 = time.time()
    predictor = dlib.train_shape_predictor(imgs, objects, opts)
    train_s = time.time() - t1
    predictor.save(model)
    del imgs, objects

    vrng = np.random.default_rng(7)
    vnames = sorted(val)
    vfaces = D.load_faces(args.data, vnames)
    vimgs, _, vsims, vowners = crops(vfaces, canon, 3, args.up, vrng, False)
    e68, e49, t_pred = [], [], 0.0
    for img, s, f in zip(vimgs, vsims, vowners):
        t2 = time.perf_counter()
        shape = predictor(img, rect)
        t_pred += time.perf_counter() - t2
        pts = (np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64) + 0.5) / args.up - 0.5
        pred = g.apply(g.invert(s), pts)
        e68.append(nme(pred, f.pts, list(range(68))))
        e49.append(nme(pred, f.pts, P49))
    s68, s49 = summary(e68), summary(e49)
    e = np.sort(np.asarray(e68))
    hard = float(np.mean(e[-max(1, len(e) // 5):]))
    report = {"training_faces": len(train_names), "training_crops": len(shapes), "validation_crops": len(vimgs),
              "options": str(opts), "train_s": train_s, "prepare_s": t1 - t0, "nme68": s68, "nme49": s49,
              "worst_fifth_nme68": hard, "ms_per_crop": 1e3 * t_pred / len(vimgs),
              "model_bytes": os.path.getsize(model)}
    print(f"dlib trained on our crops: NME68={100 * s68['mean']:.2f}% NME49={100 * s49['mean']:.2f}% "
          f"worst-fifth={100 * hard:.2f}% {report['ms_per_crop']:.2f} ms/crop, trained in {train_s:.0f} s, "
          f"{report['model_bytes'] / 1e6:.1f} MB", flush=True)
    with open(os.path.join(args.out, "report.json"), "w", encoding="utf-8") as fh:
        json.dump(report, fh, indent=2)


if __name__ == "__main__":
    main()
