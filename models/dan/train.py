"""Train the single-stage DAN with a face/no-face head.

    .venv/bin/python models/dan/train.py --data ../shared/data/faces68/train --out runs/dan-w0.5 --width 0.5

Resumable: re-running the same command continues from `<out>/last.pt`, or from `--resume-from` (a slim
checkpoint: weights, step, RNG state) when that does not exist. Writes `<out>/best.pt` (lowest validation
NME), `<out>/slim.pt` (the latest weights without optimiser state: what gets committed so that a fresh checkout
continues), `<out>/log.jsonl` (one line per evaluation, validation per subset and overall) and a tqdm progress
bar on stderr.

The learning rate follows one cosine from `--lr` at `--phase-start` to 1e-5 at `--steps`, so a phase begun on
one day continues unchanged on the next. A resumed or warm-started net keeps the mean shape (the crop frame)
and the per-pixel normalisation it was trained with; the script reports how far the mean shape of the current
training data lies from it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import data as D  # noqa: E402
import geometry as g  # noqa: E402
from net import Dan  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
MEAN_SHAPE_FILE = os.path.join(REPO, "models", "assets", "mean_shape_68.txt")
SPLIT_FILE = os.path.join(REPO, "models", "splits", "val.txt")


def write_mean_shape(path: str, canon: np.ndarray, n_faces: int) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write(
            "# DAN canonical 68-point mean shape in 112x112 crop pixels (x y per line).\n"
            f"# Generalised Procrustes mean of {n_faces} faces68/train faces (validation split excluded) and their\n"
            "# mirror images, eyes level, larger extent 56 px, point mean at (56, 56). Produced by models/dan/train.py.\n"
        )
        for x, y in canon:
            f.write(f"{x:.6f} {y:.6f}\n")


def split(root: str) -> tuple[list[str], list[str]]:
    val = set(g.read_split(SPLIT_FILE))
    names = g.list_samples(root)
    missing = val - set(names)
    if missing:
        raise SystemExit(f"validation names not found under {root}: {sorted(missing)[:3]}...")
    return [n for n in names if n not in val], sorted(val)


def batch(faces, canon, rng, n, neg_frac, occlusion=0.0, hard=0.0, spread=1.0, teacher=None, teacher_frac=0.0):
    crops = np.empty((n, 1, g.CROP, g.CROP), np.uint8)
    lms = np.zeros((n, 68, 2), np.float32)
    lab = np.zeros(n, np.int64)
    for i in range(n):
        # A share of the samples comes from the teacher-labelled faces (issue 36), the rest from the annotated.
        pool = teacher if teacher and rng.random() < teacher_frac else faces
        f = pool[rng.integers(len(pool))]
        c, lm, y = D.make_sample(f, canon, rng, positive=rng.random() >= neg_frac, occlusion=occlusion, hard=hard,
                                   spread=spread)
        crops[i, 0], lms[i], lab[i] = c, lm, y
    return torch.from_numpy(crops), torch.from_numpy(lms), torch.from_numpy(lab)


def nme(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Per-sample mean point error over 68 points / eye-centre distance (DAN's training loss)."""
    d = (gt[:, 36:42].mean(1) - gt[:, 42:48].mean(1)).norm(dim=1).clamp_min(1.0)
    return (pred - gt).norm(dim=2).mean(1) / d


def wing(pred: torch.Tensor, gt: torch.Tensor, w: float = 10.0, eps: float = 2.0) -> torch.Tensor:
    """Per-sample wing loss (Feng et al., CVPR 2018) of the point errors in percent of the eye-centre distance,
    divided by 100 so that it reads like an NME: log-shaped below `w` % (small errors keep a large gradient),
    linear above."""
    d = (gt[:, 36:42].mean(1) - gt[:, 42:48].mean(1)).norm(dim=1).clamp_min(1.0)
    x = 100.0 * (pred - gt).norm(dim=2) / d[:, None]
    c = w - w * math.log(1 + w / eps)
    return torch.where(x < w, w * torch.log1p(x / eps), x - c).mean(1) / 100.0


