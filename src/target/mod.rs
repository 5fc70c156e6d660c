//! Calibration targets: printable broadband random-noise patterns with registration features.
//!
//! A target is a grid of square cells, each black or white from a seeded hash (white noise:
//! a flat power spectrum up to the cell frequency, so every spatial frequency the PSF passes is
//! excited). Around the noise field: a white quiet zone, four corner fiducials (concentric
//! black/white squares, found at any scale and giving the four corners of the noise field), and
//! a thin frame. The same [`TargetSpec`] renders the printable PNG (1-bit, at the stated DPI)
//! and the simulated scene the mock camera sees, so both agree cell for cell.
//!
//! # Units
//! Paper geometry in millimetres; print pixels at `dpi`; `cell_dots` printer pixels per cell.
//! Reflectances: white paper `0.90`, toner `0.05` (linear).

pub mod locate;

use crate::fsutil::{write_atomic, write_atomic_with, Overwrite};
use crate::image::Plane;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Linear reflectance of white paper.
pub const WHITE: f32 = 0.90;
/// Linear reflectance of laser toner.
pub const BLACK: f32 = 0.05;

/// Everything needed to reproduce a target.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetSpec {
    pub format: String,
    pub version: u32,
    /// Paper name (A4, A3, Letter) or "custom".
    pub paper: String,
    pub width_mm: f64,
    pub height_mm: f64,
    pub dpi: u32,
    /// Printer pixels per noise cell.
    pub cell_dots: u32,
    pub seed: u64,
    /// Margin from the paper edge to the frame, mm.
    pub margin_mm: f64,
    /// Side of a corner fiducial, mm.
    pub fiducial_mm: f64,
}

/// Why a target could not be made or written.
#[derive(Debug, thiserror::Error)]
pub enum TargetError {
    #[error("unknown paper size '{0}' (use A3, A4, A5, Letter, or give width/height)")]
    UnknownPaper(String),
    #[error("invalid target: {0}")]
    Invalid(String),
    #[error("cannot write {path}: {source}")]
    Write { path: std::path::PathBuf, #[source] source: std::io::Error },
}

/// Paper sizes (portrait, mm).
pub fn paper_size(name: &str) -> Option<(f64, f64)> {
    match name.to_ascii_lowercase().as_str() {
        "a3" => Some((297.0, 420.0)),
        "a4" => Some((210.0, 297.0)),
        "a5" => Some((148.0, 210.0)),
        "letter" => Some((215.9, 279.4)),
        _ => None,
    }
}

impl TargetSpec {
    /// A landscape target on a named paper size.
    ///
    /// # Errors
    /// Unknown paper names, a DPI or cell size of zero.
    pub fn new(paper: &str, dpi: u32, cell_dots: u32, seed: u64) -> Result<Self, TargetError> {
        let (w, h) = paper_size(paper).ok_or_else(|| TargetError::UnknownPaper(paper.into()))?;
        if dpi == 0 || cell_dots == 0 {
            return Err(TargetError::Invalid("dpi and cell size must be positive".into()));
        }
        Ok(Self {
            format: "lensrig-target".into(),
            version: 1,
            paper: paper.to_ascii_uppercase(),
            width_mm: h.max(w),
            height_mm: h.min(w),
            dpi,
            cell_dots,
            seed,
            margin_mm: 10.0,
            fiducial_mm: 12.0,
        })
    }

    /// Print size in pixels.
    pub fn pixels(&self) -> (usize, usize) {
        let f = self.dpi as f64 / 25.4;
        ((self.width_mm * f).round() as usize, (self.height_mm * f).round() as usize)
    }

    fn mm_to_px(&self, mm: f64) -> usize {
        (mm * self.dpi as f64 / 25.4).round() as usize
    }

    /// The noise field in print pixels: `(x0, y0, width, height)`, a whole number of cells.
    pub fn noise_field(&self) -> (usize, usize, usize, usize) {
        let (w, h) = self.pixels();
        let inset = self.mm_to_px(self.margin_mm + self.fiducial_mm + 3.0);
        let cd = self.cell_dots as usize;
        let nw = (w.saturating_sub(2 * inset)) / cd * cd;
        let nh = (h.saturating_sub(2 * inset)) / cd * cd;
        ((w - nw) / 2, (h - nh) / 2, nw, nh)
    }

