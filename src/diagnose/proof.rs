//! Proof cases: calibration pairs rendered by the simulator ([`crate::optics::capture`]) with one
//! catalogue effect concealed at a randomised, realistic magnitude, a set of them
//! (`"vignetting+black_level"`: each drawn in turn from the same seed's generator), or none
//! (clean), plus the truth the tests and the benchmark compare the diagnosis against (the
//! effects' parameters merged into one object; their keys are distinct). Nothing here is used
//! by the diagnosis itself.
//!
//! # Target tilt (`target_tilt`)
//! The printed target tilts by `θ` (1.5–3°) about an axis in its plane through the optical axis
//! between the two captures (a target on a stand, rocked when the aperture changes). The
//! reference then sees the plane through a homography: with `a` the centred pixel coordinate
//! across the axis (unit normal `n = (cos φ, sin φ)` in the image), `b` the one along it, and
//! `f` the focal length in pixels, the reference pixel `(a, b)` sees the point
//! `(a / cos θ, b) / (1 − a·tan θ / f)` of the wide-open view. The proof images are small
//! stand-ins for a webcam frame, so `f` is that of a 50° horizontal field of view across the
//! case's width (`f = (w/2) / tan 25°`, 274 px at 256 px), not the simulator lens's
//! 16 mm / 5 µm. To first order this is the perspective row `(g, h) = (tan θ / f)·n` of
//! [`super::model`]'s `target_tilt` (the `1/cos θ` stretch, 0.14 % at 3°, is left to the
//! kernels).
//!
//! # Scene
//! The printed noise target ([`crate::target`]) framed by a dimmer background (the paper does
//! not fill the frame), so large-scale brightness varies and stray light has something to show.
//!
//! # Stopped-down reference (`pinhole_diffraction`)
//! The reference is rendered through the same lens at f/11–f/22 (diffraction, its residual
//! aberrations, the mono band's three wavelengths), with PSFs out to 10 Airy radii: the
//! Airy pattern's tails carry a few per cent of its energy far from the core, and cutting them
//! at the wide-open kernel's 15 px would flatten its transfer function at low frequencies,
//! which no lens does. The truth records the Airy radius at the band's mean wavelength and the
//! rendered PSFs' MTF50 ([`kernel_mtf50`]).
//!
//! # Truth noise floor
//! `Var_true = Var_open + s²·ΣK²·Var_pinhole` from the simulator's per-pixel variances and the
//! true kernels, mapped to the stored axis by the encoding's slope.

use super::noise::srgb_slope;
use crate::image::spectrum::RadialPsd;
use crate::image::{Plane, Transfer};
use crate::optics::capture::{render, Blur, Glare, Rendered, Sensor, Shot, Similarity};
use crate::optics::lens::{mono_band, LensModel};
use crate::optics::psf_grid::PsfGrid;
use crate::rng::Rng;
use crate::target::TargetSpec;
use serde_json::json;

/// The effects the proof suite conceals, in catalogue order.
pub const CONCEALED: [&str; 10] = ["vignetting", "illumination_gradient", "tone_curve", "black_level", "veiling_glare", "misregistration", "target_tilt", "saturation", "psf_field_variation", "pinhole_diffraction"];

/// The pairs of effects concealed together (issue 17: real rigs rarely have one flaw).
pub const PAIRS: [&str; 3] = ["vignetting+black_level", "veiling_glare+tone_curve", "misregistration+pinhole_diffraction"];

/// An effect name that is not one of [`CONCEALED`] (or a set with one such name, or with a
/// name twice).
#[derive(Debug, thiserror::Error)]
#[error("unknown effect '{0}' (expected one of {list}, or several joined by '+')", list = CONCEALED.join(", "))]
pub struct UnknownEffect(pub String);

/// The effects of a case name: `"a+b"` → `["a", "b"]` (each one of [`CONCEALED`], none twice).
///
/// # Errors
/// An unknown or repeated name.
pub fn effect_set(effect: &str) -> Result<Vec<&str>, UnknownEffect> {
    let set: Vec<&str> = effect.split('+').map(str::trim).collect();
    for (i, e) in set.iter().enumerate() {
        if !CONCEALED.contains(e) || set[..i].contains(e) {
            return Err(UnknownEffect(effect.to_string()));
        }
    }
    Ok(set)
}

/// Size and optics of a proof case.
#[derive(Clone, Debug)]
pub struct CaseSpec {
    pub width: usize,
    pub height: usize,
    /// 1 (monochrome) or 3 (RGB).
    pub channels: usize,
    pub f_number: f64,
    pub kernel_size: usize,
    /// Tile grid the truth PSFs are rendered on (matching the estimator's tiles for clean data).
    pub grid: (usize, usize),
    /// Truth PSFs for the wide-open capture instead of the simulator's lens at `f_number`
    /// (e.g. a real design's profile from the lens test bed); its size, channel count and
    /// kernel size must match the other fields.
    pub truth_psfs: Option<PsfGrid>,
}

