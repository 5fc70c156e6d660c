//! Convolution with point-spread functions, by FFT, with explicit boundary handling.
//!
//! # PSF convention
//! A kernel is an odd-sized `k × k` [`Plane`] `K` with centre `c = (k - 1) / 2`; it acts as a
//! true convolution:
//!
//! `out(x, y) = Σ_{u,v} K[v][u] · img(x − (u − c), y − (v − c))`
//!
//! so `K[c][c]` is zero displacement and a kernel that is 1 at `(c + 1, c)` moves the image one
//! pixel to the right. [`convolve_direct`] is the naive oracle every FFT path is tested against.
//!
//! Images are padded by mirror reflection ([`crate::image::reflect_index`]) before the circular
//! FFT product, then cropped, so no wrap-around reaches the output.

use super::fft::{good_size, Fft2};
use super::operator::LinearOperator;
use crate::image::Plane;
use rustfft::num_complex::Complex32;
use std::sync::Arc;

/// Direct (O(N·k²)) convolution with mirror boundaries; the test oracle.
pub fn convolve_direct(img: &Plane, k: &Plane) -> Plane {
    let c = (k.width as isize - 1) / 2;
    let cy = (k.height as isize - 1) / 2;
    Plane::from_fn(img.width, img.height, |x, y| {
        let mut acc = 0.0f64;
        for v in 0..k.height {
            for u in 0..k.width {
                let kv = k.get(u, v);
                if kv != 0.0 {
                    acc += kv as f64 * img.get_reflect(x as isize - (u as isize - c), y as isize - (v as isize - cy)) as f64;
                }
            }
        }
        acc as f32
    })
}

/// Places a kernel into a `w × h` circular buffer with its centre at index (0, 0).
pub fn kernel_to_origin(k: &Plane, w: usize, h: usize) -> Vec<f32> {
    let c = (k.width - 1) / 2;
    let cy = (k.height - 1) / 2;
    let mut buf = vec![0.0; w * h];
    for v in 0..k.height {
        for u in 0..k.width {
            let x = (u as isize - c as isize).rem_euclid(w as isize) as usize;
            let y = (v as isize - cy as isize).rem_euclid(h as isize) as usize;
            buf[y * w + x] += k.get(u, v);
        }
    }
    buf
}

/// The index of every coefficient of a `k × k` kernel (row-major, centre = zero displacement)
/// in a row-major `w × h` circular buffer whose origin is the kernel centre (the layout of
/// [`kernel_to_origin`]).
pub fn kernel_origin_index(k: usize, w: usize, h: usize) -> Vec<usize> {
    let r = (k / 2) as isize;
    (0..k * k)
        .map(|i| {
            let (u, v) = ((i % k) as isize - r, (i / k) as isize - r);
            (v.rem_euclid(h as isize) as usize) * w + u.rem_euclid(w as isize) as usize
        })
        .collect()
}

/// Reads a `kw × kh` kernel back out of a circular buffer whose origin is the kernel centre
/// (the inverse of [`kernel_to_origin`] for kernels that fit).
pub fn kernel_from_origin(buf: &[f32], w: usize, h: usize, kw: usize, kh: usize) -> Plane {
    let c = (kw - 1) / 2;
    let cy = (kh - 1) / 2;
    Plane::from_fn(kw, kh, |u, v| {
        let x = (u as isize - c as isize).rem_euclid(w as isize) as usize;
        let y = (v as isize - cy as isize).rem_euclid(h as isize) as usize;
        buf[y * w + x]
    })
}

/// A kernel transformed once for a padded image size, applied to many images.
pub struct Convolver {
    fft: Arc<Fft2>,
    pad_x: usize,
    pad_y: usize,
    width: usize,
    height: usize,
    kspec: Vec<Complex32>,
}

impl Convolver {
    /// Prepares convolution of `width × height` images with `k` (mirror boundaries).
    pub fn new(k: &Plane, width: usize, height: usize) -> Self {
        let pad_x = k.width / 2 + 1;
        let pad_y = k.height / 2 + 1;
        let pw = good_size(width + 2 * pad_x);
        let ph = good_size(height + 2 * pad_y);
        let fft = Fft2::plan(pw, ph);
        let kspec = fft.forward(&kernel_to_origin(k, pw, ph));
        Self { fft, pad_x, pad_y, width, height, kspec }
    }

