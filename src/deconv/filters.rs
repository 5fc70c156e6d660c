//! The derivative filters `H_1..H_5` (dx, dy, dxx, dyy, dxy) of the deconvolution prior and
//! their adjoints, on a **periodic** `width × height` domain (the solver's FFT domain, whose
//! outer band is cropped away, so the wrap never reaches the output).
//!
//! Stencils (row-major, `x` right, `y` down, indices taken modulo the size):
//! - `dx(i)  = i[x+1] − i[x]`,        `dy(i) = i[y+1] − i[y]`
//! - `dxx(i) = i[x+1] − 2 i[x] + i[x−1]`, `dyy` likewise (self-adjoint)
//! - `dxy(i) = i[x+1,y+1] − i[x+1,y] − i[x,y+1] + i[x,y]`

/// Which derivative.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Derivative {
    Dx,
    Dy,
    Dxx,
    Dyy,
    Dxy,
}

/// All five, in the order of docs/method.md (`H_1..H_5`).
pub const ALL: [Derivative; 5] = [Derivative::Dx, Derivative::Dy, Derivative::Dxx, Derivative::Dyy, Derivative::Dxy];
/// The first-order pair used by the cross-channel and dark-region terms (`H_1, H_2`).
pub const FIRST: [Derivative; 2] = [Derivative::Dx, Derivative::Dy];

/// `o[x] = a[x+1] − a[x]` (periodic), scaled by `s` and added when `add`.
#[inline]
fn forward_diff(a: &[f32], o: &mut [f32], s: f32, add: bool) {
    let w = a.len();
    for x in 0..w - 1 {
        let d = a[x + 1] - a[x];
        o[x] = if add { o[x] + s * d } else { d };
    }
    let d = a[0] - a[w - 1];
    o[w - 1] = if add { o[w - 1] + s * d } else { d };
}

/// `o[x] += s (a[x−1] − a[x])` (periodic): the adjoint of [`forward_diff`].
#[inline]
fn backward_diff_add(a: &[f32], o: &mut [f32], s: f32) {
    let w = a.len();
    o[0] += s * (a[w - 1] - a[0]);
    for x in 1..w {
        o[x] += s * (a[x - 1] - a[x]);
    }
}

/// `o[x] = a[x+1] − 2a[x] + a[x−1]` (periodic), scaled by `s` and added when `add`.
#[inline]
fn second_diff(a: &[f32], o: &mut [f32], s: f32, add: bool) {
    let w = a.len();
    let at = |x: usize, l: f32, r: f32| l - 2.0 * a[x] + r;
    let first = at(0, a[w - 1], a[if w > 1 { 1 } else { 0 }]);
    let last = at(w - 1, a[w.saturating_sub(2)], a[0]);
    for x in 1..w.saturating_sub(1) {
        let d = a[x + 1] - 2.0 * a[x] + a[x - 1];
        o[x] = if add { o[x] + s * d } else { d };
    }
    o[0] = if add { o[0] + s * first } else { first };
    if w > 1 {
        o[w - 1] = if add { o[w - 1] + s * last } else { last };
    }
}

/// Row `y` of a periodic `w × h` array with the rows below and above it.
fn periodic_rows(v: &[f32], w: usize, h: usize, y: usize) -> (&[f32], &[f32], &[f32]) {
    let yn = if y + 1 == h { 0 } else { y + 1 };
    let yp = if y == 0 { h - 1 } else { y - 1 };
    (&v[y * w..(y + 1) * w], &v[yn * w..(yn + 1) * w], &v[yp * w..(yp + 1) * w])
}

/// Calls `f(row, below, above, out_row, tmp)` for every row of a periodic `w × h` array: the
/// shared loop of [`apply`] and [`add_adjoint`]; `tmp` is a `w`-long scratch row (`Dxy` only).
fn for_each_row(d: Derivative, v: &[f32], w: usize, h: usize, out: &mut [f32], mut f: impl FnMut(&[f32], &[f32], &[f32], &mut [f32], &mut [f32])) {
    debug_assert_eq!(v.len(), w * h);
    let mut tmp = if d == Derivative::Dxy { vec![0.0; w] } else { Vec::new() };
    for y in 0..h {
        let (row, rown, rowp) = periodic_rows(v, w, h, y);
        f(row, rown, rowp, &mut out[y * w..(y + 1) * w], &mut tmp);
    }
}

