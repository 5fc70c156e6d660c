//! Value checks at the image boundary: non-finite and negative samples.
//!
//! A float TIFF from a camera SDK or an HDR merge can carry NaN or ±Inf (dead pixels, a
//! division by zero in a flat-field). Left in, one NaN spreads through every FFT and the
//! result is an all-NaN profile or image. So every image a command reads goes through
//! [`check_values`]:
//! - non-finite samples are counted (NaN and ±Inf separately) with the first one's location;
//!   under [`InvalidPixels::Refuse`] (the default) the image is refused with an error naming the
//!   file and that pixel; under [`InvalidPixels::Mask`] each such sample is replaced by
//!   [`MASKED_VALUE`] (full scale, what a clipped pixel reads), so the saturation masks the data
//!   terms already have (estimate, deblur, diagnose) drop it, and the count is reported;
//! - negative samples are legal noise around a black level in linear data; they are counted,
//!   and [`ValueReport::warning`] speaks up when more than [`NEGATIVE_WARN_FRACTION`] of the
//!   samples are negative (a wrong black level or a signed/unsigned mix-up).
//!
//! Locations are `(x, y)` pixel coordinates (`x` right, `y` down, `(0, 0)` top-left) plus the
//! channel name. Counts are of samples (one per pixel and channel).

use super::Image;
use std::fmt;
use std::path::Path;

/// What to do with non-finite samples (NaN, ±Inf) in an input image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum InvalidPixels {
    /// Refuse the image, naming the file and the first bad pixel.
    #[default]
    Refuse,
    /// Replace them with [`MASKED_VALUE`] so the saturation masks exclude them from the data
    /// term, and report how many there were.
    Mask,
}

/// The value a masked sample gets: full scale, at or above every saturation level lensrig uses
/// (0.995 of full scale for estimation, 0.99 linear for deblurring), so the existing
/// saturation masks exclude it from every data term.
pub const MASKED_VALUE: f32 = 1.0;

/// More than this fraction of negative samples is reported as a warning.
pub const NEGATIVE_WARN_FRACTION: f64 = 0.01;

/// Where a sample is: pixel `(x, y)` in channel `channel`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PixelLocation {
    pub x: usize,
    pub y: usize,
    pub channel: String,
}

impl fmt::Display for PixelLocation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "pixel (x={}, y={}) channel {}", self.x, self.y, self.channel)
    }
}

/// What [`scan`] found in an image.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ValueReport {
    /// Samples scanned (pixels × channels).
    pub samples: usize,
    pub nan: usize,
    /// +Inf and −Inf.
    pub infinite: usize,
    pub first_non_finite: Option<PixelLocation>,
    pub negative: usize,
    pub first_negative: Option<PixelLocation>,
    /// Samples replaced by [`MASKED_VALUE`] (0 unless the policy was [`InvalidPixels::Mask`]).
    pub masked: usize,
    /// The replaced samples as `(channel, y · width + x)`, for stages whose saturation test
    /// runs after a shift of the values (a black level) and must re-mark them.
    pub masked_samples: Vec<(usize, usize)>,
}

impl ValueReport {
    /// NaN plus infinite samples.
    pub fn non_finite(&self) -> usize {
        self.nan + self.infinite
    }

    /// Fraction of the samples that are negative (0 for an empty image).
    pub fn negative_fraction(&self) -> f64 {
        if self.samples == 0 {
            0.0
        } else {
            self.negative as f64 / self.samples as f64
        }
    }

    /// One-line notes for the user about `path`: how many samples were masked, and a warning
    /// when more than [`NEGATIVE_WARN_FRACTION`] of the samples are negative. Empty when there
    /// is nothing to say.
    pub fn notes(&self, path: &Path) -> Vec<String> {
        let mut out = Vec::new();
        if self.masked > 0 {
            let at = self.first_non_finite.as_ref().map(|l| format!(", first at {l}")).unwrap_or_default();
            out.push(format!(
                "{}: masked {} non-finite sample(s) ({} NaN, {} infinite{at}); they are excluded from the data term like saturated pixels",
                path.display(),
                self.masked,
                self.nan,
                self.infinite
            ));
        }
        if let Some(w) = self.warning(path) {
            out.push(w);
        }
        out
    }

    /// The negative-values warning, when more than [`NEGATIVE_WARN_FRACTION`] are negative.
    pub fn warning(&self, path: &Path) -> Option<String> {
        if self.negative_fraction() <= NEGATIVE_WARN_FRACTION {
            return None;
        }
        let at = self.first_negative.as_ref().map(|l| format!(", first at {l}")).unwrap_or_default();
        Some(format!(
            "{}: {} of {} samples ({:.1}%) are negative{at}; linear data may dip below 0 by noise, but this many suggests a wrong black level or signed data",
            path.display(),
            self.negative,
            self.samples,
            100.0 * self.negative_fraction()
        ))
    }
}

fn location(img: &Image, c: usize, i: usize) -> PixelLocation {
    let w = img.width().max(1);
    PixelLocation { x: i % w, y: i / w, channel: img.channels.get(c).cloned().unwrap_or_else(|| format!("C{c}")) }
}

