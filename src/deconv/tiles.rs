//! Restoration tiles and their seamless blending.
//!
//! The image is cut into a regular grid of *cores*; tile `i` along an axis keeps the pixels of
//! its core widened by `overlap / 2` on each inner side and solves on a window of FFT-friendly
//! size that adds a margin beyond that (pixels outside the image are mirrored — reflective
//! pad-and-crop). The kept pixels are blended with a separable **partition of unity**: the weight
//! is 1 inside the core and ramps linearly across each `overlap`-wide band centred on a core
//! boundary, where the neighbour's weight ramps the other way, so the weights sum to exactly 1
//! everywhere and no tile border is visible.

/// One tile along one axis.
#[derive(Clone, Debug, PartialEq)]
pub struct Span {
    /// Core `[core0, core1)`.
    pub core0: usize,
    pub core1: usize,
    /// Kept (weighted) pixels `[keep0, keep1)`.
    pub keep0: usize,
    pub keep1: usize,
    /// First pixel of the solve window (negative: mirrored beyond the image).
    pub window0: isize,
    first: bool,
    last: bool,
    overlap: usize,
}

impl Span {
    /// The core's centre in pixel coordinates (pixel `i` at `i`): where the restoration takes
    /// the tile's PSF.
    pub fn centre(&self) -> f64 {
        (self.core0 + self.core1) as f64 / 2.0 - 0.5
    }

    /// The blend weight of pixel `x` (0 outside the kept range).
    pub fn weight(&self, x: usize) -> f32 {
        if x < self.keep0 || x >= self.keep1 {
            return 0.0;
        }
        if self.overlap == 0 {
            return 1.0;
        }
        let o = self.overlap as f32;
        let p = x as f32 + 0.5;
        let up = if self.first { 1.0 } else { ((p - (self.core0 as f32 - o / 2.0)) / o).clamp(0.0, 1.0) };
        let down = if self.last { 1.0 } else { (((self.core1 as f32 + o / 2.0) - p) / o).clamp(0.0, 1.0) };
        up * down
    }
}

/// Tiles along one axis of length `n` with cores of at most `max_core` pixels, a blending band
/// of `overlap` pixels and a solve window of `window` pixels (which must be at least the largest
/// kept range plus twice the margin the caller wants).
pub fn spans(n: usize, max_core: usize, overlap: usize) -> Vec<Span> {
    let count = n.div_ceil(max_core.max(1)).max(1);
    let overlap = if count == 1 { 0 } else { overlap.min(n / count) & !1 };
    (0..count)
        .map(|i| {
            let core0 = i * n / count;
            let core1 = (i + 1) * n / count;
            let first = i == 0;
            let last = i + 1 == count;
            let keep0 = if first { 0 } else { core0 - overlap / 2 };
            let keep1 = if last { n } else { core1 + overlap / 2 };
            Span { core0, core1, keep0, keep1, window0: 0, first, last, overlap }
        })
        .collect()
}

/// Sets every span's window start so the kept range sits in the middle of a `window`-pixel
/// solve window.
pub fn place_windows(spans: &mut [Span], window: usize) {
    for s in spans {
        let keep = s.keep1 - s.keep0;
        s.window0 = s.keep0 as isize - ((window - keep) / 2) as isize;
    }
}

/// The largest kept range.
pub fn max_keep(spans: &[Span]) -> usize {
    spans.iter().map(|s| s.keep1 - s.keep0).max().unwrap_or(0)
}

/// The tile-centre approximation's kernel error for cores of at most `core` px (blend band
/// `overlap`) on a `width × height` image:
///
/// `e = √( Σ_t Σ_p w_t(p) ‖K(p) − K(c_t)‖² / ‖K(p)‖²  /  Σ_t Σ_p w_t(p) )`,
///
/// over channels, tiles `t` and their kept pixels `p` (weighted by the tile's blend `w_t`), `K(p)`
/// the profile's interpolated PSF at `p` and `K(c_t)` the one at the tile's centre, which
/// restores the whole tile. The sums are sampled: 5 × 5 pixels per tile, each standing for its
/// share of the kept range, on at most 6 × 6 tiles spread over the image from the first to the
/// last row and column (tiles in parallel, summed in order).
pub fn tile_kernel_error(grid: &crate::optics::psf_grid::PsfGrid, width: usize, height: usize, core: usize, overlap: usize) -> f64 {
    use rayon::prelude::*;
    let (xs, ys) = (spans(width, core, overlap), spans(height, core, overlap));
    let pick = |n: usize| -> Vec<usize> {
        let m = n.min(6);
        (0..m).map(|i| if m > 1 { i * (n - 1) / (m - 1) } else { 0 }).collect()
    };
    // (pixel, blend weight × the pixel's share of the kept range)
    let lattice = |s: &Span| -> Vec<(f64, f64)> {
        let len = s.keep1 - s.keep0;
        (0..5).map(|i| s.keep0 + ((2 * i + 1) * len / 10).min(len.saturating_sub(1))).map(|q| (q as f64, s.weight(q) as f64 * len as f64 / 5.0)).collect()
    };
    let tiles: Vec<(usize, usize)> = pick(ys.len()).into_iter().flat_map(|j| pick(xs.len()).into_iter().map(move |i| (i, j))).collect();
    let sums: Vec<(f64, f64)> = tiles
        .par_iter()
        .map(|&(i, j)| {
            let (sx, sy) = (&xs[i], &ys[j]);
            let (mut num, mut den) = (0.0f64, 0.0f64);
            for c in 0..grid.channels.len() {
                let kc = grid.kernel_at(c, sx.centre(), sy.centre());
                for &(y, wy) in &lattice(sy) {
                    for &(x, wx) in &lattice(sx) {
                        let kp = grid.kernel_at(c, x, y);
                        let (mut d2, mut n2) = (0.0f64, 0.0f64);
                        for (a, b) in kp.data.iter().zip(&kc.data) {
                            d2 += ((a - b) as f64).powi(2);
                            n2 += (*a as f64).powi(2);
                        }
                        if n2 > 0.0 && d2.is_finite() {
                            num += wx * wy * d2 / n2;
                            den += wx * wy;
                        }
                    }
                }
            }
            (num, den)
        })
        .collect();
    let (num, den) = sums.iter().fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
    if den > 0.0 { (num / den).sqrt() } else { 0.0 }
}

/// The largest core of [`spans`] along either axis (what a requested largest core becomes).
pub fn actual_core(xs: &[Span], ys: &[Span]) -> usize {
    xs.iter().chain(ys).map(|s| s.core1 - s.core0).max().unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_are_a_partition_of_unity() {
        for &(n, core, o) in &[(100usize, 30usize, 8usize), (257, 64, 32), (50, 64, 16), (1000, 356, 32)] {
            let sp = spans(n, core, o);
            for x in 0..n {
                let s: f32 = sp.iter().map(|s| s.weight(x)).sum();
                assert!((s - 1.0).abs() < 1e-5, "n={n} x={x} sum={s}");
            }
            // cores tile the axis
            assert_eq!(sp[0].core0, 0);
            assert_eq!(sp.last().unwrap().core1, n);
            for w in sp.windows(2) {
                assert_eq!(w[0].core1, w[1].core0);
            }
        }
    }

    #[test]
    fn windows_centre_the_kept_range() {
        let mut sp = spans(200, 80, 16);
        place_windows(&mut sp, 128);
        for s in &sp {
            assert!(s.window0 <= s.keep0 as isize && s.window0 + 128 >= s.keep1 as isize);
        }
    }
}
