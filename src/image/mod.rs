//! Image planes: the one in-memory representation every stage shares.
//!
//! # Conventions
//! - A [`Plane`] is one channel, row-major: `data[y * width + x]`, `x` to the right, `y` down,
//!   `(0, 0)` the top-left pixel; a pixel's value is sampled at its centre.
//! - Values are `f32` on a *full-scale* axis: 0 is black (after any black level the file
//!   carries), 1 is the largest code the file format holds (255 for 8-bit, 65535 for 16-bit).
//!   Float TIFFs are taken as they are.
//! - Whether the values are linear in light is a property of the data, recorded in
//!   [`Transfer`]. Files are read *as stored*: a PNG from a webcam holds gamma-encoded values
//!   and stays encoded until [`Transfer::decode`] is applied. The physics (blur, exposure,
//!   noise) is only valid on linear values.
//! - An [`Image`] is a list of equally sized planes with channel names (`R`,`G`,`B` or `Y`,
//!   or any names for multispectral data). Camera raw files ([`raw`]) are read as four
//!   half-resolution CFA planes `R`,`G1`,`G2`,`B` with the file's black level removed and its
//!   white level at 1; [`Image::raw`] records the layout.

pub mod filter;
pub mod io;
pub mod raw;
pub mod resample;
pub mod spectrum;
pub mod validate;

use serde::{Deserialize, Serialize};

/// One channel of an image, row-major `f32`.
#[derive(Clone, Debug, PartialEq)]
pub struct Plane {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl Plane {
    /// A plane of zeros.
    pub fn new(width: usize, height: usize) -> Self {
        Self { width, height, data: vec![0.0; width * height] }
    }

    /// A plane filled with `value`.
    pub fn filled(width: usize, height: usize, value: f32) -> Self {
        Self { width, height, data: vec![value; width * height] }
    }

    /// Wraps a row-major buffer; `None` when its length is not `width * height`.
    pub fn from_vec(width: usize, height: usize, data: Vec<f32>) -> Option<Self> {
        (data.len() == width * height).then_some(Self { width, height, data })
    }

    /// A plane whose pixel `(x, y)` is `f(x, y)`.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> f32) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Self { width, height, data }
    }

