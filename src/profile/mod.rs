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
//!
//! # Validity
//! A profile is valid or refused, on [`Profile::load`] and on [`Profile::save`] alike (so a bug
//! is caught where it happens, never in a later stage): see [`Profile::validate`]. Every kernel
//! is finite, non-negative within [`KERNEL_NEGATIVE_TOLERANCE`] and sums to 1 within
//! [`KERNEL_SUM_TOLERANCE`]; every centre lies inside the source image (pixel centres at
//! integers, so `-0.5 ≤ x ≤ width − 0.5`); every exposure ratio is finite and positive; and no
//! number in `profile.toml` is NaN or infinite. Errors name the file, the channel and the tile.

use crate::fsutil::{write_atomic, Overwrite};
use crate::image::io::{decode_image, write_tiff_f32, ImageError};
use crate::image::{Image, Plane, SampleFormat, Transfer};
use crate::optics::psf_grid::PsfGrid;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub mod noise;
pub mod set;
pub mod uncertainty;

/// The format version this build writes and reads.
pub const FORMAT_VERSION: u32 = 1;

/// Most PSF tiles a profile may have (a bound on what a file can make lensrig allocate).
pub const MAX_TILES: usize = 1 << 16;

/// A kernel sample below `-KERNEL_NEGATIVE_TOLERANCE · max|k|` is negative beyond round-off.
pub const KERNEL_NEGATIVE_TOLERANCE: f64 = 1e-4;

/// A kernel's sum may differ from 1 by this much. The estimator's kernels sum to 1 only
/// approximately (0.995 is typical: its sum constraint is soft and the exposure ratio is fitted
/// separately), so this is a sanity bound that catches a wrong normalisation (0.5, 2), not
/// round-off.
pub const KERNEL_SUM_TOLERANCE: f64 = 0.05;

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
    /// For profiles estimated from camera raw files: the raw channels the kernels describe
    /// (`R, G1, G2, B` CFA planes at half resolution, or bilinear `R, G, B`), the CFA pattern
    /// and the levels taken from the file. Optional; absent for PNG/TIFF sources.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw: Option<crate::image::raw::RawLayout>,
    /// The sensor's noise law on the linear axis ([`noise::NoiseLaw`]), fitted from the
    /// calibration captures by `estimate`; `deblur` uses it. Optional (older profiles have none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise: Option<noise::NoiseLaw>,
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

/// Why one kernel is invalid (positions are `(x, y)` inside the kernel).
#[derive(Debug, thiserror::Error)]
enum KernelError {
    #[error("kernel value {value} at (x={x}, y={y}) is not finite")]
    NonFinite { value: f32, x: usize, y: usize },
    #[error("kernel value {value} at (x={x}, y={y}) is negative")]
    Negative { value: f32, x: usize, y: usize },
    #[error("kernel sums to {sum:.6}, not 1 (tolerance {KERNEL_SUM_TOLERANCE})")]
    Sum { sum: f64 },
}

