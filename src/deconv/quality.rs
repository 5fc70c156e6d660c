//! Image quality measures for the deblur benchmarks, on linear values in `[0, 1]` (peak 1).
//!
//! - **PSNR** ([`psnr`]): `10 log₁₀(1 / MSE)` dB over every pixel of every channel.
//! - **SSIM** ([`ssim_luma`]): the structural similarity of Wang et al. (2004) on the luminance
//!   `Y = 0.2126 R + 0.7152 G + 0.0722 B` (three channels; one channel is used as it is), values
//!   clipped to `[0, 1]`, local statistics with a Gaussian window of σ = 1.5 px (mirrored borders):
//!   `SSIM = mean over pixels of (2 μ_a μ_b + C₁)(2 σ_ab + C₂) / ((μ_a² + μ_b² + C₁)(σ_a² + σ_b² + C₂))`
//!   with `C₁ = 0.01²`, `C₂ = 0.03²`. 1 for identical images.

use crate::image::filter::gaussian_blur;
use crate::image::Plane;

/// Window of the SSIM statistics (px).
const SSIM_SIGMA: f64 = 1.5;
const C1: f64 = 1e-4;
const C2: f64 = 9e-4;

/// PSNR (dB, peak 1) of `a` against `b`, all channels pooled; 300 dB for identical images.
pub fn psnr(a: &[Plane], b: &[Plane]) -> f64 {
    let (mut se, mut n) = (0.0f64, 0usize);
    for (p, q) in a.iter().zip(b) {
        se += p.data.iter().zip(&q.data).map(|(u, v)| ((u - v) as f64).powi(2)).sum::<f64>();
        n += p.data.len();
    }
    10.0 * (n.max(1) as f64 / se.max(1e-30)).log10()
}

/// Luminance of linear RGB (or the single channel), clipped to `[0, 1]`.
fn luma(p: &[Plane]) -> Plane {
    let clip = |v: f32| v.clamp(0.0, 1.0);
    if p.len() < 3 {
        return p[0].map(clip);
    }
    let mut y = p[0].map(|v| 0.2126 * clip(v));
    for (c, k) in [(1, 0.7152f32), (2, 0.0722)] {
        y.data.iter_mut().zip(&p[c].data).for_each(|(o, v)| *o += k * clip(*v));
    }
    y
}

/// Mean SSIM of the luminance of `a` against `b` (see the module docs).
///
/// # Panics
/// When `a` or `b` has no channel.
pub fn ssim_luma(a: &[Plane], b: &[Plane]) -> f64 {
    let (x, y) = (luma(a), luma(b));
    let prod = |p: &Plane, q: &Plane| Plane { width: p.width, height: p.height, data: p.data.iter().zip(&q.data).map(|(u, v)| u * v).collect() };
    let (mx, my) = (gaussian_blur(&x, SSIM_SIGMA), gaussian_blur(&y, SSIM_SIGMA));
    let (sxx, syy, sxy) = (gaussian_blur(&prod(&x, &x), SSIM_SIGMA), gaussian_blur(&prod(&y, &y), SSIM_SIGMA), gaussian_blur(&prod(&x, &y), SSIM_SIGMA));
    let mut sum = 0.0f64;
    for i in 0..x.data.len() {
        let (ma, mb) = (mx.data[i] as f64, my.data[i] as f64);
        let va = (sxx.data[i] as f64 - ma * ma).max(0.0);
        let vb = (syy.data[i] as f64 - mb * mb).max(0.0);
        let cov = sxy.data[i] as f64 - ma * mb;
        sum += (2.0 * ma * mb + C1) * (2.0 * cov + C2) / ((ma * ma + mb * mb + C1) * (va + vb + C2));
    }
    sum / x.data.len().max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pattern(w: usize, h: usize, f: f32) -> Vec<Plane> {
        (0..3).map(|c| Plane::from_fn(w, h, |x, y| 0.5 + 0.4 * ((x as f32 * f + c as f32) * 0.7).sin() * (y as f32 * 0.3).cos())).collect()
    }

    #[test]
    fn ssim_is_one_for_identical_images_and_drops_with_noise_and_blur() {
        let a = pattern(40, 30, 1.0);
        assert!((ssim_luma(&a, &a) - 1.0).abs() < 1e-6);
        let mut s = 7u64;
        let noisy: Vec<Plane> = a
            .iter()
            .map(|p| {
                let mut q = p.clone();
                for v in q.data.iter_mut() {
                    s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                    *v += 0.6 * ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5);
                }
                q
            })
            .collect();
        let blurred: Vec<Plane> = a.iter().map(|p| gaussian_blur(p, 2.0)).collect();
        let (sn, sb) = (ssim_luma(&a, &noisy), ssim_luma(&a, &blurred));
        assert!(sn < 0.9 && sn > 0.05, "noisy {sn}");
        assert!(sb < 0.9, "blurred {sb}");
    }

    #[test]
    fn psnr_of_a_constant_offset() {
        let a = pattern(20, 10, 1.0);
        let b: Vec<Plane> = a.iter().map(|p| p.map(|v| v + 0.01)).collect();
        assert!((psnr(&a, &b) - 40.0).abs() < 1e-3, "{}", psnr(&a, &b));
    }
}
