//! Pure decoders from raw V4L2 buffers to [`Image`] planes on the full-scale axis.
//!
//! # Conventions
//! - Full scale: 8-bit formats divide by 255, 16-bit by 65535 (`Y16 ` and 16-bit Bayer are
//!   taken as filling 16 bits; sensors with 10/12 bits in 16-bit containers therefore top out
//!   below 1.0).
//! - Transfer: `YUYV`, `MJPG` and `RGB3` come from webcam pipelines and are marked
//!   [`Transfer::Srgb`] (the values stay encoded); `GREY`, `Y16 ` and raw Bayer are
//!   [`Transfer::Linear`].
//! - `YUYV` uses BT.601 **limited range** (`Y' = (Y − 16)/219`, chroma `(C − 128)/224`), the
//!   range UVC cameras send. Values outside `[0, 1]` (foot/headroom) are kept, not clipped.
//!   `MJPG` is JFIF full range.
//! - Bayer: bilinear demosaic; each missing colour is the mean of the same-colour pixels in
//!   the 3×3 neighbourhood that lie inside the image.
//! - `stride` is bytes per line (`0` = tightly packed).

use crate::image::{Image, Plane, SampleFormat, Transfer};

use super::FourCc;

/// What to produce from colour sources.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColorMode {
    /// One `Y` plane (luma for YUYV/MJPG/RGB3, green-weighted luma for Bayer is *not*
    /// computed: Bayer always gives RGB).
    Luma,
    /// `R,G,B` planes.
    Rgb,
}

/// Pixel formats [`decode`] understands.
pub const SUPPORTED: [FourCc; 13] = [
    FourCc(*b"YUYV"),
    FourCc(*b"MJPG"),
    FourCc(*b"RGB3"),
    FourCc(*b"GREY"),
    FourCc(*b"Y16 "),
    FourCc(*b"BA81"),
    FourCc(*b"GBRG"),
    FourCc(*b"GRBG"),
    FourCc(*b"RGGB"),
    FourCc(*b"BYR2"),
    FourCc(*b"GB16"),
    FourCc(*b"GR16"),
    FourCc(*b"RG16"),
];

/// Why a buffer could not be decoded.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    #[error("pixel format {0} is not supported")]
    Unsupported(FourCc),
    #[error("{fourcc} {width}x{height}: buffer holds {got} bytes, needs {needed}")]
    ShortBuffer { fourcc: FourCc, width: usize, height: usize, needed: usize, got: usize },
    #[error("MJPG frame does not decode")]
    Jpeg(#[source] image::ImageError),
    #[error("MJPG frame is {got_w}x{got_h}, the format says {width}x{height}")]
    SizeMismatch { width: usize, height: usize, got_w: usize, got_h: usize },
}

/// The transfer function of data in `fourcc`, `None` when unsupported.
pub fn transfer_of(fourcc: FourCc) -> Option<Transfer> {
    match &fourcc.0 {
        b"YUYV" | b"MJPG" | b"RGB3" => Some(Transfer::Srgb),
        _ if SUPPORTED.contains(&fourcc) => Some(Transfer::Linear),
        _ => None,
    }
}

/// Bayer layout: colour (0 R, 1 G, 2 B) of the 2×2 cell, row-major.
fn bayer_pattern(fourcc: FourCc) -> Option<([usize; 4], bool)> {
    let (p, wide) = match &fourcc.0 {
        b"BA81" => ([2, 1, 1, 0], false),
        b"GBRG" => ([1, 2, 0, 1], false),
        b"GRBG" => ([1, 0, 2, 1], false),
        b"RGGB" => ([0, 1, 1, 2], false),
        b"BYR2" => ([2, 1, 1, 0], true),
        b"GB16" => ([1, 2, 0, 1], true),
        b"GR16" => ([1, 0, 2, 1], true),
        b"RG16" => ([0, 1, 1, 2], true),
        _ => return None,
    };
    Some((p, wide))
}

