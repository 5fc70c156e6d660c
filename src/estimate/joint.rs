//! Joint refinement of all kernels of one channel with the exact field-varying forward model.
//!
//! The per-window fits ([`super::solver`]) assume one PSF per window, so where the PSF changes
//! inside a window they return a blend of its neighbourhood. The prediction, however, uses the
//! Catmull–Rom blend of the kernels ([`crate::optics::psf_grid`], [`crate::optics::forward`]):
//!
//! `pred(x) = Σ_t w_t(x) · (I ⊛ b_t)(x)`.
//!
//! This module fits all kernels of a channel at once to exactly that model, over the whole
//! image:
//!
//! `min Σ_x ½ M(x) (pred(x) − j(x))² + Σ_t λ_t TV(b_t),  b_t ≥ 0, 1ᵀb_t = σ_t`
//!
//! (`M` the valid-data mask, `I` the registered pinhole image times the exposure ratio, `λ_t`,
//! `σ_t` from the window fits), with FISTA and adaptive restart started from the window fits;
//! the prox of `λ_t TV + simplex` is solved per kernel by a few warm-started dual projected
//! gradient steps (kernel-sized work only), the step is `1/L` with `L` measured on the
//! simplices' tangent space. The gradient for kernel `t` is `Pᵀ Iᵀ (w_t ⊙ r)` with `r` the
//! masked residual; every product is an FFT convolution on the box where `w_t ≠ 0` plus a
//! kernel radius, so one iteration costs four FFTs of that box per kernel (kernels in parallel).
//!
//! Conventions as in [`super::solver`]: linear values, `k × k` kernels with the centre at zero
//! displacement, true convolution.

use super::solver::{project_simplex, tv_gradient, tv_gradient_adjoint};
use crate::image::Plane;
use crate::optics::psf_grid::PsfGrid;
use crate::solve::fft::{good_size, Fft2, FftScratch};
use crate::solve::primal_dual::{PrimalDual, SplitOptions, Stats};
use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use std::sync::Arc;

/// One block of the image: a `sw × sh` piece of the data, the spectrum of the sharp image on
/// the piece plus a kernel radius (mirrored at the image edges), and the tiles whose weight is
/// non-zero on it.
struct Block {
    x0: usize,
    y0: usize,
    sw: usize,
    sh: usize,
    a_hat: Vec<Complex32>,
    tiles: Vec<usize>,
}

struct JointProblem {
    w: usize,
    k: usize,
    columns: usize,
    /// One `F × F` plan for every block.
    fft: Arc<Fft2>,
    blocks: Vec<Block>,
    /// `blocks_of[t]`: the blocks tile `t` touches.
    blocks_of: Vec<Vec<usize>>,
    /// Separable Catmull–Rom factors: `w_t(x, y) = cx[t % columns][x] · cy[t / columns][y]`.
    cx: Vec<Vec<f32>>,
    cy: Vec<Vec<f32>>,
    /// Kernel position `i` (row-major `k × k`, centre = zero displacement) in the wrapped
    /// `F × F` layout.
    index: Vec<usize>,
    /// Per-tile spectra: the kernels (forward) and the accumulated gradients (adjoint).
    b_hat: Vec<Vec<Complex32>>,
    g_hat: Vec<Vec<Complex32>>,
    blurred: Vec<f32>,
    mask: Vec<bool>,
    lambda: Vec<f32>,
    totals: Vec<f32>,
    pred: Vec<f32>,
    /// Advanced by one per FISTA iteration.
    progress: indicatif::ProgressBar,
}

/// Per-task work buffers for one `F × F` plan.
struct Work {
    scratch: FftScratch,
    buf: Vec<f32>,
    out: Vec<f32>,
    spec: Vec<Complex32>,
}

impl Work {
    fn new(fft: &Fft2) -> Self {
        let n = fft.width * fft.height;
        Self { scratch: fft.make_scratch(), buf: vec![0.0; n], out: vec![0.0; n], spec: vec![Complex32::new(0.0, 0.0); fft.spectrum_len()] }
    }
}