impl CaseSpec {
    /// This case rendered through a truth profile's PSFs (`diagnose --bench-lens`, e.g. a real
    /// design in `../shared/data/lenses/`): the profile's source size, grid and kernel size, RGB.
    /// Fails (with the channel count) unless the profile has three channels.
    pub fn through_truth(self, truth: &crate::profile::Profile) -> Result<CaseSpec, usize> {
        let (src, grid) = (&truth.meta.source, &truth.grid);
        if grid.channels.len() != 3 {
            return Err(grid.channels.len());
        }
        Ok(CaseSpec { width: src.width, height: src.height, channels: 3, kernel_size: grid.kernel_size, grid: (grid.columns, grid.rows), truth_psfs: Some(grid.clone()), ..self })
    }
}

impl Default for CaseSpec {
    fn default() -> Self {
        Self { width: 256, height: 192, channels: 1, f_number: 5.6, kernel_size: 15, grid: (3, 2), truth_psfs: None }
    }
}

/// A rendered pair with its truth.
pub struct Case {
    pub open: Rendered,
    pub pinhole: Rendered,
    pub effect: Option<String>,
    /// The concealed effect's parameters as rendered.
    pub truth: serde_json::Value,
    /// Per channel, the true noise variance of a perfect prediction on the stored axis.
    pub true_variance: Vec<Plane>,
    /// Frames averaged in the pinhole capture (the wide-open one: 1), capture metadata a rig
    /// records; the diagnosis is told it, not the effect.
    pub pinhole_frames: usize,
}

/// The framed noise scene, linear reflectance.
pub fn scene(w: usize, h: usize, seed: u64) -> Plane {
    scene_moved(w, h, seed, None, 1.6)
}

/// The framed noise scene seen through a moved camera: pixel `q` sees the scene at
/// `S·R(θ)·(q − c) + c + t` (the convention of [`crate::optics::capture::warp_similarity`]),
/// rendered exactly from the procedural target (area-averaged, 4×4 samples per pixel) rather
/// than by resampling a rendered image, which would low-pass the sharp reference.
pub fn scene_moved(w: usize, h: usize, seed: u64, m: Option<Similarity>, pixels_per_cell: f64) -> Plane {
    scene_moved_soft(w, h, seed, m, pixels_per_cell, 0.0)
}

/// [`scene_moved`] with the printed pattern itself softened by a Gaussian of `sigma_px` (pixels
/// of the unmoved view) *before* the pixels integrate it: the softened pattern is a property of
/// the scene, so every camera pose sees the same band-limited continuous image. Each cell is
/// constant, so the blurred pattern at a point is exact: `Σ_cells value·Δ_xΦ·Δ_yΦ` (the
/// Gaussian's mass over the cell, separable). `sigma_px = 0` is the sharp pattern.
pub fn scene_moved_soft(w: usize, h: usize, seed: u64, m: Option<Similarity>, pixels_per_cell: f64, sigma_px: f64) -> Plane {
    scene_viewed(w, h, seed, &View { moved: m, tilt: None }, pixels_per_cell, sigma_px)
}

/// How the reference's camera sees the scene relative to the wide-open capture's.
#[derive(Clone, Copy, Debug, Default)]
pub struct View {
    /// The camera's move (see [`scene_moved`]).
    pub moved: Option<Similarity>,
    /// The target's tilt (module docs, "Target tilt").
    pub tilt: Option<Tilt>,
}

/// A target tilted by `theta_deg` about an in-plane axis whose normal in the image is at
/// `axis_deg`, seen with a focal length of `focal_px` pixels (module docs).
#[derive(Clone, Copy, Debug)]
pub struct Tilt {
    pub theta_deg: f64,
    pub axis_deg: f64,
    pub focal_px: f64,
}

impl Tilt {
    /// The point of the untilted view (centred pixels) that centred reference pixel `q` sees.
    pub fn map(&self, q: (f64, f64)) -> (f64, f64) {
        let (th, phi) = (self.theta_deg.to_radians(), self.axis_deg.to_radians());
        let (nx, ny) = (phi.cos(), phi.sin());
        let (a, b) = (q.0 * nx + q.1 * ny, -q.0 * ny + q.1 * nx);
        let den = 1.0 - a * th.tan() / self.focal_px;
        let (a2, b2) = (a / th.cos() / den, b / den);
        (a2 * nx - b2 * ny, a2 * ny + b2 * nx)
    }
    /// The first-order perspective row `(g, h) = (tan θ / f)·n` (module docs).
    pub fn perspective(&self) -> [f64; 2] {
        let (th, phi) = (self.theta_deg.to_radians(), self.axis_deg.to_radians());
        let k = th.tan() / self.focal_px;
        [k * phi.cos(), k * phi.sin()]
    }
}

