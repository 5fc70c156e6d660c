//! A profile set: calibrations of one lens at several focus distances and apertures, collected
//! in one directory with an index keyed like lensfun's calibration entries.
//!
//! # `index.toml`
//! ```toml
//! format = "lensrig-profile-set"
//! version = 1
//! [[calibration]]
//! focal = 16.0        # focal length, mm
//! aperture = 5.6      # f-number
//! distance = 1.0      # focus distance, metres
//! profile = "d1.0"    # profile directory, relative to the index
//! ```
//!
//! # Choosing a calibration ([`ProfileSet::resolve`])
//! The aperture nearest in stops (`|log2 N − log2 N'|`) is taken first. Among its calibrations,
//! a distance between two of them is **interpolated**: the kernels are blended linearly with the
//! weight linear in `1/distance` (defocus is linear in `1/distance` for a thin lens; lensfun
//! interpolates vignetting the same way). Outside their range, or when the two profiles'
//! grids differ, the **nearest** one is used. [`Resolved::description`] says which.

use super::{Profile, ProfileError};
use crate::fsutil::{write_atomic, Overwrite};
use crate::image::Plane;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The index file name inside a set directory.
pub const INDEX: &str = "index.toml";

/// One calibration of the set.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// Focal length, mm.
    pub focal: f64,
    /// f-number.
    pub aperture: f64,
    /// Focus distance, metres.
    pub distance: f64,
    /// Profile directory relative to the index.
    pub profile: String,
}

/// `index.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProfileSet {
    pub format: String,
    pub version: u32,
    #[serde(default)]
    pub calibration: Vec<Calibration>,
}

/// The profile chosen for a request, and how.
#[derive(Clone, Debug)]
pub struct Resolved {
    pub profile: Profile,
    pub description: String,
}

fn invalid(path: &Path, message: impl Into<String>) -> ProfileError {
    ProfileError::Invalid { path: path.into(), message: message.into() }
}

/// Whether `dir` is a profile set (holds an `index.toml`).
pub fn is_set(dir: &Path) -> bool {
    dir.join(INDEX).is_file()
}

impl ProfileSet {
    pub fn new(calibration: Vec<Calibration>) -> Self {
        Self { format: "lensrig-profile-set".into(), version: 1, calibration }
    }

    /// Reads `dir/index.toml`.
    ///
    /// # Errors
    /// A missing or malformed index, an unknown format or version, a non-positive aperture or
    /// distance.
    pub fn load(dir: &Path) -> Result<Self, ProfileError> {
        let path = dir.join(INDEX);
        let text = std::fs::read_to_string(&path).map_err(|source| ProfileError::Io { path: path.clone(), source })?;
        let set: ProfileSet = toml::from_str(&text).map_err(|e| invalid(&path, crate::toml_error(&text, &e)))?;
        if set.format != "lensrig-profile-set" || set.version != 1 {
            return Err(invalid(&path, format!("format '{}' version {} is not a lensrig-profile-set version 1", set.format, set.version)));
        }
        if set.calibration.is_empty() {
            return Err(invalid(&path, "no [[calibration]] entries"));
        }
        for c in &set.calibration {
            if !(c.aperture > 0.0 && c.distance > 0.0 && c.focal.is_finite()) {
                return Err(invalid(&path, format!("calibration {}: aperture and distance must be > 0", c.profile)));
            }
        }
        Ok(set)
    }

    /// Writes `dir/index.toml`.
    ///
    /// # Errors
    /// I/O errors naming the file.
    pub fn save(&self, dir: &Path) -> Result<(), ProfileError> {
        let path = dir.join(INDEX);
        let text = toml::to_string_pretty(self).map_err(|e| invalid(&path, format!("cannot serialise: {e}")))?;
        write_atomic(&path, text.as_bytes(), Overwrite::Replace).map_err(|source| ProfileError::Io { path, source })
    }

    /// The calibrations to use for `(distance, aperture)`: one (nearest) or two with the blend
    /// weight `t` of the second.
    pub fn select(&self, distance: f64, aperture: f64) -> (usize, Option<(usize, f64)>) {
        let stops = |n: f64| n.max(1e-6).log2();
        let best_ap = self
            .calibration
            .iter()
            .map(|c| c.aperture)
            .min_by(|a, b| (stops(*a) - stops(aperture)).abs().total_cmp(&(stops(*b) - stops(aperture)).abs()))
            .unwrap_or(aperture);
        let mut same: Vec<usize> = (0..self.calibration.len()).filter(|&i| (stops(self.calibration[i].aperture) - stops(best_ap)).abs() < 1e-6).collect();
        let inv = |i: usize| 1.0 / self.calibration[i].distance;
        same.sort_by(|&a, &b| inv(a).total_cmp(&inv(b)));
        let q = 1.0 / distance.max(1e-9);
        let nearest = same.iter().copied().min_by(|&a, &b| (inv(a) - q).abs().total_cmp(&(inv(b) - q).abs())).unwrap_or(0);
        for w in same.windows(2) {
            let (a, b) = (w[0], w[1]);
            if inv(a) < q && q < inv(b) {
                return (a, Some((b, (q - inv(a)) / (inv(b) - inv(a)))));
            }
        }
        (nearest, None)
    }

