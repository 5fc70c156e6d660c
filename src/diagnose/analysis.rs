//! Residual analysis of a fitted model: where the normalised residual `z = (data − model)/σ`
//! departs from unit white noise, and along which variable.
//!
//! - per tile and channel: mean, RMS (spread) and reduced χ² of `z`;
//! - dependence curves (mean `z` and mean `z²` in bins) on the predicted intensity, the radius
//!   (`r = 1` at half the diagonal), the position inside the tile (distance to the nearest tile
//!   centre over half the tile diagonal), the local gradient of the prediction, and the
//!   large-scale brightness of the reference (Gaussian σ = 1/16 of the image diagonal);
//! - a histogram of `z` against the standard normal, skewness and excess kurtosis;
//! - a planar trend of `z` (`z ≈ a + bx·x̂ + by·ŷ`);
//! - the radial power spectrum of `z` ([`radial_spectrum`]): its mean over all frequencies is
//!   the reduced χ²; white noise at the floor gives 1 in every band. The floor is not quite
//!   white: the reference's noise comes through the kernel (and, restored, is amplified near
//!   the cut-off), so its share is coloured. Stray light shows as excess at low frequencies,
//!   a blurred reference (`pinhole_diffraction`) at high ones.

use super::fit::Fit;
use crate::image::filter::gaussian_blur_wide;
use crate::image::spectrum::{band_centre, radial_power_sums, Range};
use crate::image::Plane;
use crate::solve::dense::gauss_jordan;
use serde::Serialize;

/// One dependence curve.
#[derive(Clone, Debug, Serialize)]
pub struct Curve {
    pub name: String,
    /// Bin centres (mean of the variable in the bin).
    pub x: Vec<f64>,
    /// Mean normalised residual per bin.
    pub mean: Vec<f64>,
    /// Mean squared normalised residual per bin (1 = at the noise floor).
    pub msq: Vec<f64>,
}

impl Curve {
    /// Largest minus smallest bin mean.
    pub fn mean_range(&self) -> f64 {
        let mx = self.mean.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let mn = self.mean.iter().copied().fold(f64::INFINITY, f64::min);
        if mx.is_finite() { mx - mn } else { 0.0 }
    }
    /// Largest minus smallest bin mean square.
    pub fn msq_range(&self) -> f64 {
        let mx = self.msq.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let mn = self.msq.iter().copied().fold(f64::INFINITY, f64::min);
        if mx.is_finite() { mx - mn } else { 0.0 }
    }
}

/// Statistics of one tile of one channel.
#[derive(Clone, Debug, Serialize)]
pub struct TileStat {
    pub channel: String,
    pub column: usize,
    pub row: usize,
    pub mean: f64,
    pub spread: f64,
    pub reduced_chi2: f64,
}

/// The residual analysis of one fit.
#[derive(Clone, Debug, Serialize)]
pub struct Analysis {
    pub reduced_chi2: f64,
    pub reduced_chi2_channel: Vec<f64>,
    pub tiles: Vec<TileStat>,
    pub curves: Vec<Curve>,
    pub histogram_edges: Vec<f64>,
    pub histogram: Vec<f64>,
    pub histogram_normal: Vec<f64>,
    pub skewness: f64,
    pub excess_kurtosis: f64,
    /// `[a, bx, by]` of the planar trend of `z`.
    pub planar: [f64; 3],
    /// The worst tile (highest reduced χ²).
    pub worst: Option<TileStat>,
    /// `(band centre in cycles/px, power)`: the radial power spectrum of `z`, channels
    /// averaged ([`radial_spectrum`]).
    pub spectrum: Vec<(f64, f64)>,
}

