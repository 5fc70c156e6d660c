//! The exact field-varying blur of a [`PsfGrid`] on a rectangular window, as a linear operator
//! with its adjoint: the gather form `A x = Σ_t w_t · (k_t * x)` of [`super::forward`] and the
//! scatter form `Aᵀ y = Σ_t k_t ⋆ (w_t · y)`.
//!
//! `w_t` are the grid's separable Catmull–Rom weights ([`PsfGrid::weights_at`]) at the window
//! pixels' image positions; pixels of the window outside the image take the weights of their
//! mirror image (the window's data are mirrored there, [`crate::image::Plane::window_reflect`]).
//! Both products are evaluated with one FFT per contributing grid tile plus one on the
//! **periodic** window domain: the wrap-around of a kernel reaches only `kernel_size / 2` pixels
//! into the window from its edges, which callers crop (pad-and-crop). On those interior pixels
//! [`FieldOperator::apply`] equals [`super::forward::blur_channel`].
//!
//! Conventions: row-major `width × height` arrays, kernels centred at their middle pixel
//! ([`crate::solve::conv::kernel_to_origin`]), FFTs from [`crate::solve::fft`].

use super::psf_grid::{hat_weights_1d, PsfGrid};
use crate::image::reflect_index;
use crate::solve::conv::kernel_to_origin;
use crate::solve::fft::Fft2;
use crate::solve::operator::LinearOperator;
use rustfft::num_complex::Complex32;
use std::sync::Arc;

/// One grid tile's share of the window.
struct Part {
    /// Spectrum of the tile's kernel on the window domain.
    spec: Vec<Complex32>,
    /// Separable weight: `w(x, y) = wx[x] · wy[y]`.
    wx: Vec<f32>,
    wy: Vec<f32>,
}

/// The field-varying blur of one channel on one window.
pub struct FieldOperator {
    fft: Arc<Fft2>,
    parts: Vec<Part>,
}

/// 1-D weights of every grid index along one axis at the window's positions `origin..origin+n`
/// (mirrored into `0..size`); indices whose weight is zero everywhere are `None`.
fn axis_weights(centres: &[f64], origin: isize, n: usize, size: usize) -> Vec<Option<Vec<f32>>> {
    let mut out: Vec<Vec<f32>> = vec![vec![0.0; n]; centres.len()];
    for i in 0..n {
        let p = reflect_index(origin + i as isize, size) as f64;
        for (idx, w) in hat_weights_1d(centres, p) {
            out[idx][i] += w;
        }
    }
    out.into_iter().map(|v| v.iter().any(|w| *w != 0.0).then_some(v)).collect()
}

impl FieldOperator {
    /// The blur of `channel` on the `width × height` window whose top-left pixel is image pixel
    /// `(x0, y0)` of an `image_width × image_height` image.
    ///
    /// # Panics
    /// When `channel` is not a grid channel.
    #[allow(clippy::too_many_arguments)]
    pub fn new(grid: &PsfGrid, channel: usize, x0: isize, y0: isize, width: usize, height: usize, image_width: usize, image_height: usize) -> Self {
        let fft = Fft2::plan(width, height);
        let ax = axis_weights(&grid.column_xs(), x0, width, image_width);
        let ay = axis_weights(&grid.row_ys(), y0, height, image_height);
        let mut parts = Vec::new();
        for (r, wy) in ay.iter().enumerate() {
            let Some(wy) = wy else { continue };
            for (c, wx) in ax.iter().enumerate() {
                let Some(wx) = wx else { continue };
                let k = &grid.kernels[channel][r * grid.columns + c];
                let spec = fft.forward(&kernel_to_origin(k, width, height));
                parts.push(Part { spec, wx: wx.clone(), wy: wy.clone() });
            }
        }
        Self { fft, parts }
    }

    pub fn width(&self) -> usize {
        self.fft.width
    }

    pub fn height(&self) -> usize {
        self.fft.height
    }

