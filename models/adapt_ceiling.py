"""How much of the gap between KRFWS and the server a per-person correction can close, in hindsight (issue 55).

Reads one `holoface stability --aligners krfws,remote --frames FILE` run without link cuts (KRFWS tracking on its
own beside the remote pipeline, every frame of the clip) and the per-frame peer (`models/peer_video_dlib.py`).
The frames inside the cut schedule are then answered by KRFWS's own track, corrected in several ways, and scored
as `holoface stability` scores (NME49 against the peer, raw landmarks). Pairs are (KRFWS, server) on the same
frame outside the cuts, compared in the face's own frame as `models::adapt` compares them (least-squares
similarity of KRFWS's 51 inner points onto a reference with the outer eye corners one unit apart).

The rows that look at the cut frames' own server answers ("in hindsight") are not available to any headset: they
bound what a correction of that form could ever close.

    .venv/bin/python models/adapt_ceiling.py --frames runs/adapt/cap12_edit.frames.jsonl \
        --peer runs/stability/cap12_edit.dlib.tsv --cuts 15:10,35:10 --fps 25
"""

import argparse
import json
import sys

import numpy as np

INNER51 = list(range(17, 68))
PROTOCOL49 = [i for i in range(17, 68) if i not in (60, 64)]


def read_frames(path):
    """Per frame: KRFWS's raw landmarks, the remote run's raw landmarks and who answered them."""
    krfws, remote, by = [], [], []
    with open(path) as f:
        for line in f:
            a = json.loads(line)["aligners"]
            k, r = a.get("krfws") or {}, a.get("remote") or {}
            lm = lambda v: None if v.get("raw_landmarks") is None else np.array(v["raw_landmarks"], float).reshape(68, 2)
            krfws.append(lm(k))
            remote.append(lm(r))
            by.append(r.get("answered_by"))
    return krfws, remote, by


def read_peer(path, n):
    peer = [None] * n
    with open(path) as f:
        for line in f:
            v = line.split()
            if len(v) == 137 and int(v[0]) < n:
                peer[int(v[0])] = np.array(v[1:], float).reshape(68, 2)
    return peer


def fit_similarity(src, dst):
    """Least-squares similarity src -> dst as (a, b, src centroid, dst centroid)."""
    ms, md = src.mean(0), dst.mean(0)
    s, d = src - ms, dst - md
    den = (s ** 2).sum()
    a = (s * d).sum() / den
    b = (s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0]).sum() / den
    return a, b, ms, md


def apply(t, p):
    a, b, ms, md = t
    q = p - ms
    return np.stack([a * q[:, 0] - b * q[:, 1], b * q[:, 0] + a * q[:, 1]], 1) + md


def inverse(t):
    a, b, ms, md = t
    n = a * a + b * b
    return a / n, -b / n, md, ms


