"""Training data for DAN: on-the-fly perturbed crops, face/no-face negatives, validation crops."""

from __future__ import annotations

import math
import os

import numpy as np
from PIL import Image, ImageFilter

import geometry as g

# Perturbation of the box-fitted initial shape (algorithms.md 1.7): sigma of translation as a fraction of
# the shape's width/height, of rotation in degrees, of scale. Positives are clipped so they stay clearly
# apart from the grossly misaligned negatives below.
SIGMA_T, SIGMA_R, SIGMA_S = 0.2, 20.0, 0.25
POS_MAX_T, POS_MAX_R, POS_SCALE = 0.45, 50.0, (0.6, 1.5)
# Small perturbations, the tracking regime: the previous frame's landmarks are close to the truth.
TRACK_FRACTION, TRACK_SIGMA = 0.3, 0.25  # fraction of positives, multiplier of the sigmas above


class Face:
    __slots__ = ("name", "img", "pts")

    def __init__(self, name: str, img: np.ndarray, pts: np.ndarray):
        self.name, self.img, self.pts = name, img, pts


def load_faces(root: str, names: list[str]) -> list[Face]:
    faces = []
    for n in names:
        img = np.asarray(Image.open(os.path.join(root, n + ".jpg")).convert("L"), dtype=np.uint8)
        faces.append(Face(n, img, g.read_pts(os.path.join(root, n + ".pts"))))
    return faces


