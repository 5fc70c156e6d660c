//! Modulation transfer functions: of a PSF kernel along a direction, of a slanted edge, and of
//! the diffraction limit (the analytic truth the tests check both against).
//!
//! # Conventions
//! Frequencies are in **cycles per pixel** (Nyquist = 0.5); `lp/mm = cycles/px · 1000 / pitch_µm`.
//! A kernel's MTF along the unit direction `u` is `|Σ K(x,y)·e^{−2πi·f·(u·(x,y))}| / ΣK`: the
//! modulation of a sine grating whose wave vector is `f·u` (its bars run perpendicular to `u`).
//! Kernels are pixel-integrated (the simulator bins the optical PSF over square pixels), so this
//! MTF includes the pixel aperture, as a slanted-edge measurement on the sensor does.
//!
//! **Tangential** (meridional) MTF at a field point: frequency along the radius from the optical
//! centre (bars tangential); **sagittal**: frequency perpendicular to the radius (bars radial).
//! On axis, where the radius has no direction, tangential is taken along `x`.

use crate::diagnose::diffraction::half_modulation;
use crate::image::Plane;

/// Frequencies (cycles/px) at which curves are sampled: 0, 0.01, …, 0.5.
pub fn curve_frequencies() -> Vec<f64> {
    (0..=50).map(|i| i as f64 * 0.01).collect()
}

/// Kernel MTF at frequency `f` (cycles/px) along the unit direction `(ux, uy)`.
pub fn kernel_mtf(k: &Plane, ux: f64, uy: f64, f: f64) -> f64 {
    let cx = (k.width as f64 - 1.0) / 2.0;
    let cy = (k.height as f64 - 1.0) / 2.0;
    let (mut re, mut im) = (0.0f64, 0.0f64);
    for y in 0..k.height {
        for x in 0..k.width {
            let v = k.get(x, y) as f64;
            if v == 0.0 {
                continue;
            }
            let a = -2.0 * std::f64::consts::PI * f * (ux * (x as f64 - cx) + uy * (y as f64 - cy));
            re += v * a.cos();
            im += v * a.sin();
        }
    }
    re.hypot(im) / k.sum().max(1e-30)
}

/// The kernel's MTF curve along `(ux, uy)` at [`curve_frequencies`].
pub fn kernel_mtf_curve(k: &Plane, ux: f64, uy: f64) -> Vec<f64> {
    curve_frequencies().iter().map(|&f| kernel_mtf(k, ux, uy, f)).collect()
}

/// MTF50 (cycles/px) of a kernel along `(ux, uy)`: where the modulation first falls to one
/// half (bisection; 0.5 when still above one half at Nyquist).
pub fn kernel_mtf50(k: &Plane, ux: f64, uy: f64) -> f64 {
    half_modulation(|f| kernel_mtf(k, ux, uy, f))
}

/// MTF50 of a sampled curve (`freqs`, `mtf`), linear interpolation at the first crossing;
/// the last frequency when it never falls to one half.
pub fn curve_mtf50(freqs: &[f64], mtf: &[f64]) -> f64 {
    for i in 1..freqs.len().min(mtf.len()) {
        if mtf[i] <= 0.5 && mtf[i - 1] > 0.5 {
            let t = (mtf[i - 1] - 0.5) / (mtf[i - 1] - mtf[i]);
            return freqs[i - 1] + t * (freqs[i] - freqs[i - 1]);
        }
    }
    freqs.last().copied().unwrap_or(0.0)
}

/// Diffraction-limited MTF of a circular pupil at normalised frequency `f / f_c`
/// (`f_c = 1/(λN)`): `(2/π)(acos ν − ν√(1−ν²))`, 0 beyond the cutoff.
pub fn diffraction_mtf(nu: f64) -> f64 {
    if nu >= 1.0 {
        return 0.0;
    }
    let nu = nu.max(0.0);
    2.0 / std::f64::consts::PI * (nu.acos() - nu * (1.0 - nu * nu).sqrt())
}

/// The analytic MTF of a diffraction-limited lens seen by a sensor with square pixels of 100 %
/// fill factor, along a pixel axis: `diffraction(f·pitch/(λN)) · |sinc(f)|` (`f` in cycles/px,
/// `λ` and the pitch in µm).
pub fn diffraction_pixel_mtf(f: f64, lambda_um: f64, f_number: f64, pitch_um: f64) -> f64 {
    let cutoff = pitch_um / (lambda_um * f_number); // cycles/px
    let sinc = if f == 0.0 { 1.0 } else { (std::f64::consts::PI * f).sin() / (std::f64::consts::PI * f) };
    diffraction_mtf(f / cutoff) * sinc.abs()
}

/// Oversampling of the edge-spread function: bins per pixel along the edge normal.
const OS: f64 = 4.0;

