//! Preconditioned conjugate gradients for symmetric positive definite systems `A x = b`.
//!
//! `A` and the preconditioner `M⁻¹` are closures (every product in lensrig is a filtering or a
//! point-wise product, so no matrix is ever formed). Dot products accumulate in `f64`. The loop
//! stops when `‖b − A x‖ ≤ tolerance · ‖b‖` or after `max_iterations`; `x` is the warm start on
//! entry and the solution on exit.

/// What the loop did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CgStats {
    pub iterations: usize,
    /// `‖b − A x‖ / ‖b‖` at exit (0 for `b = 0`).
    pub relative_residual: f64,
    pub converged: bool,
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum()
}

/// Solves `A x = b` by preconditioned CG, starting from the `x` given.
///
/// `apply_a(v, out)` must write `A v` into `out`; `precondition(r, out)` writes `M⁻¹ r` (use
/// a copy for no preconditioning). Both operators must be symmetric positive definite.
pub fn conjugate_gradient(
    mut apply_a: impl FnMut(&[f32], &mut [f32]),
    mut precondition: impl FnMut(&[f32], &mut [f32]),
    b: &[f32],
    x: &mut [f32],
    max_iterations: usize,
    tolerance: f64,
) -> CgStats {
    let n = b.len();
    assert_eq!(x.len(), n, "CG sizes");
    let bnorm = dot(b, b).sqrt();
    if bnorm == 0.0 {
        x.iter_mut().for_each(|v| *v = 0.0);
        return CgStats { iterations: 0, relative_residual: 0.0, converged: true };
    }
    let mut r = vec![0.0f32; n];
    apply_a(x, &mut r);
    for (ri, bi) in r.iter_mut().zip(b) {
        *ri = bi - *ri;
    }
    let mut z = vec![0.0f32; n];
    precondition(&r, &mut z);
    let mut p = z.clone();
    let mut ap = vec![0.0f32; n];
    let mut rz = dot(&r, &z);
    let mut res = dot(&r, &r).sqrt() / bnorm;
    let mut stats = CgStats { iterations: 0, relative_residual: res, converged: res <= tolerance };
    for it in 1..=max_iterations {
        if res <= tolerance {
            break;
        }
        apply_a(&p, &mut ap);
        let pap = dot(&p, &ap);
        if pap <= 0.0 || !pap.is_finite() {
            break; // not positive definite along p (or exact solution reached)
        }
        let alpha = rz / pap;
        for i in 0..n {
            x[i] += (alpha * p[i] as f64) as f32;
            r[i] -= (alpha * ap[i] as f64) as f32;
        }
        res = dot(&r, &r).sqrt() / bnorm;
        stats.iterations = it;
        stats.relative_residual = res;
        if res <= tolerance {
            break;
        }
        precondition(&r, &mut z);
        let rz_new = dot(&r, &z);
        let beta = rz_new / rz;
        rz = rz_new;
        for i in 0..n {
            p[i] = z[i] + (beta * p[i] as f64) as f32;
        }
    }
    stats.converged = res <= tolerance;
    stats
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A = tridiagonal(−1, 4, −1) (SPD); compare against a direct Thomas solve.
    fn apply_tri(v: &[f32], out: &mut [f32]) {
        let n = v.len();
        for i in 0..n {
            let l = if i > 0 { v[i - 1] } else { 0.0 };
            let r = if i + 1 < n { v[i + 1] } else { 0.0 };
            out[i] = 4.0 * v[i] - l - r;
        }
    }

    fn thomas(b: &[f32]) -> Vec<f32> {
        let n = b.len();
        let (mut c, mut d) = (vec![0.0f64; n], vec![0.0f64; n]);
        c[0] = -1.0 / 4.0;
        d[0] = b[0] as f64 / 4.0;
        for i in 1..n {
            let m = 4.0 + c[i - 1];
            c[i] = -1.0 / m;
            d[i] = (b[i] as f64 + d[i - 1]) / m;
        }
        let mut x = vec![0.0f64; n];
        x[n - 1] = d[n - 1];
        for i in (0..n - 1).rev() {
            x[i] = d[i] - c[i] * x[i + 1];
        }
        x.into_iter().map(|v| v as f32).collect()
    }

    #[test]
    fn solves_tridiagonal_system() {
        let b: Vec<f32> = (0..50).map(|i| ((i * 17 % 7) as f32) - 3.0).collect();
        let want = thomas(&b);
        let mut x = vec![0.0; 50];
        let st = conjugate_gradient(apply_tri, |r, z| z.copy_from_slice(r), &b, &mut x, 200, 1e-6);
        assert!(st.converged, "{st:?}");
        for (a, w) in x.iter().zip(&want) {
            assert!((a - w).abs() < 1e-4, "{a} vs {w}");
        }
        // a Jacobi preconditioner (diag = 4) converges as well, warm start from the answer is free
        let mut x2 = want.clone();
        let st2 = conjugate_gradient(apply_tri, |r, z| z.iter_mut().zip(r).for_each(|(z, r)| *z = r / 4.0), &b, &mut x2, 200, 1e-5);
        assert!(st2.converged && st2.iterations <= 1, "{st2:?}");
    }

    #[test]
    fn zero_rhs_gives_zero() {
        let mut x = vec![1.0; 5];
        let st = conjugate_gradient(apply_tri, |r, z| z.copy_from_slice(r), &[0.0; 5], &mut x, 10, 1e-6);
        assert!(st.converged && x.iter().all(|v| *v == 0.0));
    }
}