impl JointProblem {
    /// `out = ∇` of `½‖M(pred(b) − j)‖²` (or of `½‖M pred(b)‖²` without data); returns the value.
    ///
    /// Blocked FFT convolution: the image is cut into blocks of `F − 2r` pixels; for each block
    /// and tile `pred += w_t ⊙ (I ⊛ b_t)` with one inverse FFT of size `F` (the block's
    /// spectrum of `I` is precomputed, the kernel's once per call), and the gradient's spectrum
    /// `Σ_B conj(Î_B) · FFT(w_t ⊙ r_B)` is accumulated per tile and inverted once. Exact (linear,
    /// not circular, convolution on every block), and the `F × F` work stays in cache.
    fn normal(&mut self, b: &[f32], out: &mut [f32], with_data: bool) -> f64 {
        let (k2, r) = (self.k * self.k, self.k / 2);
        let fft = self.fft.clone();
        let (fw, fh) = (fft.width, fft.height);
        let index = &self.index;
        // kernel spectra
        self.b_hat.par_iter_mut().zip(b.par_chunks(k2)).for_each_init(
            || Work::new(&fft),
            |wk, (bh, bt)| {
                let kernel_row = |y: usize| y <= r || y + r >= fh;
                for y in (0..fh).filter(|&y| kernel_row(y)) {
                    wk.buf[y * fw..(y + 1) * fw].fill(0.0);
                }
                for (&i, &v) in index.iter().zip(bt) {
                    wk.buf[i] = v;
                }
                fft.forward_rows_with(&wk.buf, bh, kernel_row, &mut wk.scratch);
            },
        );
        // forward, block by block
        let this = &*self;
        let preds: Vec<Vec<f32>> = this
            .blocks
            .par_iter()
            .map_init(
                || Work::new(&fft),
                |wk, blk| {
                    let mut local = vec![0.0f32; blk.sw * blk.sh];
                    for &t in &blk.tiles {
                        wk.spec.iter_mut().zip(&blk.a_hat).zip(&this.b_hat[t]).for_each(|((s, a), q)| *s = a * q);
                        let sh = blk.sh;
                        fft.inverse_rows_with(&mut wk.spec, &mut wk.out, |y| y >= r && y < r + sh, &mut wk.scratch);
                        let cxt = &this.cx[t % this.columns][blk.x0..blk.x0 + blk.sw];
                        let cyt = &this.cy[t / this.columns];
                        for y in 0..blk.sh {
                            let a = cyt[blk.y0 + y];
                            if a == 0.0 {
                                continue;
                            }
                            let src = &wk.out[(y + r) * fw + r..(y + r) * fw + r + blk.sw];
                            for ((o, s), q) in local[y * blk.sw..(y + 1) * blk.sw].iter_mut().zip(src).zip(cxt) {
                                *o += a * q * s;
                            }
                        }
                    }
                    local
                },
            )
            .collect();
        for (blk, local) in self.blocks.iter().zip(&preds) {
            for y in 0..blk.sh {
                let o = (blk.y0 + y) * self.w + blk.x0;
                self.pred[o..o + blk.sw].copy_from_slice(&local[y * blk.sw..(y + 1) * blk.sw]);
            }
        }
        // masked residual
        let w = self.w;
        let (blurred, mask) = (&self.blurred, &self.mask);
        let f: f64 = self
            .pred
            .par_chunks_mut(w)
            .enumerate()
            .map(|(y, row)| {
                let mut f = 0.0f64;
                for (x, p) in row.iter_mut().enumerate() {
                    let i = y * w + x;
                    let d = if mask[i] { *p - if with_data { blurred[i] } else { 0.0 } } else { 0.0 };
                    *p = d;
                    f += (d as f64) * (d as f64);
                }
                f
            })
            .sum();
        // adjoint, tile by tile
        let mut g_hat = std::mem::take(&mut self.g_hat);
        let this = &*self;
        let resid = &self.pred;
        g_hat.par_iter_mut().zip(out.par_chunks_mut(k2)).enumerate().for_each_init(
            || Work::new(&fft),
            |wk, (t, (gh, ot))| {
                gh.iter_mut().for_each(|v| *v = Complex32::new(0.0, 0.0));
                let cxt = &this.cx[t % this.columns];
                let cyt = &this.cy[t / this.columns];
                for &bi in &this.blocks_of[t] {
                    let blk = &this.blocks[bi];
                    for y in 0..blk.sh {
                        let a = cyt[blk.y0 + y];
                        let row = &mut wk.buf[(y + r) * fw..(y + r + 1) * fw];
                        row[..r].fill(0.0);
                        row[r + blk.sw..].fill(0.0);
                        let src = &resid[(blk.y0 + y) * w + blk.x0..(blk.y0 + y) * w + blk.x0 + blk.sw];
                        for ((d, s), q) in row[r..r + blk.sw].iter_mut().zip(src).zip(&cxt[blk.x0..blk.x0 + blk.sw]) {
                            *d = a * q * s;
                        }
                    }
                    let sh = blk.sh;
                    fft.forward_rows_with(&wk.buf, &mut wk.spec, |y| y >= r && y < r + sh, &mut wk.scratch);
                    for ((g, s), a) in gh.iter_mut().zip(&wk.spec).zip(&blk.a_hat) {
                        *g += s * a.conj();
                    }
                }
                wk.spec.copy_from_slice(gh);
                fft.inverse_rows_with(&mut wk.spec, &mut wk.out, |y| y <= r || y + r >= fh, &mut wk.scratch);
                for (o, &i) in ot.iter_mut().zip(index) {
                    *o = wk.out[i];
                }
            },
        );
        self.g_hat = g_hat;
        0.5 * f
    }