/// [`scene_moved_soft`] through a [`View`]: the tilt first (the reference pixel onto the
/// untilted view), then the camera's move.
pub fn scene_viewed(w: usize, h: usize, seed: u64, view: &View, pixels_per_cell: f64, sigma_px: f64) -> Plane {
    let spec = TargetSpec::new("A4", 300, 4, seed).ok();
    let (x0, x1, y0, y1) = (0.12 * w as f64, 0.80 * w as f64, 0.10 * h as f64, 0.86 * h as f64);
    let edge = |v: f64, a: f64, b: f64| {
        let s = |t: f64| 1.0 / (1.0 + (-t / 1.5).exp());
        s(v - a) * s(b - v)
    };
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let m = view.moved.unwrap_or_default();
    let th = m.rotation_deg.to_radians();
    let (a, b) = ((1.0 + m.scale) * th.cos(), (1.0 + m.scale) * th.sin());
    let (ppc, u0, v0) = (pixels_per_cell, 7.0, 5.0);
    let ss = 4;
    Plane::from_fn(w, h, |x, y| {
        let mut acc = 0.0f32;
        for j in 0..ss {
            for i in 0..ss {
                let q = (x as f64 + (i as f64 + 0.5) / ss as f64 - 0.5 - cx, y as f64 + (j as f64 + 0.5) / ss as f64 - 0.5 - cy);
                let (qx, qy) = view.tilt.map_or(q, |t| t.map(q));
                let (sx, sy) = (a * qx - b * qy + cx + m.dx, b * qx + a * qy + cy + m.dy);
                let (u, v) = (u0 + (sx + 0.5) / ppc, v0 + (sy + 0.5) / ppc);
                let n = spec.as_ref().map_or(0.5, |s| if sigma_px > 0.0 { soft_noise(s, u, v, sigma_px / ppc) } else { s.noise_at(u, v) });
                let frame = edge(sx, x0, x1) * edge(sy, y0, y1);
                acc += n * (0.2 + 0.8 * frame as f32);
            }
        }
        acc / (ss * ss) as f32
    })
}

/// The cell pattern of `spec` blurred by a Gaussian of `sigma` cells at `(u, v)` (exact for
/// piecewise-constant cells; see [`scene_moved_soft`]).
fn soft_noise(spec: &TargetSpec, u: f64, v: f64, sigma: f64) -> f32 {
    let reach = (4.0 * sigma).ceil() as i64 + 1;
    let (iu, iv) = (u.floor() as i64, v.floor() as i64);
    let mass = |c: i64, x: f64| phi((c as f64 + 1.0 - x) / sigma) - phi((c as f64 - x) / sigma);
    let wu: Vec<f64> = (iu - reach..=iu + reach).map(|c| mass(c, u)).collect();
    let wv: Vec<f64> = (iv - reach..=iv + reach).map(|c| mass(c, v)).collect();
    let mut acc = 0.0f64;
    for (j, cv) in (iv - reach..=iv + reach).enumerate() {
        for (i, cu) in (iu - reach..=iu + reach).enumerate() {
            acc += wu[i] * wv[j] * spec.noise_at(cu as f64 + 0.5, cv as f64 + 0.5) as f64;
        }
    }
    let total: f64 = wu.iter().sum::<f64>() * wv.iter().sum::<f64>();
    (acc / total) as f32
}

