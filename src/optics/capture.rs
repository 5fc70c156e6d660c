//! Simulated captures: a sharp scene through the lens and the sensor, every physical term
//! switchable so tests can conceal one.
//!
//! # Model, in the order light meets it
//! 1. `misregistration` — the scene moves between captures (rig vibration): the scene is
//!    resampled at `S·R(θ)·(p − c) + c + t` (similarity about the image centre `c`).
//! 2. `illumination_gradient` — the lamp's light on the target: gain `1 + gx·x̂ + gy·ŷ`,
//!    `x̂, ŷ ∈ [−1, 1]` across the image.
//! 3. **lens blur** — the spatially varying PSFs of [`super::lens::LensModel`] at the capture's
//!    f-number ([`super::forward`]); [`Blur::None`] is an ideal reference.
//! 4. `vignetting` — radial gain `1 + k1 r² + k2 r⁴ + k3 r⁶`, `r = 1` at half the diagonal
//!    (lensfun's `pa` model).
//! 5. `veiling_glare` — stray light: `(1 − g)·E + g·(E * G_σ)` with a wide Gaussian `G_σ`
//!    (energy conserving).
//! 6. **exposure** — `E·exposure` on the full-scale axis (1.0 = full well).
//! 7. **sensor** — Poisson shot noise on `E·full_well` electrons, Gaussian read noise,
//!    additive `black_offset` (ambient light / black-level mismatch), clipping to [0, 1]
//!    (`saturation`), optional transfer encoding (`tone_curve`), quantisation to 8/16 bits.
//!
//! Noise variance on the full-scale axis (linear, before encoding) is
//! `Var = v/full_well + (read_noise/full_well)² + Δ²/12` (`Δ` the quantisation step).

use super::forward::blur;
use super::lens::LensModel;
use super::psf_grid::PsfGrid;
use crate::image::filter::gaussian_blur;
use crate::image::resample::{warp, Affine, Interpolation};
use crate::image::{Image, Plane, SampleFormat, Transfer};
use crate::rng::Rng;
use serde::{Deserialize, Serialize};

/// The sensor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sensor {
    pub full_well_e: f64,
    pub read_noise_e: f64,
    pub bits: u32,
    /// Encoding applied before quantisation (webcams: sRGB).
    pub transfer: Transfer,
    /// Whether to add noise at all.
    pub noise: bool,
}

impl Default for Sensor {
    fn default() -> Self {
        Self { full_well_e: 20_000.0, read_noise_e: 6.0, bits: 16, transfer: Transfer::Linear, noise: true }
    }
}

impl Sensor {
    /// Noise variance (full-scale², linear) at linear signal `v`.
    pub fn variance(&self, v: f32) -> f32 {
        if !self.noise {
            return 0.0;
        }
        let fw = self.full_well_e as f32;
        let q = 1.0 / ((1u64 << self.bits) - 1) as f32;
        v.max(0.0) / fw + (self.read_noise_e as f32 / fw).powi(2) + q * q / 12.0
    }
}

/// A similarity transform of the scene (misregistration).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Similarity {
    pub dx: f64,
    pub dy: f64,
    pub rotation_deg: f64,
    /// Relative scale change (0 = none).
    pub scale: f64,
}

/// Stray light.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Glare {
    pub fraction: f64,
    pub sigma_px: f64,
}

/// How the image is blurred.
#[derive(Clone, Debug, PartialEq)]
pub enum Blur {
    /// No blur at all: an ideal sharp reference.
    None,
    /// The lens at this f-number, PSFs sampled on a `columns × rows` grid with `k × k` kernels.
    Lens { f_number: f64, columns: usize, rows: usize, kernel_size: usize },
    /// Given PSFs.
    Grid(PsfGrid),
}

/// One exposure of the rig with every optional physical term.
#[derive(Clone, Debug, PartialEq)]
pub struct Shot {
    pub blur: Blur,
    /// Linear full-scale value recorded for a white (reflectance 1) scene point.
    pub exposure: f64,
    pub misregistration: Option<Similarity>,
    pub illumination_gradient: Option<[f64; 2]>,
    pub vignetting: Option<[f64; 3]>,
    pub veiling_glare: Option<Glare>,
    /// Added per channel after exposure (full scale).
    pub black_offset: Option<Vec<f32>>,
    /// Clip at full scale (a real sensor always does; off only for analysis).
    pub clip: bool,
}