/// A slanted-edge MTF measurement (ISO 12233 style) on a near-vertical edge filling `img`:
/// the edge is located row by row (centroid of the horizontal derivative), a line is fitted,
/// pixels are projected onto the edge normal and binned at 1/4 px into an edge-spread function,
/// differentiated, Hamming-windowed and Fourier transformed. The returned curve is sampled at
/// [`curve_frequencies`] (cycles/px along the edge normal), corrected for the finite-difference
/// derivative. `None` when no edge is found.
pub fn slanted_edge_mtf(img: &Plane) -> Option<Vec<f64>> {
    if img.width < 8 || img.height < 8 {
        return None;
    }
    let pts = edge_points(img);
    if pts.len() < 4 {
        return None;
    }
    let (a, b) = fit_edge_line(&pts);
    let esf = edge_spread(img, a, b)?;
    let (lsf, dc) = windowed_line_spread(&esf)?;
    Some(line_spread_mtf(&lsf, dc))
}

/// Step 1: The edge position per row `(y, x)`: the centroid of `|d/dx|` (rows without any
/// gradient are skipped).
fn edge_points(img: &Plane) -> Vec<(f64, f64)> {
    let (w, h) = (img.width, img.height);
    let mut pts: Vec<(f64, f64)> = Vec::with_capacity(h);
    for y in 0..h {
        let (mut s, mut sx) = (0.0f64, 0.0f64);
        for x in 1..w - 1 {
            let d = (img.get(x + 1, y) as f64 - img.get(x - 1, y) as f64).abs();
            s += d;
            sx += d * x as f64;
        }
        if s > 1e-9 {
            pts.push((y as f64, sx / s));
        }
    }
    pts
}

/// Step 2: The least-squares line `x = a + b·y` through the edge points; returns `(a, b)`.
fn fit_edge_line(pts: &[(f64, f64)]) -> (f64, f64) {
    let n = pts.len() as f64;
    let (my, mx) = (pts.iter().map(|p| p.0).sum::<f64>() / n, pts.iter().map(|p| p.1).sum::<f64>() / n);
    let syy: f64 = pts.iter().map(|p| (p.0 - my).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| (p.0 - my) * (p.1 - mx)).sum();
    let b = if syy > 0.0 { sxy / syy } else { 0.0 };
    (mx - b * my, b)
}

/// Step 3: The edge-spread function: pixels projected onto the normal of the line `x = a + b·y`
/// (signed distance `d = (x − a − b·y)/√(1+b²)`) and averaged in bins of `1/OS` px over
/// `|d| ≤ min(w/2, 32)`; empty bins are filled from their neighbours. `None` when every bin
/// is empty.
fn edge_spread(img: &Plane, a: f64, b: f64) -> Option<Vec<f64>> {
    let (w, h) = (img.width, img.height);
    let norm = (1.0 + b * b).sqrt();
    let half = (w as f64 / 2.0).min(32.0);
    let nb = (2.0 * half * OS) as usize;
    let mut sum = vec![0.0f64; nb];
    let mut cnt = vec![0usize; nb];
    for y in 0..h {
        for x in 0..w {
            let d = (x as f64 - a - b * y as f64) / norm;
            let i = ((d + half) * OS).floor();
            if i >= 0.0 && (i as usize) < nb {
                sum[i as usize] += img.get(x, y) as f64;
                cnt[i as usize] += 1;
            }
        }
    }
    // fill empty bins from their neighbours
    let mut esf: Vec<f64> = (0..nb).map(|i| if cnt[i] > 0 { sum[i] / cnt[i] as f64 } else { f64::NAN }).collect();
    for i in 0..nb {
        if esf[i].is_nan() {
            let l = (0..i).rev().find(|&j| cnt[j] > 0);
            let r = (i + 1..nb).find(|&j| cnt[j] > 0);
            esf[i] = match (l, r) {
                (Some(l), Some(r)) => esf[l] + (esf[r] - esf[l]) * (i - l) as f64 / (r - l) as f64,
                (Some(l), None) => esf[l],
                (None, Some(r)) => sum[r] / cnt[r] as f64,
                (None, None) => return None,
            };
        }
    }
    Some(esf)
}

/// Step 4: The line-spread function by central difference, Hamming-windowed about its peak, and its
/// sum (the DC term). `None` without a peak or with a vanishing DC term.
fn windowed_line_spread(esf: &[f64]) -> Option<(Vec<f64>, f64)> {
    let nb = esf.len();
    let mut lsf = vec![0.0f64; nb];
    for i in 1..nb - 1 {
        lsf[i] = (esf[i + 1] - esf[i - 1]) / 2.0;
    }
    let peak = lsf.iter().enumerate().max_by(|x, y| x.1.abs().total_cmp(&y.1.abs())).map(|(i, _)| i)?;
    let m = nb as f64;
    for (i, v) in lsf.iter_mut().enumerate() {
        let t = (i as f64 - peak as f64) / m;
        *v *= if t.abs() <= 0.5 { 0.54 + 0.46 * (2.0 * std::f64::consts::PI * t).cos() } else { 0.0 };
    }
    let dc: f64 = lsf.iter().sum();
    if dc.abs() < 1e-12 {
        return None;
    }
    Some((lsf, dc))
}