/// Decodes one frame.
///
/// # Errors
/// [`DecodeError::Unsupported`] for other FourCCs, [`DecodeError::ShortBuffer`] when `data` is
/// smaller than the format needs, JPEG errors for `MJPG`.
pub fn decode(fourcc: FourCc, width: usize, height: usize, stride: usize, data: &[u8], mode: ColorMode) -> Result<Image, DecodeError> {
    let bpp = match &fourcc.0 {
        b"YUYV" | b"Y16 " => 2,
        b"RGB3" => 3,
        b"GREY" => 1,
        b"MJPG" => 0,
        _ => match bayer_pattern(fourcc) {
            Some((_, true)) => 2,
            Some((_, false)) => 1,
            None => return Err(DecodeError::Unsupported(fourcc)),
        },
    };
    if bpp == 0 {
        return decode_mjpg(width, height, data, mode);
    }
    let stride = if stride == 0 { width * bpp } else { stride };
    let needed = if height == 0 { 0 } else { stride * (height - 1) + width * bpp };
    if data.len() < needed || stride < width * bpp {
        return Err(DecodeError::ShortBuffer { fourcc, width, height, needed: needed.max(width * bpp * height), got: data.len() });
    }
    let row = |y: usize| &data[y * stride..y * stride + width * bpp];
    let (planes, transfer, format) = match &fourcc.0 {
        b"GREY" => (vec![Plane::from_fn(width, height, |x, y| row(y)[x] as f32 / 255.0)], Transfer::Linear, SampleFormat::U8),
        b"Y16 " => (
            vec![Plane::from_fn(width, height, |x, y| u16::from_le_bytes([row(y)[2 * x], row(y)[2 * x + 1]]) as f32 / 65535.0)],
            Transfer::Linear,
            SampleFormat::U16,
        ),
        b"RGB3" => {
            let rgb: Vec<Plane> = (0..3).map(|c| Plane::from_fn(width, height, |x, y| row(y)[3 * x + c] as f32 / 255.0)).collect();
            let planes = match mode {
                ColorMode::Rgb => rgb,
                ColorMode::Luma => vec![luma(&rgb)],
            };
            (planes, Transfer::Srgb, SampleFormat::U8)
        }
        b"YUYV" => (decode_yuyv(width, height, &row, mode), Transfer::Srgb, SampleFormat::U8),
        _ => {
            let Some((pattern, wide)) = bayer_pattern(fourcc) else { return Err(DecodeError::Unsupported(fourcc)) };
            let raw = if wide {
                Plane::from_fn(width, height, |x, y| u16::from_le_bytes([row(y)[2 * x], row(y)[2 * x + 1]]) as f32 / 65535.0)
            } else {
                Plane::from_fn(width, height, |x, y| row(y)[x] as f32 / 255.0)
            };
            (demosaic_bilinear(&raw, pattern), Transfer::Linear, if wide { SampleFormat::U16 } else { SampleFormat::U8 })
        }
    };
    let mut img = Image::new(planes);
    img.transfer = transfer;
    img.format = format;
    Ok(img)
}

fn luma(rgb: &[Plane]) -> Plane {
    // BT.601 luma weights on the encoded values (what a camera's Y channel holds).
    let (r, g, b) = (&rgb[0], &rgb[1], &rgb[2]);
    Plane::from_fn(r.width, r.height, |x, y| 0.299 * r.get(x, y) + 0.587 * g.get(x, y) + 0.114 * b.get(x, y))
}

