//! `pinhole_diffraction`: the stopped-down reference is not sharp.
//!
//! # Physics
//! At the pinhole stop (f-number `N`) the lens is close to diffraction-limited: its PSF is the
//! Airy pattern, whose first dark ring has the radius `r = 1.22·λ·N / p` pixels (`p` the pixel
//! pitch; the Airy core is `2.44·λ·N` across). Its optical transfer function is the incoherent
//! OTF of a circular pupil,
//!
//! `OTF(ν) = (2/π)·(acos ν − ν·√(1 − ν²))` for `ν = |f|/f_c < 1`, 0 beyond,
//!
//! with the cut-off `f_c = 1/(λN)` = `1.22 / r` cycles per pixel. The sensor integrates over the
//! pixel, so the reference is `P = D * S + n` with
//!
//! `D̂(fx, fy) = OTF(|f|/f_c) · sinc(fx) · sinc(fy)` (frequencies in cycles per pixel),
//!
//! relative to a pixel-integrated sharp target `S` (the convention of the wide-open kernels,
//! which include the pixel's own integration). A non-negative kernel `K` has `|K̂| ≤ ΣK`, so the
//! base model `K * P` cannot restore what `D̂` removed: wherever the wide-open lens passes more
//! than the stopped-down one, the wide-open capture holds detail the model cannot reproduce.
//!
//! At a real stop the lens is not quite diffraction-limited: its residual aberrations add a
//! small blur, modelled as a Gaussian of standard deviation `σ_a` pixels (one for the whole
//! field), so that the reference's transfer function is
//!
//! `D̂_a(fx, fy) = D̂(fx, fy) · exp(−2π²·σ_a²·(fx² + fy²))`
//!
//! (`σ_a = 0`: diffraction alone). Without it the fitted Airy radius absorbs the aberrations
//! and comes out too large.
//!
//! A colour channel integrates a band of wavelengths, and the Airy radius scales with `λ`: the
//! channel's transfer function is the band's average, by a three-point quadrature of a band of
//! relative half-width `δ` (`λ_c·(1 − δ)`, `λ_c`, `λ_c·(1 + δ)` with weights ¼, ½, ¼):
//!
//! `D̂_band(f) = ¼·D̂_a(f; r·(1 − δ)) + ½·D̂_a(f; r) + ¼·D̂_a(f; r·(1 + δ))`.
//!
//! The longer wavelengths cut off lower and the shorter ones higher, so a band passes more fine
//! detail near the cut-off than one wavelength does; at a stop where the noise is low enough
//! to restore up to the cut-off this matters. The nominal `δ` of a channel is
//! [`channel_bandwidth`]. `D` below stands for `D_band`, and [`ReferencePsf`] holds its three
//! parameters.
//!
//! # The model term
//! The reference is restored before the kernels act, by the Wiener filter of `D`:
//!
//! `S̃ = F⁻¹[ D̂·P̂ / (D̂² + ε) ]`, `ε = σ²_P / σ²_S`
//!
//! (`σ²_P` the reference's noise variance, `σ²_S` the target's variance, both measured: the
//! noise-to-signal ratio of a white target). Parameters: `airy_radius_px` per channel (one
//! fitted scale; channels follow their nominal wavelengths), and `epsilon`: the flat ratio
//! ([`epsilon`]) times a factor `9^k` per channel, chosen by the held-out squared residual of short fits
//! (`candidates::DiffractionSearch::decide_epsilon`; the printed target's spectrum is not white).
//! The restored reference carries more noise: the pinhole's noise reaches the prediction
//! through `K * W` (`Ŵ = D̂/(D̂² + ε)`), whose energy [`noise_gain`] gives.
//!
//! # The detail the restoration gives up
//! Where `D̂² ≲ ε` the filter gives up the target's detail rather than amplify the noise:
//! `S̃ − S = (ŴD̂ − 1)·Ŝ + Ŵ·n̂`. No non-negative kernel brings it back, so the wide-open
//! detail there stays in the residual of the best model. For a white target of variance
//! `σ²_S = σ²_P/ε` (the ratio the filter assumes) its energy through the kernel is
//!
//! `σ²_P · mean_f |K̂|²·|1 − ŴD̂|²/ε = σ²_P · mean_f |K̂|²·ε/(D̂² + ε)²`
//!
//! ([`propagated_energies`]). It is not noise: it grows with the target's contrast, as the
//! square of the level, and a noise curve measured from the residual reads it as the wide-open
//! capture's noise departing from a Poisson–Gaussian law (red at 1024×768 RGB, seed 71: 8× the
//! sensor's variance in the brightest bins). Where its high-pass share is above the law's bound
//! the residual cannot test the law in that channel ([`super::fit::LOST_DETAIL_LAW_BOUND`]).
//! The prediction's variance does not count it: with the white target's `σ²_S` it over-counts
//! the detail a real target holds near the cut-off, and a variance that grows with the Airy
//! radius favours too wide a radius (docs/notes/diagnosis-history.md, "Session 57").
//!
//! # The stop from the channels' spectra
//! The fitted radius trades off against the kernels (a wider PSF over-restores, which
//! non-negative kernels can blur back) and against `σ_a`. A colour reference holds a check that
//! neither can bias. The printed target is grey, so every channel sees the same target spectrum
//! `S(f)` up to a colour scale `a_c`; the residual aberrations' Gaussian, the pixel's sinc and
//! the print's own blur are common to all channels; only diffraction scales with wavelength.
//! The channels' periodograms (Hann window, radial bands, noise level `σ²_c` from the corners
//! beyond 0.6 cycles/px subtracted) therefore obey
//!
//! `ln[(P_c(f) − σ²_c) / (P_G(f) − σ²_G)] = ln(a_c/a_G) + ln[D̂²_c(f; N/p) / D̂²_G(f; N/p)]`,
//!
//! with `D̂_c` the band-averaged Airy transfer at radius `1.22·λ_c·N/p` and no other unknown.
//! [`spectral_stop`] fits `N/p` (f-number per µm of pixel pitch) by least squares on the bands
//! where both channels hold at least 20 standard errors of their noise, each pair's colour
//! scale free; the four quadrants' fits give its spread. A blur that does not scale with
//! wavelength leaves the ratio flat and gives no stop. It rests on the channels' nominal band
//! centres ([`channel_wavelength_um`]) and on a neutral target. Where it gives a stop, the
//! diagnosis takes the radii from it and fits only `σ_a` (`candidates::DiffractionSearch`):
//! a χ²-searched radius drifts wide (a wider PSF over-restores, which the kernels blur back),
//! and on the never-used seed 72 at 1024×768 RGB the searched stop was 2.6 % wide against the
//! spectra's 0.7 % (docs/notes/diagnosis-history.md, "Session 60"). A monochrome reference
//! keeps the search.
//!
//! Pixels are linear values; the FFT is mirror-padded so that no circular wrap reaches the image.

use crate::image::spectrum::{band_centre, radial_power_sums, Range};
use crate::image::Plane;
use crate::solve::fft::{good_size, Fft2};

/// Nominal relative half-width `δ` of a channel's band (module docs): a colour filter's band
/// (`R`, `G`, `B`) about ±5 % of its centre wavelength; anything else (a monochrome channel
/// behind a green-weighted filter) ±9 % (500–600 nm).
pub fn channel_bandwidth(name: &str) -> f64 {
    match name {
        "R" => 0.045,
        "G" | "B" => 0.055,
        _ => 0.09,
    }
}

/// The reference's PSF at the stop for one channel: Airy radius at the band's centre, residual
/// aberration blur and band half-width (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReferencePsf {
    /// Airy radius `1.22·λ_c·N / p` (px) at the band's centre wavelength.
    pub radius_px: f64,
    /// `σ_a` (px) of the residual aberrations' Gaussian.
    pub aberration_px: f64,
    /// Relative half-width `δ` of the band (0: one wavelength).
    pub bandwidth: f64,
}

