//! The corrected forward model: the physics `diagnose` can add to a profile, stored in
//! `profile.toml`'s `[corrections]` table and applied by [`apply_corrections`].
//!
//! # The model, in the order it is applied to a sharp (pinhole) image `P`
//! 1. `tone_curve` — both captures are encoded: `L_p = T⁻¹(P)` (`transfer = "srgb"`), and the
//!    prediction is encoded back at the end. Without it the profile's source transfer is used.
//!    Then `pinhole_diffraction` — the reference is restored by the Wiener filter of its own
//!    PSF at the stop (`airy_radius_px`, `epsilon` and `bandwidth` per channel,
//!    `aberration_sigma_px`; [`super::diffraction`]).
//! 2. `misregistration` — the reference is resampled onto the wide-open geometry with the fitted
//!    similarity (`matrix`, `translation`; the convention of [`crate::profile::RegistrationInfo`]).
//!    `target_tilt` — the target tilted between the captures: a homography whose perspective
//!    row `(g, h)` (per pixel) maps wide-open pixel `p` to the reference pixel
//!    `ψ(p) = c + L·d / (1 + g·dx + h·dy)`, `d = p − c`, `c` the image centre and `L` the
//!    similarity's linear part under `misregistration` (else `I`). For a plane tilted by `θ`
//!    about an in-plane axis through the optical axis, `(g, h) = (tan θ / f)·n` with `f` the
//!    focal length in pixels and `n` the unit normal of the axis in the image; the displacement
//!    `p − ψ(p) ≈ d·(g·dx + h·dy)` grows with the square of the distance from the centre (a
//!    keystone), which no similarity and no tile-wise kernel follows. See [`reference_map`].
//! 3. **blur** — `A = Σ_t w_t·(K_t * L_p)`, the profile's kernels (sum 1), hat-interpolated.
//!    `psf_field_variation` records the grid (`columns`, `rows`) the kernels were refitted on,
//!    its outer centres on the frame's edges (`PsfGrid::edge_centers`: the blend holds no kernel
//!    constant inside the frame); the kernels themselves are the profile's `[psf]`.
//! 4. `veiling_glare` — `B = (1 − f)·A + f·(G_σ * L_p)` (`fraction f`, `sigma_px σ`, a
//!    Gaussian, energy conserving like the simulator's).
//! 5. **exposure and gain** — `s·V(r)·D(x̂, ŷ)·B` with `s` the profile's exposure ratio,
//!    `vignetting` `V = 1 + k1 r² + k2 r⁴ + k3 r⁶` (`r = 1` at half the diagonal) and
//!    `illumination_gradient` `D = 1 + gx·x̂ + gy·ŷ` (`x̂, ŷ ∈ [−1, 1]` across the image):
//!    the gain of the wide-open capture *relative to* the reference.
//! 6. `black_level` — `+ β_c` per channel (linear full scale): the offset of the wide-open
//!    capture relative to `s` times the reference's.
//! 7. encode (step 1), then `saturation` — `min(value, clip_level)` on the stored axis.
//!
//! Every correction is optional; an empty table is the base model of docs/method.md §6.

use crate::estimate::register;
use crate::image::resample::{warp_projective_with_variance, warp_with_variance, Affine, Interpolation, Projective};
use crate::image::{Image, Plane, Transfer};
use crate::image::filter::gaussian_blur_wide;
use crate::optics::forward::blur_channel;
use crate::profile::{Profile, RegistrationInfo};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Veiling glare parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GlareCorrection {
    pub fraction: f64,
    pub sigma_px: f64,
}

/// Tone curve: the transfer function both captures were encoded with.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToneCorrection {
    pub transfer: Transfer,
}

/// Clipping level on the stored axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SaturationCorrection {
    pub clip_level: f32,
}

/// The grid the kernels were refitted on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldCorrection {
    pub columns: usize,
    pub rows: usize,
}

/// Vignetting ratio coefficients.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VignettingCorrection {
    pub k1: f64,
    pub k2: f64,
    pub k3: f64,
}

/// Planar gain.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GradientCorrection {
    pub gx: f64,
    pub gy: f64,
}

