//! Proximal maps and projections shared by the kernel fits: the scaled simplex, the isotropic
//! total variation of a `k × k` kernel (its forward-difference operator and adjoint), the
//! dual-ball projection of TV, and the prox of TV plus the simplex.
//!
//! # Conventions
//! Kernels are `k × k`, row-major, zero outside their support. The TV operator
//! [`tv_gradient`] maps a kernel to `[dx; dy]` on the `(k+1) × (k+1)` grid of positions
//! `-1..k` (so the steps into and out of the support count); `‖∇‖² ≤ 8`. Values are `f32`,
//! sums and norms accumulate in `f64`.

/// Euclidean projection of `v` (in place) onto `{b ≥ 0, Σ b = total}`; all zeros when
/// `total ≤ 0`. The threshold `θ` with `Σ (v − θ)₊ = total` is found by Michelot's pivoting
/// (Condat 2016, §2): the active set `S` starts as all entries above the mean shift and
/// shrinks to `{v > θ}` with `θ = (Σ_S v − total)/|S|`, in expected linear time — the same
/// `θ` as the sort-based rule (Held et al.), which costs `O(n log n)`.
pub fn project_simplex(v: &mut [f32], total: f32) {
    if total <= 0.0 {
        v.iter_mut().for_each(|x| *x = 0.0);
        return;
    }
    let theta = simplex_threshold(v, total as f64);
    v.iter_mut().for_each(|x| *x = (*x as f64 - theta).max(0.0) as f32);
}

/// The threshold of [`project_simplex`]: the fixed point of `S ← {i ∈ S : v_i > θ(S)}`,
/// `θ(S) = (Σ_S v − total)/|S|`, from `S` = all entries (`θ` only grows, so `S` only shrinks).
fn simplex_threshold(v: &[f32], total: f64) -> f64 {
    let n = v.len().max(1);
    let mut theta = (v.iter().map(|&x| x as f64).sum::<f64>() - total) / n as f64;
    let mut active: Vec<f32> = v.iter().copied().filter(|&x| x as f64 > theta).collect();
    loop {
        let sum: f64 = active.iter().map(|&x| x as f64).sum();
        let next = (sum - total) / active.len().max(1) as f64;
        let before = active.len();
        active.retain(|&x| x as f64 > next);
        theta = next;
        if active.len() == before || active.is_empty() {
            return theta;
        }
    }
}

/// Forward differences of a `k × k` kernel that is zero outside its support, on the
/// `(k+1) × (k+1)` grid of positions `-1..k` (so the steps into and out of the support count):
/// `out = [dx; dy]`.
pub fn tv_gradient(b: &[f32], k: usize, out: &mut [f32]) {
    let k1 = k + 1;
    let (gx, gy) = out.split_at_mut(k1 * k1);
    // grid row yy holds kernel row yy − 1 (rows 0 and k + 1 are zero), grid column xx likewise
    let zero = vec![0.0f32; k];
    let row = |yy: usize| -> &[f32] { if yy >= 1 && yy <= k { &b[(yy - 1) * k..yy * k] } else { &zero } };
    for yy in 0..k1 {
        let (cur, below) = (row(yy), row(yy + 1));
        let gxr = &mut gx[yy * k1..(yy + 1) * k1];
        gxr[0] = cur[0];
        for xx in 1..k {
            gxr[xx] = cur[xx] - cur[xx - 1];
        }
        gxr[k] = -cur[k - 1];
        let gyr = &mut gy[yy * k1..(yy + 1) * k1];
        gyr[0] = 0.0;
        for ((g, &d), &c) in gyr[1..].iter_mut().zip(below).zip(cur) {
            *g = d - c;
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

    /// The pivoting threshold is the sort-based one (Held et al.), on random vectors with
    /// ties, negative entries and a large zero mass; the TV gradient is the direct
    /// difference of the zero-padded kernel.
    #[test]
    fn pivoting_projection_and_tv_gradient_match_the_reference() {
        let mut r = Rng::new(11);
        for n in [1usize, 2, 7, 100, 3969] {
            let v: Vec<f32> = (0..n).map(|i| if i % 5 == 0 { 0.25 } else { (r.normal() * 0.01) as f32 }).collect();
            let mut sorted = v.clone();
            sorted.sort_unstable_by(|a, b| b.total_cmp(a));
            let (mut cum, mut want) = (0.0f64, 0.0f64);
            for (i, &u) in sorted.iter().enumerate() {
                cum += u as f64;
                let t = (cum - 1.0) / (i + 1) as f64;
                if (u as f64) - t > 0.0 {
                    want = t;
                }
            }
            let got = simplex_threshold(&v, 1.0);
            assert!((got - want).abs() <= 1e-12 * want.abs().max(1e-3), "n {n}: {got} vs {want}");
        }
        let k = 6;
        let b: Vec<f32> = (0..k * k).map(|_| r.uniform() as f32).collect();
        let at = |x: isize, y: isize| if x < 0 || y < 0 || x >= k as isize || y >= k as isize { 0.0 } else { b[y as usize * k + x as usize] };
        let mut g = vec![0.0; tv_dual_len(k)];
        tv_gradient(&b, k, &mut g);
        let k1 = k + 1;
        for yy in 0..k1 {
            for xx in 0..k1 {
                let (x, y) = (xx as isize - 1, yy as isize - 1);
                assert_eq!(g[yy * k1 + xx], at(x + 1, y) - at(x, y));
                assert_eq!(g[k1 * k1 + yy * k1 + xx], at(x, y + 1) - at(x, y));
            }
        }
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