    /// Largest eigenvalue of the data term's Hessian on the simplices' tangent space (each
    /// kernel's component of zero sum), by power iteration from `start` (or a fixed
    /// pseudo-random vector when it is empty), times a safety factor of 1.3. `start` returns
    /// the last iterate, a warm start for the next channel's (similar) operator.
    fn lipschitz(&mut self, iterations: usize, start: &mut Vec<f32>) -> f32 {
        let (k2, n) = (self.k * self.k, self.b_hat.len() * self.k * self.k);
        let mut v: Vec<f32> = if start.len() == n { start.clone() } else { (0..n).map(|i| ((i * 7919 % 101) as f32 / 101.0) - 0.5).collect() };
        let mut hv = vec![0.0; n];
        let zero_mean = |v: &mut [f32]| {
            for c in v.chunks_mut(k2) {
                let m = c.iter().sum::<f32>() / k2 as f32;
                c.iter_mut().for_each(|x| *x -= m);
            }
        };
        let mut est = 0.0f64;
        for _ in 0..iterations.max(1) {
            zero_mean(&mut v);
            let nrm = v.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt().max(1e-30);
            v.iter_mut().for_each(|x| *x = (*x as f64 / nrm) as f32);
            self.normal(&v.clone(), &mut hv, false);
            zero_mean(&mut hv);
            est = hv.iter().zip(&v).map(|(&a, &b)| a as f64 * b as f64).sum::<f64>();
            std::mem::swap(&mut v, &mut hv);
        }
        *start = v;
        (est.max(1e-30) * 1.3) as f32
    }
}

impl PrimalDual for JointProblem {
    fn primal_len(&self) -> usize {
        self.b_hat.len() * self.k * self.k
    }
    fn dual_len(&self) -> usize {
        self.b_hat.len() * 2 * (self.k + 1) * (self.k + 1)
    }
    fn apply_k(&self, x: &[f32], out: &mut [f32]) {
        let (k2, d) = (self.k * self.k, 2 * (self.k + 1) * (self.k + 1));
        for (xb, ob) in x.chunks(k2).zip(out.chunks_mut(d)) {
            tv_gradient(xb, self.k, ob);
        }
    }
    fn apply_kt(&self, y: &[f32], out: &mut [f32]) {
        let (k2, d) = (self.k * self.k, 2 * (self.k + 1) * (self.k + 1));
        for (yb, ob) in y.chunks(d).zip(out.chunks_mut(k2)) {
            tv_gradient_adjoint(yb, self.k, ob);
        }
    }
    fn prox_f_conj(&mut self, _sigma: f32, y: &mut [f32]) {
        let d = 2 * (self.k + 1) * (self.k + 1);
        for (yb, &lam) in y.chunks_mut(d).zip(&self.lambda) {
            let (gx, gy) = yb.split_at_mut(d / 2);
            let lam = lam.max(1e-30);
            for (a, b) in gx.iter_mut().zip(gy.iter_mut()) {
                let s = (*a * *a + *b * *b).sqrt() / lam;
                if s > 1.0 {
                    *a /= s;
                    *b /= s;
                }
            }
        }
    }
    fn prox_g(&mut self, _tau: f32, x: &mut [f32]) {
        let k2 = self.k * self.k;
        for (xb, &t) in x.chunks_mut(k2).zip(&self.totals) {
            project_simplex(xb, t);
        }
    }
}

/// Largest number of data pixels the joint fit uses. Beyond it (12-megapixel captures) every
/// n-th block is kept, in a staggered pattern so every tile's support keeps data: the
/// kernels' ~10⁵ unknowns per channel are still determined by millions of pixels, at a
/// fraction of the cost.
pub const JOINT_DATA_PIXELS: usize = 2_500_000;

/// Splits of one axis into blocks: `(start, length)` intervals.
type Splits = Vec<(usize, usize)>;

