//! Registration of the pinhole capture to the wide-open one.
//!
//! Per tile, the displacement between the two captures is the peak of the phase correlation
//! of the Hann-windowed patches, refined to sub-pixel precision by a parabola through the peak
//! and its neighbours. A global model is fitted to the tile displacements by least squares
//! (with one round of outlier rejection at 3× the median residual):
//! - `translation`: `d = t` (default — the kernel support absorbs the fractional part exactly,
//!   so only the integer part is applied, without interpolation);
//! - `similarity`: `d = (A − I)(p − c) + t` with `A = [[a, −b], [b, a]]` (rotation and scale from
//!   rig vibration), applied by bicubic resampling.
//!
//! The blur of the wide-open capture is not symmetric off axis (coma), which biases each tile's
//! displacement by its PSF's centroid; for a lens centred on the sensor these biases cancel in
//! the mean, which is why `translation` is the default and `similarity` is opt-in (the
//! diagnosis tests for rotation and scale separately).

use crate::image::Plane;
use crate::optics::capture::{warp_similarity, Similarity};
use crate::profile::RegistrationInfo;
use crate::solve::dense::gauss_jordan;
use crate::solve::fft::Fft2;

/// Which global motion to fit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RegistrationModel {
    None,
    Translation,
    Similarity,
}

impl std::str::FromStr for RegistrationModel {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "none" => Ok(Self::None),
            "translation" => Ok(Self::Translation),
            "similarity" => Ok(Self::Similarity),
            o => Err(format!("unknown registration model '{o}' (none, translation, similarity)")),
        }
    }
}

/// Displacement `(dx, dy)` such that `open(p) ≈ pinhole(p − d)` for one patch pair.
pub fn phase_correlation(open: &Plane, pinhole: &Plane) -> (f64, f64, f64) {
    let (w, h) = (open.width, open.height);
    let fft = Fft2::plan(w, h);
    let hann = |i: usize, n: usize| 0.5 - 0.5 * (2.0 * std::f32::consts::PI * i as f32 / n as f32).cos();
    let prep = |p: &Plane| {
        let m = p.mean() as f32;
        let mut v = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                v[y * w + x] = (p.get(x, y) - m) * hann(x, w) * hann(y, h);
            }
        }
        fft.forward(&v)
    };
    let a = prep(open);
    let b = prep(pinhole);
    let mut c: Vec<_> = a.iter().zip(&b).map(|(x, y)| {
        let p = x * y.conj();
        let n = p.norm();
        if n > 1e-20 { p / n } else { p }
    }).collect();
    // a mild low-pass keeps the peak stable on blurred data
    for (i, v) in c.iter_mut().enumerate() {
        let (fx, fy) = fft.frequency(i);
        *v *= (-(fx * fx + fy * fy) / (2.0 * 0.15f32 * 0.15)).exp();
    }
    let r = fft.inverse(c);
    let (mut best, mut bi) = (f32::NEG_INFINITY, 0);
    for (i, &v) in r.iter().enumerate() {
        if v > best {
            best = v;
            bi = i;
        }
    }
    let (px, py) = (bi % w, bi / w);
    let at = |x: isize, y: isize| r[(y.rem_euclid(h as isize) as usize) * w + x.rem_euclid(w as isize) as usize] as f64;
    let sub = |m: f64, c0: f64, p: f64| {
        let d = m - 2.0 * c0 + p;
        if d.abs() > 1e-12 { 0.5 * (m - p) / d } else { 0.0 }
    };
    let (xi, yi) = (px as isize, py as isize);
    let dx = sub(at(xi - 1, yi), at(xi, yi), at(xi + 1, yi));
    let dy = sub(at(xi, yi - 1), at(xi, yi), at(xi, yi + 1));
    let wrap = |v: f64, n: usize| if v > n as f64 / 2.0 { v - n as f64 } else { v };
    (wrap(px as f64 + dx, w), wrap(py as f64 + dy, h), best as f64)
}

/// A fitted registration.
#[derive(Clone, Debug)]
pub struct Registration {
    pub info: RegistrationInfo,
    /// Per-tile measured displacements `(x, y, dx, dy)`.
    pub samples: Vec<[f64; 4]>,
}

