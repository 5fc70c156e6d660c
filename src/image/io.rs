//! Reading and writing image files.
//!
//! Reads PNG (8/16-bit, gray or RGB; palette images are expanded, an alpha channel is accepted
//! only when fully opaque) and TIFF (8/16-bit integer or 32-bit float, gray or RGB) into
//! [`Image`]s on the full-scale axis described in [`crate::image`]. Writes 16-bit PNG and
//! 32-bit float TIFF, atomically (see [`crate::fsutil`]).
//!
//! Values are read *as stored*; no transfer curve is applied here. Every image is then checked
//! for non-finite and negative samples ([`super::validate`]): [`read_image`] refuses NaN/±Inf,
//! [`read_image_with`] takes an [`InvalidPixels`] policy and returns the [`ValueReport`].
//! Writers refuse non-finite samples before anything is renamed into place.
//!
//! Decoding is bounded: the PNG and TIFF decoders run with [`MAX_DECODE_BYTES`] as their
//! allocation limit, so a decompression bomb is refused instead of exhausting memory.

use super::validate::{check_values, first_non_finite, InvalidPixels, ValueReport};
use super::{Image, Plane, SampleFormat, Transfer};
use crate::fsutil::{write_atomic_with, Overwrite};
use std::io::{BufWriter, Cursor};
use std::path::{Path, PathBuf};