/// The block layout of the blocked convolutions: intervals along x and y and the FFT side `F`.
///
/// The cost of one pass is `F² · (Σ_x a_x) · (Σ_y a_y)` with `a` the number of tiles active
/// (non-zero weight) on an interval. Candidates: every axis split evenly into blocks of at most
/// `m` kernels, or cut at the PSF centres (where the set of active tiles changes, so a block
/// sees at most four tiles per axis) and then split evenly, for `m = 2…8`; the cheapest wins.
fn block_layout(cx: &[Vec<f32>], cy: &[Vec<f32>], xs: &[f64], ys: &[f64], k: usize) -> (Splits, Splits, usize) {
    let r = k / 2;
    let split = |cuts: &[usize], s_max: usize| -> Splits {
        let mut out = Vec::new();
        for win in cuts.windows(2) {
            let len = win[1] - win[0];
            if len == 0 {
                continue;
            }
            let parts = len.div_ceil(s_max);
            let step = len.div_ceil(parts);
            let mut a = win[0];
            while a < win[1] {
                out.push((a, step.min(win[1] - a)));
                a += step;
            }
        }
        out
    };
    let active = |fs: &[Vec<f32>], sp: &Splits| -> usize { sp.iter().map(|&(a, l)| fs.iter().filter(|f| f[a..a + l].iter().any(|&v| v != 0.0)).count()).sum() };
    let centre_cuts = |cs: &[f64], n: usize| -> Vec<usize> {
        let mut c = vec![0];
        c.extend(cs.iter().map(|&x| ((x + 0.5).round().max(0.0) as usize).min(n)));
        c.push(n);
        c.dedup();
        c
    };
    let (w, h) = (cx.first().map_or(0, |f| f.len()), cy.first().map_or(0, |f| f.len()));
    let mut best: Option<(f64, Splits, Splits, usize)> = None;
    for m in 2..=8 {
        let s_max = m * k;
        for aligned in [false, true] {
            let (cut_x, cut_y) = if aligned { (centre_cuts(xs, w), centre_cuts(ys, h)) } else { (vec![0, w], vec![0, h]) };
            let (sx, sy) = (split(&cut_x, s_max), split(&cut_y, s_max));
            let longest = sx.iter().chain(&sy).map(|&(_, l)| l).max().unwrap_or(1);
            let f = good_size(longest + 2 * r);
            let cost = (f * f) as f64 * (active(cx, &sx) * active(cy, &sy)) as f64;
            if best.as_ref().map_or(true, |b| cost < b.0) {
                best = Some((cost, sx, sy, f));
            }
        }
    }
    match best {
        Some((_, sx, sy, f)) => (sx, sy, f),
        None => (vec![(0, w)], vec![(0, h)], good_size(w.max(h) + 2 * r)),
    }
}

/// Inner iterations of the TV–simplex prox per outer step (warm-started dual).
const PROX_ITERATIONS: usize = 12;

/// `out = argmin_{x ≥ 0, 1ᵀx = total} ½‖x − v‖² + γ·TV(x)` by projected gradient on the dual
/// (Beck & Teboulle 2009, with the constraint): `x = P(v − Kᵀq)`, `q ← Π_{|q|≤γ}(q + Kx/8)`,
/// `‖K‖² ≤ 8`. `q` is the warm start and is updated in place. Kernel-sized work only.
fn prox_tv_simplex(v: &[f32], q: &mut [f32], gamma: f32, total: f32, k: usize, iterations: usize, out: &mut [f32]) {
    let d = q.len();
    let mut kx = vec![0.0f32; d];
    let mut ktq = vec![0.0f32; k * k];
    let gamma = gamma.max(1e-30);
    for it in 0..=iterations {
        tv_gradient_adjoint(q, k, &mut ktq);
        for ((o, &a), &b) in out.iter_mut().zip(v).zip(&ktq) {
            *o = a - b;
        }
        project_simplex(out, total);
        if it == iterations {
            break;
        }
        tv_gradient(out, k, &mut kx);
        let (qx, qy) = q.split_at_mut(d / 2);
        let (kxx, kxy) = kx.split_at(d / 2);
        for (((a, b), &ga), &gb) in qx.iter_mut().zip(qy.iter_mut()).zip(kxx).zip(kxy) {
            *a += ga / 8.0;
            *b += gb / 8.0;
            let s = (*a * *a + *b * *b).sqrt() / gamma;
            if s > 1.0 {
                *a /= s;
                *b /= s;
            }
        }
    }
}

/// Iterations over which the data term's relative decrease is measured for the stopping rule.
const STALL_WINDOW: usize = 5;

/// Stop when the data term `½‖M r‖²` (∝ χ²) fell by less than this fraction over the last
/// [`STALL_WINDOW`] iterations: the fit no longer changes at the noise level.
const STALL_DECREASE: f64 = 1e-3;

