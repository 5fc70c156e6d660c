//! The sensor noise law stored with a profile (`[noise]` in `profile.toml`,
//! docs/profile-format.md "Noise law"), and its fit from calibration captures.
//!
//! # Model
//! Poisson–Gaussian per channel on the **linear full-scale axis** (after the black level is
//! subtracted, before any transfer encoding):
//!
//! ```text
//! Var[x] = g_c · x + r_c²
//! ```
//!
//! `g_c` (the *gain*, full-scale units: `1 / full_well` for a sensor whose full scale is its
//! full well of electrons) and `r_c` (the *read noise*, full-scale units: read electrons /
//! full well). Quantisation adds `Δ²/12`, which the fit absorbs into `r²`.
//!
//! # Fits
//! All three fits bin samples by signal level into equal-count bins, estimate one variance per
//! bin and fit the line `v = g x + r²` by weighted least squares (weights `n_b / v_b²`, the
//! inverse variance of a variance estimate), with `g, r² ≥ 0`:
//! - [`NoiseLaw::fit_frames`]: repeated frames of a static scene (the frames a rig session
//!   averages): per pixel the sample mean and the unbiased sample variance; a bin's variance is
//!   the mean of its pixels' sample variances (unbiased, no outlier trimming needed);
//! - [`NoiseLaw::fit_residual`]: a prediction and its residual (data − prediction); a bin's
//!   variance is the robust `(MAD / 0.6745)²` of its residuals;
//! - [`NoiseLaw::fit_image`]: one blurred capture alone: the diagonal Haar detail
//!   `d = (a − b − c + e)/2` of each 2×2 block (`Var d = Var x`, and it cancels any linear
//!   gradient) against the block mean, with the robust bin variance.

use crate::image::Plane;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Fewer samples than this per bin give no bin.
const MIN_BIN: usize = 32;
/// Bins per fit.
const BINS: usize = 24;

/// A per-channel Poisson–Gaussian noise law (module docs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseLaw {
    /// Always `"poisson-gaussian"`.
    pub model: String,
    /// How it was obtained: `frames`, `residual`, `image` or `given`.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub source: String,
    /// `g_c` per channel (full-scale units).
    pub gain: Vec<f64>,
    /// `r_c` per channel (full-scale units).
    pub read: Vec<f64>,
}

/// Why a noise law cannot be fitted or used.
#[derive(Debug, thiserror::Error)]
pub enum NoiseLawError {
    #[error("noise law: too few samples to fit channel {channel} ({samples} usable)")]
    TooFewSamples { channel: usize, samples: usize },
    #[error("noise law: {0}")]
    Invalid(String),
}

impl NoiseLaw {
    /// A law from per-channel values (`source` = `given`).
    pub fn new(gain: Vec<f64>, read: Vec<f64>, source: &str) -> Self {
        Self { model: "poisson-gaussian".into(), source: source.into(), gain, read }
    }

    /// White Gaussian noise of standard deviation `sigma` on `channels` channels (`g = 0`).
    pub fn white(sigma: f64, channels: usize) -> Self {
        Self::new(vec![0.0; channels], vec![sigma; channels], "given")
    }

    /// The channel count.
    pub fn channels(&self) -> usize {
        self.gain.len()
    }

    /// `Var[x]` of channel `c` at linear signal `x` (negative signals count as 0).
    pub fn variance(&self, c: usize, x: f32) -> f32 {
        (self.gain[c] * x.max(0.0) as f64 + self.read[c] * self.read[c]) as f32
    }

    /// The law for `channels` channels: itself, or a one-channel law repeated.
    ///
    /// # Errors
    /// [`NoiseLawError::Invalid`] when the counts differ (and the law is not one channel), or a
    /// value is negative or not finite.
    pub fn for_channels(&self, channels: usize) -> Result<NoiseLaw, NoiseLawError> {
        self.check()?;
        if self.channels() == channels {
            return Ok(self.clone());
        }
        if self.channels() == 1 {
            return Ok(Self { gain: vec![self.gain[0]; channels], read: vec![self.read[0]; channels], ..self.clone() });
        }
        Err(NoiseLawError::Invalid(format!("{} channel(s) in the law, {channels} in the image", self.channels())))
    }