def nme49(x, peer):
    eye = np.linalg.norm(peer[36] - peer[45])
    return np.mean(np.linalg.norm(x[PROTOCOL49] - peer[PROTOCOL49], axis=1)) / eye


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", required=True, help="holoface stability --aligners krfws,remote --frames output")
    ap.add_argument("--peer", required=True, help="per-frame peer landmarks (models/peer_video_dlib.py)")
    ap.add_argument("--cuts", required=True, help="START:LENGTH[,...] in seconds, as holoface stability --link-cuts")
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--warm", type=int, default=30, help="the shipped schedule: first this many remote answers")
    ap.add_argument("--every", type=int, default=20, help="then every this many")
    ap.add_argument("--out", help="JSON report")
    args = ap.parse_args()

    krfws, remote, by = read_frames(args.frames)
    n = len(krfws)
    peer = read_peer(args.peer, n)
    cut = np.zeros(n, bool)
    for c in args.cuts.split(","):
        start, length = (float(v) for v in c.split(":"))
        cut[int(round(start * args.fps)):int(round((start + length) * args.fps))] = True

    first = next((k for k in krfws if k is not None), None)
    if first is None:
        sys.exit("no KRFWS answer in the frames")
    inner = first[INNER51]
    reference = (inner - inner.mean(0)) / np.linalg.norm(first[36] - first[45])
    frame = {}
    for t, k in enumerate(krfws):
        if k is not None:
            s = fit_similarity(k[INNER51], reference)
            frame[t] = (s, apply(s, k[INNER51]))

    def offset(t):
        return apply(frame[t][0], remote[t][INNER51]) - frame[t][1]

    answered = [t for t in range(n) if t in frame and remote[t] is not None and by[t] == "RemoteDan"]
    up = [t for t in answered if not cut[t]]
    scheduled = [t for i, t in enumerate(up) if i < args.warm or i % args.every == 0]
    test = [t for t in range(n) if cut[t] and t in frame and peer[t] is not None]
    if not test or not up:
        sys.exit("no cut frames with a peer, or no server answer outside the cuts")

    def score(correct):
        errs = []
        for t in test:
            x = krfws[t].copy()
            x[INNER51] = apply(inverse(frame[t][0]), frame[t][1] + correct(t))
            errs.append(nme49(x, peer[t]))
        return float(np.mean(errs))

    def online_mean(pairs):
        offs = {t: offset(t) for t in pairs}

        def correct(t):
            seen = [offs[u] for u in pairs if u < t]
            return np.mean(seen, 0) if len(seen) >= 10 else 0.0

        return correct

    alone = score(lambda t: 0.0)
    server = float(np.mean([nme49(remote[t], peer[t]) for t in test if t in answered]))
    in_cut = [t for t in test if t in answered]
    hindsight_mean = np.mean([offset(t) for t in in_cut], 0)
    all_up = np.mean([offset(t) for t in up], 0)

    # A regression on KRFWS's own shape (its first principal components over the pairs), in hindsight of every
    # pair outside the cuts: does the correction follow expressions?
    x = np.array([frame[t][1].ravel() for t in up])
    y = np.array([offset(t).ravel() for t in up])
    mu = x.mean(0)
    _, _, vt = np.linalg.svd(x - mu, full_matrices=False)

    def shape_ridge(dims, lam):
        z = (x - mu) @ vt[:dims].T
        zm, ym = z.mean(0), y.mean(0)
        a = (z - zm).T @ (z - zm) / len(z) + lam * np.diag(np.var(z, 0))
        w = np.linalg.solve(a, (z - zm).T @ (y - ym) / len(z))
        return lambda t: (ym + ((frame[t][1].ravel() - mu) @ vt[:dims].T - zm) @ w).reshape(-1, 2)

    rows = [
        ("mean offset, the shipped schedule (pairs before the frame)", score(online_mean(scheduled)), len(scheduled)),
        ("mean offset, every server answer before the frame", score(online_mean(up)), len(up)),
        ("mean offset of every pair outside the cuts (hindsight)", score(lambda t: all_up), len(up)),
        ("the cut frames' own mean offset (hindsight, the best constant)", score(lambda t: hindsight_mean), len(in_cut)),
    ]
    for dims in (4, 16):
        rows.append((f"ridge on KRFWS's shape, {dims} components, every pair outside the cuts (hindsight)",
                     score(shape_ridge(dims, 0.1)), len(up)))
    gap = alone - server
    report = {
        "frames": n, "cut_frames": len(test), "krfws_alone": alone, "server": server,
        "rows": [{"correction": r, "nme49": e, "pairs": p, "closure": (alone - e) / gap if gap > 0 else None}
                 for r, e, p in rows],
    }
    print(f"{n} frames, {len(test)} in the cuts: KRFWS alone {100 * alone:.2f} %, the server {100 * server:.2f} %")
    for r in report["rows"]:
        print(f"  {r['correction']:<88} {100 * r['nme49']:.2f} %  closure {100 * r['closure']:3.0f} %  ({r['pairs']} pairs)")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
