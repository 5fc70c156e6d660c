//! Camera RAW / DNG input (feature `raw`, decoder: `rawler`, LGPL-2.1) and the CFA conventions.
//!
//! [`read_raw`] decodes a raw file into an [`Image`] on the full-scale axis of
//! [`crate::image`], with everything taken from the file:
//! - only the **active area** is kept (masked border pixels are dropped); an odd width or
//!   height loses its last column or row so that every 2×2 CFA cell is complete;
//! - the **black level** (per CFA position when the file gives a repeat pattern) is subtracted
//!   and the result divided by `white − black`, so 0 is black and 1 the file's **white level**
//!   (the saturation point); values slightly below 0 are kept (read noise around black);
//! - values are **linear** ([`Transfer::Linear`]); no white balance, colour matrix or
//!   demosaicing is applied.
//!
//! # CFA handling ([`RawMethod`])
//! - [`RawMethod::CfaPlanes`] (the default, used by [`crate::image::io::read_image`]): the
//!   Bayer mosaic becomes four half-resolution planes named `R`, `G1`, `G2`, `B`, always in
//!   that order; `G1` is the green in the pattern's top row, `G2` the one in its bottom row.
//!   Plane pixel `(i, j)` is mosaic pixel `(2i + dx, 2j + dy)` where `(dx, dy)` is the
//!   channel's place in the 2×2 cell. No value is interpolated, so a PSF measured on a plane is
//!   the lens's (sampled at twice the pixel pitch) and not the lens's convolved with a
//!   demosaicing filter.
//! - [`RawMethod::Bilinear`]: bilinear demosaicing to full-resolution `R`, `G`, `B`: a pixel's
//!   missing colour is the mean of the same-colour pixels in its 3×3 neighbourhood (2 or 4 of
//!   them), borders mirrored without repeating the edge pixel so the CFA phase is kept.
//!
//! Coordinates: the CFA pattern and a black-level repeat pattern are indexed from the sensor's
//! top-left pixel (rawler's convention, which shifts a DNG's active-area-relative
//! `CFAPattern` accordingly); [`RawLayout::cfa`] is the pattern at the kept area's top-left.
//!
//! Supported: single-sample 2×2 Bayer mosaics (R, G, G, B in any phase), integer or float.
//! X-Trans, CYGM, monochrome and already-demosaiced ("linear") raws are refused with a
//! one-line [`ImageError::Unsupported`] naming the file.

use super::{Image, Plane, SampleFormat, Transfer};
use crate::fsutil::{write_atomic_with, Overwrite};
use crate::image::io::ImageError;
use serde::{Deserialize, Serialize};
use std::io::BufWriter;
use std::path::Path;

/// File extensions (lower case) read as camera raw files.
pub const RAW_EXTENSIONS: &[&str] = &[
    "dng", "cr2", "cr3", "crw", "nef", "nrw", "arw", "srf", "sr2", "orf", "rw2", "raf", "pef", "srw", "3fr", "fff", "iiq", "erf", "mef", "mos", "mrw",
    "dcr", "dcs", "kdc",
];

/// Whether `path` names a camera raw file (by extension, case-insensitive).
pub fn is_raw_path(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| RAW_EXTENSIONS.iter().any(|r| r.eq_ignore_ascii_case(e)))
}

/// How a CFA mosaic becomes image planes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RawMethod {
    /// Four half-resolution planes `R`, `G1`, `G2`, `B`; nothing interpolated.
    CfaPlanes,
    /// Full-resolution `R`, `G`, `B` by bilinear interpolation.
    Bilinear,
}

/// Which raw channels an image (and a profile estimated from it) holds, and what was taken
/// from the file. Written as the optional `[raw]` table of `profile.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawLayout {
    /// The 2×2 CFA pattern at the kept area's top-left, row-major, e.g. `"RGGB"`.
    pub cfa: String,
    pub method: RawMethod,
    /// The channels, in plane order: `R, G1, G2, B` for `cfa-planes`, `R, G, B` for `bilinear`.
    pub channels: Vec<String>,
    /// Black level subtracted, raw codes, for the 2×2 cell positions row-major.
    pub black_level: [f32; 4],
    /// White (saturation) level, raw codes, mapped to 1.
    pub white_level: f32,
    /// The kept sensor area `[left, top, width, height]` in sensor pixels (full resolution).
    pub active_area: [usize; 4],
    /// Camera make and model as the file names them.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub camera: String,
}

