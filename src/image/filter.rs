//! Linear filters on image planes, one implementation each: the Keys cubic kernel and the
//! separable Gaussian blur (mirror or periodic boundaries).
//!
//! # Conventions
//! `σ` in pixels; the Gaussian's taps cover `±max(⌈3σ⌉, min_radius)` and are normalised to sum 1
//! (computed in `f64`, applied in `f32`). The horizontal pass runs first; each output pixel
//! sums its taps in ascending offset order. Mirror boundaries reflect about the edge pixels'
//! outer edges ([`super::reflect_index`]); periodic boundaries wrap (the solvers' tile domains).

use super::{reflect_index, Plane};

/// Keys cubic convolution weight (a = −0.5): the interpolation kernel of
/// [`super::resample`]'s bicubic warp and the antialiasing filter of the deconvolution's
/// scale space.
pub fn keys_cubic(t: f64) -> f64 {
    let t = t.abs();
    if t < 1.0 {
        1.5 * t * t * t - 2.5 * t * t + 1.0
    } else if t < 2.0 {
        -0.5 * t * t * t + 2.5 * t * t - 4.0 * t + 2.0
    } else {
        0.0
    }
}

/// How a filter reads outside the plane.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Boundary {
    Mirror,
    Periodic,
}

impl Boundary {
    fn index(self, i: isize, n: usize) -> usize {
        match self {
            Boundary::Mirror => reflect_index(i, n),
            Boundary::Periodic => i.rem_euclid(n as isize) as usize,
        }
    }
}

/// Normalised Gaussian taps for `σ > 0`, offsets `−r..=r` with `r = max(⌈3σ⌉, min_radius)`.
pub fn gaussian_taps(sigma: f64, min_radius: usize) -> Vec<f32> {
    let r = ((3.0 * sigma).ceil() as isize).max(min_radius as isize);
    let wts: Vec<f64> = (-r..=r).map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp()).collect();
    let s: f64 = wts.iter().sum();
    wts.iter().map(|w| (w / s) as f32).collect()
}

/// Separable filtering of a row-major `w × h` array with the odd-length `taps` (centre = zero
/// offset) along x, then along y.
pub fn filter_separable(v: &[f32], w: usize, h: usize, taps: &[f32], boundary: Boundary) -> Vec<f32> {
    let r = (taps.len() / 2) as isize;
    let mut tmp = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut a = 0.0;
            for (k, t) in taps.iter().enumerate() {
                a += t * v[y * w + boundary.index(x as isize + k as isize - r, w)];
            }
            tmp[y * w + x] = a;
        }
    }
    let mut out = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut a = 0.0;
            for (k, t) in taps.iter().enumerate() {
                a += t * tmp[boundary.index(y as isize + k as isize - r, h) * w + x];
            }
            out[y * w + x] = a;
        }
    }
    out
}

/// Separable Gaussian blur with mirror boundaries (support `±⌈3σ⌉`); `σ ≤ 0` copies.
pub fn gaussian_blur(p: &Plane, sigma: f64) -> Plane {
    if sigma <= 0.0 {
        return p.clone();
    }
    let data = filter_separable(&p.data, p.width, p.height, &gaussian_taps(sigma, 0), Boundary::Mirror);
    Plane { width: p.width, height: p.height, data }
}

/// Separable Gaussian blur of a periodic `w × h` array (support `±max(⌈3σ⌉, 1)`, `σ > 0`).
pub fn gaussian_blur_periodic(v: &[f32], w: usize, h: usize, sigma: f32) -> Vec<f32> {
    filter_separable(v, w, h, &gaussian_taps(sigma as f64, 1), Boundary::Periodic)
}

/// A `k × k` Gaussian spot of width `sigma` (px), integrated over each pixel (5 × 5 samples),
/// with its centre `(ox, oy)` px from the centre pixel, normalised to sum 1: a test and
/// benchmark PSF with a known centroid and blur.
pub fn pixel_gaussian(k: usize, sigma: f64, ox: f64, oy: f64) -> Plane {
    let c = (k as f64 - 1.0) / 2.0;
    let mut p = Plane::from_fn(k, k, |x, y| {
        let mut s = 0.0;
        for j in 0..5 {
            for i in 0..5 {
                let xx = x as f64 - 0.4 + 0.2 * i as f64 - c - ox;
                let yy = y as f64 - 0.4 + 0.2 * j as f64 - c - oy;
                s += (-(xx * xx + yy * yy) / (2.0 * sigma * sigma)).exp();
            }
        }
        s as f32
    });
    let t = p.sum() as f32;
    p.scale(1.0 / t);
    p
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_interpolates_and_sums_to_one() {
        assert_eq!(keys_cubic(0.0), 1.0);
        assert_eq!(keys_cubic(1.0), 0.0);
        assert_eq!(keys_cubic(2.5), 0.0);
        for f in [0.1, 0.37, 0.5, 0.9] {
            let s: f64 = (-1..=2).map(|i| keys_cubic(f - i as f64)).sum();
            assert!((s - 1.0).abs() < 1e-12, "{s}");
        }
    }

    /// Both boundaries keep a constant; mirror and periodic agree away from the edges; the
    /// blur of a centred impulse has variance σ².
    #[test]
    fn gaussian_blur_boundaries_and_width() {
        let (w, h) = (31, 29);
        let flat = Plane::filled(w, h, 0.3);
        assert!(gaussian_blur(&flat, 2.0).data.iter().all(|v| (v - 0.3).abs() < 1e-6));
        assert!(gaussian_blur_periodic(&flat.data, w, h, 2.0).iter().all(|v| (v - 0.3).abs() < 1e-6));
        let mut delta = Plane::new(w, h);
        delta.set(15, 14, 1.0);
        let (m, p) = (gaussian_blur(&delta, 1.5), gaussian_blur_periodic(&delta.data, w, h, 1.5));
        assert!(m.data.iter().zip(&p).all(|(a, b)| (a - b).abs() < 1e-7));
        let var: f64 = (0..w).map(|x| m.data[14 * w + x] as f64 * ((x as f64 - 15.0).powi(2))).sum::<f64>() / (0..w).map(|x| m.data[14 * w + x] as f64).sum::<f64>();
        assert!((var - 2.25).abs() < 0.05, "{var}");
        // mirror reflects, periodic wraps: an impulse at the left edge differs
        let mut edge = Plane::new(w, h);
        edge.set(0, 14, 1.0);
        let (m, p) = (gaussian_blur(&edge, 1.5), gaussian_blur_periodic(&edge.data, w, h, 1.5));
        assert!(m.data[14 * w + w - 1] == 0.0 && p[14 * w + w - 1] > 0.05);
    }
}
