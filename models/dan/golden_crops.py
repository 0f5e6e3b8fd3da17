"""Write DAN crops of validation faces for the Rust golden test (models/tests/golden.rs).

    .venv/bin/python models/dan/golden_crops.py --data ../shared/data/faces68/train --out target/golden/dan_crops.bin

Layout (little-endian): u32 count, then per crop: u16 name length, name (UTF-8), u32 width, u32 height,
width*height u8 source pixels as PIL decodes them, 4 x f64 similarity crop_from_image (a, b, tx, ty),
112*112 u8 crop pixels. The source pixels let the test tell the warp apart from JPEG decoder differences.
"""

from __future__ import annotations

import argparse
import os
import struct
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import data as D  # noqa: E402
import geometry as g  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--count", type=int, default=24)
    args = ap.parse_args()
    canon = np.loadtxt(os.path.join(REPO, "models", "assets", "mean_shape_68.txt"), comments="#")
    names = g.read_split(os.path.join(REPO, "models", "splits", "val.txt"))[: args.count]
    faces = D.load_faces(args.data, names)
    rng = np.random.default_rng(7)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "wb") as f:
        f.write(struct.pack("<I", len(faces)))
        for face in faces:
            # Large rotations and scales exercise the sampler, not only near-identity warps.
            init = D.perturb(g.fit_to_box(canon, D.gt_box(face.pts)), rng, rng.uniform(0, 0.3),
                             rng.normal(0, 25), rng.uniform(0.6, 1.5))
            sim = g.best_fit(init, canon)
            crop = g.warp_crop(face.img, sim)
            name = face.name.encode()
            h, w = face.img.shape
            f.write(struct.pack("<H", len(name)) + name + struct.pack("<II", w, h) + face.img.tobytes())
            f.write(struct.pack("<4d", *sim) + crop.tobytes())


if __name__ == "__main__":
    main()
