//! Resampling a plane through an affine (or projective) map about its centre: the one warp of
//! the crate.
//!
//! Output pixel `q` takes the value of `p` at `s = M·(q − c) + c + t` (`c` the plane's centre
//! `((w−1)/2, (h−1)/2)`, pixel values sampled at pixel centres), so the content moves by the
//! inverse of that map. A [`Projective`] map divides by `1 + g·(q − c)` first:
//! `s = (M·(q − c) + t) / (1 + g·(q − c)) + c`. Reads outside the plane are mirrored ([`super::reflect_index`]).
//! Two separable interpolators: Keys cubic (4 taps, a = −0.5, [`super::filter::keys_cubic`]) and
//! Lanczos-4 (8 taps, weights renormalised to sum 1). Weights and sums in `f64`.

use super::filter::keys_cubic;
use super::Plane;

/// The interpolation kernel of a [`warp`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    /// Keys cubic convolution, taps at offsets `−1..=2`.
    Keys,
    /// Lanczos with `a = 4`, taps at offsets `−3..=4`, renormalised.
    Lanczos4,
}

/// The Lanczos-4 window `sinc(t)·sinc(t/4)`: the definition [`Interpolation::weights`] computes
/// with five sines and cosines per axis.
#[cfg(test)]
fn lanczos4(t: f64) -> f64 {
    let t = t.abs();
    if t < 1e-9 {
        1.0
    } else if t >= 4.0 {
        0.0
    } else {
        let pt = std::f64::consts::PI * t;
        4.0 * pt.sin() * (pt / 4.0).sin() / (pt * pt)
    }
}

/// `(sin, cos)` of `πk/4` for `k = 0..8`.
const QUARTER_TURNS: [(f64, f64); 8] = {
    let r = std::f64::consts::FRAC_1_SQRT_2;
    [(0.0, 1.0), (r, r), (1.0, 0.0), (r, -r), (0.0, -1.0), (-r, -r), (-1.0, 0.0), (-r, r)]
};

impl Interpolation {
    /// Index of the first tap relative to `floor(s)` and the number of taps.
    fn taps(self) -> (isize, usize) {
        match self {
            Interpolation::Keys => (-1, 4),
            Interpolation::Lanczos4 => (-3, 8),
        }
    }

    /// Weights for the fractional position `f ∈ [0, 1)` (into `out[..n]`) and their sum
    /// (1 for Keys, which is not renormalised).
    fn weights(self, f: f64, out: &mut [f64; 8]) -> f64 {
        let (first, n) = self.taps();
        match self {
            Interpolation::Keys => {
                for (i, o) in out.iter_mut().enumerate().take(n) {
                    *o = keys_cubic(f - (i as isize + first) as f64);
                }
                1.0
            }
            Interpolation::Lanczos4 => {
                // tap `t = f + k` (integer `k`): `sin πt = (−1)^k sin πf` and
                // `sin(πt/4) = sin(πf/4)·cos(πk/4) + cos(πf/4)·sin(πk/4)`, so five sines and cosines per
                // axis instead of sixteen ([`lanczos4`] is the definition)
                let pi = std::f64::consts::PI;
                // (sin πf from the nearer end: `1 − f` is exact, so no cancellation near 1)
                let s = if f > 0.5 { (pi * (1.0 - f)).sin() } else { (pi * f).sin() };
                let (sq, cq) = (pi * f / 4.0).sin_cos();
                for (i, o) in out.iter_mut().enumerate().take(n) {
                    let k = -(i as isize + first);
                    let t = f + k as f64;
                    *o = if t.abs() < 1e-9 {
                        1.0
                    } else if t.abs() >= 4.0 {
                        0.0
                    } else {
                        let (sk, ck) = QUARTER_TURNS[k.rem_euclid(8) as usize];
                        let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
                        let pt = pi * t;
                        // near t = 0 the sum below cancels: the sine of the tap itself
                        let s4 = if t.abs() < 1.0 { (pt / 4.0).sin() } else { sq * ck + cq * sk };
                        4.0 * sign * s * s4 / (pt * pt)
                    };
                }
                out[..n].iter().sum()
            }
        }
    }
}

