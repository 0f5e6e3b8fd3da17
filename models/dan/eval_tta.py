"""Validation metrics of a DAN checkpoint with and without mirror test-time augmentation (the training
script's validation: jittered GT-box crops of models/splits/val.txt, 12 negatives per face).

    .venv/bin/python models/dan/eval_tta.py --ckpt runs/dan-w0.5/best.pt --out runs/tta.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import data as D  # noqa: E402
import train as T  # noqa: E402
from net import Dan  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.path.join(os.environ.get("HOLOFACE_DATA", os.path.join(T.REPO, "..", "shared", "data")), "faces68", "train"))
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    ck = torch.load(args.ckpt, weights_only=False, map_location="cpu")
    canon = ck["model"]["mean_shape"].reshape(68, 2).double().numpy()
    net = Dan(torch.from_numpy(canon), ck["width"])
    net.load_state_dict(ck["model"])
    _, val_names = T.split(args.data)
    val = T.validation_set(D.load_faces(args.data, val_names), canon, seed=12345)
    out = {"ckpt": args.ckpt, "step": ck["step"]}
    for mirror in (False, True):
        m = T.evaluate(net, val, channels_last=False, mirror=mirror)
        out["mirror" if mirror else "plain"] = m
        print(f"mirror={mirror}: NME68 {100 * m['val_nme68_corners']:.3f} %, fail {100 * m['val_fail_008']:.2f} %, "
              f"face AUC {m['face_auc']:.4f} FRR {100 * m['face_frr@0.5']:.2f} % FAR {100 * m['face_far@0.5']:.2f} %")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
