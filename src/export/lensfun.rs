//! A lensfun database file (`<lensdatabase version="1">`, read by lensfun 0.3, the version
//! today's distributions ship) from what lensrig measured.
//!
//! # What is written, and only when measured
//! - `<tca model="poly3">`: fitted to the lateral colour of the profile, the R and B kernel
//!   centroids against G at every tile ([`fit_tca`]); needs an R, G, B profile.
//! - `<vignetting model="pa">`: fitted to a flat-field capture (wide open, a uniform target
//!   or a diffuser) ([`fit_vignetting`]). The ratio of the wide-open and pinhole exposures is
//!   *relative* vignetting between two apertures, not the lens's falloff, and is never exported.
//! - `<distortion model="ptlens">`: fitted by registering a sharp (pinhole) capture to the
//!   target file itself ([`crate::target::locate`]), stored with the profile as
//!   `distortion.toml` ([`crate::target::locate::MeasuredDistortion`]).
//!
//! # lensfun's conventions (checked against liblensfun 0.3.3 by `tests/lensfun.rs`)
//! - Distortion ptlens: `r_d = r_u·(a·r_u³ + b·r_u² + c·r_u + 1 − a − b − c)`, `r_u` in the
//!   corrected image, `r_d` on the sensor, same centre and radius unit as TCA
//!   ([`crate::optics::distortion`]).
//! - TCA poly3: `r_d = r_u·(b·r_u² + c·r_u + v)` per channel, `r_u` the radius in the corrected
//!   (G-aligned) image and `r_d` where that channel's content lies in the capture; radii are
//!   about the image centre `((w−1)/2, (h−1)/2)`, normalised so that 1 is about half the
//!   **shorter** side ([`tca_norm`]).
//! - Vignetting pa: captured = true · `(1 + k1·r² + k2·r⁴ + k3·r⁶)`, `r` normalised so that 1 is
//!   half the image **diagonal** ([`vignetting_norm`]); lensfun's correction divides by it.
//! - The lens's `<cropfactor>` and `<aspect-ratio>` describe the calibration sensor; a reader
//!   passes the same crop factor for images from that sensor.
//! - Element order follows lensfun's XSD: `maker, model, mount, cropfactor, aspect-ratio,
//!   calibration`, and inside `calibration`: `distortion, tca, vignetting`.

use crate::image::Image;
use crate::optics::distortion::PtLens;
use crate::report::ProfileReport;
use std::fmt::Write as _;

/// Lens identity and the conditions of the calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct LensInfo {
    pub maker: String,
    pub model: String,
    pub mount: String,
    pub focal_mm: f64,
    pub crop_factor: f64,
    /// f-number the PSFs (and so the TCA) and the flat field were measured at.
    pub aperture: f64,
    /// Focus distance, metres.
    pub distance_m: f64,
    /// Sensor size in pixels (for the aspect ratio).
    pub width: usize,
    pub height: usize,
}

/// A fitted poly3 TCA model (lensfun's `vr, cr, br, vb, cb, bb`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tca {
    pub red: [f64; 3],
    pub blue: [f64; 3],
    /// Tiles used and RMS radial residual of the fit, pixels.
    pub tiles: usize,
    pub residual_px: f64,
}

/// A fitted pa vignetting model.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Vignetting {
    pub k: [f64; 3],
    /// RMS residual of the fit, relative to the centre brightness.
    pub residual: f64,
    pub samples: usize,
}

/// Radius normalisation of TCA and distortion (pixels → lensfun units), as liblensfun 0.3.3
/// computes it for an image of the calibration's aspect ratio: one unit is half the diagonal
/// of `(w−1) × (h−1)` divided by `hypot(aspect, 1)`, i.e. about half the shorter side.
pub fn tca_norm(width: usize, height: usize) -> f64 {
    crate::optics::distortion::radius_norm(width, height)
}

/// Radius normalisation of vignetting: one unit is half the diagonal of `(w−1) × (h−1)`.
pub fn vignetting_norm(width: usize, height: usize) -> f64 {
    2.0 / ((width as f64 - 1.0).hypot(height as f64 - 1.0))
}

fn centre(width: usize, height: usize) -> (f64, f64) {
    ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0)
}