def load_teacher_faces(path: str, limit: int = 0) -> list[Face]:
    """The faces of a teacher-label file (`holoface teacher-labels`, format in tools/src/labels.rs): magic
    `HFLABEL1`, u32 header length + JSON header (its `images` folder), u32 count, per record u16 name length +
    name + 136 f32 + 1 f32, CRC-32 at the end. At most `limit` faces (0 = all), evenly spaced over the file."""
    import json
    import struct
    import zlib

    with open(path, "rb") as f:
        data = f.read()
    if data[:8] != b"HFLABEL1" or len(data) < 20:
        raise SystemExit(f"{path}: not a holoface label file")
    if zlib.crc32(data[:-4]) != struct.unpack("<I", data[-4:])[0]:
        raise SystemExit(f"{path}: checksum mismatch (damaged; make teacher-labels again)")
    (hlen,) = struct.unpack_from("<I", data, 8)
    header = json.loads(data[12 : 12 + hlen])
    at = 12 + hlen
    (count,) = struct.unpack_from("<I", data, at)
    at += 4
    records = []
    for _ in range(count):
        (n,) = struct.unpack_from("<H", data, at)
        name = data[at + 2 : at + 2 + n].decode()
        at += 2 + n
        pts = np.frombuffer(data, np.float32, 136, at).reshape(68, 2).astype(np.float64)
        at += 137 * 4
        records.append((name, pts))
    take = min(limit, len(records)) if limit else len(records)
    faces = []
    for k in range(take):
        name, pts = records[k * len(records) // max(take, 1)]
        img = np.asarray(Image.open(os.path.join(header["images"], name)).convert("L"), dtype=np.uint8)
        faces.append(Face(f"{header['collection']}/{name}", img, pts))
    return faces


def gt_box(pts: np.ndarray) -> tuple[float, float, float, float]:
    lo = pts.min(axis=0)
    hi = pts.max(axis=0)
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def perturb(shape: np.ndarray, rng: np.random.Generator, dt: float, dr_deg: float, ds: float) -> np.ndarray:
    """Translate by dt*(width,height) along a random direction, rotate by dr about the centroid, scale by ds."""
    lo, hi = shape.min(axis=0), shape.max(axis=0)
    wh = hi - lo
    ang = rng.uniform(0, 2 * math.pi)
    off = np.array([math.cos(ang) * dt * wh[0], math.sin(ang) * dt * wh[1]])
    c = shape.mean(axis=0)
    r = math.radians(dr_deg)
    cr, sr = math.cos(r), math.sin(r)
    p = shape - c
    p = np.stack([cr * p[:, 0] - sr * p[:, 1], sr * p[:, 0] + cr * p[:, 1]], axis=1) * ds
    return p + c + off


def positive_init(canon: np.ndarray, pts: np.ndarray, rng: np.random.Generator, spread: float = 1.0) -> np.ndarray:
    """`spread` multiplies the sigmas (the clip limits stay): below 1 the net trains closer to the
    face detector's and the tracker's initialisation errors."""
    init = g.fit_to_box(canon, gt_box(pts))
    k = (TRACK_SIGMA if rng.random() < TRACK_FRACTION else 1.0) * spread
    lo, hi = init.min(axis=0), init.max(axis=0)
    wh = hi - lo
    t = np.clip(rng.normal(0, SIGMA_T * k, 2), -POS_MAX_T, POS_MAX_T) * wh
    r = float(np.clip(rng.normal(0, SIGMA_R * k), -POS_MAX_R, POS_MAX_R))
    s = float(np.clip(rng.normal(1, SIGMA_S * k), *POS_SCALE))
    c = init.mean(axis=0)
    rr = math.radians(r)
    cr, sr = math.cos(rr), math.sin(rr)
    p = init - c
    p = np.stack([cr * p[:, 0] - sr * p[:, 1], sr * p[:, 0] + cr * p[:, 1]], axis=1) * s
    return p + c + t


# Near-miss negatives (harder than the gross ones below, still clearly apart from the positives' clip above):
# translation as a fraction of the shape's width/height, scale factors, rotation in degrees.
NEAR_T, NEAR_S_UP, NEAR_S_DOWN, NEAR_R = (0.65, 1.0), (1.9, 2.6), (0.35, 0.5), (80.0, 110.0)


def near_miss_init(canon: np.ndarray, pts: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A face at a wrong offset, scale or rotation just outside what the aligner is trained to recover."""
    base = g.fit_to_box(canon, gt_box(pts))
    kind = rng.random()
    if kind < 0.5:
        return perturb(base, rng, rng.uniform(*NEAR_T), rng.normal(0, 10), rng.uniform(0.8, 1.25))
    if kind < 0.8:
        ds = rng.uniform(*NEAR_S_UP) if rng.random() < 0.5 else rng.uniform(*NEAR_S_DOWN)
        return perturb(base, rng, rng.uniform(0, 0.25), rng.normal(0, 10), ds)
    r = rng.uniform(*NEAR_R) * (1 if rng.random() < 0.5 else -1)
    return perturb(base, rng, rng.uniform(0, 0.25), r, rng.uniform(0.8, 1.25))


def negative_init(canon: np.ndarray, img: np.ndarray, pts: np.ndarray, rng: np.random.Generator,
                  hard: float = 0.0) -> np.ndarray:
    """An initial shape whose crop does not hold a trackable face: background or gross misalignment, or with
    probability `hard` a near miss (`near_miss_init`)."""
    if hard > 0 and rng.random() < hard:
        return near_miss_init(canon, pts, rng)
    base = g.fit_to_box(canon, gt_box(pts))
    kind = rng.random()
    if kind < 0.45:
        # Background: a face-sized window away from the face (the images carry 2.2x context).
        h, w = img.shape
        x0, y0, x1, y1 = gt_box(pts)
        fw, fh = x1 - x0, y1 - y0
        for _ in range(20):
            s = rng.uniform(0.4, 1.2)
            cx, cy = rng.uniform(0, w), rng.uniform(0, h)
            bw, bh = fw * s, fh * s
            ix = max(0.0, min(x1, cx + bw / 2) - max(x0, cx - bw / 2))
            iy = max(0.0, min(y1, cy + bh / 2) - max(y0, cy - bh / 2))
            if ix * iy < 0.1 * bw * bh:
                return g.fit_to_box(canon, (cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2))
        return perturb(base, rng, 1.2, 0.0, 1.0)
    if kind < 0.7:
        return perturb(base, rng, rng.uniform(0.8, 1.3), rng.normal(0, 10), rng.uniform(0.8, 1.2))
    if kind < 0.85:
        ds = rng.uniform(2.6, 4.0) if rng.random() < 0.5 else rng.uniform(0.15, 0.35)
        return perturb(base, rng, rng.uniform(0, 0.2), 0.0, ds)
    return perturb(base, rng, rng.uniform(0, 0.2), rng.uniform(110, 250), rng.uniform(0.8, 1.2))


def photometric(crop: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Blur, contrast/brightness and a little noise (applied to both positives and negatives)."""
    if rng.random() < 0.3:
        crop = np.asarray(Image.fromarray(crop).filter(ImageFilter.GaussianBlur(rng.uniform(0.4, 1.6))))
    x = crop.astype(np.float32)
    x = (x - 128.0) * rng.uniform(0.7, 1.3) + 128.0 + rng.uniform(-25, 25)
    if rng.random() < 0.3:
        x += rng.normal(0, rng.uniform(1, 5), x.shape).astype(np.float32)
    return np.clip(np.floor(x + 0.5), 0, 255).astype(np.uint8)


def occlude(crop: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Paint one rectangle (side 15-45 % of the crop) of flat grey or noise over the crop: hands, microphones,
    hair and glasses hide parts of real faces. The landmark targets stay, so the net learns to infer them."""
    c = crop.copy()
    w, h = (rng.uniform(0.15, 0.45, 2) * g.CROP).astype(int)
    x0 = int(rng.uniform(0, g.CROP - w))
    y0 = int(rng.uniform(0, g.CROP - h))
    if rng.random() < 0.5:
        c[y0:y0 + h, x0:x0 + w] = rng.integers(0, 256)
    else:
        c[y0:y0 + h, x0:x0 + w] = rng.integers(0, 256, (h, w))
    return c


def procedural_negative(rng: np.random.Generator) -> np.ndarray:
    """Flat, gradient or noise texture: no face at all."""
    v, u = np.mgrid[0:g.CROP, 0:g.CROP].astype(np.float32)
    ang = rng.uniform(0, 2 * math.pi)
    x = rng.uniform(0, 255) + rng.uniform(-1.5, 1.5) * (math.cos(ang) * u + math.sin(ang) * v)
    x += rng.normal(0, rng.uniform(0, 40), x.shape)
    return np.clip(x, 0, 255).astype(np.uint8)


def make_sample(face: Face, canon: np.ndarray, rng: np.random.Generator, positive: bool,
                occlusion: float = 0.0, hard: float = 0.0, spread: float = 1.0):
    """Returns (crop uint8 112x112, landmarks in crop px (68x2), is_face).

    `occlusion`: probability of an occluding rectangle (`occlude`); `hard`: fraction of negatives that are
    near misses (`near_miss_init`); `spread`: multiplier of the positives' perturbation sigmas."""
    img, pts = face.img, face.pts
    if rng.random() < 0.5:
        img = img[:, ::-1]
        pts = g.mirror_points(pts, img.shape[1])
    if positive:
        init = positive_init(canon, pts, rng, spread)
    else:
        if rng.random() < 0.1:
            return photometric(procedural_negative(rng), rng), np.zeros((68, 2)), 0
        init = negative_init(canon, img, pts, rng, hard)
    sim = g.best_fit(init, canon)
    crop = g.warp_crop(np.ascontiguousarray(img), sim)
    if occlusion > 0 and rng.random() < occlusion:
        crop = occlude(crop, rng)
    return photometric(crop, rng), g.apply(sim, pts), int(positive)


def validation_init(canon: np.ndarray, pts: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Deterministic detector-like init for validation: GT box fit, jittered like a face detector box."""
    init = g.fit_to_box(canon, gt_box(pts))
    return perturb(init, rng, abs(rng.normal(0, 0.05)), rng.normal(0, 3.0), rng.normal(1.0, 0.05))
