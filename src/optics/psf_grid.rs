//! A grid of PSFs across the field and the smooth interpolation between them.
//!
//! # Geometry
//! Tiles are laid out in `rows × columns`, row-major: tile `t` is row `t / columns`, column
//! `t % columns`. `centers[t] = [x, y]` is the tile centre in input pixels. Centres must form a
//! rectilinear grid (every row shares the column x's, every column shares the row y's), which
//! all lensrig grids do.
//!
//! # Interpolation
//! The PSF at a point is the separable **Catmull–Rom** blend of the 4 × 4 surrounding tile PSFs,
//! `w_t(x, y) = c_i(x) · c_j(y)`: along each axis, between centres `x_i` and `x_{i+1}` with
//! `t = (x − x_i)/(x_{i+1} − x_i)`, the weights of centres `i−1, i, i+1, i+2` are
//! `(−t³+2t²−t)/2, (3t³−5t²+2)/2, (−3t³+4t²+t)/2, (t³−t²)/2` (at the grid's edge the missing
//! centre is the linear extrapolation of the last two; constant beyond the outer centres). The blend passes through every tile's kernel at its
//! centre, is continuous with a continuous first derivative across the field, reproduces
//! quadratic variation exactly on a regular grid, and its weights sum to one, so the blended
//! kernel sums to one (it may carry small negative lobes where the PSF changes fast). The
//! forward model ([`super::forward`]) applies exactly this blend, point by point.

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

