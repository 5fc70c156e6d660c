//! Noise through the linear part of the restoration: the regularised inverse and the noise
//! spectrum it leaves (docs/method.md §9, docs/deconvolution.md "Noise").
//!
//! # Model
//! The linear part of a restoration of data `j = B x + n` is the regularised inverse (DEB-BM3D's
//! first stage, Dabov et al. 2008)
//!
//! ```text
//! T(ω) = conj(B̂(ω)) / (|B̂(ω)|² + α R(ω)),     R(ω) = |D̂_x(ω)|² + |D̂_y(ω)|² = 4 sin²(π f_x) + 4 sin²(π f_y)
//! ```
//!
//! (`D_x, D_y` the forward differences of [`super::filters`]). For white input noise of
//! variance `σ²` (a noise law evaluated at the tile's level, `σ² = g x̄ + r²`), the output noise
//! is coloured with power spectral density
//!
//! ```text
//! S_out(ω) = σ² |T(ω)|²
//! ```
//!
//! and its variance is the mean of `S_out` over the spectrum ([`output_variance`]). A channel
//! whose `B̂` is near zero over a wide band (a far-defocused channel) gets `|T|²` up to
//! `1/(4 α R)` there: that is the coloured noise a flat-spectrum denoiser does not expect.
//!
//! # Conventions
//! Spectra use [`Fft2`]'s half layout (bin `(kx, ky)` at `kx · height + ky`); the PSD is per
//! bin with the unnormalised forward transform divided by the pixel count, so a white noise of
//! variance `σ²` has PSD `σ²` in every bin. Frequencies are in cycles per pixel; radial bands
//! split `|f| ∈ [0, 1/√2]` evenly.

use super::problem::KernelSpectrum;
use crate::solve::fft::Fft2;
use rustfft::num_complex::Complex32;

/// `R(ω) = 4 sin²(π f_x) + 4 sin²(π f_y)` per spectrum bin.
pub fn gradient_power(fft: &Fft2) -> Vec<f32> {
    (0..fft.spectrum_len())
        .map(|i| {
            let (fx, fy) = fft.frequency(i);
            4.0 * (std::f32::consts::PI * fx).sin().powi(2) + 4.0 * (std::f32::consts::PI * fy).sin().powi(2)
        })
        .collect()
}

/// The regularised inverse `T(ω)` of a kernel with Tikhonov weight `alpha` on the gradient.
pub fn regularised_inverse(ks: &KernelSpectrum, reg: &[f32], alpha: f32) -> Vec<Complex32> {
    ks.b.iter().zip(&ks.b2).zip(reg).map(|((b, b2), r)| b.conj() / (b2 + alpha * r).max(1e-20)).collect()
}

/// `|T(ω)|²`, the noise power gain per bin.
pub fn noise_gain(t: &[Complex32]) -> Vec<f32> {
    t.iter().map(|c| c.norm_sqr()).collect()
}

/// Applies a transfer function to a plane (circular).
pub fn apply(fft: &Fft2, data: &[f32], t: &[Complex32]) -> Vec<f32> {
    let mut s = fft.forward(data);
    s.iter_mut().zip(t).for_each(|(a, b)| *a *= b);
    fft.inverse(s)
}

/// The output noise variance `mean_ω σ² |T(ω)|²` (the half spectrum weighted as the full one).
pub fn output_variance(fft: &Fft2, gain: &[f32], sigma2: f32) -> f32 {
    let (w, h) = (fft.width, fft.height);
    let mut sum = 0.0f64;
    for (i, g) in gain.iter().enumerate() {
        sum += bin_weight(i / h, w) * *g as f64;
    }
    (sigma2 as f64 * sum / (w * h) as f64) as f32
}

/// How many full-spectrum bins half-spectrum column `kx` stands for (1 or 2).
pub(crate) fn bin_weight(kx: usize, w: usize) -> f64 {
    if kx == 0 || (w % 2 == 0 && kx == w / 2) {
        1.0
    } else {
        2.0
    }
}

/// The radial band (of `bands`) of every spectrum bin (DC is band 0).
pub fn radial_bands(fft: &Fft2, bands: usize) -> Vec<usize> {
    let top = std::f32::consts::FRAC_1_SQRT_2;
    (0..fft.spectrum_len())
        .map(|i| {
            let (fx, fy) = fft.frequency(i);
            (((fx * fx + fy * fy).sqrt() / top * bands as f32) as usize).min(bands - 1)
        })
        .collect()
}