/// An affine map about the plane's centre: `s = matrix·(q − c) + c + shift` (row-major 2×2).
#[derive(Clone, Copy, Debug)]
pub struct Affine {
    pub matrix: [f64; 4],
    pub shift: [f64; 2],
}

/// One sample of `p` at `(x, y)` and the white-noise variance factor `Σw²` of its weights.
fn sample(p: &Plane, x: f64, y: f64, interp: Interpolation) -> (f32, f64) {
    let (first, n) = interp.taps();
    let (x0, y0) = (x.floor(), y.floor());
    let (mut wx, mut wy) = ([0.0f64; 8], [0.0f64; 8]);
    let sxw = interp.weights(x - x0, &mut wx);
    let syw = interp.weights(y - y0, &mut wy);
    let mut acc = 0.0;
    for (j, wyj) in wy[..n].iter().enumerate() {
        let mut row = 0.0;
        for (i, wxi) in wx[..n].iter().enumerate() {
            row += wxi * p.get_reflect(x0 as isize + i as isize + first, y0 as isize + j as isize + first) as f64;
        }
        acc += wyj * row;
    }
    let q = wx[..n].iter().map(|v| v * v).sum::<f64>() * wy[..n].iter().map(|v| v * v).sum::<f64>() / (sxw * sxw * syw * syw);
    ((acc / (sxw * syw)) as f32, q)
}

/// A projective map about the plane's centre: `s = (matrix·d + shift) / (1 + perspective·d) + c`
/// with `d = q − c` (module docs); a zero `perspective` is the [`Affine`] map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Projective {
    pub matrix: [f64; 4],
    pub shift: [f64; 2],
    /// `[g, h]`, per pixel.
    pub perspective: [f64; 2],
}

impl From<Affine> for Projective {
    fn from(a: Affine) -> Self {
        Self { matrix: a.matrix, shift: a.shift, perspective: [0.0, 0.0] }
    }
}

impl Projective {
    /// The inverse map (`shift` must be zero: the maps the crate inverts are about the centre):
    /// `d = M⁻¹·s' / (1 − g·M⁻¹·s')` for `s' = s − c`. `None` when `M` is singular or `shift`
    /// is not zero.
    pub fn inverse(&self) -> Option<Projective> {
        let m = self.matrix;
        let det = m[0] * m[3] - m[1] * m[2];
        if det.abs() < 1e-12 || self.shift != [0.0, 0.0] {
            return None;
        }
        let inv = [m[3] / det, -m[1] / det, -m[2] / det, m[0] / det];
        let [g, h] = self.perspective;
        Some(Projective { matrix: inv, shift: [0.0, 0.0], perspective: [-(g * inv[0] + h * inv[2]), -(g * inv[1] + h * inv[3])] })
    }
}

/// Resamples `p` through `map` (see the module docs); also returns, per pixel, `Σw²` of the
/// interpolation weights (the factor on white noise's variance).
pub fn warp_with_variance(p: &Plane, map: &Affine, interp: Interpolation) -> (Plane, Plane) {
    warp_projective_with_variance(p, &Projective::from(*map), interp)
}

/// [`warp_with_variance`] through a [`Projective`] map.
pub fn warp_projective_with_variance(p: &Plane, map: &Projective, interp: Interpolation) -> (Plane, Plane) {
    warp_projective_where(p, map, interp, None)
}

