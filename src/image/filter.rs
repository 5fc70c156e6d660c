//! Linear filters on image planes, one implementation each: the Keys cubic kernel and the
//! separable Gaussian blur (mirror or periodic boundaries), directly or, for long taps, through
//! the FFT ([`filter_separable_fft`], [`gaussian_blur_wide`]).
//!
//! # Conventions
//! `σ` in pixels; the Gaussian's taps cover `±max(⌈3σ⌉, min_radius)` and are normalised to sum 1
//! (computed in `f64`, applied in `f32`). The horizontal pass runs first; each output pixel
//! sums its taps in ascending offset order. Mirror boundaries reflect about the edge pixels'
//! outer edges ([`super::reflect_index`]); periodic boundaries wrap (the solvers' tile domains).

use super::{reflect_index, Plane};
use rayon::prelude::*;

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
    let (r, n) = ((taps.len() / 2) as isize, taps.len());
    // rows in parallel; a pixel whose taps stay inside its row reads the row slice directly
    let mut tmp = vec![0.0f32; w * h];
    tmp.par_chunks_mut(w.max(1)).enumerate().for_each(|(y, row)| {
        let src = &v[y * w..(y + 1) * w];
        for (x, o) in row.iter_mut().enumerate() {
            let lo = x as isize - r;
            let mut a = 0.0;
            if lo >= 0 && lo as usize + n <= w {
                for (t, s) in taps.iter().zip(&src[lo as usize..lo as usize + n]) {
                    a += t * s;
                }
            } else {
                for (k, t) in taps.iter().enumerate() {
                    a += t * src[boundary.index(lo + k as isize, w)];
                }
            }
            *o = a;
        }
    });
    // columns: each output row accumulates whole source rows, taps in ascending order (the same
    // sum, term by term, as a per-pixel loop)
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w.max(1)).enumerate().for_each(|(y, row)| {
        for (k, t) in taps.iter().enumerate() {
            let sy = boundary.index(y as isize + k as isize - r, h);
            for (o, s) in row.iter_mut().zip(&tmp[sy * w..(sy + 1) * w]) {
                *o += t * s;
            }
        }
    });
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

/// Taps at or below this radius are applied directly by [`gaussian_blur_wide`]; longer ones
/// through the FFT ([`filter_separable_fft`]), whose cost does not grow with the radius.
pub const DIRECT_MAX_RADIUS: usize = 24;

/// [`gaussian_blur`] for any width: the same taps and mirror boundary, applied directly up to
/// [`DIRECT_MAX_RADIUS`] and through the FFT above it (the same sums up to `f32` rounding; a
/// halo of `σ` = a quarter of a 1024 × 768 diagonal has 1 845 taps per pass).
pub fn gaussian_blur_wide(p: &Plane, sigma: f64) -> Plane {
    if sigma <= 0.0 {
        return p.clone();
    }
    let taps = gaussian_taps(sigma, 0);
    let data = if taps.len() / 2 <= DIRECT_MAX_RADIUS {
        filter_separable(&p.data, p.width, p.height, &taps, Boundary::Mirror)
    } else {
        filter_separable_fft(&p.data, p.width, p.height, &taps, Boundary::Mirror)
    };
    Plane { width: p.width, height: p.height, data }
}

/// [`filter_separable`] through the FFT, one line at a time: each row, then each column,
/// extended to one period of its boundary (`2n` mirrored, [`super::reflect_index`]'s period;
/// `n` periodic), circularly convolved with the taps wrapped onto that period
/// (`K[(r − i) mod L] += taps[i]`) by a real FFT, then cropped. Equal to the direct filter for
/// taps of any length, up to `f32` rounding; `O(log n)` per pixel instead of `2·len(taps)`, with
/// lines in parallel and one line's buffers per thread (a 2-D transform of the `2w × 2h`
/// extension would hold 16 times the plane).
pub fn filter_separable_fft(v: &[f32], w: usize, h: usize, taps: &[f32], boundary: Boundary) -> Vec<f32> {
    let rows = convolve_lines_fft(v, w, h, taps, boundary);
    let cols = convolve_lines_fft(&transpose(&rows, w, h), h, w, taps, boundary);
    transpose(&cols, h, w)
}