/// Radial power spectrum of `z` on the evaluation set `mask` (zero elsewhere):
/// `mean_{|f| in band} |Ẑ(f)|² / N_mask` in `bands` bands of `|f|` over (0, 0.5] cycles/px.
/// Unit white noise gives 1 in every band; a residual that is smooth (stray light, gains) puts
/// its power in the low bands, one that is missing fine detail in the high ones.
pub fn radial_spectrum(z: &Plane, mask: &[bool], bands: usize) -> Vec<(f64, f64)> {
    let (w, h) = (z.width, z.height);
    let n = mask.iter().filter(|&&m| m).count();
    if n == 0 || bands == 0 {
        return Vec::new();
    }
    let fft = crate::solve::fft::Fft2::plan(w, h);
    let masked: Vec<f32> = z.data.iter().zip(mask).map(|(&v, &m)| if m { v } else { 0.0 }).collect();
    let spec = fft.forward(&masked);
    let (sum, cnt) = radial_power_sums(&fft, &[&spec], bands, 0.5, Range::OpenClosed(0.0, 0.5));
    (0..bands).filter(|&b| cnt[b] > 0).map(|b| (band_centre(b, bands, 0.5), sum[0][b] / cnt[b] as f64 / n as f64)).collect()
}

/// Upper edge (cycles/px) of the residual spectrum's lowest band: the first of the 16 bands of
/// [`Analysis::spectrum`] over (0, 0.5].
pub const LOW_BAND_TOP: f64 = 0.5 / SPECTRUM_BANDS as f64;

/// Bands of [`Analysis::spectrum`].
const SPECTRUM_BANDS: usize = 16;

/// The frequencies of a `w × h` image's lowest band ([`LOW_BAND_TOP`]) on the half plane the
/// real FFT keeps (`kx ≥ 0`, every `ky`): `(fx, fy)` in cycles/px.
pub fn low_band_bins(w: usize, h: usize) -> Vec<(f64, f64)> {
    let (kxm, kym) = ((w as f64 * LOW_BAND_TOP) as i64, (h as f64 * LOW_BAND_TOP) as i64);
    let mut out = Vec::new();
    for kx in 0..=kxm.min(w as i64 / 2) {
        for ky in -kym..=kym {
            let (fx, fy) = (kx as f64 / w as f64, ky as f64 / h as f64);
            let f = fx.hypot(fy);
            if f > 0.0 && f <= LOW_BAND_TOP {
                out.push((fx, fy));
            }
        }
    }
    out
}

/// Mean of `|K̂(f)|²` over `bins` (`K̂(f) = Σ K(x)·e^{−2πi f·x}`): the gain with which white
/// noise of unit variance comes through the kernel `k` in that band (its mean over every
/// frequency is `ΣK²`).
pub fn band_gain(k: &Plane, bins: &[(f64, f64)]) -> f64 {
    if bins.is_empty() {
        return 0.0;
    }
    let tau = std::f64::consts::TAU;
    // each row's transform at a given fx (bins share few fx), then its phase at fy
    let mut rows: Vec<(f64, Vec<(f64, f64)>)> = Vec::new();
    let mut total = 0.0f64;
    for &(fx, fy) in bins {
        let idx = match rows.iter().position(|r| r.0 == fx) {
            Some(i) => i,
            None => {
                let ph: Vec<(f64, f64)> = (0..k.width).map(|x| (tau * fx * x as f64).sin_cos()).collect();
                let r = (0..k.height)
                    .map(|y| {
                        let row = &k.data[y * k.width..(y + 1) * k.width];
                        row.iter().zip(&ph).fold((0.0, 0.0), |(a, b), (&v, &(sn, cs))| (a + v as f64 * cs, b - v as f64 * sn))
                    })
                    .collect();
                rows.push((fx, r));
                rows.len() - 1
            }
        };
        let (mut re, mut im) = (0.0f64, 0.0f64);
        for (y, &(rr, ri)) in rows[idx].1.iter().enumerate() {
            let (sn, cs) = (tau * fy * y as f64).sin_cos();
            re += rr * cs + ri * sn;
            im += ri * cs - rr * sn;
        }
        total += re * re + im * im;
    }
    total / bins.len() as f64
}

