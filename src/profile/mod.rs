//! The lens profile: what `estimate` writes and `simulate`, `deblur` and `diagnose` read.
//!
//! A profile is a directory:
//! - `profile.toml` — format version, the source images' geometry and encoding, the exposure
//!   ratio, the registration, estimation settings and figures, and the `[psf]` table
//!   (`kernel_size`, `columns`, `rows`, `centers`, `files`);
//! - `psf-<CHANNEL>.tiff` — one 32-bit float mosaic per channel, `columns·k` wide and
//!   `rows·k` tall; tile `t` is the cell at row `t / columns`, column `t % columns`.
//!
//! The full specification is `docs/profile-format.md`. Kernels follow the PSF convention of
//! [`crate::solve::conv`] and each sums to 1; the exposure ratio is stored separately.

use crate::fsutil::{write_atomic, Overwrite};
use crate::image::io::{read_image, write_tiff_f32, ImageError};
use crate::image::{Image, Plane, SampleFormat, Transfer};
use crate::optics::psf_grid::PsfGrid;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub mod set;

/// The format version this build writes and reads.
pub const FORMAT_VERSION: u32 = 1;

/// Why a profile could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum ProfileError {
    #[error("cannot read {path}: {source}")]
    Io { path: PathBuf, #[source] source: std::io::Error },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error(transparent)]
    Image(#[from] ImageError),
}

/// Geometry and encoding of the images a profile was estimated from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SourceInfo {
    pub width: usize,
    pub height: usize,
    pub channels: Vec<String>,
    pub sample_format: SampleFormat,
    /// How the source files were encoded; estimation ran on linearised values.
    pub transfer: Transfer,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub open: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pinhole: Option<String>,
    /// Black level subtracted before estimation, per channel, on the full-scale axis.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub black_level: Vec<f32>,
}

/// The pinhole-to-wide-open registration that was applied (pinhole pixel `p` was sampled at
/// `A·p + t` about the image centre; identity when none was needed).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegistrationInfo {
    pub model: String,
    /// `[a11, a12, a21, a22]`
    pub matrix: [f64; 4],
    /// `[tx, ty]` in pixels
    pub translation: [f64; 2],
    /// RMS of the per-tile displacement residuals after the fit, pixels.
    pub residual_px: f64,
}

impl Default for RegistrationInfo {
    fn default() -> Self {
        Self { model: "none".into(), matrix: [1.0, 0.0, 0.0, 1.0], translation: [0.0, 0.0], residual_px: 0.0 }
    }
}

/// The `[psf]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PsfTable {
    pub kernel_size: usize,
    pub columns: usize,
    pub rows: usize,
    pub centers: Vec<[f64; 2]>,
    /// Tile size in pixels `[w, h]` the kernels were fitted on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tile_size: Option<[usize; 2]>,
    /// Channel name -> mosaic file name (relative to the profile directory).
    pub files: BTreeMap<String, String>,
}

/// Figures from the estimation, per channel and tile, for the report and for users.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EstimationInfo {
    #[serde(default)]
    pub lambda: f64,
    #[serde(default)]
    pub mu: f64,
    /// Noise standard deviation estimated in the wide-open image, per channel (full scale).
    #[serde(default)]
    pub noise_sigma: Vec<f64>,
    /// Solver iterations per `[channel][tile]`.
    #[serde(default)]
    pub iterations: Vec<Vec<usize>>,
    /// Final relative primal-dual gap per `[channel][tile]`.
    #[serde(default)]
    pub relative_gap: Vec<Vec<f64>>,
    /// RMS of the data residual (wide-open minus prediction) per `[channel][tile]`, full scale.
    #[serde(default)]
    pub residual_rms: Vec<Vec<f64>>,
    #[serde(default)]
    pub saturated_fraction: f64,
    #[serde(default)]
    pub seconds: f64,
}

