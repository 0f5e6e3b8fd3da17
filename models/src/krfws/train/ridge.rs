//! The two ridge regressions of the trainer: the global regression on the forests' binary leaf codes (sparse,
//! conjugate gradients on the normal equations) and the failure detector's on dense HOG (see [`super`]).

use super::*;

/// How [`ridge_sparse`] solves: ridge `lambda`, relative residual `tol` per column, worker `threads`.
#[derive(Clone, Copy)]
pub(super) struct Solve {
    pub(super) lambda: f64,
    pub(super) tol: f64,
    pub(super) threads: usize,
}

/// Ridge regression from sparse binary codes (`per` global leaf ids per sample) to `y` (n × 102) by
/// Jacobi-preconditioned multi-right-hand-side conjugate gradients. Returns `W` and the iterations.
/// `lid_weights` (one per sample) weigh each sample's lid outputs ([`LID_POINTS`]): each output column is
/// its own weighted least-squares problem; `None` weighs everything 1. The products run on `threads`
/// threads with the same result bits whatever their number.
pub(super) fn ridge_sparse(
    codes: &[u32],
    per: usize,
    n_leaves: usize,
    y: &[f32],
    lid_weights: Option<&[f32]>,
    solve: Solve,
) -> (Vec<f32>, usize) {
    const K: usize = DELTA_DIM;
    let Solve { lambda, tol, threads } = solve;
    let n = codes.len() / per.max(1);
    let lids = lid_columns();
    // Scales a sample-major n × K buffer by the sample weights in the lid columns.
    let weigh = |v: &mut [f64]| {
        if let Some(w) = lid_weights {
            for (row, &wi) in v.chunks_exact_mut(K).zip(w) {
                for (x, _) in row.iter_mut().zip(&lids).filter(|(_, l)| **l) {
                    *x *= f64::from(wi);
                }
            }
        }
    };
    let mut diag = vec![lambda; n_leaves];
    for &c in codes {
        diag[c as usize] += 1.0;
    }
    let threads = threads.clamp(1, 64);
    let xt = |r: &[f64], out: &mut [f64]| sparse_xt(codes, per, n_leaves, threads, r, out);
    let x_mul = |p: &[f64], out: &mut [f64]| sparse_x_mul(codes, per, n, threads, p, out);
    let mut yd: Vec<f64> = y.iter().map(|&v| f64::from(v)).collect();
    weigh(&mut yd);
    let mut b = vec![0.0; n_leaves * K];
    xt(&yd, &mut b);
    let mut x = vec![0.0f64; n_leaves * K];
    let mut r = b.clone();
    let mut z: Vec<f64> = r.iter().enumerate().map(|(j, v)| v / diag[j / K]).collect();
    let mut p = z.clone();
    let bnorm = col_dot(&b, &b);
    let mut rz = col_dot(&r, &z);
    let mut tmp = vec![0.0f64; n * K];
    let mut q = vec![0.0f64; n_leaves * K];
    let mut iters = 0;
    for it in 0..200 {
        iters = it + 1;
        x_mul(&p, &mut tmp);
        weigh(&mut tmp);
        xt(&tmp, &mut q);
        for (j, qv) in q.iter_mut().enumerate() {
            *qv += lambda * p[j];
        }
        let pq = col_dot(&p, &q);
        let alpha: Vec<f64> = (0..K)
            .map(|k| if pq[k] > 0.0 { rz[k] / pq[k] } else { 0.0 })
            .collect();
        for j in 0..x.len() {
            let k = j % K;
            x[j] += alpha[k] * p[j];
            r[j] -= alpha[k] * q[j];
        }
        let rr = col_dot(&r, &r);
        if (0..K).all(|k| rr[k] <= tol * bnorm[k].max(1e-30)) {
            break;
        }
        for (j, zv) in z.iter_mut().enumerate() {
            *zv = r[j] / diag[j / K];
        }
        let rz_new = col_dot(&r, &z);
        for j in 0..p.len() {
            let k = j % K;
            let beta = if rz[k] > 0.0 { rz_new[k] / rz[k] } else { 0.0 };
            p[j] = z[j] + beta * p[j];
        }
        rz = rz_new;
    }
    (x.iter().map(|&v| v as f32).collect(), iters)
}