/// Why one kernel is invalid, or `Ok`.
fn check_kernel(k: &Plane) -> Result<(), KernelError> {
    if let Some(i) = k.data.iter().position(|v| !v.is_finite()) {
        return Err(KernelError::NonFinite { value: k.data[i], x: i % k.width.max(1), y: i / k.width.max(1) });
    }
    let peak = k.data.iter().fold(0.0f64, |a, &v| a.max((v as f64).abs()));
    if let Some(i) = k.data.iter().position(|&v| (v as f64) < -KERNEL_NEGATIVE_TOLERANCE * peak) {
        return Err(KernelError::Negative { value: k.data[i], x: i % k.width.max(1), y: i / k.width.max(1) });
    }
    let sum: f64 = k.data.iter().map(|&v| v as f64).sum();
    if (sum - 1.0).abs() > KERNEL_SUM_TOLERANCE {
        return Err(KernelError::Sum { sum });
    }
    Ok(())
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
    /// The profile is checked first ([`Profile::validate`]); an invalid profile is not written.
    pub fn save(&self, dir: &Path) -> Result<(), ProfileError> {
        self.validate(dir)?;
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
        Self::load_with(dir, &|p| std::fs::read(p))
    }

    /// [`Profile::load`] with the files read by `read` (the fuzz targets feed bytes from
    /// memory); `dir` names the files in errors and is joined to each file name.
    ///
    /// # Errors
    /// As [`Profile::load`].
    pub fn load_with(dir: &Path, read: &dyn Fn(&Path) -> std::io::Result<Vec<u8>>) -> Result<Profile, ProfileError> {
        let path = dir.join("profile.toml");
        let bytes = read(&path).map_err(|source| ProfileError::Io { path: path.clone(), source })?;
        let text = String::from_utf8(bytes).map_err(|_| invalid(&path, "is not UTF-8 text"))?;
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
        // checked products: the numbers come from a file and may be anything
        let tiles = p.columns.checked_mul(p.rows).filter(|&n| n > 0 && n <= MAX_TILES);
        let mosaic = p.columns.checked_mul(p.kernel_size).zip(p.rows.checked_mul(p.kernel_size));
        let (Some(tiles), Some(_)) = (tiles, mosaic) else {
            return Err(invalid(&path, format!("psf grid {} × {} of kernels {} is empty or too large", p.columns, p.rows, p.kernel_size)));
        };
        if p.centers.len() != tiles {
            return Err(invalid(&path, format!("psf.centers has {} entries but columns × rows = {tiles}", p.centers.len())));
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
            let bytes = read(&fpath).map_err(|source| ProfileError::Io { path: fpath.clone(), source })?;
            // values are checked per tile below, where the error can name channel and tile
            let img = decode_image(&fpath, &bytes)?;
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
        let profile = Profile { meta, grid };
        profile.validate(dir)?;
        Ok(profile)
    }

    /// Checks the rules of the module docs (see "Validity"); `dir` names the files in errors.
    ///
    /// # Errors
    /// [`ProfileError::Invalid`] naming the file (`profile.toml` or the channel's mosaic), and
    /// for kernels the channel and the tile (index, row and column).
    pub fn validate(&self, dir: &Path) -> Result<(), ProfileError> {
        let toml_path = dir.join("profile.toml");
        let m = &self.meta;
        let g = &self.grid;
        if let Some(key) = crate::fsutil::first_non_finite(m) {
            return Err(invalid(&toml_path, format!("{key} is not a finite number")));
        }
        for (c, r) in m.exposure_ratio.iter().enumerate() {
            if !(r.is_finite() && *r > 0.0) {
                let ch = m.source.channels.get(c).map_or("?", |s| s.as_str());
                return Err(invalid(&toml_path, format!("channel {ch}: exposure_ratio {r} must be finite and positive")));
            }
        }
        if let Some(law) = &m.noise {
            law.check().map_err(|e| invalid(&toml_path, e.to_string()))?;
            if law.channels() != m.source.channels.len() {
                return Err(invalid(&toml_path, format!("noise law has {} channel(s), the source {}", law.channels(), m.source.channels.len())));
            }
        }
        let (w, h) = (m.source.width as f64, m.source.height as f64);
        for (t, c) in g.centers.iter().enumerate() {
            let inside = c[0].is_finite() && c[1].is_finite() && c[0] >= -0.5 && c[0] <= w - 0.5 && c[1] >= -0.5 && c[1] <= h - 0.5;
            if !inside {
                return Err(invalid(
                    &toml_path,
                    format!("tile {t}: centre ({}, {}) lies outside the {}x{} source image", c[0], c[1], m.source.width, m.source.height),
                ));
            }
        }
        if g.kernels.len() != g.channels.len() {
            return Err(invalid(&toml_path, format!("{} kernel sets for {} channels", g.kernels.len(), g.channels.len())));
        }
        for (name, set) in g.channels.iter().zip(&g.kernels) {
            let file = m.psf.files.get(name).cloned().unwrap_or_else(|| psf_file_name(name));
            let fpath = dir.join(file);
            if set.len() != g.tile_count() {
                return Err(invalid(&fpath, format!("channel {name}: {} kernels for {} tiles", set.len(), g.tile_count())));
            }
            for (t, k) in set.iter().enumerate() {
                let at = format!("channel {name}, tile {t} (row {}, column {})", t / g.columns.max(1), t % g.columns.max(1));
                if let Err(why) = check_kernel(k) {
                    return Err(invalid(&fpath, format!("{at}: {why}")));
                }
            }
        }
        Ok(())
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
            raw: None,
            noise: None,
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
            kernels: (0..3)
                .map(|c| {
                    (0..6)
                        .map(|t| {
                            let mut p = Plane::from_fn(k, k, |x, y| (c * 100 + t * 10 + x + y) as f32);
                            let s = p.sum() as f32;
                            p.scale(1.0 / s);
                            p
                        })
                        .collect()
                })
                .collect(),
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

    /// Writes mosaic `channel` of the profile in `dir` with the raw encoder (NaN allowed).
    fn write_raw_mosaic(dir: &Path, p: &Profile, channel: usize) {
        let g = &p.grid;
        let k = g.kernel_size;
        let mut mosaic = Plane::new(g.columns * k, g.rows * k);
        for t in 0..g.tile_count() {
            mosaic.paste(&g.kernels[channel][t], ((t % g.columns) * k) as isize, ((t / g.columns) * k) as isize);
        }
        let f = std::fs::File::create(dir.join(psf_file_name(&g.channels[channel]))).unwrap();
        let mut enc = tiff::encoder::TiffEncoder::new(std::io::BufWriter::new(f)).unwrap();
        enc.write_image::<tiff::encoder::colortype::Gray32Float>(mosaic.width as u32, mosaic.height as u32, &mosaic.data).unwrap();
    }

    #[test]
    fn broken_kernels_are_refused_on_load_and_on_save_naming_file_channel_tile() {
        type Break = fn(&mut Plane);
        let cases: [(&str, Break, &str); 3] = [
            ("NaN kernel", |k| k.data[7] = f32::NAN, "not finite"),
            ("negative kernel", |k| k.data[3] = -0.05, "negative"),
            ("kernel sum 0.5", |k| k.scale(0.5), "sums to 0.5"),
        ];
        for (what, brk, expect) in cases {
            let d = tempfile::tempdir().unwrap();
            let good = sample();
            good.save(d.path()).unwrap();
            let mut bad = good.clone();
            brk(&mut bad.grid.kernels[1][4]);
            // save refuses and leaves the good profile in place
            let e = bad.save(d.path()).unwrap_err().to_string();
            assert!(e.contains("psf-G.tiff") && e.contains("channel G") && e.contains("tile 4 (row 1, column 1)") && e.contains(expect), "{what}: {e}");
            assert_eq!(Profile::load(d.path()).unwrap().grid, good.grid, "{what}");
            // load refuses a damaged file
            write_raw_mosaic(d.path(), &bad, 1);
            let e = Profile::load(d.path()).unwrap_err().to_string();
            assert!(e.contains("psf-G.tiff") && e.contains("channel G") && e.contains("tile 4 (row 1, column 1)") && e.contains(expect), "{what}: {e}");
        }
    }

    #[test]
    fn bad_centres_and_ratios_are_refused_on_load_and_on_save() {
        type Edit = fn(&mut toml::Table);
        fn at<'a>(t: &'a mut toml::Table, path: &[&str]) -> &'a mut toml::Value {
            let mut v = t.get_mut(path[0]).unwrap();
            for k in &path[1..] {
                v = match k.parse::<usize>() {
                    Ok(i) => v.as_array_mut().unwrap().get_mut(i).unwrap(),
                    Err(_) => v.as_table_mut().unwrap().get_mut(*k).unwrap(),
                };
            }
            v
        }
        let cases: [(Edit, &str, &str); 5] = [
            (|t| *at(t, &["exposure_ratio", "1"]) = toml::Value::Float(0.0), "channel G: exposure_ratio 0", "ratio 0"),
            (|t| *at(t, &["exposure_ratio", "2"]) = toml::Value::Float(-1.0), "channel B: exposure_ratio -1", "ratio -1"),
            (|t| *at(t, &["exposure_ratio", "0"]) = toml::Value::Float(f64::NAN), "exposure_ratio[0] is not a finite number", "ratio NaN"),
            (|t| *at(t, &["psf", "centers", "0", "1"]) = toml::Value::Float(95.0), "tile 0: centre (14.5, 95) lies outside the 90x40", "centre outside"),
            (|t| *at(t, &["estimation", "lambda"]) = toml::Value::Float(f64::INFINITY), "estimation.lambda is not a finite number", "inf figure"),
        ];
        for (edit, expect, what) in cases {
            let d = tempfile::tempdir().unwrap();
            sample().save(d.path()).unwrap();
            let path = d.path().join("profile.toml");
            let mut t: toml::Table = toml::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
            edit(&mut t);
            std::fs::write(&path, toml::to_string(&t).unwrap()).unwrap();
            let e = Profile::load(d.path()).unwrap_err().to_string();
            assert!(e.contains("profile.toml") && e.contains(expect), "{what}: {e}");
        }
        let mut p = sample();
        p.meta.exposure_ratio[0] = f64::NAN;
        let d = tempfile::tempdir().unwrap();
        let e = p.save(d.path()).unwrap_err().to_string();
        assert!(e.contains("exposure_ratio[0] is not a finite number"), "{e}");
        assert!(!d.path().join("profile.toml").exists());
        let mut p = sample();
        p.grid.centers[5] = [-3.0, 10.0];
        let e = p.save(d.path()).unwrap_err().to_string();
        assert!(e.contains("tile 5: centre (-3, 10)"), "{e}");
    }
}