/// FISTA (Beck & Teboulle 2009) with adaptive restart (O'Donoghue & Candès 2015) on
/// `½‖M(pred(b) − j)‖² + Σ λ_t TV(b_t)` over the simplices, step `1/L` with `L` the Lipschitz
/// constant on the simplices' tangent space; the prox is [`prox_tv_simplex`], its duals `q`
/// carried over between steps (and calls). Stops (after `min_iterations`) at a relative step
/// below `tolerance`, or when the data term stalls ([`STALL_DECREASE`]).
fn fista(p: &mut JointProblem, x: &mut [f32], q: &mut [f32], opts: &SplitOptions, l_f: f32) -> Stats {
    let n = x.len();
    let (k, k2, d) = (p.k, p.k * p.k, 2 * (p.k + 1) * (p.k + 1));
    let mut z = x.to_vec();
    let mut x_prev = x.to_vec();
    let mut g = vec![0.0f32; n];
    let mut v = vec![0.0f32; n];
    let mut t = 1.0f64;
    let mut stats = Stats { operator_norm: 8f32.sqrt(), ..Default::default() };
    let mut history = Vec::with_capacity(opts.max_iterations);
    for it in 1..=opts.max_iterations {
        stats.primal_objective = p.normal(&z, &mut g, true);
        history.push(stats.primal_objective);
        p.progress.inc(1);
        for ((vi, &zi), &gi) in v.iter_mut().zip(&z).zip(&g) {
            *vi = zi - gi / l_f;
        }
        let (lambda, totals) = (&p.lambda, &p.totals);
        x.par_chunks_mut(k2).zip(v.par_chunks(k2)).zip(q.par_chunks_mut(d)).zip(lambda.par_iter().zip(totals.par_iter())).for_each(|(((xb, vb), qb), (&lam, &tot))| {
            prox_tv_simplex(vb, qb, lam / l_f, tot, k, PROX_ITERATIONS, xb);
        });
        let (mut dx2, mut x2, mut dot) = (0.0f64, 0.0f64, 0.0f64);
        for i in 0..n {
            let dx = (x[i] - x_prev[i]) as f64;
            dx2 += dx * dx;
            x2 += (x[i] as f64) * (x[i] as f64);
            dot += (z[i] - x[i]) as f64 * dx;
        }
        // restart the momentum when the step goes against the gradient mapping
        if dot > 0.0 {
            t = 1.0;
        }
        let t_new = 0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt());
        let beta = ((t - 1.0) / t_new) as f32;
        for i in 0..n {
            z[i] = x[i] + beta * (x[i] - x_prev[i]);
        }
        x_prev.copy_from_slice(x);
        t = t_new;
        stats.iterations = it;
        let crit = (dx2 / x2.max(1e-300)).sqrt();
        stats.criterion = crit;
        let stalled = it > STALL_WINDOW && history[it - 1 - STALL_WINDOW] - history[it - 1] < STALL_DECREASE * history[it - 1];
        if it >= opts.min_iterations && (crit < opts.tolerance || stalled) {
            stats.converged = true;
            break;
        }
    }
    stats
}

/// Builds the joint problem of one channel (see [`refine_channel`]); the data are subsampled
/// to about `max_pixels` pixels.
fn build_problem(open: &Plane, sharp: &Plane, valid: &[bool], grid: &PsfGrid, kernels: &[Plane], fits: &[(f32, usize, f64)], max_pixels: usize) -> JointProblem {
    let (w, h) = (open.width, open.height);
    let k = grid.kernel_size;
    let r = k / 2;
    let (xs, ys) = (grid.column_xs(), grid.row_ys());
    let factors = |cs: &[f64], n: usize| -> Vec<Vec<f32>> {
        let mut out = vec![vec![0.0f32; n]; cs.len()];
        for p in 0..n {
            for (i, q) in crate::optics::psf_grid::hat_weights_1d(cs, p as f64) {
                out[i][p] += q;
            }
        }
        out
    };
    let (cx, cy) = (factors(&xs, w), factors(&ys, h));
    let (bx, by, f) = block_layout(&cx, &cy, &xs, &ys, k);
    let fft = Fft2::plan(f, f);
    let mut blocks = Vec::new();
    for &(y0, sh) in &by {
        for &(x0, sw) in &bx {
            let tiles: Vec<usize> = (0..grid.tile_count())
                .filter(|&t| cx[t % grid.columns][x0..x0 + sw].iter().any(|&v| v != 0.0) && cy[t / grid.columns][y0..y0 + sh].iter().any(|&v| v != 0.0))
                .collect();
            blocks.push((x0, y0, sw, sh, tiles));
        }
    }
    // data subsampling on large images: keep every n-th block in a staggered pattern
    let mut mask = valid.to_vec();
    let total: usize = blocks.iter().map(|b| b.2 * b.3).sum();
    let keep_every = total.div_ceil(max_pixels.max(1)).max(1);
    if keep_every > 1 {
        let nbx = bx.len();
        let (kept, dropped): (Vec<_>, Vec<_>) = blocks.into_iter().enumerate().partition(|(i, _)| {
            let (ix, iy) = (i % nbx, i / nbx);
            (ix + 2 * iy) % keep_every == 0
        });
        for (_, (x0, y0, sw, sh, _)) in &dropped {
            for y in *y0..y0 + sh {
                mask[y * w + x0..y * w + x0 + sw].fill(false);
            }
        }
        blocks = kept.into_iter().map(|(_, b)| b).collect();
    }
    let valid = &mask[..];
    let blocks: Vec<Block> = blocks
        .into_par_iter()
        .map(|(x0, y0, sw, sh, tiles)| {
            let win = sharp.window_reflect(x0 as isize - r as isize, y0 as isize - r as isize, f, f);
            let a_hat = fft.forward(&win.data);
            Block { x0, y0, sw, sh, a_hat, tiles }
        })
        .collect();
    let mut blocks_of = vec![Vec::new(); grid.tile_count()];
    for (bi, blk) in blocks.iter().enumerate() {
        for &t in &blk.tiles {
            blocks_of[t].push(bi);
        }
    }
    // λ = c · σ · sd · √N: rescale the window's √N to the effective data Σ w_t² M here
    let mut lam = Vec::with_capacity(grid.tile_count());
    for (t, &(l0, n0, _)) in fits.iter().enumerate().take(grid.tile_count()) {
        let (i, j) = (t % grid.columns, t / grid.columns);
        let mut w2 = 0.0f64;
        for y in 0..h {
            let a = cy[j][y];
            if a == 0.0 {
                continue;
            }
            for x in 0..w {
                let q = a * cx[i][x];
                if q != 0.0 && valid[y * w + x] {
                    w2 += (q as f64) * (q as f64);
                }
            }
        }
        lam.push(l0 * (w2 / n0.max(1) as f64).sqrt() as f32);
    }
    let index: Vec<usize> = (0..k * k)
        .map(|i| {
            let (u, v) = ((i % k) as isize - r as isize, (i / k) as isize - r as isize);
            (v.rem_euclid(f as isize) as usize) * f + u.rem_euclid(f as isize) as usize
        })
        .collect();
    let spectra = vec![vec![Complex32::new(0.0, 0.0); fft.spectrum_len()]; grid.tile_count()];
    let totals: Vec<f32> = kernels.iter().map(|p| p.sum() as f32).collect();
    JointProblem {
        w,
        k,
        columns: grid.columns,
        fft,
        blocks,
        blocks_of,
        cx,
        cy,
        index,
        b_hat: spectra.clone(),
        g_hat: spectra,
        blurred: open.data.clone(),
        mask,
        lambda: lam,
        totals,
        pred: vec![0.0; w * h],
        progress: indicatif::ProgressBar::hidden(),
    }
}