fn decode_yuyv<'a>(width: usize, height: usize, row: &dyn Fn(usize) -> &'a [u8], mode: ColorMode) -> Vec<Plane> {
    let yv = |x: usize, y: usize| (row(y)[2 * x] as f32 - 16.0) / 219.0;
    // Each 4-byte macropixel Y0 U Y1 V covers pixels 2k and 2k+1.
    let chroma = |x: usize, y: usize| {
        let base = 4 * (x / 2);
        let r = row(y);
        // A trailing odd pixel has no V byte of its own: reuse the last complete pair's.
        let (u, v) = if base + 3 < r.len() { (r[base + 1], r[base + 3]) } else { (r[base.saturating_sub(3)], r[base.saturating_sub(1)]) };
        ((u as f32 - 128.0) / 224.0, (v as f32 - 128.0) / 224.0)
    };
    match mode {
        ColorMode::Luma => vec![Plane::from_fn(width, height, yv)],
        ColorMode::Rgb => {
            let mut planes = vec![Plane::new(width, height), Plane::new(width, height), Plane::new(width, height)];
            for y in 0..height {
                for x in 0..width {
                    let l = yv(x, y);
                    let (pb, pr) = chroma(x, y);
                    // BT.601: R = Y' + 1.402 Pr, G = Y' − 0.344136 Pb − 0.714136 Pr, B = Y' + 1.772 Pb
                    planes[0].set(x, y, l + 1.402 * pr);
                    planes[1].set(x, y, l - 0.344_136 * pb - 0.714_136 * pr);
                    planes[2].set(x, y, l + 1.772 * pb);
                }
            }
            planes
        }
    }
}

fn decode_mjpg(width: usize, height: usize, data: &[u8], mode: ColorMode) -> Result<Image, DecodeError> {
    let img = image::load_from_memory_with_format(data, image::ImageFormat::Jpeg).map_err(DecodeError::Jpeg)?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    if (w, h) != (width, height) {
        return Err(DecodeError::SizeMismatch { width, height, got_w: w, got_h: h });
    }
    let planes = match mode {
        ColorMode::Luma => {
            let l = img.to_luma8();
            vec![Plane::from_fn(w, h, |x, y| l.get_pixel(x as u32, y as u32)[0] as f32 / 255.0)]
        }
        ColorMode::Rgb => {
            let rgb = img.to_rgb8();
            (0..3).map(|c| Plane::from_fn(w, h, |x, y| rgb.get_pixel(x as u32, y as u32)[c] as f32 / 255.0)).collect()
        }
    };
    let mut out = Image::new(planes);
    out.transfer = Transfer::Srgb;
    out.format = SampleFormat::U8;
    Ok(out)
}

