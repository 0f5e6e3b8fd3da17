"""DAN training throughput on this machine: forward + backward + Adam on random crops, per precision, width,
thread count and memory format (no data pipeline; train.py's data generation adds about 1 ms per sample).

    .venv/bin/python models/dan/bench_train.py --threads 1 2 --precision fp32 bf16 --width 0.5 1.0
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from net import Dan  # noqa: E402


def samples_per_s(threads: int, precision: str, width: float, channels_last: bool, batch: int, steps: int) -> float:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    net = Dan(torch.zeros(68, 2), width)
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    net = net.to(memory_format=fmt)
    opt = torch.optim.Adam(net.parameters(), 1e-4)
    x = torch.randint(0, 255, (batch, 1, 112, 112), dtype=torch.uint8).contiguous(memory_format=fmt)
    t0 = 0.0
    for i in range(steps + 2):
        if i == 2:
            t0 = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
            lm, logits = net(x)
        loss = lm.square().mean() + logits.square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return batch * steps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--precision", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    ap.add_argument("--width", type=float, nargs="+", default=[0.5])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--steps", type=int, default=4)
    args = ap.parse_args()
    print(f"torch {torch.__version__}, CPU capability {torch.backends.cpu.get_cpu_capability()}")
    for threads, precision, width in itertools.product(args.threads, args.precision, args.width):
        r = samples_per_s(threads, precision, width, True, args.batch, args.steps)
        print(f"threads {threads} {precision} width {width} channels-last batch {args.batch}: {r:.1f} samples/s",
              flush=True)


if __name__ == "__main__":
    main()