    /// Number of noise cells `(columns, rows)`.
    pub fn cells(&self) -> (usize, usize) {
        let (_, _, nw, nh) = self.noise_field();
        (nw / self.cell_dots as usize, nh / self.cell_dots as usize)
    }

    /// Whether cell `(i, j)` is white (a stateless hash of seed and position).
    pub fn cell_white(&self, i: i64, j: i64) -> bool {
        let mut z = self.seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        z & 1 == 1
    }

    /// Reflectance of the noise pattern at continuous cell coordinates (cells are unit squares).
    pub fn noise_at(&self, u: f64, v: f64) -> f32 {
        if self.cell_white(u.floor() as i64, v.floor() as i64) {
            WHITE
        } else {
            BLACK
        }
    }

    /// The printable page as 0 (black) / 1 (white) per print pixel.
    pub fn render_print(&self) -> Vec<u8> {
        let (w, h) = self.pixels();
        let mut px = vec![1u8; w * h];
        let (nx, ny, nw, nh) = self.noise_field();
        let cd = self.cell_dots as usize;
        for y in 0..nh {
            for x in 0..nw {
                px[(ny + y) * w + nx + x] = self.cell_white((x / cd) as i64, (y / cd) as i64) as u8;
            }
        }
        // frame, 1 mm wide, at the margin
        let m = self.mm_to_px(self.margin_mm);
        let t = self.mm_to_px(1.0).max(1);
        for y in m..h - m {
            for x in m..w - m {
                if x < m + t || x >= w - m - t || y < m + t || y >= h - m - t {
                    px[y * w + x] = 0;
                }
            }
        }
        // fiducials: concentric squares (black 7/7, white 5/7, black 3/7 of the side)
        let f = self.mm_to_px(self.fiducial_mm);
        let off = m + t + self.mm_to_px(1.5);
        for &(fx, fy) in &[(off, off), (w - off - f, off), (off, h - off - f), (w - off - f, h - off - f)] {
            for y in 0..f {
                for x in 0..f {
                    let d = (x.min(f - 1 - x)).min(y.min(f - 1 - y)) as f64 / f as f64; // 0 at edge, 0.5 at centre
                    let ring = if d < 1.0 / 7.0 { 0 } else if d < 2.0 / 7.0 { 1 } else { 0 };
                    px[(fy + y) * w + fx + x] = ring;
                }
            }
        }
        px
    }

    /// Writes `NAME.png` (1-bit, DPI recorded in the pHYs chunk) and `NAME.toml` into `dir`.
    ///
    /// # Errors
    /// I/O errors naming the file; existing files are replaced only with `overwrite`.
    pub fn write(&self, dir: &Path, name: &str, overwrite: Overwrite) -> Result<(), TargetError> {
        std::fs::create_dir_all(dir).map_err(|source| TargetError::Write { path: dir.into(), source })?;
        let (w, h) = self.pixels();
        let bits = self.render_print();
        let row_bytes = w.div_ceil(8);
        let mut packed = vec![0u8; row_bytes * h];
        for y in 0..h {
            for x in 0..w {
                if bits[y * w + x] == 1 {
                    packed[y * row_bytes + x / 8] |= 0x80 >> (x % 8);
                }
            }
        }
        let png_path = dir.join(format!("{name}.png"));
        let ppm = (self.dpi as f64 / 0.0254).round() as u32;
        write_atomic_with(&png_path, overwrite, |f| {
            let mut enc = png::Encoder::new(std::io::BufWriter::new(f), w as u32, h as u32);
            enc.set_color(png::ColorType::Grayscale);
            enc.set_depth(png::BitDepth::One);
            enc.set_pixel_dims(Some(png::PixelDimensions { xppu: ppm, yppu: ppm, unit: png::Unit::Meter }));
            let mut wr = enc.write_header().map_err(std::io::Error::other)?;
            wr.write_image_data(&packed).map_err(std::io::Error::other)?;
            wr.finish().map_err(std::io::Error::other)
        })
        .map_err(|source| TargetError::Write { path: png_path.clone(), source })?;
        let toml_path = dir.join(format!("{name}.toml"));
        let (cw, ch) = self.cells();
        let (nx, ny, nw, nh) = self.noise_field();
        let mm = 25.4 / self.dpi as f64;
        let text = format!(
            "# lensrig calibration target. Print at 100% (no scaling), {dpi} DPI, on {paper} landscape.\n\
             # Noise field: {cw} x {ch} cells of {cmm:.3} mm at ({x0:.2}, {y0:.2}) mm, size {nwm:.2} x {nhm:.2} mm.\n{}",
            toml::to_string_pretty(self).map_err(|e| TargetError::Invalid(e.to_string()))?,
            dpi = self.dpi,
            paper = self.paper,
            cmm = self.cell_dots as f64 * mm,
            x0 = nx as f64 * mm,
            y0 = ny as f64 * mm,
            nwm = nw as f64 * mm,
            nhm = nh as f64 * mm,
        );
        write_atomic(&toml_path, text.as_bytes(), overwrite).map_err(|source| TargetError::Write { path: toml_path, source })
    }