/// The curve of `vals` (variable, z) in `bins` bins: equal counts (`quantile`, a stable sort by
/// the variable) or equal widths; bins of fewer than 20 pixels are left out. Sorts `vals` in
/// place and sums over slices of it (no copy: it is the analysis' largest buffer).
fn binned(name: &str, mut vals: Vec<(f32, f32)>, bins: usize, quantile: bool) -> Curve {
    let (mut x, mut mean, mut msq) = (vec![], vec![], vec![]);
    if vals.is_empty() {
        return Curve { name: name.into(), x, mean, msq };
    }
    let mut push = |s: (f64, f64, f64), n: usize| {
        if n >= 20 {
            let n = n as f64;
            x.push(s.0 / n);
            mean.push(s.1 / n);
            msq.push(s.2 / n);
        }
    };
    if quantile {
        vals.sort_by(|a, b| a.0.total_cmp(&b.0));
        let len = vals.len();
        for b in 0..bins {
            let g = &vals[b * len / bins..(b + 1) * len / bins];
            let sums = (g.iter().map(|q| q.0 as f64).sum::<f64>(), g.iter().map(|q| q.1 as f64).sum::<f64>(), g.iter().map(|q| (q.1 as f64).powi(2)).sum::<f64>());
            push(sums, g.len());
        }
    } else {
        let lo = vals.iter().map(|q| q.0).fold(f32::INFINITY, f32::min);
        let hi = vals.iter().map(|q| q.0).fold(f32::NEG_INFINITY, f32::max);
        // per bin, the sums in the pixels' order (as the groups' sums were)
        let mut acc = vec![((0.0f64, 0.0f64, 0.0f64), 0usize); bins];
        for q in &vals {
            let b = (((q.0 - lo) / (hi - lo).max(1e-12)) * bins as f32) as usize;
            let a = &mut acc[b.min(bins - 1)];
            a.0 .0 += q.0 as f64;
            a.0 .1 += q.1 as f64;
            a.0 .2 += (q.1 as f64).powi(2);
            a.1 += 1;
        }
        for (s, n) in acc {
            push(s, n);
        }
    }
    Curve { name: name.into(), x, mean, msq }
}

/// The histogram of `z` over [−5, 5) in 40 bins (a density), the standard normal density at
/// the bin centres, and the third and fourth standardised moments.
struct Histogram {
    edges: Vec<f64>,
    density: Vec<f64>,
    normal: Vec<f64>,
    skewness: f64,
    excess_kurtosis: f64,
}

