"""Write the slim checkpoint of a training checkpoint: weights (fp16, the crop-frame buffers exact), step, RNG
state, metrics; no optimiser state. This is what gets committed under models/dan/checkpoints/ so that a fresh
checkout resumes (`make train-dan`).

    .venv/bin/python models/dan/slim.py --ckpt runs/dan-w0.5/last.pt --out models/dan/checkpoints/dan-w0.5-last.pt

Prints the largest difference the fp16 rounding makes to the net's outputs on random crops.
"""

from __future__ import annotations

import argparse
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import train as T  # noqa: E402
from net import Dan  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    ck = torch.load(args.ckpt, weights_only=False, map_location="cpu")
    slim = {k: v for k, v in ck.items() if k != "opt"}
    slim["model"] = T.slim_weights(ck["model"])
    tmp = args.out + ".tmp"
    torch.save(slim, tmp)
    os.replace(tmp, args.out)

    canon = ck["model"]["mean_shape"].reshape(68, 2)
    full, half = Dan(canon, ck["width"]), Dan(canon, ck["width"])
    full.load_state_dict(ck["model"])
    half.load_state_dict(torch.load(args.out, weights_only=False)["model"])
    x = torch.randint(0, 256, (16, 1, 112, 112), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        (a, pa), (b, pb) = full.eval()(x), half.eval()(x)
    d_lm = float((a - b).abs().max())
    d_p = float((torch.softmax(pa, 1) - torch.softmax(pb, 1)).abs().max())
    print(f"wrote {args.out} ({os.path.getsize(args.out)} B, step {ck['step']}); fp16 rounding changes landmarks "
          f"by at most {d_lm:.4f} crop px and the face probability by {d_p:.2e}")


if __name__ == "__main__":
    main()
