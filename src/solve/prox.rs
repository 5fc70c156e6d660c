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
/// The active set is compacted in place in a per-thread buffer (no allocation per call) and
/// summed by [`sum_f64`].
fn simplex_threshold(v: &[f32], total: f64) -> f64 {
    thread_local! {
        static ACTIVE: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    let n = v.len().max(1);
    let mut theta = (sum_f64(v) - total) / n as f64;
    let mut active = ACTIVE.with(|c| std::mem::take(&mut *c.borrow_mut()));
    active.clear();
    active.extend(v.iter().copied().filter(|&x| x as f64 > theta));
    loop {
        let next = (sum_f64(&active) - total) / active.len().max(1) as f64;
        let before = active.len();
        let kept = retain_above(&mut active, next);
        active.truncate(kept);
        theta = next;
        if kept == before || kept == 0 {
            break;
        }
    }
    ACTIVE.with(|c| *c.borrow_mut() = active);
    theta
}

/// Moves the entries of `a` above `t` to its front (order kept), branch-free; returns how many.
fn retain_above(a: &mut [f32], t: f64) -> usize {
    let mut j = 0;
    for i in 0..a.len() {
        let x = a[i];
        a[j] = x;
        j += usize::from(x as f64 > t);
    }
    j
}

/// `Σ v` in `f64` with [`SUM_LANES`] independent partial sums (entry `i` into lane `i mod
/// SUM_LANES`, lanes added in order): the same value up to rounding as the sequential sum, without
/// its chain of dependent additions.
pub fn sum_f64(v: &[f32]) -> f64 {
    let mut acc = [0.0f64; SUM_LANES];
    let chunks = v.chunks_exact(SUM_LANES);
    let rest = chunks.remainder();
    for c in chunks {
        for (a, &x) in acc.iter_mut().zip(c) {
            *a += x as f64;
        }
    }
    for (a, &x) in acc.iter_mut().zip(rest) {
        *a += x as f64;
    }
    acc.iter().sum()
}

/// Partial sums of [`sum_f64`].
const SUM_LANES: usize = 8;

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

/// The adjoint of [`tv_gradient`]: kernel `(x, y)` (grid `(x + 1, y + 1)`, index `i`) gets
/// `gx[i − 1] − gx[i] + gy[i − (k+1)] − gy[i]`, row by row on slices.
pub fn tv_gradient_adjoint(g: &[f32], k: usize, out: &mut [f32]) {
    let k1 = k + 1;
    let (gx, gy) = g.split_at(k1 * k1);
    for (y, o) in out[..k * k].chunks_exact_mut(k).enumerate() {
        let i0 = (y + 1) * k1 + 1;
        let (gxl, gxc) = (&gx[i0 - 1..i0 - 1 + k], &gx[i0..i0 + k]);
        let (gyu, gyc) = (&gy[i0 - k1..i0 - k1 + k], &gy[i0..i0 + k]);
        for ((((o, &a), &b), &c), &d) in o.iter_mut().zip(gxl).zip(gxc).zip(gyu).zip(gyc) {
            *o = a - b + c - d;
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
    // branch-free: dividing by max(s, 1) leaves the pairs inside the disc exactly as they are
    for (a, b) in gx.iter_mut().zip(gy.iter_mut()) {
        let s = ((*a * *a + *b * *b).sqrt() / lam).max(1.0);
        *a /= s;
        *b /= s;
    }
}

/// `y_i ← M_i y_i` for every pair `y_i = (gx[i], gy[i])` of `y = [gx; gy]` (`transpose`:
/// `M_iᵀ y_i`), `M_i = [m0 m1; m2 m3]` row-major.
pub fn apply_pair_frames(y: &mut [f32], frames: &[[f32; 4]], transpose: bool) {
    let m = y.len() / 2;
    let (gx, gy) = y.split_at_mut(m);
    for ((a, b), f) in gx.iter_mut().zip(gy.iter_mut()).zip(frames) {
        let (u, v) = if transpose { (f[0] * *a + f[2] * *b, f[1] * *a + f[3] * *b) } else { (f[0] * *a + f[1] * *b, f[2] * *a + f[3] * *b) };
        *a = u;
        *b = v;
    }
}

/// The frames of the polar TV of a `k × k` kernel ([`prox_tv_simplex`]): for gradient pair `i`
/// ([`tv_gradient`]'s grid, position `p_i = (xx − ½, yy − ½)` in kernel pixels) at distance
/// `r ≥ 1` from `centre`, `M_i = diag(a, 1) · [r̂ᵀ; t̂ᵀ]` (`r̂` the unit vector from `centre` to
/// `p_i`, `t̂` its perpendicular), so `|M_i ∇b_i| = √(a² (r̂·∇b_i)² + (t̂·∇b_i)²)`: the radial
/// change weighted `a ≤ 1`, the change along the ring 1; within 1 px of the centre
/// `M_i = a·I`. Within `core` px of the centre (the core release, docs/estimation.md "Core
/// release"; 0: none) `M_i = 0`: the TV is off there. `‖M_i‖ ≤ 1`.
pub fn polar_tv_frames(k: usize, centre: [f32; 2], a: f32, core: f32) -> Vec<[f32; 4]> {
    let k1 = k + 1;
    (0..k1 * k1)
        .map(|i| {
            let (px, py) = ((i % k1) as f32 - 0.5 - centre[0], (i / k1) as f32 - 0.5 - centre[1]);
            let r = (px * px + py * py).sqrt();
            if r <= core {
                [0.0; 4]
            } else if r < 1.0 {
                [a, 0.0, 0.0, a]
            } else {
                let (c, s) = (px / r, py / r);
                [a * c, a * s, -s, c]
            }
        })
        .collect()
}

/// `out = argmin_{x ≥ 0, 1ᵀx = total} ½‖x − v‖² + γ·TV_M(x)` by projected gradient on the dual
/// (Beck & Teboulle 2009, with the constraint): `x = P(v − KᵀMᵀq)`, `q ← Π_{|q_i|≤γ}(q + MKx/8)`,
/// `‖K‖² ≤ 8`. `TV_M(x) = Σ_i |M_i (∇x)_i|` with one 2×2 matrix `M_i` of norm ≤ 1 per gradient
/// pair (`frames`, `(k+1)²` of them in [`tv_gradient`]'s pair order, e.g. [`polar_tv_frames`]),
/// or the plain isotropic TV (`M_i = I`) when `None`. `q` ([`tv_dual_len`] long) is the warm
/// start and is updated in place; `iterations` dual steps. Kernel-sized work only.
#[allow(clippy::too_many_arguments)]
pub fn prox_tv_simplex(v: &[f32], q: &mut [f32], gamma: f32, frames: Option<&[[f32; 4]]>, total: f32, k: usize, iterations: usize, out: &mut [f32]) {
    thread_local! {
        static WORK: std::cell::RefCell<(Vec<f32>, Vec<f32>)> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
    }
    let (mut kx, mut ktq) = WORK.with(|c| std::mem::take(&mut *c.borrow_mut()));
    kx.resize(q.len(), 0.0);
    ktq.resize(k * k, 0.0);
    prox_tv_simplex_with(v, q, gamma, frames, total, k, iterations, out, &mut kx, &mut ktq);
    WORK.with(|c| *c.borrow_mut() = (kx, ktq));
}

/// [`prox_tv_simplex`] with caller-owned work buffers `kx` (`q.len()`) and `ktq` (`k²`).
#[allow(clippy::too_many_arguments)]
fn prox_tv_simplex_with(v: &[f32], q: &mut [f32], gamma: f32, frames: Option<&[[f32; 4]]>, total: f32, k: usize, iterations: usize, out: &mut [f32], kx: &mut [f32], ktq: &mut [f32]) {
    let gamma = gamma.max(1e-30);
    for it in 0..=iterations {
        match frames {
            Some(f) => {
                kx.copy_from_slice(q);
                apply_pair_frames(kx, f, true);
                tv_gradient_adjoint(kx, k, ktq);
            }
            None => tv_gradient_adjoint(q, k, ktq),
        }
        for ((o, &a), &b) in out.iter_mut().zip(v).zip(ktq.iter()) {
            *o = a - b;
        }
        project_simplex(out, total);
        if it == iterations {
            break;
        }
        tv_gradient(out, k, kx);
        if let Some(f) = frames {
            apply_pair_frames(kx, f, false);
        }
        for (a, &g) in q.iter_mut().zip(kx.iter()) {
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

    /// The lane sum equals the sequential `f64` sum up to rounding (lengths around the lane
    /// count, a large one with mixed signs), and the slice form of the TV adjoint is the adjoint:
    /// `⟨∇b, g⟩ = ⟨b, ∇ᵀg⟩` for random `b`, `g`.
    #[test]
    fn lane_sum_and_tv_adjoint_match_their_definitions() {
        let mut r = Rng::new(17);
        for n in [0usize, 1, 7, 8, 9, 4097] {
            let v: Vec<f32> = (0..n).map(|_| r.normal() as f32).collect();
            let seq: f64 = v.iter().map(|&x| x as f64).sum();
            let scale: f64 = v.iter().map(|&x| (x as f64).abs()).sum::<f64>().max(1.0);
            assert!((sum_f64(&v) - seq).abs() <= 1e-12 * scale, "n {n}: {} vs {seq}", sum_f64(&v));
        }
        for k in [1usize, 5, 8] {
            let b: Vec<f32> = (0..k * k).map(|_| r.normal() as f32).collect();
            let g: Vec<f32> = (0..tv_dual_len(k)).map(|_| r.normal() as f32).collect();
            let (mut kb, mut ktg) = (vec![0.0; tv_dual_len(k)], vec![0.0; k * k]);
            tv_gradient(&b, k, &mut kb);
            tv_gradient_adjoint(&g, k, &mut ktg);
            let dot = |a: &[f32], c: &[f32]| a.iter().zip(c).map(|(x, y)| *x as f64 * *y as f64).sum::<f64>();
            let (lhs, rhs) = (dot(&kb, &g), dot(&b, &ktg));
            assert!((lhs - rhs).abs() <= 1e-5 * lhs.abs().max(1.0), "k {k}: {lhs} vs {rhs}");
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
        prox_tv_simplex(&v, &mut q, 0.0, None, 1.0, k, 20, &mut out);
        assert!(out.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-6));
        let mut q = vec![0.0; tv_dual_len(k)];
        prox_tv_simplex(&v, &mut q, 1.0, None, 1.0, k, 200, &mut out);
        assert!((out.iter().sum::<f32>() - 1.0).abs() < 1e-5 && out.iter().all(|&x| x >= 0.0));
        assert!(total_variation(&out, k) < 0.9 * total_variation(&want, k), "{} vs {}", total_variation(&out, k), total_variation(&want, k));
    }

    /// A unit-sum disc with rings (a defocus disc's Fresnel ripples, ±25 % of its level) plus
    /// noise: at the same weight the polar TV (`a = ¼`) ends closer to the ringed truth than the
    /// isotropic TV, which flattens the rings, and well below the input's noise; identity frames
    /// are the plain prox.
    #[test]
    fn polar_tv_keeps_rings_that_isotropic_tv_flattens() {
        let k = 31;
        let c = (k / 2) as f32;
        let mut truth: Vec<f32> = (0..k * k)
            .map(|i| {
                let r = (((i % k) as f32 - c).powi(2) + ((i / k) as f32 - c).powi(2)).sqrt();
                if r <= 11.0 { 1.0 + 0.25 * (r * std::f32::consts::PI / 2.0).cos() } else { 0.0 }
            })
            .collect();
        let s: f32 = truth.iter().sum();
        truth.iter_mut().for_each(|v| *v /= s);
        let level = 1.0 / s;
        let mut r = Rng::new(3);
        let v: Vec<f32> = truth.iter().map(|&t| t + 0.15 * level * r.normal() as f32).collect();
        let run = |frames: Option<&[[f32; 4]]>| {
            let (mut q, mut out) = (vec![0.0; tv_dual_len(k)], vec![0.0; k * k]);
            prox_tv_simplex(&v, &mut q, 0.4 * level, frames, 1.0, k, 300, &mut out);
            out
        };
        let err = |x: &[f32]| x.iter().zip(&truth).map(|(a, b)| ((a - b) as f64).powi(2)).sum::<f64>().sqrt();
        let (iso, polar) = (run(None), run(Some(&polar_tv_frames(k, [c, c], 0.25, 0.0))));
        let noisy = err(&v);
        assert!(err(&polar) < 0.95 * err(&iso), "polar {:.3e} vs isotropic {:.3e}", err(&polar), err(&iso));
        assert!(err(&polar) < 0.8 * noisy, "polar {:.3e} vs the noisy input {noisy:.3e}", err(&polar));
        let ident = vec![[1.0, 0.0, 0.0, 1.0]; (k + 1) * (k + 1)];
        assert!(run(Some(&ident)).iter().zip(&iso).all(|(a, b)| (a - b).abs() <= 1e-6 * level), "identity frames differ from the plain TV");
    }

    /// The core release: pairs within `core` px of the centre get `M_i = 0`, and the prox then
    /// keeps a fine central structure (a one-pixel dip ringed by a bright ring, as in a defocus
    /// disc's centre) that the polar TV fills, while the disc outside the core is smoothed as before.
    #[test]
    fn core_release_keeps_the_central_structure() {
        let k = 31;
        let c = (k / 2) as f32;
        let f = polar_tv_frames(k, [c, c], 0.25, 3.0);
        let radius = |i: usize| (((i % (k + 1)) as f32 - 0.5 - c).powi(2) + ((i / (k + 1)) as f32 - 0.5 - c).powi(2)).sqrt();
        assert!(f.iter().enumerate().all(|(i, m)| (radius(i) <= 3.0) == (*m == [0.0; 4])));
        let mut truth: Vec<f32> = (0..k * k)
            .map(|i| {
                let r = (((i % k) as f32 - c).powi(2) + ((i / k) as f32 - c).powi(2)).sqrt();
                if r < 0.5 { 0.4 } else if r < 1.5 { 1.6 } else if r <= 11.0 { 1.0 } else { 0.0 }
            })
            .collect();
        let s: f32 = truth.iter().sum();
        truth.iter_mut().for_each(|v| *v /= s);
        let level = 1.0 / s;
        let mut r = Rng::new(5);
        let v: Vec<f32> = truth.iter().map(|&t| t + 0.05 * level * r.normal() as f32).collect();
        let run = |core: f32| {
            let (mut q, mut out) = (vec![0.0; tv_dual_len(k)], vec![0.0; k * k]);
            prox_tv_simplex(&v, &mut q, 0.4 * level, Some(&polar_tv_frames(k, [c, c], 0.25, core)), 1.0, k, 300, &mut out);
            out
        };
        let err = |x: &[f32], inner: bool| {
            let e: f64 = (0..k * k).filter(|&i| ((((i % k) as f32 - c).powi(2) + ((i / k) as f32 - c).powi(2)).sqrt() <= 2.0) == inner).map(|i| ((x[i] - truth[i]) as f64).powi(2)).sum();
            e.sqrt()
        };
        let (plain, released) = (run(0.0), run(3.0));
        assert!(err(&released, true) < 0.5 * err(&plain, true), "core: released {:.3e} vs polar {:.3e}", err(&released, true), err(&plain, true));
        assert!(err(&released, false) < 1.2 * err(&plain, false), "outside: released {:.3e} vs polar {:.3e}", err(&released, false), err(&plain, false));
    }

    #[test]
    fn tv_dual_projection_clips_pairs() {
        let mut y = vec![3.0, 0.1, 4.0, 0.1];
        project_tv_dual(&mut y, 1.0);
        assert!((y[0] - 0.6).abs() < 1e-6 && (y[2] - 0.8).abs() < 1e-6, "{y:?}");
        assert!((y[1] - 0.1).abs() < 1e-7 && (y[3] - 0.1).abs() < 1e-7);
    }
}