    /// Loads the profile for `(distance, aperture)` from the set in `dir` (see the module docs).
    ///
    /// # Errors
    /// A profile of the set that does not load.
    pub fn resolve(&self, dir: &Path, distance: f64, aperture: f64) -> Result<Resolved, ProfileError> {
        let (a, second) = self.select(distance, aperture);
        let ca = &self.calibration[a];
        let pa = Profile::load(&dir.join(&ca.profile))?;
        let describe = |c: &Calibration| format!("{} (f/{}, {} m)", c.profile, c.aperture, c.distance);
        let ap_note = if (ca.aperture - aperture).abs() > 1e-9 { format!("; nearest calibrated aperture f/{} for f/{aperture}", ca.aperture) } else { String::new() };
        if let Some((b, t)) = second {
            let cb = &self.calibration[b];
            let pb = Profile::load(&dir.join(&cb.profile))?;
            if let Some(p) = blend(&pa, &pb, t) {
                return Ok(Resolved { profile: p, description: format!("interpolated {:.0} % {} + {:.0} % {} for {distance} m{ap_note}", (1.0 - t) * 100.0, describe(ca), t * 100.0, describe(cb)) });
            }
            let (n, c) = if t < 0.5 { (pa, ca) } else { (pb, cb) };
            return Ok(Resolved { profile: n, description: format!("nearest calibration {} for {distance} m (the bracketing profiles' PSF grids differ, no interpolation){ap_note}", describe(c)) });
        }
        Ok(Resolved { profile: pa, description: format!("nearest calibration {} for {distance} m (outside the calibrated distances or only one){ap_note}", describe(ca)) })
    }
}

/// `(1 − t)·a + t·b` kernel by kernel (each renormalised to sum 1), with `a`'s metadata;
/// `None` when the grids differ in kernel size, tile layout or channels.
pub fn blend(a: &Profile, b: &Profile, t: f64) -> Option<Profile> {
    let (ga, gb) = (&a.grid, &b.grid);
    if ga.kernel_size != gb.kernel_size || ga.columns != gb.columns || ga.rows != gb.rows || ga.channels != gb.channels {
        return None;
    }
    let mut out = a.clone();
    let t = t.clamp(0.0, 1.0) as f32;
    for (kc, kb) in out.grid.kernels.iter_mut().zip(&gb.kernels) {
        for (k, k2) in kc.iter_mut().zip(kb) {
            let data: Vec<f32> = k.data.iter().zip(&k2.data).map(|(x, y)| (1.0 - t) * x + t * y).collect();
            let mut p = Plane { width: k.width, height: k.height, data };
            let s = p.sum() as f32;
            if s > 0.0 {
                p.scale(1.0 / s);
            }
            *k = p;
        }
    }
    for (e, eb) in out.meta.exposure_ratio.iter_mut().zip(&b.meta.exposure_ratio) {
        *e = (1.0 - t as f64) * *e + t as f64 * eb;
    }
    out.meta.note = format!("interpolated: {:.3} of the second calibration", t);
    Some(out)
}