    /// Checks the values (finite, non-negative, one gain per read noise, a known model).
    ///
    /// # Errors
    /// [`NoiseLawError::Invalid`] saying which value is wrong.
    pub fn check(&self) -> Result<(), NoiseLawError> {
        if self.model != "poisson-gaussian" {
            return Err(NoiseLawError::Invalid(format!("model '{}' is not 'poisson-gaussian'", self.model)));
        }
        if self.gain.len() != self.read.len() || self.gain.is_empty() {
            return Err(NoiseLawError::Invalid(format!("{} gain and {} read values", self.gain.len(), self.read.len())));
        }
        if let Some(v) = self.gain.iter().chain(&self.read).find(|v| !(v.is_finite() && **v >= 0.0)) {
            return Err(NoiseLawError::Invalid(format!("value {v} is not finite and non-negative")));
        }
        Ok(())
    }

    /// Fits the law from repeated frames: `frames[c][f]` is frame `f` of channel `c` (linear,
    /// black level subtracted, at least 2 frames of one size).
    ///
    /// # Errors
    /// [`NoiseLawError`] for fewer than 2 frames, frames of different sizes, or too few
    /// samples.
    pub fn fit_frames(frames: &[Vec<&Plane>]) -> Result<NoiseLaw, NoiseLawError> {
        let mut law = Self::new(Vec::new(), Vec::new(), "frames");
        for (c, ch) in frames.iter().enumerate() {
            let n = ch.len();
            if n < 2 || ch.iter().any(|p| p.len() != ch[0].len()) {
                return Err(NoiseLawError::Invalid(format!("channel {c}: needs ≥ 2 frames of one size, got {n}")));
            }
            let samples: Vec<(f32, f32)> = (0..ch[0].len())
                .map(|i| {
                    let m = ch.iter().map(|p| p.data[i] as f64).sum::<f64>() / n as f64;
                    let v = ch.iter().map(|p| (p.data[i] as f64 - m).powi(2)).sum::<f64>() / (n - 1) as f64;
                    (m as f32, v as f32)
                })
                .collect();
            let (g, r2) = fit_line(c, samples, BinStat::Mean)?;
            law.gain.push(g);
            law.read.push(r2.sqrt());
        }
        Ok(law)
    }

    /// Fits the law from a prediction and its residual per channel (`mask`: samples to use,
    /// `None` all).
    ///
    /// # Errors
    /// [`NoiseLawError`] for mismatched lengths or too few samples.
    pub fn fit_residual(signal: &[Plane], residual: &[Plane], mask: Option<&[Vec<bool>]>) -> Result<NoiseLaw, NoiseLawError> {
        // channels in parallel (each fit is the same as alone; the first error in channel order)
        let fits: Vec<Result<(f64, f64), NoiseLawError>> = signal
            .par_iter()
            .zip(residual.par_iter())
            .enumerate()
            .map(|(c, (s, r))| {
                if s.len() != r.len() {
                    return Err(NoiseLawError::Invalid(format!("channel {c}: signal and residual differ in size")));
                }
                let m = mask.and_then(|m| m.get(c));
                let samples: Vec<(f32, f32)> = (0..s.len()).filter(|&i| m.map_or(true, |m| m[i])).map(|i| (s.data[i], r.data[i])).collect();
                fit_line(c, samples, BinStat::RobustSquare)
            })
            .collect();
        Self::from_fits("residual", fits)
    }

    /// Fits the law from one (blurred) capture per channel: 2×2 diagonal Haar details against
    /// block means (module docs). Blocks with a sample at or above `saturation` are left out
    /// (clipping removes their noise).
    ///
    /// # Errors
    /// [`NoiseLawError::TooFewSamples`] for images with too few blocks.
    pub fn fit_image(planes: &[Plane], saturation: f32) -> Result<NoiseLaw, NoiseLawError> {
        let fits: Vec<_> = planes.par_iter().enumerate().map(|(c, p)| fit_line(c, haar_samples(p, saturation), BinStat::RobustSquare)).collect();
        Self::from_fits("image", fits)
    }