    #[inline]
    pub fn get(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    #[inline]
    pub fn set(&mut self, x: usize, y: usize, v: f32) {
        self.data[y * self.width + x] = v;
    }

    /// Pixel at signed coordinates with mirror-symmetric extension (`-1` reads `0`, i.e.
    /// half-sample symmetric, the boundary rule used for padding everywhere in lensrig).
    #[inline]
    pub fn get_reflect(&self, x: isize, y: isize) -> f32 {
        let xi = reflect_index(x, self.width);
        let yi = reflect_index(y, self.height);
        self.data[yi * self.width + xi]
    }

    /// Pixel at signed coordinates, clamped to the nearest edge pixel.
    #[inline]
    pub fn get_clamped(&self, x: isize, y: isize) -> f32 {
        let xi = x.clamp(0, self.width as isize - 1) as usize;
        let yi = y.clamp(0, self.height as isize - 1) as usize;
        self.data[yi * self.width + xi]
    }

    /// The `w × h` window whose top-left pixel is `(x0, y0)`; pixels outside are mirrored
    /// (as [`Plane::get_reflect`]). Per row the columns inside the image are one slice copy and
    /// only the mirrored columns are looked up (their indices computed once per call).
    pub fn window_reflect(&self, x0: isize, y0: isize, w: usize, h: usize) -> Plane {
        let mut out = Plane::new(w, h);
        if self.width == 0 || self.height == 0 {
            return out;
        }
        let width = self.width as isize;
        // window columns [a, b) lie inside the image (image columns x0 + a .. x0 + b)
        let a = (-x0).clamp(0, w as isize) as usize;
        let b = (width - x0).clamp(a as isize, w as isize) as usize;
        let mirrored: Vec<(usize, usize)> = (0..a).chain(b..w).map(|x| (x, reflect_index(x0 + x as isize, self.width))).collect();
        for (y, row) in out.data.chunks_exact_mut(w.max(1)).take(h).enumerate() {
            let yy = reflect_index(y0 + y as isize, self.height);
            let src = &self.data[yy * self.width..(yy + 1) * self.width];
            if b > a {
                let s = (x0 + a as isize) as usize;
                row[a..b].copy_from_slice(&src[s..s + (b - a)]);
            }
            for &(x, i) in &mirrored {
                row[x] = src[i];
            }
        }
        out
    }

    /// Bilinear sample at real coordinates (pixel centres at integers), edges clamped.
    pub fn sample_bilinear(&self, x: f32, y: f32) -> f32 {
        let x0 = x.floor();
        let y0 = y.floor();
        let fx = x - x0;
        let fy = y - y0;
        let (xi, yi) = (x0 as isize, y0 as isize);
        let a = self.get_clamped(xi, yi);
        let b = self.get_clamped(xi + 1, yi);
        let c = self.get_clamped(xi, yi + 1);
        let d = self.get_clamped(xi + 1, yi + 1);
        (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + d * fx) * fy
    }

    pub fn len(&self) -> usize {
        self.data.len()
    }

    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    pub fn sum(&self) -> f64 {
        self.data.iter().map(|&v| v as f64).sum()
    }

    /// The pixel-wise sum of equally sized planes (e.g. the channels, for registration).
    pub fn sum_of(planes: &[Plane]) -> Plane {
        let mut s = Plane::new(planes[0].width, planes[0].height);
        for p in planes {
            for (a, b) in s.data.iter_mut().zip(&p.data) {
                *a += b;
            }
        }
        s
    }

    pub fn mean(&self) -> f64 {
        if self.data.is_empty() { 0.0 } else { self.sum() / self.data.len() as f64 }
    }

    /// Variance of the values about their mean (population; 0 when empty).
    pub fn variance(&self) -> f64 {
        let m = self.mean();
        self.data.iter().map(|&v| (v as f64 - m).powi(2)).sum::<f64>() / self.data.len().max(1) as f64
    }

    pub fn max(&self) -> f32 {
        self.data.iter().copied().fold(f32::NEG_INFINITY, f32::max)
    }

    pub fn min(&self) -> f32 {
        self.data.iter().copied().fold(f32::INFINITY, f32::min)
    }

    /// Multiplies every pixel by `k`.
    pub fn scale(&mut self, k: f32) {
        self.data.iter_mut().for_each(|v| *v *= k);
    }

    /// The same plane with `f` applied to every pixel.
    pub fn map(&self, f: impl Fn(f32) -> f32) -> Plane {
        Plane { width: self.width, height: self.height, data: self.data.iter().map(|&v| f(v)).collect() }
    }

    /// Copies `src` into this plane with its top-left pixel at `(x0, y0)`; parts that fall
    /// outside are dropped.
    pub fn paste(&mut self, src: &Plane, x0: isize, y0: isize) {
        for y in 0..src.height {
            let yy = y0 + y as isize;
            if yy < 0 || yy as usize >= self.height {
                continue;
            }
            for x in 0..src.width {
                let xx = x0 + x as isize;
                if xx < 0 || xx as usize >= self.width {
                    continue;
                }
                self.data[yy as usize * self.width + xx as usize] = src.data[y * src.width + x];
            }
        }
    }
}

/// Half-sample symmetric reflection of an index into `0..n` (`-1 -> 0`, `n -> n-1`).
#[inline]
pub fn reflect_index(i: isize, n: usize) -> usize {
    let n = n as isize;
    if n == 1 {
        return 0;
    }
    let period = 2 * n;
    let mut m = i.rem_euclid(period);
    if m >= n {
        m = period - 1 - m;
    }
    m as usize
}

/// How stored values relate to light.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Transfer {
    /// Values are proportional to the light collected (raw sensors, machine-vision cameras).
    #[default]
    Linear,
    /// The IEC 61966-2-1 sRGB curve (webcams' YUYV/MJPG, most PNGs from cameras).
    Srgb,
}

impl Transfer {
    /// Encoded value -> linear value.
    pub fn decode(self, v: f32) -> f32 {
        match self {
            Transfer::Linear => v,
            Transfer::Srgb => srgb_decode(v),
        }
    }