/// [`warp_projective_with_variance`] at the output pixels where `need` is true (every pixel
/// with `None`), value and `Σw²` 0 elsewhere; rows in parallel. The same values where computed.
pub fn warp_projective_where(p: &Plane, map: &Projective, interp: Interpolation, need: Option<&[bool]>) -> (Plane, Plane) {
    use rayon::prelude::*;
    let w = p.width;
    let mut out = Plane::new(p.width, p.height);
    let mut wsq = Plane::new(p.width, p.height);
    if w == 0 {
        return (out, wsq);
    }
    out.data.par_chunks_mut(w).zip(wsq.data.par_chunks_mut(w)).enumerate().for_each(|(y, (orow, qrow))| {
        super::for_needed(orow, super::mask_row(need, y, w), |x, o| {
            let (sx, sy) = map.source(x, y, w, p.height);
            let (v, q) = sample(p, sx, sy, interp);
            *o = v;
            qrow[x] = q as f32;
        });
    });
    (out, wsq)
}

impl Projective {
    /// The source position `s` of output pixel `(x, y)` in a `width × height` plane (about its
    /// centre, the module docs' convention).
    pub fn source(&self, x: usize, y: usize, width: usize, height: usize) -> (f64, f64) {
        let (cx, cy) = ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
        let m = self.matrix;
        let [g, h] = self.perspective;
        let (dx, dy) = (x as f64 - cx, y as f64 - cy);
        let den = 1.0 + g * dx + h * dy;
        ((m[0] * dx + m[1] * dy + self.shift[0]) / den + cx, (m[2] * dx + m[3] * dy + self.shift[1]) / den + cy)
    }
}

/// Resamples `p` through `map` (see the module docs).
pub fn warp(p: &Plane, map: &Affine, interp: Interpolation) -> Plane {
    warp_with_variance(p, map, interp).0
}