impl Shot {
    /// A plain exposure through the lens, no extra effects.
    pub fn lens(f_number: f64, exposure: f64, columns: usize, rows: usize, kernel_size: usize) -> Self {
        Self {
            blur: Blur::Lens { f_number, columns, rows, kernel_size },
            exposure,
            misregistration: None,
            illumination_gradient: None,
            vignetting: None,
            veiling_glare: None,
            black_offset: None,
            clip: true,
        }
    }

    /// An ideal sharp reference (no blur).
    pub fn ideal(exposure: f64) -> Self {
        Self { blur: Blur::None, ..Self::lens(1.0, exposure, 1, 1, 1) }
    }
}

/// A simulated capture with its truth.
#[derive(Clone, Debug)]
pub struct Rendered {
    /// What the camera recorded (quantised, encoded as the sensor says).
    pub image: Image,
    /// The noise-free linear signal before clipping.
    pub clean: Vec<Plane>,
    /// Noise variance per pixel (linear full scale²).
    pub variance: Vec<Plane>,
    /// The PSFs that were applied (None for an ideal reference).
    pub psfs: Option<PsfGrid>,
}

/// Renders `scene` (linear reflectance planes, one per lens band) through `lens` as `shot`.
pub fn render(scene: &[Plane], lens: &LensModel, shot: &Shot, sensor: &Sensor, rng: &mut Rng) -> Rendered {
    let mut planes: Vec<Plane> = scene.to_vec();
    if let Some(m) = shot.misregistration {
        planes = planes.iter().map(|p| warp_similarity(p, &m)).collect();
    }
    if let Some([gx, gy]) = shot.illumination_gradient {
        for p in &mut planes {
            apply_gain(p, |xn, yn, _| 1.0 + gx * xn + gy * yn);
        }
    }
    let psfs = match &shot.blur {
        Blur::None => None,
        Blur::Lens { f_number, columns, rows, kernel_size } => Some(lens.psf_grid(*f_number, *columns, *rows, *kernel_size)),
        Blur::Grid(g) => Some(g.clone()),
    };
    if let Some(g) = &psfs {
        planes = blur(&planes, g);
    }
    if let Some([k1, k2, k3]) = shot.vignetting {
        for p in &mut planes {
            apply_gain(p, |_, _, r2| 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2);
        }
    }
    if let Some(gl) = shot.veiling_glare {
        for p in &mut planes {
            let wide = gaussian_blur(p, gl.sigma_px);
            for (v, b) in p.data.iter_mut().zip(&wide.data) {
                *v = (1.0 - gl.fraction as f32) * *v + gl.fraction as f32 * b;
            }
        }
    }
    for p in &mut planes {
        p.scale(shot.exposure as f32);
    }
    let clean = planes.clone();
    let variance: Vec<Plane> = clean.iter().map(|p| p.map(|v| sensor.variance(v))).collect();
    let full = ((1u64 << sensor.bits) - 1) as f32;
    let fw = sensor.full_well_e;
    for (c, p) in planes.iter_mut().enumerate() {
        let off = shot.black_offset.as_ref().and_then(|o| o.get(c).copied()).unwrap_or(0.0);
        for v in p.data.iter_mut() {
            let mut x = *v as f64;
            if sensor.noise {
                x = (rng.poisson(x.max(0.0) * fw) + sensor.read_noise_e * rng.normal()) / fw;
            }
            let mut y = x as f32 + off;
            if shot.clip {
                y = y.clamp(0.0, 1.0);
            }
            y = sensor.transfer.encode(y);
            *v = if shot.clip { (y * full).round() / full } else { y };
        }
    }
    let mut image = Image::new(planes);
    image.channels = lens.channel_names();
    image.format = if sensor.bits <= 8 { SampleFormat::U8 } else { SampleFormat::U16 };
    image.transfer = sensor.transfer;
    Rendered { image, clean, variance, psfs }
}