/// Step 5: The normalised DFT magnitude of the line-spread function at the curve frequencies
/// (cycles/px → cycles/bin = f/OS), divided by the central difference's own transfer.
fn line_spread_mtf(lsf: &[f64], dc: f64) -> Vec<f64> {
    curve_frequencies()
        .iter()
        .map(|&f| {
            let (mut re, mut im) = (0.0f64, 0.0f64);
            for (i, &v) in lsf.iter().enumerate() {
                let ph = -2.0 * std::f64::consts::PI * f / OS * i as f64;
                re += v * ph.cos();
                im += v * ph.sin();
            }
            let x = 2.0 * std::f64::consts::PI * f / OS; // central difference over 2 bins
            let corr = if x == 0.0 { 1.0 } else { x.sin() / x };
            re.hypot(im) / dc.abs() / corr
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::lens::{Aberrations, Band, LensModel};
    use crate::solve::conv::convolve;

    /// A diffraction-limited lens at one wavelength: its MTF is known in closed form.
    fn ideal_lens(lambda_nm: f64) -> LensModel {
        let mut l = LensModel::demo(64, 64);
        l.aberrations = Aberrations::default();
        l.glass = None;
        l.bands = vec![Band { name: "Y".into(), wavelengths: vec![(lambda_nm, 1.0)] }];
        l
    }

    #[test]
    fn kernel_mtf_matches_the_diffraction_limit() {
        let (lambda, n) = (550.0, 22.0);
        let lens = ideal_lens(lambda);
        let k = lens.psf(n, 0, 31.5, 31.5, 45);
        let pitch = lens.pixel_pitch_um;
        let truth50 = half_modulation(|f| diffraction_pixel_mtf(f, lambda / 1000.0, n, pitch));
        let got50 = kernel_mtf50(&k, 1.0, 0.0);
        let rel = (got50 / truth50 - 1.0).abs();
        println!("diffraction-limited f/{n}, {lambda} nm: kernel MTF50 {got50:.4} c/px vs analytic {truth50:.4} ({:.2} %)", rel * 100.0);
        assert!(rel < 0.05, "MTF50 {got50:.4} vs analytic {truth50:.4} ({:.1} %)", rel * 100.0);
        // and the whole curve
        for &f in &curve_frequencies() {
            let d = (kernel_mtf(&k, 1.0, 0.0, f) - diffraction_pixel_mtf(f, lambda / 1000.0, n, pitch)).abs();
            assert!(d < 0.03, "f = {f}: |Δ| = {d:.3}");
        }
        // a direction-independent PSF: same along y and diagonals
        assert!((kernel_mtf50(&k, 0.0, 1.0) / got50 - 1.0).abs() < 0.01);
    }

    #[test]
    fn a_defocused_kernel_has_a_lower_mtf50() {
        let mut lens = ideal_lens(550.0);
        let sharp = kernel_mtf50(&lens.psf(22.0, 0, 31.5, 31.5, 45), 1.0, 0.0);
        lens.aberrations.defocus_um = 3.0;
        let soft = kernel_mtf50(&lens.psf(8.0, 0, 31.5, 31.5, 45), 1.0, 0.0);
        assert!(soft < 0.8 * sharp, "{soft} vs {sharp}");
    }

    #[test]
    fn slanted_edge_agrees_with_the_kernel_mtf() {
        // an off-axis, aberrated kernel from the demo lens (coma, astigmatism, chromatic)
        let lens = LensModel::demo(384, 288);
        for (band, n) in [(1usize, 5.6), (0, 8.0)] {
            let k = lens.psf(n, band, 40.0, 30.0, 31);
            let angle = 5.0f64.to_radians();
            let (w, h) = (96usize, 96usize);
            // point-sampled slanted step: bright where x − 48 > −tan(angle)·(y − 48)
            let edge = Plane::from_fn(w, h, |x, y| {
                let d = (x as f64 - 47.7) * angle.cos() + (y as f64 - 48.0) * angle.sin();
                if d > 0.0 {
                    0.8
                } else {
                    0.1
                }
            });
            let img = convolve(&edge, &k);
            // crop away the mirror-padded borders' influence
            let crop = img.window_reflect(16, 16, 64, 64);
            let se = slanted_edge_mtf(&crop).expect("edge found");
            let se50 = curve_mtf50(&curve_frequencies(), &se);
            let k50 = kernel_mtf50(&k, angle.cos(), angle.sin());
            let rel = (se50 / k50 - 1.0).abs();
            println!("slanted edge, band {band} f/{n}: MTF50 {se50:.4} c/px vs kernel {k50:.4} ({:.2} %)", rel * 100.0);
            assert!(rel < 0.05, "band {band}: slanted edge {se50:.4} vs kernel {k50:.4} ({:.1} %)", rel * 100.0);
        }
    }

    #[test]
    fn no_edge_is_reported() {
        assert!(slanted_edge_mtf(&Plane::filled(32, 32, 0.5)).is_none());
    }
}