/// Why an image could not be read or written. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("cannot read {path}: {source}")]
    Io { path: PathBuf, #[source] source: std::io::Error },
    #[error("cannot decode {path}: {source}")]
    Decode { path: PathBuf, #[source] source: Box<dyn std::error::Error + Send + Sync> },
    #[error("{path}: unsupported image format: {message}")]
    Unsupported { path: PathBuf, message: String },
    #[error("cannot write {path}: {source}")]
    Write { path: PathBuf, #[source] source: std::io::Error },
    #[error("{path}: {message}")]
    Mismatch { path: PathBuf, message: String },
    /// Non-finite samples in an input refused under [`InvalidPixels::Refuse`], or in an image
    /// about to be written (a bug upstream, caught before the file appears).
    #[error("{path}: {message}")]
    NonFinite { path: PathBuf, message: String },
}

/// Largest decoded sample buffer lensrig accepts, bytes (256 MiB: 16-bit RGB up to 44 Mpixel,
/// float RGB up to 22 Mpixel).
pub const MAX_DECODE_BYTES: u64 = 256 << 20;

/// An image as loaded, with what the value check found.
#[derive(Clone, Debug)]
pub struct Loaded {
    pub image: Image,
    pub values: ValueReport,
}

fn decode_err(path: &Path, e: impl std::error::Error + Send + Sync + 'static) -> ImageError {
    ImageError::Decode { path: path.into(), source: Box::new(e) }
}

/// Reads a PNG or TIFF file (chosen by content, not by extension), or a camera raw file
/// (chosen by extension, see [`super::raw`]: CFA planes `R, G1, G2, B`, levels from the file).
///
/// # Errors
/// [`ImageError`] naming `path` for unreadable files, corrupt data, and unsupported layouts
/// (alpha with transparency, 2 or more than 4 channels, sample types other than 8/16-bit
/// integer or 32-bit float).
/// Images with non-finite samples are refused ([`ImageError::NonFinite`] naming the first).
pub fn read_image(path: &Path) -> Result<Image, ImageError> {
    read_image_with(path, InvalidPixels::Refuse).map(|l| l.image)
}

/// Reads an image and applies `policy` to its non-finite samples (see [`super::validate`]).
///
/// # Errors
/// As [`read_image`]; [`ImageError::NonFinite`] only under [`InvalidPixels::Refuse`].
pub fn read_image_with(path: &Path, policy: InvalidPixels) -> Result<Loaded, ImageError> {
    let mut image = if super::raw::is_raw_path(path) {
        super::raw::read_raw(path, super::raw::RawMethod::CfaPlanes)?
    } else {
        let bytes = std::fs::read(path).map_err(|source| ImageError::Io { path: path.into(), source })?;
        decode_image(path, &bytes)?
    };
    let values = check_values(&mut image, policy).map_err(|e| ImageError::NonFinite { path: path.into(), message: e.to_string() })?;
    Ok(Loaded { image, values })
}

/// Decodes PNG or TIFF bytes (chosen by content) without any value check; `path` only names
/// the source in errors. The entry point of the fuzz targets.
///
/// # Errors
/// As [`read_image`], without the I/O and value errors.
pub fn decode_image(path: &Path, bytes: &[u8]) -> Result<Image, ImageError> {
    if bytes.starts_with(b"II*\0") || bytes.starts_with(b"MM\0*") {
        read_tiff(path, bytes)
    } else if bytes.starts_with(b"\x89PNG") {
        read_png(path, bytes)
    } else {
        Err(ImageError::Unsupported { path: path.into(), message: "not a PNG or TIFF file".into() })
    }
}

fn read_png(path: &Path, bytes: &[u8]) -> Result<Image, ImageError> {
    use image::DynamicImage as D;
    let mut reader = image::ImageReader::with_format(Cursor::new(bytes), image::ImageFormat::Png);
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_DECODE_BYTES);
    reader.limits(limits);
    let img = reader.decode().map_err(|e| decode_err(path, e))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (format, nch, has_alpha, samples): (SampleFormat, usize, bool, Vec<f32>) = match img {
        D::ImageLuma8(b) => (SampleFormat::U8, 1, false, b.into_raw().into_iter().map(f32::from).collect()),
        D::ImageLumaA8(b) => (SampleFormat::U8, 2, true, b.into_raw().into_iter().map(f32::from).collect()),
        D::ImageRgb8(b) => (SampleFormat::U8, 3, false, b.into_raw().into_iter().map(f32::from).collect()),
        D::ImageRgba8(b) => (SampleFormat::U8, 4, true, b.into_raw().into_iter().map(f32::from).collect()),
        D::ImageLuma16(b) => (SampleFormat::U16, 1, false, b.into_raw().into_iter().map(f32::from).collect()),
        D::ImageLumaA16(b) => (SampleFormat::U16, 2, true, b.into_raw().into_iter().map(f32::from).collect()),
        D::ImageRgb16(b) => (SampleFormat::U16, 3, false, b.into_raw().into_iter().map(f32::from).collect()),
        D::ImageRgba16(b) => (SampleFormat::U16, 4, true, b.into_raw().into_iter().map(f32::from).collect()),
        other => {
            return Err(ImageError::Unsupported { path: path.into(), message: format!("PNG color type {:?}", other.color()) })
        }
    };
    interleaved_to_image(path, w, h, nch, has_alpha, format, &samples)
}

fn interleaved_to_image(
    path: &Path,
    w: usize,
    h: usize,
    nch: usize,
    has_alpha: bool,
    format: SampleFormat,
    samples: &[f32],
) -> Result<Image, ImageError> {
    let full = format.full_scale();
    let color = if has_alpha { nch - 1 } else { nch };
    if has_alpha {
        let opaque = samples.chunks_exact(nch).all(|px| px[nch - 1] >= full);
        if !opaque {
            return Err(ImageError::Unsupported {
                path: path.into(),
                message: "the alpha channel has transparent pixels; save the image without alpha".into(),
            });
        }
    }
    let mut planes: Vec<Plane> = (0..color).map(|_| Plane::new(w, h)).collect();
    for (i, px) in samples.chunks_exact(nch).enumerate() {
        for c in 0..color {
            planes[c].data[i] = px[c] / full;
        }
    }
    let mut img = Image::new(planes);
    img.format = format;
    img.transfer = Transfer::Linear;
    Ok(img)
}

fn read_tiff(path: &Path, bytes: &[u8]) -> Result<Image, ImageError> {
    use tiff::decoder::{Decoder, DecodingResult};
    use tiff::ColorType;
    let err = |e: tiff::TiffError| decode_err(path, e);
    let mut limits = tiff::decoder::Limits::default();
    limits.decoding_buffer_size = MAX_DECODE_BYTES as usize;
    limits.intermediate_buffer_size = MAX_DECODE_BYTES as usize;
    let mut dec = Decoder::new(Cursor::new(bytes)).map_err(err)?.with_limits(limits);
    let (w, h) = dec.dimensions().map_err(err)?;
    let ct = dec.colortype().map_err(err)?;
    let (nch, has_alpha) = match ct {
        ColorType::Gray(_) => (1, false),
        ColorType::GrayA(_) => (2, true),
        ColorType::RGB(_) => (3, false),
        ColorType::RGBA(_) => (4, true),
        other => return Err(ImageError::Unsupported { path: path.into(), message: format!("TIFF color type {other:?}") }),
    };
    let (format, samples): (SampleFormat, Vec<f32>) = match dec.read_image().map_err(err)? {
        DecodingResult::U8(v) => (SampleFormat::U8, v.into_iter().map(f32::from).collect()),
        DecodingResult::U16(v) => (SampleFormat::U16, v.into_iter().map(f32::from).collect()),
        DecodingResult::F32(v) => (SampleFormat::F32, v),
        _ => {
            return Err(ImageError::Unsupported {
                path: path.into(),
                message: "TIFF sample type (lensrig reads 8/16-bit integer and 32-bit float)".into(),
            })
        }
    };
    if samples.len() != w as usize * h as usize * nch {
        return Err(ImageError::Decode { path: path.into(), source: "sample count does not match the dimensions".into() });
    }
    interleaved_to_image(path, w as usize, h as usize, nch, has_alpha, format, &samples)
}

/// Refuses an image with non-finite samples before it is written.
fn ensure_finite(path: &Path, img: &Image) -> Result<(), ImageError> {
    match first_non_finite(img) {
        None => Ok(()),
        Some(at) => Err(ImageError::NonFinite {
            path: path.into(),
            message: format!("refusing to write an image with a non-finite value at {at} (a bug: please report it)"),
        }),
    }
}

fn interleave(img: &Image, scale: f32) -> Vec<f32> {
    let n = img.width() * img.height();
    let c = img.channel_count();
    let mut out = vec![0.0; n * c];
    for (ci, p) in img.planes.iter().enumerate() {
        for (i, &v) in p.data.iter().enumerate() {
            out[i * c + ci] = v * scale;
        }
    }
    out
}

/// Writes a 16-bit PNG (gray for one channel, RGB for three). Values are clipped to [0, 1] and
/// rounded to 0..65535; they are written as they are (encode first if the file should hold
/// gamma-encoded values).
///
/// # Errors
/// [`ImageError::Unsupported`] for channel counts other than 1 or 3; [`ImageError::NonFinite`]
/// for a NaN or ±Inf sample; [`ImageError::Write`] when the file cannot be written (nothing is
/// left behind in either case).
pub fn write_png16(path: &Path, img: &Image, overwrite: Overwrite) -> Result<(), ImageError> {
    ensure_finite(path, img)?;
    let (w, h) = (img.width() as u32, img.height() as u32);
    let data: Vec<u16> = interleave(img, 65535.0).into_iter().map(|v| v.round().clamp(0.0, 65535.0) as u16).collect();
    let buf: Vec<u8> = {
        let mut out = Vec::new();
        let enc = image::codecs::png::PngEncoder::new(&mut out);
        let ct = match img.channel_count() {
            1 => image::ExtendedColorType::L16,
            3 => image::ExtendedColorType::Rgb16,
            n => return Err(ImageError::Unsupported { path: path.into(), message: format!("PNG output needs 1 or 3 channels, not {n}") }),
        };
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_ne_bytes()).collect();
        image::ImageEncoder::write_image(enc, &bytes, w, h, ct)
            .map_err(|e| ImageError::Write { path: path.into(), source: std::io::Error::other(e.to_string()) })?;
        out
    };
    write_atomic_with(path, overwrite, |f| std::io::Write::write_all(f, &buf))
        .map_err(|source| ImageError::Write { path: path.into(), source })
}

