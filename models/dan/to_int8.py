"""8-bit DAN for CPUs with VNNI: the exported fp32 graph quantised by ONNX Runtime's own static quantiser, inputs
and outputs unchanged (uint8 pixels in, float32 landmarks and face probability out), so the alignment server
loads it like the fp32 model and says `precision=int8` in its log, metrics and welcome.

    .venv/bin/python models/dan/to_int8.py --model models/assets/dan.onnx --out models/assets/dan.int8.onnx

Recipe (ONNX Runtime's quantisation guide for CNNs on x86: static, QDQ, S8S8):
  1. `quant_pre_process` with shape inference only, no graph optimisation. ORT's optimisation would fold the
     BatchNormalization after the first fully connected layer into it as a Gemm, which ORT then runs in float
     with its 3.2 M int8 weights dequantised on every call: 6.2 of 10.9 ms per crop at batch 1 (profiled), the
     reason an untuned quantisation gained 1.2x at batch 1 and 2.5x at batch 8. Unfolded, the layer runs as
     QLinearMatMul (0.09 ms) and the BatchNormalization in float on 256 values.
  2. Calibration on crops of the *training* split only (faces68/train minus models/splits/val.txt), cut as the
     training script cuts validation crops (ground-truth box jittered like a detector's) and sent through a JPEG
     q75 round trip, as the server receives them; --calib faces evenly spaced over the sorted names, fixed seed,
     MinMax ranges (percentile and entropy calibration measured the same to 0.0005 NME points).
  3. `quantize_static`: QDQ format, int8 activations (asymmetric, so the Relus fold into the quantised
     convolutions) and int8 weights (symmetric, per output channel), no reduced range (VNNI does not saturate).
     The landmark head (HEAD below) stays in float.
  4. The gate: both graphs run on the validation crops (as `to_fp16.py` does) and the model is written only if no
     landmark moves more than --max-shift px and the NME (outer eye corners) worsens by at most
     --max-nme-increase (relative). One JSON line reports what was measured.
`--bench` then times both graphs side by side (batch 1 and 8, one and two intra-op threads, alternating rounds).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import data as D  # noqa: E402
import geometry as g  # noqa: E402
from to_fp16 import REPO, gate  # noqa: E402


# The landmark head stays in float: its output is the landmarks themselves, and an 8-bit output over the crop's
# 112 px moves them by up to half a pixel (mean 0.20 px and +0.06 NME points on validation when quantised,
# 0.05 px and +0.002 left in float); it is a 256 x 136 product, a few microseconds.
HEAD = ["/net/out/Gemm", "/net/Reshape", "/net/Add"]


def training_crops(data: str, count: int, seed: int) -> np.ndarray:
    """`count` training-split faces (evenly spaced over the sorted list), cropped as for validation and passed
    through JPEG q75 like a headset's crop: uint8 [count, 1, 112, 112]."""
    from PIL import Image

    canon = np.loadtxt(os.path.join(REPO, "models", "assets", "mean_shape_68.txt"), comments="#")
    val = set(g.read_split(os.path.join(REPO, "models", "splits", "val.txt")))
    names = [n for n in g.list_samples(data) if n not in val]
    if count < len(names):
        names = [names[int(i * len(names) / count)] for i in range(count)]
    rng = np.random.default_rng(seed)
    crops = []
    for f in D.load_faces(data, names):
        crop = g.warp_crop(f.img, g.best_fit(D.validation_init(canon, f.pts, rng), canon))
        buf = io.BytesIO()
        Image.fromarray(crop).save(buf, format="JPEG", quality=75)
        crops.append(np.asarray(Image.open(buf).convert("L"), dtype=np.uint8))
    return np.stack(crops)[:, None]


