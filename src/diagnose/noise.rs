//! The noise model, measured from the wide-open capture alone — or, when a capture session
//! averaged several frames, from those frames' temporal variance (the sidecar's
//! `temporal_noise`, [`crate::rig::camera::temporal_noise_curve`]: at every pixel the sample
//! variance over the frames, binned by level, divided by the frame count for the average),
//! which needs no model of the signal at all and is preferred by `diagnose --session`.
//!
//! # Method
//! At every pixel whose 3×3 neighbourhood is neither clipped nor black, the high-pass
//! `d = (4·c − n − s − e − w) / √20` (unit gain on white noise) removes the blurred signal and
//! keeps the noise; the 3×3 mean gives the local level. Pixels are binned by level (equal
//! counts) and each bin's variance is the squared robust deviation `(1.4826·MAD(d))²`. The
//! result is a [`NoiseCurve`]: variance of the *stored* values as a function of the stored
//! value, valid whatever the encoding. A Poisson–Gaussian law `Var = a·L + b` on the linear
//! axis `L` is then fitted to the bins ([`PoissonGaussian::fit`]) for the chosen transfer
//! curve; how well it fits is itself evidence about the encoding.
//!
//! The curve is a property of the sensor, so the same curve describes the pinhole capture
//! (same camera): its noise is propagated through the kernel as
//! `Var_pred = s²·ΣK²·Var_pinhole` ([`super::fit`]). Measured from a model's residual, the
//! curve must not count that propagated noise as the wide-open capture's: with a restored
//! reference (`pinhole_diffraction`) it dominates the residual's high-pass
//! ([`measure_residual`]).
//!
//! All variances are on the full-scale axis squared ([`crate::image`]).

use crate::image::{Plane, Transfer};
use serde::Serialize;

/// Measured noise variance against level, stored domain, one channel.
#[derive(Clone, Debug, Serialize)]
pub struct NoiseCurve {
    /// `(mean stored value, variance of stored values, pixel count)` per bin, sorted by mean.
    pub bins: Vec<(f64, f64, usize)>,
}

impl NoiseCurve {
    /// Variance of a stored value `v`, interpolated linearly between bins and held flat
    /// beyond the measured range.
    pub fn variance(&self, v: f32) -> f32 {
        let b = &self.bins;
        if b.is_empty() {
            return 0.0;
        }
        let v = v as f64;
        if v <= b[0].0 {
            return b[0].1 as f32;
        }
        for i in 1..b.len() {
            if v <= b[i].0 {
                let t = (v - b[i - 1].0) / (b[i].0 - b[i - 1].0).max(1e-12);
                return (b[i - 1].1 + t * (b[i].1 - b[i - 1].1)) as f32;
            }
        }
        b[b.len() - 1].1 as f32
    }

    /// The curve of the noise a fit's residual came from, when the fit absorbed the fraction
    /// `alpha` of the noise's high-pass energy ([`super::kernels::Divergence`]): every bin's
    /// variance divided by `1 − alpha`.
    pub fn absorbed(mut self, alpha: f64) -> NoiseCurve {
        let f = 1.0 / (1.0 - alpha.clamp(0.0, super::kernels::MAX_ABSORBED));
        self.bins.iter_mut().for_each(|b| b.1 *= f);
        self
    }

    /// The curve's trend at a stored value `v`: linear between bins as [`NoiseCurve::variance`],
    /// extrapolated along the end segments beyond them (at least a fifth of the nearest bin).
    /// For ratios of the noise at nearby levels; 1 when the curve is empty.
    pub fn trend(&self, v: f64) -> f64 {
        let b = &self.bins;
        match b.len() {
            0 => 1.0,
            1 => b[0].1.max(1e-30),
            n => {
                let i = b.partition_point(|q| q.0 < v).clamp(1, n - 1);
                let (p, q) = (b[i - 1], b[i]);
                let t = (v - p.0) / (q.0 - p.0).max(1e-12);
                let nearest = if t < 0.5 { p.1 } else { q.1 };
                (p.1 + t * (q.1 - p.1)).max(0.2 * nearest).max(1e-30)
            }
        }
    }

