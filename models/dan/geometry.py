"""Crop geometry shared by DAN training, export and the golden test.

This file is the Python twin of `models/src/geometry.rs` and `models/src/crop.rs`; the two must produce
the same numbers (the golden test `models/tests/golden_crop.rs` compares them). Conventions:

* Points are (x, y) in pixels, 0-based, pixel centres at integer coordinates (the iBUG `.pts` convention
  of `../shared/data/faces68`).
* A similarity is (a, b, tx, ty) and maps p = (x, y) to (a*x - b*y + tx, b*x + a*y + ty).
* The canonical 112x112 crop frame holds the 68-point mean shape scaled so that its larger extent is
  56 px (25 % margin on each side) and translated so that the mean of its points is (56, 56).
* A crop pixel (u, v) samples the image at S^-1(u, v) bilinearly; neighbours outside the image count as
  0 (zero fill); the value is rounded half up and clamped to [0, 255].
"""

from __future__ import annotations

import math
import os

import numpy as np

CROP = 112
MARGIN = 0.25

# iBUG 68-point left/right swap used for mirroring.
MIRROR_68 = np.array(
    list(range(16, -1, -1))
    + list(range(26, 21, -1))
    + list(range(21, 16, -1))
    + [27, 28, 29, 30]
    + [35, 34, 33, 32, 31]
    + [45, 44, 43, 42, 47, 46]
    + [39, 38, 37, 36, 41, 40]
    + [54, 53, 52, 51, 50, 49, 48]
    + [59, 58, 57, 56, 55]
    + [64, 63, 62, 61, 60]
    + [67, 66, 65]
)
assert sorted(MIRROR_68.tolist()) == list(range(68))


def read_pts(path: str) -> np.ndarray:
    """Read a 68-line `x y` file (0-based pixels)."""
    rows = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            rows.append((float(parts[0]), float(parts[1])))
    pts = np.asarray(rows, dtype=np.float64)
    if pts.shape != (68, 2):
        raise ValueError(f"{path}: expected 68 points, found {pts.shape[0]}")
    return pts


def list_samples(root: str) -> list[str]:
    """All `<subset>/<name>` sample ids under a faces68 folder, sorted."""
    out = []
    for sub in sorted(os.listdir(root)):
        d = os.path.join(root, sub)
        if not os.path.isdir(d):
            continue
        for f in sorted(os.listdir(d)):
            if f.endswith(".pts"):
                out.append(f"{sub}/{f[:-4]}")
    return sorted(out)


def read_split(path: str) -> list[str]:
    with open(path, encoding="utf-8") as f:
        return [ln.strip() for ln in f if ln.strip() and not ln.startswith("#")]


def mirror_points(pts: np.ndarray, width: int) -> np.ndarray:
    out = pts[MIRROR_68].copy()
    out[:, 0] = (width - 1) - out[:, 0]
    return out


def best_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity (a, b, tx, ty) mapping src onto dst (DAN's `bestFit`)."""
    ms = src.mean(axis=0)
    md = dst.mean(axis=0)
    s = src - ms
    d = dst - md
    n = float((s * s).sum())
    a = float((s * d).sum()) / n
    b = float((s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0]).sum()) / n
    tx = md[0] - (a * ms[0] - b * ms[1])
    ty = md[1] - (b * ms[0] + a * ms[1])
    return np.array([a, b, tx, ty], dtype=np.float64)


def apply(sim: np.ndarray, pts: np.ndarray) -> np.ndarray:
    a, b, tx, ty = sim
    x = pts[:, 0]
    y = pts[:, 1]
    return np.stack([a * x - b * y + tx, b * x + a * y + ty], axis=1)


def invert(sim: np.ndarray) -> np.ndarray:
    a, b, tx, ty = sim
    n = a * a + b * b
    ia, ib = a / n, -b / n
    return np.array([ia, ib, -(ia * tx - ib * ty), -(ib * tx + ia * ty)], dtype=np.float64)