def quantise(model: str, out: str, crops: np.ndarray, exclude: list[str], per_channel: bool = True,
             skip_optimization: bool = False, method: str = "minmax") -> None:
    import onnx
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.batches = iter([{"pixels": crops[i : i + 32]} for i in range(0, len(crops), 32)])

        def get_next(self):
            return next(self.batches, None)

    with tempfile.TemporaryDirectory() as tmp:
        pre = os.path.join(tmp, "pre.onnx")
        quant_pre_process(model, pre, skip_optimization=skip_optimization, skip_symbolic_shape=True)
        quantize_static(
            pre,
            out,
            Reader(),
            quant_format=QuantFormat.QDQ,
            per_channel=per_channel,
            reduce_range=False,
            activation_type=QuantType.QInt8,
            weight_type=QuantType.QInt8,
            calibrate_method={"minmax": CalibrationMethod.MinMax, "entropy": CalibrationMethod.Entropy,
                              "percentile": CalibrationMethod.Percentile}[method],
            nodes_to_exclude=exclude or None,
            extra_options={"ActivationSymmetric": False, "WeightSymmetric": True},
        )
    q = onnx.load(out)
    src = onnx.load(model)
    meta = {p.key: p.value for p in src.metadata_props}
    if meta.get("holoface.precision", "fp32") != "fp32":
        raise SystemExit(f"{model} is not an fp32 model (holoface.precision = {meta['holoface.precision']})")
    meta["holoface.precision"] = "int8"
    import onnxruntime

    meta["holoface.quantization"] = json.dumps({
        "tool": f"onnxruntime.quantization {onnxruntime.__version__}", "format": "QDQ", "activations": "int8 asymmetric",
        "weights": "int8 symmetric per channel" if per_channel else "int8 symmetric per tensor",
        "calibration": f"{method}, {len(crops)} training-split faces (faces68/train minus models/splits/val.txt), "
                       "JPEG q75", "float": exclude, "graph_optimisation_first": not skip_optimization,
    })
    del q.metadata_props[:]
    for k, v in meta.items():
        p = q.metadata_props.add()
        p.key, p.value = k, v
    onnx.checker.check_model(q)
    onnx.save(q, out)


def bench(models: list[str], seconds: float = 2.0) -> list[dict]:
    """Images per second of each model, batch 1 and 8, 1 and 2 intra-op threads, no spinning, alternating rounds
    (median of 3); the machine's load moves both alike."""
    import onnxruntime as ort

    rows = []
    rng = np.random.default_rng(0)
    for threads in (1, 2):
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        sess = {m: ort.InferenceSession(m, so, providers=["CPUExecutionProvider"]) for m in models}
        for b in (1, 8):
            x = rng.integers(0, 256, (b, 1, 112, 112), dtype=np.uint8)
            res: dict[str, list[float]] = {m: [] for m in sess}
            for s in sess.values():
                s.run(None, {"pixels": x})
            for _ in range(3):
                for m, s in sess.items():
                    n, t0 = 0, time.perf_counter()
                    while time.perf_counter() - t0 < seconds / 3:
                        s.run(None, {"pixels": x})
                        n += 1
                    res[m].append(n * b / (time.perf_counter() - t0))
            row = {"threads": threads, "batch": b}
            row.update({os.path.basename(m): round(float(np.median(v)), 1) for m, v in res.items()})
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=os.path.join(REPO, "models", "assets", "dan.onnx"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--data", default=os.path.join(os.environ.get("HOLOFACE_DATA", os.path.join(REPO, "..", "shared", "data")), "faces68", "train"))
    ap.add_argument("--calib", type=int, default=512, help="training faces to calibrate on")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--exclude", default=",".join(HEAD), help="comma-separated node names left in fp32 "
                    "[default: the landmark head]")
    ap.add_argument("--max-shift", type=float, default=0.5, help="largest landmark move allowed, crop pixels")
    ap.add_argument("--max-nme-increase", type=float, default=0.005, help="relative NME increase allowed")
    ap.add_argument("--method", choices=["minmax", "entropy", "percentile"], default="minmax",
                    help="how activation ranges are calibrated")
    ap.add_argument("--per-tensor", action="store_true", help="one weight scale per tensor, not per channel")
    ap.add_argument("--optimize-first", action="store_true",
                    help="let quant_pre_process run ORT's optimisations first (folds bn1 into fc1: see the module doc)")
    ap.add_argument("--bench", action="store_true", help="time both graphs side by side afterwards")
    args = ap.parse_args()

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    tmp = args.out + ".tmp"
    t0 = time.perf_counter()
    quantise(args.model, tmp, training_crops(args.data, args.calib, args.seed),
             [n for n in args.exclude.split(",") if n], not args.per_tensor, not args.optimize_first, args.method)
    gate(args.model, tmp, args.out, args.data, "int8", args.max_shift, args.max_nme_increase,
         calibration_faces=args.calib, seconds=round(time.perf_counter() - t0, 1))
    if args.bench:
        bench([args.model, args.out])


if __name__ == "__main__":
    main()