    /// The curve without bin `b` (unchanged when it has fewer than three bins): the shape
    /// [`measure_residual`] normalises bin `b`'s windows by, so that no bin's own value
    /// shapes it.
    pub fn without(&self, b: usize) -> NoiseCurve {
        let mut c = self.clone();
        if c.bins.len() >= 3 && b < c.bins.len() {
            c.bins.remove(b);
        }
        c
    }

    /// Variance of a *linear* value `l` under `transfer`: `Var_stored(enc(l)) / enc'(l)²`.
    pub fn linear_variance(&self, l: f32, transfer: Transfer) -> f32 {
        match transfer {
            Transfer::Linear => self.variance(l),
            Transfer::Srgb => {
                let d = srgb_slope(l.max(1e-4));
                self.variance(transfer.encode(l.max(0.0))) / (d * d)
            }
        }
    }
}

/// Derivative of the sRGB encoding at linear value `l`.
pub fn srgb_slope(l: f32) -> f32 {
    if l <= 0.003_130_8 {
        12.92
    } else {
        1.055 / 2.4 * l.powf(1.0 / 2.4 - 1.0)
    }
}

/// Measures the noise curve of one stored plane with `bins` level bins.
pub fn measure(p: &Plane, bins: usize) -> NoiseCurve {
    let (w, h) = (p.width, p.height);
    let mut pairs: Vec<(f32, f32)> = Vec::with_capacity(w * h);
    for y in 1..h.saturating_sub(1) {
        for x in 1..w.saturating_sub(1) {
            let mut sum = 0.0;
            let mut ok = true;
            for j in 0..3 {
                for i in 0..3 {
                    let v = p.get(x + i - 1, y + j - 1);
                    ok &= v > 0.0 && v < 0.995;
                    sum += v;
                }
            }
            if !ok {
                continue;
            }
            let c = p.get(x, y);
            let d = (4.0 * c - p.get(x - 1, y) - p.get(x + 1, y) - p.get(x, y - 1) - p.get(x, y + 1)) / 20f32.sqrt();
            pairs.push((sum / 9.0, d));
        }
    }
    if pairs.is_empty() {
        return NoiseCurve { bins: vec![] };
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let nb = bins.clamp(1, (pairs.len() / 200).max(1));
    let mut out = Vec::with_capacity(nb);
    for b in 0..nb {
        let chunk = &pairs[b * pairs.len() / nb..(b + 1) * pairs.len() / nb];
        let mean = chunk.iter().map(|q| q.0 as f64).sum::<f64>() / chunk.len() as f64;
        let mut d: Vec<f32> = chunk.iter().map(|q| q.1).collect();
        let med = median(&mut d);
        let mut dev: Vec<f32> = d.iter().map(|v| (v - med).abs()).collect();
        let mad = median(&mut dev) as f64 * 1.4826;
        out.push((mean, mad * mad, chunk.len()));
    }
    NoiseCurve { bins: out }
}

/// Measures the noise curve from a model's residual `open − predicted` (stored axis) instead
/// of the image: the high-pass `d` of the residual, in `win × win` windows, after removing the
/// part proportional to the high-pass of the prediction (a local gain error: vignetting,
/// gradients, glare and tone errors are locally gains, offsets vanish in the high-pass). The
/// windows are binned by level and each bin takes the lower quartile of its windows'
/// variances, divided by the lower quartile of `χ²_{n−1}/(n−1)`, so windows that still hold
/// model error do not inflate the noise. The quartile is taken of each window's variance over
/// the curve's trend at the window's own level (two passes, [`NoiseCurve::trend`]), times the
/// trend at the bin's mean level: otherwise the noise's growth with the level inside a bin
/// makes the quartile pick the darker windows (7–8 % low on the proof scenes). The trend a bin
/// is normalised by is that of the *other* bins ([`NoiseCurve::without`]): a bin of windows
/// that straddle a target's dark and bright cells spans most of the range between them, and
/// normalised by a trend through its own low first-pass value it kept that value (0.48× the
/// law on a large-cell target, 0.72× at 4000×3000, where it was the noise law's misfit).
/// `mask` marks
/// usable pixels. The result is the noise the residual holds: a fit that absorbed part of it
/// is corrected by the caller ([`NoiseCurve::absorbed`]).
///
/// The prediction carries the reference's noise (propagated through the kernel and, with
/// `pinhole_diffraction`, amplified by the restoration); `reference_hp` is the variance it
/// adds to `d` at each pixel relative to the wide-open noise variance `v` there
/// ([`super::fit::Fit::reference_highpass`], ρ). With `q` that noise's high-pass, `e` the
/// wide-open noise's and `s` the prediction's signal high-pass, a window of `n` pixels holds
/// `a = e + γ·s − q` (residual) and `b = s + q` (prediction); with `Q = Σq² = v·Σρ`,
///
/// `Σa² = (n − 1)·v + (Σab + Q)²/(Σb² − Q) + Q`
///
/// (no regression term where `Σb² ≤ Q`: no signal), solved for `v` by fixed-point iteration.
/// `Q` scales with `v`, so the estimate divides by `n − 1 + Σρ` instead of subtracting a
/// separately estimated `Q`: well conditioned even where the reference's noise dominates
/// (a restored reference).
pub fn measure_residual(open: &Plane, predicted: &Plane, mask: &[bool], win: usize, bins: usize, reference_hp: Option<&Plane>) -> NoiseCurve {
    measure_residual_passes(open, predicted, mask, win, bins, reference_hp, LEVEL_PASSES)
}

/// [`measure_residual`] with `passes` of the level normalisation (0: none).
fn measure_residual_passes(open: &Plane, predicted: &Plane, mask: &[bool], win: usize, bins: usize, reference_hp: Option<&Plane>, passes: usize) -> NoiseCurve {
    let (w, h) = (open.width, open.height);
    let res: Vec<f32> = open.data.iter().zip(&predicted.data).map(|(o, p)| o - p).collect();
    let mut windows: Vec<(f64, f64)> = Vec::new();
    for wy in 0..h / win {
        for wx in 0..w / win {
            let (mut n, mut rr, mut pp, mut rp, mut lv, mut qq) = (0usize, 0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
            for y in (wy * win).max(1)..((wy + 1) * win).min(h - 1) {
                for x in (wx * win).max(1)..((wx + 1) * win).min(w - 1) {
                    let ok = [y * w + x, y * w + x - 1, y * w + x + 1, (y - 1) * w + x, (y + 1) * w + x].iter().all(|&i| mask[i] && open.data[i] < 0.995 && open.data[i] > 0.0);
                    if !ok {
                        continue;
                    }
                    let a = highpass(&res, w, y * w + x) as f64;
                    let b = highpass(&predicted.data, w, y * w + x) as f64;
                    n += 1;
                    qq += reference_hp.map_or(0.0, |q| q.data[y * w + x] as f64);
                    rr += a * a;
                    pp += b * b;
                    rp += a * b;
                    lv += open.data[y * w + x] as f64;
                }
            }
            if n * 5 < win * win * 4 || n < 16 {
                continue;
            }
            let explained = |q: f64| {
                let signal = pp - q;
                if signal > 1e-3 * pp && pp > 0.0 {
                    ((rp + q).powi(2) / signal).min(rr)
                } else {
                    0.0
                }
            };
            let mut v = (rr - explained(0.0)) / (n as f64 - 1.0 + qq);
            for _ in 0..8 {
                v = (rr - explained(v * qq)).max(0.0) / (n as f64 - 1.0 + qq);
            }
            if v <= 0.0 {
                continue;
            }
            windows.push((lv / n as f64, v));
        }
    }
    if windows.is_empty() {
        return NoiseCurve { bins: vec![] };
    }
    windows.sort_by(|a, b| a.0.total_cmp(&b.0));
    let nb = bins.clamp(1, (windows.len() / 12).max(1));
    let dof = ((win * win) as f64 * 0.9 - 2.0).max(4.0);
    let q25 = 1.0 - 0.6745 * (2.0 / dof).sqrt();
    // the noise grows with the level inside a bin too, and the lower quartile picks the
    // darker windows: each window is compared with the curve's trend at its own level (the
    // previous pass's bins), so the quartile measures the noise, not the level spread
    let mut curve = NoiseCurve { bins: lower_quartiles(&windows, nb, q25, &|_, _| 1.0) };
    for _ in 0..passes {
        // bin b's shape is the trend of the other bins: with its own (biased) value in it, a
        // bin of mixed windows normalises itself and the bias is a fixed point
        let others: Vec<NoiseCurve> = (0..curve.bins.len()).map(|b| curve.without(b)).collect();
        curve = NoiseCurve { bins: lower_quartiles(&windows, nb, q25, &|b, l| others[b].trend(l)) };
    }
    curve
}

/// Passes of [`measure_residual`]'s level normalisation (the curve's shape converges in two).
const LEVEL_PASSES: usize = 2;

/// Per level bin `b` of `windows` (`(level, variance)`, sorted by level; `nb` bins of equal
/// counts): `(mean level, variance, count)`, the variance the lower quartile of
/// `variance / shape(b, level)` over the bin, times `shape(b, mean level)`, over `q25` (the
/// lower quartile of a window's variance in units of its expectation).
fn lower_quartiles(windows: &[(f64, f64)], nb: usize, q25: f64, shape: &dyn Fn(usize, f64) -> f64) -> Vec<(f64, f64, usize)> {
    (0..nb)
        .map(|b| {
            let chunk = &windows[b * windows.len() / nb..(b + 1) * windows.len() / nb];
            let mean = chunk.iter().map(|q| q.0).sum::<f64>() / chunk.len() as f64;
            let mut v: Vec<f64> = chunk.iter().map(|q| q.1 / shape(b, q.0)).collect();
            v.sort_by(|a, b| a.total_cmp(b));
            let lq = v[(v.len() - 1) / 4];
            (mean, lq * shape(b, mean) / q25, chunk.len())
        })
        .collect()
}

/// The high-pass `d = (4·c − n − s − e − w) / √20` (unit gain on white noise) of a row-major
/// image of width `w` at the interior index `i`.
pub fn highpass(data: &[f32], w: usize, i: usize) -> f32 {
    (4.0 * data[i] - data[i - 1] - data[i + 1] - data[i - w] - data[i + w]) / 20f32.sqrt()
}

fn median(v: &mut [f32]) -> f32 {
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m
}

/// Relative precision assumed for one bin of a [`NoiseCurve`] when scoring a law against it.
pub const BIN_PRECISION: f64 = 0.05;

/// `Var = a·L + b` on the linear axis: `a` the inverse gain (full scale per electron), `b` the
/// read (and quantisation) noise variance; both non-negative (the physics of a sensor).
#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct PoissonGaussian {
    pub a: f64,
    pub b: f64,
    /// RMS relative deviation of the bins from the fitted law (0.05 = 5%).
    pub misfit: f64,
    /// `Σ (relative deviation / BIN_PRECISION)²` over the bins: the law's share of the
    /// likelihood, added to a model's BIC (an sRGB-encoded sensor's variance *falls* with the
    /// stored level, which no non-negative linear law can follow).
    pub chi2: f64,
}

impl PoissonGaussian {
    /// Weighted least-squares fit with `a, b ≥ 0` to a curve's bins mapped to the linear axis
    /// by `transfer` (relative errors: weights `1/Var²`, which suits a law spanning decades).
    pub fn fit(curve: &NoiseCurve, transfer: Transfer) -> PoissonGaussian {
        Self::fit_pedestal(curve, transfer, 0.0)
    }

    /// [`PoissonGaussian::fit`] of `Var = a·(L − β) + b` for a model whose wide-open capture
    /// carries a `black_level` offset `β` (linear full scale): a pedestal adds no noise, so the
    /// law's intercept on the stored level may reach `b − a·β`. Only a positive `β` shifts the
    /// axis (an offset the reference carries, or ambient light, which brings its own shot noise,
    /// are then `b ≥ a·β`: still within the law). `L` and `β` on the linear axis of `transfer`.
    pub fn fit_pedestal(curve: &NoiseCurve, transfer: Transfer, beta: f64) -> PoissonGaussian {
        let beta = if beta.is_finite() { beta.max(0.0) } else { 0.0 };
        let pts: Vec<(f64, f64)> = curve
            .bins
            .iter()
            .map(|&(m, _, _)| {
                let l = transfer.decode(m as f32).max(0.0);
                ((l as f64 - beta).max(0.0), curve.linear_variance(l, transfer) as f64)
            })
            .filter(|p| p.1 > 0.0)
            .collect();
        if pts.is_empty() {
            return PoissonGaussian { a: 0.0, b: 0.0, misfit: 0.0, chi2: 0.0 };
        }
        let (mut s00, mut s01, mut s11, mut t0, mut t1) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for &(l, v) in &pts {
            let wt = 1.0 / (v * v);
            s00 += wt * l * l;
            s01 += wt * l;
            s11 += wt;
            t0 += wt * l * v;
            t1 += wt * v;
        }
        let det = s00 * s11 - s01 * s01;
        let (mut a, mut b) = if det.abs() > 1e-300 { ((t0 * s11 - t1 * s01) / det, (s00 * t1 - s01 * t0) / det) } else { (0.0, t1 / s11) };
        let score = |a: f64, b: f64| pts.iter().map(|&(l, v)| ((a * l + b) / v - 1.0).powi(2)).sum::<f64>();
        if a < 0.0 || b < 0.0 {
            // the better of the two boundary solutions
            let (a1, b1) = (0.0, t1 / s11.max(1e-300));
            let (a2, b2) = (t0 / s00.max(1e-300), 0.0);
            (a, b) = if score(a1, b1) <= score(a2, b2) { (a1, b1) } else { (a2, b2) };
        }
        let ss = score(a, b);
        PoissonGaussian { a, b, misfit: (ss / pts.len() as f64).sqrt(), chi2: ss / (BIN_PRECISION * BIN_PRECISION) }
    }

    pub fn variance(&self, l: f64) -> f64 {
        self.a * l.max(0.0) + self.b
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn recovers_a_poisson_gaussian_law_on_smooth_data() {
        let mut r = Rng::new(4);
        let (a, b) = (5e-5, 1e-6);
        let p = Plane::from_fn(300, 200, |x, y| {
            let l = 0.05 + 0.9 * (x as f64 / 300.0) * (0.5 + 0.5 * (y as f64 / 40.0).sin().abs());
            (l + (a * l + b).sqrt() * r.normal()) as f32
        });
        let c = measure(&p, 12);
        let pg = PoissonGaussian::fit(&c, Transfer::Linear);
        assert!((pg.a / a - 1.0).abs() < 0.08, "{pg:?}");
        assert!(pg.misfit < 0.08, "{pg:?}");
        for &(m, v, _) in &c.bins {
            let want = a * m + b;
            assert!((v / want - 1.0).abs() < 0.15, "bin {m}: {v} vs {want}");
        }
    }

    /// The residual's high-pass holds the wide-open noise `e` (variance `v`) and the
    /// prediction's copy of the reference's noise `q` (here white, variance `3v`: a restored
    /// reference dominates). Told `ρ = 3`, [`measure_residual`] recovers `v`. Not told, it
    /// reads high: about 1.4·v, not 4·v, because regressing on the prediction's high-pass (the
    /// local-gain term) removes part of `q` by chance. A local gain error (the prediction's
    /// signal scaled by 1.02) is regressed out either way.
    #[test]
    fn residual_noise_does_not_count_the_reference_noise() {
        let (w, h) = (320, 240);
        let mut r = Rng::new(8);
        let signal = crate::image::filter::gaussian_blur(&Plane::from_fn(w, h, |_, _| (0.2 + 0.6 * r.uniform()) as f32), 1.5);
        let v = 4e-5f64;
        let open = Plane::from_fn(w, h, |x, y| signal.get(x, y) * 1.02 + (v.sqrt() * r.normal()) as f32);
        let predicted = Plane::from_fn(w, h, |x, y| signal.get(x, y) + ((3.0 * v).sqrt() * r.normal()) as f32);
        let mask = vec![true; w * h];
        let rho = Plane::filled(w, h, 3.0);
        let mean = |c: &NoiseCurve| c.bins.iter().map(|b| b.1).sum::<f64>() / c.bins.len() as f64;
        let told = mean(&measure_residual(&open, &predicted, &mask, 16, 4, Some(&rho)));
        let untold = mean(&measure_residual(&open, &predicted, &mask, 16, 4, None));
        assert!((told / v - 1.0).abs() < 0.10, "told: {told:.3e} vs {v:.3e}");
        assert!(untold > 1.25 * v, "untold: {untold:.3e} vs {v:.3e}");
    }

    /// A perfect prediction on a scene whose level spans a decade inside the lowest bins: the
    /// residual is the Poisson–Gaussian noise itself. Without the level normalisation the
    /// lower quartile of a bin picks its darker windows and the curve reads lower; with it
    /// every bin is within 10 % of the law and the mean within 4 %.
    #[test]
    fn residual_noise_is_unbiased_across_a_bins_level_spread() {
        let (w, h) = (384, 256);
        let mut r = Rng::new(11);
        let (a, b) = (5e-5, 1e-7);
        let texture = crate::image::filter::gaussian_blur(&Plane::from_fn(w, h, |_, _| r.uniform() as f32), 1.0);
        let signal = Plane::from_fn(w, h, |x, y| (0.02 + 0.8 * (x as f32 / w as f32).powi(2)) * (0.6 + 0.8 * texture.get(x, y)));
        let open = Plane::from_fn(w, h, |x, y| {
            let l = signal.get(x, y) as f64;
            (l + (a * l + b).sqrt() * r.normal()) as f32
        });
        let ratios = |passes: usize| -> (f64, Vec<f64>) {
            let c = measure_residual_passes(&open, &signal, &vec![true; w * h], 16, 8, None, passes);
            let r: Vec<f64> = c.bins.iter().map(|&(m, v, _)| v / (a * m + b)).collect();
            (r.iter().sum::<f64>() / r.len() as f64, r)
        };
        let ((mean, r), (mean0, r0)) = (ratios(LEVEL_PASSES), ratios(0));
        eprintln!("measured / true variance per bin: {r:.3?} (mean {mean:.3}); without the level normalisation {r0:.3?} (mean {mean0:.3})");
        assert!((mean - 1.0).abs() < 0.04, "mean ratio {mean:.3}: {r:.3?}");
        assert!(r.iter().all(|q| (q - 1.0).abs() < 0.10), "{r:.3?}");
        assert!(mean0 < mean - 0.02, "without the normalisation: {mean0:.3} vs {mean:.3}");
    }

    /// A binary target of large cells (dark 0.055, bright 0.32, blurred a little), as the
    /// proof scenes look at 4000×3000: most 16-px windows are uniform and the few that hold
    /// an edge form one bin whose levels span most of the range between the two. A perfect
    /// prediction: the residual is the Poisson–Gaussian noise itself, and every bin, that
    /// mixed one too, is within 10 % of the law.
    #[test]
    fn residual_noise_is_unbiased_in_a_bin_of_mixed_windows() {
        let (w, h, cell) = (768, 512, 48);
        let mut r = Rng::new(12);
        let (a, b) = (4.4e-5, 2.9e-7);
        let cells: Vec<bool> = (0..(w / cell + 1) * (h / cell + 1)).map(|_| r.uniform() < 0.55).collect();
        let sharp = Plane::from_fn(w, h, |x, y| if cells[(y / cell) * (w / cell + 1) + x / cell] { 0.32 } else { 0.055 });
        let signal = crate::image::filter::gaussian_blur(&sharp, 2.0);
        let open = Plane::from_fn(w, h, |x, y| {
            let l = signal.get(x, y) as f64;
            (l + (a * l + b).sqrt() * r.normal()) as f32
        });
        let c = measure_residual(&open, &signal, &vec![true; w * h], 16, 8, None);
        let ratios: Vec<(f64, f64)> = c.bins.iter().map(|&(m, v, _)| (m, v / (a * m + b))).collect();
        eprintln!("level: measured / true variance per bin: {ratios:.3?}");
        assert!(ratios.iter().any(|q| q.0 > 0.09 && q.0 < 0.28), "no bin of mixed windows: {ratios:.3?}");
        assert!(ratios.iter().all(|q| (q.1 - 1.0).abs() < 0.10), "{ratios:.3?}");
        let pg = PoissonGaussian::fit(&c, Transfer::Linear);
        assert!(pg.misfit < 0.06, "{pg:?}");
    }

    /// A wide-open capture with a noiseless pedestal `β` (a black-level mismatch): its curve
    /// against the stored level has the intercept `b − a·β < 0`, which no law with `b ≥ 0`
    /// follows. Told the model's `β`, the law fits and recovers `a`; an ordinary curve fits the
    /// same whether or not its model has an offset.
    #[test]
    fn a_black_level_pedestal_shifts_the_laws_axis() {
        let (a, b, beta) = (4e-5, 2e-7, 0.035);
        let levels = [0.05, 0.06, 0.08, 0.12, 0.2, 0.3, 0.33, 0.36];
        let pedestal = NoiseCurve { bins: levels.iter().map(|&m| (m, a * (m - beta) + b, 500)).collect() };
        let plain = PoissonGaussian::fit(&pedestal, Transfer::Linear);
        let told = PoissonGaussian::fit_pedestal(&pedestal, Transfer::Linear, beta);
        assert!(plain.misfit > 0.10, "{plain:?}");
        assert!(told.misfit < 0.01 && (told.a / a - 1.0).abs() < 0.02, "{told:?}");
        let ordinary = NoiseCurve { bins: levels.iter().map(|&m| (m, a * m + b, 500)).collect() };
        let with_offset = PoissonGaussian::fit_pedestal(&ordinary, Transfer::Linear, beta);
        assert!(with_offset.misfit < 0.01 && (with_offset.a / a - 1.0).abs() < 0.02, "{with_offset:?}");
        assert_eq!(PoissonGaussian::fit_pedestal(&ordinary, Transfer::Linear, -0.02), PoissonGaussian::fit(&ordinary, Transfer::Linear));
    }

    #[test]
    fn srgb_data_misfits_a_linear_law_and_fits_after_decoding() {
        let mut r = Rng::new(5);
        let (a, b) = (5e-5, 4e-7);
        let p = Plane::from_fn(300, 200, |x, _| {
            let l = 0.02 + 0.9 * x as f64 / 300.0;
            let n = l + (a * l + b).sqrt() * r.normal();
            crate::image::srgb_encode(n as f32)
        });
        let c = measure(&p, 12);
        let lin = PoissonGaussian::fit(&c, Transfer::Linear);
        let srgb = PoissonGaussian::fit(&c, Transfer::Srgb);
        assert!(srgb.misfit < 0.1 && srgb.misfit < 0.5 * lin.misfit, "linear {lin:?} srgb {srgb:?}");
        assert!((srgb.a / a - 1.0).abs() < 0.15, "{srgb:?}");
    }
}