    /// The law of per-channel fits `(g, r²)` in channel order; the first channel's error if any.
    fn from_fits(source: &str, fits: Vec<Result<(f64, f64), NoiseLawError>>) -> Result<NoiseLaw, NoiseLawError> {
        let mut law = Self::new(Vec::new(), Vec::new(), source);
        for fit in fits {
            let (g, r2) = fit?;
            law.gain.push(g);
            law.read.push(r2.sqrt());
        }
        Ok(law)
    }
}

/// `(block mean, diagonal detail)` of every 2×2 block of `p` whose samples are all below
/// `saturation`.
pub fn haar_samples(p: &Plane, saturation: f32) -> Vec<(f32, f32)> {
    let mut out = Vec::with_capacity((p.width / 2) * (p.height / 2));
    for y in (0..p.height.saturating_sub(1)).step_by(2) {
        for x in (0..p.width.saturating_sub(1)).step_by(2) {
            let (a, b, c, e) = (p.get(x, y), p.get(x + 1, y), p.get(x, y + 1), p.get(x + 1, y + 1));
            if a.max(b).max(c).max(e) < saturation {
                out.push(((a + b + c + e) * 0.25, (a - b - c + e) * 0.5));
            }
        }
    }
    out
}

/// How a bin's variance is computed from its second values.
#[derive(Clone, Copy)]
enum BinStat {
    /// The values are variances: their mean.
    Mean,
    /// The values are zero-mean deviates: `(median |v| / 0.6745)²`.
    RobustSquare,
}

/// Bins `(level, value)` samples by level (equal-count bins) and fits `v = g x + r²`.
fn fit_line(channel: usize, mut samples: Vec<(f32, f32)>, stat: BinStat) -> Result<(f64, f64), NoiseLawError> {
    samples.retain(|(x, v)| x.is_finite() && v.is_finite());
    let total = samples.len();
    if total < 2 * MIN_BIN {
        return Err(NoiseLawError::TooFewSamples { channel, samples: total });
    }
    samples.sort_by(|a, b| a.0.total_cmp(&b.0));
    let per = (total / BINS).max(MIN_BIN);
    let mut bins: Vec<(f64, f64, f64)> = Vec::new(); // (level, variance, count)
    for chunk in samples.chunks(per) {
        if chunk.len() < MIN_BIN {
            continue;
        }
        let level = chunk.iter().map(|s| s.0 as f64).sum::<f64>() / chunk.len() as f64;
        let var = match stat {
            BinStat::Mean => chunk.iter().map(|s| s.1 as f64).sum::<f64>() / chunk.len() as f64,
            BinStat::RobustSquare => {
                let mut a: Vec<f32> = chunk.iter().map(|s| s.1.abs()).collect();
                let mid = a.len() / 2;
                let (_, m, _) = a.select_nth_unstable_by(mid, |p, q| p.total_cmp(q));
                (*m as f64 / 0.6745).powi(2)
            }
        };
        bins.push((level, var, chunk.len() as f64));
    }
    // weights n/v² with the bins' measured variances, then twice with the fitted line's
    let floor = bins.iter().map(|b| b.1).fold(0.0f64, f64::max) * 1e-6 + 1e-30;
    let (mut g, mut r2) = weighted_line(&bins, |b| b.2 / b.1.max(floor).powi(2));
    for _ in 0..2 {
        (g, r2) = weighted_line(&bins, |b| b.2 / (g * b.0.max(0.0) + r2).max(floor).powi(2));
    }
    Ok((g, r2))
}