/// One bicubic (Keys) sample at real coordinates, mirror boundaries.
pub fn sample_bicubic(p: &Plane, x: f64, y: f64) -> f32 {
    sample(p, x, y, Interpolation::Keys).0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The weights from three sines equal the window's definition at every tap.
    #[test]
    fn lanczos_weights_match_the_window() {
        let mut out = [0.0f64; 8];
        for j in 0..=200 {
            let f = j as f64 / 200.0 * 0.999_999;
            let sum = Interpolation::Lanczos4.weights(f, &mut out);
            let mut want = 0.0;
            for (i, o) in out.iter().enumerate() {
                let d = lanczos4(f - (i as isize - 3) as f64);
                want += d;
                assert!((o - d).abs() < 1e-12, "f {f}, tap {i}: {o} vs {d}");
            }
            assert!((sum - want).abs() < 1e-12);
        }
    }

    fn ramp(w: usize, h: usize) -> Plane {
        Plane::from_fn(w, h, |x, y| 0.01 * x as f32 + 0.02 * y as f32)
    }

    /// Both interpolators reproduce a linear ramp inside the plane under a shift and a
    /// rotation (Lanczos-4 to 1e-3), and the identity is exact at pixel centres.
    #[test]
    fn warps_reproduce_a_ramp() {
        let p = ramp(40, 30);
        let id = Affine { matrix: [1.0, 0.0, 0.0, 1.0], shift: [0.0, 0.0] };
        let (th, s) = (0.1f64, 1.02f64);
        let rot = Affine { matrix: [s * th.cos(), -s * th.sin(), s * th.sin(), s * th.cos()], shift: [1.3, -0.7] };
        for interp in [Interpolation::Keys, Interpolation::Lanczos4] {
            let (out, q) = warp_with_variance(&p, &id, interp);
            assert!(out.data.iter().zip(&p.data).all(|(a, b)| (a - b).abs() < 1e-6), "{interp:?}");
            assert!(q.data.iter().all(|v| (v - 1.0).abs() < 1e-6));
            let out = warp(&p, &rot, interp);
            let (cx, cy) = (19.5, 14.5);
            for &(x, y) in &[(15usize, 12usize), (20, 15), (25, 18)] {
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                let sx = rot.matrix[0] * dx + rot.matrix[1] * dy + cx + 1.3;
                let sy = rot.matrix[2] * dx + rot.matrix[3] * dy + cy - 0.7;
                let want = 0.01 * sx + 0.02 * sy;
                // Keys reproduces linear functions; renormalised Lanczos-4 nearly
                let tol = if interp == Interpolation::Keys { 1e-5 } else { 1e-3 };
                assert!((out.get(x, y) as f64 - want).abs() < tol, "{interp:?} at {x},{y}: {} vs {want}", out.get(x, y));
            }
        }
        // a half-pixel shift averages white noise: Σw² < 1
        let half = Affine { matrix: [1.0, 0.0, 0.0, 1.0], shift: [0.5, 0.0] };
        let (_, q) = warp_with_variance(&p, &half, Interpolation::Lanczos4);
        assert!(q.get(20, 15) < 0.9, "{}", q.get(20, 15));
    }

    /// The masked, row-parallel warp has the whole warp's bits on the needed pixels (value and
    /// `Σw²`) and 0 elsewhere; `Projective::source` is the map the warp samples at.
    #[test]
    fn masked_warp_is_the_warp_where_needed() {
        let map = Projective { matrix: [1.002, -0.003, 0.003, 1.002], shift: [0.7, -0.4], perspective: [1e-4, -2e-4] };
        let p = Plane::from_fn(83, 57, |x, y| ((x as f32 * 0.3).sin() + (y as f32 * 0.2).cos()) * 0.5 + 1.0);
        let need: Vec<bool> = (0..83 * 57).map(|i| (i * 7919) % 3 != 0).collect();
        let (v, q) = warp_projective_with_variance(&p, &map, Interpolation::Lanczos4);
        let (vm, qm) = warp_projective_where(&p, &map, Interpolation::Lanczos4, Some(&need));
        for i in 0..83 * 57 {
            let (a, b) = if need[i] { (v.data[i], q.data[i]) } else { (0.0, 0.0) };
            assert_eq!((vm.data[i].to_bits(), qm.data[i].to_bits()), (a.to_bits(), b.to_bits()), "pixel {i}");
        }
        let (sx, sy) = map.source(10, 20, 83, 57);
        assert_eq!(v.get(10, 20), sample(&p, sx, sy, Interpolation::Lanczos4).0);
    }

    /// A projective warp followed by its inverse returns the (smooth) plane; the inverse's
    /// composition with the map is the identity on points.
    #[test]
    fn projective_inverse_round_trip() {
        let map = Projective { matrix: [1.003, -0.004, 0.004, 1.003], shift: [0.0, 0.0], perspective: [2e-4, -1.5e-4] };
        let inv = map.inverse().unwrap();
        let apply = |m: &Projective, d: (f64, f64)| {
            let den = 1.0 + m.perspective[0] * d.0 + m.perspective[1] * d.1;
            ((m.matrix[0] * d.0 + m.matrix[1] * d.1) / den, (m.matrix[2] * d.0 + m.matrix[3] * d.1) / den)
        };
        for d in [(40.0, -30.0), (-60.0, 25.0), (0.0, 0.0)] {
            let back = apply(&inv, apply(&map, d));
            assert!((back.0 - d.0).abs() < 1e-9 && (back.1 - d.1).abs() < 1e-9, "{d:?} -> {back:?}");
        }
        let p = Plane::from_fn(96, 64, |x, y| ((x as f32 * 0.21).sin() * (y as f32 * 0.17).cos()) + 1.0);
        let there = warp_projective_with_variance(&p, &map, Interpolation::Lanczos4).0;
        let back = warp_projective_with_variance(&there, &inv, Interpolation::Lanczos4).0;
        let mut worst = 0.0f32;
        for y in 12..52 {
            for x in 12..84 {
                worst = worst.max((back.get(x, y) - p.get(x, y)).abs());
            }
        }
        assert!(worst < 2e-3, "round trip error {worst}");
        assert!(Projective { shift: [1.0, 0.0], ..map }.inverse().is_none());
    }
}