    /// Number of grid tiles that contribute to the window.
    pub fn tiles(&self) -> usize {
        self.parts.len()
    }
}

impl LinearOperator for FieldOperator {
    fn input_len(&self) -> usize {
        self.fft.width * self.fft.height
    }

    fn output_len(&self) -> usize {
        self.fft.width * self.fft.height
    }

    /// `out = A x` (gather).
    fn apply(&self, x: &[f32], out: &mut [f32]) {
        let w = self.fft.width;
        let xs = self.fft.forward(x);
        let mut spec = vec![Complex32::new(0.0, 0.0); xs.len()];
        let mut conv = vec![0.0; x.len()];
        out.iter_mut().for_each(|v| *v = 0.0);
        for p in &self.parts {
            spec.iter_mut().zip(&xs).zip(&p.spec).for_each(|((s, a), b)| *s = a * b);
            self.fft.inverse_into(&mut spec, &mut conv);
            for (y, wy) in p.wy.iter().enumerate() {
                if *wy == 0.0 {
                    continue;
                }
                let row = y * w..(y + 1) * w;
                for ((o, c), wx) in out[row.clone()].iter_mut().zip(&conv[row]).zip(&p.wx) {
                    *o += wy * wx * c;
                }
            }
        }
    }

    /// `out = Aᵀ y` (scatter).
    fn apply_adjoint(&self, y: &[f32], out: &mut [f32]) {
        let w = self.fft.width;
        let n = self.fft.spectrum_len();
        let mut acc = vec![Complex32::new(0.0, 0.0); n];
        let mut spec = vec![Complex32::new(0.0, 0.0); n];
        let mut weighted = vec![0.0; y.len()];
        for p in &self.parts {
            for (r, wy) in p.wy.iter().enumerate() {
                let row = r * w..(r + 1) * w;
                for ((o, v), wx) in weighted[row.clone()].iter_mut().zip(&y[row]).zip(&p.wx) {
                    *o = wy * wx * v;
                }
            }
            self.fft.forward_into(&weighted, &mut spec);
            acc.iter_mut().zip(&spec).zip(&p.spec).for_each(|((a, s), k)| *a += s * k.conj());
        }
        self.fft.inverse_into(&mut acc, out);
    }}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deconv::synth::SyntheticLens;
    use crate::image::Plane;
    use crate::optics::forward::blur_channel;

    fn noise(w: usize, h: usize, seed: u64) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..w * h)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (s >> 40) as f32 / (1u64 << 24) as f32 - 0.5
            })
            .collect()
    }

    /// Inside the window (away from the wrap band), the operator is the project's forward model.
    #[test]
    fn matches_the_forward_model_away_from_the_window_edge() {
        let (iw, ih) = (96, 80);
        let grid = SyntheticLens::new(11, 3).grid(iw, ih, 3, 4, 3);
        let sharp = Plane::from_vec(iw, ih, noise(iw, ih, 3).iter().map(|v| v + 0.5).collect()).unwrap();
        let r = 5;
        for &(x0, y0, w, h) in &[(-12isize, -10isize, 64usize, 48usize), (40, 30, 64, 60)] {
            let win = sharp.window_reflect(x0, y0, w, h);
            for ch in 0..3 {
                let want = blur_channel(&sharp, &grid, ch);
                let op = FieldOperator::new(&grid, ch, x0, y0, w, h, iw, ih);
                let mut got = vec![0.0; w * h];
                op.apply(&win.data, &mut got);
                for y in r..h - r {
                    for x in r..w - r {
                        let (ix, iy) = (x0 + x as isize, y0 + y as isize);
                        if ix < 0 || iy < 0 || ix >= iw as isize || iy >= ih as isize {
                            continue;
                        }
                        let (a, b) = (got[y * w + x], want.get(ix as usize, iy as usize));
                        assert!((a - b).abs() < 1e-4, "ch {ch} at {ix},{iy}: {a} vs {b}");
                    }
                }
            }
        }
    }
}