/// `count` lines of `n` values each (row-major), each convolved with `taps` under `boundary`
/// through a real FFT of the boundary's period ([`filter_separable_fft`]).
fn convolve_lines_fft(v: &[f32], n: usize, count: usize, taps: &[f32], boundary: Boundary) -> Vec<f32> {
    let l = match boundary {
        Boundary::Mirror => 2 * n,
        Boundary::Periodic => n,
    };
    let mut out = vec![0.0f32; n * count];
    if n == 0 || count == 0 {
        return out;
    }
    let mut planner = realfft::RealFftPlanner::<f32>::new();
    let (fwd, inv) = (planner.plan_fft_forward(l), planner.plan_fft_inverse(l));
    let r = (taps.len() / 2) as isize;
    let mut wrapped = vec![0.0f64; l];
    for (i, t) in taps.iter().enumerate() {
        wrapped[(r - i as isize).rem_euclid(l as isize) as usize] += *t as f64;
    }
    // the kernel's spectrum with the inverse's 1/L folded in
    let mut kt: Vec<f32> = wrapped.iter().map(|&k| (k / l as f64) as f32).collect();
    let mut kspec = fwd.make_output_vec();
    fwd.process(&mut kt, &mut kspec).expect("a real FFT of its own plan's length");
    out.par_chunks_mut(n).enumerate().for_each_init(
        || (fwd.make_input_vec(), fwd.make_output_vec(), fwd.make_scratch_vec(), inv.make_scratch_vec()),
        |(buf, spec, s_fwd, s_inv), (y, o)| {
            let line = &v[y * n..(y + 1) * n];
            for (i, b) in buf.iter_mut().enumerate() {
                *b = line[boundary.index(i as isize, n)];
            }
            fwd.process_with_scratch(buf, spec, s_fwd).expect("a real FFT of its own plan's length");
            spec.iter_mut().zip(&kspec).for_each(|(a, k)| *a *= k);
            // a real kernel's spectrum keeps the DC (and Nyquist) bins real; the inverse checks
            spec[0].im = 0.0;
            if l % 2 == 0 {
                let last = spec.len() - 1;
                spec[last].im = 0.0;
            }
            inv.process_with_scratch(spec, buf, s_inv).expect("a real inverse FFT of its own plan's length");
            o.copy_from_slice(&buf[..n]);
        },
    );
    out
}

/// The `h × w` transpose of a row-major `w × h` array.
fn transpose(v: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut t = vec![0.0f32; w * h];
    t.par_chunks_mut(h.max(1)).enumerate().for_each(|(x, col)| {
        for (y, o) in col.iter_mut().enumerate() {
            *o = v[y * w + x];
        }
    });
    t
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

    /// The definition: per output pixel, taps in ascending offset order, x then y.
    fn filter_direct(v: &[f32], w: usize, h: usize, taps: &[f32], b: Boundary) -> Vec<f32> {
        let r = (taps.len() / 2) as isize;
        let tmp: Vec<f32> = (0..w * h).map(|i| taps.iter().enumerate().fold(0.0, |a, (k, t)| a + t * v[(i / w) * w + b.index((i % w) as isize + k as isize - r, w)])).collect();
        (0..w * h).map(|i| taps.iter().enumerate().fold(0.0, |a, (k, t)| a + t * tmp[b.index((i / w) as isize + k as isize - r, h) * w + i % w])).collect()
    }

    #[test]
    fn separable_filter_equals_its_definition_bit_for_bit() {
        let (w, h) = (37, 23);
        let v: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 101) as f32 / 101.0).collect();
        // short taps (interior fast path and edges) and taps longer than the plane (all edges)
        for taps in [gaussian_taps(1.3, 0), gaussian_taps(9.0, 0)] {
            for b in [Boundary::Mirror, Boundary::Periodic] {
                assert_eq!(filter_separable(&v, w, h, &taps, b), filter_direct(&v, w, h, &taps, b), "{} taps, {b:?}", taps.len());
            }
        }
    }

    /// The FFT path equals the direct filter (to `f32` rounding) for short taps, taps longer
    /// than the plane (several reflections) and both boundaries, on odd and even sizes.
    #[test]
    fn fft_filter_matches_the_direct_one() {
        for (w, h) in [(37usize, 23usize), (40, 30)] {
            let v: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 101) as f32 / 101.0).collect();
            for taps in [gaussian_taps(1.3, 0), gaussian_taps(9.0, 0), gaussian_taps(31.0, 0)] {
                for b in [Boundary::Mirror, Boundary::Periodic] {
                    let (d, f) = (filter_separable(&v, w, h, &taps, b), filter_separable_fft(&v, w, h, &taps, b));
                    let worst = d.iter().zip(&f).map(|(a, c)| (a - c).abs()).fold(0.0f32, f32::max);
                    assert!(worst < 2e-6, "{w}x{h}, {} taps, {b:?}: {worst}", taps.len());
                }
            }
        }
        let p = Plane { width: 40, height: 30, data: (0..1200).map(|i| ((i * 31) % 17) as f32).collect() };
        for sigma in [2.0, 12.0] {
            let (a, b) = (gaussian_blur(&p, sigma), gaussian_blur_wide(&p, sigma));
            assert!(a.data.iter().zip(&b.data).all(|(x, y)| (x - y).abs() < 2e-5), "σ {sigma}");
        }
    }

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