/// Writes an 8-bit PNG (for previews in reports; never for data).
///
/// # Errors
/// As [`write_png16`].
pub fn write_png8(path: &Path, img: &Image, overwrite: Overwrite) -> Result<(), ImageError> {
    ensure_finite(path, img)?;
    let (w, h) = (img.width() as u32, img.height() as u32);
    let data: Vec<u8> = interleave(img, 255.0).into_iter().map(|v| v.round().clamp(0.0, 255.0) as u8).collect();
    let ct = match img.channel_count() {
        1 => image::ExtendedColorType::L8,
        3 => image::ExtendedColorType::Rgb8,
        n => return Err(ImageError::Unsupported { path: path.into(), message: format!("PNG output needs 1 or 3 channels, not {n}") }),
    };
    let mut out = Vec::new();
    image::ImageEncoder::write_image(image::codecs::png::PngEncoder::new(&mut out), &data, w, h, ct)
        .map_err(|e| ImageError::Write { path: path.into(), source: std::io::Error::other(e.to_string()) })?;
    write_atomic_with(path, overwrite, |f| std::io::Write::write_all(f, &out))
        .map_err(|source| ImageError::Write { path: path.into(), source })
}

/// Writes a 32-bit float TIFF, gray for one plane, RGB for three; values are stored unclipped.
///
/// # Errors
/// [`ImageError::Unsupported`] for other channel counts, [`ImageError::NonFinite`] for a NaN or
/// ±Inf sample, [`ImageError::Write`] on I/O errors.
pub fn write_tiff_f32(path: &Path, img: &Image, overwrite: Overwrite) -> Result<(), ImageError> {
    ensure_finite(path, img)?;
    use tiff::encoder::{colortype, TiffEncoder};
    let (w, h) = (img.width() as u32, img.height() as u32);
    let data = interleave(img, 1.0);
    let werr = |e: tiff::TiffError| std::io::Error::other(e.to_string());
    let nch = img.channel_count();
    if nch != 1 && nch != 3 {
        return Err(ImageError::Unsupported { path: path.into(), message: format!("TIFF output needs 1 or 3 channels, not {nch}") });
    }
    write_atomic_with(path, overwrite, |f| {
        let mut enc = TiffEncoder::new(BufWriter::new(f)).map_err(werr)?;
        if nch == 1 {
            enc.write_image::<colortype::Gray32Float>(w, h, &data).map_err(werr)?;
        } else {
            enc.write_image::<colortype::RGB32Float>(w, h, &data).map_err(werr)?;
        }
        Ok(())
    })
    .map_err(|source| ImageError::Write { path: path.into(), source })
}