/// The reference's own diffraction PSF ([`super::diffraction`]), per channel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffractionCorrection {
    /// Radius of the Airy pattern's first dark ring at the band's centre wavelength,
    /// `1.22·λ·N / pitch`, pixels.
    pub airy_radius_px: Vec<f64>,
    /// Wiener noise-to-signal ratio of the restoration.
    pub epsilon: Vec<f64>,
    /// Standard deviation (px) of the Gaussian blur of the lens's residual aberrations at the
    /// stop, on top of diffraction (0: diffraction alone).
    #[serde(default)]
    pub aberration_sigma_px: f64,
    /// Relative half-width of each channel's band of wavelengths
    /// ([`super::diffraction::channel_bandwidth`]; empty: one wavelength).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub bandwidth: Vec<f64>,
    /// Each channel's band-centre wavelength, µm, at which `airy_radius_px` is stated
    /// ([`super::diffraction::channel_wavelength_um`]; empty: 0.55 µm).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub wavelength_um: Vec<f64>,
    /// The stop read from the reference's colour spectra alone
    /// ([`super::diffraction::spectral_stop`]), which the kernels cannot bias: where it is
    /// given, `airy_radius_px` follows it (only `aberration_sigma_px` is fitted). `None` where
    /// the channels do not determine it (a monochrome reference: the radius is fitted).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spectral_stop: Option<super::diffraction::SpectralStop>,
}

impl DiffractionCorrection {
    /// The f-number per micrometre of pixel pitch that the radii mean, `N / p = r / (1.22·λ)`
    /// (one value: the channels' radii scale with their wavelengths), from the first channel at
    /// its own wavelength.
    pub fn f_number_per_um_pitch(&self) -> Option<f64> {
        let r = self.airy_radius_px.first()?;
        Some(r / (1.22 * Self::pick(&self.wavelength_um, 0, 0.55)))
    }
    fn pick(v: &[f64], c: usize, default: f64) -> f64 {
        v.get(c).or(v.first()).copied().unwrap_or(default)
    }
    /// Restores channel `c` of a linear reference.
    pub fn restore(&self, c: usize, p: &Plane) -> Plane {
        let (psf, e) = self.channel(c);
        super::diffraction::restore(p, &psf, e)
    }
    /// The PSF and the Wiener `ε` of channel `c`.
    pub fn channel(&self, c: usize) -> (super::diffraction::ReferencePsf, f64) {
        let psf = super::diffraction::ReferencePsf { radius_px: Self::pick(&self.airy_radius_px, c, 1.0), aberration_px: self.aberration_sigma_px, bandwidth: Self::pick(&self.bandwidth, c, 0.0) };
        (psf, Self::pick(&self.epsilon, c, 1e-2))
    }
}

/// The perspective row of the homography between the captures (`target_tilt`, module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TiltCorrection {
    /// Per pixel, across x.
    pub g: f64,
    /// Per pixel, across y.
    pub h: f64,
}

/// Per-channel offsets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BlackLevelCorrection {
    pub offset: Vec<f64>,
}

/// Every correction the diagnosis can fit; `None` = not part of the model.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Corrections {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tone_curve: Option<ToneCorrection>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pinhole_diffraction: Option<DiffractionCorrection>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub misregistration: Option<RegistrationInfo>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target_tilt: Option<TiltCorrection>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub psf_field_variation: Option<FieldCorrection>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub veiling_glare: Option<GlareCorrection>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vignetting: Option<VignettingCorrection>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub illumination_gradient: Option<GradientCorrection>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub black_level: Option<BlackLevelCorrection>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub saturation: Option<SaturationCorrection>,
}

/// Why corrections could not be read or applied.
#[derive(Debug, thiserror::Error)]
pub enum CorrectionError {
    #[error("[corrections] table: {0}")]
    Table(String),
    #[error("image does not fit the profile: {0}")]
    Mismatch(String),
}

impl Corrections {
    /// The `black_level` offset `β_c` of channel `c` (linear full scale; 0 without one).
    pub fn black_offset(&self, c: usize) -> f64 {
        self.black_level.as_ref().and_then(|b| b.offset.get(c).copied()).unwrap_or(0.0)
    }

