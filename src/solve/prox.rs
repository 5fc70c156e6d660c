//! Proximal maps and projections shared by the kernel fits: the scaled simplex, the isotropic
//! total variation of a `k × k` kernel (its forward-difference operator and adjoint), the
//! dual-ball projection of TV, and the prox of TV plus the simplex.
//!
//! # Conventions
//! Kernels are `k × k`, row-major, zero outside their support. The TV operator
//! [`tv_gradient`] maps a kernel to `[dx; dy]` on the `(k+1) × (k+1)` grid of positions
//! `-1..k` (so the steps into and out of the support count); `‖∇‖² ≤ 8`. Values are `f32`,
//! sums and norms accumulate in `f64`.

/// Euclidean projection of `v` (in place) onto `{b ≥ 0, Σ b = total}` (sort-based, Held et
/// al.); all zeros when `total ≤ 0`.
pub fn project_simplex(v: &mut [f32], total: f32) {
    if total <= 0.0 {
        v.iter_mut().for_each(|x| *x = 0.0);
        return;
    }
    let mut vals: Vec<f32> = v.to_vec();
    vals.sort_unstable_by(|a, b| b.total_cmp(a));
    let mut cum = 0.0f64;
    let mut theta = 0.0f64;
    for (i, &u) in vals.iter().enumerate() {
        cum += u as f64;
        let t = (cum - total as f64) / (i + 1) as f64;
        if (u as f64) - t > 0.0 {
            theta = t;
        }
    }
    v.iter_mut().for_each(|x| *x = (*x as f64 - theta).max(0.0) as f32);
}

/// Forward differences of a `k × k` kernel that is zero outside its support, on the
/// `(k+1) × (k+1)` grid of positions `-1..k` (so the steps into and out of the support count):
/// `out = [dx; dy]`.
pub fn tv_gradient(b: &[f32], k: usize, out: &mut [f32]) {
    let k1 = k + 1;
    let bv = |x: usize, y: usize| -> f32 {
        // (x, y) are shifted by one: 0 is position -1
        if x == 0 || y == 0 || x > k || y > k {
            0.0
        } else {
            b[(y - 1) * k + x - 1]
        }
    };
    let (gx, gy) = out.split_at_mut(k1 * k1);
    for yy in 0..k1 {
        for xx in 0..k1 {
            let c = bv(xx, yy);
            gx[yy * k1 + xx] = bv(xx + 1, yy) - c;
            gy[yy * k1 + xx] = bv(xx, yy + 1) - c;
        }
    }
}

/// The adjoint of [`tv_gradient`].
pub fn tv_gradient_adjoint(g: &[f32], k: usize, out: &mut [f32]) {
    let k1 = k + 1;
    let (gx, gy) = g.split_at(k1 * k1);
    for y in 0..k {
        for x in 0..k {
            // kernel (x, y) sits at grid (x + 1, y + 1)
            let (gxx, gyy) = (x + 1, y + 1);
            let i = gyy * k1 + gxx;
            out[y * k + x] = gx[i - 1] - gx[i] + gy[i - k1] - gy[i];
        }
    }
}

/// Length of [`tv_gradient`]'s output for a `k × k` kernel.
pub fn tv_dual_len(k: usize) -> usize {
    2 * (k + 1) * (k + 1)
}

/// Isotropic total variation of a `k × k` kernel (zero outside), as [`tv_gradient`] measures it.
pub fn total_variation(b: &[f32], k: usize) -> f64 {
    let k1 = k + 1;
    let mut g = vec![0.0; 2 * k1 * k1];
    tv_gradient(b, k, &mut g);
    let (gx, gy) = g.split_at(k1 * k1);
    gx.iter().zip(gy).map(|(a, b)| ((a * a + b * b) as f64).sqrt()).sum()
}

/// Projects each pair `(gx[i], gy[i])` of `y = [gx; gy]` onto the disc of radius `radius`
/// (in place): the prox of the conjugate of `radius · TV`, whatever the step.
pub fn project_tv_dual(y: &mut [f32], radius: f32) {
    let m = y.len() / 2;
    let lam = radius.max(1e-30);
    let (gx, gy) = y.split_at_mut(m);
    for (a, b) in gx.iter_mut().zip(gy.iter_mut()) {
        let s = (*a * *a + *b * *b).sqrt() / lam;
        if s > 1.0 {
            *a /= s;
            *b /= s;
        }
    }
}