/// Refines `kernels` (one channel, in the grid's tile order) in place. `fits[t] = (λ, N, σ̂)`
/// are the TV weight, data pixel count and noise level of window fit `t`: `λ = c·σ̂·sd·√N`.
/// The joint fit first runs a quarter of its iterations with `λ` rescaled to the data the
/// kernel sees here (`√Σ_x w_t² M` for `√N`), then replaces `σ̂` (which counted the window
/// model's mismatch) by the joint model's residual RMS and continues. Returns the loop's
/// statistics and the masked residual RMS (at the last extrapolated point, within a step of
/// the result). `power` carries the Lipschitz power iteration's vector from one channel to the
/// next (start with an empty vector): a warm start needs 2 iterations instead of 5.
/// `progress` advances by one per iteration. The data are subsampled to about `max_pixels`
/// pixels (the pipeline passes [`JOINT_DATA_PIXELS`]).
#[allow(clippy::too_many_arguments)]
pub fn refine_channel(
    open: &Plane,
    sharp: &Plane,
    valid: &[bool],
    grid: &PsfGrid,
    kernels: &mut [Plane],
    fits: &[(f32, usize, f64)],
    opts: &SplitOptions,
    power: &mut Vec<f32>,
    progress: &indicatif::ProgressBar,
    max_pixels: usize,
) -> (Stats, f64) {
    let mut p = build_problem(open, sharp, valid, grid, kernels, fits, max_pixels);
    p.progress = progress.clone();
    let k = grid.kernel_size;
    let mut x: Vec<f32> = kernels.iter().flat_map(|p| p.data.iter().copied()).collect();
    let l_f = p.lipschitz(if power.is_empty() { 5 } else { 2 }, power);
    let mut q = vec![0.0f32; p.dual_len()];
    let count = p.mask.iter().filter(|&&b| b).count().max(1);
    let first = SplitOptions { max_iterations: opts.max_iterations / 4, min_iterations: usize::MAX, tolerance: 0.0 };
    let st1 = fista(&mut p, &mut x, &mut q, &first, l_f);
    let mut g = vec![0.0f32; x.len()];
    let f1 = if st1.iterations > 0 { st1.primal_objective } else { p.normal(&x, &mut g, true) };
    let sigma_joint = (2.0 * f1 / count as f64).sqrt();
    for (l, &(_, _, s0)) in p.lambda.iter_mut().zip(fits) {
        *l *= (sigma_joint / s0.max(1e-12)) as f32;
    }
    let rest = SplitOptions { max_iterations: opts.max_iterations.saturating_sub(st1.iterations), ..opts.clone() };
    let mut stats = fista(&mut p, &mut x, &mut q, &rest, l_f);
    stats.iterations += st1.iterations;
    let f = if stats.iterations > st1.iterations { stats.primal_objective } else { p.normal(&x, &mut g, true) };
    for (kp, xb) in kernels.iter_mut().zip(x.chunks(k * k)) {
        kp.data.copy_from_slice(xb);
    }
    (stats, (2.0 * f / count as f64).sqrt())
}