    /// The names of the corrections present, in model order.
    pub fn names(&self) -> Vec<&'static str> {
        let mut v = Vec::new();
        if self.tone_curve.is_some() {
            v.push("tone_curve");
        }
        if self.pinhole_diffraction.is_some() {
            v.push("pinhole_diffraction");
        }
        if self.misregistration.is_some() {
            v.push("misregistration");
        }
        if self.target_tilt.is_some() {
            v.push("target_tilt");
        }
        if self.psf_field_variation.is_some() {
            v.push("psf_field_variation");
        }
        if self.veiling_glare.is_some() {
            v.push("veiling_glare");
        }
        if self.vignetting.is_some() {
            v.push("vignetting");
        }
        if self.illumination_gradient.is_some() {
            v.push("illumination_gradient");
        }
        if self.black_level.is_some() {
            v.push("black_level");
        }
        if self.saturation.is_some() {
            v.push("saturation");
        }
        v
    }

    /// The `[corrections]` table of `profile.toml`.
    ///
    /// # Errors
    /// When a value cannot be represented in TOML (not expected for finite numbers).
    pub fn to_table(&self) -> Result<BTreeMap<String, toml::Value>, CorrectionError> {
        let v = toml::Value::try_from(self).map_err(|e| CorrectionError::Table(e.to_string()))?;
        match v {
            toml::Value::Table(t) => Ok(t.into_iter().collect()),
            _ => Err(CorrectionError::Table("corrections did not serialise to a table".into())),
        }
    }

    /// Reads the `[corrections]` table (unknown effect names are an error).
    ///
    /// # Errors
    /// Unknown names or malformed parameters.
    pub fn from_table(t: &BTreeMap<String, toml::Value>) -> Result<Corrections, CorrectionError> {
        let table: toml::Table = t.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        toml::Value::Table(table).try_into().map_err(|e: toml::de::Error| CorrectionError::Table(e.message().to_string()))
    }

    /// Gain `V(r)·D(x̂, ŷ)` at pixel `(x, y)` of a `w × h` image.
    pub fn gain(&self, x: usize, y: usize, w: usize, h: usize) -> f64 {
        let cx = (w as f64 - 1.0) / 2.0;
        let cy = (h as f64 - 1.0) / 2.0;
        let (dx, dy) = (x as f64 - cx, y as f64 - cy);
        let r2 = (dx * dx + dy * dy) / (0.25 * ((w * w + h * h) as f64));
        let mut g = 1.0;
        if let Some(v) = self.vignetting {
            g *= 1.0 + v.k1 * r2 + v.k2 * r2 * r2 + v.k3 * r2 * r2 * r2;
        }
        if let Some(d) = self.illumination_gradient {
            g *= 1.0 + d.gx * dx / cx.max(0.5) + d.gy * dy / cy.max(0.5);
        }
        g
    }
}

/// The transfer a model uses for both captures.
pub fn model_transfer(c: &Corrections, declared: Transfer) -> Transfer {
    c.tone_curve.map_or(declared, |t| t.transfer)
}

/// Linear reference planes as the model sees them: decoded, then shifted by the registration's
/// integer translation (the kernels carry the fraction; a similarity's rotation and scale are
/// applied to the band-limited side instead, see [`misregistration_map`]).
pub fn reference_planes(pinhole: &Image, transfer: Transfer, registration: &RegistrationInfo) -> Vec<Plane> {
    let shift = RegistrationInfo { model: "translation".into(), ..registration.clone() };
    pinhole.planes.iter().map(|p| register::apply(&p.map(|v| transfer.decode(v)), &shift)).collect()
}

/// The linear part of a similarity registration as a map `ψ(p) = (2I − A)(p − c) + c` from
/// wide-open pixels to reference pixels: `open(p) ≈ (K * reference)(ψ(p))`.
///
/// The sharp reference is *not* resampled: a printed noise target is aliased at the sensor, and
/// no interpolation of aliased samples reproduces a sub-pixel move (a half-pixel Lanczos shift of
/// a 4-px-cell target errs by 0.07 RMS on a 0.4 signal). The lens has band-limited the
/// wide-open capture, so the model resamples that side: the data onto the reference geometry
/// for fitting, the prediction back onto the wide-open geometry for output.
pub fn misregistration_map(info: &RegistrationInfo) -> [f64; 4] {
    let (a, b) = (info.matrix[0], info.matrix[2]);
    [2.0 - a, b, -b, 2.0 - a]
}

/// The map `ψ` from wide-open pixels to reference pixels under `misregistration` (its linear
/// part, [`misregistration_map`]) and `target_tilt` (module docs, step 2); `None` when the
/// model has neither. The fit resamples the wide-open data through its inverse onto the
/// reference geometry and the prediction back through it.
pub fn reference_map(c: &Corrections) -> Option<Projective> {
    if c.misregistration.is_none() && c.target_tilt.is_none() {
        return None;
    }
    let matrix = c.misregistration.as_ref().map_or([1.0, 0.0, 0.0, 1.0], misregistration_map);
    let perspective = c.target_tilt.map_or([0.0, 0.0], |t| [t.g, t.h]);
    Some(Projective { matrix, shift: [0.0, 0.0], perspective })
}