NEG_PER_FACE = 12  # 168 validation faces -> 2,016 negative crops


def validation_set(faces, canon, seed):
    """Jittered GT-box crops of the validation faces, and NEG_PER_FACE negatives cut from each validation image
    (half of them near misses: the face at a wrong offset, scale or rotation)."""
    rng = np.random.default_rng(seed)
    pos, pos_lm, neg = [], [], []
    for f in faces:
        init = D.validation_init(canon, f.pts, rng)
        sim = g.best_fit(init, canon)
        pos.append(g.warp_crop(f.img, sim))
        pos_lm.append(g.apply(sim, f.pts))
        for _ in range(NEG_PER_FACE):
            sim_n = g.best_fit(D.negative_init(canon, f.img, f.pts, rng, hard=0.5), canon)
            neg.append(g.warp_crop(f.img, sim_n))
    t = lambda a: torch.from_numpy(np.stack(a)[:, None])  # noqa: E731
    subsets = np.array([f.name.split("/")[0] for f in faces])
    return t(pos), torch.from_numpy(np.stack(pos_lm)).float(), t(neg), subsets


def roc_auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """Probability that a random positive scores above a random negative (ties count half)."""
    s = np.concatenate([pos, neg])
    order = s.argsort(kind="mergesort")
    ranks = np.empty(len(s))
    ranks[order] = np.arange(1, len(s) + 1)
    # average ranks over ties
    _, inv, cnt = np.unique(s, return_inverse=True, return_counts=True)
    sums = np.bincount(inv, weights=ranks)
    ranks = (sums / cnt)[inv]
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def mirror_crop(x: torch.Tensor) -> torch.Tensor:
    """The crop mirrored about the mean shape's own axis, x = CROP / 2 (its point mean; the shape is the
    Procrustes mean of faces and their mirror images, so it is symmetric about that line): u -> CROP - u.
    A plain `flip` mirrors about the grid's centre (CROP - 1) / 2 instead and shifts the face by a pixel. The
    column that falls outside is dropped; the new column 0 is zero, as outside the image."""
    return F.pad(torch.flip(x, dims=[3]), (1, 0))[..., : g.CROP]