    /// Linear value -> encoded value.
    pub fn encode(self, v: f32) -> f32 {
        match self {
            Transfer::Linear => v,
            Transfer::Srgb => srgb_encode(v),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Transfer::Linear => "linear",
            Transfer::Srgb => "srgb",
        }
    }
}

impl std::str::FromStr for Transfer {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "linear" => Ok(Transfer::Linear),
            "srgb" => Ok(Transfer::Srgb),
            other => Err(format!("unknown transfer function '{other}' (expected linear or srgb)")),
        }
    }
}

/// sRGB decoding (IEC 61966-2-1), odd-symmetric for negative inputs.
pub fn srgb_decode(v: f32) -> f32 {
    let a = v.abs();
    let l = if a <= 0.04045 { a / 12.92 } else { ((a + 0.055) / 1.055).powf(2.4) };
    l.copysign(v)
}

/// sRGB encoding (IEC 61966-2-1), odd-symmetric for negative inputs.
pub fn srgb_encode(v: f32) -> f32 {
    let a = v.abs();
    let e = if a <= 0.003_130_8 { a * 12.92 } else { 1.055 * a.powf(1.0 / 2.4) - 0.055 };
    e.copysign(v)
}

/// The storage a file used (and the one predictions are written back in).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum SampleFormat {
    U8,
    #[default]
    U16,
    F32,
}

impl SampleFormat {
    /// The largest code, i.e. the value stored for full scale 1.0.
    pub fn full_scale(self) -> f32 {
        match self {
            SampleFormat::U8 => 255.0,
            SampleFormat::U16 => 65535.0,
            SampleFormat::F32 => 1.0,
        }
    }
    pub fn bits(self) -> u32 {
        match self {
            SampleFormat::U8 => 8,
            SampleFormat::U16 => 16,
            SampleFormat::F32 => 32,
        }
    }
}

/// Equally sized planes with channel names and the encoding they came in.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub planes: Vec<Plane>,
    pub channels: Vec<String>,
    pub format: SampleFormat,
    pub transfer: Transfer,
    /// Set for images read from a camera raw file: which raw channels the planes hold and
    /// the levels taken from the file ([`raw`]).
    pub raw: Option<raw::RawLayout>,
}

impl Image {
    /// An image from planes; channel names follow the count (`Y`, `RGB`, or `C0..`).
    ///
    /// # Panics
    /// When the planes differ in size (a programming error, not a user input).
    pub fn new(planes: Vec<Plane>) -> Self {
        if let Some(p0) = planes.first() {
            assert!(planes.iter().all(|p| p.width == p0.width && p.height == p0.height), "planes differ in size");
        }
        let channels = default_channel_names(planes.len());
        Self { planes, channels, format: SampleFormat::U16, transfer: Transfer::Linear, raw: None }
    }

    pub fn width(&self) -> usize {
        self.planes.first().map_or(0, |p| p.width)
    }

    pub fn height(&self) -> usize {
        self.planes.first().map_or(0, |p| p.height)
    }

    pub fn channel_count(&self) -> usize {
        self.planes.len()
    }

    /// Decodes every plane to linear values (a no-op for linear data).
    pub fn to_linear(&self) -> Image {
        let mut out = self.clone();
        if self.transfer != Transfer::Linear {
            for p in &mut out.planes {
                *p = p.map(|v| self.transfer.decode(v));
            }
            out.transfer = Transfer::Linear;
        }
        out
    }

    /// Encodes linear planes with `transfer`.
    pub fn encoded(&self, transfer: Transfer) -> Image {
        let mut out = self.to_linear();
        if transfer != Transfer::Linear {
            for p in &mut out.planes {
                *p = p.map(|v| transfer.encode(v));
            }
        }
        out.transfer = transfer;
        out
    }
}

/// Row `y` of a `width`-wide pixel mask (`None` stays `None`: every pixel).
pub fn mask_row(mask: Option<&[bool]>, y: usize, width: usize) -> Option<&[bool]> {
    mask.map(|m| &m[y * width..(y + 1) * width])
}