/// Reads two images that must agree in size and channel count (a wide-open/pinhole pair).
///
/// # Errors
/// Read errors, or [`ImageError::Mismatch`] naming the second file and both sizes.
pub fn read_pair(a: &Path, b: &Path) -> Result<(Image, Image), ImageError> {
    read_pair_with(a, b, InvalidPixels::Refuse).map(|(a, b)| (a.image, b.image))
}

/// [`read_pair`] with a policy for non-finite samples.
///
/// # Errors
/// As [`read_pair`] and [`read_image_with`].
pub fn read_pair_with(a: &Path, b: &Path, policy: InvalidPixels) -> Result<(Loaded, Loaded), ImageError> {
    let la = read_image_with(a, policy)?;
    let lb = read_image_with(b, policy)?;
    let (ia, ib) = (&la.image, &lb.image);
    if ia.width() != ib.width() || ia.height() != ib.height() {
        return Err(ImageError::Mismatch {
            path: b.into(),
            message: format!(
                "is {}x{} but {} is {}x{}; the pair must have the same size",
                ib.width(),
                ib.height(),
                a.display(),
                ia.width(),
                ia.height()
            ),
        });
    }
    if ia.channel_count() != ib.channel_count() {
        return Err(ImageError::Mismatch {
            path: b.into(),
            message: format!("has {} channels but {} has {}", ib.channel_count(), a.display(), ia.channel_count()),
        });
    }
    Ok((la, lb))
}