/// Multiplies by a gain of normalised position: `f(x̂, ŷ, r²)` with `x̂, ŷ ∈ [−1, 1]` across the
/// image and `r² = ((x−cx)² + (y−cy)²)/(half diagonal)²`.
pub fn apply_gain(p: &mut Plane, f: impl Fn(f64, f64, f64) -> f64) {
    let (w, h) = (p.width, p.height);
    let cx = (w as f64 - 1.0) / 2.0;
    let cy = (h as f64 - 1.0) / 2.0;
    let hd2 = 0.25 * ((w * w + h * h) as f64);
    for y in 0..h {
        for x in 0..w {
            let (dx, dy) = (x as f64 - cx, y as f64 - cy);
            let g = f(dx / cx.max(0.5), dy / cy.max(0.5), (dx * dx + dy * dy) / hd2);
            p.data[y * w + x] *= g as f32;
        }
    }
}

/// Resamples `p` at `S·R·(q − c) + c + t` for every output pixel `q` (bicubic, Keys a = −0.5,
/// [`crate::image::resample::warp`]), i.e. the content moves by the inverse of that map.
pub fn warp_similarity(p: &Plane, m: &Similarity) -> Plane {
    let th = m.rotation_deg.to_radians();
    let s = 1.0 + m.scale;
    let (a, b) = (s * th.cos(), s * th.sin());
    warp(p, &Affine { matrix: [a, -b, b, a], shift: [m.dx, m.dy] }, Interpolation::Keys)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(v: f32) -> Vec<Plane> {
        vec![Plane::filled(64, 48, v); 3]
    }

    #[test]
    fn noise_matches_the_stated_variance() {
        let lens = LensModel::demo(64, 48);
        let sensor = Sensor { full_well_e: 5000.0, read_noise_e: 10.0, ..Default::default() };
        let shot = Shot::ideal(0.5);
        let r = render(&flat(1.0), &lens, &shot, &sensor, &mut Rng::new(3));
        let d = &r.image.planes[1].data;
        let m = d.iter().map(|v| *v as f64).sum::<f64>() / d.len() as f64;
        let var = d.iter().map(|v| (*v as f64 - m).powi(2)).sum::<f64>() / d.len() as f64;
        let want = r.variance[1].get(0, 0) as f64;
        assert!((m - 0.5).abs() < 0.002, "mean {m}");
        assert!((var / want - 1.0).abs() < 0.08, "var {var} vs {want}");
    }

    #[test]
    fn effects_do_what_they_say() {
        let lens = LensModel::demo(64, 48);
        let sensor = Sensor { noise: false, ..Default::default() };
        let mut shot = Shot::ideal(0.5);
        shot.vignetting = Some([-0.3, 0.0, 0.0]);
        shot.black_offset = Some(vec![0.01, 0.02, 0.03]);
        let r = render(&flat(1.0), &lens, &shot, &sensor, &mut Rng::new(1));
        let p = &r.image.planes[2];
        // centre: 0.5 + 0.03; corner: r² = 1 → 0.5·0.7 + 0.03
        assert!((p.get(32, 24) - 0.53).abs() < 0.003, "{}", p.get(32, 24));
        assert!((p.get(0, 0) - (0.35 * 1.0 + 0.03)).abs() < 0.01, "{}", p.get(0, 0));
        // clipping and sRGB encoding
        let s2 = Sensor { noise: false, transfer: Transfer::Srgb, bits: 8, ..Default::default() };
        let r2 = render(&flat(1.0), &lens, &Shot::ideal(2.0), &s2, &mut Rng::new(1));
        assert_eq!(r2.image.planes[0].get(5, 5), 1.0);
        let r3 = render(&flat(1.0), &lens, &Shot::ideal(0.2), &s2, &mut Rng::new(1));
        assert!((r3.image.planes[0].get(5, 5) - (crate::image::srgb_encode(0.2) * 255.0).round() / 255.0).abs() < 1e-6);
    }

    #[test]
    fn warp_moves_content_by_the_inverse_map() {
        let p = Plane::from_fn(40, 30, |x, y| (x as f32 * 0.3).sin() + (y as f32 * 0.2).cos());
        let w = warp_similarity(&p, &Similarity { dx: 2.0, ..Default::default() });
        assert!((w.get(10, 10) - p.get(12, 10)).abs() < 1e-5);
    }
}