impl ReferencePsf {
    /// One wavelength, no aberrations.
    pub fn airy(radius_px: f64) -> Self {
        Self { radius_px, aberration_px: 0.0, bandwidth: 0.0 }
    }
    /// `D̂_band` at `(fx, fy)` (cycles per pixel).
    pub fn transfer(&self, fx: f64, fy: f64) -> f64 {
        if self.bandwidth <= 0.0 {
            return reference_transfer(fx, fy, self.radius_px, self.aberration_px);
        }
        let (r, d) = (self.radius_px, self.bandwidth);
        0.25 * reference_transfer(fx, fy, r * (1.0 - d), self.aberration_px) + 0.5 * reference_transfer(fx, fy, r, self.aberration_px) + 0.25 * reference_transfer(fx, fy, r * (1.0 + d), self.aberration_px)
    }
    /// MTF50: the frequency (cycles per pixel, along a pixel row) at which `D̂_band` falls to
    /// one half, by bisection; 0.5 (Nyquist) when it is still above one half there. Unlike the
    /// radius and `σ_a`, which trade off against each other when the aberrations are not
    /// Gaussian (a wider Airy core or a wider Gaussian blur the reference alike), this is
    /// what the data determine.
    pub fn mtf50(&self) -> f64 {
        half_modulation(|f| self.transfer(f, 0.0))
    }
    /// Support (px) beyond which the PSF is negligible: several Airy radii of the band's
    /// longest wavelength plus the Gaussian's.
    fn margin(&self) -> usize {
        (6.0 * self.radius_px * (1.0 + self.bandwidth) + 4.0 * self.aberration_px).ceil() as usize + 8
    }
}