impl RawLayout {
    /// The channel names [`RawMethod::CfaPlanes`] produces, in order.
    pub const PLANES: [&'static str; 4] = ["R", "G1", "G2", "B"];

    /// `(dx, dy)` of each of `R, G1, G2, B` in the 2×2 cell.
    ///
    /// # Errors
    /// [`ImageError::Unsupported`] (naming `path`) unless `cfa` is a Bayer pattern.
    pub fn plane_offsets(&self, path: &Path) -> Result<[(usize, usize); 4], ImageError> {
        bayer_offsets(&self.cfa).ok_or_else(|| unsupported(path, format!("CFA pattern {} is not a 2x2 Bayer pattern (R, G, G, B)", self.cfa)))
    }
}

/// The places of R, G1, G2, B in a 2×2 pattern such as `"GRBG"`.
fn bayer_offsets(cfa: &str) -> Option<[(usize, usize); 4]> {
    let c: Vec<char> = cfa.chars().collect();
    if c.len() != 4 {
        return None;
    }
    let at = |i: usize| (i % 2, i / 2);
    let r = c.iter().position(|&x| x == 'R')?;
    let b = c.iter().position(|&x| x == 'B')?;
    let g: Vec<usize> = (0..4).filter(|&i| c[i] == 'G').collect();
    if g.len() != 2 || c.iter().filter(|&&x| x == 'R').count() != 1 || c.iter().filter(|&&x| x == 'B').count() != 1 {
        return None;
    }
    Some([at(r), at(g[0]), at(g[1]), at(b)])
}

fn unsupported(path: &Path, message: impl Into<String>) -> ImageError {
    ImageError::Unsupported { path: path.into(), message: message.into() }
}

/// A decoded mosaic: active area only, black removed, 1 = white level.
#[derive(Clone, Debug)]
pub struct Mosaic {
    pub plane: Plane,
    pub layout: RawLayout,
}

/// Reads a camera raw file.
///
/// # Errors
/// [`ImageError`] naming `path`: unreadable or truncated files and decoder failures
/// ([`ImageError::Decode`], one line), layouts lensrig does not handle and builds without the
/// `raw` feature ([`ImageError::Unsupported`]).
pub fn read_raw(path: &Path, method: RawMethod) -> Result<Image, ImageError> {
    let m = decode_mosaic(path)?;
    let planes = split_planes(&m, path)?;
    match method {
        RawMethod::CfaPlanes => Ok(planes),
        RawMethod::Bilinear => demosaic_bilinear(&planes, path),
    }
}

/// The four CFA planes of a mosaic (see the module docs).
///
/// # Errors
/// [`ImageError::Unsupported`] for a non-Bayer pattern or a mosaic smaller than 2×2.
pub fn split_planes(m: &Mosaic, path: &Path) -> Result<Image, ImageError> {
    let off = m.layout.plane_offsets(path)?;
    let (w, h) = (m.plane.width / 2, m.plane.height / 2);
    if w == 0 || h == 0 {
        return Err(unsupported(path, format!("the active area {}x{} is smaller than one CFA cell", m.plane.width, m.plane.height)));
    }
    let planes = off.iter().map(|&(dx, dy)| Plane::from_fn(w, h, |x, y| m.plane.get(2 * x + dx, 2 * y + dy))).collect();
    let mut img = Image::new(planes);
    img.channels = RawLayout::PLANES.iter().map(|s| s.to_string()).collect();
    img.format = SampleFormat::U16;
    img.transfer = Transfer::Linear;
    let mut layout = m.layout.clone();
    layout.method = RawMethod::CfaPlanes;
    layout.channels = img.channels.clone();
    img.raw = Some(layout);
    Ok(img)
}

/// The full-resolution mosaic of a CFA-plane image (the inverse of [`split_planes`]).
///
/// # Errors
/// [`ImageError::Unsupported`] when `img` is not a [`RawMethod::CfaPlanes`] image.
pub fn merge_planes(img: &Image, path: &Path) -> Result<Mosaic, ImageError> {
    let layout = match &img.raw {
        Some(l) if l.method == RawMethod::CfaPlanes && img.channel_count() == 4 => l.clone(),
        _ => return Err(unsupported(path, "not a CFA-plane raw image (R, G1, G2, B)")),
    };
    let off = layout.plane_offsets(path)?;
    let (w, h) = (img.width(), img.height());
    let mut plane = Plane::new(2 * w, 2 * h);
    for (p, &(dx, dy)) in img.planes.iter().zip(&off) {
        for y in 0..h {
            for x in 0..w {
                plane.set(2 * x + dx, 2 * y + dy, p.get(x, y));
            }
        }
    }
    Ok(Mosaic { plane, layout })
}

/// Reflection without repeating the edge sample (`-1 → 1`, `n → n − 2`): keeps the CFA phase.
fn reflect101(i: isize, n: usize) -> usize {
    if n == 1 {
        return 0;
    }
    let n = n as isize;
    let period = 2 * (n - 1);
    let m = i.rem_euclid(period);
    (if m < n { m } else { period - m }) as usize
}

/// Bilinear demosaicing of a CFA-plane image to full-resolution `R`, `G`, `B` (see the module
/// docs); the result keeps the [`RawLayout`] with `method = bilinear`.
///
/// # Errors
/// [`ImageError::Unsupported`] when `img` is not a [`RawMethod::CfaPlanes`] image.
pub fn demosaic_bilinear(img: &Image, path: &Path) -> Result<Image, ImageError> {
    let m = merge_planes(img, path)?;
    let off = m.layout.plane_offsets(path)?;
    // colour index (0 R, 1 G, 2 B) per 2×2 cell position
    let mut cell = [[0usize; 2]; 2];
    for (ci, &(dx, dy)) in off.iter().enumerate() {
        cell[dy][dx] = [0, 1, 1, 2][ci];
    }
    let (w, h) = (m.plane.width, m.plane.height);
    let mut out: Vec<Plane> = (0..3).map(|_| Plane::new(w, h)).collect();
    for y in 0..h {
        for x in 0..w {
            let own = cell[y % 2][x % 2];
            let mut sum = [0.0f32; 3];
            let mut n = [0u32; 3];
            for dy in -1isize..=1 {
                for dx in -1isize..=1 {
                    let yy = reflect101(y as isize + dy, h);
                    let xx = reflect101(x as isize + dx, w);
                    let c = cell[yy % 2][xx % 2];
                    sum[c] += m.plane.get(xx, yy);
                    n[c] += 1;
                }
            }
            for c in 0..3 {
                let v = if c == own { m.plane.get(x, y) } else if n[c] > 0 { sum[c] / n[c] as f32 } else { 0.0 };
                out[c].set(x, y, v);
            }
        }
    }
    let mut rgb = Image::new(out);
    rgb.format = img.format;
    rgb.transfer = Transfer::Linear;
    let mut layout = m.layout;
    layout.method = RawMethod::Bilinear;
    layout.channels = rgb.channels.clone();
    rgb.raw = Some(layout);
    Ok(rgb)
}

/// What a command that writes a picture should write for `img`: a CFA-plane image becomes
/// bilinear RGB, anything else is returned as it is.
///
/// # Errors
/// As [`demosaic_bilinear`].
pub fn for_output(img: &Image, path: &Path) -> Result<Image, ImageError> {
    match &img.raw {
        Some(l) if l.method == RawMethod::CfaPlanes => demosaic_bilinear(img, path),
        _ => Ok(img.clone()),
    }
}

/// Writes a linear 16-bit integer TIFF (gray for one plane, RGB for three): values clipped to
/// [0, 1] and scaled to 0..65535, no transfer curve. A CFA-plane raw image is demosaiced
/// first ([`for_output`]). This is what `deblur` writes for raw input: 0 is the file's black
/// level and 65535 its white level, ready for a raw converter's linear-TIFF path.
///
/// # Errors
/// [`ImageError::Unsupported`] for other channel counts, [`ImageError::Write`] on I/O errors
/// (nothing is left behind).
pub fn write_linear_tiff16(path: &Path, img: &Image, overwrite: Overwrite) -> Result<(), ImageError> {
    use tiff::encoder::{colortype, TiffEncoder};
    let img = for_output(img, path)?;
    let (w, h) = (img.width() as u32, img.height() as u32);
    let nch = img.channel_count();
    if nch != 1 && nch != 3 {
        return Err(unsupported(path, format!("TIFF output needs 1 or 3 channels, not {nch}")));
    }
    let n = img.width() * img.height();
    let mut data = vec![0u16; n * nch];
    for (ci, p) in img.planes.iter().enumerate() {
        for (i, &v) in p.data.iter().enumerate() {
            // NaN maps to 0 (`as` saturates; NaN becomes 0), never into the file as NaN
            data[i * nch + ci] = (v.clamp(0.0, 1.0) * 65535.0).round() as u16;
        }
    }
    let werr = |e: tiff::TiffError| std::io::Error::other(e.to_string());
    write_atomic_with(path, overwrite, |f| {
        let mut enc = TiffEncoder::new(BufWriter::new(f)).map_err(werr)?;
        if nch == 1 {
            enc.write_image::<colortype::Gray16>(w, h, &data).map_err(werr)?;
        } else {
            enc.write_image::<colortype::RGB16>(w, h, &data).map_err(werr)?;
        }
        Ok(())
    })
    .map_err(|source| ImageError::Write { path: path.into(), source })
}

/// One line: decoder messages may span several.
#[cfg(feature = "raw")]
fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

#[cfg(not(feature = "raw"))]
fn decode_mosaic(path: &Path) -> Result<Mosaic, ImageError> {
    Err(unsupported(
        path,
        "camera raw files need a lensrig built with the `raw` feature (cargo install --path . --features raw); or convert the file to a linear 16-bit TIFF",
    ))
}

/// A rawler error as one line a user can act on.
#[cfg(feature = "raw")]
fn decoder_error(path: &Path, e: &rawler::RawlerError) -> ImageError {
    use rawler::RawlerError as R;
    match e {
        R::Unsupported { what, .. } if what.contains("No decoder") => unsupported(
            path,
            "not a camera raw file the decoder (rawler) recognises; a truncated or damaged header looks the same",
        ),
        R::Unsupported { what, make, model, .. } => unsupported(path, one_line(&format!("{what} (camera '{make} {model}')"))),
        R::DecoderFailed(m) if m.contains("EOF") => {
            ImageError::Decode { path: path.into(), source: "the file is truncated: the image data runs past its end".into() }
        }
        R::DecoderFailed(m) => ImageError::Decode { path: path.into(), source: format!("corrupt raw data: {}", one_line(m)).into() },
    }
}

/// Decodes the file with rawler and normalises the active area (see the module docs).
#[cfg(feature = "raw")]
fn decode_mosaic(path: &Path) -> Result<Mosaic, ImageError> {
    use rawler::rawimage::RawPhotometricInterpretation;
    let bytes = std::fs::read(path).map_err(|source| ImageError::Io { path: path.into(), source })?;
    let src = rawler::rawsource::RawSource::new_from_slice(&bytes);
    let raw = rawler::decode(&src, &rawler::decoders::RawDecodeParams::default()).map_err(|e| decoder_error(path, &e))?;
    let cfa = match &raw.photometric {
        RawPhotometricInterpretation::Cfa(c) => c.cfa.clone(),
        RawPhotometricInterpretation::LinearRaw => return Err(unsupported(path, "a linear (already demosaiced) raw; convert it to a linear TIFF")),
        RawPhotometricInterpretation::BlackIsZero => return Err(unsupported(path, "a monochrome raw without a colour filter array")),
    };
    if raw.cpp != 1 {
        return Err(unsupported(path, format!("{} samples per pixel; lensrig reads single-sample CFA mosaics", raw.cpp)));
    }
    if cfa.width != 2 || cfa.height != 2 {
        return Err(unsupported(path, format!("a {}x{} CFA pattern ({}); lensrig reads 2x2 Bayer patterns", cfa.width, cfa.height, cfa.name)));
    }
    let (sw, sh) = (raw.width, raw.height);
    let (ax, ay, aw, ah) = match raw.active_area {
        Some(r) if r.p.x + r.d.w <= sw && r.p.y + r.d.h <= sh && r.d.w > 0 && r.d.h > 0 => (r.p.x, r.p.y, r.d.w, r.d.h),
        Some(r) => return Err(ImageError::Decode { path: path.into(), source: format!("active area {r:?} lies outside the {sw}x{sh} sensor").into() }),
        None => (0, 0, sw, sh),
    };
    let (aw, ah) = (aw & !1, ah & !1);
    let letter = |c: usize| match c {
        0 => Some('R'),
        1 => Some('G'),
        2 => Some('B'),
        _ => None,
    };
    let mut pattern = String::new();
    for dy in 0..2 {
        for dx in 0..2 {
            match letter(cfa.color_at(ay + dy, ax + dx)) {
                Some(ch) => pattern.push(ch),
                None => return Err(unsupported(path, format!("CFA pattern {} has colours other than R, G, B", cfa.name))),
            }
        }
    }
    if bayer_offsets(&pattern).is_none() {
        return Err(unsupported(path, format!("CFA pattern {pattern} is not a Bayer pattern (R, G, G, B)")));
    }
    // black level per cell position of the kept area (sensor-indexed repeat pattern)
    let bl = &raw.blacklevel;
    let black_at = |x: usize, y: usize| -> f32 {
        let (bw, bh) = (bl.width.max(1), bl.height.max(1));
        let i = ((y % bh) * bw + (x % bw)) * bl.cpp.max(1);
        bl.levels.get(i).or(bl.levels.first()).map_or(0.0, |r| r.as_f32())
    };
    let black = [black_at(ax, ay), black_at(ax + 1, ay), black_at(ax, ay + 1), black_at(ax + 1, ay + 1)];
    let white = raw.whitelevel.0.first().copied().unwrap_or(u16::MAX as u32) as f32;
    if black.iter().any(|&b| !(b.is_finite() && b < white)) {
        return Err(ImageError::Decode { path: path.into(), source: format!("black level {black:?} is not below the white level {white}").into() });
    }
    let samples = raw.data.as_f32();
    if samples.len() < sw * sh {
        return Err(ImageError::Decode { path: path.into(), source: format!("{} samples for a {sw}x{sh} sensor (truncated file?)", samples.len()).into() });
    }
    let plane = Plane::from_fn(aw, ah, |x, y| {
        let b = black[(y % 2) * 2 + (x % 2)];
        let v = samples[(ay + y) * sw + ax + x];
        if v.is_finite() {
            (v - b) / (white - b)
        } else {
            0.0
        }
    });
    let camera = one_line(&format!("{} {}", raw.make, raw.model));
    let layout = RawLayout {
        cfa: pattern,
        method: RawMethod::CfaPlanes,
        channels: RawLayout::PLANES.iter().map(|s| s.to_string()).collect(),
        black_level: black,
        white_level: white,
        active_area: [ax, ay, aw, ah],
        camera,
    };
    Ok(Mosaic { plane, layout })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(cfa: &str) -> RawLayout {
        RawLayout {
            cfa: cfa.into(),
            method: RawMethod::CfaPlanes,
            channels: RawLayout::PLANES.iter().map(|s| s.to_string()).collect(),
            black_level: [0.0; 4],
            white_level: 1.0,
            active_area: [0, 0, 8, 6],
            camera: String::new(),
        }
    }

    #[test]
    fn bayer_offsets_follow_the_pattern() {
        assert_eq!(bayer_offsets("RGGB"), Some([(0, 0), (1, 0), (0, 1), (1, 1)]));
        assert_eq!(bayer_offsets("BGGR"), Some([(1, 1), (1, 0), (0, 1), (0, 0)]));
        assert_eq!(bayer_offsets("GRBG"), Some([(1, 0), (0, 0), (1, 1), (0, 1)]));
        assert_eq!(bayer_offsets("RGBE"), None);
        assert_eq!(bayer_offsets("RRGB"), None);
    }

    #[test]
    fn split_then_merge_is_the_identity_for_every_phase() {
        let p = Path::new("x.dng");
        for cfa in ["RGGB", "BGGR", "GRBG", "GBRG"] {
            let m = Mosaic { plane: Plane::from_fn(8, 6, |x, y| (x * 10 + y) as f32), layout: layout(cfa) };
            let img = split_planes(&m, p).unwrap();
            assert_eq!((img.width(), img.height(), img.channels.join(",")), (4, 3, "R,G1,G2,B".to_string()));
            // the R plane holds the mosaic's R pixels
            let (dx, dy) = bayer_offsets(cfa).unwrap()[0];
            assert_eq!(img.planes[0].get(1, 2), m.plane.get(2 + dx, 4 + dy));
            assert_eq!(merge_planes(&img, p).unwrap().plane, m.plane);
        }
    }

    #[test]
    fn bilinear_demosaic_is_exact_on_affine_colours_and_keeps_samples() {
        // every colour an affine function of position: bilinear interpolation reproduces it
        // away from the border (mirroring is exact for affine only in the interior)
        let (w, h) = (12, 10);
        let f = |c: usize, x: usize, y: usize| 0.1 + 0.01 * (c + 1) as f32 * x as f32 + 0.02 * y as f32 + 0.1 * c as f32;
        for cfa in ["RGGB", "GBRG"] {
            let off = bayer_offsets(cfa).unwrap();
            let mut cell = [[0usize; 2]; 2];
            for (ci, &(dx, dy)) in off.iter().enumerate() {
                cell[dy][dx] = [0, 1, 1, 2][ci];
            }
            let m = Mosaic { plane: Plane::from_fn(w, h, |x, y| f(cell[y % 2][x % 2], x, y)), layout: layout(cfa) };
            let rgb = demosaic_bilinear(&split_planes(&m, Path::new("a.dng")).unwrap(), Path::new("a.dng")).unwrap();
            assert_eq!(rgb.channels, vec!["R", "G", "B"]);
            assert_eq!(rgb.raw.as_ref().unwrap().method, RawMethod::Bilinear);
            for y in 1..h - 1 {
                for x in 1..w - 1 {
                    for c in 0..3 {
                        assert!((rgb.planes[c].get(x, y) - f(c, x, y)).abs() < 1e-5, "{cfa} c{c} ({x},{y})");
                    }
                }
            }
            // measured samples pass through unchanged, borders included
            for y in 0..h {
                for x in 0..w {
                    assert_eq!(rgb.planes[cell[y % 2][x % 2]].get(x, y), m.plane.get(x, y));
                }
            }
        }
    }

    #[test]
    fn reflect101_keeps_parity() {
        assert_eq!(reflect101(-1, 6), 1);
        assert_eq!(reflect101(6, 6), 4);
        assert_eq!(reflect101(3, 6), 3);
        assert_eq!(reflect101(-1, 1), 0);
    }

    #[test]
    fn linear_tiff16_round_trips_and_clips() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("out.tiff");
        let m = Mosaic { plane: Plane::from_fn(8, 6, |x, y| x as f32 * 0.1 - y as f32 * 0.05), layout: layout("RGGB") };
        let img = split_planes(&m, &p).unwrap();
        write_linear_tiff16(&p, &img, Overwrite::Never).unwrap();
        let back = crate::image::io::read_image(&p).unwrap();
        assert_eq!((back.width(), back.height(), back.channel_count(), back.format), (8, 6, 3, SampleFormat::U16));
        let rgb = demosaic_bilinear(&img, &p).unwrap();
        for (a, b) in rgb.planes.iter().zip(&back.planes) {
            for (x, y) in a.data.iter().zip(&b.data) {
                assert!((x.clamp(0.0, 1.0) - y).abs() <= 0.5 / 65535.0 + 1e-6, "{x} {y}");
            }
        }
        assert!(write_linear_tiff16(&p, &img, Overwrite::Never).is_err(), "an existing file is kept");
    }

    #[test]
    fn raw_extensions_are_recognised() {
        assert!(is_raw_path(Path::new("a/b.DNG")) && is_raw_path(Path::new("x.nef")));
        assert!(!is_raw_path(Path::new("x.tiff")) && !is_raw_path(Path::new("dng")));
    }

    #[cfg(not(feature = "raw"))]
    #[test]
    fn without_the_feature_a_raw_is_a_one_line_error_naming_the_file() {
        let e = read_raw(Path::new("capture.dng"), RawMethod::CfaPlanes).unwrap_err().to_string();
        assert!(e.contains("capture.dng") && e.contains("--features raw") && !e.contains('\n'), "{e}");
    }
}