/// Resamples `p` at `map(q)` for every pixel `q` (Lanczos-4, mirror boundaries); also returns
/// `Σw²` of the interpolation weights (see [`resample`]).
pub fn resample_map(p: &Plane, map: &Projective) -> (Plane, Plane) {
    warp_projective_with_variance(p, map, Interpolation::Lanczos4)
}

/// [`resample_map`] at the pixels where `need` is true (every pixel with `None`), 0 elsewhere.
pub fn resample_map_where(p: &Plane, map: &Projective, need: Option<&[bool]>) -> (Plane, Plane) {
    crate::image::resample::warp_projective_where(p, map, Interpolation::Lanczos4, need)
}

/// Resamples `p` at `M·(q − c) + c` for every pixel `q` (Lanczos-4, mirror boundaries); also
/// returns, per pixel, `Σw²` of the interpolation weights (the factor on white noise's variance).
pub fn resample(p: &Plane, m: [f64; 4]) -> (Plane, Plane) {
    warp_with_variance(p, &Affine { matrix: m, shift: [0.0, 0.0] }, Interpolation::Lanczos4)
}

/// The inverse of a 2×2 matrix (row-major); identity when singular.
pub fn invert2(m: [f64; 4]) -> [f64; 4] {
    let det = m[0] * m[3] - m[1] * m[2];
    if det.abs() < 1e-12 {
        return [1.0, 0.0, 0.0, 1.0];
    }
    [m[3] / det, -m[1] / det, -m[2] / det, m[0] / det]
}

/// The linear prediction (steps 3–6 of the module docs) from registered linear reference
/// planes, with per-channel exposure ratios.
pub fn predict_linear(c: &Corrections, profile_grid: &crate::optics::psf_grid::PsfGrid, exposure: &[f64], reference: &[Plane]) -> Vec<Plane> {
    reference
        .iter()
        .enumerate()
        .map(|(ch, p)| {
            let (w, h) = (p.width, p.height);
            let mut a = blur_channel(p, profile_grid, ch);
            if let Some(g) = c.veiling_glare {
                let wide = gaussian_blur_wide(p, g.sigma_px);
                for (v, b) in a.data.iter_mut().zip(&wide.data) {
                    *v = (1.0 - g.fraction as f32) * *v + g.fraction as f32 * b;
                }
            }
            let s = exposure.get(ch).copied().unwrap_or(1.0);
            let off = c.black_offset(ch);
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    a.data[i] = (a.data[i] as f64 * s * c.gain(x, y, w, h) + off) as f32;
                }
            }
            a
        })
        .collect()
}

/// Encodes a linear prediction for storage (step 7).
pub fn encode_prediction(c: &Corrections, transfer: Transfer, linear: &[Plane]) -> Vec<Plane> {
    let clip = c.saturation.map(|s| s.clip_level);
    linear
        .iter()
        .map(|p| {
            p.map(|v| {
                let e = transfer.encode(v);
                clip.map_or(e, |l| e.min(l))
            })
        })
        .collect()
}

