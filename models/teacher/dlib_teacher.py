"""Teacher 1 of the teacher-label pipeline (issue 36): dlib's shipped 68-point predictor on every image of a
folder, on the image and on its mirror image.

    .venv/bin/python models/teacher/dlib_teacher.py --images .data/unlabeled/lfw --out .data/labels/lfw.dlib.tsv
    .venv/bin/python models/teacher/dlib_teacher.py --images ../shared/data/faces68/train \
        --names models/splits/val.txt --out runs/teacher/validation.dlib.tsv

For each image (every `.jpg`/`.png` under `--images`, recursively, or the `--names` listed there): dlib's HOG
frontal face detector (no upsampling first, one 2x upsampling when that finds nothing); the largest detection
over the image centre is the face (the collections are centred crops). The predictor then runs from that box on the grey image and on its mirror image (the mirror's
answer is flipped back and its points renumbered with the iBUG left/right swap), each on the image scaled by
`--scale` (dlib answers whole pixels; predicting on a 2x image halves that rounding). One line per image with a
face: `name x0 y0 x1 y1` then 136 numbers (image) then 136 numbers (mirror), in the image's pixels. Images
without a face are listed in `<out>.missed`. `holoface teacher-labels` combines these answers with our own
remote pipeline's and writes the label file the trainers read.

The output is written to `<out>.tmp` and renamed when complete; an interrupted run resumes from the `.tmp`
file (the names it already holds are skipped).
"""

from __future__ import annotations

import argparse
import importlib.util
import multiprocessing as mp
import os
import sys
import time

import numpy as np
from PIL import Image

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "dan"))
import geometry as g  # noqa: E402

EXTS = (".jpg", ".jpeg", ".png")
_state: dict = {}


def model_path() -> str:
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or spec.origin is None:
        raise SystemExit("face_recognition_models is not installed (make venv-peer)")
    return os.path.join(os.path.dirname(spec.origin), "models", "shape_predictor_68_face_landmarks.dat")


def list_images(root: str) -> list[str]:
    out = []
    for dirpath, dirnames, files in os.walk(root):
        dirnames.sort()
        for f in sorted(files):
            if f.lower().endswith(EXTS):
                out.append(os.path.relpath(os.path.join(dirpath, f), root))
    return out


def _init(scale: int) -> None:
    import dlib

    _state["dlib"] = dlib
    _state["pred"] = dlib.shape_predictor(model_path())
    _state["det"] = dlib.get_frontal_face_detector()
    _state["scale"] = scale


def _predict(img: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    dlib = _state["dlib"]
    s = _state["scale"]
    if s != 1:
        img = np.asarray(Image.fromarray(img).resize((img.shape[1] * s, img.shape[0] * s), Image.BILINEAR))
    # A pixel centre at integer coordinates: scaling by s maps x to s*x + (s-1)/2.
    off = (s - 1) / 2.0
    rect = dlib.rectangle(*(int(round(v * s + off)) for v in box))
    shape = _state["pred"](img, rect)
    pts = np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64)
    return (pts - off) / s


def label_one(args: tuple[str, str]) -> tuple[str, str | None]:
    root, name = args
    try:
        img = np.asarray(Image.open(os.path.join(root, name)).convert("L"))
    except Exception as e:  # a damaged file is reported, not fatal
        return name, f"unreadable: {e}"
    det = _state["det"]
    rects = det(img, 0)
    if len(rects) == 0:
        rects = det(img, 1)
    if len(rects) == 0:
        return name, None
    # The photograph's subject: the largest detection over the image centre (the collections are centred
    # crops; other people in the background are not labelled), else the largest.
    cy, cx = (img.shape[0] - 1) / 2.0, (img.shape[1] - 1) / 2.0
    central = [r for r in rects if r.left() <= cx <= r.right() and r.top() <= cy <= r.bottom()]
    r = max(central or list(rects), key=lambda r: r.width() * r.height())
    box = (r.left(), r.top(), r.right(), r.bottom())
    a = _predict(img, box)
    w = img.shape[1]
    mirrored = np.ascontiguousarray(img[:, ::-1])
    mbox = (w - 1 - box[2], box[1], w - 1 - box[0], box[3])
    m = _predict(mirrored, mbox)
    m[:, 0] = w - 1 - m[:, 0]
    m = m[g.MIRROR_68]
    nums = " ".join(f"{v:.2f}" for v in (*box, *a.reshape(-1), *m.reshape(-1)))
    return name, f"{name}\t{nums}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", required=True, help="folder of face photographs (searched recursively)")
    ap.add_argument("--names", help="only these `<subset>/<stem>` names (a split file); `.jpg` is appended")
    ap.add_argument("--out", required=True)
    ap.add_argument("--scale", type=int, default=2, help="predict on the image scaled by this integer factor")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--limit", type=int, default=0, help="label only the first N images (0 = all)")
    args = ap.parse_args()

    if args.names:
        names = [n + ".jpg" for n in g.read_split(args.names)]
    else:
        names = list_images(args.images)
    if args.limit:
        names = names[: args.limit]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)) or ".", exist_ok=True)
    tmp, missed_path = args.out + ".tmp", args.out + ".missed"
    done: set[str] = set()
    if os.path.exists(tmp):
        with open(tmp, encoding="utf-8") as f:
            done = {line.split("\t", 1)[0] for line in f if line.endswith("\n")}
    missed: list[str] = []
    todo = [(args.images, n) for n in names if n not in done]
    print(f"dlib teacher: {len(names)} images in {args.images}, {len(done)} already labelled, "
          f"{len(todo)} to go (scale {args.scale}, {args.workers} workers)", flush=True)
    t0 = time.time()
    with open(tmp, "a", encoding="utf-8") as out, mp.Pool(args.workers, _init, (args.scale,)) as pool:
        for i, (name, line) in enumerate(pool.imap(label_one, todo, chunksize=16)):
            if line is None or line.startswith("unreadable"):
                missed.append(f"{name}\t{line or 'no face found'}")
            else:
                out.write(line + "\n")
            if (i + 1) % 2000 == 0:
                out.flush()
                rate = (i + 1) / (time.time() - t0)
                print(f"  {i + 1}/{len(todo)} ({rate:.1f}/s)", flush=True)
    with open(missed_path, "w", encoding="utf-8") as f:
        f.writelines(m + "\n" for m in missed)
    os.replace(tmp, args.out)
    print(f"dlib teacher: wrote {args.out} ({len(names) - len(missed)} faces, {len(missed)} without one listed in "
          f"{missed_path}) in {time.time() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