/// Bilinear demosaic of a CFA plane; `pattern` is the colour of the 2×2 cell (0 R, 1 G, 2 B).
pub fn demosaic_bilinear(raw: &Plane, pattern: [usize; 4]) -> Vec<Plane> {
    let (w, h) = (raw.width, raw.height);
    let color = |x: usize, y: usize| pattern[(y % 2) * 2 + (x % 2)];
    let mut out = vec![Plane::new(w, h), Plane::new(w, h), Plane::new(w, h)];
    for y in 0..h {
        for x in 0..w {
            let own = color(x, y);
            let mut sum = [0.0f32; 3];
            let mut n = [0u32; 3];
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    let c = color(xx, yy);
                    sum[c] += raw.get(xx, yy);
                    n[c] += 1;
                }
            }
            for c in 0..3 {
                let v = if c == own { raw.get(x, y) } else if n[c] > 0 { sum[c] / n[c] as f32 } else { 0.0 };
                out[c].set(x, y, v);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f32, b: f32) -> bool {
        (a - b).abs() < 1e-6
    }

    #[test]
    fn grey_and_y16_with_stride() {
        let data = [0u8, 255, 51, 9, 102, 204, 7, 9]; // stride 4, width 3, last byte of each row padding
        let img = decode(FourCc(*b"GREY"), 3, 2, 4, &data, ColorMode::Luma).unwrap();
        assert_eq!(img.planes[0].data, vec![0.0, 1.0, 0.2, 0.4, 0.8, 7.0 / 255.0]);
        assert_eq!(img.transfer, Transfer::Linear);
        let y16 = [0x00, 0x00, 0xFF, 0xFF, 0x01, 0x80];
        let img = decode(FourCc(*b"Y16 "), 3, 1, 0, &y16, ColorMode::Luma).unwrap();
        assert_eq!(img.planes[0].data, vec![0.0, 1.0, 0x8001 as f32 / 65535.0]);
        assert_eq!(img.format, SampleFormat::U16);
    }

    #[test]
    fn rgb3_planes_and_luma() {
        let data = [255u8, 0, 0, 0, 255, 0];
        let img = decode(FourCc(*b"RGB3"), 2, 1, 0, &data, ColorMode::Rgb).unwrap();
        assert_eq!(img.channels, vec!["R", "G", "B"]);
        assert_eq!(img.planes[0].data, vec![1.0, 0.0]);
        assert_eq!(img.planes[1].data, vec![0.0, 1.0]);
        assert_eq!(img.transfer, Transfer::Srgb);
        let l = decode(FourCc(*b"RGB3"), 2, 1, 0, &data, ColorMode::Luma).unwrap();
        assert!(close(l.planes[0].data[0], 0.299) && close(l.planes[0].data[1], 0.587));
    }

    #[test]
    fn yuyv_limited_range_bt601() {
        // Pixel pair 1: black/white with neutral chroma; pair 2: pure red (Y=81, U=90, V=240).
        let data = [16u8, 128, 235, 128, 81, 90, 81, 240];
        let y = decode(FourCc(*b"YUYV"), 4, 1, 0, &data, ColorMode::Luma).unwrap();
        assert_eq!(y.planes.len(), 1);
        assert!(close(y.planes[0].data[0], 0.0) && close(y.planes[0].data[1], 1.0));
        let rgb = decode(FourCc(*b"YUYV"), 4, 1, 0, &data, ColorMode::Rgb).unwrap();
        assert_eq!(rgb.transfer, Transfer::Srgb);
        for c in 0..3 {
            assert!(close(rgb.planes[c].data[0], 0.0) && close(rgb.planes[c].data[1], 1.0));
        }
        let (r, g, b) = (rgb.planes[0].data[2], rgb.planes[1].data[2], rgb.planes[2].data[2]);
        assert!((r - 1.0).abs() < 0.01 && g.abs() < 0.01 && b.abs() < 0.01, "{r} {g} {b}");
    }

    #[test]
    fn bayer_constant_colour_and_interpolation() {
        // RGGB 4×4 with R = 0.2, G = 0.6, B = 1.0 everywhere: every output pixel is (0.2, 0.6, 1.0).
        let code = |x: usize, y: usize| match (y % 2, x % 2) {
            (0, 0) => 51u8,
            (1, 1) => 255,
            _ => 153,
        };
        let data: Vec<u8> = (0..16).map(|i| code(i % 4, i / 4)).collect();
        let img = decode(FourCc(*b"RGGB"), 4, 4, 0, &data, ColorMode::Rgb).unwrap();
        for (c, want) in [0.2f32, 0.6, 1.0].into_iter().enumerate() {
            assert!(img.planes[c].data.iter().all(|&v| close(v, want)), "channel {c}: {:?}", img.planes[c].data);
        }
        // BGGR 16-bit: G at the B site (0,0) is the mean of its in-image G neighbours (1,0),(0,1).
        let mut raw = vec![0u8; 2 * 9];
        let set = |raw: &mut Vec<u8>, x: usize, y: usize, v: u16| raw[2 * (y * 3 + x)..2 * (y * 3 + x) + 2].copy_from_slice(&v.to_le_bytes());
        set(&mut raw, 1, 0, 1000);
        set(&mut raw, 0, 1, 3000);
        set(&mut raw, 1, 1, 6000); // R site
        let img = decode(FourCc(*b"BYR2"), 3, 3, 0, &raw, ColorMode::Rgb).unwrap();
        assert!(close(img.planes[1].get(0, 0), 2000.0 / 65535.0));
        assert!(close(img.planes[0].get(0, 0), 6000.0 / 65535.0)); // R: the one diagonal neighbour
        assert!(close(img.planes[0].get(1, 1), 6000.0 / 65535.0));
        assert_eq!(img.transfer, Transfer::Linear);
        for f in [*b"BA81", *b"GBRG", *b"GRBG", *b"GB16", *b"GR16", *b"RG16"] {
            let bytes = if f[2].is_ascii_digit() { 2 } else { 1 };
            assert!(decode(FourCc(f), 2, 2, 0, &vec![7u8; 4 * bytes], ColorMode::Rgb).is_ok());
        }
    }

    #[test]
    fn every_bayer_layout_puts_each_colour_where_its_name_says() {
        // V4L2 names: BA81 = SBGGR8, BYR2 = SBGGR16, the rest spell their 2×2 cell.
        let (r, g, b) = (0.2f32, 0.6f32, 1.0f32);
        for (fourcc, cell) in [("BA81", "BGGR"), ("GBRG", "GBRG"), ("GRBG", "GRBG"), ("RGGB", "RGGB"), ("BYR2", "BGGR"), ("GB16", "GBRG"), ("GR16", "GRBG"), ("RG16", "RGGB")] {
            let wide = matches!(fourcc, "BYR2" | "GB16" | "GR16" | "RG16");
            let cell = cell.as_bytes();
            let (w, h) = (6, 4);
            let mut data = Vec::new();
            for y in 0..h {
                for x in 0..w {
                    let v = match cell[(y % 2) * 2 + x % 2] {
                        b'R' => r,
                        b'G' => g,
                        _ => b,
                    };
                    if wide {
                        data.extend_from_slice(&((v * 65535.0).round() as u16).to_le_bytes());
                    } else {
                        data.push((v * 255.0).round() as u8);
                    }
                }
            }
            let img = decode(FourCc::from_str_padded(fourcc), w, h, 0, &data, ColorMode::Rgb).unwrap();
            assert_eq!(img.format, if wide { SampleFormat::U16 } else { SampleFormat::U8 }, "{fourcc}");
            assert_eq!(img.transfer, Transfer::Linear);
            for (c, want) in [r, g, b].into_iter().enumerate() {
                assert!(img.planes[c].data.iter().all(|&v| (v - want).abs() < 1e-4), "{fourcc} channel {c}: {:?}", img.planes[c].data);
            }
            // every supported format is in the table the camera checks against
            assert!(SUPPORTED.contains(&FourCc::from_str_padded(fourcc)));
        }
    }

    #[test]
    fn mjpg_round_trip() {
        let mut buf = std::io::Cursor::new(Vec::new());
        let src = image::GrayImage::from_pixel(8, 8, image::Luma([200u8]));
        src.write_to(&mut buf, image::ImageFormat::Jpeg).unwrap();
        let img = decode(FourCc(*b"MJPG"), 8, 8, 0, buf.get_ref(), ColorMode::Luma).unwrap();
        assert!(img.planes[0].data.iter().all(|&v| (v - 200.0 / 255.0).abs() < 2.0 / 255.0));
        assert_eq!(img.transfer, Transfer::Srgb);
        assert!(matches!(decode(FourCc(*b"MJPG"), 4, 8, 0, buf.get_ref(), ColorMode::Luma), Err(DecodeError::SizeMismatch { .. })));
        assert!(matches!(decode(FourCc(*b"MJPG"), 8, 8, 0, b"not a jpeg", ColorMode::Luma), Err(DecodeError::Jpeg(_))));
    }

    #[test]
    fn errors() {
        assert!(matches!(decode(FourCc(*b"NV12"), 2, 2, 0, &[0; 6], ColorMode::Luma), Err(DecodeError::Unsupported(_))));
        let e = decode(FourCc(*b"Y16 "), 4, 4, 0, &[0; 31], ColorMode::Luma).unwrap_err();
        assert!(matches!(e, DecodeError::ShortBuffer { needed: 32, got: 31, .. }), "{e}");
        assert_eq!(transfer_of(FourCc(*b"YUYV")), Some(Transfer::Srgb));
        assert_eq!(transfer_of(FourCc(*b"Y16 ")), Some(Transfer::Linear));
        assert_eq!(transfer_of(FourCc(*b"H264")), None);
    }
}
