"""Export a DAN checkpoint to ONNX with the normalisation folded in, and verify it with ONNX Runtime.

    .venv/bin/python models/dan/export_onnx.py --ckpt runs/dan-w0.5/best.pt --out models/assets/dan.onnx

Graph contract (checked by the alignment server at load):
* input  `pixels`     uint8   [N, 1, 112, 112]  raw grey levels of the crop
* output `landmarks`  float32 [N, 68, 2]        crop pixels
* output `face_prob`  float32 [N]               softmax probability that the crop holds an aligned face
Metadata (`metadata_props`): holoface.* keys, see METADATA below. `--random` exports an untrained net of the
same shape (for engine tests when no checkpoint exists).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import geometry as g  # noqa: E402
from net import Dan, DanExport  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--ckpt")
    ap.add_argument("--random", action="store_true", help="export an untrained network (tests only)")
    ap.add_argument("--width", type=float, default=0.5)
    ap.add_argument("--out", required=True)
    ap.add_argument("--version", default="0.1.0")
    ap.add_argument("--name", default="holoface-dan")
    ap.add_argument("--threshold", type=float, default=0.5, help="face-probability threshold shipped in metadata")
    ap.add_argument("--mirror", action="store_true", help="mirror test-time augmentation in the graph (2x cost)")
    ap.add_argument("--training-data", default="faces68/train (300-W re-annotation of AFW + HELEN + LFPW), "
                    "1844 faces, validation split models/splits/val.txt (168 faces) excluded",
                    help="the training-data note stored in the metadata")
    args = ap.parse_args()

    canon = np.loadtxt(os.path.join(REPO, "models", "assets", "mean_shape_68.txt"), comments="#")
    metrics = {}
    if args.random:
        torch.manual_seed(0)
        net = Dan(torch.from_numpy(canon), args.width)
        steps = 0
    else:
        ck = torch.load(args.ckpt, weights_only=False, map_location="cpu")
        net = Dan(torch.from_numpy(canon), ck["width"])
        net.load_state_dict(ck["model"])
        metrics, steps = ck.get("metrics", {}), ck["step"]
    net = net.eval().float().to(memory_format=torch.contiguous_format)
    model = DanExport(net, mirror=args.mirror, swap=g.MIRROR_68.tolist()).eval()

    rng = np.random.default_rng(0)
    probe = torch.from_numpy(rng.integers(0, 256, (4, 1, 112, 112), dtype=np.uint8))
    with torch.no_grad():
        ref_lm, ref_p = model(probe)

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    torch.onnx.export(
        model,
        (probe,),
        args.out,
        input_names=["pixels"],
        output_names=["landmarks", "face_prob"],
        dynamic_axes={"pixels": {0: "N"}, "landmarks": {0: "N"}, "face_prob": {0: "N"}},
        opset_version=17,
        dynamo=False,
    )

    import onnx

    m = onnx.load(args.out)
    meta = {
        "holoface.name": args.name,
        "holoface.version": args.version,
        "holoface.width": str(net.width),
        "holoface.landmarks": "68",
        "holoface.crop_size": "112",
        "holoface.mean_shape": json.dumps([[round(float(x), 6), round(float(y), 6)] for x, y in canon]),
        "holoface.face_threshold": str(args.threshold),
        "holoface.training_data": args.training_data,
        "holoface.mirror_tta": "true" if args.mirror else "false",
        "holoface.training_steps": str(steps),
        "holoface.validation": json.dumps(metrics),
        "holoface.licence": "research use only (as the 300-W annotations it was trained on)",
        "holoface.untrained": "true" if args.random else "false",
    }
    del m.metadata_props[:]
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.checker.check_model(m)
    onnx.save(m, args.out)

    import onnxruntime as ort

    sess = ort.InferenceSession(args.out, providers=["CPUExecutionProvider"])
    lm, p = sess.run(None, {"pixels": probe.numpy()})
    err = max(float(np.abs(lm - ref_lm.numpy()).max()), float(np.abs(p - ref_p.numpy()).max()))
    print(f"wrote {args.out} ({os.path.getsize(args.out)} B); max |onnxruntime - pytorch| = {err:.2e}")
    if err > 1e-4:
        raise SystemExit(f"ONNX output differs from PyTorch by {err} > 1e-4")


if __name__ == "__main__":
    main()
