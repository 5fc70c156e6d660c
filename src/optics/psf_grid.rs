//! A grid of PSFs across the field and the smooth interpolation between them.
//!
//! # Geometry
//! Tiles are laid out in `rows × columns`, row-major: tile `t` is row `t / columns`, column
//! `t % columns`. `centers[t] = [x, y]` is the tile centre in input pixels. Centres must form a
//! rectilinear grid (every row shares the column x's, every column shares the row y's), which
//! all lensrig grids do.
//!
//! # Interpolation
//! The PSF at a point is the bilinear blend of the four surrounding tile PSFs with *hat*
//! weights `w_t(x, y) = h_i(x) · h_j(y)` (piecewise linear, 1 at the tile's own centre, 0 at its
//! neighbours', constant beyond the outer centres). The weights sum to one everywhere, so the
//! blended kernel sums to one. The forward model ([`super::forward`]) applies exactly this
//! blend, point by point.

use crate::image::Plane;

/// PSFs for every tile and channel.
#[derive(Clone, Debug, PartialEq)]
pub struct PsfGrid {
    /// Odd side of every kernel.
    pub kernel_size: usize,
    pub columns: usize,
    pub rows: usize,
    /// Tile centres `[x, y]`, row-major.
    pub centers: Vec<[f64; 2]>,
    /// Channel names, one per entry of `kernels`.
    pub channels: Vec<String>,
    /// `kernels[channel][tile]`, each `kernel_size × kernel_size`.
    pub kernels: Vec<Vec<Plane>>,
}

/// One tile's share of a pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Weight {
    pub tile: usize,
    pub weight: f32,
}

/// Hat-function weights along one axis: up to two `(index, weight)` pairs.
pub fn hat_weights_1d(centers: &[f64], x: f64) -> [(usize, f32); 2] {
    let n = centers.len();
    if n == 1 || x <= centers[0] {
        return [(0, 1.0), (0, 0.0)];
    }
    if x >= centers[n - 1] {
        return [(n - 1, 1.0), (n - 1, 0.0)];
    }
    let i = centers.partition_point(|&c| c <= x).saturating_sub(1).min(n - 2);
    let t = ((x - centers[i]) / (centers[i + 1] - centers[i])) as f32;
    [(i, 1.0 - t), (i + 1, t)]
}

impl PsfGrid {
    /// Column centre x's (from the first row).
    pub fn column_xs(&self) -> Vec<f64> {
        (0..self.columns).map(|c| self.centers[c][0]).collect()
    }

    /// Row centre y's (from the first column).
    pub fn row_ys(&self) -> Vec<f64> {
        (0..self.rows).map(|r| self.centers[r * self.columns][1]).collect()
    }

    pub fn tile_count(&self) -> usize {
        self.columns * self.rows
    }

    /// The (up to four) tiles blended at `(x, y)` and their weights.
    pub fn weights_at(&self, x: f64, y: f64) -> Vec<Weight> {
        let wx = hat_weights_1d(&self.column_xs(), x);
        let wy = hat_weights_1d(&self.row_ys(), y);
        let mut out = Vec::with_capacity(4);
        for &(j, a) in &wy {
            for &(i, b) in &wx {
                let w = a * b;
                if w > 0.0 {
                    out.push(Weight { tile: j * self.columns + i, weight: w });
                }
            }
        }
        out
    }

    /// The interpolated PSF of `channel` at `(x, y)`.
    pub fn kernel_at(&self, channel: usize, x: f64, y: f64) -> Plane {
        let k = self.kernel_size;
        let mut out = Plane::new(k, k);
        for w in self.weights_at(x, y) {
            for (o, v) in out.data.iter_mut().zip(&self.kernels[channel][w.tile].data) {
                *o += w.weight * v;
            }
        }
        out
    }

    /// The pixel box `[x0, x1) × [y0, y1)` inside a `width × height` image where tile `t` has a
    /// non-zero weight.
    pub fn support(&self, t: usize, width: usize, height: usize) -> (usize, usize, usize, usize) {
        let (c, r) = (t % self.columns, t / self.columns);
        let xs = self.column_xs();
        let ys = self.row_ys();
        let span = |cs: &[f64], i: usize, n: usize| -> (usize, usize) {
            let lo = if i == 0 { 0.0 } else { cs[i - 1].floor() };
            let hi = if i + 1 == cs.len() { n as f64 } else { cs[i + 1].ceil() + 1.0 };
            (lo.max(0.0) as usize, (hi.min(n as f64)) as usize)
        };
        let (x0, x1) = span(&xs, c, width);
        let (y0, y1) = span(&ys, r, height);
        (x0, x1, y0, y1)
    }

    /// Regular tile centres for `columns × rows` tiles covering a `width × height` image.
    pub fn regular_centers(width: usize, height: usize, columns: usize, rows: usize) -> Vec<[f64; 2]> {
        let mut out = Vec::with_capacity(columns * rows);
        for r in 0..rows {
            for c in 0..columns {
                let x = (c as f64 + 0.5) * width as f64 / columns as f64 - 0.5;
                let y = (r as f64 + 0.5) * height as f64 / rows as f64 - 0.5;
                out.push([x, y]);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> PsfGrid {
        let centers = PsfGrid::regular_centers(100, 60, 3, 2);
        let kernels = vec![(0..6).map(|t| Plane::filled(3, 3, t as f32)).collect()];
        PsfGrid { kernel_size: 3, columns: 3, rows: 2, centers, channels: vec!["Y".into()], kernels }
    }

    #[test]
    fn weights_sum_to_one_and_interpolate_at_centres() {
        let g = grid();
        for y in (0..60).step_by(7) {
            for x in (0..100).step_by(9) {
                let s: f32 = g.weights_at(x as f64, y as f64).iter().map(|w| w.weight).sum();
                assert!((s - 1.0).abs() < 1e-6);
            }
        }
        for t in 0..6 {
            let [x, y] = g.centers[t];
            let w = g.weights_at(x, y);
            assert_eq!(w.len(), 1);
            assert_eq!(w[0].tile, t);
            assert_eq!(g.kernel_at(0, x, y).get(1, 1), t as f32);
        }
    }

    #[test]
    fn midpoint_is_the_average() {
        let g = grid();
        let (a, b) = (g.centers[0], g.centers[1]);
        let k = g.kernel_at(0, (a[0] + b[0]) / 2.0, a[1]);
        assert!((k.get(0, 0) - 0.5).abs() < 1e-6);
    }

    #[test]
    fn support_covers_every_nonzero_weight() {
        let g = grid();
        for t in 0..6 {
            let (x0, x1, y0, y1) = g.support(t, 100, 60);
            for y in 0..60 {
                for x in 0..100 {
                    let inside = x >= x0 && x < x1 && y >= y0 && y < y1;
                    let w: f32 = g.weights_at(x as f64, y as f64).iter().filter(|w| w.tile == t).map(|w| w.weight).sum();
                    assert!(inside || w == 0.0, "tile {t} at {x},{y}");
                }
            }
        }
    }
}