/// Counts non-finite and negative samples and finds the first of each (row-major, channel by
/// channel: the first is the lowest channel index, then the lowest `y`, then `x`).
pub fn scan(img: &Image) -> ValueReport {
    let mut r = ValueReport::default();
    for (c, p) in img.planes.iter().enumerate() {
        r.samples += p.data.len();
        for (i, &v) in p.data.iter().enumerate() {
            if v.is_nan() {
                r.nan += 1;
            } else if v.is_infinite() {
                r.infinite += 1;
            } else if v < 0.0 {
                r.negative += 1;
                if r.first_negative.is_none() {
                    r.first_negative = Some(location(img, c, i));
                }
                continue;
            } else {
                continue;
            }
            if r.first_non_finite.is_none() {
                r.first_non_finite = Some(location(img, c, i));
            }
        }
    }
    r
}

/// The message of a refused image (without the file name, which the error adds).
pub fn refusal_message(r: &ValueReport) -> String {
    let at = r.first_non_finite.as_ref().map(|l| format!(", first at {l}")).unwrap_or_default();
    format!(
        "{} non-finite sample(s) ({} NaN, {} infinite){at}; refusing the image (--mask-invalid excludes them from the data term instead)",
        r.non_finite(),
        r.nan,
        r.infinite
    )
}

/// An image refused under [`InvalidPixels::Refuse`]: its scan, which holds non-finite samples
/// (the message is [`refusal_message`]).
#[derive(Debug, thiserror::Error)]
#[error("{}", refusal_message(.0))]
pub struct Refused(pub Box<ValueReport>);

/// Scans `img` and applies `policy`.
///
/// # Errors
/// [`Refused`] when it holds non-finite samples under [`InvalidPixels::Refuse`]; under
/// [`InvalidPixels::Mask`] those samples become [`MASKED_VALUE`] and [`ValueReport::masked`]
/// counts them.
pub fn check_values(img: &mut Image, policy: InvalidPixels) -> Result<ValueReport, Refused> {
    let mut r = scan(img);
    if r.non_finite() == 0 {
        return Ok(r);
    }
    match policy {
        InvalidPixels::Refuse => Err(Refused(Box::new(r))),
        InvalidPixels::Mask => {
            for (c, p) in img.planes.iter_mut().enumerate() {
                for (i, v) in p.data.iter_mut().enumerate().filter(|(_, v)| !v.is_finite()) {
                    *v = MASKED_VALUE;
                    r.masked_samples.push((c, i));
                }
            }
            r.masked = r.masked_samples.len();
            Ok(r)
        }
    }
}

/// The first non-finite sample of `img`, if any (for the checks before a file is written).
pub fn first_non_finite(img: &Image) -> Option<PixelLocation> {
    img.planes.iter().enumerate().find_map(|(c, p)| p.data.iter().position(|v| !v.is_finite()).map(|i| location(img, c, i)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::Plane;

    fn img(values: &[f32]) -> Image {
        let n = values.len();
        let mut im = Image::new(vec![Plane::from_vec(n, 1, values.to_vec()).unwrap(), Plane::filled(n, 1, 0.5), Plane::filled(n, 1, 0.5)]);
        im.planes[2].data[n - 1] = f32::NEG_INFINITY;
        im
    }

    #[test]
    fn scan_counts_and_locates() {
        let im = img(&[0.1, f32::NAN, -0.2, f32::INFINITY, 0.3]);
        let r = scan(&im);
        assert_eq!((r.samples, r.nan, r.infinite, r.negative), (15, 1, 2, 1));
        assert_eq!(r.first_non_finite, Some(PixelLocation { x: 1, y: 0, channel: "R".into() }));
        assert_eq!(r.first_negative, Some(PixelLocation { x: 2, y: 0, channel: "R".into() }));
    }

    #[test]
    fn refuse_names_the_pixel_and_mask_replaces() {
        let mut im = img(&[0.1, 0.2, f32::NAN, 0.3]);
        let e = check_values(&mut im.clone(), InvalidPixels::Refuse).unwrap_err().to_string();
        assert!(e.contains("x=2, y=0") && e.contains("channel R") && e.contains("1 NaN") && e.contains("1 infinite"), "{e}");
        let r = check_values(&mut im, InvalidPixels::Mask).unwrap();
        assert_eq!(r.masked, 2);
        assert_eq!(im.planes[0].data, vec![0.1, 0.2, MASKED_VALUE, 0.3]);
        assert_eq!(im.planes[2].data[3], MASKED_VALUE);
        assert_eq!(r.masked_samples, vec![(0, 2), (2, 3)]);
        assert!(first_non_finite(&im).is_none());
        let notes = r.notes(Path::new("x.tiff"));
        assert!(notes.len() == 1 && notes[0].contains("masked 2"), "{notes:?}");
    }

    #[test]
    fn many_negatives_warn_a_few_do_not() {
        let mut few = Image::new(vec![Plane::filled(100, 10, 0.2)]);
        few.planes[0].data[..10].iter_mut().for_each(|v| *v = -0.01);
        let r = check_values(&mut few, InvalidPixels::Refuse).unwrap();
        assert_eq!(r.negative, 10);
        assert!(r.warning(Path::new("a.tiff")).is_none());
        let mut many = Image::new(vec![Plane::filled(100, 10, 0.2)]);
        many.planes[0].data[5..105].iter_mut().for_each(|v| *v = -0.01);
        let r = check_values(&mut many, InvalidPixels::Refuse).unwrap();
        let w = r.warning(Path::new("a.tiff")).unwrap();
        assert!(w.contains("100 of 1000") && w.contains("x=5, y=0"), "{w}");
    }
}