impl Histogram {
    /// `all_z` is iterated twice (the mean, then the central moments).
    fn of<I: Iterator<Item = f32> + Clone>(all_z: I) -> Self {
        let edges: Vec<f64> = (0..=40).map(|i| -5.0 + 0.25 * i as f64).collect();
        let mut density = vec![0.0f64; 40];
        let n = all_z.clone().count().max(1) as f64;
        let (mut m1, mut m2, mut m3, mut m4) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for z in all_z.clone() {
            let z = z as f64;
            m1 += z;
            if (-5.0..5.0).contains(&z) {
                density[((z + 5.0) / 0.25) as usize] += 1.0 / (n * 0.25);
            }
        }
        m1 /= n;
        for z in all_z {
            let d = z as f64 - m1;
            m2 += d * d;
            m3 += d * d * d;
            m4 += d * d * d * d;
        }
        m2 /= n;
        m3 /= n;
        m4 /= n;
        let normal: Vec<f64> = edges
            .windows(2)
            .map(|e| {
                let x = 0.5 * (e[0] + e[1]);
                (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt()
            })
            .collect();
        Self { edges, density, normal, skewness: m3 / m2.max(1e-300).powf(1.5), excess_kurtosis: m4 / m2.max(1e-300).powi(2) - 3.0 }
    }
}

/// The radial spectrum of the normalised residual ([`radial_spectrum`], 16 bands), channels
/// averaged.
fn mean_spectrum(fit: &Fit) -> Vec<(f64, f64)> {
    let nch = fit.normalized.len();
    let per_channel: Vec<Vec<(f64, f64)>> = (0..nch).map(|c| radial_spectrum(&fit.normalized[c], &fit.eval[c], SPECTRUM_BANDS)).collect();
    match per_channel.first() {
        Some(first) => first.iter().enumerate().map(|(b, &(f, _))| (f, per_channel.iter().map(|s| s.get(b).map_or(0.0, |q| q.1)).sum::<f64>() / nch as f64)).collect(),
        None => Vec::new(),
    }
}

/// Per-tile statistics of channel `c` from the sums `(Σz, Σz², n)` of each tile's pixels.
fn tile_stats(grid: &crate::optics::psf_grid::PsfGrid, c: usize, tsum: &[(f64, f64, usize)]) -> Vec<TileStat> {
    let mut tiles = Vec::new();
    for (t, &(s, s2, n)) in tsum.iter().enumerate() {
        if n == 0 {
            continue;
        }
        let mean = s / n as f64;
        tiles.push(TileStat {
            channel: grid.channels.get(c).cloned().unwrap_or_default(),
            column: t % grid.columns,
            row: t / grid.columns,
            mean,
            spread: (s2 / n as f64 - mean * mean).max(0.0).sqrt(),
            reduced_chi2: s2 / n as f64,
        });
    }
    tiles
}

/// Analyses a fit's normalised residual.
pub fn analyse(fit: &Fit) -> Analysis {
    let grid = &fit.model.grid;
    let nch = fit.normalized.len();
    let (w, h) = (fit.normalized[0].width, fit.normalized[0].height);
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let hd = 0.5 * ((w * w + h * h) as f64).sqrt();
    let xs = grid.column_xs();
    let ys = grid.row_ys();
    let tile_half_diag = 0.5 * ((w as f64 / grid.columns as f64).powi(2) + (h as f64 / grid.rows as f64).powi(2)).sqrt();
    // the evaluated interior pixels, channel by channel in row order: every pass below visits
    // them in this order (the curves' quantile sort is stable, so ties keep it)
    let evaluated = |c: usize| (1..h.saturating_sub(1)).flat_map(move |y| (1..w.saturating_sub(1)).map(move |x| (x, y, y * w + x))).filter(move |&(_, _, i)| fit.eval[c][i]);
    // the nearest PSF centre's column of each x and row of each y
    let nearest = |v: &[f64], p: f64| v.iter().enumerate().min_by(|a, b| (a.1 - p).abs().total_cmp(&(b.1 - p).abs())).map_or(0, |q| q.0);
    let col_of: Vec<usize> = (0..w).map(|x| nearest(&xs, x as f64)).collect();
    let row_of: Vec<usize> = (0..h).map(|y| nearest(&ys, y as f64)).collect();
    let mut tiles = Vec::new();
    let mut count = 0usize;
    let (mut ata, mut atb) = ([[0.0f64; 3]; 3], [0.0f64; 3]);
    for c in 0..nch {
        let z = &fit.normalized[c];
        let mut tsum = vec![(0.0f64, 0.0f64, 0usize); grid.tile_count()];
        for (x, y, i) in evaluated(c) {
            let zi = z.data[i];
            count += 1;
            let (dx, dy) = (x as f64 - cx, y as f64 - cy);
            let t = &mut tsum[row_of[y] * grid.columns + col_of[x]];
            t.0 += zi as f64;
            t.1 += (zi as f64).powi(2);
            t.2 += 1;
            let row3 = [1.0, dx / cx.max(0.5), dy / cy.max(0.5)];
            for a in 0..3 {
                atb[a] += row3[a] * zi as f64;
                for b in 0..3 {
                    ata[a][b] += row3[a] * row3[b];
                }
            }
        }
        tiles.extend(tile_stats(grid, c, &tsum));
    }
    // one feature at a time: its (value, z) pairs are the only per-pixel storage (8 bytes per
    // evaluated pixel, not five features' at once)
    let names = ["intensity", "radius", "position_in_tile", "gradient", "large_scale_brightness"];
    let curves = names
        .iter()
        .enumerate()
        .map(|(j, n)| {
            let mut pairs: Vec<(f32, f32)> = Vec::with_capacity(count);
            for c in 0..nch {
                let (z, pred) = (&fit.normalized[c], &fit.predicted[c]);
                let large = (j == 4).then(|| gaussian_blur_wide(&fit.reference[c], (2.0 * hd / 16.0).max(2.0)));
                pairs.extend(evaluated(c).map(|(x, y, i)| {
                    let v = match j {
                        0 => pred.data[i],
                        1 => (((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)).sqrt() / hd) as f32,
                        2 => {
                            let (col, row) = (col_of[x], row_of[y]);
                            (((x as f64 - xs[col]).powi(2) + (y as f64 - ys[row]).powi(2)).sqrt() / tile_half_diag) as f32
                        }
                        3 => {
                            let gx = pred.get(x + 1, y) - pred.get(x - 1, y);
                            let gy = pred.get(x, y + 1) - pred.get(x, y - 1);
                            0.5 * (gx * gx + gy * gy).sqrt()
                        }
                        _ => large.as_ref().map_or(0.0, |l| l.data[i]),
                    };
                    (v, z.data[i])
                }));
            }
            binned(n, pairs, 10, j != 1 && j != 2)
        })
        .collect();
    let hist = Histogram::of((0..nch).flat_map(|c| evaluated(c).map(move |(_, _, i)| fit.normalized[c].data[i])));
    let planar = gauss_jordan(ata, atb, 1e-12).unwrap_or([0.0; 3]);
    let spectrum = mean_spectrum(fit);
    let worst = tiles.iter().max_by(|a, b| a.reduced_chi2.total_cmp(&b.reduced_chi2)).cloned();
    Analysis {
        reduced_chi2: fit.reduced_chi2(),
        reduced_chi2_channel: fit.reduced_chi2_channel(),
        tiles,
        curves,
        histogram_edges: hist.edges,
        histogram: hist.density,
        histogram_normal: hist.normal,
        skewness: hist.skewness,
        excess_kurtosis: hist.excess_kurtosis,
        planar,
        worst,
        spectrum,
    }
}

/// The curve called `name`.
pub fn curve<'a>(a: &'a Analysis, name: &str) -> Option<&'a Curve> {
    a.curves.iter().find(|c| c.name == name)
}

