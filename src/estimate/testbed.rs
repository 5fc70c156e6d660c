//! Scoring an estimated PSF grid against a truth grid (the estimation test bed, issue 16;
//! docs/estimation.md "Test bed").
//!
//! # Truth at an estimated centre
//! The truth at an estimated centre `(x, y)` is the truth grid's Catmull–Rom blend at that point
//! ([`PsfGrid::kernel_at`]), the blend `simulate` applies point by point
//! ([`crate::optics::forward`]), so it is the kernel the rendered wide-open data hold there.
//!
//! # Alignment rule
//! None. The profile format fixes a kernel's geometry absolutely: `K[v][u]` is the light landing
//! at offset `(u − c, v − c)` px with `c = (k − 1)/2`, so a kernel displaced by a sub-pixel shift
//! predicts a displaced image and is wrong, not equivalent. Kernels of different sizes are
//! compared on the larger square, each embedded about its centre pixel (zero outside its own
//! support); nothing is shifted, rescaled or renormalised.
//!
//! # Units
//! Errors are relative L2, `‖b − b_true‖₂ / ‖b_true‖₂` (a fraction, 0.05 = 5 %); centres in
//! pixels (pixel centres at integers).

use crate::image::Plane;
use crate::optics::psf_grid::PsfGrid;

/// `k` embedded about its centre in a `size × size` square (`size ≥ k`, both odd), zero
/// outside; a larger `k` is cropped about its centre.
pub fn embed_centered(k: &Plane, size: usize) -> Plane {
    let off = size as isize / 2 - k.width as isize / 2;
    let mut out = Plane::new(size, size);
    out.paste(k, off, off);
    out
}

/// Relative L2 error `‖a − b‖ / ‖b‖` of two centred kernels of any odd sizes, compared on the
/// larger square (module docs: no alignment).
pub fn relative_error_centered(a: &Plane, b: &Plane) -> f64 {
    let n = a.width.max(b.width);
    super::relative_error(&embed_centered(a, n), &embed_centered(b, n))
}

/// Per channel of `est` (matched to `truth` by name; a channel the truth lacks scores
/// nothing), the relative L2 error of every tile's kernel against the truth blended at that
/// tile's centre, tiles in grid order.
pub fn errors_against_truth(est: &PsfGrid, truth: &PsfGrid) -> Vec<Vec<f64>> {
    est.channels
        .iter()
        .enumerate()
        .map(|(c, name)| match truth.channels.iter().position(|n| n == name) {
            Some(tc) => (0..est.tile_count())
                .map(|t| {
                    let [x, y] = est.centers[t];
                    relative_error_centered(&est.kernels[c][t], &truth.kernel_at(tc, x, y))
                })
                .collect(),
            None => vec![],
        })
        .collect()
}

/// The `p`-quantile (`0 ≤ p ≤ 1`, nearest rank on the sorted values) of `v`; `None` when empty.
pub fn quantile(v: &[f64], p: f64) -> Option<f64> {
    let mut s: Vec<f64> = v.to_vec();
    s.sort_by(f64::total_cmp);
    let last = s.len().checked_sub(1)?;
    let i = ((p.clamp(0.0, 1.0) * last as f64).round() as usize).min(last);
    Some(s[i])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gauss(k: usize, cx: f32, cy: f32, s: f32) -> Plane {
        let c = (k / 2) as f32;
        let mut p = Plane::from_fn(k, k, |x, y| {
            let (dx, dy) = (x as f32 - c - cx, y as f32 - c - cy);
            (-(dx * dx + dy * dy) / (2.0 * s * s)).exp()
        });
        let sum = p.sum() as f32;
        p.scale(1.0 / sum);
        p
    }

    /// A grid whose kernels vary linearly with x: `b(x) = (1 − x/W)·A + (x/W)·B`.
    fn linear_grid(w: usize, h: usize, columns: usize, rows: usize, k: usize) -> PsfGrid {
        let centers = PsfGrid::regular_centers(w, h, columns, rows);
        let (a, b) = (gauss(k, 0.0, 0.0, 1.0), gauss(k, 1.0, -0.5, 2.5));
        let kernels = vec![centers.iter().map(|&[x, _]| mix(&a, &b, x / w as f64)).collect()];
        PsfGrid { kernel_size: k, columns, rows, centers, channels: vec!["G".into()], kernels }
    }

    fn mix(a: &Plane, b: &Plane, t: f64) -> Plane {
        Plane::from_fn(a.width, a.height, |x, y| ((1.0 - t) as f32) * a.get(x, y) + t as f32 * b.get(x, y))
    }

    /// The truth scored against itself is exact; a grid on other centres gets the truth
    /// blended at its own centres: Catmull–Rom reproduces a linear field, so an estimate equal to
    /// the analytic kernel there scores ~0, while the nearest truth tile's kernel does not.
    #[test]
    fn truth_is_interpolated_at_the_estimated_centres() {
        let (w, h, k) = (700, 500, 9);
        let truth = linear_grid(w, h, 7, 5, k);
        assert!(errors_against_truth(&truth, &truth)[0].iter().all(|&e| e < 1e-6));
        // a 4 × 3 grid: its interior centres fall between the truth's
        let est = linear_grid(w, h, 4, 3, k);
        let e = &errors_against_truth(&est, &truth)[0];
        // only centres inside the truth's outer centres are reproduced exactly (beyond them
        // the blend is constant by definition)
        let xs = truth.column_xs();
        for (t, &[x, _]) in est.centers.iter().enumerate() {
            if x >= xs[0] && x <= xs[xs.len() - 1] {
                assert!(e[t] < 1e-5, "tile {t} at x={x}: {}", e[t]);
            }
        }
        // the nearest truth tile is a different kernel: scoring against it would be wrong
        let [x, y] = est.centers[1];
        let nearest = truth.centers.iter().enumerate().min_by(|a, b| {
            let d = |c: &[f64; 2]| (c[0] - x).powi(2) + (c[1] - y).powi(2);
            d(a.1).total_cmp(&d(b.1))
        });
        let nearest = nearest.map_or(0, |n| n.0);
        assert!(relative_error_centered(&est.kernels[0][1], &truth.kernels[0][nearest]) > 0.01);
    }

    /// Kernels of different sizes compare about their centres; a one-pixel shift is an error
    /// (no alignment), and a channel the truth lacks scores nothing.
    #[test]
    fn sizes_are_embedded_and_shifts_count() {
        let small = gauss(7, 0.0, 0.0, 1.0);
        let big = embed_centered(&small, 15);
        assert!((big.sum() - small.sum()).abs() < 1e-6);
        assert!(relative_error_centered(&small, &big) < 1e-7);
        assert!(relative_error_centered(&big, &small) < 1e-7);
        let shifted = gauss(7, 1.0, 0.0, 1.0);
        assert!(relative_error_centered(&shifted, &big) > 0.5);
        let mut g = linear_grid(300, 200, 3, 2, 7);
        let truth = g.clone();
        g.channels = vec!["R".into()];
        assert!(errors_against_truth(&g, &truth)[0].is_empty());
    }

    #[test]
    fn quantiles() {
        let v = [5.0, 1.0, 3.0, 2.0, 4.0];
        assert_eq!(quantile(&v, 0.5), Some(3.0));
        assert_eq!(quantile(&v, 0.9), Some(5.0));
        assert_eq!(quantile(&v, 0.0), Some(1.0));
        assert_eq!(quantile(&[], 0.5), None);
    }
}
