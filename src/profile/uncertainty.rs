//! Optional per-kernel uncertainty mosaics of a profile (issue 16; docs/profile-format.md
//! "Uncertainty"): `psf-unc-<CHANNEL>.tiff`, one 32-bit float mosaic per channel with the
//! geometry of the channel's PSF mosaic (`columns·k × rows·k`, tile `t` at row `t / columns`,
//! column `t % columns`). Each cell is the per-pixel standard deviation of the kernel
//! ([`crate::estimate::bootstrap`]), on the kernel's scale; every value finite and ≥ 0.
//!
//! The files are optional: a profile without them loads as before ([`load_uncertainty`] gives
//! `None`). They are written and read beside [`super::Profile::save`] / [`super::Profile::load`],
//! which do not touch them.

use super::{invalid, ProfileError};
use crate::fsutil::Overwrite;
use crate::image::io::{decode_image, write_tiff_f32};
use crate::image::{Image, Plane, SampleFormat};
use crate::optics::psf_grid::PsfGrid;
use std::path::Path;

/// The uncertainty mosaic file name for a channel.
pub fn unc_file_name(channel: &str) -> String {
    format!("psf-unc-{channel}.tiff")
}

/// Writes `unc[channel][tile]` (the grid's geometry) as `psf-unc-<C>.tiff` into `dir`,
/// atomically, after checking every value is finite and non-negative.
///
/// # Errors
/// [`ProfileError::Invalid`] naming the file, channel and tile for a wrong count, size or
/// value; I/O errors naming the file.
pub fn save_uncertainty(dir: &Path, grid: &PsfGrid, unc: &[Vec<Plane>]) -> Result<(), ProfileError> {
    let k = grid.kernel_size;
    if unc.len() != grid.channels.len() {
        return Err(invalid(dir, format!("{} uncertainty sets for {} channels", unc.len(), grid.channels.len())));
    }
    for (name, set) in grid.channels.iter().zip(unc) {
        let path = dir.join(unc_file_name(name));
        check_set(&path, name, grid, set)?;
        let mut mosaic = Plane::new(grid.columns * k, grid.rows * k);
        for (t, u) in set.iter().enumerate() {
            mosaic.paste(u, ((t % grid.columns) * k) as isize, ((t / grid.columns) * k) as isize);
        }
        let mut img = Image::new(vec![mosaic]);
        img.format = SampleFormat::F32;
        write_tiff_f32(&path, &img, Overwrite::Replace)?;
    }
    Ok(())
}

/// Reads the uncertainty mosaics of the profile in `dir` whose grid is `grid`: `None` when no
/// channel has one (an older profile), all channels otherwise.
///
/// # Errors
/// [`ProfileError::Invalid`] naming the file when only some channels have one, a mosaic has the
/// wrong size, or a value is NaN, infinite or negative (with channel and tile); decode errors.
pub fn load_uncertainty(dir: &Path, grid: &PsfGrid) -> Result<Option<Vec<Vec<Plane>>>, ProfileError> {
    let paths: Vec<_> = grid.channels.iter().map(|c| dir.join(unc_file_name(c))).collect();
    let present = paths.iter().filter(|p| p.exists()).count();
    if present == 0 {
        return Ok(None);
    }
    let k = grid.kernel_size;
    let mut out = Vec::with_capacity(paths.len());
    for (name, path) in grid.channels.iter().zip(&paths) {
        let bytes = std::fs::read(path).map_err(|source| ProfileError::Io { path: path.clone(), source })?;
        let img = decode_image(path, &bytes)?;
        if img.channel_count() != 1 || img.width() != grid.columns * k || img.height() != grid.rows * k {
            return Err(invalid(path, format!("uncertainty mosaic is {}x{} with {} channel(s); expected {}x{} single-channel", img.width(), img.height(), img.channel_count(), grid.columns * k, grid.rows * k)));
        }
        let m = &img.planes[0];
        let set: Vec<Plane> = (0..grid.tile_count()).map(|t| m.window_reflect(((t % grid.columns) * k) as isize, ((t / grid.columns) * k) as isize, k, k)).collect();
        check_set(path, name, grid, &set)?;
        out.push(set);
    }
    Ok(Some(out))
}