/// Runs `f(x, &mut row[x])` on the pixels of one image row that `need` marks (every pixel when
/// `None`), leaving the others as they are. The one loop of the masked computations that
/// produce only the pixels a caller reads (a subset fit's planes, blends and warps;
/// `diagnose::fit`, [`crate::optics::psf_grid`], [`resample`]).
pub fn for_needed<T>(row: &mut [T], need: Option<&[bool]>, mut f: impl FnMut(usize, &mut T)) {
    match need {
        None => row.iter_mut().enumerate().for_each(|(x, v)| f(x, v)),
        Some(n) => {
            debug_assert_eq!(n.len(), row.len(), "mask row length");
            row.iter_mut().zip(n).enumerate().filter(|(_, (_, &b))| b).for_each(|(x, (v, _))| f(x, v));
        }
    }
}

/// `Y` for one channel, `R,G,B` for three, `R,G,B,A`-free `C0..Cn` otherwise.
pub fn default_channel_names(n: usize) -> Vec<String> {
    match n {
        1 => vec!["Y".into()],
        3 => vec!["R".into(), "G".into(), "B".into()],
        _ => (0..n).map(|i| format!("C{i}")).collect(),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn for_needed_visits_the_marked_pixels_only_and_leaves_the_rest() {
        let need = [false, true, false, true, true];
        let mut row = [9.0f32; 5];
        let mut seen = Vec::new();
        super::for_needed(&mut row, Some(&need), |x, v| {
            seen.push(x);
            *v = x as f32;
        });
        assert_eq!(seen, vec![1, 3, 4]);
        assert_eq!(row, [9.0, 1.0, 9.0, 3.0, 4.0]);
        // no mask: every pixel, in order
        let mut all = [0.0f32; 3];
        super::for_needed(&mut all, None, |x, v| *v = 10.0 + x as f32);
        assert_eq!(all, [10.0, 11.0, 12.0]);
        // an empty row is not visited at all
        let mut calls = 0;
        super::for_needed(&mut [1.0f32; 4], Some(&[false; 4]), |_, _| calls += 1);
        assert_eq!(calls, 0);
        // the mask's rows
        let mask = [true, false, false, true, true, false];
        assert_eq!(super::mask_row(Some(&mask), 1, 3), Some(&mask[3..6]));
        assert_eq!(super::mask_row(None, 1, 3), None);
    }

    use super::*;

    /// The window equals the per-pixel mirrored lookup for windows inside, across every
    /// edge, wider than the image and wholly outside it.
    #[test]
    fn window_reflect_matches_the_mirrored_lookup() {
        let p = Plane::from_fn(13, 9, |x, y| (y * 13 + x) as f32);
        for &(x0, y0, w, h) in &[(2isize, 1isize, 5usize, 4usize), (-3, -2, 8, 6), (9, 6, 7, 5), (-4, -3, 22, 16), (15, 11, 4, 3), (-20, 4, 6, 2), (0, 0, 13, 9), (5, 3, 0, 2)] {
            let got = p.window_reflect(x0, y0, w, h);
            assert_eq!((got.width, got.height), (w, h));
            for y in 0..h {
                for x in 0..w {
                    assert_eq!(got.get(x, y), p.get_reflect(x0 + x as isize, y0 + y as isize), "window ({x0}, {y0}, {w}, {h}) at ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn reflect_index_is_half_sample_symmetric() {
        let got: Vec<usize> = (-4..8).map(|i| reflect_index(i, 4)).collect();
        assert_eq!(got, vec![3, 2, 1, 0, 0, 1, 2, 3, 3, 2, 1, 0]);
    }

    #[test]
    fn srgb_round_trip() {
        for i in 0..=100 {
            let v = i as f32 / 100.0;
            assert!((srgb_decode(srgb_encode(v)) - v).abs() < 1e-5);
        }
        assert!((srgb_encode(0.5) - 0.735_356_6).abs() < 1e-5);
    }

    #[test]
    fn window_reflect_matches_get_reflect() {
        let p = Plane::from_fn(5, 4, |x, y| (x * 10 + y) as f32);
        let w = p.window_reflect(-2, -1, 9, 6);
        for y in 0..6 {
            for x in 0..9 {
                assert_eq!(w.get(x, y), p.get_reflect(x as isize - 2, y as isize - 1));
            }
        }
    }
}
