"""Raw ONNX Runtime throughput of two DAN exports side by side (2 intra-op threads, no spinning, batch 1/8/32,
alternating rounds, median of 3):

    .venv/bin/python models/dan/bench_ort.py runs/dan-0.2.0.onnx models/assets/dan.onnx
"""

import sys
import time

import numpy as np
import onnxruntime as ort

so = ort.SessionOptions()
so.intra_op_num_threads = 2
so.inter_op_num_threads = 1
so.add_session_config_entry("session.intra_op.allow_spinning", "0")
sess = {m: ort.InferenceSession(m, so, providers=["CPUExecutionProvider"]) for m in sys.argv[1:]}
rng = np.random.default_rng(0)
for b in (1, 8, 32):
    x = rng.integers(0, 256, (b, 1, 112, 112), dtype=np.uint8)
    res = {m: [] for m in sess}
    for s in sess.values():
        s.run(None, {"pixels": x})
    for _ in range(3):
        for m, s in sess.items():
            n = max(1, 64 // b)
            t = time.perf_counter()
            for _ in range(n):
                s.run(None, {"pixels": x})
            res[m].append(n * b / (time.perf_counter() - t))
    print(f"batch {b}: " + ", ".join(f"{m} {np.median(v):.1f} img/s" for m, v in res.items()))