/// One channel's uncertainty kernels: one per tile, `k × k`, finite and non-negative.
fn check_set(path: &Path, name: &str, grid: &PsfGrid, set: &[Plane]) -> Result<(), ProfileError> {
    if set.len() != grid.tile_count() {
        return Err(invalid(path, format!("channel {name}: {} uncertainty kernels for {} tiles", set.len(), grid.tile_count())));
    }
    for (t, u) in set.iter().enumerate() {
        let at = format!("channel {name}, tile {t} (row {}, column {})", t / grid.columns.max(1), t % grid.columns.max(1));
        if u.width != grid.kernel_size || u.height != grid.kernel_size {
            return Err(invalid(path, format!("{at}: uncertainty is {}x{}, the kernel {}", u.width, u.height, grid.kernel_size)));
        }
        if let Some(v) = u.data.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
            return Err(invalid(path, format!("{at}: uncertainty value {v} is not finite and non-negative")));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> PsfGrid {
        let k = 5;
        let centers = PsfGrid::regular_centers(60, 40, 3, 2);
        let kernels = (0..2).map(|_| (0..6).map(|_| Plane::from_fn(k, k, |x, y| if (x, y) == (2, 2) { 1.0 } else { 0.0 })).collect()).collect();
        PsfGrid { kernel_size: k, columns: 3, rows: 2, centers, channels: vec!["R".into(), "G".into()], kernels }
    }

    fn unc(g: &PsfGrid) -> Vec<Vec<Plane>> {
        (0..g.channels.len()).map(|c| (0..g.tile_count()).map(|t| Plane::from_fn(5, 5, |x, y| 1e-3 * (1 + c + t + x + 5 * y) as f32)).collect()).collect()
    }

    /// The mosaics round-trip; a profile without them loads (`None`); a partial set, a NaN and a
    /// negative value are refused naming the file, the channel and the tile.
    #[test]
    fn uncertainty_round_trips_and_damage_is_refused() {
        let d = tempfile::tempdir().unwrap();
        let g = grid();
        assert!(load_uncertainty(d.path(), &g).unwrap().is_none());
        let u = unc(&g);
        save_uncertainty(d.path(), &g, &u).unwrap();
        assert_eq!(load_uncertainty(d.path(), &g).unwrap(), Some(u.clone()));
        // a damaged file: NaN in tile 4 of G, written with the raw encoder
        let mut m = Plane::new(15, 10);
        for (t, p) in u[1].iter().enumerate() {
            m.paste(p, ((t % 3) * 5) as isize, ((t / 3) * 5) as isize);
        }
        m.set(7, 7, f32::NAN);
        let f = std::fs::File::create(d.path().join("psf-unc-G.tiff")).unwrap();
        let mut enc = tiff::encoder::TiffEncoder::new(std::io::BufWriter::new(f)).unwrap();
        enc.write_image::<tiff::encoder::colortype::Gray32Float>(15, 10, &m.data).unwrap();
        drop(enc);
        let e = load_uncertainty(d.path(), &g).unwrap_err().to_string();
        assert!(e.contains("psf-unc-G.tiff") && e.contains("channel G, tile 4") && e.contains("NaN"), "{e}");
        std::fs::remove_file(d.path().join("psf-unc-G.tiff")).unwrap();
        let e = load_uncertainty(d.path(), &g).unwrap_err().to_string();
        assert!(e.contains("psf-unc-G.tiff"), "{e}");
        let mut neg = u;
        neg[0][2].set(0, 0, -1.0);
        let e = save_uncertainty(d.path(), &g, &neg).unwrap_err().to_string();
        assert!(e.contains("psf-unc-R.tiff") && e.contains("tile 2"), "{e}");
    }
}