/// Mean of `values` per band (full-spectrum weighted), `None` for empty bands.
pub fn band_means(fft: &Fft2, values: &[f32], band: &[usize], bands: usize) -> Vec<Option<f64>> {
    let mut s = vec![(0.0f64, 0.0f64); bands];
    for (i, (v, b)) in values.iter().zip(band).enumerate() {
        let wt = bin_weight(i / fft.height, fft.width);
        s[*b].0 += wt * *v as f64;
        s[*b].1 += wt;
    }
    s.into_iter().map(|(a, n)| (n > 0.0).then(|| a / n)).collect()
}

/// The periodogram `|F(x − mean x)|² / N` of a plane (its PSD estimate per bin).
pub fn periodogram(fft: &Fft2, x: &[f32]) -> Vec<f32> {
    let mean = x.iter().map(|v| *v as f64).sum::<f64>() / x.len().max(1) as f64;
    let centred: Vec<f32> = x.iter().map(|v| v - mean as f32).collect();
    let n = x.len() as f32;
    fft.forward(&centred).iter().map(|c| c.norm_sqr() / n).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deconv::synth::SyntheticLens;
    use crate::rng::Rng;
    use crate::solve::conv::kernel_to_origin;

    /// A flat grey patch with Poisson–Gaussian noise, through the regularised inverse of a
    /// strongly defocused kernel: the measured output spectrum matches `σ² |T|²` within 20 %
    /// in every radial band (and the variance as a whole).
    #[test]
    fn measured_output_spectrum_matches_the_prediction_per_band() {
        let (w, h) = (256, 256);
        let fft = Fft2::plan(w, h);
        // the synthetic lens' blue channel at the corner: the most defocused kernel it has
        let kernel = SyntheticLens::new(21, 3).kernel(2, 0.0, 0.0, w, h);
        let ks = KernelSpectrum::new(&fft, &kernel_to_origin(&kernel, w, h));
        let reg = gradient_power(&fft);
        let (fw, read_e, level) = (15_000.0f64, 4.0f64, 0.3f64);
        let sigma2 = (level / fw + (read_e / fw).powi(2)) as f32;
        let t = regularised_inverse(&ks, &reg, 2e-3);
        let gain = noise_gain(&t);
        let bands = 8;
        let band = radial_bands(&fft, bands);
        let mut rng = Rng::new(3);
        let mut measured = vec![0.0f32; fft.spectrum_len()];
        let reps = 12;
        for _ in 0..reps {
            let flat: Vec<f32> = (0..w * h).map(|_| ((rng.poisson(level * fw) + read_e * rng.normal()) / fw) as f32).collect();
            let out = apply(&fft, &flat, &t);
            periodogram(&fft, &out).iter().zip(measured.iter_mut()).for_each(|(p, m)| *m += p / reps as f32);
        }
        let predicted: Vec<f32> = gain.iter().map(|g| g * sigma2).collect();
        let (pm, mm) = (band_means(&fft, &predicted, &band, bands), band_means(&fft, &measured, &band, bands));
        for b in 0..bands {
            let (p, m) = (pm[b].unwrap(), mm[b].unwrap());
            assert!((m / p - 1.0).abs() < 0.2, "band {b}: measured {m:.3e}, predicted {p:.3e}");
        }
        // the noise is strongly coloured: the bands differ by far more than 20 %
        let lo = pm.iter().flatten().fold(f64::INFINITY, |a, b| a.min(*b));
        let hi = pm.iter().flatten().fold(0.0f64, |a, b| a.max(*b));
        assert!(hi > 5.0 * lo, "{pm:?}");
        let var = output_variance(&fft, &gain, sigma2);
        let meas_var: f64 = {
            let flat: Vec<f32> = (0..w * h).map(|_| ((rng.poisson(level * fw) + read_e * rng.normal()) / fw) as f32).collect();
            let out = apply(&fft, &flat, &t);
            let m = out.iter().map(|v| *v as f64).sum::<f64>() / out.len() as f64;
            out.iter().map(|v| (*v as f64 - m).powi(2)).sum::<f64>() / out.len() as f64
        };
        assert!((meas_var / var as f64 - 1.0).abs() < 0.1, "{meas_var:.3e} vs {var:.3e}");
    }
}