/// A short plain-text description of the worst place.
pub fn where_text(a: &Analysis) -> String {
    match &a.worst {
        Some(t) => format!("whole field; worst at tile column {} row {} of channel {} (reduced χ² {:.2}, mean z {:+.2})", t.column, t.row, t.channel, t.reduced_chi2, t.mean),
        None => "no evaluated pixels".into(),
    }
}

/// Normalised residual map as a displayable plane: `z` mapped from [−5, 5] to [0, 1].
pub fn residual_image(z: &Plane) -> Plane {
    z.map(|v| ((v + 5.0) / 10.0).clamp(0.0, 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Unit white noise is flat at 1; blurred noise (a smooth residual) has its power in the
    /// low bands and almost none in the high ones. A mask leaves the normalisation right.
    #[test]
    fn radial_spectrum_of_white_and_smooth_residuals() {
        let (w, h) = (160, 120);
        let mut r = Rng::new(12);
        let white = Plane::from_fn(w, h, |_, _| r.normal() as f32);
        let mask: Vec<bool> = (0..w * h).map(|i| (i % w) >= 10 && (i % w) < w - 10).collect();
        let s = radial_spectrum(&white, &mask, 8);
        assert_eq!(s.len(), 8);
        for &(f, p) in &s {
            assert!((p - 1.0).abs() < 0.15, "band {f:.3}: {p:.3}");
        }
        let smooth = crate::image::filter::gaussian_blur(&white, 2.0).map(|v| v * 5.0);
        let s = radial_spectrum(&smooth, &vec![true; w * h], 8);
        assert!(s[0].1 > 2.0 && s[7].1 < 0.01, "{s:?}");
    }

    /// A delta passes white noise with gain 1 in every band; a kernel summing to 1 passes
    /// about 1 at the lowest frequencies, far above its `ΣK²` (its mean gain over all
    /// frequencies); the low band holds the half-plane bins up to [`LOW_BAND_TOP`].
    #[test]
    fn band_gain_of_a_delta_and_a_box() {
        let bins = low_band_bins(256, 192);
        assert!(bins.iter().all(|&(fx, fy)| fx >= 0.0 && fx.hypot(fy) > 0.0 && fx.hypot(fy) <= LOW_BAND_TOP));
        // about half the disc of radius 0.031 on a 256 × 192 grid: π·8·6/2 ≈ 75
        assert!((60..=90).contains(&bins.len()), "{} bins", bins.len());
        let mut delta = Plane::new(5, 5);
        delta.data[12] = 1.0;
        assert!((band_gain(&delta, &bins) - 1.0).abs() < 1e-9);
        let boxk = Plane::from_fn(9, 9, |_, _| 1.0 / 81.0);
        let g = band_gain(&boxk, &bins);
        let k2 = 1.0 / 81.0;
        assert!(g > 0.8 && g < 1.0 && g > 50.0 * k2, "box gain {g:.3} vs ΣK² {k2:.4}");
    }

    /// The curves as equal-count or equal-width groups of the pixels, each group's sums in the
    /// pixels' order: what [`binned`] computes without copying the groups (the analysis' former
    /// implementation, kept here as the reference).
    fn grouped(vals: &[(f32, f32)], bins: usize, quantile: bool) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let mut v = vals.to_vec();
        let groups: Vec<Vec<(f32, f32)>> = if quantile {
            v.sort_by(|a, b| a.0.total_cmp(&b.0));
            (0..bins).map(|b| v[b * v.len() / bins..(b + 1) * v.len() / bins].to_vec()).collect()
        } else {
            let lo = v.iter().map(|q| q.0).fold(f32::INFINITY, f32::min);
            let hi = v.iter().map(|q| q.0).fold(f32::NEG_INFINITY, f32::max);
            let mut g = vec![Vec::new(); bins];
            for q in v {
                let b = (((q.0 - lo) / (hi - lo).max(1e-12)) * bins as f32) as usize;
                g[b.min(bins - 1)].push(q);
            }
            g
        };
        let (mut x, mut mean, mut msq) = (vec![], vec![], vec![]);
        for g in groups.iter().filter(|g| g.len() >= 20) {
            let n = g.len() as f64;
            x.push(g.iter().map(|q| q.0 as f64).sum::<f64>() / n);
            mean.push(g.iter().map(|q| q.1 as f64).sum::<f64>() / n);
            msq.push(g.iter().map(|q| (q.1 as f64).powi(2)).sum::<f64>() / n);
        }
        (x, mean, msq)
    }

    /// [`binned`] gives the grouped curves to the bit, with ties in the variable (a stable sort
    /// keeps the pixels' order), skewed values whose equal-width bins fall below 20 pixels, and
    /// too few pixels for any bin.
    #[test]
    fn binned_curves_equal_the_grouped_ones() {
        let mut r = Rng::new(7);
        for (n, quantile) in [(5000, true), (5000, false), (1234, true), (1234, false), (30, true), (30, false)] {
            // quantised values give ties; the square skews the equal-width bins
            let vals: Vec<(f32, f32)> = (0..n).map(|_| ((((r.uniform() * 40.0).floor() / 40.0) as f32).powi(2), r.normal() as f32)).collect();
            let c = binned("v", vals.clone(), 10, quantile);
            let (x, mean, msq) = grouped(&vals, 10, quantile);
            assert_eq!((c.x.clone(), c.mean.clone(), c.msq.clone()), (x, mean, msq), "n {n}, quantile {quantile}");
            assert!(n >= 1000 || c.x.len() < 10);
        }
        assert!(binned("v", Vec::new(), 10, true).x.is_empty());
    }
}