/// Weighted least squares `v = g x + r²` over `(x, v, n)` bins with `g, r² ≥ 0`.
fn weighted_line(bins: &[(f64, f64, f64)], weight: impl Fn(&(f64, f64, f64)) -> f64) -> (f64, f64) {
    let (mut sw, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for b in bins {
        let w = weight(b);
        sw += w;
        sx += w * b.0;
        sy += w * b.1;
        sxx += w * b.0 * b.0;
        sxy += w * b.0 * b.1;
    }
    if sw <= 0.0 {
        return (0.0, 0.0);
    }
    let det = sw * sxx - sx * sx;
    let (g, r2) = if det.abs() > 1e-30 * sw * sw { ((sw * sxy - sx * sy) / det, (sxx * sy - sx * sxy) / det) } else { (0.0, sy / sw) };
    if g < 0.0 {
        return (0.0, (sy / sw).max(0.0));
    }
    if r2 < 0.0 {
        return ((sxy / sxx.max(1e-30)).max(0.0), 0.0);
    }
    (g, r2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// A smooth scene from black to 0.9 with many dark pixels (read noise dominates only below
    /// `r²/g` ≈ 0.001 at 15 000 e⁻ / 4 e⁻, so a fit needs those to see it).
    fn scene(w: usize, h: usize) -> Plane {
        Plane::from_fn(w, h, |x, y| {
            let t = x as f32 / w as f32 * (0.8 + 0.2 * ((y as f32) * 0.05).sin());
            0.9 * t * t * t
        })
    }

    fn capture(clean: &Plane, fw: f64, read_e: f64, rng: &mut Rng) -> Plane {
        Plane::from_fn(clean.width, clean.height, |x, y| ((rng.poisson(clean.get(x, y) as f64 * fw) + read_e * rng.normal()) / fw) as f32)
    }

    fn close(got: f64, want: f64, tol: f64) -> bool {
        ((got - want) / want).abs() <= tol
    }

    #[test]
    fn frames_fit_recovers_the_simulated_sensor() {
        let (fw, read_e) = (15_000.0, 4.0);
        let clean = scene(96, 64);
        let mut rng = Rng::new(5);
        let frames: Vec<Plane> = (0..8).map(|_| capture(&clean, fw, read_e, &mut rng)).collect();
        let law = NoiseLaw::fit_frames(&[frames.iter().collect()]).unwrap();
        assert!(close(law.gain[0], 1.0 / fw, 0.1), "{law:?}");
        assert!(close(law.read[0], read_e / fw, 0.1), "{law:?}");
    }

    #[test]
    fn single_image_fit_recovers_the_simulated_sensor() {
        let (fw, read_e) = (3_000.0, 6.0);
        let clean = scene(512, 384);
        let mut rng = Rng::new(9);
        let law = NoiseLaw::fit_image(&[capture(&clean, fw, read_e, &mut rng)], 1.0).unwrap();
        assert!(close(law.gain[0], 1.0 / fw, 0.1), "{law:?}");
        assert!(close(law.read[0], read_e / fw, 0.1), "{law:?}");
    }

    /// The channels are fitted in parallel: a three-channel fit gives exactly the laws of the
    /// channels fitted alone, in channel order, and a bad channel's error is the first in
    /// channel order.
    #[test]
    fn channels_fitted_in_parallel_match_the_single_channel_fits() {
        let clean = scene(256, 192);
        let mut rng = Rng::new(5);
        let sensors = [(15_000.0, 4.0), (3_000.0, 6.0), (30_000.0, 2.0)];
        let noisy: Vec<Plane> = sensors.iter().map(|&(fw, re)| capture(&clean, fw, re, &mut rng)).collect();
        let res: Vec<Plane> = noisy.iter().map(|n| Plane::from_fn(clean.width, clean.height, |x, y| n.get(x, y) - clean.get(x, y))).collect();
        let signal = vec![clean.clone(); 3];
        let mask: Vec<Vec<bool>> = (0..3).map(|c| (0..clean.len()).map(|i| (i + c) % 3 != 0).collect()).collect();
        let all = NoiseLaw::fit_residual(&signal, &res, Some(&mask)).unwrap();
        let img = NoiseLaw::fit_image(&noisy, 1.0).unwrap();
        for c in 0..3 {
            let one = NoiseLaw::fit_residual(&signal[c..=c], &res[c..=c], Some(&mask[c..=c])).unwrap();
            assert_eq!((all.gain[c], all.read[c]), (one.gain[0], one.read[0]), "residual, channel {c}");
            let one = NoiseLaw::fit_image(&noisy[c..=c], 1.0).unwrap();
            assert_eq!((img.gain[c], img.read[c]), (one.gain[0], one.read[0]), "image, channel {c}");
        }
        assert_eq!((all.source.as_str(), img.source.as_str()), ("residual", "image"));
        let tiny = Plane::new(4, 4);
        match NoiseLaw::fit_image(&[noisy[0].clone(), tiny.clone(), tiny], 1.0) {
            Err(NoiseLawError::TooFewSamples { channel, .. }) => assert_eq!(channel, 1),
            other => panic!("expected channel 1 to fail: {other:?}"),
        }
    }

    #[test]
    fn residual_fit_recovers_the_simulated_sensor() {
        let (fw, read_e) = (15_000.0, 4.0);
        let clean = scene(512, 384);
        let mut rng = Rng::new(2);
        let noisy = capture(&clean, fw, read_e, &mut rng);
        let res = Plane::from_fn(clean.width, clean.height, |x, y| noisy.get(x, y) - clean.get(x, y));
        let law = NoiseLaw::fit_residual(&[clean], &[res], None).unwrap();
        assert!(close(law.gain[0], 1.0 / fw, 0.1), "{law:?}");
        assert!(close(law.read[0], read_e / fw, 0.1), "{law:?}");
    }

    /// Fit from a simulated capture, store in a profile, load, recover gain and read noise.
    #[test]
    fn law_round_trips_through_a_profile() {
        use crate::deconv::synth::SyntheticLens;
        use crate::image::{SampleFormat, Transfer};
        use crate::profile::{Profile, PsfTable, SourceInfo};
        let (fw, read_e, w, h) = (15_000.0, 4.0, 384, 256);
        let mut rng = Rng::new(11);
        let clean = scene(w, h);
        let noisy: Vec<Plane> = (0..3).map(|_| capture(&clean, fw, read_e, &mut rng)).collect();
        let grid = SyntheticLens::new(9, 3).grid(w, h, 3, 2, 2);
        let source = SourceInfo { width: w, height: h, channels: grid.channels.clone(), sample_format: SampleFormat::F32, transfer: Transfer::Linear, open: None, pinhole: None, black_level: vec![] };
        let table = PsfTable { kernel_size: 9, columns: 2, rows: 2, centers: grid.centers.clone(), tile_size: None, files: Default::default() };
        let mut meta = Profile::new_meta(source, vec![1.0; 3], table);
        meta.noise = Some(NoiseLaw::fit_image(&noisy, 1.0).unwrap());
        let d = tempfile::tempdir().unwrap();
        Profile { meta, grid }.save(d.path()).unwrap();
        let text = std::fs::read_to_string(d.path().join("profile.toml")).unwrap();
        assert!(text.contains("[noise]") && text.contains("poisson-gaussian"), "{text}");
        let law = Profile::load(d.path()).unwrap().meta.noise.unwrap();
        for c in 0..3 {
            assert!(close(law.gain[c], 1.0 / fw, 0.1), "{law:?}");
            assert!(close(law.read[c], read_e / fw, 0.1), "{law:?}");
        }
        // a profile without the table still loads (older profiles)
        std::fs::write(d.path().join("profile.toml"), text.split("[noise]").next().unwrap()).unwrap();
        assert!(Profile::load(d.path()).unwrap().meta.noise.is_none());
    }

    #[test]
    fn bad_laws_are_refused() {
        assert!(NoiseLaw::new(vec![1.0], vec![f64::NAN], "given").check().is_err());
        assert!(NoiseLaw::new(vec![1.0, 2.0], vec![0.0], "given").check().is_err());
        assert!(NoiseLaw::white(0.01, 2).for_channels(3).is_err());
        assert_eq!(NoiseLaw::white(0.01, 1).for_channels(3).unwrap().read, vec![0.01; 3]);
        assert!(NoiseLaw::fit_image(&[Plane::filled(4, 4, 0.5)], 1.0).is_err());
    }
}
