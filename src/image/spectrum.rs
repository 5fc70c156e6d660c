//! Radial binning of power spectra: the one implementation behind the residual spectrum
//! ([`crate::diagnose::analysis::radial_spectrum`]), a plane's PSD ([`RadialPsd`]: the
//! target's in the proof suite, the wide-open capture's for the detail a restored reference
//! gives up, [`crate::diagnose::diffraction::lost_signal_variance`]) and the excess-detail test
//! ([`crate::diagnose::diffraction::excess_detail`]).
//!
//! # Conventions
//! Spectra are the half spectra of [`crate::solve::fft::Fft2::forward`] (unnormalised forward
//! FFT; every stored bin counts once); `|f| = hypot(fx, fy)` in cycles per pixel from
//! [`crate::solve::fft::Fft2::frequency`]. Band `b` of `bands` covers
//! `[b, b + 1)·top/bands` (radii at or above `top` fall in the last band); bins outside
//! `range` are skipped. Each caller applies its own window, mean removal and normalisation.

use crate::image::Plane;
use crate::solve::fft::Fft2;
use rustfft::num_complex::Complex32;

/// Which radii count: `lo < |f| ≤ hi` or `lo ≤ |f| < hi`.
#[derive(Clone, Copy, Debug)]
pub enum Range {
    /// `lo < |f| ≤ hi`.
    OpenClosed(f64, f64),
    /// `lo ≤ |f| < hi`.
    ClosedOpen(f64, f64),
    /// Every bin.
    All,
}

impl Range {
    fn contains(self, f: f64) -> bool {
        match self {
            Range::OpenClosed(lo, hi) => f > lo && f <= hi,
            Range::ClosedOpen(lo, hi) => f >= lo && f < hi,
            Range::All => true,
        }
    }
}

/// Per band, the sums of `|S_j(f)|²` for every spectrum `S_j` of `spectra` over the bins in
/// the band, and the bin count: `(sums[j][b], counts[b])`.
pub fn radial_power_sums(fft: &Fft2, spectra: &[&[Complex32]], bands: usize, top: f64, range: Range) -> (Vec<Vec<f64>>, Vec<usize>) {
    let mut sums = vec![vec![0.0f64; bands]; spectra.len()];
    let mut counts = vec![0usize; bands];
    if bands == 0 {
        return (sums, counts);
    }
    for i in 0..fft.spectrum_len() {
        let (fx, fy) = fft.frequency(i);
        let f = (fx as f64).hypot(fy as f64);
        if !range.contains(f) {
            continue;
        }
        let b = ((f / top * bands as f64) as usize).min(bands - 1);
        for (s, spec) in sums.iter_mut().zip(spectra) {
            s[b] += spec[i].norm_sqr() as f64;
        }
        counts[b] += 1;
    }
    (sums, counts)
}

/// The centre of band `b` of `bands` up to `top`.
pub fn band_centre(b: usize, bands: usize, top: f64) -> f64 {
    (b as f64 + 0.5) * top / bands as f64
}

/// Radially averaged power spectral density of a plane (mean removed; per-pixel
/// normalisation: the variance is the mean of the PSD over frequencies), in 64 bands of `|f|`
/// up to `|f| = 0.71` cycles per pixel.
pub struct RadialPsd {
    bands: Vec<f64>,
}

impl RadialPsd {
    const BANDS: usize = 64;
    const FMAX: f64 = 0.7072;

    pub fn of(p: &Plane) -> Self {
        let (w, h) = (p.width, p.height);
        let fft = Fft2::plan(w, h);
        let m = p.mean() as f32;
        let spec = fft.forward(&p.data.iter().map(|v| v - m).collect::<Vec<_>>());
        let (sum, cnt) = radial_power_sums(&fft, &[&spec], Self::BANDS, Self::FMAX, Range::All);
        let sum: Vec<f64> = sum[0].iter().map(|s| s / (w * h) as f64).collect();
        // empty bands take the nearest filled one below
        let mut bands = vec![0.0; Self::BANDS];
        let mut last = 0.0;
        for b in 0..Self::BANDS {
            if cnt[b] > 0 {
                last = sum[b] / cnt[b] as f64;
            }
            bands[b] = last;
        }
        Self { bands }
    }

    fn band(f: f64) -> usize {
        ((f / Self::FMAX * Self::BANDS as f64) as usize).min(Self::BANDS - 1)
    }

    pub fn at(&self, fx: f64, fy: f64) -> f64 {
        self.bands[Self::band(fx.hypot(fy))]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A single cosine puts all its power in the band of its frequency; the counts cover every
    /// bin of the range once.
    #[test]
    fn a_cosine_lands_in_its_band() {
        let (w, h) = (64, 48);
        let fft = Fft2::plan(w, h);
        // fx = 12/64 = 0.1875 cycles/px: band 3 of 8 up to 0.5
        let data: Vec<f32> = (0..w * h).map(|i| (2.0 * std::f32::consts::PI * 12.0 * (i % w) as f32 / w as f32).cos()).collect();
        let spec = fft.forward(&data);
        let (sums, counts) = radial_power_sums(&fft, &[&spec], 8, 0.5, Range::OpenClosed(0.0, 0.5));
        let total: f64 = sums[0].iter().sum();
        assert!(sums[0][3] > 0.999 * total, "{:?}", sums[0]);
        let (_, all) = radial_power_sums(&fft, &[&spec], 8, 0.5, Range::All);
        assert_eq!(all.iter().sum::<usize>(), fft.spectrum_len());
        assert!(counts.iter().sum::<usize>() < fft.spectrum_len());
        assert!((band_centre(3, 8, 0.5) - 0.21875).abs() < 1e-12);
    }
}