def mirror_predict(net, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mirror test-time augmentation: the mean of the net on the crop and on its mirror image (landmarks
    mapped back through the 68-point swap and x -> CROP - x), and the mean face probability."""
    lm, logits = net(x)
    lm_m, logits_m = net(mirror_crop(x))
    lm_m = lm_m[:, torch.from_numpy(g.MIRROR_68)]
    lm_m = torch.stack([g.CROP - lm_m[..., 0], lm_m[..., 1]], dim=-1)
    p = 0.5 * (torch.softmax(logits, 1)[:, 1] + torch.softmax(logits_m, 1)[:, 1])
    return 0.5 * (lm + lm_m), p


@torch.no_grad()
def evaluate(net, val, channels_last, mirror=False):
    net.eval()
    pos, pos_lm, neg, subsets = val
    outs = []
    for x in (pos, neg):
        lm_all, p_all = [], []
        for i in range(0, len(x), 64):
            xb = x[i : i + 64]
            if channels_last:
                xb = xb.contiguous(memory_format=torch.channels_last)
            if mirror:
                lm, p = mirror_predict(net, xb)
            else:
                lm, logits = net(xb)
                p = torch.softmax(logits, 1)[:, 1]
            lm_all.append(lm)
            p_all.append(p)
        outs.append((torch.cat(lm_all), torch.cat(p_all)))
    (lm, p_pos), (_, p_neg) = outs
    e_centres = nme(lm, pos_lm)
    corners = (pos_lm[:, 36] - pos_lm[:, 45]).norm(dim=1)
    e_corners = (lm - pos_lm).norm(dim=2).mean(1) / corners
    net.train()
    pp, pn = p_pos.numpy(), p_neg.numpy()
    m = {
        "val_nme_centres": float(e_centres.mean()),
        "val_nme68_corners": float(e_corners.mean()),
        "val_fail_008": float((e_corners > 0.08).float().mean()),
        "face_auc": roc_auc(pp, pn),
        "face_frr@0.5": float((pp < 0.5).mean()),
        "face_far@0.5": float((pn >= 0.5).mean()),
        "face_negatives": int(len(pn)),
    }
    for sub in sorted(set(subsets)):
        m[f"val_nme68_corners_{sub}"] = float(e_corners[torch.from_numpy(subsets == sub)].mean())
    return m


# Buffers that define the crop frame and the input normalisation: kept in fp32 in every checkpoint.
EXACT_BUFFERS = ("mean_shape", "pix_mean", "pix_std")


def slim_weights(model_state: dict) -> dict:
    """The weights for a committed slim checkpoint: float parameters and batch-norm statistics in fp16 (half
    the bytes in the repository; the rounding, about 5e-4 relative, is far below one optimiser step's change
    and is undone by the first steps after a resume), the frame-defining buffers exact."""
    return {k: (v.half() if v.is_floating_point() and k not in EXACT_BUFFERS else v) for k, v in model_state.items()}


def native_bf16() -> bool:
    """Whether this CPU multiplies bf16 in hardware (AVX512-BF16 or AMX-BF16)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            flags = f.read()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.environ.get("HOLOFACE_DATA", os.path.join(REPO, "..", "shared", "data")) + "/faces68/train")
    ap.add_argument("--out", default=os.path.join(REPO, "runs", "dan-w0.5"))
    ap.add_argument("--width", type=float, default=0.5)
    ap.add_argument("--steps", type=int, default=12000, help="the step at which this phase's cosine ends")
    ap.add_argument("--phase-start", type=int, default=0, help="the step at which this phase's cosine starts at --lr")
    ap.add_argument("--stop-at", type=int, help="stop after this step (the schedule still runs to --steps)")
    ap.add_argument("--loss", choices=["nme", "wing"], default="nme", help="landmark loss: mean point error or wing")
    ap.add_argument("--occlusion", type=float, default=0.0, help="probability of an occluding rectangle per crop")
    ap.add_argument("--spread", type=float, default=1.0,
                    help="multiplier of the positives' perturbation sigmas (data.SIGMA_T/R/S)")
    ap.add_argument("--hard-neg", type=float, default=0.0, help="fraction of negatives that are near misses")
    ap.add_argument("--teacher-labels", default="", help="comma-separated teacher-label files (make teacher-labels)")
    ap.add_argument("--teacher-frac", type=float, default=0.5, help="share of samples from teacher-labelled faces")
    ap.add_argument("--teacher-limit", type=int, default=0, help="at most this many faces per label file (0 = all)")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--neg-frac", type=float, default=0.25)
    ap.add_argument("--face-weight", type=float, default=0.1, help="weight of the face cross-entropy")
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--precision", choices=["auto", "bf16", "fp32"], default="auto",
                    help="bf16 autocast or fp32; auto: bf16 on a GPU or on a CPU with native bf16 (AVX512-BF16 or "
                    "AMX), fp32 elsewhere (emulated bf16 is about 20x slower than fp32)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (the full-width recipe on a GPU)")
    ap.add_argument("--write-mean-shape", action="store_true", help=f"(re)write {MEAN_SHAPE_FILE}")
    ap.add_argument("--resume-from", help="slim checkpoint (weights, step, RNG state; no optimiser state) to continue "
                    "from when <out>/last.pt does not exist, e.g. the committed models/dan/checkpoints/*.pt")
    ap.add_argument("--init-from", help="warm start: weights (mean shape and normalisation included) of this "
                    "checkpoint, a new RNG stream from --seed; used when neither <out>/last.pt nor --resume-from exists")
    args = ap.parse_args()

    if args.precision == "auto":
        args.precision = "bf16" if args.device != "cpu" or native_bf16() else "fp32"
    print(f"precision {args.precision}, {args.threads} threads, device {args.device}", file=sys.stderr)
    torch.set_num_threads(args.threads)
    os.makedirs(args.out, exist_ok=True)
    train_names, val_names = split(args.data)
    print(f"train {len(train_names)} faces, validation {len(val_names)} faces ({SPLIT_FILE})", file=sys.stderr)
    train = D.load_faces(args.data, train_names)
    val_faces = D.load_faces(args.data, val_names)
    teacher = [f for p in args.teacher_labels.split(",") if p for f in D.load_teacher_faces(p, args.teacher_limit)]
    if teacher:
        print(f"teacher-labelled faces: {len(teacher)} ({args.teacher_frac:.0%} of the samples)", file=sys.stderr)

    data_canon = g.canonical_from_mean(g.procrustes_mean([f.pts for f in train]))
    last = os.path.join(args.out, "last.pt")
    resume = last if os.path.exists(last) else (args.resume_from if args.resume_from and os.path.exists(args.resume_from) else None)
    if args.resume_from and not resume:
        print(f"{args.resume_from} does not exist: not resuming", file=sys.stderr)
    warm = args.init_from if not resume else None
    ck = torch.load(resume or warm, weights_only=False, map_location="cpu") if (resume or warm) else None
    if ck is not None:
        # A trained net keeps its crop frame: the committed mean shape must be the one it was trained with.
        canon = ck["model"]["mean_shape"].reshape(68, 2).double().numpy()
        committed = np.loadtxt(MEAN_SHAPE_FILE, comments="#")
        if np.abs(committed - canon).max() > 1e-4:
            raise SystemExit(f"{MEAN_SHAPE_FILE} is not the mean shape of {resume or warm}")
        dev_px = float(np.linalg.norm(data_canon - canon, axis=1).max())
        print(f"mean shape kept from {resume or warm}; the {len(train)} training faces' own mean lies within "
              f"{dev_px:.3f} crop px of it", file=sys.stderr)
    else:
        canon = data_canon
        if args.write_mean_shape or not os.path.exists(MEAN_SHAPE_FILE):
            write_mean_shape(MEAN_SHAPE_FILE, canon, len(train))
        committed = np.loadtxt(MEAN_SHAPE_FILE, comments="#")
        if np.abs(committed - canon).max() > 1e-4:
            raise SystemExit(f"{MEAN_SHAPE_FILE} differs from the mean shape of this data; pass --write-mean-shape")

    dev = torch.device(args.device)
    channels_last = args.device == "cpu"
    net = Dan(torch.from_numpy(canon), args.width)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    step, best = 0, math.inf
    rng = np.random.default_rng(args.seed)
    if ck is not None and ck.get("width", args.width) != args.width:
        raise SystemExit(f"{resume or warm} is width {ck['width']}, not {args.width}")
    if warm:
        net.load_state_dict(ck["model"])
        step = ck["step"]
        torch.manual_seed(args.seed)
        print(f"warm start from {warm} (step {step}): its weights, mean shape and pixel normalisation", file=sys.stderr)
    elif resume:
        if ck.get("width", args.width) != args.width:
            raise SystemExit(f"{resume} is width {ck['width']}, not {args.width}")
        net.load_state_dict(ck["model"])
        if "opt" in ck:
            opt.load_state_dict(ck["opt"])
        step, best = ck["step"], ck["best"]
        if ck.get("val_names") != val_names:
            # Another validation split (e.g. LFPW added): the old best is not comparable.
            best = math.inf
        rng.bit_generator.state = ck["rng"]
        torch.set_rng_state(ck["torch_rng"])
        print(f"resumed from {resume} at step {step}", file=sys.stderr)
    else:
        torch.manual_seed(args.seed)
        # Per-pixel normalisation over the training distribution (positives and negatives alike).
        stat_rng = np.random.default_rng(args.seed + 1000)
        xs = torch.cat([batch(train, canon, stat_rng, 256, args.neg_frac)[0] for _ in range(16)]).float()
        net.pix_mean.copy_(xs.mean(0, keepdim=True))
        net.pix_std.copy_(xs.std(0, keepdim=True).clamp_min(1.0))
    net.to(dev)
    if channels_last:
        net = net.to(memory_format=torch.channels_last)
    val = validation_set(val_faces, canon, seed=12345)

    def lr_at(s: int) -> float:
        span = max(1, args.steps - args.phase_start)
        t = min(max(s - args.phase_start, 0), span) / span
        return 1e-5 + 0.5 * (args.lr - 1e-5) * (1 + math.cos(math.pi * t))

    def log(rec: dict) -> None:
        with open(os.path.join(args.out, "log.jsonl"), "a", encoding="utf-8") as f:
            f.write(json.dumps(rec) + "\n")

    if warm:
        # The warm start's own numbers on this validation split: the baseline of the phase.
        log({"step": step, "lr": lr_at(step), "warm_start": warm, "time": time.time(),
             **evaluate(net, val, channels_last)})
    loss_fn = wing if args.loss == "wing" else nme
    end = min(args.steps, args.stop_at) if args.stop_at else args.steps
    if step >= end:
        print(f"step {step}: this phase ends at {end}, nothing to train (start a new phase with --phase-start "
              f"{step} --steps N)", file=sys.stderr)
        return
    bar = tqdm(total=end, initial=step, desc="DAN", file=sys.stderr, mininterval=10)
    t0, seen = time.time(), 0
    run_loss = []
    while step < end:
        x, lm, y = batch(train, canon, rng, args.batch, args.neg_frac, args.occlusion, args.hard_neg, args.spread,
                         teacher, args.teacher_frac)
        x, lm, y = x.to(dev), lm.to(dev), y.to(dev)
        if channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        for pg in opt.param_groups:
            pg["lr"] = lr_at(step)
        with torch.autocast(args.device, dtype=torch.bfloat16, enabled=args.precision == "bf16"):
            pred, logits = net(x)
        pos = y == 1
        l_lm = loss_fn(pred[pos], lm[pos]).mean()
        l_face = F.cross_entropy(logits, y)
        loss = l_lm + args.face_weight * l_face
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        seen += args.batch
        run_loss.append((l_lm.item(), l_face.item()))
        bar.update(1)
        if step % args.eval_every == 0 or step == end:
            m = evaluate(net, val, channels_last)
            lm_avg = float(np.mean([a for a, _ in run_loss]))
            face_avg = float(np.mean([b for _, b in run_loss]))
            run_loss.clear()
            rec = {"step": step, "lr": lr_at(step), "train_loss": args.loss, "train_nme": lm_avg, "train_face_ce": face_avg,
                   "samples_per_s": seen / (time.time() - t0), "time": time.time(), **m}
            log(rec)
            bar.set_postfix(val=f"{m['val_nme68_corners']:.4f}", auc=f"{m['face_auc']:.4f}")
            state = {"model": net.state_dict(), "opt": opt.state_dict(), "step": step, "best": best,
                     "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
                     "width": args.width, "args": vars(args), "metrics": m, "val_names": val_names}
            if m["val_nme68_corners"] < best:
                best = m["val_nme68_corners"]
                state["best"] = best
                torch.save(state, os.path.join(args.out, "best.pt.tmp"))
                os.replace(os.path.join(args.out, "best.pt.tmp"), os.path.join(args.out, "best.pt"))
            torch.save(state, last + ".tmp")
            os.replace(last + ".tmp", last)
            slim = {k: v for k, v in state.items() if k != "opt"}
            slim["model"] = slim_weights(state["model"])
            torch.save(slim, os.path.join(args.out, "slim.pt.tmp"))
            os.replace(os.path.join(args.out, "slim.pt.tmp"), os.path.join(args.out, "slim.pt"))
            t0, seen = time.time(), 0
    bar.close()


if __name__ == "__main__":
    main()