/// The profile behind `--profile DIR`: a set (needs `distance` and `aperture`) or a single
/// profile (they are then ignored, and the description says so).
///
/// # Errors
/// A set without both `distance` and `aperture`; loading errors.
pub fn load_profile_or_set(dir: &Path, distance: Option<f64>, aperture: Option<f64>) -> Result<Resolved, ProfileError> {
    if is_set(dir) {
        let set = ProfileSet::load(dir)?;
        match (distance, aperture) {
            (Some(d), Some(n)) => set.resolve(dir, d, n),
            _ => Err(invalid(&dir.join(INDEX), "a profile set needs --distance (m) and --aperture (f-number)")),
        }
    } else {
        let p = Profile::load(dir)?;
        let note = if distance.is_some() || aperture.is_some() { " (a single profile: --distance/--aperture ignored)" } else { "" };
        Ok(Resolved { profile: p, description: format!("profile {}{note}", dir.display()) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimate::relative_error;
    use crate::image::SampleFormat;
    use crate::image::Transfer;
    use crate::optics::lens::{mono_band, LensModel};
    use crate::profile::{PsfTable, SourceInfo};

    /// A thin lens focused at 1 m: defocus (µm of wavefront at f/4) linear in 1/d − 1/d₀.
    fn profile_at(distance: f64) -> Profile {
        profile_with(distance, 1.5)
    }

    fn profile_with(distance: f64, um_per_diopter: f64) -> Profile {
        let (w, h) = (96, 64);
        let mut lens = LensModel::demo(w, h);
        lens.bands = mono_band();
        lens.aberrations.defocus_um = um_per_diopter * (1.0 / distance - 1.0);
        let grid = lens.psf_grid(4.0, 2, 2, 21);
        let psf = PsfTable { kernel_size: 21, columns: 2, rows: 2, centers: grid.centers.clone(), tile_size: None, files: Default::default() };
        let source = SourceInfo { width: w, height: h, channels: vec!["Y".into()], sample_format: SampleFormat::U16, transfer: Transfer::Linear, open: None, pinhole: None, black_level: vec![] };
        Profile { meta: Profile::new_meta(source, vec![1.0], psf), grid }
    }

    fn err(a: &Profile, b: &Profile) -> f64 {
        let e: Vec<f64> = a.grid.kernels[0].iter().zip(&b.grid.kernels[0]).map(|(x, y)| relative_error(x, y)).collect();
        e.iter().sum::<f64>() / e.len() as f64
    }

    #[test]
    fn interpolation_beats_nearest_on_a_held_out_calibration() {
        let d = tempfile::tempdir().expect("tempdir");
        let mut cal = Vec::new();
        for dist in [0.5, 0.7, 0.9, 1.2, 2.0] {
            let name = format!("d{dist}");
            profile_at(dist).save(&d.path().join(&name)).expect("save");
            cal.push(Calibration { focal: 16.0, aperture: 4.0, distance: dist, profile: name });
        }
        ProfileSet::new(cal).save(d.path()).expect("index");
        let set = ProfileSet::load(d.path()).expect("load");
        // held out: 0.8 m, between 0.7 and 0.9 m
        let truth = profile_at(0.8);
        let r = set.resolve(d.path(), 0.8, 4.0).expect("resolve");
        assert!(r.description.starts_with("interpolated"), "{}", r.description);
        let nearest = Profile::load(&d.path().join("d0.9")).expect("nearest");
        let (ei, en) = (err(&r.profile, &truth), err(&nearest, &truth));
        println!("held-out 0.8 m: interpolated kernel error {:.1} %, nearest (0.9 m) {:.1} % ({})", ei * 100.0, en * 100.0, r.description);
        // how the blend degrades as calibrations get sparser (printed, not asserted)
        for (k, lo, hi) in [(1.5, 0.6, 1.2), (3.0, 0.7, 0.9), (3.0, 0.6, 1.2)] {
            let (a, b, c) = (profile_with(lo, k), profile_with(hi, k), profile_with(0.8, k));
            let t = (1.0 / lo - 1.0 / 0.8) / (1.0 / lo - 1.0 / hi);
            let bl = blend(&a, &b, t).expect("same grid");
            println!("  {k} µm/dioptre, {lo}–{hi} m: blend {:.1} %, nearest {:.1} %", err(&bl, &c) * 100.0, err(&a, &c).min(err(&b, &c)) * 100.0);
        }
        assert!(ei < 0.75 * en, "interpolated {ei:.3} vs nearest {en:.3}");
        assert!(ei < 0.15, "interpolated kernel error {ei:.3}");
        // outside the range: nearest, and it says so
        let far = set.resolve(d.path(), 5.0, 4.0).expect("far");
        assert!(far.description.contains("nearest calibration d2"), "{}", far.description);
        // another aperture: the nearest in stops, noted
        let ap = set.resolve(d.path(), 0.5, 5.6).expect("aperture");
        assert!(ap.description.contains("nearest calibrated aperture f/4"), "{}", ap.description);
        // a set needs both keys
        assert!(load_profile_or_set(d.path(), Some(1.0), None).is_err());
        assert!(load_profile_or_set(&d.path().join("d0.5"), Some(1.0), Some(4.0)).is_ok());
    }

    #[test]
    fn select_brackets_in_inverse_distance() {
        let c = |d: f64, n: f64| Calibration { focal: 16.0, aperture: n, distance: d, profile: format!("{d}-{n}") };
        let set = ProfileSet::new(vec![c(0.5, 4.0), c(2.0, 4.0), c(1.0, 8.0)]);
        let (a, b) = set.select(1.0, 4.0);
        let (b, t) = b.expect("bracketed");
        // 1/d: 0.5 (2 m) … 2 (0.5 m); q = 1 → t = (1 − 0.5)/(2 − 0.5) = 1/3
        assert_eq!((set.calibration[a].distance, set.calibration[b].distance), (2.0, 0.5));
        assert!((t - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(set.select(1.0, 11.0), (2, None));
    }
}