/// `profile.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProfileToml {
    pub format: String,
    pub version: u32,
    pub software: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub created: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
    pub source: SourceInfo,
    /// Wide-open / pinhole exposure ratio `s` per channel: `open ≈ s · (K * pinhole)`.
    pub exposure_ratio: Vec<f64>,
    #[serde(default)]
    pub registration: RegistrationInfo,
    #[serde(default)]
    pub estimation: EstimationInfo,
    pub psf: PsfTable,
    /// Extra physics fitted by `diagnose` (effect name -> parameters), applied by `simulate`.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub corrections: BTreeMap<String, toml::Value>,
}

/// A profile in memory.
#[derive(Clone, Debug, PartialEq)]
pub struct Profile {
    pub meta: ProfileToml,
    pub grid: PsfGrid,
}

fn invalid(path: &Path, message: impl Into<String>) -> ProfileError {
    ProfileError::Invalid { path: path.into(), message: message.into() }
}

/// The mosaic file name for a channel.
pub fn psf_file_name(channel: &str) -> String {
    format!("psf-{channel}.tiff")
}

impl Profile {
    /// Writes the profile into `dir` (created if missing; files replaced atomically).
    ///
    /// # Errors
    /// I/O errors naming the file.
    pub fn save(&self, dir: &Path) -> Result<(), ProfileError> {
        std::fs::create_dir_all(dir).map_err(|source| ProfileError::Io { path: dir.into(), source })?;
        let g = &self.grid;
        let k = g.kernel_size;
        let mut meta = self.meta.clone();
        meta.psf.files.clear();
        for (ci, name) in g.channels.iter().enumerate() {
            let mut mosaic = Plane::new(g.columns * k, g.rows * k);
            for t in 0..g.tile_count() {
                mosaic.paste(&g.kernels[ci][t], ((t % g.columns) * k) as isize, ((t / g.columns) * k) as isize);
            }
            let file = psf_file_name(name);
            let mut img = Image::new(vec![mosaic]);
            img.format = SampleFormat::F32;
            write_tiff_f32(&dir.join(&file), &img, Overwrite::Replace)?;
            meta.psf.files.insert(name.clone(), file);
        }
        let text = toml::to_string_pretty(&meta).map_err(|e| invalid(dir, format!("cannot serialise profile.toml: {e}")))?;
        let path = dir.join("profile.toml");
        write_atomic(&path, text.as_bytes(), Overwrite::Replace).map_err(|source| ProfileError::Io { path, source })
    }

    /// Reads and validates a profile directory.
    ///
    /// # Errors
    /// Missing files, unknown keys, an unsupported version, inconsistent geometry (even kernel
    /// size, wrong number of centres, mosaics of the wrong size) — each naming the file.
    pub fn load(dir: &Path) -> Result<Profile, ProfileError> {
        let path = dir.join("profile.toml");
        let text = std::fs::read_to_string(&path).map_err(|source| ProfileError::Io { path: path.clone(), source })?;
        let meta: ProfileToml = toml::from_str(&text).map_err(|e| invalid(&path, crate::toml_error(&text, &e)))?;
        if meta.format != "lensrig-profile" {
            return Err(invalid(&path, format!("format is '{}', expected 'lensrig-profile'", meta.format)));
        }
        if meta.version != FORMAT_VERSION {
            return Err(invalid(&path, format!("profile version {} is not supported (this lensrig reads version {FORMAT_VERSION})", meta.version)));
        }
        let p = &meta.psf;
        if p.kernel_size == 0 || p.kernel_size % 2 == 0 {
            return Err(invalid(&path, format!("psf.kernel_size must be odd, got {}", p.kernel_size)));
        }
        if p.columns == 0 || p.rows == 0 || p.centers.len() != p.columns * p.rows {
            return Err(invalid(&path, format!("psf.centers has {} entries but columns × rows = {}", p.centers.len(), p.columns * p.rows)));
        }
        let channels = meta.source.channels.clone();
        if meta.exposure_ratio.len() != channels.len() {
            return Err(invalid(&path, "exposure_ratio needs one value per channel"));
        }
        let k = p.kernel_size;
        let mut kernels = Vec::with_capacity(channels.len());
        for ch in &channels {
            let file = p.files.get(ch).cloned().unwrap_or_else(|| psf_file_name(ch));
            let fpath = dir.join(&file);
            let img = read_image(&fpath)?;
            if img.channel_count() != 1 || img.width() != p.columns * k || img.height() != p.rows * k {
                return Err(invalid(
                    &fpath,
                    format!("mosaic is {}x{} with {} channel(s); expected {}x{} single-channel", img.width(), img.height(), img.channel_count(), p.columns * k, p.rows * k),
                ));
            }
            let m = &img.planes[0];
            kernels.push(
                (0..p.columns * p.rows)
                    .map(|t| m.window_reflect(((t % p.columns) * k) as isize, ((t / p.columns) * k) as isize, k, k))
                    .collect(),
            );
        }
        let grid = PsfGrid { kernel_size: k, columns: p.columns, rows: p.rows, centers: p.centers.clone(), channels, kernels };
        Ok(Profile { meta, grid })
    }