/// The wide-open image a profile predicts from a sharp (pinhole) image with the profile's
/// `[corrections]` applied (module docs), in the profile's source encoding (or the tone
/// curve's), same size and sample format. Without corrections this equals the base
/// prediction of `lensrig simulate` (which subtracts and restores the source black level).
///
/// # Errors
/// A malformed `[corrections]` table, or an image whose size or channel count differs from
/// the profile's source.
pub fn apply_corrections(profile: &Profile, sharp: &Image) -> Result<Image, CorrectionError> {
    let src = &profile.meta.source;
    if sharp.width() != src.width || sharp.height() != src.height {
        return Err(CorrectionError::Mismatch(format!("image is {}x{}, profile source {}x{}", sharp.width(), sharp.height(), src.width, src.height)));
    }
    if sharp.channel_count() != profile.grid.channels.len() {
        return Err(CorrectionError::Mismatch(format!("image has {} channel(s), the profile {}", sharp.channel_count(), profile.grid.channels.len())));
    }
    let c = Corrections::from_table(&profile.meta.corrections)?;
    let transfer = model_transfer(&c, src.transfer);
    let black = &src.black_level;
    let bl = |ch: usize| black.get(ch).or(black.first()).copied().unwrap_or(0.0);
    let reference: Vec<Plane> = sharp
        .planes
        .iter()
        .enumerate()
        .map(|(ch, p)| {
            let mut lin = p.map(|v| transfer.decode(v) - bl(ch));
            if let Some(d) = &c.pinhole_diffraction {
                lin = d.restore(ch, &lin);
            }
            match &c.misregistration {
                Some(info) => register::apply(&lin, &RegistrationInfo { model: "translation".into(), ..info.clone() }),
                None => lin,
            }
        })
        .collect();
    let mut linear = predict_linear(&c, &profile.grid, &profile.meta.exposure_ratio, &reference);
    if let Some(m) = reference_map(&c) {
        linear = linear.iter().map(|p| resample_map(p, &m).0).collect();
    }
    for (ch, p) in linear.iter_mut().enumerate() {
        let b = bl(ch);
        p.data.iter_mut().for_each(|v| *v += b);
    }
    let mut img = Image::new(encode_prediction(&c, transfer, &linear));
    img.channels = profile.grid.channels.clone();
    img.transfer = transfer;
    img.format = src.sample_format;
    Ok(img)
}

#[cfg(test)]
mod tests {
    use super::*;
    /// The f-number a fit's radii mean is read at the first channel's own wavelength: an RGB
    /// fit (red first, at 0.61 µm) and a mono one (0.55 µm) of the same stop give the same
    /// `N / p` (reading red's radius at 0.55 µm would give 11 % more).
    #[test]
    fn f_number_per_pitch_reads_each_radius_at_its_own_wavelength() {
        let n_per_p = 4.0;
        let rgb = DiffractionCorrection { airy_radius_px: [0.61, 0.55, 0.465].iter().map(|l| 1.22 * l * n_per_p).collect(), epsilon: vec![1e-4; 3], aberration_sigma_px: 0.0, bandwidth: vec![], wavelength_um: vec![0.61, 0.55, 0.465], spectral_stop: None };
        let mono = DiffractionCorrection { airy_radius_px: vec![1.22 * 0.55 * n_per_p], epsilon: vec![1e-4], aberration_sigma_px: 0.0, bandwidth: vec![], wavelength_um: vec![], spectral_stop: None };
        for d in [rgb, mono] {
            assert!((d.f_number_per_um_pitch().unwrap() - n_per_p).abs() < 1e-12, "{d:?}");
        }
    }

    #[test]
    fn table_round_trip_and_unknown_names() {
        let c = Corrections {
            vignetting: Some(VignettingCorrection { k1: -0.2, k2: 0.01, k3: 0.0 }),
            black_level: Some(BlackLevelCorrection { offset: vec![0.01, 0.02] }),
            tone_curve: Some(ToneCorrection { transfer: Transfer::Srgb }),
            ..Default::default()
        };
        let t = c.to_table().unwrap();
        assert!(t.contains_key("vignetting") && t.contains_key("black_level") && t.contains_key("tone_curve"));
        assert_eq!(Corrections::from_table(&t).unwrap(), c);
        let mut bad = t.clone();
        bad.insert("lens_flare".into(), toml::Value::Integer(1));
        assert!(Corrections::from_table(&bad).is_err());
        assert_eq!(c.names(), vec!["tone_curve", "vignetting", "black_level"]);
    }

    #[test]
    fn gain_matches_the_simulator() {
        let c = Corrections {
            vignetting: Some(VignettingCorrection { k1: -0.3, k2: 0.05, k3: 0.01 }),
            illumination_gradient: Some(GradientCorrection { gx: 0.1, gy: -0.05 }),
            ..Default::default()
        };
        let (w, h) = (40, 30);
        let mut p = Plane::filled(w, h, 1.0);
        crate::optics::capture::apply_gain(&mut p, |xn, yn, _| 1.0 + 0.1 * xn - 0.05 * yn);
        crate::optics::capture::apply_gain(&mut p, |_, _, r2| 1.0 - 0.3 * r2 + 0.05 * r2 * r2 + 0.01 * r2 * r2 * r2);
        for (x, y) in [(0, 0), (39, 29), (20, 3), (7, 21)] {
            assert!((p.get(x, y) as f64 - c.gain(x, y, w, h)).abs() < 1e-5);
        }
    }
}