/// `out = argmin_{x ≥ 0, 1ᵀx = total} ½‖x − v‖² + γ·TV(x)` by projected gradient on the dual
/// (Beck & Teboulle 2009, with the constraint): `x = P(v − Kᵀq)`, `q ← Π_{|q|≤γ}(q + Kx/8)`,
/// `‖K‖² ≤ 8`. `q` ([`tv_dual_len`] long) is the warm start and is updated in place;
/// `iterations` dual steps. Kernel-sized work only.
pub fn prox_tv_simplex(v: &[f32], q: &mut [f32], gamma: f32, total: f32, k: usize, iterations: usize, out: &mut [f32]) {
    let d = q.len();
    let mut kx = vec![0.0f32; d];
    let mut ktq = vec![0.0f32; k * k];
    let gamma = gamma.max(1e-30);
    for it in 0..=iterations {
        tv_gradient_adjoint(q, k, &mut ktq);
        for ((o, &a), &b) in out.iter_mut().zip(v).zip(&ktq) {
            *o = a - b;
        }
        project_simplex(out, total);
        if it == iterations {
            break;
        }
        tv_gradient(out, k, &mut kx);
        for (a, &g) in q.iter_mut().zip(&kx) {
            *a += g / 8.0;
        }
        project_tv_dual(q, gamma);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn tv_of_a_single_coefficient() {
        // the coefficient's two outgoing steps form one pair (√2), the two incoming ones two
        // pairs of height 1
        let k = 5;
        let mut one = vec![0.0; k * k];
        one[12] = 1.0;
        let tv = total_variation(&one, k);
        assert!((tv - (1.0 + 2f64.sqrt() + 1.0)).abs() < 1e-6, "{tv}");
    }

    #[test]
    fn simplex_projection_is_feasible_and_idempotent() {
        let mut v = vec![0.5, -0.2, 0.9, 0.1];
        project_simplex(&mut v, 1.0);
        let s: f32 = v.iter().sum();
        assert!((s - 1.0).abs() < 1e-6 && v.iter().all(|&x| x >= 0.0), "{v:?}");
        assert!((v[2] - v[0] - 0.4).abs() < 1e-6);
        let mut again = v.clone();
        project_simplex(&mut again, 1.0);
        assert!(v.iter().zip(&again).all(|(a, b)| (a - b).abs() < 1e-6));
    }

    /// With γ = 0 the prox is the simplex projection; with a large γ it flattens the kernel
    /// (lower TV) while staying on the simplex.
    #[test]
    fn tv_simplex_prox_limits() {
        let k = 5;
        let mut r = Rng::new(5);
        let v: Vec<f32> = (0..k * k).map(|_| r.uniform() as f32).collect();
        let mut want = v.clone();
        project_simplex(&mut want, 1.0);
        let mut out = vec![0.0; k * k];
        let mut q = vec![0.0; tv_dual_len(k)];
        prox_tv_simplex(&v, &mut q, 0.0, 1.0, k, 20, &mut out);
        assert!(out.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-6));
        let mut q = vec![0.0; tv_dual_len(k)];
        prox_tv_simplex(&v, &mut q, 1.0, 1.0, k, 200, &mut out);
        assert!((out.iter().sum::<f32>() - 1.0).abs() < 1e-5 && out.iter().all(|&x| x >= 0.0));
        assert!(total_variation(&out, k) < 0.9 * total_variation(&want, k), "{} vs {}", total_variation(&out, k), total_variation(&want, k));
    }

    #[test]
    fn tv_dual_projection_clips_pairs() {
        let mut y = vec![3.0, 0.1, 4.0, 0.1];
        project_tv_dual(&mut y, 1.0);
        assert!((y[0] - 0.6).abs() < 1e-6 && (y[2] - 0.8).abs() < 1e-6, "{y:?}");
        assert!((y[1] - 0.1).abs() < 1e-7 && (y[3] - 0.1).abs() < 1e-7);
    }
}