def compose(s2: np.ndarray, s1: np.ndarray) -> np.ndarray:
    """s2 after s1."""
    a1, b1, x1, y1 = s1
    a2, b2, x2, y2 = s2
    return np.array(
        [a2 * a1 - b2 * b1, a2 * b1 + b2 * a1, a2 * x1 - b2 * y1 + x2, b2 * x1 + a2 * y1 + y2], dtype=np.float64
    )


def _normalise(shape: np.ndarray) -> np.ndarray:
    c = shape - shape.mean(axis=0)
    return c / math.sqrt(float((c * c).sum()))


def _upright(shape: np.ndarray) -> np.ndarray:
    """Rotate about the centroid so that the line from eye centre 36-41 to eye centre 42-47 is along +x."""
    el = shape[36:42].mean(axis=0)
    er = shape[42:48].mean(axis=0)
    ang = math.atan2(er[1] - el[1], er[0] - el[0])
    c, s = math.cos(-ang), math.sin(-ang)
    m = shape.mean(axis=0)
    p = shape - m
    return np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], axis=1) + m


def procrustes_mean(shapes: list[np.ndarray], iters: int = 20) -> np.ndarray:
    """Generalised Procrustes mean (unit norm, centred, eyes level) of shapes and of their mirror images."""
    pool = []
    for s in shapes:
        pool.append(s)
        m = s[MIRROR_68].copy()
        m[:, 0] = -m[:, 0]
        pool.append(m)
    ref = _upright(_normalise(pool[0]))
    for _ in range(iters):
        aligned = np.stack([apply(best_fit(s, ref), s) for s in pool])
        new = _upright(_normalise(aligned.mean(axis=0)))
        delta = float(np.abs(new - ref).max())
        ref = new
        if delta < 1e-12:
            break
    return ref


def canonical_from_mean(mean: np.ndarray) -> np.ndarray:
    """Scale and centre a mean shape into the 112x112 crop frame (DAN's rule: 25 % margin, mean at centre)."""
    ext = mean.max(axis=0) - mean.min(axis=0)
    scale = CROP * (1.0 - 2.0 * MARGIN) / float(ext.max())
    out = mean * scale
    return out - out.mean(axis=0) + CROP / 2.0


def fit_to_box(canonical: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """DAN's `bestFitRect`: no rotation, scale = mean of width and height ratios, extent centre on box centre.

    box = (x0, y0, x1, y1).
    """
    x0, y0, x1, y1 = box
    lo = canonical.min(axis=0)
    hi = canonical.max(axis=0)
    sw, sh = hi - lo
    s = 0.5 * ((x1 - x0) / sw + (y1 - y0) / sh)
    centre = (lo + hi) / 2.0
    return (canonical - centre) * s + np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0])


def warp_crop(img: np.ndarray, crop_from_image: np.ndarray, size: int = CROP) -> np.ndarray:
    """Bilinear, zero-filled crop: pixel (u, v) samples img at crop_from_image^-1 (u, v). Returns uint8."""
    inv = invert(crop_from_image).astype(np.float32)
    a, b, tx, ty = inv
    h, w = img.shape
    v, u = np.mgrid[0:size, 0:size].astype(np.float32)
    sx = a * u - b * v + tx
    sy = b * u + a * v + ty
    x0 = np.floor(sx)
    y0 = np.floor(sy)
    fx = sx - x0
    fy = sy - y0
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    src = img.astype(np.float32)

    def tap(yy, xx):
        ok = (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
        val = np.zeros(xx.shape, dtype=np.float32)
        val[ok] = src[yy[ok], xx[ok]]
        return val

    top = tap(y0, x0) * (1.0 - fx) + tap(y0, x0 + 1) * fx
    bot = tap(y0 + 1, x0) * (1.0 - fx) + tap(y0 + 1, x0 + 1) * fx
    val = top * (1.0 - fy) + bot * fy
    return np.clip(np.floor(val + 0.5), 0, 255).astype(np.uint8)


def eye_centre_distance(pts: np.ndarray) -> float:
    return float(np.linalg.norm(pts[36:42].mean(axis=0) - pts[42:48].mean(axis=0)))


def outer_corner_distance(pts: np.ndarray) -> float:
    return float(np.linalg.norm(pts[36] - pts[45]))