    /// Reads a target description.
    ///
    /// # Errors
    /// Unreadable or invalid TOML (with line and key).
    pub fn load(path: &Path) -> Result<Self, TargetError> {
        let text = std::fs::read_to_string(path).map_err(|source| TargetError::Write { path: path.into(), source })?;
        toml::from_str(&text).map_err(|e| TargetError::Invalid(format!("{}: {}", path.display(), crate::toml_error(&text, &e))))
    }
}

/// The noise field as seen by a sensor: `width × height` pixels with `pixels_per_cell` sensor
/// pixels per target cell, starting at cell coordinates `(u0, v0)`, area-averaged over each
/// pixel (`ss × ss` supersampling). Linear reflectance.
pub fn render_noise_scene(spec: &TargetSpec, width: usize, height: usize, pixels_per_cell: f64, u0: f64, v0: f64) -> Plane {
    render_noise_scene_mapped(spec, width, height, pixels_per_cell, u0, v0, |x, y| (x, y))
}

/// [`render_noise_scene`] through a geometric map: sensor pixel coordinates `(x, y)` (pixel
/// centres at integers) are mapped by `map` to the undistorted pixel coordinates the target
/// is laid out in (`u = u0 + x_u / pixels_per_cell`), per supersample.
pub fn render_noise_scene_mapped(spec: &TargetSpec, width: usize, height: usize, pixels_per_cell: f64, u0: f64, v0: f64, map: impl Fn(f64, f64) -> (f64, f64)) -> Plane {
    let ss = 4;
    Plane::from_fn(width, height, |x, y| {
        let mut acc = 0.0;
        for j in 0..ss {
            for i in 0..ss {
                let (xu, yu) = map(x as f64 + (i as f64 + 0.5) / ss as f64 - 0.5, y as f64 + (j as f64 + 0.5) / ss as f64 - 0.5);
                acc += spec.noise_at(u0 + xu / pixels_per_cell, v0 + yu / pixels_per_cell);
            }
        }
        acc / (ss * ss) as f32
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_balanced_and_white() {
        let t = TargetSpec::new("A4", 300, 4, 42).unwrap();
        let n = 200;
        let whites = (0..n).flat_map(|j| (0..n).map(move |i| (i, j))).filter(|&(i, j)| t.cell_white(i, j)).count();
        let frac = whites as f64 / (n * n) as f64;
        assert!((frac - 0.5).abs() < 0.01, "{frac}");
        // neighbouring cells are uncorrelated
        let mut agree = 0;
        for j in 0..n {
            for i in 0..n - 1 {
                agree += (t.cell_white(i, j) == t.cell_white(i + 1, j)) as usize;
            }
        }
        let a = agree as f64 / (n * (n - 1)) as f64;
        assert!((a - 0.5).abs() < 0.01, "{a}");
    }

    #[test]
    fn a4_geometry_and_files() {
        let t = TargetSpec::new("a4", 150, 3, 1).unwrap();
        assert_eq!(t.pixels(), (1754, 1240));
        let (x0, y0, w, h) = t.noise_field();
        assert!(x0 > 0 && y0 > 0 && w % 3 == 0 && h % 3 == 0 && x0 + w < 1754);
        let d = tempfile::tempdir().unwrap();
        t.write(d.path(), "t", Overwrite::Never).unwrap();
        let img = image::open(d.path().join("t.png")).unwrap();
        assert_eq!((img.width(), img.height()), (1754, 1240));
        let back = TargetSpec::load(&d.path().join("t.toml")).unwrap();
        assert_eq!(back, t);
        // never overwrite
        assert!(t.write(d.path(), "t", Overwrite::Never).is_err());
        assert!(TargetSpec::new("B7", 300, 4, 1).is_err());
    }
}