/// Catmull–Rom weights along one axis: four `(index, weight)` pairs (indices may repeat at the
/// edges, with zero weight).
pub fn hat_weights_1d(centers: &[f64], x: f64) -> [(usize, f32); 4] {
    let n = centers.len();
    if n == 1 || x <= centers[0] {
        return [(0, 1.0), (0, 0.0), (0, 0.0), (0, 0.0)];
    }
    if x >= centers[n - 1] {
        return [(n - 1, 1.0), (n - 1, 0.0), (n - 1, 0.0), (n - 1, 0.0)];
    }
    let i = centers.partition_point(|&c| c <= x).saturating_sub(1).min(n - 2);
    let t = ((x - centers[i]) / (centers[i + 1] - centers[i])) as f32;
    let (t2, t3) = (t * t, t * t * t);
    let w = [(-t3 + 2.0 * t2 - t) / 2.0, (3.0 * t3 - 5.0 * t2 + 2.0) / 2.0, (-3.0 * t3 + 4.0 * t2 + t) / 2.0, (t3 - t2) / 2.0];
    // Beyond the grid the phantom centre is the linear extrapolation of the last two
    // (v₋₁ = 2v₀ − v₁), so linear variation is reproduced up to the edge.
    let mut out = [(i, w[1]), (i + 1, w[2]), (i, 0.0), (i + 1, 0.0)];
    if i >= 1 {
        out[2] = (i - 1, w[0]);
    } else {
        out[0].1 += 2.0 * w[0];
        out[1].1 -= w[0];
    }
    if i + 2 < n {
        out[3] = (i + 2, w[3]);
    } else {
        out[1].1 += 2.0 * w[3];
        out[0].1 -= w[3];
    }
    out
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

    /// The centroid of tile `t`'s kernels (pixels from the kernel centre, `(x, y)`), averaged
    /// over the channels: where the lens moves the light at that centre, colour aside.
    pub fn mean_centroid(&self, t: usize) -> (f64, f64) {
        let (mut dx, mut dy) = (0.0, 0.0);
        for c in 0..self.channels.len() {
            let (a, b) = crate::optics::lens::centroid(&self.kernels[c][t]);
            dx += a / self.channels.len() as f64;
            dy += b / self.channels.len() as f64;
        }
        (dx, dy)
    }

    /// The (up to sixteen) tiles blended at `(x, y)` and their weights (non-zero only).
    pub fn weights_at(&self, x: f64, y: f64) -> Vec<Weight> {
        let wx = hat_weights_1d(&self.column_xs(), x);
        let wy = hat_weights_1d(&self.row_ys(), y);
        let mut out: Vec<Weight> = Vec::with_capacity(16);
        for &(j, a) in &wy {
            for &(i, b) in &wx {
                let w = a * b;
                if w != 0.0 {
                    let tile = j * self.columns + i;
                    match out.iter_mut().find(|q| q.tile == tile) {
                        Some(q) => q.weight += w,
                        None => out.push(Weight { tile, weight: w }),
                    }
                }
            }
        }
        out.retain(|q| q.weight != 0.0);
        out
    }

    /// Tile `t`'s weight `w_t(x, y)` over the box `[x0, x1) × [y0, y1)`, row-major. Equal to
    /// [`Self::weights_at`] summed for `t`, computed from the separable factors
    /// `w_t = c_i(x) · c_j(y)` (one 1-D evaluation per row and column).
    pub fn tile_weights(&self, t: usize, x0: usize, x1: usize, y0: usize, y1: usize) -> Vec<f32> {
        let (i, j) = (t % self.columns, t / self.columns);
        let (xs, ys) = (self.column_xs(), self.row_ys());
        let factor = |cs: &[f64], idx: usize, p: usize| -> f32 { hat_weights_1d(cs, p as f64).iter().filter(|q| q.0 == idx).map(|q| q.1).sum() };
        let cx: Vec<f32> = (x0..x1).map(|x| factor(&xs, i, x)).collect();
        let mut out = Vec::with_capacity((x1 - x0) * (y1 - y0));
        for y in y0..y1 {
            let a = factor(&ys, j, y);
            out.extend(cx.iter().map(|&b| a * b));
        }
        out
    }

    /// The blend `Σ_t w_t(x, y) · values[t]` of one scalar per tile over a `width × height`
    /// image (e.g. a per-tile kernel energy).
    pub fn blend_scalars(&self, values: &[f32], width: usize, height: usize) -> Plane {
        self.blend_scalars_where(values, width, height, None)
    }

    /// [`PsfGrid::blend_scalars`] on the pixels where `need` is true (every pixel with
    /// `None`); 0 elsewhere. The same values where computed.
    pub fn blend_scalars_where(&self, values: &[f32], width: usize, height: usize, need: Option<&[bool]>) -> Plane {
        assert_eq!(values.len(), self.tile_count(), "one value per tile");
        let (xs, ys) = (self.column_xs(), self.row_ys());
        let cx: Vec<[(usize, f32); 4]> = (0..width).map(|x| hat_weights_1d(&xs, x as f64)).collect();
        let mut out = Plane::new(width, height);
        for y in 0..height {
            let wy = hat_weights_1d(&ys, y as f64);
            let row = &mut out.data[y * width..(y + 1) * width];
            crate::image::for_needed(row, crate::image::mask_row(need, y, width), |x, o| {
                let mut s = 0.0f32;
                for &(j, a) in &wy {
                    for &(i, b) in &cx[x] {
                        s += a * b * values[j * self.columns + i];
                    }
                }
                *o = s;
            });
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

    /// The pixel box `[x0, x1) × [y0, y1)` inside a `width × height` image where tile `t` may
    /// have a non-zero weight.
    pub fn support(&self, t: usize, width: usize, height: usize) -> (usize, usize, usize, usize) {
        let (c, r) = (t % self.columns, t / self.columns);
        let xs = self.column_xs();
        let ys = self.row_ys();
        // a centre influences the two intervals on either side of it (Catmull–Rom), and the
        // outer centres everything beyond them
        let span = |cs: &[f64], i: usize, n: usize| -> (usize, usize) {
            let lo = if i <= 1 { 0.0 } else { cs[i - 2].floor() };
            let hi = if i + 2 >= cs.len() { n as f64 } else { cs[i + 2].ceil() + 1.0 };
            (lo.max(0.0) as usize, (hi.min(n as f64)) as usize)
        };
        let (x0, x1) = span(&xs, c, width);
        let (y0, y1) = span(&ys, r, height);
        (x0, x1, y0, y1)
    }

    /// Centres on a `columns × rows` lattice whose outer centres lie **on the frame's edges**:
    /// `x_i = i·(width − 1)/(columns − 1)` (the middle for one column), likewise in `y`. The
    /// blend then never holds a kernel constant inside the frame, as it does in the outer half
    /// tile of [`Self::regular_centers`]; a lens's PSF changes fastest there, towards the
    /// corners. `diagnose`'s `psf_field_variation` refits on this layout.
    pub fn edge_centers(width: usize, height: usize, columns: usize, rows: usize) -> Vec<[f64; 2]> {
        let at = |n: usize, len: usize, i: usize| if n <= 1 { (len as f64 - 1.0) / 2.0 } else { i as f64 * (len as f64 - 1.0) / (n - 1) as f64 };
        (0..rows).flat_map(|r| (0..columns).map(move |c| [at(columns, width, c), at(rows, height, r)])).collect()
    }

    /// Whether the centres are [`Self::edge_centers`] of this grid's size on a `width × height`
    /// frame (for one tile: the frame's middle).
    pub fn is_edge_anchored(&self, width: usize, height: usize) -> bool {
        self.centers == Self::edge_centers(width, height, self.columns, self.rows)
    }

    /// The profile's `tile_size` for this grid on a `width × height` frame
    /// (docs/profile-format.md): the centre spacing, rounded, when the outer centres lie on the
    /// frame's edges ([`Self::edge_centers`]), else the tile side `width / columns`,
    /// `height / rows` of [`Self::regular_centers`].
    pub fn tile_size(&self, width: usize, height: usize) -> [usize; 2] {
        if self.is_edge_anchored(width, height) {
            let spacing = |cs: &[f64], len: usize| if cs.len() > 1 { (cs[1] - cs[0]).round() as usize } else { len };
            [spacing(&self.column_xs(), width), spacing(&self.row_ys(), height)]
        } else {
            [width / self.columns, height / self.rows]
        }
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

    /// The separable fast paths equal the pointwise weights.
    #[test]
    fn tile_weights_and_blend_match_weights_at() {
        let g = PsfGrid { kernel_size: 3, columns: 4, rows: 3, centers: PsfGrid::regular_centers(97, 61, 4, 3), channels: vec!["Y".into()], kernels: vec![vec![Plane::new(3, 3); 12]] };
        let values: Vec<f32> = (0..12).map(|t| 1.0 + (t * t) as f32 * 0.37).collect();
        let blend = g.blend_scalars(&values, 97, 61);
        for t in 0..12 {
            let (x0, x1, y0, y1) = g.support(t, 97, 61);
            let tw = g.tile_weights(t, x0, x1, y0, y1);
            for y in y0..y1 {
                for x in x0..x1 {
                    let want: f32 = g.weights_at(x as f64, y as f64).iter().filter(|q| q.tile == t).map(|q| q.weight).sum();
                    assert!((tw[(y - y0) * (x1 - x0) + x - x0] - want).abs() < 1e-6, "tile {t} at ({x}, {y})");
                }
            }
        }
        for y in 0..61 {
            for x in 0..97 {
                let want: f32 = g.weights_at(x as f64, y as f64).iter().map(|q| q.weight * values[q.tile]).sum();
                assert!((blend.get(x, y) - want).abs() < 1e-4, "blend at ({x}, {y})");
            }
        }
    }

    /// The masked blend has the whole blend's values on the needed pixels and 0 elsewhere.
    #[test]
    fn masked_blend_is_the_blend_where_needed() {
        let g = PsfGrid { kernel_size: 3, columns: 4, rows: 3, centers: PsfGrid::regular_centers(97, 61, 4, 3), channels: vec!["Y".into()], kernels: vec![vec![Plane::new(3, 3); 12]] };
        let values: Vec<f32> = (0..12).map(|t| 1.0 + t as f32 * 0.5).collect();
        let need: Vec<bool> = (0..97 * 61).map(|i| (i % 97) % 5 != 0 && (i / 97) > 10).collect();
        let (all, some) = (g.blend_scalars(&values, 97, 61), g.blend_scalars_where(&values, 97, 61, Some(&need)));
        for i in 0..97 * 61 {
            assert_eq!(some.data[i], if need[i] { all.data[i] } else { 0.0 }, "pixel {i}");
        }
    }

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
    fn quadratic_variation_is_reproduced_inside_the_grid() {
        let xs: Vec<f64> = (0..6).map(|i| 10.0 + 20.0 * i as f64).collect();
        for k in 0..100 {
            let x = 30.0 + 60.0 * k as f64 / 99.0; // between the 2nd and 5th centres
            let v: f64 = hat_weights_1d(&xs, x).iter().map(|&(i, w)| w as f64 * xs[i] * xs[i]).sum();
            assert!((v - x * x).abs() < 1e-3 * x * x, "{x}: {v}");
        }
    }

    /// Edge-anchored centres put the outer kernels on the frame's edges, so a field that varies
    /// linearly out to the corner is followed on every pixel; tile-centred ones hold the
    /// outer half tile constant.
    #[test]
    fn edge_centres_follow_the_field_to_the_frame_edge() {
        let (w, h) = (100, 60);
        let field = |x: f64| 1.0 + 0.02 * x;
        let make = |centers: Vec<[f64; 2]>| {
            let kernels = vec![centers.iter().map(|&[x, _]| Plane::filled(1, 1, field(x) as f32)).collect()];
            PsfGrid { kernel_size: 1, columns: 4, rows: 3, centers, channels: vec!["Y".into()], kernels }
        };
        let edge = make(PsfGrid::edge_centers(w, h, 4, 3));
        assert_eq!(edge.centers[0], [0.0, 0.0]);
        assert_eq!(edge.centers[11], [99.0, 59.0]);
        assert_eq!(edge.centers[5], [33.0, 29.5]);
        let regular = make(PsfGrid::regular_centers(w, h, 4, 3));
        let err = |g: &PsfGrid, x: usize| (g.kernel_at(0, x as f64, 7.0).get(0, 0) as f64 - field(x as f64)).abs();
        for x in 0..w {
            assert!(err(&edge, x) < 1e-5, "x = {x}: {}", err(&edge, x));
        }
        // the regular grid's outer centre is at x = 12: the corner reads the field there
        assert!((err(&regular, 0) - 0.24).abs() < 1e-5, "{}", err(&regular, 0));
        assert_eq!(PsfGrid::edge_centers(w, h, 1, 1), vec![[49.5, 29.5]]);
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