    /// A new profile's metadata with the fixed fields filled in.
    pub fn new_meta(source: SourceInfo, exposure_ratio: Vec<f64>, psf: PsfTable) -> ProfileToml {
        ProfileToml {
            format: "lensrig-profile".into(),
            version: FORMAT_VERSION,
            software: format!("lensrig {}", env!("CARGO_PKG_VERSION")),
            created: crate::timestamp_utc(),
            note: String::new(),
            source,
            exposure_ratio,
            registration: RegistrationInfo::default(),
            estimation: EstimationInfo::default(),
            psf,
            corrections: BTreeMap::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Profile {
        let k = 5;
        let grid = PsfGrid {
            kernel_size: k,
            columns: 3,
            rows: 2,
            centers: PsfGrid::regular_centers(90, 40, 3, 2),
            channels: vec!["R".into(), "G".into(), "B".into()],
            kernels: (0..3).map(|c| (0..6).map(|t| Plane::from_fn(k, k, |x, y| (c * 100 + t * 10 + x + y) as f32)).collect()).collect(),
        };
        let source = SourceInfo {
            width: 90,
            height: 40,
            channels: grid.channels.clone(),
            sample_format: SampleFormat::U16,
            transfer: Transfer::Linear,
            open: None,
            pinhole: None,
            black_level: vec![],
        };
        let psf = PsfTable { kernel_size: k, columns: 3, rows: 2, centers: grid.centers.clone(), tile_size: Some([30, 20]), files: BTreeMap::new() };
        Profile { meta: Profile::new_meta(source, vec![2.0, 2.0, 2.0], psf), grid }
    }

    #[test]
    fn save_load_round_trip() {
        let d = tempfile::tempdir().unwrap();
        let p = sample();
        p.save(d.path()).unwrap();
        let q = Profile::load(d.path()).unwrap();
        assert_eq!(p.grid, q.grid);
        assert_eq!(q.meta.psf.files["G"], "psf-G.tiff");
        let text = std::fs::read_to_string(d.path().join("profile.toml")).unwrap();
        assert!(text.contains("[psf]") && text.contains("kernel_size = 5"), "{text}");
    }

    #[test]
    fn unknown_keys_and_bad_sizes_are_rejected() {
        let d = tempfile::tempdir().unwrap();
        sample().save(d.path()).unwrap();
        let path = d.path().join("profile.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        std::fs::write(&path, text.replace("[psf]", "[psf]\nbogus_key = 1")).unwrap();
        let e = Profile::load(d.path()).unwrap_err().to_string();
        assert!(e.contains("bogus_key") && e.contains("profile.toml") && e.contains("line"), "{e}");
        std::fs::write(&path, text.replace("kernel_size = 5", "kernel_size = 4")).unwrap();
        let e = Profile::load(d.path()).unwrap_err().to_string();
        assert!(e.contains("odd"), "{e}");
    }
}
