//! The one dense solver of the crate: Cholesky for the symmetric positive-definite systems every fit here
//! solves (normal equations `AᵀA x = Aᵀb`, with or without a ridge): CANDIDE-3's Gauss-Newton step, the
//! blendshapes' head-turn and brow fits, the adaptation's regression and the KRFWS trainer's ridge.

/// Solves `a · x = b` for the symmetric positive-definite `a` (n×n, row-major; the lower triangle is read and
/// overwritten by the factor), `x` written over `b`. `false` when `a` is not positive definite (or not finite).
pub fn cholesky_solve(a: &mut [f64], n: usize, b: &mut [f64]) -> bool {
    cholesky_factor(a, n) && {
        solve_factored(a, n, b);
        true
    }
}

/// The Cholesky factor of the symmetric positive-definite `a` (n×n, row-major), written over its lower
/// triangle; `false` when `a` is not positive definite (or not finite). Solve with [`solve_factored`].
pub fn cholesky_factor(a: &mut [f64], n: usize) -> bool {
    debug_assert!(a.len() >= n * n);
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if d <= 0.0 || !d.is_finite() {
            return false;
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = s / d;
        }
    }
    true
}

/// Solves `a · x = b` with `a`'s factor from [`cholesky_factor`], `x` written over `b`.
pub fn solve_factored(factor: &[f64], n: usize, b: &mut [f64]) {
    debug_assert!(factor.len() >= n * n && b.len() >= n);
    for i in 0..n {
        let mut s = b[i];
        for k in 0..i {
            s -= factor[i * n + k] * b[k];
        }
        b[i] = s / factor[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in i + 1..n {
            s -= factor[k * n + i] * b[k];
        }
        b[i] = s / factor[i * n + i];
    }
}

/// [`cholesky_solve`] of a small fixed-size system; `None` when `a` is not positive definite.
pub fn solve_spd<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    cholesky_solve(a.as_flattened_mut(), N, &mut b).then_some(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solves_a_small_system_and_refuses_an_indefinite_one() {
        let mut a = [4.0, 2.0, 2.0, 3.0];
        let mut b = [2.0, 1.0];
        assert!(cholesky_solve(&mut a, 2, &mut b));
        assert!((4.0 * b[0] + 2.0 * b[1] - 2.0).abs() < 1e-12);
        assert!((2.0 * b[0] + 3.0 * b[1] - 1.0).abs() < 1e-12);
        assert!(!cholesky_solve(&mut [-1.0], 1, &mut [1.0]));
        assert!(!cholesky_solve(&mut [f64::NAN], 1, &mut [1.0]));
    }

    #[test]
    fn the_fixed_size_form_agrees() {
        let x = solve_spd(
            [[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]],
            [1.0, 2.0, 3.0],
        )
        .unwrap();
        let back = [4.0 * x[0] + x[1], x[0] + 3.0 * x[1] + x[2], x[1] + 2.0 * x[2]];
        for (got, want) in back.iter().zip([1.0, 2.0, 3.0]) {
            assert!((got - want).abs() < 1e-12);
        }
        assert!(solve_spd([[1.0, 2.0], [2.0, 1.0]], [1.0, 1.0]).is_none());
    }
}