/// A note when the two captures of a pair were stored at different sample depths (8-bit and
/// 16-bit, or an integer and a float file). Both are read onto the same linear full scale, so
/// the pair is usable, but the coarser file's quantisation step `q` (full scale / largest code)
/// adds `q²/12` of variance to its noise: with 8 bits `q/√12` ≈ 0.0011 of full scale, larger
/// than the read noise of most sensors. `None` when the depths agree.
pub fn depth_note(a: &Path, ia: &Image, b: &Path, ib: &Image) -> Option<String> {
    if ia.format == ib.format {
        return None;
    }
    let bits = |f: SampleFormat| format!("{}-bit {}", f.bits(), if f == SampleFormat::F32 { "float" } else { "integer" });
    // the coarser of the two: the larger quantisation step (floats have none worth naming)
    let step = |f: SampleFormat| if f == SampleFormat::F32 { 0.0 } else { 1.0 / f.full_scale() as f64 };
    let (coarse, fmt) = if step(ia.format) >= step(ib.format) { (a, ia.format) } else { (b, ib.format) };
    Some(format!(
        "{} is {} and {} is {}: both are read on one linear full scale, but {}'s quantisation (σ = {:.1e} of full scale) is part of its noise; capture both at the same depth for the best profile",
        a.display(),
        bits(ia.format),
        b.display(),
        bits(ib.format),
        coarse.display(),
        step(fmt) / 12f64.sqrt()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rgb() -> Image {
        Image::new((0..3).map(|c| Plane::from_fn(7, 5, |x, y| ((x + 2 * y + c) % 11) as f32 / 10.0)).collect())
    }

    #[test]
    fn pairs_of_different_depth_get_a_note_naming_the_coarser_file() {
        let mut a = rgb();
        let mut b = rgb();
        a.format = SampleFormat::U8;
        b.format = SampleFormat::U16;
        let (pa, pb) = (Path::new("open.png"), Path::new("pinhole.png"));
        let note = depth_note(pa, &a, pb, &b).expect("8-bit against 16-bit is noted");
        assert!(note.contains("open.png is 8-bit integer") && note.contains("pinhole.png is 16-bit integer"), "{note}");
        // the 8-bit file is the coarser one; its quantisation σ = (1/255)/√12
        assert!(note.contains("but open.png's quantisation (σ = 1.1e-3"), "{note}");
        let swapped = depth_note(pb, &b, pa, &a).unwrap();
        assert!(swapped.contains("but open.png's quantisation"), "{swapped}");
        b.format = SampleFormat::U8;
        assert_eq!(depth_note(pa, &a, pb, &b), None);
        b.format = SampleFormat::F32;
        assert!(depth_note(pa, &a, pb, &b).unwrap().contains("pinhole.png is 32-bit float"));
    }

    #[test]
    fn png16_round_trip_is_exact_to_16_bits() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("a.png");
        let img = rgb();
        write_png16(&p, &img, Overwrite::Never).unwrap();
        let back = read_image(&p).unwrap();
        assert_eq!(back.format, SampleFormat::U16);
        assert_eq!(back.channel_count(), 3);
        for (a, b) in img.planes.iter().zip(&back.planes) {
            for (x, y) in a.data.iter().zip(&b.data) {
                assert!((x - y).abs() <= 0.5 / 65535.0 + 1e-7);
            }
        }
    }

    #[test]
    fn tiff_f32_round_trip_is_exact() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("a.tiff");
        let mut img = Image::new(vec![Plane::from_fn(9, 4, |x, y| x as f32 * 0.01 - y as f32 * 3.5)]);
        img.format = SampleFormat::F32;
        write_tiff_f32(&p, &img, Overwrite::Replace).unwrap();
        let back = read_image(&p).unwrap();
        assert_eq!(back.format, SampleFormat::F32);
        assert_eq!(back.planes[0], img.planes[0]);
    }

    #[test]
    fn errors_name_the_file() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("junk.png");
        std::fs::write(&p, b"definitely not an image").unwrap();
        let e = read_image(&p).unwrap_err().to_string();
        assert!(e.contains("junk.png"), "{e}");
        let e = read_image(&d.path().join("missing.png")).unwrap_err().to_string();
        assert!(e.contains("missing.png"), "{e}");
    }

    #[test]
    fn pair_size_mismatch_is_reported() {
        let d = tempfile::tempdir().unwrap();
        let a = d.path().join("a.png");
        let b = d.path().join("b.png");
        write_png16(&a, &rgb(), Overwrite::Never).unwrap();
        write_png16(&b, &Image::new(vec![Plane::new(3, 3); 3]), Overwrite::Never).unwrap();
        let e = read_pair(&a, &b).unwrap_err().to_string();
        assert!(e.contains("b.png") && e.contains("3x3") && e.contains("7x5"), "{e}");
    }

    #[test]
    fn eight_bit_png_reads_on_full_scale() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("g8.png");
        let buf = image::GrayImage::from_raw(2, 1, vec![0u8, 255]).unwrap();
        buf.save(&p).unwrap();
        let img = read_image(&p).unwrap();
        assert_eq!(img.format, SampleFormat::U8);
        assert_eq!(img.planes[0].data, vec![0.0, 1.0]);
    }

    /// A gray float TIFF written with the raw encoder (the lensrig writers refuse NaN).
    fn raw_f32_tiff(path: &Path, w: u32, h: u32, data: &[f32]) {
        let f = std::fs::File::create(path).unwrap();
        let mut enc = tiff::encoder::TiffEncoder::new(BufWriter::new(f)).unwrap();
        enc.write_image::<tiff::encoder::colortype::Gray32Float>(w, h, data).unwrap();
    }

    #[test]
    fn non_finite_tiff_is_refused_naming_file_and_pixel() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("hdr.tiff");
        let mut v = vec![0.25f32; 12];
        v[5] = f32::NAN;
        v[7] = f32::INFINITY;
        v[8] = -0.5;
        raw_f32_tiff(&p, 4, 3, &v);
        let e = read_image(&p).unwrap_err();
        assert!(matches!(e, ImageError::NonFinite { .. }));
        let e = e.to_string();
        assert!(e.contains("hdr.tiff") && e.contains("x=1, y=1") && e.contains("2 non-finite"), "{e}");
        let l = read_image_with(&p, InvalidPixels::Mask).unwrap();
        assert_eq!(l.values.masked, 2);
        assert_eq!(l.values.negative, 1);
        assert_eq!(l.image.planes[0].data[5], crate::image::validate::MASKED_VALUE);
        assert_eq!(l.image.planes[0].data[8], -0.5);
        let (a, _) = read_pair_with(&p, &p, InvalidPixels::Mask).unwrap();
        assert_eq!(a.values.masked, 2);
        assert!(read_pair(&p, &p).is_err());
    }

    #[test]
    fn writers_refuse_non_finite_and_leave_nothing() {
        let d = tempfile::tempdir().unwrap();
        let mut img = rgb();
        img.planes[1].data[9] = f32::NAN;
        for (name, r) in [
            ("a.png", write_png16(&d.path().join("a.png"), &img, Overwrite::Replace)),
            ("b.png", write_png8(&d.path().join("b.png"), &img, Overwrite::Replace)),
            ("c.tiff", write_tiff_f32(&d.path().join("c.tiff"), &img, Overwrite::Replace)),
        ] {
            let e = r.unwrap_err().to_string();
            assert!(e.contains(name) && e.contains("x=2, y=1") && e.contains("channel G"), "{e}");
        }
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 0);
    }

    #[test]
    fn decode_error_keeps_its_source() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("cut.png");
        let mut bytes = Vec::new();
        image::ImageEncoder::write_image(image::codecs::png::PngEncoder::new(&mut bytes), &[7u8; 64], 8, 8, image::ExtendedColorType::L8).unwrap();
        bytes.truncate(bytes.len() - 20);
        std::fs::write(&p, &bytes).unwrap();
        let e = read_image(&p).unwrap_err();
        assert!(matches!(e, ImageError::Decode { .. }));
        assert!(std::error::Error::source(&e).is_some());
    }
}