/// The standard normal CDF (Abramowitz–Stegun 7.1.26 for erf, |error| < 1.5e-7).
fn phi(x: f64) -> f64 {
    let z = x.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * z);
    let poly = t * (0.254_829_592 + t * (-0.284_496_736 + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let erf = 1.0 - poly * (-z * z).exp();
    if x >= 0.0 { 0.5 * (1.0 + erf) } else { 0.5 * (1.0 - erf) }
}

fn signed(r: &mut Rng, lo: f64, hi: f64) -> f64 {
    let v = r.range(lo, hi);
    if r.uniform() < 0.5 { -v } else { v }
}

/// The two shots and sensors of a proof case, and what the concealed effect changed.
struct Setup {
    sensor: Sensor,
    open_shot: Shot,
    pin_shot: Shot,
    pin_sensor: Sensor,
    pinhole_frames: usize,
    /// Under `misregistration` and `target_tilt`, how the reference sees the scene.
    view: View,
}

/// Renders a proof case: `effect` (one of [`CONCEALED`], or several joined by `+`, see
/// [`effect_set`]) or `None` for clean data.
///
/// # Errors
/// An unknown effect name.
pub fn render_case(effect: Option<&str>, seed: u64, spec: &CaseSpec) -> Result<Case, UnknownEffect> {
    let set = effect.map(effect_set).transpose()?.unwrap_or_default();
    let (w, h) = (spec.width, spec.height);
    let mut lens = LensModel::demo(w, h);
    if spec.channels == 1 {
        lens.bands = mono_band();
    }
    let mut rng = Rng::new(seed.wrapping_mul(7919).wrapping_add(17));
    let ppc = 1.6;
    // A sub-pixel move of a reference is only reproducible when the reference is band-limited;
    // an aliased 1.6-px-cell target is not (a real pinhole reference is softened by diffraction,
    // about 2.44·λ·N across). The misregistration case therefore uses a softened target
    // (Gaussian σ = 1 px) in both captures, softened before the pixels integrate it: blurring
    // the sampled image instead keeps the aliasing of each pose's sampling, which differs
    // between the poses, and no resampling model reproduces it (it held the fit at ~2.7× the
    // floor even with the true similarity and kernels).
    // (`target_tilt` moves the reference's geometry as well)
    let soft_sigma = if set.iter().any(|e| ["misregistration", "target_tilt"].contains(e)) { 1.0 } else { 0.0 };
    let sc: Vec<Plane> = vec![scene_moved_soft(w, h, seed, None, ppc, soft_sigma); lens.bands.len()];
    let sensor = Sensor::default();
    let mut s = Setup {
        pin_sensor: sensor.clone(),
        sensor,
        open_shot: Shot::lens(spec.f_number, 0.7, spec.grid.0, spec.grid.1, spec.kernel_size),
        pin_shot: Shot::ideal(0.7),
        pinhole_frames: 1,
        view: View::default(),
    };
    if let Some(g) = &spec.truth_psfs {
        s.open_shot.blur = Blur::Grid(g.clone());
    }
    let mut truth = json!({});
    for e in &set {
        let t = conceal(Some(e), &mut rng, spec, &lens, &mut s)?;
        if let (Some(all), Some(one)) = (truth.as_object_mut(), t.as_object()) {
            all.extend(one.clone());
        }
    }
    // one camera records both captures: the reference shares the wide-open capture's encoding
    // (`pin_sensor` is cloned before the effect is chosen, so `tone_curve` must reach it here)
    s.pin_sensor.transfer = s.sensor.transfer;
    let mut open = render(&sc, &lens, &s.open_shot, &s.sensor, &mut Rng::new(seed * 2 + 1));
    let pin_scene: Vec<Plane> = match s.view {
        View { moved: None, tilt: None } => sc.clone(),
        v => vec![scene_viewed(w, h, seed, &v, ppc, soft_sigma); lens.bands.len()],
    };
    let mut pinhole = render(&pin_scene, &lens, &s.pin_shot, &s.pin_sensor, &mut Rng::new(seed * 2 + 2));
    if let (Some(pg), Some(t)) = (&pinhole.psfs, truth.as_object_mut()) {
        // the rendered reference PSFs' MTF50, averaged over the tiles (first channel)
        t.insert("mtf50_cycles_per_px".into(), json!(kernel_mtf50(&pg.kernels[0])));
    }
    // concealed: the files are declared linear whatever the sensor did
    open.image.transfer = Transfer::Linear;
    pinhole.image.transfer = Transfer::Linear;
    let true_variance = true_variance(&open, &pinhole, &sc, &s, (w, h));
    Ok(Case { open, pinhole, effect: effect.map(str::to_string), truth, true_variance, pinhole_frames: s.pinhole_frames })
}

/// Conceals `effect` in the shots and sensors of `s` at a magnitude drawn from `rng`; returns
/// its parameters as rendered (the truth).
fn conceal(effect: Option<&str>, rng: &mut Rng, spec: &CaseSpec, lens: &LensModel, s: &mut Setup) -> Result<serde_json::Value, UnknownEffect> {
    let k = spec.kernel_size;
    Ok(match effect {
        None => json!({}),
        Some("vignetting") => {
            let (k1, k2) = (-rng.range(0.15, 0.35), rng.range(0.0, 0.05));
            s.open_shot.vignetting = Some([k1, k2, 0.0]);
            json!({"k1": k1, "k2": k2, "k3": 0.0})
        }
        Some("illumination_gradient") => {
            let (gx, gy) = (signed(rng, 0.04, 0.12), signed(rng, 0.04, 0.12));
            s.open_shot.illumination_gradient = Some([gx, gy]);
            json!({"gx": gx, "gy": gy})
        }
        Some("tone_curve") => {
            s.sensor.transfer = Transfer::Srgb;
            json!({"transfer": "srgb"})
        }
        Some("black_level") => {
            let off: Vec<f32> = (0..lens.bands.len()).map(|_| rng.range(0.01, 0.04) as f32).collect();
            s.open_shot.black_offset = Some(off.clone());
            json!({"offset": off})
        }
        Some("veiling_glare") => {
            // A veiling glare's halo is a fraction of the frame (the candidate searches it as a
            // fraction of the diagonal, `candidates::glare_sigma`): 18–36 px on the 256 × 192
            // proof frame (diagonal 320 px), the same fraction of the diagonal at any size.
            let frame = ((spec.width * spec.width + spec.height * spec.height) as f64).sqrt() / 320.0;
            let (f, sigma) = (rng.range(0.04, 0.10), rng.range(18.0, 36.0) * frame);
            s.open_shot.veiling_glare = Some(Glare { fraction: f, sigma_px: sigma });
            json!({"fraction": f, "sigma_px": sigma})
        }
        Some("misregistration") => {
            let m = Similarity { dx: signed(rng, 0.3, 2.0), dy: signed(rng, 0.3, 2.0), rotation_deg: signed(rng, 0.25, 0.6), scale: signed(rng, 0.002, 0.005) };
            s.view.moved = Some(m);
            json!({"dx": m.dx, "dy": m.dy, "rotation_deg": m.rotation_deg, "scale": m.scale})
        }
        Some("target_tilt") => {
            let focal_px = 0.5 * spec.width as f64 / 25f64.to_radians().tan();
            let t = Tilt { theta_deg: signed(rng, 1.5, 3.0), axis_deg: rng.range(0.0, 180.0), focal_px };
            s.view.tilt = Some(t);
            let [g, h] = t.perspective();
            json!({"theta_deg": t.theta_deg, "axis_deg": t.axis_deg, "focal_px": focal_px, "g": g, "h": h})
        }
        Some("saturation") => {
            let e = rng.range(1.6, 2.2);
            s.open_shot.exposure = e;
            json!({"open_exposure": e})
        }
        Some("pinhole_diffraction") => {
            // a real stop: f/11–f/22 through the same lens (its residual aberrations included);
            // the reference averages 16 frames, as the rig's pinhole captures do
            let n = rng.range(11.0, 22.0);
            let (lw, ww) = lens.bands.iter().flat_map(|b| b.wavelengths.iter()).fold((0.0, 0.0), |(a, b), (l, w)| (a + l * w, b + w));
            let lam = lw / ww / 1000.0;
            let airy = 1.22 * lam * n / lens.pixel_pitch_um;
            // the Airy pattern's tails fall off as r⁻³ and carry energy far out (2/(π·v) beyond
            // v = 3.83·ρ/r_Airy): the reference's PSF is rendered out to 10 Airy radii (< 2 %
            // of its energy beyond), not on the wide-open kernel's support, which cuts the
            // tails and flattens the transfer function's low-frequency fall
            let pin_k = (2 * (10.0 * airy).ceil() as usize + 1).max(k);
            s.pin_shot = Shot::lens(n, 0.7, spec.grid.0, spec.grid.1, pin_k);
            s.pinhole_frames = 16;
            s.pin_sensor.full_well_e *= s.pinhole_frames as f64;
            s.pin_sensor.read_noise_e *= (s.pinhole_frames as f64).sqrt();
            // the truth as a fit states it: the first channel's radius (red in an RGB case) at
            // the wavelength the fit states it at, and the f-number per µm of pitch (which the
            // reference's colour spectra are read for too, `diffraction::spectral_stop`)
            let lam0 = lens.bands.first().map_or(0.55, |b| crate::diagnose::diffraction::channel_wavelength_um(&b.name));
            let airy0 = 1.22 * lam0 * n / lens.pixel_pitch_um;
            json!({"f_number": n, "airy_radius_px": airy0, "f_number_per_um_pitch": n / lens.pixel_pitch_um, "spectral_f_number_per_um_pitch": n / lens.pixel_pitch_um})
        }
        Some("psf_field_variation") => match &s.open_shot.blur {
            // a real design's own field (`CaseSpec::truth_psfs`) stays the truth: the bench
            // diagnoses it against a profile on a coarser grid (`bench::FIELD_CASE_GRID`)
            Blur::Grid(g) => json!({"true_grid": [g.columns, g.rows]}),
            _ => {
                s.open_shot.blur = Blur::Lens { f_number: spec.f_number, columns: 9, rows: 7, kernel_size: k };
                json!({"true_grid": [9, 7]})
            }
        },
        Some(other) => return Err(UnknownEffect(other.to_string())),
    })
}

/// Per channel, the true noise floor of a perfect prediction on the stored axis (module doc,
/// "Truth noise floor").
fn true_variance(open: &Rendered, pinhole: &Rendered, sc: &[Plane], s: &Setup, (w, h): (usize, usize)) -> Vec<Plane> {
    let grid = open.psfs.clone().expect("the wide-open shot is blurred");
    let ratio = s.open_shot.exposure / s.pin_shot.exposure;
    (0..open.variance.len())
        .map(|c| {
            // the reference's noise through the wide-open kernel, `ΣK²`; with a blurred
            // reference, the error of the best prediction from it instead (see
            // [`wiener_error_gain`])
            let e: Vec<f32> = match &pinhole.psfs {
                Some(pg) => {
                    let nv = pinhole.variance[c].mean();
                    let scene = sc[c.min(sc.len() - 1)].map(|v| v * s.pin_shot.exposure as f32);
                    let psd = RadialPsd::of(&scene);
                    grid.kernels[c].iter().zip(&pg.kernels[c]).map(|(kk, dk)| wiener_error_gain(kk, dk, &psd, nv) as f32).collect()
                }
                None => grid.kernels[c].iter().map(|kk| kk.data.iter().map(|v| v * v).sum()).collect(),
            };
            let pin_local = crate::optics::forward::blur_channel(&pinhole.variance[c], &grid, c);
            let kq_plane = grid.blend_scalars(&e, w, h);
            Plane::from_fn(w, h, |x, y| {
                let kq = kq_plane.get(x, y);
                let v = open.variance[c].get(x, y) + (ratio * ratio) as f32 * kq * pin_local.get(x, y);
                match s.sensor.transfer {
                    Transfer::Linear => v,
                    Transfer::Srgb => {
                        let d = srgb_slope(open.clean[c].get(x, y).max(1e-4));
                        v * d * d
                    }
                }
            })
        })
        .collect()
}

/// Mean modulation of a set of kernels along a pixel row at `f` cycles per pixel:
/// `mean_t |Σ K_t(x, y)·e^{−2πi·f·x}| / ΣK_t`.
pub fn kernel_modulation(kernels: &[Plane], f: f64) -> f64 {
    kernels
        .iter()
        .map(|k| {
            let (mut re, mut im) = (0.0f64, 0.0f64);
            for y in 0..k.height {
                for x in 0..k.width {
                    let a = -2.0 * std::f64::consts::PI * f * x as f64;
                    let v = k.get(x, y) as f64;
                    re += v * a.cos();
                    im += v * a.sin();
                }
            }
            re.hypot(im) / k.sum().max(1e-30)
        })
        .sum::<f64>()
        / kernels.len().max(1) as f64
}

/// MTF50 of a set of kernels along a pixel row: the frequency (cycles per pixel) at which
/// their mean modulation ([`kernel_modulation`]) falls to one half (bisection; 0.5 when still
/// above one half at Nyquist).
pub fn kernel_mtf50(kernels: &[Plane]) -> f64 {
    super::diffraction::half_modulation(|f| kernel_modulation(kernels, f))
}

/// The error gain of the best linear prediction of `K * S` from a reference `D * S + n`
/// (white noise `n` of variance `σ²`, `S` with power spectrum `P_S`): per frequency the
/// Wiener estimation error of `S` is `P_S·σ² / (|D̂|²·P_S + σ²)`, so the prediction's error
/// variance is `σ²` times
///
/// `mean_f |K̂(f)|²·P_S(f) / (|D̂(f)|²·P_S(f) + σ²)`.
///
/// This is the true noise floor's pinhole term when the reference is blurred
/// (`pinhole_diffraction`): beyond the reference's pass band no method can recover the detail
/// the wide-open capture holds, and that loss counts like noise. For a sharp reference
/// (`D̂ = 1`, `P_S ≫ σ²`) it is `ΣK²`, the plain propagated noise.
pub fn wiener_error_gain(k: &Plane, d: &Plane, psd: &RadialPsd, noise_var: f64) -> f64 {
    let side = k.width.max(k.height).max(d.width).max(d.height);
    let n = crate::solve::fft::good_size((4 * side).max(64));
    let fft = crate::solve::fft::Fft2::plan(n, n);
    let place = |p: &Plane| {
        let mut buf = vec![0.0f32; n * n];
        for y in 0..p.height {
            for x in 0..p.width {
                buf[y * n + x] = p.get(x, y);
            }
        }
        fft.forward(&buf)
    };
    let (ks, ds) = (place(k), place(d));
    let dsum = d.sum().max(1e-30);
    let mut e = 0.0f64;
    for (i, (a, b)) in ks.iter().zip(&ds).enumerate() {
        let (fx, fy) = fft.frequency(i);
        let ps = psd.at(fx as f64, fy as f64);
        // interior columns of the half spectrum count twice
        let kx = i / n;
        let mult = if kx == 0 || (n % 2 == 0 && kx == n / 2) { 1.0 } else { 2.0 };
        let dd = b.norm_sqr() as f64 / (dsum * dsum);
        e += mult * a.norm_sqr() as f64 * ps / (dd * ps + noise_var).max(1e-300);
    }
    e / (n * n) as f64
}

/// `sqrt(Σ(stored − predicted)² / ΣVar_true)` over `mask`: the residual relative to the true
/// noise floor (1.0 = at the floor).
pub fn floor_ratio(case: &Case, predicted: &[Plane], mask: &[Vec<bool>]) -> f64 {
    let (mut sq, mut v) = (0.0f64, 0.0f64);
    for c in 0..predicted.len() {
        for i in 0..predicted[c].data.len() {
            if mask[c][i] {
                sq += ((case.open.image.planes[c].data[i] - predicted[c].data[i]) as f64).powi(2);
                v += case.true_variance[c].data[i] as f64;
            }
        }
    }
    (sq / v.max(1e-300)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A truth profile sets the case's size, grid, kernel size and PSFs and makes it RGB; a
    /// profile of another channel count is refused with its count.
    #[test]
    fn a_truth_profile_sets_the_case() {
        use crate::image::SampleFormat;
        use crate::profile::{PsfTable, SourceInfo};
        let (w, h) = (200, 150);
        let lens = LensModel::demo(w, h);
        let grid = lens.psf_grid(5.6, 4, 3, 11);
        let psf = PsfTable { kernel_size: 11, columns: 4, rows: 3, centers: grid.centers.clone(), tile_size: None, files: Default::default() };
        let channels: Vec<String> = grid.channels.clone();
        let source = SourceInfo { width: w, height: h, channels, sample_format: SampleFormat::U16, transfer: Transfer::Linear, open: None, pinhole: None, black_level: vec![] };
        let truth = crate::profile::Profile { meta: crate::profile::Profile::new_meta(source, vec![1.0; grid.channels.len()], psf), grid: grid.clone() };
        assert_eq!(grid.channels.len(), 3, "the demo lens is RGB");
        let spec = CaseSpec { f_number: 4.0, ..CaseSpec::default() }.through_truth(&truth).expect("an RGB profile");
        assert_eq!((spec.width, spec.height, spec.channels, spec.kernel_size, spec.grid, spec.f_number), (w, h, 3, 11, (4, 3), 4.0));
        assert_eq!(spec.truth_psfs.as_ref().map(|g| g.kernels.clone()), Some(grid.kernels.clone()));
        let mut mono = truth.clone();
        mono.grid.channels.truncate(1);
        mono.grid.kernels.truncate(1);
        assert_eq!(CaseSpec::default().through_truth(&mono).err(), Some(1));
    }

    /// The Wiener error gain: a sharp reference (`D = δ`) with a strong signal gives the plain
    /// `ΣK²`; a blurred reference gives more (the inverse of `D` amplifies its noise), and the
    /// error variance `σ²·gain` grows with the noise.
    /// A sampled Gaussian of standard deviation σ has the modulation `exp(−2π²σ²f²)`, one half
    /// at `f = √(ln 2 / 2) / (π·σ)`.
    #[test]
    fn kernel_mtf50_of_a_gaussian() {
        let sigma = 1.5f64;
        let k = Plane::from_fn(21, 21, |x, y| (-((x as f64 - 10.0).powi(2) + (y as f64 - 10.0).powi(2)) / (2.0 * sigma * sigma)).exp() as f32);
        let want = (std::f64::consts::LN_2 / 2.0).sqrt() / (std::f64::consts::PI * sigma);
        let got = kernel_mtf50(&[k.clone(), k]);
        assert!((got / want - 1.0).abs() < 1e-3, "{got} vs {want}");
        let mut delta = Plane::new(5, 5);
        delta.set(2, 2, 1.0);
        assert_eq!(kernel_mtf50(&[delta]), 0.5);
    }

    /// The field case keeps a real design's own grid (`CaseSpec::truth_psfs`) as its truth
    /// (the bench diagnoses it against a coarser profile); on the simulator's lens it renders
    /// the 9 × 7 grid.
    #[test]
    fn the_field_case_keeps_a_given_truth_grid() {
        let spec = CaseSpec { width: 128, height: 96, kernel_size: 9, ..CaseSpec::default() };
        let sim = render_case(Some("psf_field_variation"), 3, &spec).expect("renders");
        assert_eq!(sim.truth["true_grid"], serde_json::json!([9, 7]));
        let given = render_case(None, 3, &spec).expect("renders").open.psfs.expect("the wide-open PSFs");
        assert_eq!((given.columns, given.rows), spec.grid);
        let real = CaseSpec { truth_psfs: Some(given.clone()), ..spec };
        let case = render_case(Some("psf_field_variation"), 3, &real).expect("renders");
        assert_eq!(case.truth["true_grid"], serde_json::json!([given.columns, given.rows]));
        let rendered = case.open.psfs.expect("the wide-open PSFs");
        assert_eq!((rendered.columns, rendered.rows), (given.columns, given.rows));
    }

    #[test]
    fn wiener_error_gain_is_the_propagated_noise_plus_the_lost_detail() {
        let mut rng = Rng::new(5);
        let white = Plane::from_fn(128, 128, |_, _| rng.normal() as f32);
        let psd = RadialPsd::of(&white);
        assert!((psd.at(0.1, 0.2) - 1.0).abs() < 0.15 && (psd.at(0.45, 0.0) - 1.0).abs() < 0.15, "white PSD {} {}", psd.at(0.1, 0.2), psd.at(0.45, 0.0));
        let k = crate::image::filter::gaussian_blur(&Plane::from_fn(15, 15, |x, y| ((x, y) == (7, 7)) as u8 as f32), 1.5);
        let sum_k2: f64 = k.data.iter().map(|&v| (v as f64).powi(2)).sum();
        let delta = Plane::from_fn(15, 15, |x, y| ((x, y) == (7, 7)) as u8 as f32);
        let sharp = wiener_error_gain(&k, &delta, &psd, 1e-4);
        assert!((sharp / sum_k2 - 1.0).abs() < 0.02, "sharp reference: {sharp:.4e} vs ΣK² {sum_k2:.4e}");
        let d = crate::image::filter::gaussian_blur(&delta, 1.2);
        let (low, high) = (wiener_error_gain(&k, &d, &psd, 1e-4), wiener_error_gain(&k, &d, &psd, 1e-2));
        assert!(low > 1.5 * sharp && high * 1e-2 > 10.0 * low * 1e-4, "blurred reference: {low:.3e} (σ² 1e-4), {high:.3e} (1e-2) vs sharp {sharp:.3e}");
    }

    /// The softened pattern is band-limited before sampling: a rotated view equals (to well under
    /// the noise) a resampling of the unrotated one, which the sharp pattern blurred after
    /// sampling does not achieve.
    #[test]
    fn softened_scene_moves_reproducibly() {
        let (w, h) = (64, 48);
        let m = Similarity { rotation_deg: 0.5, ..Default::default() };
        let th = 0.5f64.to_radians();
        let a = scene_moved_soft(w, h, 3, None, 1.6, 1.0);
        let b = scene_moved_soft(w, h, 3, Some(m), 1.6, 1.0);
        let err = |p: &Plane, q: &Plane| {
            let shifted = crate::diagnose::model::resample(p, [th.cos(), -th.sin(), th.sin(), th.cos()]).0;
            let (mut s, mut n) = (0.0f64, 0);
            for y in 8..h - 8 {
                for x in 8..w - 8 {
                    s += ((shifted.get(x, y) - q.get(x, y)) as f64).powi(2);
                    n += 1;
                }
            }
            (s / n as f64).sqrt()
        };
        let soft = err(&a, &b);
        let blur = |p: Plane| crate::image::filter::gaussian_blur(&p, 1.0);
        let after = err(&blur(scene_moved(w, h, 3, None, 1.6)), &blur(scene_moved(w, h, 3, Some(m), 1.6)));
        assert!(soft < 1e-3 && after > 10.0 * soft, "softened before sampling: RMS {soft:.2e}; blurred after sampling: {after:.2e}");
        // the blur conserves the mean reflectance
        assert!((a.mean() - scene_moved(w, h, 3, None, 1.6).mean()).abs() < 5e-3);
    }

    /// `tone_curve` conceals an sRGB camera: both captures are encoded (the catalogue's model,
    /// [`super::super::model`] step 1), not only the wide-open one.
    #[test]
    fn tone_curve_case_encodes_both_captures() {
        let spec = CaseSpec { width: 96, height: 64, ..Default::default() };
        let c = render_case(Some("tone_curve"), 5, &spec).expect("renders");
        for (name, r) in [("wide-open", &c.open), ("pinhole", &c.pinhole)] {
            let stored = r.image.planes[0].mean();
            let encoded = r.clean[0].map(|v| Transfer::Srgb.encode(v.clamp(0.0, 1.0))).mean();
            let linear = r.clean[0].mean();
            assert!((stored - encoded).abs() < 0.01 && (stored - linear).abs() > 0.05, "{name}: stored mean {stored:.4}, sRGB-encoded {encoded:.4}, linear {linear:.4}");
        }
        let clean = render_case(None, 5, &spec).expect("renders");
        let (stored, linear) = (clean.pinhole.image.planes[0].mean(), clean.pinhole.clean[0].mean());
        assert!((stored - linear).abs() < 0.01, "clean pinhole: stored {stored:.4} vs linear {linear:.4}");
    }

    /// The rendered tilt is the model's `target_tilt` homography (`ψ(d) = d / (1 + g·d)`,
    /// [`super::super::model::reference_map`]) to first order: mapping a corner through the
    /// model and back through the renderer's exact map returns it within the `1/cos θ`
    /// stretch the model leaves out, while the keystone itself moves it by pixels.
    #[test]
    fn tilt_is_the_models_homography_to_first_order() {
        use crate::diagnose::model::{reference_map, Corrections, TiltCorrection};
        let t = Tilt { theta_deg: 3.0, axis_deg: 30.0, focal_px: 274.5 };
        let [g, h] = t.perspective();
        let map = reference_map(&Corrections { target_tilt: Some(TiltCorrection { g, h }), ..Default::default() }).expect("a map");
        let stretch = (1.0 / 3f64.to_radians().cos() - 1.0) * 160.0;
        for d in [(127.5, 95.5), (-127.5, 95.5), (60.0, -80.0)] {
            let den = 1.0 + map.perspective[0] * d.0 + map.perspective[1] * d.1;
            let psi = (d.0 / den, d.1 / den);
            let back = t.map(psi);
            let err = (back.0 - d.0).hypot(back.1 - d.1);
            let keystone = (psi.0 - d.0).hypot(psi.1 - d.1);
            assert!(err <= stretch + 0.02, "{d:?}: round trip off by {err:.3} px (stretch {stretch:.3})");
            if d.0.abs() > 100.0 {
                assert!(keystone > 1.5, "{d:?}: keystone {keystone:.2} px");
            }
        }
    }
}