    /// `k * img` with mirror boundaries, the same size as `img`.
    ///
    /// # Panics
    /// When `img` is not the size the convolver was prepared for.
    pub fn apply(&self, img: &Plane) -> Plane {
        assert_eq!((img.width, img.height), (self.width, self.height), "convolver size");
        let (pw, ph) = (self.fft.width, self.fft.height);
        let padded = img.window_reflect(-(self.pad_x as isize), -(self.pad_y as isize), pw, ph);
        let mut spec = self.fft.forward(&padded.data);
        for (s, k) in spec.iter_mut().zip(&self.kspec) {
            *s *= k;
        }
        let full = self.fft.inverse(spec);
        Plane::from_fn(self.width, self.height, |x, y| full[(y + self.pad_y) * pw + x + self.pad_x])
    }
}

/// `k * img` with mirror boundaries (see the module docs for the convention).
pub fn convolve(img: &Plane, k: &Plane) -> Plane {
    Convolver::new(k, img.width, img.height).apply(img)
}

/// Circular convolution with a kernel on a periodic `width × height` domain (the solvers'
/// padded tiles): `A x = k ⊛ x`, `Aᵀ y = k ⋆ y` (correlation), one forward and one inverse FFT
/// each.
pub struct CircularConvolution {
    fft: Arc<Fft2>,
    spec: Vec<Complex32>,
}

impl CircularConvolution {
    /// Prepares convolution with `k` (centre at zero displacement) on a `width × height` torus.
    pub fn new(k: &Plane, width: usize, height: usize) -> Self {
        let fft = Fft2::plan(width, height);
        let spec = fft.forward(&kernel_to_origin(k, width, height));
        Self { fft, spec }
    }

    fn product(&self, x: &[f32], out: &mut [f32], conj: bool) {
        let mut s = self.fft.forward(x);
        for (a, k) in s.iter_mut().zip(&self.spec) {
            *a *= if conj { k.conj() } else { *k };
        }
        self.fft.inverse_into(&mut s, out);
    }
}

impl LinearOperator for CircularConvolution {
    fn input_len(&self) -> usize {
        self.fft.width * self.fft.height
    }
    fn output_len(&self) -> usize {
        self.fft.width * self.fft.height
    }
    fn apply(&self, x: &[f32], out: &mut [f32]) {
        self.product(x, out, false)
    }
    fn apply_adjoint(&self, y: &[f32], out: &mut [f32]) {
        self.product(y, out, true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn noise(w: usize, h: usize, seed: u64) -> Plane {
        let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        Plane::from_fn(w, h, |_, _| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 33) as f32) / (1u64 << 31) as f32
        })
    }

    #[test]
    fn shift_kernel_moves_right() {
        let img = Plane::from_fn(8, 6, |x, y| (x + 10 * y) as f32);
        let mut k = Plane::new(3, 3);
        k.set(2, 1, 1.0); // u - c = +1
        let out = convolve(&img, &k);
        assert!((out.get(4, 3) - img.get(3, 3)).abs() < 1e-4);
        let d = convolve_direct(&img, &k);
        assert!((d.get(4, 3) - img.get(3, 3)).abs() < 1e-6);
    }

    /// Away from the wrap band the circular convolution is the direct one.
    #[test]
    fn circular_matches_direct_inside() {
        let (w, h) = (24, 18);
        let img = noise(w, h, 3);
        let k = noise(5, 5, 4);
        let mut out = vec![0.0; w * h];
        CircularConvolution::new(&k, w, h).apply(&img.data, &mut out);
        let d = convolve_direct(&img, &k);
        for y in 2..h - 2 {
            for x in 2..w - 2 {
                assert!((out[y * w + x] - d.get(x, y)).abs() < 1e-4, "{x},{y}");
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        #[test]
        fn fft_convolution_matches_direct(w in 5usize..40, h in 5usize..40, kr in 0usize..6, seed in 0u64..1000) {
            let img = noise(w, h, seed);
            let k = noise(2 * kr + 1, 2 * kr + 1, seed + 7);
            let a = convolve(&img, &k);
            let b = convolve_direct(&img, &k);
            for (x, y) in a.data.iter().zip(&b.data) {
                prop_assert!((x - y).abs() < 2e-4 * (1.0 + y.abs()), "{x} vs {y}");
            }
        }
    }
}