#[cfg(test)]
mod tests {
    use crate::estimate::{estimate, relative_error, EstimateOptions};
    use crate::image::{Image, Plane};
    use crate::optics::forward::blur_channel;
    use crate::optics::psf_grid::PsfGrid;
    use crate::rng::Rng;

    /// A field whose PSF changes quickly (width and centroid vary across a 4×3 grid).
    fn truth(w: usize, h: usize, k: usize) -> PsfGrid {
        let (cols, rows) = (4, 3);
        let centers = PsfGrid::regular_centers(w, h, cols, rows);
        let kernels = (0..cols * rows)
            .map(|t| {
                let (c, r) = ((t % cols) as f32, (t / cols) as f32);
                let (sx, sy) = (0.8 + 0.7 * c, 2.2 - 0.6 * r);
                let (mx, my) = (0.9 * (c - 1.5), 0.8 * (r - 1.0));
                let half = (k / 2) as f32;
                let mut p = Plane::from_fn(k, k, |x, y| {
                    let (dx, dy) = ((x as f32 - half - mx) / sx, (y as f32 - half - my) / sy);
                    (-0.5 * (dx * dx + dy * dy)).exp()
                });
                let s = p.sum() as f32;
                p.scale(1.0 / s);
                p
            })
            .collect();
        PsfGrid { kernel_size: k, columns: cols, rows, centers, channels: vec!["Y".into()], kernels: vec![kernels] }
    }

    fn pair(g: &PsfGrid, w: usize, h: usize, noise: f32, seed: u64) -> (Plane, Plane) {
        let mut r = Rng::new(seed);
        let sharp = Plane::from_fn(w, h, |_, _| if r.uniform() < 0.5 { 0.2 } else { 0.8 });
        let clean = blur_channel(&sharp, g, 0);
        let open = Plane::from_fn(w, h, |x, y| clean.get(x, y) + noise * r.normal() as f32);
        (open, sharp)
    }

    fn random_kernels(g: &mut PsfGrid, seed: u64) {
        let mut r = Rng::new(seed);
        let k = g.kernel_size;
        for kp in g.kernels[0].iter_mut() {
            *kp = Plane::from_fn(k, k, |_, _| r.uniform() as f32);
            let s = kp.sum() as f32;
            kp.scale(1.0 / s);
        }
    }

    /// The blocked FFT operator is the forward model of `optics::forward` (same mirrored
    /// boundaries), and its normal operator is symmetric with `f = ½⟨b, Nb⟩`.
    #[test]
    fn blocked_operator_matches_the_forward_model_and_is_self_adjoint() {
        let (w, h, k) = (157, 113, 9);
        let mut g = truth(w, h, k);
        random_kernels(&mut g, 3);
        let (open, sharp) = pair(&g, w, h, 0.01, 4);
        let valid = vec![true; w * h];
        let fits = vec![(1e-3f32, 1000usize, 0.01f64); g.tile_count()];
        let mut p = super::build_problem(&open, &sharp, &valid, &g, &g.kernels[0], &fits, usize::MAX);
        assert!(p.blocks.len() > 1, "several blocks");
        let b: Vec<f32> = g.kernels[0].iter().flat_map(|q| q.data.iter().copied()).collect();
        let mut out = vec![0.0f32; b.len()];
        let f = p.normal(&b, &mut out, true);
        let pred = blur_channel(&sharp, &g, 0);
        let direct: f64 = pred.data.iter().zip(&open.data).map(|(a, o)| 0.5 * ((a - o) as f64).powi(2)).sum();
        assert!((f - direct).abs() <= 1e-3 * direct, "blocked {f} vs direct {direct}");
        // symmetry and energy of the normal operator N = AᵀMA
        let mut r = Rng::new(9);
        let u: Vec<f32> = (0..b.len()).map(|_| r.normal() as f32).collect();
        let v: Vec<f32> = (0..b.len()).map(|_| r.normal() as f32).collect();
        let (mut nu, mut nv) = (vec![0.0f32; b.len()], vec![0.0f32; b.len()]);
        let fu = p.normal(&u, &mut nu, false);
        p.normal(&v, &mut nv, false);
        let dot = |a: &[f32], c: &[f32]| a.iter().zip(c).map(|(x, y)| *x as f64 * *y as f64).sum::<f64>();
        let (a1, a2) = (dot(&nu, &v), dot(&u, &nv));
        assert!((a1 - a2).abs() <= 1e-3 * a1.abs().max(a2.abs()), "⟨Nu, v⟩ {a1} vs ⟨u, Nv⟩ {a2}");
        let e = 0.5 * dot(&u, &nu);
        assert!((fu - e).abs() <= 1e-3 * e, "f {fu} vs ½⟨u, Nu⟩ {e}");
    }