/// Solves the normal equations of a small weighted least-squares problem `Σ w·(a·x − y)²`
/// ([`crate::solve::dense::solve`]); `None` when they are singular.
fn lstsq(rows: &[(Vec<f64>, f64, f64)]) -> Option<Vec<f64>> {
    let n = rows.first()?.0.len();
    let (mut ata, mut aty) = (vec![vec![0.0f64; n]; n], vec![0.0f64; n]);
    for (a, y, w) in rows {
        for i in 0..n {
            for j in 0..n {
                ata[i][j] += w * a[i] * a[j];
            }
            aty[i] += w * a[i] * y;
        }
    }
    crate::solve::dense::solve(ata, aty, 1e-18)
}

/// Fits poly3 TCA to the report's lateral colour: for each tile off axis, the radial component
/// `Δr` of the channel's centroid offset gives `r_d/r_u = 1 + Δr/r`; `v + c·r + b·r²` is fitted
/// weighted by `r²` (offsets near the axis say little about a ratio). `None` without R, G and B
/// or with fewer than four tiles off axis.
pub fn fit_tca(r: &ProfileReport) -> Option<Tca> {
    let idx = |n: &str| r.channels.iter().position(|c| c == n);
    let (ri, _, bi) = (idx("R")?, idx("G")?, idx("B")?);
    let s = tca_norm(r.width, r.height);
    let (cx, cy) = centre(r.width, r.height);
    let fit = |c: usize| -> Option<([f64; 3], Vec<f64>)> {
        let mut rows = Vec::new();
        for (t, f) in r.tiles.iter().enumerate() {
            let (dx, dy) = (f.x - cx, f.y - cy);
            let rp = dx.hypot(dy);
            if rp < 0.1 * r.width.min(r.height) as f64 {
                continue;
            }
            let (lx, ly) = r.lateral(c, t);
            let dr = (lx * dx + ly * dy) / rp;
            let ru = rp * s;
            rows.push((vec![1.0, ru, ru * ru], 1.0 + dr / rp, ru * ru));
        }
        if rows.len() < 4 {
            return None;
        }
        let p = lstsq(&rows)?;
        let res: Vec<f64> = rows.iter().map(|(a, y, _)| (a[0] * p[0] + a[1] * p[1] + a[2] * p[2] - y) * a[1] / s).collect();
        Some(([p[0], p[1], p[2]], res))
    };
    let (red, rr) = fit(ri)?;
    let (blue, rb) = fit(bi)?;
    let all: Vec<f64> = rr.iter().chain(&rb).copied().collect();
    let residual_px = (all.iter().map(|v| v * v).sum::<f64>() / all.len() as f64).sqrt();
    Some(Tca { red, blue, tiles: rr.len(), residual_px })
}

impl Tca {
    /// Where channel content of the corrected pixel `(x, y)` lies in the capture, by lensrig's
    /// reading of the model: `(R, B)` source positions in pixels.
    pub fn source_positions(&self, x: f64, y: f64, width: usize, height: usize) -> ((f64, f64), (f64, f64)) {
        let s = tca_norm(width, height);
        let (cx, cy) = centre(width, height);
        let ru = (x - cx).hypot(y - cy) * s;
        let m = |p: &[f64; 3]| p[0] + p[1] * ru + p[2] * ru * ru;
        let (mr, mb) = (m(&self.red), m(&self.blue));
        ((cx + (x - cx) * mr, cy + (y - cy) * mr), (cx + (x - cx) * mb, cy + (y - cy) * mb))
    }
}

/// Fits pa vignetting to a flat-field image (channels averaged, 8 × 8 block means): the
/// brightness `a0·(1 + k1·r² + k2·r⁴ + k3·r⁶)`, `r` normalised to half the diagonal. `None`
/// when the image is too small or dark.
pub fn fit_vignetting(flat: &Image) -> Option<Vignetting> {
    let (w, h) = (flat.width(), flat.height());
    const B: usize = 8;
    if w < 4 * B || h < 4 * B || flat.planes.is_empty() {
        return None;
    }
    let s = vignetting_norm(w, h);
    let (cx, cy) = centre(w, h);
    let mut rows = Vec::new();
    for by in 0..h / B {
        for bx in 0..w / B {
            let mut sum = 0.0f64;
            for p in &flat.planes {
                for y in by * B..(by + 1) * B {
                    for x in bx * B..(bx + 1) * B {
                        sum += p.get(x, y) as f64;
                    }
                }
            }
            let v = sum / (B * B * flat.planes.len()) as f64;
            let (xm, ym) = ((bx * B) as f64 + (B as f64 - 1.0) / 2.0, (by * B) as f64 + (B as f64 - 1.0) / 2.0);
            let r2 = ((xm - cx).powi(2) + (ym - cy).powi(2)) * s * s;
            rows.push((vec![1.0, r2, r2 * r2, r2 * r2 * r2], v, 1.0));
        }
    }
    let p = lstsq(&rows)?;
    if p[0].is_nan() || p[0] <= 1e-6 {
        return None;
    }
    let res = (rows.iter().map(|(a, y, _)| ((a.iter().zip(&p).map(|(x, q)| x * q).sum::<f64>() - y) / p[0]).powi(2)).sum::<f64>() / rows.len() as f64).sqrt();
    Some(Vignetting { k: [p[1] / p[0], p[2] / p[0], p[3] / p[0]], residual: res, samples: rows.len() })
}