/// `Xᵀr` for the sparse 0/1 rows `codes` (`per` leaves a sample) into `out` (`n_leaves` × [`DELTA_DIM`]): every
/// thread sums its own block of output columns over all samples in sample order, so the result is the same
/// bits whatever the thread count.
fn sparse_xt(codes: &[u32], per: usize, n_leaves: usize, threads: usize, r: &[f64], out: &mut [f64]) {
    const K: usize = DELTA_DIM;
    let bw = K.div_ceil(threads);
    let parts: Vec<(usize, Vec<f64>)> = std::thread::scope(|sc| {
        let handles: Vec<_> = (0..K)
            .step_by(bw)
            .map(|k0| {
                sc.spawn(move || {
                    let w = bw.min(K - k0);
                    let mut part = vec![0.0f64; n_leaves * w];
                    for (i, row) in codes.chunks_exact(per).enumerate() {
                        let ri = &r[i * K + k0..i * K + k0 + w];
                        for &c in row {
                            for (o, v) in part[c as usize * w..(c as usize + 1) * w].iter_mut().zip(ri) {
                                *o += v;
                            }
                        }
                    }
                    (k0, part)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
            .collect()
    });
    for (k0, part) in parts {
        let w = part.len() / n_leaves.max(1);
        for (o, src) in out.chunks_exact_mut(K).zip(part.chunks_exact(w.max(1))) {
            o[k0..k0 + w].copy_from_slice(src);
        }
    }
}

/// `Xp` for the sparse rows `codes` (`n` samples) into `out` (`n` × [`DELTA_DIM`]): rows split over the threads
/// (each row is one sample's own sum).
fn sparse_x_mul(codes: &[u32], per: usize, n: usize, threads: usize, p: &[f64], out: &mut [f64]) {
    const K: usize = DELTA_DIM;
    let rows = n.div_ceil(threads).max(1);
    std::thread::scope(|sc| {
        for (o, cs) in out.chunks_mut(rows * K).zip(codes.chunks(rows * per)) {
            sc.spawn(move || {
                for (oi, row) in o.chunks_exact_mut(K).zip(cs.chunks_exact(per)) {
                    oi.fill(0.0);
                    for &c in row {
                        for (o, v) in oi.iter_mut().zip(&p[c as usize * K..(c as usize + 1) * K]) {
                            *o += v;
                        }
                    }
                }
            });
        }
    });
}

/// Per output column, the dot product of two sample- or leaf-major × [`DELTA_DIM`] buffers.
fn col_dot(a: &[f64], b: &[f64]) -> [f64; DELTA_DIM] {
    let mut s = [0.0f64; DELTA_DIM];
    for (ra, rb) in a.chunks_exact(DELTA_DIM).zip(b.chunks_exact(DELTA_DIM)) {
        for k in 0..DELTA_DIM {
            s[k] += ra[k] * rb[k];
        }
    }
    s
}

/// Ridge regression with intercept on dense rows (`x`: n × d) by CG on the centred normal equations.
pub(super) fn ridge_dense(x: &[f32], y: &[f64], d: usize, factor: f64) -> (Vec<f32>, f32) {
    let n = y.len();
    if n == 0 {
        return (vec![0.0; d], 0.0);
    }
    let mut mx = vec![0.0f64; d];
    for row in x.chunks_exact(d) {
        for (m, &v) in mx.iter_mut().zip(row) {
            *m += f64::from(v);
        }
    }
    for m in &mut mx {
        *m /= n as f64;
    }
    let my = y.iter().sum::<f64>() / n as f64;
    // A v = Xcᵀ Xc v + λ v, with Xc = X − 1 mxᵀ.
    let apply = |v: &[f64], out: &mut [f64], s: &mut [f64]| {
        let mv: f64 = mx.iter().zip(v).map(|(a, b)| a * b).sum();
        for (si, row) in s.iter_mut().zip(x.chunks_exact(d)) {
            *si = dot_f32_f64(row, v) - mv;
        }
        out.fill(0.0);
        for (&si, row) in s.iter().zip(x.chunks_exact(d)) {
            for (o, &a) in out.iter_mut().zip(row) {
                *o += si * f64::from(a);
            }
        }
        // Xcᵀ s = Xᵀ s − mx · Σ s.
        let ssum: f64 = s.iter().sum();
        for (o, m) in out.iter_mut().zip(&mx) {
            *o -= ssum * m;
        }
    };
    let mut diag_mean = 0.0;
    for row in x.chunks_exact(d) {
        for (&a, m) in row.iter().zip(&mx) {
            diag_mean += (f64::from(a) - m).powi(2);
        }
    }
    diag_mean /= d as f64;
    let lambda = factor * diag_mean + 1e-9;
    let mut b = vec![0.0f64; d];
    for (row, &t) in x.chunks_exact(d).zip(y) {
        for ((o, &a), m) in b.iter_mut().zip(row).zip(&mx) {
            *o += (f64::from(a) - m) * (t - my);
        }
    }
    let mut w = vec![0.0f64; d];
    let mut r = b.clone();
    let mut p = r.clone();
    let mut rr: f64 = r.iter().map(|v| v * v).sum();
    let bn = rr.max(1e-300);
    let mut q = vec![0.0f64; d];
    let mut sbuf = vec![0.0f64; n];
    for _ in 0..300 {
        apply(&p, &mut q, &mut sbuf);
        for (qv, pv) in q.iter_mut().zip(&p) {
            *qv += lambda * pv;
        }
        let pq: f64 = p.iter().zip(&q).map(|(a, b)| a * b).sum();
        if pq <= 0.0 {
            break;
        }
        let alpha = rr / pq;
        for j in 0..d {
            w[j] += alpha * p[j];
            r[j] -= alpha * q[j];
        }
        let rr_new: f64 = r.iter().map(|v| v * v).sum();
        if rr_new <= 1e-10 * bn {
            break;
        }
        let beta = rr_new / rr;
        for j in 0..d {
            p[j] = r[j] + beta * p[j];
        }
        rr = rr_new;
    }
    let intercept = my - w.iter().zip(&mx).map(|(a, b)| a * b).sum::<f64>();
    (w.iter().map(|&v| v as f32).collect(), intercept as f32)
}

pub(super) fn dot_f32_f64(a: &[f32], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    for (x, y) in a.chunks_exact(4).zip(b.chunks_exact(4)) {
        for k in 0..4 {
            acc[k] += f64::from(x[k]) * y[k];
        }
    }
    let tail = a.len() / 4 * 4;
    let rest: f64 = a[tail..]
        .iter()
        .zip(&b[tail..])
        .map(|(x, y)| f64::from(*x) * y)
        .sum();
    acc.iter().sum::<f64>() + rest
}