    /// RMS of `a − b` over the pixels at least `m` from the border.
    fn interior_rms(a: &Plane, b: &Plane, m: usize) -> f64 {
        let (w, h) = (a.width, a.height);
        let (mut ss, mut n) = (0.0f64, 0usize);
        for y in m..h - m {
            for x in m..w - m {
                ss += ((a.get(x, y) - b.get(x, y)) as f64).powi(2);
                n += 1;
            }
        }
        (ss / n as f64).sqrt()
    }

    /// With the data subsampled to a third, every tile keeps data and the joint fit still
    /// brings the prediction of an independent pair to within 10% of the noise.
    #[test]
    fn subsampled_joint_fit_still_converges() {
        let (w, h, k, noise) = (192, 144, 11, 0.003f32);
        let g = truth(w, h, k);
        let (open, sharp) = pair(&g, w, h, noise, 1);
        let (open2, sharp2) = pair(&g, w, h, noise, 2);
        let img = |p: &Plane| Image::new(vec![p.clone()]);
        let opts = EstimateOptions { kernel_size: Some(k), tile: Some(48), window: Some(48), joint_iterations: 0, tolerance: 1e-4, ..Default::default() };
        let est = estimate(&img(&open), &img(&sharp), &opts).expect("estimate");
        let grid = est.profile.grid.clone();
        let s = est.profile.meta.exposure_ratio[0] as f32;
        let mut kernels = grid.kernels[0].clone();
        let fits = vec![(est.profile.meta.estimation.lambda as f32, 48 * 48, est.noise_sigma[0]); grid.tile_count()];
        let sharp_s = est.pinhole_registered[0].map(|v| v * s);
        let cap = w * h / 3;
        let p = super::build_problem(&est.open_linear[0], &sharp_s, &est.valid_masks[0], &grid, &kernels, &fits, cap);
        let kept = p.mask.iter().filter(|&&b| b).count();
        assert!(kept < w * h / 2 && kept > w * h / 6, "kept {kept} of {}", w * h);
        assert!(p.blocks_of.iter().all(|b| !b.is_empty()), "a tile lost all its data");
        let o = crate::solve::primal_dual::SplitOptions { max_iterations: 200, min_iterations: 5, tolerance: 1e-5 };
        super::refine_channel(&est.open_linear[0], &sharp_s, &est.valid_masks[0], &grid, &mut kernels, &fits, &o, &mut Vec::new(), &indicatif::ProgressBar::hidden(), cap);
        let mut refined = grid.clone();
        refined.kernels[0] = kernels;
        let cv = |gr: &PsfGrid| interior_rms(&blur_channel(&sharp2.map(|v| v * s), gr, 0), &open2, k / 2) / noise as f64;
        let (cv0, cv1) = (cv(&grid), cv(&refined));
        assert!(cv1 < 1.10 && cv1 < cv0 - 0.05, "subsampled joint cv {cv1} vs window fits {cv0}");
    }

    /// The joint fit predicts an independent pair much better than the per-window fits, to
    /// within 10% of the noise, and its kernels are closer to the truth.
    #[test]
    fn joint_refinement_beats_window_fits_on_a_varying_field() {
        let (w, h, k, noise) = (192, 144, 11, 0.003f32);
        let g = truth(w, h, k);
        let (open, sharp) = pair(&g, w, h, noise, 1);
        let (open2, sharp2) = pair(&g, w, h, noise, 2);
        let img = |p: &Plane| Image::new(vec![p.clone()]);
        let run = |joint: usize| {
            let opts = EstimateOptions { kernel_size: Some(k), tile: Some(48), window: Some(48), joint_iterations: joint, tolerance: 1e-4, ..Default::default() };
            let est = estimate(&img(&open), &img(&sharp), &opts).expect("estimate");
            let grid = &est.profile.grid;
            let s = est.profile.meta.exposure_ratio[0] as f32;
            let ratio = interior_rms(&blur_channel(&sharp2.map(|v| v * s), grid, 0), &open2, k / 2) / noise as f64;
            let mut errs: Vec<f64> = (0..grid.tile_count()).map(|t| relative_error(&grid.kernels[0][t], &g.kernels[0][t])).collect();
            errs.sort_by(|a, b| a.total_cmp(b));
            (ratio, errs[errs.len() / 2])
        };
        let (cv0, e0) = run(0);
        let (cv1, e1) = run(200);
        eprintln!("window fits: cv {cv0:.3}, median error {e0:.3}; joint: cv {cv1:.3}, median error {e1:.3}");
        assert!(cv1 < 1.10, "joint cv {cv1}");
        assert!(cv1 < cv0 - 0.05, "joint {cv1} vs window fits {cv0}");
        assert!(e1 < e0, "joint error {e1} vs {e0}");
    }
}
