"""Half-precision DAN for GPUs: the exported fp32 graph with its weights and arithmetic in float16, the
inputs and outputs unchanged (uint8 pixels in, float32 landmarks and face probability out), so the alignment
server loads it like the fp32 model and says `precision=fp16` in its log and metrics.

    .venv/bin/python models/dan/to_fp16.py --model models/assets/dan.onnx --out .cache/models/dan.fp16.onnx

The conversion is ONNX Runtime's own (`onnxruntime.transformers.float16`, casts kept at the graph's edges).
Before writing, both graphs run on the validation faces (models/splits/val.txt, the training script's
jittered GT-box crops) with ONNX Runtime's CPU provider, and the script refuses to write a model whose
landmarks move more than --max-shift px from the fp32 ones or whose NME (outer eye corners) is worse by
more than --max-nme-increase (relative). It prints one JSON line of what it measured. The CPU runs fp16 graphs
(through its own casts) only to check them; the point is the GPU's tensor cores (deploy/README.md).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import data as D  # noqa: E402
import geometry as g  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


def validation_crops(data: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The validation faces as the training script crops them: uint8 [N, 1, 112, 112] and truth [N, 68, 2]."""
    canon = np.loadtxt(os.path.join(REPO, "models", "assets", "mean_shape_68.txt"), comments="#")
    names = g.read_split(os.path.join(REPO, "models", "splits", "val.txt"))
    rng = np.random.default_rng(seed)
    crops, truth = [], []
    for f in D.load_faces(data, names):
        sim = g.best_fit(D.validation_init(canon, f.pts, rng), canon)
        crops.append(g.warp_crop(f.img, sim))
        truth.append(g.apply(sim, f.pts))
    return np.stack(crops)[:, None], np.stack(truth).astype(np.float32)


def nme_corners(pred: np.ndarray, truth: np.ndarray) -> float:
    err = np.linalg.norm(pred - truth, axis=2).mean(axis=1)
    return float(np.mean([e / g.outer_corner_distance(t) for e, t in zip(err, truth)]))


def run(path: str, crops: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import onnxruntime as ort

    sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    out = [sess.run(None, {"pixels": crops[i : i + 32]}) for i in range(0, len(crops), 32)]
    return np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=os.path.join(REPO, "models", "assets", "dan.onnx"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--data", default=os.path.join(os.environ.get("HOLOFACE_DATA", os.path.join(REPO, "..", "shared", "data")), "faces68", "train"))
    ap.add_argument("--max-shift", type=float, default=0.5, help="largest landmark move allowed, crop pixels")
    ap.add_argument("--max-nme-increase", type=float, default=0.01, help="relative NME increase allowed")
    args = ap.parse_args()

    import onnx
    from onnxruntime.transformers.float16 import convert_float_to_float16

    model = onnx.load(args.model)
    meta = {p.key: p.value for p in model.metadata_props}
    if meta.get("holoface.precision", "fp32") != "fp32":
        raise SystemExit(f"{args.model} is not an fp32 model (holoface.precision = {meta['holoface.precision']})")
    half = convert_float_to_float16(model, keep_io_types=True)
    for p in half.metadata_props:
        if p.key == "holoface.precision":
            break
    else:
        p = half.metadata_props.add()
        p.key = "holoface.precision"
    p.value = "fp16"
    onnx.checker.check_model(half)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    tmp = args.out + ".tmp"
    onnx.save(half, tmp)

    gate(args.model, tmp, args.out, args.data, "fp16", args.max_shift, args.max_nme_increase)


def gate(model: str, tmp: str, out: str, data: str, tag: str, max_shift: float, max_nme_increase: float,
         **extra) -> dict:
    """Runs the fp32 `model` and the converted `tmp` on the validation crops, prints one JSON line of what it
    measured (with `extra`), and moves `tmp` to `out` only if no landmark moved more than `max_shift` px and the
    NME (outer eye corners) worsened by at most `max_nme_increase` (relative); else removes it and fails."""
    crops, truth = validation_crops(data)
    lm32, p32 = run(model, crops)
    lmx, px = run(tmp, crops)
    report = {
        "model": os.path.relpath(model, REPO),
        "out": out,
        "bytes_fp32": os.path.getsize(model),
        f"bytes_{tag}": os.path.getsize(tmp),
        **extra,
        "faces": len(crops),
        "max_landmark_shift_px": float(np.abs(lmx - lm32).max()),
        "mean_landmark_shift_px": float(np.linalg.norm(lmx - lm32, axis=2).mean()),
        "max_face_prob_change": float(np.abs(px - p32).max()),
        "nme68_corners_fp32": nme_corners(lm32, truth),
        f"nme68_corners_{tag}": nme_corners(lmx, truth),
    }
    print(json.dumps(report), flush=True)
    increase = report[f"nme68_corners_{tag}"] / report["nme68_corners_fp32"] - 1.0
    if report["max_landmark_shift_px"] > max_shift or increase > max_nme_increase:
        os.remove(tmp)
        raise SystemExit(f"the {tag} graph moves landmarks by up to {report['max_landmark_shift_px']:.3f} px "
                         f"(NME {increase:+.2%}): not written")
    os.replace(tmp, out)
    return report


if __name__ == "__main__":
    main()
