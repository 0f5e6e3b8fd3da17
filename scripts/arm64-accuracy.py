#!/usr/bin/env python3
"""ARM accuracy against x86-64's: the same faces through the detector and KRFWS on both architectures
(runtime/examples/detector_krfws.rs, x86-64 natively and aarch64 under qemu-aarch64), compared face by face.

    scripts/arm64-accuracy.py X86_64.tsv AARCH64.tsv [--bound 0.05] [--json OUT]

The aarch64 file may hold its faces in another order (the emulated run is split over several processes).

Prints the mean NME49 of each architecture over the faces both found, how many faces each found, and the
per-face differences (the detection box's largest coordinate difference and the largest landmark displacement
in pixels, the NME49 difference), then fails (exit 1) when the
two means differ by more than --bound points of NME49 (percent of the outer-eye-corner distance), when the two
runs found different faces, or when the files do not hold the same faces.
"""

import argparse
import json
import math
import sys


def read(path):
    rows = {}
    order = []
    with open(path) as f:
        for line in f:
            cols = line.rstrip("\n").split("\t")
            if len(cols) < 3:
                continue
            name, detected, nme = cols[0], cols[1] == "1", float(cols[2])
            box = tuple(map(float, cols[3].split())) if detected else ()
            points = [tuple(map(float, c.split())) for c in cols[4:]]
            rows[name] = (detected, nme, box, points)
            order.append(name)
    return order, rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("x86")
    ap.add_argument("arm")
    ap.add_argument("--bound", type=float, default=0.05, help="largest allowed difference of the means, points")
    ap.add_argument("--json", help="also write the comparison here")
    a = ap.parse_args()
    order, x86 = read(a.x86)
    arm_order, arm = read(a.arm)
    problems = []
    if sorted(order) != sorted(arm_order) or not order:
        problems.append(f"the runs hold different faces ({len(order)} on x86-64, {len(arm_order)} on aarch64)")
    both = [n for n in order if n in arm and x86[n][0] and arm[n][0]]
    found = (sum(x86[n][0] for n in order), sum(arm[n][0] for n in arm_order))
    if found[0] != found[1]:
        problems.append(f"the detector found {found[0]} faces on x86-64 and {found[1]} on aarch64")
    print(f"{'face':<24} {'NME49 x86-64':>13} {'aarch64':>9} {'diff':>9} {'box shift px':>13} {'max shift px':>13}")
    per_face = []
    for n in both:
        (_, e1, b1, p1), (_, e2, b2, p2) = x86[n], arm[n]
        shift = max((math.dist(u, v) for u, v in zip(p1, p2)), default=0.0)
        box = max((abs(u - v) for u, v in zip(b1, b2)), default=0.0)
        per_face.append({"face": n, "nme49_x86_64": e1, "nme49_aarch64": e2, "box_shift_px": box, "max_shift_px": shift})
        print(f"{n:<24} {100 * e1:>12.3f}% {100 * e2:>8.3f}% {100 * (e2 - e1):>+8.4f}  {box:>12.6f}  {shift:>12.4f}")
    mean = lambda xs: sum(xs) / len(xs) if xs else float("nan")
    m1 = 100 * mean([x86[n][1] for n in both])
    m2 = 100 * mean([arm[n][1] for n in both])
    shifts = [f["max_shift_px"] for f in per_face]
    same = sum(s < 0.01 for s in shifts)
    boxes = [f["box_shift_px"] for f in per_face]
    print(
        f"NME49 over {len(both)} faces found on both: x86-64 {m1:.4f}%, aarch64 {m2:.4f}% "
        f"(difference {m2 - m1:+.4f} points, bound {a.bound}); {same} of {len(both)} faces with every landmark "
        f"within 0.01 px of x86-64's, largest shift {max(shifts, default=0.0):.4f} px; detection boxes differ by at most "
        f"{max(boxes, default=0.0):.6f} px (ONNX Runtime's kernels differ by architecture)"
    )
    if not both:
        problems.append("no face was found on both")
    elif not abs(m2 - m1) <= a.bound:
        problems.append(f"mean NME49 differs by {m2 - m1:+.4f} points (bound {a.bound})")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(
                {"faces": len(order), "found": found, "nme49_x86_64": m1, "nme49_aarch64": m2, "per_face": per_face},
                f,
                indent=1,
            )
    sys.stdout.flush()
    for p in problems:
        print(f"arm64-accuracy: {p}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