/// Measures displacements on a grid of patches and fits `model`.
pub fn register(open: &Plane, pinhole: &Plane, model: RegistrationModel) -> Registration {
    let (w, h) = (open.width, open.height);
    if model == RegistrationModel::None {
        return Registration { info: RegistrationInfo::default(), samples: vec![] };
    }
    let ps = crate::solve::fft::good_size((w.min(h) / 4).clamp(32, 256)) .min(w).min(h) & !1;
    let nx = (w / ps).clamp(1, 6);
    let ny = (h / ps).clamp(1, 6);
    let mut samples = Vec::new();
    for j in 0..ny {
        for i in 0..nx {
            let cx = (i as f64 + 0.5) * w as f64 / nx as f64;
            let cy = (j as f64 + 0.5) * h as f64 / ny as f64;
            let x0 = (cx - ps as f64 / 2.0).round() as isize;
            let y0 = (cy - ps as f64 / 2.0).round() as isize;
            let a = open.window_reflect(x0, y0, ps, ps);
            let b = pinhole.window_reflect(x0, y0, ps, ps);
            let (dx, dy, _) = phase_correlation(&a, &b);
            samples.push([x0 as f64 + ps as f64 / 2.0 - 0.5, y0 as f64 + ps as f64 / 2.0 - 0.5, dx, dy]);
        }
    }
    let c = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let fit = |s: &[[f64; 4]]| -> [f64; 4] {
        match model {
            RegistrationModel::Similarity if s.len() >= 3 => {
                // d = [ (a-1)X - bY + tx , bX + (a-1)Y + ty ]; unknowns (a-1, b, tx, ty)
                let mut ata = [[0.0f64; 4]; 4];
                let mut atb = [0.0f64; 4];
                for q in s {
                    let (x, y) = (q[0] - c.0, q[1] - c.1);
                    for (row, d) in [([x, -y, 1.0, 0.0], q[2]), ([y, x, 0.0, 1.0], q[3])] {
                        for i in 0..4 {
                            atb[i] += row[i] * d;
                            for k in 0..4 {
                                ata[i][k] += row[i] * row[k];
                            }
                        }
                    }
                }
                gauss_jordan(ata, atb, 1e-12).unwrap_or([0.0; 4])
            }
            _ => {
                let n = s.len().max(1) as f64;
                [0.0, 0.0, s.iter().map(|q| q[2]).sum::<f64>() / n, s.iter().map(|q| q[3]).sum::<f64>() / n]
            }
        }
    };
    let resid = |p: &[f64; 4], q: &[f64; 4]| {
        let (x, y) = (q[0] - c.0, q[1] - c.1);
        let ex = p[0] * x - p[1] * y + p[2] - q[2];
        let ey = p[1] * x + p[0] * y + p[3] - q[3];
        (ex * ex + ey * ey).sqrt()
    };
    let mut p = fit(&samples);
    let mut rs: Vec<f64> = samples.iter().map(|q| resid(&p, q)).collect();
    let mut sorted = rs.clone();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let med = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
    let keep: Vec<[f64; 4]> = samples.iter().zip(&rs).filter(|(_, &r)| r <= 3.0 * med.max(0.05)).map(|(q, _)| *q).collect();
    if !keep.is_empty() && keep.len() < samples.len() {
        p = fit(&keep);
        rs = keep.iter().map(|q| resid(&p, q)).collect();
    }
    let rms = (rs.iter().map(|r| r * r).sum::<f64>() / rs.len().max(1) as f64).sqrt();
    let name = match model {
        RegistrationModel::Similarity => "similarity",
        _ => "translation",
    };
    Registration {
        info: RegistrationInfo { model: name.into(), matrix: [1.0 + p[0], -p[1], p[1], 1.0 + p[0]], translation: [p[2], p[3]], residual_px: rms },
        samples,
    }
}

/// Applies the fitted registration to a pinhole plane so it lines up with the wide-open one.
/// Translation: the integer part, exactly (the kernel carries the fraction). Similarity: full
/// bicubic resampling.
pub fn apply(pinhole: &Plane, info: &RegistrationInfo) -> Plane {
    match info.model.as_str() {
        "translation" => {
            let (tx, ty) = (info.translation[0].round() as isize, info.translation[1].round() as isize);
            if tx == 0 && ty == 0 {
                return pinhole.clone();
            }
            pinhole.window_reflect(-tx, -ty, pinhole.width, pinhole.height)
        }
        "similarity" => {
            // open(p) = pinhole(p − d(p)) with d(p) = (A − I)(p − c) + t  ⇒ sample at p − d(p)
            let a = info.matrix[0];
            let b = info.matrix[2];
            // p − d(p) = (2I − A)(p − c) + c − t, itself a similarity about c
            let sim = Similarity { dx: -info.translation[0], dy: -info.translation[1], rotation_deg: (-b).atan2(2.0 - a).to_degrees(), scale: ((2.0 - a).powi(2) + b * b).sqrt() - 1.0 };
            warp_similarity(pinhole, &sim)
        }
        _ => pinhole.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::filter::gaussian_blur;

    fn noise(w: usize, h: usize, seed: u64) -> Plane {
        let mut r = crate::rng::Rng::new(seed);
        Plane::from_fn(w, h, |_, _| r.uniform() as f32)
    }

    #[test]
    fn finds_subpixel_shift_through_blur() {
        let base = gaussian_blur(&noise(200, 160, 3), 0.7);
        let shifted = warp_similarity(&base, &Similarity { dx: -2.3, dy: 1.6, ..Default::default() });
        let blurred = gaussian_blur(&shifted, 2.0);
        let r = register(&blurred, &base, RegistrationModel::Translation);
        assert!((r.info.translation[0] - 2.3).abs() < 0.15 && (r.info.translation[1] + 1.6).abs() < 0.15, "{:?}", r.info);
        let rs = register(&blurred, &base, RegistrationModel::Similarity);
        assert!((rs.info.translation[0] - 2.3).abs() < 0.15, "{:?}", rs.info);
        assert!((rs.info.matrix[0] - 1.0).abs() < 2e-3 && rs.info.matrix[2].abs() < 2e-3);
    }
}