/// [`fit_vignetting`] on a flat field minus its dark frame (per pixel, per channel, clamped
/// at 0), the black level a real sensor adds (it would otherwise read as less falloff).
/// `None` as [`fit_vignetting`], or when the dark frame's size or channel count differs.
pub fn fit_flat(flat: &Image, dark: Option<&Image>) -> Option<Vignetting> {
    let Some(d) = dark else { return fit_vignetting(flat) };
    if d.width() != flat.width() || d.height() != flat.height() || d.planes.len() != flat.planes.len() {
        return None;
    }
    let mut f = flat.clone();
    for (p, q) in f.planes.iter_mut().zip(&d.planes) {
        for (v, b) in p.data.iter_mut().zip(&q.data) {
            *v = (*v - *b).max(0.0);
        }
    }
    fit_vignetting(&f)
}

impl Vignetting {
    /// Relative brightness (1 on axis) at pixel `(x, y)` of a `width × height` image.
    pub fn falloff(&self, x: f64, y: f64, width: usize, height: usize) -> f64 {
        let s = vignetting_norm(width, height);
        let (cx, cy) = centre(width, height);
        let r2 = ((x - cx).powi(2) + (y - cy).powi(2)) * s * s;
        1.0 + self.k[0] * r2 + self.k[1] * r2 * r2 + self.k[2] * r2 * r2 * r2
    }
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// A number for an XML attribute: 6 significant decimals, no exponent, never `NaN`.
fn num(v: f64) -> String {
    if v.is_finite() {
        let s = format!("{v:.6}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        if s == "-0" {
            "0".into()
        } else {
            s.to_string()
        }
    } else {
        "0".into()
    }
}

fn gcd(a: usize, b: usize) -> usize {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// The database file. `provenance` lines go into the header comment (what was measured, from
/// which files, when).
pub fn lensfun_xml(info: &LensInfo, distortion: Option<&PtLens>, tca: Option<&Tca>, vignetting: Option<&Vignetting>, provenance: &[String]) -> String {
    let mut s = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<!DOCTYPE lensdatabase SYSTEM \"lensfun-database.dtd\">\n<!--\n");
    for line in provenance {
        let _ = writeln!(s, "  {}", line.replace("--", "- -"));
    }
    s.push_str("-->\n<lensdatabase version=\"1\">\n    <lens>\n");
    let _ = writeln!(s, "        <maker>{}</maker>", xml_escape(&info.maker));
    let _ = writeln!(s, "        <model>{}</model>", xml_escape(&info.model));
    let _ = writeln!(s, "        <mount>{}</mount>", xml_escape(&info.mount));
    let _ = writeln!(s, "        <cropfactor>{}</cropfactor>", num(info.crop_factor));
    let g = gcd(info.width, info.height).max(1);
    let _ = writeln!(s, "        <aspect-ratio>{}:{}</aspect-ratio>", info.width.max(info.height) / g, info.width.min(info.height) / g);
    if distortion.is_some() || tca.is_some() || vignetting.is_some() {
        s.push_str("        <calibration>\n");
        if let Some(d) = distortion {
            let _ = writeln!(s, "            <distortion model=\"ptlens\" focal=\"{}\" a=\"{}\" b=\"{}\" c=\"{}\" />", num(info.focal_mm), num(d.a), num(d.b), num(d.c));
        }
        if let Some(t) = tca {
            let _ = writeln!(
                s,
                "            <tca model=\"poly3\" focal=\"{}\" vr=\"{}\" cr=\"{}\" br=\"{}\" vb=\"{}\" cb=\"{}\" bb=\"{}\" />",
                num(info.focal_mm),
                num(t.red[0]),
                num(t.red[1]),
                num(t.red[2]),
                num(t.blue[0]),
                num(t.blue[1]),
                num(t.blue[2])
            );
        }
        if let Some(v) = vignetting {
            let _ = writeln!(
                s,
                "            <vignetting model=\"pa\" focal=\"{}\" aperture=\"{}\" distance=\"{}\" k1=\"{}\" k2=\"{}\" k3=\"{}\" />",
                num(info.focal_mm),
                num(info.aperture),
                num(info.distance_m),
                num(v.k[0]),
                num(v.k[1]),
                num(v.k[2])
            );
        }
        s.push_str("        </calibration>\n");
    }
    s.push_str("    </lens>\n</lensdatabase>\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::Plane;

    #[test]
    fn vignetting_fit_recovers_a_known_falloff() {
        let (w, h) = (320, 240);
        let truth = Vignetting { k: [-0.3, 0.05, -0.01], residual: 0.0, samples: 0 };
        let p = Plane::from_fn(w, h, |x, y| (0.7 * truth.falloff(x as f64, y as f64, w, h)) as f32);
        let v = fit_vignetting(&Image::new(vec![p])).expect("fit");
        for (a, b) in v.k.iter().zip(truth.k) {
            assert!((a - b).abs() < 0.01, "{:?} vs {:?}", v.k, truth.k);
        }
        assert!(v.residual < 1e-3);
    }

    #[test]
    fn dark_frame_is_subtracted_before_the_fit() {
        let (w, h) = (160, 120);
        let truth = Vignetting { k: [-0.2, 0.0, 0.0], residual: 0.0, samples: 0 };
        let flat = Plane::from_fn(w, h, |x, y| (0.05 + 0.6 * truth.falloff(x as f64, y as f64, w, h)) as f32);
        let dark = Plane::filled(w, h, 0.05);
        let biased = fit_vignetting(&Image::new(vec![flat.clone()])).expect("fit");
        assert!(biased.k[0] > -0.19, "the black level reads as less falloff: {:?}", biased.k);
        let v = fit_flat(&Image::new(vec![flat.clone()]), Some(&Image::new(vec![dark]))).expect("fit");
        assert!((v.k[0] + 0.2).abs() < 1e-3 && v.k[1].abs() < 1e-3, "{:?}", v.k);
        assert!(fit_flat(&Image::new(vec![flat]), Some(&Image::new(vec![Plane::filled(8, 8, 0.0)]))).is_none());
    }

    #[test]
    fn xml_has_lensfun_order_and_only_measured_blocks() {
        let info = LensInfo { maker: "lensrig".into(), model: "A & B".into(), mount: "C".into(), focal_mm: 16.0, crop_factor: 18.0, aperture: 5.6, distance_m: 1.0, width: 384, height: 288 };
        let t = Tca { red: [1.001, 0.0, 0.0002], blue: [0.999, 0.0, 0.0], tiles: 12, residual_px: 0.01 };
        let x = lensfun_xml(&info, None, Some(&t), None, &["measured: tca".into()]);
        assert!(x.contains("<lensdatabase version=\"1\">"));
        assert!(x.contains("<model>A &amp; B</model>"));
        assert!(x.contains("<aspect-ratio>4:3</aspect-ratio>"));
        assert!(x.contains("vr=\"1.001\"") && x.contains("br=\"0.0002\""));
        assert!(!x.contains("vignetting") && !x.contains("distortion"));
        let order = ["<maker>", "<model>", "<mount>", "<cropfactor>", "<aspect-ratio>", "<calibration>", "<tca"];
        let pos: Vec<usize> = order.iter().map(|o| x.find(o).unwrap_or(usize::MAX)).collect();
        assert!(pos.windows(2).all(|p| p[0] < p[1]), "{pos:?}");
        let none = lensfun_xml(&info, None, None, None, &[]);
        assert!(!none.contains("<calibration>"));
        let d = PtLens { a: 0.001, b: -0.02, c: 0.0 };
        let x = lensfun_xml(&info, Some(&d), Some(&t), None, &[]);
        assert!(x.contains("<distortion model=\"ptlens\" focal=\"16\" a=\"0.001\" b=\"-0.02\" c=\"0\" />"), "{x}");
        assert!(x.find("<distortion").unwrap() < x.find("<tca").unwrap());
    }
}