/// `out = H v` (overwrites `out`).
pub fn apply(d: Derivative, v: &[f32], w: usize, h: usize, out: &mut [f32]) {
    for_each_row(d, v, w, h, out, |row, rown, rowp, o, tmp| {
        match d {
            Derivative::Dx => forward_diff(row, o, 1.0, false),
            Derivative::Dy => o.iter_mut().zip(rown).zip(row).for_each(|((o, n), c)| *o = n - c),
            Derivative::Dxx => second_diff(row, o, 1.0, false),
            Derivative::Dyy => {
                for x in 0..w {
                    o[x] = rown[x] - 2.0 * row[x] + rowp[x];
                }
            }
            Derivative::Dxy => {
                tmp.iter_mut().zip(rown).zip(row).for_each(|((t, n), c)| *t = n - c);
                forward_diff(tmp, o, 1.0, false);
            }
        }
    });
}

/// `out += s · Hᵀ v`.
pub fn add_adjoint(d: Derivative, v: &[f32], w: usize, h: usize, s: f32, out: &mut [f32]) {
    for_each_row(d, v, w, h, out, |row, rown, rowp, o, tmp| {
        match d {
            // (Dxᵀ v)[x] = v[x−1] − v[x]
            Derivative::Dx => backward_diff_add(row, o, s),
            Derivative::Dy => o.iter_mut().zip(rowp).zip(row).for_each(|((o, p), c)| *o += s * (p - c)),
            Derivative::Dxx => second_diff(row, o, s, true),
            Derivative::Dyy => {
                for x in 0..w {
                    o[x] += s * (rown[x] - 2.0 * row[x] + rowp[x]);
                }
            }
            // Dxy = Dx∘Dy, so Dxyᵀ = Dyᵀ∘Dxᵀ: e = v[y−1] − v[y], then e[x−1] − e[x]
            Derivative::Dxy => {
                tmp.iter_mut().zip(rowp).zip(row).for_each(|((t, p), c)| *t = p - c);
                backward_diff_add(tmp, o, s);
            }
        }
    });
}

/// The squared operator norm of each filter (largest `|Ĥ|²`): 4, 4, 16, 16, 16.
pub fn norm_squared(d: Derivative) -> f32 {
    match d {
        Derivative::Dx | Derivative::Dy => 4.0,
        _ => 16.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        /// <H x, y> = <x, Hᵀ y> for every filter.
        #[test]
        fn adjoints_are_adjoint(w in 2usize..12, h in 2usize..12, seed in 0u32..10_000) {
            let gen = |k: u32| -> Vec<f32> {
                (0..w * h).map(|i| (((i as u32).wrapping_mul(2654435761).wrapping_add(seed.wrapping_mul(k)) >> 8) % 1000) as f32 / 500.0 - 1.0).collect()
            };
            let (xv, yv) = (gen(7), gen(13));
            for d in ALL {
                let mut hx = vec![0.0; w * h];
                apply(d, &xv, w, h, &mut hx);
                let mut hty = vec![0.0; w * h];
                add_adjoint(d, &yv, w, h, 1.0, &mut hty);
                let a: f64 = hx.iter().zip(&yv).map(|(p, q)| (*p as f64) * (*q as f64)).sum();
                let b: f64 = xv.iter().zip(&hty).map(|(p, q)| (*p as f64) * (*q as f64)).sum();
                prop_assert!((a - b).abs() < 1e-3 * (1.0 + a.abs()), "{d:?}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn derivatives_of_a_ramp() {
        let (w, h) = (6, 5);
        let v: Vec<f32> = (0..w * h).map(|i| ((i % w) * (i % w) + 3 * (i / w)) as f32).collect();
        let mut o = vec![0.0; w * h];
        apply(Derivative::Dx, &v, w, h, &mut o);
        assert_eq!(o[2 * w + 2], 5.0); // 9 − 4
        apply(Derivative::Dxx, &v, w, h, &mut o);
        assert_eq!(o[2 * w + 2], 2.0);
        apply(Derivative::Dy, &v, w, h, &mut o);
        assert_eq!(o[w + 3], 3.0);
        apply(Derivative::Dxy, &v, w, h, &mut o);
        assert_eq!(o[w + 3], 0.0);
    }
}