/// The frequency in (0, 0.5] cycles/px at which a falling modulation `m(f)` (1 at 0) drops to
/// one half, by bisection; 0.5 (Nyquist) when it is still above one half there.
pub fn half_modulation(m: impl Fn(f64) -> f64) -> f64 {
    if m(0.5) >= 0.5 {
        return 0.5;
    }
    let (mut lo, mut hi) = (0.0, 0.5);
    for _ in 0..50 {
        let mid = 0.5 * (lo + hi);
        if m(mid) > 0.5 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Nominal centre wavelength (µm) of a channel name, for scaling the Airy radius across
/// channels (`R`, `G`, `B`; anything else counts as green).
pub fn channel_wavelength_um(name: &str) -> f64 {
    match name {
        "R" => 0.61,
        "B" => 0.465,
        _ => 0.55,
    }
}

/// The diffraction OTF of a circular pupil at normalised frequency `nu = |f|/f_c`.
pub fn circular_otf(nu: f64) -> f64 {
    if nu >= 1.0 {
        return 0.0;
    }
    let nu = nu.max(0.0);
    (2.0 / std::f64::consts::PI) * (nu.acos() - nu * (1.0 - nu * nu).sqrt())
}

fn sinc(x: f64) -> f64 {
    if x.abs() < 1e-12 {
        1.0
    } else {
        let px = std::f64::consts::PI * x;
        px.sin() / px
    }
}

/// `D̂` at frequency `(fx, fy)` (cycles per pixel) for Airy radius `radius_px`.
pub fn transfer(fx: f64, fy: f64, radius_px: f64) -> f64 {
    let fc = 1.22 / radius_px.max(1e-6);
    circular_otf((fx * fx + fy * fy).sqrt() / fc) * sinc(fx) * sinc(fy)
}

/// `D̂_a`: [`transfer`] times the Gaussian of the residual aberrations, `σ_a = aberration_px`.
pub fn reference_transfer(fx: f64, fy: f64, radius_px: f64, aberration_px: f64) -> f64 {
    let g = if aberration_px > 0.0 { (-2.0 * std::f64::consts::PI.powi(2) * aberration_px * aberration_px * (fx * fx + fy * fy)).exp() } else { 1.0 };
    transfer(fx, fy, radius_px) * g
}

/// The Wiener restoration `S̃` of a reference plane (module docs). Mirror-padded by a margin
/// of several Airy radii; returns a plane of the input's size.
pub fn restore(p: &Plane, psf: &ReferencePsf, epsilon: f64) -> Plane {
    let (w, h) = (p.width, p.height);
    let m = psf.margin().min(w.max(h));
    let (pw, ph) = (good_size(w + 2 * m), good_size(h + 2 * m));
    let fft = Fft2::plan(pw, ph);
    let win = p.window_reflect(-(m as isize), -(m as isize), pw, ph);
    let mean = win.mean() as f32;
    let centred: Vec<f32> = win.data.iter().map(|v| v - mean).collect();
    let mut spec = fft.forward(&centred);
    for (i, s) in spec.iter_mut().enumerate() {
        let (fx, fy) = fft.frequency(i);
        let d = psf.transfer(fx as f64, fy as f64);
        *s *= (d / (d * d + epsilon)) as f32;
    }
    let full = fft.inverse(spec);
    Plane::from_fn(w, h, |x, y| full[(y + m) * pw + x + m] + mean)
}

/// The restoration's Wiener ε for a reference plane with noise variance `noise_var`: its
/// noise-to-signal ratio ([`noise_to_signal`]), at least [`EPSILON_MIN`].
pub fn epsilon(p: &Plane, noise_var: f64, psf: &ReferencePsf) -> f64 {
    noise_to_signal(p, noise_var, psf).max(EPSILON_MIN)
}

/// The lower bound of [`epsilon`]. The flat ε is right for a white target; the printed noise
/// target's spectrum falls at high frequencies, so the ratio computed from the sensor's true noise
/// (about 2e-6 on the bench's seed 72) restores far too much there (docs/notes/diagnosis-history.md,
/// "Session 59").
pub const EPSILON_MIN: f64 = 1e-4;

/// The mean of `f(fx, fy)` over the Nyquist square, sampled at the centres of a `steps × steps`
/// grid (rows of `fy` outer, `fx` inner).
fn nyquist_mean(steps: usize, f: impl Fn(f64, f64) -> f64) -> f64 {
    let mut acc = 0.0;
    for j in 0..steps {
        for i in 0..steps {
            acc += f((i as f64 + 0.5) / steps as f64 - 0.5, (j as f64 + 0.5) / steps as f64 - 0.5);
        }
    }
    acc / (steps * steps) as f64
}

/// The noise-to-signal ratio `σ²_P / σ²_S` of a reference plane with noise variance `noise_var`,
/// the target's variance taken from the plane's spectrum (`σ²_S = (var P − σ²_P) / mean D̂²`),
/// unbounded.
pub fn noise_to_signal(p: &Plane, noise_var: f64, psf: &ReferencePsf) -> f64 {
    let var = p.variance();
    let md2 = nyquist_mean(64, |fx, fy| psf.transfer(fx, fy).powi(2)).max(1e-9);
    let signal = ((var - noise_var).max(1e-3 * var)) / md2;
    noise_var / signal.max(1e-30)
}

/// Energy `Σ (K * W)²` of the combined kernel through which the reference's noise reaches the
/// prediction (`Ŵ = D̂/(D̂² + ε)`), computed on a periodic grid of side `good_size(4k)`.
pub fn noise_gain(kernel: &Plane, psf: &ReferencePsf, epsilon: f64) -> f32 {
    propagated_energy(kernel, Some((psf, epsilon)), false)
}

/// The variance, per pixel of the prediction (linear axis), of the detail a restored reference
/// gives up: the signal error `K * (1 − W * D) * S` of a prediction `K * S̃` from the restored
/// reference `S̃ = W * P` (`Ŵ = D̂/(D̂² + ε)`, so `1 − Ŵ·D̂ = ε/(D̂² + ε)`). Its spectrum is the
/// wide-open capture's signal `|K̂·Ŝ|² = P_O − N_O` (the capture's PSD `psd` less its white
/// noise variance `noise_var`) times `(ε/(D̂² + ε))²`, so
///
/// `L = max(0, mean_f (P_O(f) − N_O) · (ε/(D̂(f)² + ε))²)`
///
/// over the Nyquist square (a 128 × 128 grid of frequencies). The difference is not clipped per
/// band: where the signal is below the noise, clipping would keep every upward fluctuation of
/// the measured PSD (+47 % on the unit test's target with a lost signal of 2 % of the noise). Unlike the white-target energy
/// of [`propagated_energies`], this takes the target's spectrum from the capture itself: a
/// printed target's falls at high frequencies, where the restoration loses most.
pub fn lost_signal_variance(psd: &crate::image::spectrum::RadialPsd, noise_var: f64, psf: &ReferencePsf, epsilon: f64) -> f64 {
    nyquist_mean(128, |fx, fy| {
        let d = psf.transfer(fx, fy);
        let loss = epsilon / (d * d + epsilon);
        (psd.at(fx, fy) - noise_var) * loss * loss
    })
    .max(0.0)
}

/// The high-pass `d = (4·c − n − s − e − w)/√20` of the noise measurement
/// ([`super::noise`]): `|Ĥ(f)|² = (4 − 2·cos 2πfx − 2·cos 2πfy)² / 20` (unit gain on white
/// noise).
pub fn highpass_power(fx: f64, fy: f64) -> f64 {
    let tau = 2.0 * std::f64::consts::PI;
    (4.0 - 2.0 * (tau * fx).cos() - 2.0 * (tau * fy).cos()).powi(2) / 20.0
}

/// `mean_f |K̂|²·|Ŵ|²·(|Ĥ|² if highpass)`: the variance gain from white reference noise to the
/// prediction (`Ŵ` the restoration of `reference`, 1 without), or to the prediction's
/// high-pass `d` — the share of the residual's high-pass that is the reference's noise, which
/// the noise measurement must not count as the wide-open capture's own.
pub fn propagated_energy(kernel: &Plane, reference: Option<(&ReferencePsf, f64)>, highpass: bool) -> f32 {
    propagated_energies(kernel, reference, highpass).0
}

/// [`propagated_energy`] and, under a restoration, the **lost detail**'s energy
/// `mean_f |K̂|²·ε/(D̂² + ε)²·(|Ĥ|² if highpass)` (module docs, "The detail the restoration
/// gives up"; 0 without a restoration), both per unit of the reference's noise variance.
pub fn propagated_energies(kernel: &Plane, reference: Option<(&ReferencePsf, f64)>, highpass: bool) -> (f32, f32) {
    let k = kernel.width.max(kernel.height);
    let n = good_size((4 * k).max(64));
    let fft = Fft2::plan(n, n);
    let mut buf = vec![0.0f32; n * n];
    for y in 0..kernel.height {
        for x in 0..kernel.width {
            buf[y * n + x] = kernel.get(x, y);
        }
    }
    let spec = fft.forward(&buf);
    // Parseval over the half spectrum: interior columns count twice
    let (mut e, mut lost) = (0.0f64, 0.0f64);
    for (i, s) in spec.iter().enumerate() {
        let (fx, fy) = fft.frequency(i);
        // |Ŵ| and ε/(D̂² + ε)², in the order of operations `propagated_energy` always had (its
        // figures feed the search's comparisons, and their last bits with them)
        let (g, l2) = match reference {
            Some((psf, epsilon)) => {
                let d = psf.transfer(fx as f64, fy as f64);
                let q = d * d + epsilon;
                (d / q, epsilon / (q * q))
            }
            None => (1.0, 0.0),
        };
        let hp = if highpass { highpass_power(fx as f64, fy as f64) } else { 1.0 };
        let g = if highpass { g * hp.sqrt() } else { g };
        let kx = i / n;
        let mult = if kx == 0 || (n % 2 == 0 && kx == n / 2) { 1.0 } else { 2.0 };
        e += mult * (s.norm_sqr() as f64) * g * g;
        lost += mult * (s.norm_sqr() as f64) * hp * l2;
    }
    ((e / (n * n) as f64) as f32, (lost / (n * n) as f64) as f32)
}

/// Radially averaged power ratio `(|Ô|² − N_O) / (s²·(|P̂|² − N_P))` in eight frequency bands
/// (a Hann-windowed central square of both planes): above 1 where the wide-open capture holds
/// detail that no non-negative kernel of sum `s` can produce from the reference. Bands where
/// the reference holds less than twice its noise power are skipped (no information there).
/// Returns `(band centre in cycles/px, ratio)`.
pub fn excess_detail(open: &Plane, reference: &Plane, s: f64, var_open: f64, var_ref: f64) -> Vec<(f64, f64)> {
    let side = open.width.min(open.height);
    let n = {
        let mut n = good_size(side);
        while n > side {
            n = good_size(n * 3 / 4);
            if n <= 8 {
                break;
            }
        }
        n.min(side)
    };
    if n < 16 {
        return Vec::new();
    }
    let (x0, y0) = ((open.width - n) / 2, (open.height - n) / 2);
    let ((fft, so, w2), (_, sp, _)) = (hann_spectrum(open, x0, y0, n, n), hann_spectrum(reference, x0, y0, n, n));
    let bands = 8;
    let (sums, cnt) = radial_power_sums(&fft, &[&so, &sp], bands, 0.5, Range::ClosedOpen(0.02, 0.5));
    let (po, pp) = (&sums[0], &sums[1]);
    // white noise of variance v has the expected windowed power v·Σ_xy w² = v·w2 per bin (the
    // forward transform is unnormalised)
    (0..bands)
        .filter(|&b| cnt[b] > 0)
        .filter_map(|b| {
            let (mo, mp) = (po[b] / cnt[b] as f64, pp[b] / cnt[b] as f64);
            let (so_, sp_) = (mo - var_open * w2, mp - var_ref * w2);
            (mp > 2.0 * var_ref * w2 && sp_ > 0.0).then(|| (band_centre(b, bands, 0.5), so_.max(0.0) / (s * s * sp_)))
        })
        .collect()
}

/// The stop measured from the reference's own colour spectra, independently of the kernels
/// (module docs, "The stop from the channels' spectra").
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpectralStop {
    /// `N / p`, the f-number per micrometre of pixel pitch, fitted on the whole frame.
    pub f_number_per_um_pitch: f64,
    /// Standard deviation of the quadrants' own fits (two to four: a quadrant whose bands do
    /// not determine the stop is left out), the field's consistency and the estimate's noise
    /// together; each quadrant holds a quarter of the frame, so this is about twice the whole
    /// frame's own noise.
    pub spread: f64,
    /// Radial bands the whole frame's fit used, over every channel pair.
    pub bands: usize,
}

/// Radial bands of [`spectral_stop`]'s periodograms, up to the Nyquist corner [`STOP_TOP`].
const STOP_BANDS: usize = 64;
const STOP_TOP: f64 = std::f64::consts::FRAC_1_SQRT_2;
/// Bands beyond this radial frequency (cycles/px; the periodogram's corners) give the noise level.
const STOP_NOISE_FROM: f64 = 0.6;
/// Least excess power of a band [`spectral_stop`] uses, in standard errors of the noise's band
/// mean (`σ²/√n` for `n` bins).
const STOP_SNR: f64 = 20.0;
/// Least span (natural log) of the modelled channel ratio over the bands used: below it the
/// ratio hardly depends on the stop (the cut-offs far beyond the bands the data resolve) and
/// the stop is not determined.
const STOP_MIN_SPAN: f64 = 0.3;
/// Least number of bands per channel pair.
const STOP_MIN_BANDS: usize = 6;
/// Least side (px) of a quadrant [`spectral_stop`] fits.
const STOP_MIN_SIDE: usize = 32;
/// Largest spread of the quadrants' stops, relative to the whole frame's, that [`spectral_stop`]
/// accepts: a field whose parts disagree more (a blur that is not the stop's, a target that is
/// not neutral everywhere) gives no stop, and the radius is searched. The benchmark seeds spread
/// by at most 3 % (seed 24, f/12).
const STOP_MAX_SPREAD: f64 = 0.05;

/// `N / p` from the ratio of the channels' power spectra (module docs, "The stop from the
/// channels' spectra"): `planes` the registered linear reference, one per channel, `names`
/// their channel names. `None` with fewer than two channels of known, distinct wavelengths
/// ([`channel_wavelength_um`]: `R`, `G`, `B`), planes under `2·`[`STOP_MIN_SIDE`] px or of
/// unequal sizes, or where the ratio does not determine the stop: fewer than
/// [`STOP_MIN_BANDS`] significant bands in every pair, a modelled ratio that spans less than
/// [`STOP_MIN_SPAN`] over them, a best `N/p` at the edge of the searched range (f/1–f/30 per µm),
/// fewer than two quadrants with a stop, or quadrants that spread by more than
/// [`STOP_MAX_SPREAD`]. Known limits: the noise level is read beyond 0.6 cycles/px, which holds
/// signal where a channel's cut-off lies beyond it (blue below `N/p` ≈ 3.8), and a blur that
/// scales with wavelength without being diffraction (chromatic defocus at the stop) is read as
/// a stop.
pub fn spectral_stop(planes: &[Plane], names: &[&str]) -> Option<SpectralStop> {
    let known: Vec<usize> = (0..planes.len().min(names.len())).filter(|&c| matches!(names[c], "R" | "G" | "B")).collect();
    let reference = known.iter().copied().find(|&c| names[c] == "G").or(known.first().copied())?;
    let others: Vec<usize> = known.iter().copied().filter(|&c| channel_wavelength_um(names[c]) != channel_wavelength_um(names[reference])).collect();
    if others.is_empty() {
        return None;
    }
    let (w, h) = (planes[reference].width, planes[reference].height);
    if w.min(h) < 2 * STOP_MIN_SIDE || planes.iter().any(|p| (p.width, p.height) != (w, h)) {
        return None;
    }
    let fit = |x0: usize, y0: usize, ww: usize, hh: usize| -> Option<(f64, usize)> {
        let spectra: Vec<(Vec<f64>, f64, Vec<usize>)> = planes.iter().map(|p| windowed_radial_power(p, x0, y0, ww, hh)).collect();
        let pairs: Vec<(usize, Vec<(f64, f64)>)> = others
            .iter()
            .map(|&c| {
                let excess = |k: usize, b: usize| spectra[k].0[b] - spectra[k].1;
                let significant = |k: usize, b: usize| excess(k, b) > STOP_SNR * spectra[k].1 / (spectra[k].2[b].max(1) as f64).sqrt();
                let bands = (1..STOP_BANDS).filter(|&b| spectra[c].2[b] > 0 && significant(c, b) && significant(reference, b)).map(|b| (band_centre(b, STOP_BANDS, STOP_TOP), (excess(c, b) / excess(reference, b)).ln())).collect();
                (c, bands)
            })
            .filter(|(_, b): &(usize, Vec<(f64, f64)>)| b.len() >= STOP_MIN_BANDS)
            .collect();
        if pairs.is_empty() {
            return None;
        }
        let psf = |c: usize, np: f64| ReferencePsf { radius_px: 1.22 * channel_wavelength_um(names[c]) * np, aberration_px: 0.0, bandwidth: channel_bandwidth(names[c]) };
        // each pair's modelled log ratio at its bands, and the span over those bands
        let model = |np: f64, c: usize, bands: &[(f64, f64)]| -> Vec<f64> {
            let (pc, pr) = (psf(c, np), psf(reference, np));
            bands.iter().map(|&(f, _)| (pc.transfer(f, 0.0).powi(2).max(1e-9) / pr.transfer(f, 0.0).powi(2).max(1e-9)).ln()).collect()
        };
        // mean square of the log ratios' misfit, each pair's colour scale (its mean) removed
        let cost = |np: f64| -> f64 {
            let (mut sum, mut n) = (0.0, 0usize);
            for (c, bands) in &pairs {
                let r: Vec<f64> = model(np, *c, bands).iter().zip(bands).map(|(m, b)| b.1 - m).collect();
                let mean = r.iter().sum::<f64>() / r.len() as f64;
                sum += r.iter().map(|v| (v - mean).powi(2)).sum::<f64>();
                n += r.len();
            }
            sum / n as f64
        };
        // a log grid in steps of 0.2 %, f/1 to f/30 at 1 µm
        let (lo, hi, step) = (1.0f64.ln(), 30.0f64.ln(), 0.002);
        let costs: Vec<f64> = (0..=((hi - lo) / step) as usize).map(|i| cost((lo + i as f64 * step).exp())).collect();
        let i = (0..costs.len()).filter(|&i| costs[i].is_finite()).min_by(|&a, &b| costs[a].total_cmp(&costs[b]))?;
        // the parabola through the minimum and its neighbours, within the step
        let offset = match (i.checked_sub(1).map(|j| costs[j]), costs.get(i + 1)) {
            (Some(a), Some(&b)) if a.is_finite() && b.is_finite() && a + b - 2.0 * costs[i] > 0.0 => (0.5 * (a - b) / (a + b - 2.0 * costs[i])).clamp(-0.5, 0.5),
            _ => 0.0,
        };
        let best = ((lo + (i as f64 + offset) * step).exp(), costs[i]);
        let span = pairs
            .iter()
            .map(|(c, bands)| {
                let m = model(best.0, *c, bands);
                m.iter().copied().fold(f64::NEG_INFINITY, f64::max) - m.iter().copied().fold(f64::INFINITY, f64::min)
            })
            .fold(0.0, f64::max);
        (span >= STOP_MIN_SPAN && best.0 > lo.exp() * 1.01 && best.0 < hi.exp() / 1.01).then(|| (best.0, pairs.iter().map(|p| p.1.len()).sum()))
    };
    let (np, bands) = fit(0, 0, w, h)?;
    let quadrants: Vec<f64> = [(0, 0), (w / 2, 0), (0, h / 2), (w / 2, h / 2)].iter().filter_map(|&(x, y)| fit(x, y, w / 2, h / 2)).map(|q| q.0).collect();
    if quadrants.len() < 2 {
        return None;
    }
    let mean = quadrants.iter().sum::<f64>() / quadrants.len() as f64;
    let spread = (quadrants.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (quadrants.len() - 1) as f64).sqrt();
    (spread <= STOP_MAX_SPREAD * np).then_some(SpectralStop { f_number_per_um_pitch: np, spread, bands })
}

/// The Hann-windowed periodogram of the `ww × hh` window at `(x0, y0)` of `p` (mean removed)
/// in [`STOP_BANDS`] radial bands up to [`STOP_TOP`], normalised so that white noise of
/// variance `σ²` gives `σ²` in every band; the noise level (the mean beyond
/// [`STOP_NOISE_FROM`]); and each band's bin count.
fn windowed_radial_power(p: &Plane, x0: usize, y0: usize, ww: usize, hh: usize) -> (Vec<f64>, f64, Vec<usize>) {
    let (fft, spec, w2) = hann_spectrum(p, x0, y0, ww, hh);
    let (sums, counts) = radial_power_sums(&fft, &[&spec], STOP_BANDS, STOP_TOP, Range::All);
    let power: Vec<f64> = sums[0].iter().zip(&counts).map(|(s, &n)| s / n.max(1) as f64 / w2).collect();
    let beyond: Vec<usize> = (0..STOP_BANDS).filter(|&b| band_centre(b, STOP_BANDS, STOP_TOP) > STOP_NOISE_FROM && counts[b] > 0).collect();
    let noise = beyond.iter().map(|&b| power[b] * counts[b] as f64).sum::<f64>() / beyond.iter().map(|&b| counts[b]).sum::<usize>().max(1) as f64;
    (power, noise, counts)
}

/// The spectrum of the `ww × hh` window at `(x0, y0)` of `p`, mean removed, under a separable
/// Hann window; with its plan and `Σ_xy w²` (white noise of variance `σ²` has the expected
/// power `σ²·Σ_xy w²` per bin: the forward transform is unnormalised).
fn hann_spectrum(p: &Plane, x0: usize, y0: usize, ww: usize, hh: usize) -> (std::sync::Arc<Fft2>, Vec<rustfft::num_complex::Complex32>, f64) {
    let hann = |n: usize| -> Vec<f64> { (0..n).map(|i| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * (i as f64 + 0.5) / n as f64).cos()).collect() };
    let (hx, hy) = (hann(ww), hann(hh));
    let win = Plane::from_fn(ww, hh, |x, y| p.get(x0 + x, y0 + y));
    let mean = win.mean();
    let buf: Vec<f32> = (0..ww * hh).map(|i| ((win.data[i] as f64 - mean) * hx[i % ww] * hy[i / ww]) as f32).collect();
    let w2 = hx.iter().map(|v| v * v).sum::<f64>() * hy.iter().map(|v| v * v).sum::<f64>();
    let fft = Fft2::plan(ww, hh);
    let spec = fft.forward(&buf);
    (fft, spec, w2)
}

/// `K * D` cropped to the kernel's support, clamped non-negative and rescaled to `K`'s sum: the
/// wide-open kernel that a kernel fitted against the unrestored reference (`K_base ≈ K * D⁻¹`)
/// implies, the warm start of the refit once the reference is restored.
pub fn blur_kernel(kernel: &Plane, psf: &ReferencePsf) -> Plane {
    filter_kernel(kernel, |fx, fy| psf.transfer(fx, fy))
}

/// The kernel that keeps the prediction `K * W_from * P` when the restoration changes from
/// `W_from` (`from`: the reference's PSF and Wiener ratio ε) to the one for `to`:
/// `K̂' = K̂ · Ŵ_from · D̂_to` (`1/Ŵ_to ≈ D̂_to` where the new restoration passes signal), cropped,
/// clamped non-negative and rescaled as [`blur_kernel`]. A smaller radius sharpens the kernel,
/// a larger one blurs it: fits at neighbouring radii start from the same prediction
/// (`super::candidates`' re-searched diffraction radius).
pub fn rerestored_kernel(kernel: &Plane, from: (&ReferencePsf, f64), to: &ReferencePsf) -> Plane {
    filter_kernel(kernel, |fx, fy| {
        let d = from.0.transfer(fx, fy);
        to.transfer(fx, fy) * d / (d * d + from.1.max(1e-12))
    })
}

/// `K` filtered by the transfer function `t(fx, fy)` (cycles/px), cropped to the kernel's
/// support, clamped non-negative and rescaled to `K`'s sum.
fn filter_kernel(kernel: &Plane, t: impl Fn(f64, f64) -> f64) -> Plane {
    let (kw, kh) = (kernel.width, kernel.height);
    let n = good_size(2 * kw.max(kh) + 16);
    let fft = Fft2::plan(n, n);
    let padded = crate::solve::conv::kernel_to_origin(kernel, n, n);
    let mut spec = fft.forward(&padded);
    for (i, s) in spec.iter_mut().enumerate() {
        let (fx, fy) = fft.frequency(i);
        *s *= t(fx as f64, fy as f64) as f32;
    }
    let full = fft.inverse(spec);
    let mut out = crate::solve::conv::kernel_from_origin(&full, n, n, kw, kh);
    out.data.iter_mut().for_each(|v| *v = v.max(0.0));
    let (s0, s1) = (kernel.sum(), out.sum());
    if s1 > 0.0 {
        out.scale((s0 / s1) as f32);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// [`excess_detail`]: a sharp reference behind a blurring wide-open kernel shows no band
    /// above 1 even where both captures hold only noise (the pinhole averaged 16 frames, so its
    /// noise is 1/16 of the open's: unsubtracted, such bands read about 16); a blurred reference
    /// behind a sharp kernel does.
    #[test]
    fn excess_detail_subtracts_the_noise_and_finds_a_blurred_reference() {
        let n = 256;
        let mut rng = Rng::new(5);
        // a soft scene: above about 0.25 cycles/px both captures hold noise only
        let scene = crate::image::filter::gaussian_blur_wide(&Plane::from_fn(n, n, |_, _| (0.4 + 0.3 * rng.normal()) as f32), 1.5);
        let noisy = |p: &Plane, v: f64, rng: &mut Rng| Plane { width: p.width, height: p.height, data: crate::estimate::bootstrap::add_noise(&p.data, |_| v as f32, rng) };
        let (no, np) = (1e-3, 1e-3 / 16.0);
        let open = noisy(&crate::image::filter::gaussian_blur_wide(&scene, 1.2), no, &mut rng);
        let sharp_ref = noisy(&scene, np, &mut rng);
        let worst = |bands: Vec<(f64, f64)>| bands.iter().map(|b| b.1).fold(0.0, f64::max);
        let clean = worst(excess_detail(&open, &sharp_ref, 1.0, no, np));
        assert!(clean < 1.2, "a sharp reference: worst band {clean:.2}");
        let sharp_open = noisy(&scene, no, &mut rng);
        let blurred_ref = noisy(&crate::image::filter::gaussian_blur_wide(&scene, 1.2), np, &mut rng);
        let blurred = worst(excess_detail(&sharp_open, &blurred_ref, 1.0, no, np));
        assert!(blurred > 2.0, "a blurred reference: worst band {blurred:.2}");
    }

    #[test]
    fn otf_is_one_at_dc_zero_at_cutoff_and_decreasing() {
        assert!((circular_otf(0.0) - 1.0).abs() < 1e-12);
        assert_eq!(circular_otf(1.0), 0.0);
        let mut last = 1.0;
        for i in 1..100 {
            let v = circular_otf(i as f64 / 100.0);
            assert!(v < last && v > 0.0);
            last = v;
        }
        // a known value: OTF(0.5) = (2/π)(π/3 − 0.5·√0.75) ≈ 0.391
        assert!((circular_otf(0.5) - 0.3910).abs() < 1e-3);
    }

    /// The Airy pattern's OTF against a direct numerical transform of the Airy intensity
    /// `(2 J1(v)/v)²`: the first dark ring at `r = 1.22 λN` gives the cut-off `f_c = 1.22/r`.
    #[test]
    fn transfer_matches_the_airy_intensity_transform() {
        // J1 by its series (fine for v < 25)
        fn j1(v: f64) -> f64 {
            let mut term = v / 2.0;
            let mut sum = term;
            for k in 1..60 {
                term *= -(v * v / 4.0) / (k as f64 * (k as f64 + 1.0));
                sum += term;
            }
            sum
        }
        let r = 3.0; // px
        let scale = 3.8317 / r; // first zero of J1 at v = 3.8317
        let n = 96;
        let mut p = vec![0.0f64; n * n];
        let ss = 4;
        for y in 0..n {
            for x in 0..n {
                let mut acc = 0.0;
                for j in 0..ss {
                    for i in 0..ss {
                        let dx = x as f64 + (i as f64 + 0.5) / ss as f64 - 0.5 - (n / 2) as f64;
                        let dy = y as f64 + (j as f64 + 0.5) / ss as f64 - 0.5 - (n / 2) as f64;
                        let v = scale * (dx * dx + dy * dy).sqrt();
                        let a = if v < 1e-9 { 1.0 } else if v > 24.0 { 0.0 } else { 2.0 * j1(v) / v };
                        acc += a * a;
                    }
                }
                p[y * n + x] = acc;
            }
        }
        let total: f64 = p.iter().sum();
        // the transform at a few frequencies along x
        for f in [0.05, 0.15, 0.25] {
            let mut re = 0.0;
            for y in 0..n {
                for x in 0..n {
                    re += p[y * n + x] * (2.0 * std::f64::consts::PI * f * (x as f64 - (n / 2) as f64)).cos();
                }
            }
            let got = re / total;
            let want = transfer(f, 0.0, r);
            // the truncated Airy tails and the series' precision allow a few percent
            assert!((got - want).abs() < 0.03, "f {f}: direct {got:.4} vs model {want:.4}");
        }
    }

    /// `sharp` blurred by the transfer function `otf(fx, fy)` on its own periodic grid.
    fn periodic_blur(sharp: &Plane, otf: impl Fn(f64, f64) -> f64) -> Plane {
        let fft = Fft2::plan(sharp.width, sharp.height);
        let mut spec = fft.forward(&sharp.data);
        for (i, s) in spec.iter_mut().enumerate() {
            let (fx, fy) = fft.frequency(i);
            *s *= otf(fx as f64, fy as f64) as f32;
        }
        Plane { width: sharp.width, height: sharp.height, data: fft.inverse(spec) }
    }

    /// Uniform noise of seed `seed` smoothed by a Gaussian of `sigma` px: a textured sharp image.
    fn smooth_noise(w: usize, h: usize, seed: u64, sigma: f64) -> Plane {
        let mut r = Rng::new(seed);
        crate::image::filter::gaussian_blur(&Plane::from_fn(w, h, |_, _| r.uniform() as f32), sigma)
    }

    /// L2 distance of `a` and `b` away from a border of `m` pixels.
    fn interior_error(a: &Plane, b: &Plane, m: usize) -> f64 {
        let mut s = 0.0f64;
        for y in m..a.height - m {
            for x in m..a.width - m {
                s += ((a.get(x, y) - b.get(x, y)) as f64).powi(2);
            }
        }
        s.sqrt()
    }

    #[test]
    fn restore_undoes_the_blur_where_the_otf_is_strong() {
        let (w, h) = (96, 80);
        let sharp = smooth_noise(w, h, 5, 1.2);
        // blur with D by FFT on a large periodic grid (periodic sharp image)
        let blurred = periodic_blur(&sharp, |fx, fy| transfer(fx, fy, 2.0));
        let restored = restore(&blurred, &ReferencePsf::airy(2.0), 1e-4);
        let err = |a: &Plane| interior_error(a, &sharp, 16);
        assert!(err(&restored) < 0.25 * err(&blurred), "restored {:.4} vs blurred {:.4}", err(&restored), err(&blurred));
    }

    /// [`rerestored_kernel`]: a kernel carried from the restoration at one radius to another
    /// keeps the prediction `K * W * P` (the search's fits at a neighbouring radius start where
    /// the last one stood) to within half the error of the kernel left as it was (measured: 0.030
    /// and 0.011 against 0.090 and 0.082; the 31-px crop, the clamp at zero and `1/Ŵ_to ≈ D̂_to` keep it
    /// from exact). Both ways: to a smaller radius (the kernel sharpens) and to a larger one.
    #[test]
    fn a_kernel_carried_to_another_restoration_keeps_the_prediction() {
        let (w, h) = (96, 80);
        let sharp = smooth_noise(w, h, 7, 1.0);
        let reference = periodic_blur(&sharp, |fx, fy| transfer(fx, fy, 2.5));
        let kernel = {
            let k = Plane::from_fn(31, 31, |x, y| (-((x as f32 - 15.0).powi(2) + (y as f32 - 15.0).powi(2)) / 18.0).exp());
            let s = k.sum() as f32;
            k.map(|v| v / s)
        };
        // `K * W * P` on the interior (the kernel never leaves the image there)
        let predict = |k: &Plane, psf: &ReferencePsf, eps: f64| {
            let restored = restore(&reference, psf, eps);
            Plane::from_fn(w, h, |x, y| {
                if x < 15 || y < 15 || x + 15 >= w || y + 15 >= h {
                    return 0.0;
                }
                (0..31).flat_map(|j| (0..31).map(move |i| (i, j))).map(|(i, j)| k.get(i, j) * restored.get(x + 15 - i, y + 15 - j)).sum()
            })
        };
        for (r_from, r_to) in [(3.0, 2.0), (2.0, 3.0)] {
            // the new restoration's own ε differs (it is measured per radius)
            let (from, to, eps, eps_to) = (ReferencePsf::airy(r_from), ReferencePsf::airy(r_to), 1e-3, 3e-3);
            let want = predict(&kernel, &from, eps);
            let carried = rerestored_kernel(&kernel, (&from, eps), &to);
            assert!((carried.sum() - kernel.sum()).abs() < 1e-5 && carried.data.iter().all(|v| *v >= 0.0), "{r_from} → {r_to}: sum {} or a negative value", carried.sum());
            let (e_carried, e_kept) = (interior_error(&predict(&carried, &to, eps_to), &want, 16), interior_error(&predict(&kernel, &to, eps_to), &want, 16));
            assert!(e_carried < 0.5 * e_kept, "{r_from} → {r_to}: carried kernel misses the prediction by {e_carried:.4}, the kept kernel by {e_kept:.4}");
        }
    }

    /// `D̂_a` is the diffraction transfer times the Gaussian's (`exp(−2π²σ²f²)`), and restoring
    /// an Airy ⊛ Gaussian blur with the Gaussian modelled beats the Airy pattern alone.
    #[test]
    fn aberrated_transfer_and_its_restoration() {
        assert_eq!(reference_transfer(0.1, 0.2, 1.5, 0.0), transfer(0.1, 0.2, 1.5));
        let want = transfer(0.2, 0.0, 1.5) * (-2.0 * std::f64::consts::PI.powi(2) * 0.49 * 0.04f64).exp();
        assert!((reference_transfer(0.2, 0.0, 1.5, 0.7) - want).abs() < 1e-12);
        let (w, h) = (96, 80);
        let sharp = smooth_noise(w, h, 6, 1.0);
        let blurred = periodic_blur(&sharp, |fx, fy| reference_transfer(fx, fy, 1.5, 0.7));
        let err = |a: &Plane| interior_error(a, &sharp, 16);
        let (with, without) = (err(&restore(&blurred, &ReferencePsf { aberration_px: 0.7, ..ReferencePsf::airy(1.5) }, 1e-4)), err(&restore(&blurred, &ReferencePsf::airy(1.5), 1e-4)));
        assert!(with < 0.7 * without, "with the Gaussian {with:.4}, Airy alone {without:.4}");
    }

    /// MTF50 of an Airy pattern: `OTF(ν) = ½` at `ν ≈ 0.4040`, times the pixel's sinc; it falls
    /// as the radius, the aberrations or the band grow.
    #[test]
    fn mtf50_of_the_reference() {
        let r = 2.5;
        let f = ReferencePsf::airy(r).mtf50();
        assert!((ReferencePsf::airy(r).transfer(f, 0.0) - 0.5).abs() < 1e-9);
        // the pixel's sinc pulls it below the OTF's own half point 0.4040·f_c
        let nu = 0.4040 * 1.22 / r;
        assert!(f < nu && f > 0.8 * nu, "{f} vs {nu}");
        let wider = ReferencePsf { aberration_px: 0.5, ..ReferencePsf::airy(r) }.mtf50();
        let band = ReferencePsf { bandwidth: 0.09, ..ReferencePsf::airy(r) }.mtf50();
        assert!(wider < f && ReferencePsf::airy(1.2 * r).mtf50() < f, "{wider} {f}");
        // the band averages a longer and a shorter wavelength: close to the centre's
        assert!((band / f - 1.0).abs() < 0.02, "{band} {f}");
        assert_eq!(ReferencePsf::airy(0.1).mtf50(), 0.5);
    }

    /// Without a restoration the propagated energy is `ΣK²` (Parseval); the high-pass passes
    /// a delta's white noise at unit gain and a smooth kernel's far less.
    #[test]
    fn propagated_energy_parseval_and_highpass() {
        let mut delta = Plane::new(9, 9);
        delta.set(4, 4, 1.0);
        assert!((propagated_energy(&delta, None, true) - 1.0).abs() < 1e-4);
        let g = Plane::from_fn(9, 9, |x, y| (-((x as f32 - 4.0).powi(2) + (y as f32 - 4.0).powi(2)) / 4.5).exp());
        let k2: f32 = g.data.iter().map(|v| v * v).sum();
        assert!((propagated_energy(&g, None, false) / k2 - 1.0).abs() < 1e-4);
        assert!(propagated_energy(&g, None, true) < 0.05 * k2);
    }

    #[test]
    fn noise_gain_grows_as_epsilon_falls_and_matches_a_delta_kernel() {
        let mut delta = Plane::new(9, 9);
        delta.set(4, 4, 1.0);
        let big = noise_gain(&delta, &ReferencePsf::airy(2.5), 1e-3);
        let small = noise_gain(&delta, &ReferencePsf::airy(2.5), 1e-1);
        assert!(big > small && small > 0.0, "{big} {small}");
        // a delta kernel: Σ W² = mean over frequencies of Ŵ²
        let n = good_size(64);
        let mut acc = 0.0f64;
        for j in 0..n {
            for i in 0..n {
                let fx = if i <= n / 2 { i as f64 } else { i as f64 - n as f64 } / n as f64;
                let fy = if j <= n / 2 { j as f64 } else { j as f64 - n as f64 } / n as f64;
                let d = transfer(fx, fy, 2.5);
                acc += (d / (d * d + 1e-1)).powi(2);
            }
        }
        let want = acc / (n * n) as f64;
        assert!((small as f64 / want - 1.0).abs() < 1e-3, "{small} vs {want}");
    }
    /// Three channels of one grey target, each blurred by its band's diffraction at one stop
    /// (`N/p` 3.2), all by a common Gaussian (residual aberrations, `σ_a` 0.5 px), with
    /// different colour scales and white noise: [`spectral_stop`] recovers the stop within 1 %,
    /// as the common blur and the scales cancel in the channels' ratio. A blur that does not
    /// scale with wavelength (the same Gaussian in every channel, no diffraction) is not read
    /// as a stop, nor is a single channel.
    #[test]
    fn the_stop_is_read_from_the_channels_spectra() {
        let (w, h) = (384, 256);
        let mut rng = crate::rng::Rng::new(17);
        let target: Vec<f32> = (0..w * h).map(|_| rng.normal() as f32 * 0.1).collect();
        let fft = Fft2::plan(w, h);
        let spec = fft.forward(&target);
        let names = ["R", "G", "B"];
        let render = |rng: &mut crate::rng::Rng, np: Option<f64>| -> Vec<Plane> {
            (0..3)
                .map(|c| {
                    let psf = ReferencePsf { radius_px: 1.22 * channel_wavelength_um(names[c]) * np.unwrap_or(1.0), aberration_px: 0.5, bandwidth: channel_bandwidth(names[c]) };
                    let mut s = spec.clone();
                    for (i, v) in s.iter_mut().enumerate() {
                        let (fx, fy) = fft.frequency(i);
                        let (fx, fy) = (fx as f64, fy as f64);
                        let d = if np.is_some() { psf.transfer(fx, fy) } else { (-2.0 * std::f64::consts::PI.powi(2) * 1.2f64.powi(2) * (fx * fx + fy * fy)).exp() };
                        *v *= (d * [0.8, 1.0, 0.6][c]) as f32;
                    }
                    let mut p = Plane { width: w, height: h, data: fft.inverse(s) };
                    p.data.iter_mut().for_each(|v| *v += 0.3 + (rng.normal() * 1e-3) as f32);
                    p
                })
                .collect()
        };
        let planes = render(&mut rng, Some(3.2));
        let stop = spectral_stop(&planes, &names).expect("a stop");
        assert!((stop.f_number_per_um_pitch / 3.2 - 1.0).abs() < 0.01, "{stop:?}");
        assert!(stop.spread < 0.05 * 3.2 && stop.bands >= 2 * STOP_MIN_BANDS, "{stop:?}");
        assert_eq!(spectral_stop(&render(&mut rng, None), &names), None, "a grey blur is not a stop");
        assert_eq!(spectral_stop(&planes[1..2], &["G"]), None, "one channel");
        assert_eq!(spectral_stop(&planes, &["Y", "Y", "Y"]), None, "no known wavelengths");
        // any order, and two channels suffice
        let bgr = [planes[2].clone(), planes[1].clone(), planes[0].clone()];
        let reordered = spectral_stop(&bgr, &["B", "G", "R"]).expect("a stop in B, G, R order");
        assert!((reordered.f_number_per_um_pitch / stop.f_number_per_um_pitch - 1.0).abs() < 1e-9, "{reordered:?}");
        let two = spectral_stop(&planes[..2], &["R", "G"]).expect("a stop from R and G");
        assert!((two.f_number_per_um_pitch / 3.2 - 1.0).abs() < 0.02, "{two:?}");
        // too small to fit quadrants: no stop, no panic
        let tiny: Vec<Plane> = planes.iter().map(|p| Plane::from_fn(40, 1, |x, _| p.get(x, 0))).collect();
        assert_eq!(spectral_stop(&tiny, &names), None);
    }

    /// A white target of variance `σ²_S`, blurred by `D̂` with white noise `σ²_P` added: the
    /// noise-to-signal ratio recovers `σ²_P/σ²_S` from the plane, and `epsilon` bounds it below.
    #[test]
    fn noise_to_signal_recovers_a_white_targets_ratio() {
        let n = 256;
        let psf = ReferencePsf::airy(2.5);
        let mut rng = crate::rng::Rng::new(9);
        let fft = Fft2::plan(n, n);
        for (var_s, var_p) in [(1e-2f64, 1e-4f64), (1e-2, 1e-7)] {
            let target: Vec<f32> = (0..n * n).map(|_| (rng.normal() * var_s.sqrt()) as f32).collect();
            let mut spec = fft.forward(&target);
            for (i, v) in spec.iter_mut().enumerate() {
                let (fx, fy) = fft.frequency(i);
                *v *= psf.transfer(fx as f64, fy as f64) as f32;
            }
            let mut p = Plane { width: n, height: n, data: fft.inverse(spec) };
            p.data.iter_mut().for_each(|v| *v += (rng.normal() * var_p.sqrt()) as f32 + 0.5);
            let r = noise_to_signal(&p, var_p, &psf);
            assert!((r / (var_p / var_s) - 1.0).abs() < 0.1, "{r} vs {}", var_p / var_s);
            // 1e-2 is above the bound and kept; 1e-5 is below it and raised to it
            let e = epsilon(&p, var_p, &psf);
            if var_p / var_s > EPSILON_MIN { assert_eq!(e, r) } else { assert_eq!(e, EPSILON_MIN) }
        }
    }

    /// A printed-like target (white noise blurred, so its spectrum falls) seen wide open
    /// through a sharp Gaussian kernel `K` with sensor noise about as strong as the lost signal, and stopped down through the Airy
    /// disc `D` without noise: the prediction `K * S̃` from the restored reference misses
    /// `K * S` by the lost signal's variance, which [`lost_signal_variance`] predicts from the
    /// wide-open capture's PSD within 10 %; the white-target formula (the same target variance
    /// spread evenly) overstates it several times.
    #[test]
    fn the_lost_signal_is_predicted_from_the_wide_open_spectrum() {
        let n = 256;
        let psf = ReferencePsf::airy(2.5);
        let (sigma_k, noise_var, eps) = (0.6f64, 2e-6f64, 1e-3f64);
        let mut rng = crate::rng::Rng::new(7);
        let fft = Fft2::plan(n, n);
        let filtered = |data: &[f32], t: &dyn Fn(f64, f64) -> f64| -> Vec<f32> {
            let mut spec = fft.forward(data);
            for (i, v) in spec.iter_mut().enumerate() {
                let (fx, fy) = fft.frequency(i);
                *v *= t(fx as f64, fy as f64) as f32;
            }
            fft.inverse(spec)
        };
        let gauss = |s: f64| move |fx: f64, fy: f64| (-2.0 * std::f64::consts::PI.powi(2) * s * s * (fx * fx + fy * fy)).exp();
        let white: Vec<f32> = (0..n * n).map(|_| rng.normal() as f32 * 0.2).collect();
        let target = filtered(&white, &gauss(0.8));
        let sharp_open = filtered(&target, &gauss(sigma_k));
        let open = Plane { width: n, height: n, data: sharp_open.iter().map(|v| v + (rng.normal() * noise_var.sqrt()) as f32).collect() };
        let reference = Plane { width: n, height: n, data: filtered(&target, &|fx, fy| psf.transfer(fx, fy)) };
        let predicted = filtered(&restore(&reference, &psf, eps).data, &gauss(sigma_k));
        let (m, mut acc, mut count) = (32, 0.0f64, 0usize);
        for y in m..n - m {
            for x in m..n - m {
                acc += ((predicted[y * n + x] - sharp_open[y * n + x]) as f64).powi(2);
                count += 1;
            }
        }
        let measured = acc / count as f64;
        let psd = crate::image::spectrum::RadialPsd::of(&open);
        let predicted_var = lost_signal_variance(&psd, noise_var, &psf, eps);
        assert!((predicted_var / measured - 1.0).abs() < 0.10, "lost signal: measured {measured:.3e}, predicted {predicted_var:.3e}");
        let mut delta = Plane::new(9, 9);
        delta.set(4, 4, 1.0);
        let var_target = Plane { width: n, height: n, data: target }.variance();
        let (_, white_lost) = propagated_energies(&delta, Some((&psf, eps)), false);
        assert!(white_lost as f64 * eps * var_target > 3.0 * measured, "white-target formula {:.3e} against {measured:.3e}", white_lost as f64 * eps * var_target);
    }

    /// The detail the restoration gives up (module docs): a white target of variance
    /// `σ²_S = σ²_P/ε` blurred by `D` and restored without noise misses `σ²_P` times the lost
    /// energy of a delta kernel ([`propagated_energies`]); restored alone, white noise of
    /// variance `σ²_P` comes out with the noise energy; both also through the noise
    /// measurement's high-pass.
    #[test]
    fn lost_detail_and_noise_energies_match_a_restored_white_target() {
        let n = 256;
        let psf = ReferencePsf::airy(2.5);
        let (var_s, var_p) = (1e-2f64, 1e-4f64);
        let eps = var_p / var_s;
        let mut rng = crate::rng::Rng::new(5);
        let white = |rng: &mut crate::rng::Rng, var: f64| -> Vec<f32> { (0..n * n).map(|_| (rng.normal() * var.sqrt()) as f32).collect() };
        let target = white(&mut rng, var_s);
        let noise = white(&mut rng, var_p);
        let fft = Fft2::plan(n, n);
        let mut spec = fft.forward(&target);
        for (i, v) in spec.iter_mut().enumerate() {
            let (fx, fy) = fft.frequency(i);
            *v *= psf.transfer(fx as f64, fy as f64) as f32;
        }
        let blurred = Plane { width: n, height: n, data: fft.inverse(spec) };
        // mean squares over the interior (the mirror padding differs from the periodic blur at
        // the edges), of the plane and of its high-pass `d` (the noise measurement's)
        let interior_msq = |p: &Plane| {
            let m = 32;
            let (mut acc, mut acc_hp, mut count) = (0.0f64, 0.0f64, 0usize);
            for y in m..n - m {
                for x in m..n - m {
                    acc += (p.get(x, y) as f64).powi(2);
                    acc_hp += (super::super::noise::highpass(&p.data, n, y * n + x) as f64).powi(2);
                    count += 1;
                }
            }
            (acc / count as f64 / var_p, acc_hp / count as f64 / var_p)
        };
        let restored = restore(&blurred, &psf, eps);
        let (lost, lost_hp) = interior_msq(&Plane { width: n, height: n, data: restored.data.iter().zip(&target).map(|(r, t)| r - t).collect() });
        let (amplified, amplified_hp) = interior_msq(&restore(&Plane { width: n, height: n, data: noise }, &psf, eps));
        let mut delta = Plane::new(9, 9);
        delta.set(4, 4, 1.0);
        let close = |measured: f64, predicted: f32| (measured / predicted as f64 - 1.0).abs() < 0.08;
        let (e, l) = propagated_energies(&delta, Some((&psf, eps)), false);
        assert!(close(lost, l), "lost detail: measured {lost:.2}, predicted {l:.2}");
        assert!(close(amplified, e), "noise: measured {amplified:.2}, predicted {e:.2}");
        let (eh, lh) = propagated_energies(&delta, Some((&psf, eps)), true);
        assert!(close(lost_hp, lh), "lost detail's high-pass: measured {lost_hp:.2}, predicted {lh:.2}");
        assert!(close(amplified_hp, eh), "noise's high-pass: measured {amplified_hp:.2}, predicted {eh:.2}");
        let (plain, none_lost) = propagated_energies(&delta, None, false);
        assert!((plain - 1.0).abs() < 1e-5 && none_lost == 0.0, "{plain} {none_lost}");
        // the lost detail lies beyond the pass band, where the high-pass gains more than its
        // white-noise mean of 1; the amplified noise peaks inside it
        assert!(lh > l && lh / l > eh / e, "noise {e} → {eh}, lost {l} → {lh}");
    }
}

#[cfg(test)]
mod simulator_tests {
    use super::*;
    use crate::optics::capture::{render, Sensor, Shot};
    use crate::optics::lens::{mono_band, LensModel};
    use crate::rng::Rng;

    /// A reference rendered by the lens simulator at f/11 (diffraction, pixel integration, the
    /// lens's residual aberrations) is brought closer to the ideal one by [`restore`] with the
    /// nominal Airy radius than with a wrong one.
    #[test]
    fn restoring_a_simulated_stopped_down_reference() {
        let (w, h) = (192, 144);
        let mut lens = LensModel::demo(w, h);
        lens.bands = mono_band();
        let sc = vec![crate::diagnose::proof::scene(w, h, 3)];
        let sensor = Sensor { noise: false, ..Sensor::default() };
        let n = 11.0;
        let ideal = render(&sc, &lens, &Shot::ideal(0.7), &sensor, &mut Rng::new(1));
        let stopped = render(&sc, &lens, &Shot::lens(n, 0.7, 3, 2, 15), &sensor, &mut Rng::new(1));
        let (lw, ww) = lens.bands.iter().flat_map(|b| b.wavelengths.iter()).fold((0.0, 0.0), |(a, b), (l, w)| (a + l * w, b + w));
        let r_true = 1.22 * lw / ww / 1000.0 * n / lens.pixel_pitch_um;
        let err = |p: &Plane| {
            let mut s = 0.0f64;
            for y in 20..h - 20 {
                for x in 20..w - 20 {
                    s += ((p.get(x, y) - ideal.clean[0].get(x, y)) as f64).powi(2);
                }
            }
            s.sqrt()
        };
        let e0 = err(&stopped.clean[0]);
        let mut rows = vec![];
        for r in [0.6 * r_true, r_true, 1.6 * r_true] {
            rows.push((r, err(&restore(&stopped.clean[0], &ReferencePsf::airy(r), 1e-3))));
        }
        eprintln!("unrestored {e0:.4}; {rows:?}");
        // with a 16-frame average's noise and the measured ε
        let noisy_sensor = Sensor { full_well_e: 16.0 * 20_000.0, read_noise_e: 24.0, ..Sensor::default() };
        let noisy = render(&sc, &lens, &Shot::lens(n, 0.7, 3, 2, 15), &noisy_sensor, &mut Rng::new(2));
        let nv = noisy.variance[0].mean();
        let mut nrows = vec![];
        for r in [0.6 * r_true, 0.9 * r_true, r_true, 1.1 * r_true, 1.35 * r_true, 1.6 * r_true] {
            let psf = ReferencePsf::airy(r);
            let e = epsilon(&noisy.image.planes[0], nv, &psf);
            nrows.push((r, e, err(&restore(&noisy.image.planes[0], &psf, e))));
        }
        eprintln!("noisy: unrestored {:.4}; {nrows:?}", err(&noisy.image.planes[0]));
        assert!(rows[1].1 < 0.5 * e0, "{rows:?} vs {e0}");
        assert!(rows[1].1 < rows[0].1 && rows[1].1 < rows[2].1, "{rows:?}");
    }
}
