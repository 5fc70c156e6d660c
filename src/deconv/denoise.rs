//! Block-DCT shrinkage of a deconvolved image (the "regularised inverse + coloured-noise
//! denoising" stage of DEB-BM3D, Dabov et al. 2008): a light BM3D on luminance (groups of
//! similar blocks, 2-D DCT + Haar across the group; [`DenoiseOptions::search`]) and sliding
//! single blocks on the chroma planes.
//!
//! The image is denoised in the domain its result is delivered in (gamma-encoded values, where
//! the benchmark measures PSNR) and in an orthonormal opponent colour space
//! (`Y = (R+G+B)/√3`, `C₁ = (R−B)/√2`, `C₂ = (R−2G+B)/√6`), so the strongly correlated channels
//! of a photograph share their structure in `Y` and the chroma planes are nearly flat.
//! Other channel counts (monochrome, multispectral) are denoised channel by channel, each with
//! its own noise level (block matching on the first `bm_channels` of them).
//! Two stages on every 8×8 block (or group) of a lattice with step `s` (Foi, Katkovnik &
//! Egiazarian's sliding-window DCT; BM3D's two steps):
//! 1. hard thresholding of the block's DCT coefficients at `τ σ_b` (DC kept); the inverse is
//!    aggregated with weight `1 / (σ_b² N_b)`, `N_b` the retained coefficients;
//! 2. empirical Wiener shrinkage `Ŷ = P²/(P² + σ_b²) · Z` with the stage-1 result `P` as pilot,
//!    aggregated with weight `1 / (σ_b² Σ W²)`.
//!
//! `σ_b` is the block's noise level on the encoded axis: the linear noise level of the
//! deconvolved channel times the slope `g'(v̄_b)` of the transfer curve at the block's mean
//! linear brightness (the delta method), and, for signal-dependent noise, by the local level
//! of the noise law ([`DenoiseOptions::local_variance`]). Work is done in strips of rows with a halo, so only a
//! strip's buffers are held besides the input and the output.

use crate::image::{Plane, Transfer};
use rayon::prelude::*;

const B: usize = 8;

/// Settings of the stage.
#[derive(Clone, Debug)]
pub struct DenoiseOptions {
    /// Linear noise level of each (RGB) channel of the deconvolved image.
    pub sigma: Vec<f32>,
    /// Encoding the denoiser works in (its noise level follows the slope of the curve).
    pub transfer: Transfer,
    /// Block lattice step (1..=8).
    pub step: usize,
    /// Hard threshold `τ` (in units of `σ_b`) of stage 1.
    pub threshold: f32,
    /// Noise multiplier of the chroma planes relative to luminance (the cross-channel prior makes
    /// chroma noise smaller than luminance noise).
    pub chroma: f32,
    /// Run the Wiener stage.
    pub wiener: bool,
    /// Block matching (BM3D-style groups): search radius in pixels
    /// (0: sliding-window DCT only).
    pub search: usize,
    /// How many of the decorrelated channels (luminance first) are filtered with block matching;
    /// the others use single sliding blocks.
    pub bm_channels: usize,
    /// Search step (pixels) inside the window.
    pub search_step: usize,
    /// Most blocks per group (rounded down to a power of 2).
    pub group: usize,
    /// Matching threshold: a candidate joins when its mean squared difference to the reference
    /// is below `match_tau · σ_b²`.
    pub match_tau: f32,
    /// Coloured noise (docs/deconvolution.md "Coloured-noise denoising"): per decorrelated plane
    /// (opponent `Y, C₁, C₂` for RGB, else the channels), the linear-axis variance `σ²_k` of each
    /// 8×8 DCT coefficient (row-major `k = 8u + v`) of the noise the stage faces. When set, it
    /// replaces `sigma` and `chroma`: the plane's level is `σ = √(mean_k σ²_k)` and coefficient
    /// `k` is thresholded and Wiener-shrunk at `σ_b √(σ²_k / mean σ²)`. The variances may vary
    /// across the field ([`CoefficientField`]: interpolated between nodes at the block centre).
    pub coefficient_variance: Option<CoefficientField>,
    /// Exponent `p`: the block noise level is `σ g'(0.18) (g'(v̄_b)/g'(0.18))^p` (1: the delta
    /// method; smaller values account for the solver's prior, which already regularises dark
    /// regions more).
    pub slope_power: f32,
    /// Local noise level (signal-dependent noise): per RGB channel, the ratio
    /// `m_c(x) = V_c(x) / σ_c²` of the local noise variance to the variance `sigma` (or
    /// `coefficient_variance`) describes. A block's level on plane `i` is multiplied by
    /// `√(Σ_c a_ic m_c(b))`, `a_ic = w_ic σ_c² / Σ_c w_ic σ_c²` with `w_ic` the squared
    /// opponent weights (identity without the opponent transform), `m_c` read at the block
    /// centre. `None`: stationary noise.
    pub local_variance: Option<Vec<Plane>>,
    pub parallel: bool,
}

/// Field-varying coloured noise (docs/deconvolution.md "Per-tile coloured noise"): the
/// variances `σ²_k` of [`DenoiseOptions::coefficient_variance`] at the nodes of a rectangular
/// lattice of image positions, blended bilinearly between them (a partition of unity, as the
/// deconvolution blends its tiles) and held constant beyond the outer nodes:
///
/// ```text
/// σ²_k(x, y) = Σ_ij a_i(x) b_j(y) σ²_k,ij        (a, b the 1-D linear hat weights)
/// ```
///
/// Positions in pixels (block centres); variances on the linear axis, per decorrelated plane.
#[derive(Clone, Debug)]
pub struct CoefficientField {
    /// Node columns (pixels, increasing).
    pub xs: Vec<f32>,
    /// Node rows (pixels, increasing).
    pub ys: Vec<f32>,
    /// `variance[j · xs.len() + i][plane]`: the node `(xs[i], ys[j])`'s variances.
    pub variance: Vec<Vec<[f32; 64]>>,
}

impl CoefficientField {
    /// The same variances everywhere (one node).
    pub fn uniform(variance: Vec<[f32; 64]>) -> Self {
        Self { xs: vec![0.0], ys: vec![0.0], variance: vec![variance] }
    }

    /// Planes described (the smallest count over the nodes).
    pub fn planes(&self) -> usize {
        self.variance.iter().map(Vec::len).min().unwrap_or(0)
    }

    /// The linear hat weights of position `v` between `nodes`: (lower node, upper node, weight
    /// of the upper one).
    fn hat(nodes: &[f32], v: f32) -> (usize, usize, f32) {
        let n = nodes.len();
        if n < 2 || v <= nodes[0] {
            return (0, 0, 0.0);
        }
        if v >= nodes[n - 1] {
            return (n - 1, n - 1, 0.0);
        }
        let i = nodes.partition_point(|x| *x <= v).clamp(1, n - 1) - 1;
        let span = (nodes[i + 1] - nodes[i]).max(1e-6);
        (i, i + 1, ((v - nodes[i]) / span).clamp(0.0, 1.0))
    }

    /// `σ²_k` of `plane` at pixel `(x, y)`.
    pub fn at(&self, plane: usize, x: f32, y: f32) -> [f32; 64] {
        let (i0, i1, tx) = Self::hat(&self.xs, x);
        let (j0, j1, ty) = Self::hat(&self.ys, y);
        let nx = self.xs.len();
        let mut v = [0.0f32; 64];
        for (j, wy) in [(j0, 1.0 - ty), (j1, ty)] {
            for (i, wx) in [(i0, 1.0 - tx), (i1, tx)] {
                let wt = wx * wy;
                if wt > 0.0 {
                    v.iter_mut().zip(&self.variance[j * nx + i][plane]).for_each(|(a, b)| *a += wt * b);
                }
            }
        }
        v
    }
}

impl Default for DenoiseOptions {
    /// The defaults `deblur` uses ([`super::DeconvOptions::denoiser`]); `sigma`, `transfer` and
    /// `parallel` are set per call from the noise estimate and the output encoding.
    fn default() -> Self {
        Self {
            sigma: Vec::new(),
            transfer: Transfer::Linear,
            step: 3,
            threshold: 2.7,
            chroma: 1.5,
            wiener: true,
            search: 6,
            bm_channels: 1,
            search_step: 2,
            group: 8,
            match_tau: 10.0,
            slope_power: 0.0,
            coefficient_variance: None,
            local_variance: None,
            parallel: true,
        }
    }
}

/// The orthonormal DCT-II matrix (reference for the fast transforms).
#[cfg(test)]
fn dct_matrix() -> [f32; B * B] {
    let mut m = [0.0f32; B * B];
    for k in 0..B {
        let a = if k == 0 { (1.0 / B as f64).sqrt() } else { (2.0 / B as f64).sqrt() };
        for n in 0..B {
            m[k * B + n] = (a * (std::f64::consts::PI * (2 * n + 1) as f64 * k as f64 / (2 * B) as f64).cos()) as f32;
        }
    }
    m
}

// cos(mπ/16)
const C1: f32 = 0.980_785_3;
const C2: f32 = 0.923_879_5;
const C3: f32 = 0.831_469_6;
const C4: f32 = 0.707_106_77;
const C5: f32 = 0.555_570_24;
const C6: f32 = 0.382_683_43;
const C7: f32 = 0.195_090_32;
const S0: f32 = 0.353_553_38; // 1/√8

/// `D X`: the orthonormal 8-point DCT-II along the row index of a row-major 8×8 block (every
/// column at once; even/odd butterflies, 22 instead of 64 products per column).
#[inline]
fn fdct_rows(x: &[f32; 64]) -> [f32; 64] {
    let mut y = [0.0f32; 64];
    for j in 0..B {
        let v = |i: usize| x[i * B + j];
        let (e0, e1, e2, e3) = (v(0) + v(7), v(1) + v(6), v(2) + v(5), v(3) + v(4));
        let (o0, o1, o2, o3) = (v(0) - v(7), v(1) - v(6), v(2) - v(5), v(3) - v(4));
        let (ee0, ee1, eo0, eo1) = (e0 + e3, e1 + e2, e0 - e3, e1 - e2);
        y[j] = S0 * (ee0 + ee1);
        y[4 * B + j] = 0.5 * C4 * (ee0 - ee1);
        y[2 * B + j] = 0.5 * (C2 * eo0 + C6 * eo1);
        y[6 * B + j] = 0.5 * (C6 * eo0 - C2 * eo1);
        y[B + j] = 0.5 * (C1 * o0 + C3 * o1 + C5 * o2 + C7 * o3);
        y[3 * B + j] = 0.5 * (C3 * o0 - C7 * o1 - C1 * o2 - C5 * o3);
        y[5 * B + j] = 0.5 * (C5 * o0 - C1 * o1 + C7 * o2 + C3 * o3);
        y[7 * B + j] = 0.5 * (C7 * o0 - C5 * o1 + C3 * o2 - C1 * o3);
    }
    y
}

/// `Dᵀ C`: the inverse of [`fdct_rows`].
#[inline]
fn idct_rows(c: &[f32; 64]) -> [f32; 64] {
    let mut x = [0.0f32; 64];
    for j in 0..B {
        let v = |i: usize| c[i * B + j];
        let (p, q) = (S0 * v(0), 0.5 * C4 * v(4));
        let (r0, r1) = (0.5 * (C2 * v(2) + C6 * v(6)), 0.5 * (C6 * v(2) - C2 * v(6)));
        let e = [p + q + r0, p - q + r1, p - q - r1, p + q - r0];
        let o = [
            0.5 * (C1 * v(1) + C3 * v(3) + C5 * v(5) + C7 * v(7)),
            0.5 * (C3 * v(1) - C7 * v(3) - C1 * v(5) - C5 * v(7)),
            0.5 * (C5 * v(1) - C1 * v(3) + C7 * v(5) + C3 * v(7)),
            0.5 * (C7 * v(1) - C5 * v(3) + C3 * v(5) - C1 * v(7)),
        ];
        for n in 0..4 {
            x[n * B + j] = e[n] + o[n];
            x[(7 - n) * B + j] = e[n] - o[n];
        }
    }
    x
}

#[inline]
fn transpose(d: &[f32; 64]) -> [f32; 64] {
    let mut t = [0.0f32; 64];
    for r in 0..B {
        for c in 0..B {
            t[c * B + r] = d[r * B + c];
        }
    }
    t
}

/// `D X Dᵀ` (forward 2-D DCT) of an 8×8 block.
#[inline]
pub(crate) fn dct2(x: &[f32; 64], out: &mut [f32; 64]) {
    *out = transpose(&fdct_rows(&transpose(&fdct_rows(x))));
}

/// `Dᵀ C D` (inverse 2-D DCT) of an 8×8 block.
#[inline]
fn idct2(c: &[f32; 64], out: &mut [f32; 64]) {
    *out = transpose(&idct_rows(&transpose(&idct_rows(c))));
}

/// Block origins along an axis of length `n`: multiples of `step`, plus `n − 8` so the last
/// pixels are covered.
fn lattice(n: usize, step: usize) -> Vec<usize> {
    let mut v: Vec<usize> = (0..=n - B).step_by(step).collect();
    if *v.last().unwrap_or(&0) != n - B {
        v.push(n - B);
    }
    v
}

/// The orthonormal opponent transform (rows `Y`, `C₁`, `C₂`).
pub(crate) const OPP: [[f32; 3]; 3] = [
    [0.577_350_26, 0.577_350_26, 0.577_350_26],
    [0.707_106_77, 0.0, -0.707_106_77],
    [0.408_248_3, -0.816_496_6, 0.408_248_3],
];

/// Denoises `planes` (linear, as the solver delivers them) and returns the result (linear).
/// Images smaller than a block are returned unchanged.
pub fn denoise(planes: &[Plane], opts: &DenoiseOptions) -> Vec<Plane> {
    let nch = planes.len();
    let (w, h) = (planes[0].width, planes[0].height);
    let silent = match &opts.coefficient_variance {
        Some(f) => f.planes() < nch || f.variance.iter().flatten().all(|c| c.iter().all(|s| *s <= 1e-18)),
        None => opts.sigma.len() < nch || opts.sigma.iter().all(|s| *s <= 1e-9),
    };
    if w < B || h < B || nch == 0 || silent {
        return planes.to_vec();
    }
    let plan = Plan::new(planes, opts);
    let starts: Vec<usize> = (0..h).step_by(plan.strip).collect();
    // a few strips per worker at a time, copied out at once: the strips' results never add up
    // to a second copy of the image
    let mut out: Vec<Plane> = (0..nch).map(|_| Plane::new(w, h)).collect();
    for batch in starts.chunks(2 * rayon::current_num_threads().max(1)) {
        let work = |y0: &usize| (*y0, plan.strip_result(*y0));
        let parts: Vec<(usize, Vec<Vec<f32>>)> = if opts.parallel { batch.par_iter().map(work).collect() } else { batch.iter().map(work).collect() };
        for (y0, p) in parts {
            for (c, v) in p.into_iter().enumerate() {
                out[c].data[y0 * w..y0 * w + v.len()].copy_from_slice(&v);
            }
        }
    }
    out
}

/// The slope `g'(v)` of the output encoding at linear value `v`, softened by the exponent `p`
/// ([`DenoiseOptions::slope_power`]): `g'(0.18) (g'(v)/g'(0.18))^p`.
#[derive(Clone, Copy)]
struct Slope {
    transfer: Transfer,
    mid: f32,
    power: f32,
}

impl Slope {
    fn new(transfer: Transfer, power: f32) -> Self {
        let mut s = Self { transfer, mid: 1.0, power };
        s.mid = s.raw(0.18);
        s
    }
    fn raw(&self, v: f32) -> f32 {
        if self.transfer == Transfer::Linear {
            return 1.0;
        }
        let v = v.clamp(1e-4, 1.0);
        let dv = 1e-3 * v;
        (self.transfer.encode(v + dv) - self.transfer.encode(v - dv)) / (2.0 * dv)
    }
    fn at(&self, v: f32) -> f32 {
        self.mid * (self.raw(v) / self.mid).powf(self.power)
    }
}

/// What every strip of one [`denoise`] call shares: the block lattice, the strip geometry and
/// the noise of each decorrelated plane.
struct Plan<'a> {
    planes: &'a [Plane],
    opts: &'a DenoiseOptions,
    w: usize,
    h: usize,
    xs: Vec<usize>,
    ys: Vec<usize>,
    /// Block matching on the first `nbm` planes (search radius `sr`).
    bm: bool,
    nbm: usize,
    sr: usize,
    strip: usize,
    halo: usize,
    opponent: bool,
    sig_lin: Vec<f32>,
    rel: Vec<[f32; 64]>,
    slope: Slope,
    /// `a_ic` of [`DenoiseOptions::local_variance`] per plane (empty without a map).
    local_weights: Vec<Vec<f32>>,
}

/// One strip's decorrelated, encoded planes (rows `a..a + rows` of the image) and the linear
/// mean over channels that sets each block's brightness.
struct Strip {
    a: usize,
    rows: usize,
    noisy: Vec<Vec<f32>>,
    mean_lin: Vec<f32>,
}

impl<'a> Plan<'a> {
    fn new(planes: &'a [Plane], opts: &'a DenoiseOptions) -> Self {
        let (w, h) = (planes[0].width, planes[0].height);
        let step = opts.step.clamp(1, B);
        let bm = opts.search > 0 && opts.group > 1;
        let sr = if bm { opts.search } else { 0 };
        let opponent = planes.len() == 3;
        let (sig_lin, rel) = plane_noise(opts, opponent);
        Self {
            planes,
            opts,
            w,
            h,
            xs: lattice(w, step),
            ys: lattice(h, step),
            bm,
            nbm: opts.bm_channels.max(1),
            sr,
            strip: if bm { 128 } else { 64 },
            halo: 2 * B + 4 * sr,
            opponent,
            sig_lin,
            rel,
            slope: Slope::new(opts.transfer, opts.slope_power),
            local_weights: local_weights(opts, planes.len(), opponent),
        }
    }

    /// `√(Σ_c a_ic m_c(b))` of [`DenoiseOptions::local_variance`] for plane `ch` and the block at
    /// (local row `ly` of strip `s`, column `px`); 1 without a map.
    fn local_gain(&self, s: &Strip, ly: usize, px: usize, ch: usize) -> f32 {
        let (Some(maps), Some(a)) = (&self.opts.local_variance, self.local_weights.get(ch)) else { return 1.0 };
        let k = (s.a + ly + B / 2).min(self.h - 1) * self.w + (px + B / 2).min(self.w - 1);
        a.iter().zip(maps).map(|(a, m)| a * m.data[k].max(0.0)).sum::<f32>().sqrt()
    }

    /// The linear noise level of plane `ch` for the block at (image row `py`, column `px`) and
    /// each DCT coefficient's level relative to it: the plane's constants, or, with a
    /// field-varying [`CoefficientField`], its variances at the block centre.
    fn plane_noise_at(&self, ch: usize, py: usize, px: usize) -> (f32, [f32; 64]) {
        match &self.opts.coefficient_variance {
            Some(f) if f.variance.len() > 1 => level_and_rel(&f.at(ch, (px + B / 2) as f32, (py + B / 2) as f32)),
            _ => (self.sig_lin[ch], self.rel[ch]),
        }
    }

    /// Block origins (image rows) in `[lo, hi)`.
    fn blocks(&self, lo: isize, hi: isize) -> Vec<usize> {
        self.ys.iter().copied().filter(|&py| (py as isize) >= lo && (py as isize) < hi).collect()
    }

    /// The rows of the strip starting at `y0` with the two stages' halos, encoded and
    /// decorrelated.
    fn load_strip(&self, y0: usize) -> Strip {
        let (w, t, nch) = (self.w, self.opts.transfer, self.planes.len());
        let y1 = (y0 + self.strip).min(self.h);
        let a = y0.saturating_sub(self.halo);
        let b = (y1 + self.halo).min(self.h);
        let rows = b - a;
        let lin: Vec<&[f32]> = self.planes.iter().map(|p| &p.data[a * w..b * w]).collect();
        let mean_lin: Vec<f32> = (0..rows * w).map(|i| lin.iter().map(|p| p[i]).sum::<f32>() / nch as f32).collect();
        let enc: Vec<Vec<f32>> = lin.iter().map(|p| p.iter().map(|v| t.encode(*v)).collect()).collect();
        let noisy: Vec<Vec<f32>> = if self.opponent {
            (0..3).map(|i| (0..rows * w).map(|k| OPP[i][0] * enc[0][k] + OPP[i][1] * enc[1][k] + OPP[i][2] * enc[2][k]).collect()).collect()
        } else {
            enc
        };
        Strip { a, rows, noisy, mean_lin }
    }

    /// The encoding slope at the mean linear brightness of the block at (local row, column).
    fn block_gain(&self, s: &Strip, by: usize, bx: usize) -> f32 {
        let mut m = 0.0;
        for r in 0..B {
            for q in 0..B {
                m += s.mean_lin[(by + r) * self.w + bx + q];
            }
        }
        self.slope.at(m / (B * B) as f32)
    }

    /// The denoised rows `y0..y0 + strip` of every channel (linear).
    fn strip_result(&self, y0: usize) -> Vec<Vec<f32>> {
        let s = self.load_strip(y0);
        let y1 = (y0 + self.strip).min(self.h);
        // stage 1 over blocks whose rows lie in [y0 − 2B + 1, y1 + B − 1) (the pilot then is
        // complete on [y0 − B, y1 + B))
        let (mut pilot, wsum) = self.hard_threshold_stage(&s, y0, y1);
        for (p, w) in pilot.iter_mut().zip(&wsum) {
            p.iter_mut().zip(w).for_each(|(p, w)| *p = if *w > 0.0 { *p / w } else { 0.0 });
        }
        let result = if self.opts.wiener { self.wiener_stage(&s, &pilot, y0, y1) } else { pilot };
        self.decode_rows(&result, (y0 - s.a) * self.w, (y1 - s.a) * self.w)
    }

    /// Stage 1: hard thresholding of single blocks (planes without block matching) and of
    /// groups (planes with it); returns the unnormalised aggregate and its weights.
    fn hard_threshold_stage(&self, s: &Strip, y0: usize, y1: usize) -> (Vec<Vec<f32>>, Vec<Vec<f32>>) {
        let (w, n) = (self.w, s.noisy.len());
        let s1 = self.blocks(y0 as isize - 2 * B as isize + 1, y1 as isize + B as isize);
        let mut pilot = vec![vec![0.0f32; s.rows * w]; n];
        let mut wsum = vec![vec![0.0f32; s.rows * w]; n];
        let (mut x, mut c, mut o) = ([0.0f32; 64], [0.0f32; 64], [0.0f32; 64]);
        for &py in &s1 {
            let ly = py - s.a;
            for &px in &self.xs {
                let g = self.block_gain(s, ly, px);
                for (ch, plane) in s.noisy.iter().enumerate() {
                    if self.bm && ch < self.nbm {
                        continue;
                    }
                    let (sl, rc) = self.plane_noise_at(ch, py, px);
                    let sg = sl * g * self.local_gain(s, ly, px, ch);
                    load_block(plane, w, ly, px, &mut x);
                    dct2(&x, &mut c);
                    let rc = &rc;
                    // the estimate's noise variance, in units of sg²: Σ over kept coefficients
                    let kept = hard_threshold(&mut c, self.opts.threshold * sg, rc, 0.0);
                    idct2(&c, &mut o);
                    add_block(&o, 1.0 / (sg * sg * kept).max(1e-20), w, ly, px, &mut pilot[ch], &mut wsum[ch]);
                }
            }
        }
        if self.bm {
            let srs = self.sr as isize;
            let refs = self.blocks(y0 as isize - 2 * B as isize + 2 - 3 * srs, y1 as isize + 3 * srs + B as isize - 1);
            self.bm_planes(s, None, &refs, &mut pilot, &mut wsum);
        }
        (pilot, wsum)
    }

    /// Stage 2: empirical Wiener shrinkage against the pilot; returns the normalised result.
    fn wiener_stage(&self, s: &Strip, pilot: &[Vec<f32>], y0: usize, y1: usize) -> Vec<Vec<f32>> {
        let (w, n) = (self.w, s.noisy.len());
        let s2 = self.blocks(y0 as isize - B as isize + 1, y1 as isize);
        let mut num = vec![vec![0.0f32; s.rows * w]; n];
        let mut den = vec![vec![0.0f32; s.rows * w]; n];
        let (mut x, mut c, mut pc, mut o) = ([0.0f32; 64], [0.0f32; 64], [0.0f32; 64], [0.0f32; 64]);
        for &py in &s2 {
            let ly = py - s.a;
            for &px in &self.xs {
                let g = self.block_gain(s, ly, px);
                for ch in 0..n {
                    if self.bm && ch < self.nbm {
                        continue;
                    }
                    let (sl, rc) = self.plane_noise_at(ch, py, px);
                    let sg = sl * g * self.local_gain(s, ly, px, ch);
                    let s2v = sg * sg;
                    load_block(&s.noisy[ch], w, ly, px, &mut x);
                    dct2(&x, &mut c);
                    load_block(&pilot[ch], w, ly, px, &mut x);
                    dct2(&x, &mut pc);
                    let wn = wiener_shrink(&mut c, &pc, s2v, &rc);
                    idct2(&c, &mut o);
                    add_block(&o, 1.0 / (s2v * wn).max(1e-20), w, ly, px, &mut num[ch], &mut den[ch]);
                }
            }
        }
        if self.bm {
            let srs = self.sr as isize;
            let refs = self.blocks(y0 as isize - B as isize + 1 - srs, y1 as isize + srs);
            self.bm_planes(s, Some(pilot), &refs, &mut num, &mut den);
        }
        num.iter_mut().zip(&den).for_each(|(n, d)| n.iter_mut().zip(d).for_each(|(n, d)| *n = if *d > 0.0 { *n / d } else { 0.0 }));
        num
    }

    /// [`bm_stage`] on each plane filtered with block matching.
    fn bm_planes(&self, s: &Strip, pilot: Option<&[Vec<f32>]>, refs: &[usize], num: &mut [Vec<f32>], den: &mut [Vec<f32>]) {
        let ctx = BmContext { w: self.w, h: self.h, a: s.a, b: s.a + s.rows, xs: &self.xs, opts: self.opts };
        for ch in 0..self.nbm.min(s.noisy.len()) {
            let noise = |ly: usize, px: usize| {
                let (sl, rc) = self.plane_noise_at(ch, s.a + ly, px);
                (sl * self.block_gain(s, ly, px) * self.local_gain(s, ly, px, ch), rc)
            };
            bm_stage(&ctx, &s.noisy[ch], pilot.map(|p| p[ch].as_slice()), refs, &noise, &mut num[ch], &mut den[ch]);
        }
    }

    /// Back to RGB (from the opponent planes) and to linear values, rows `k0..k1` (flat
    /// indices) of the strip.
    fn decode_rows(&self, result: &[Vec<f32>], k0: usize, k1: usize) -> Vec<Vec<f32>> {
        let t = self.opts.transfer;
        if self.opponent {
            (0..3).map(|c| (k0..k1).map(|k| t.decode(OPP[0][c] * result[0][k] + OPP[1][c] * result[1][k] + OPP[2][c] * result[2][k])).collect()).collect()
        } else {
            result.iter().map(|r| r[k0..k1].iter().map(|v| t.decode(*v)).collect()).collect()
        }
    }
}

/// Copies the 8×8 block at (row `ly`, column `px`) of a row-major plane of width `w`.
#[inline]
fn load_block(plane: &[f32], w: usize, ly: usize, px: usize, x: &mut [f32; 64]) {
    for r in 0..B {
        x[r * B..r * B + B].copy_from_slice(&plane[(ly + r) * w + px..(ly + r) * w + px + B]);
    }
}

/// Adds `wt · o` and `wt` into the aggregation buffers at the block (row `ly`, column `px`).
#[inline]
fn add_block(o: &[f32; 64], wt: f32, w: usize, ly: usize, px: usize, num: &mut [f32], den: &mut [f32]) {
    for r in 0..B {
        let row = (ly + r) * w + px;
        for q in 0..B {
            num[row + q] += wt * o[r * B + q];
            den[row + q] += wt;
        }
    }
}

/// Zeroes the AC coefficients below `thr · rel_k`; returns `acc + Σ rel_k²` over the kept ones
/// (DC always kept): the estimate's noise variance in units of the block's `σ_b²`.
#[inline]
fn hard_threshold(c: &mut [f32; 64], thr: f32, rel: &[f32; 64], acc: f32) -> f32 {
    let mut kept = acc + rel[0] * rel[0];
    for (v, r) in c.iter_mut().zip(rel).skip(1) {
        if v.abs() < thr * r {
            *v = 0.0;
        } else {
            kept += r * r;
        }
    }
    kept
}

/// Empirical Wiener shrinkage `c_k ← p_k²/(p_k² + σ_b² rel_k²) · c_k` (DC kept); returns
/// `Σ f_k² rel_k²`, the estimate's noise variance in units of `σ_b²`.
#[inline]
fn wiener_shrink(c: &mut [f32; 64], pc: &[f32; 64], s2v: f32, rel: &[f32; 64]) -> f32 {
    let mut wn = 0.0;
    for (k, ((cv, pv), r)) in c.iter_mut().zip(pc).zip(rel).enumerate() {
        let f = if k == 0 { 1.0 } else { pv * pv / (pv * pv + s2v * r * r).max(1e-30) };
        *cv *= f;
        wn += f * f * r * r;
    }
    wn
}

/// The weights `a_ic` of [`DenoiseOptions::local_variance`] (empty without a map or when the
/// map or `sigma` does not cover every channel).
fn local_weights(opts: &DenoiseOptions, nch: usize, opponent: bool) -> Vec<Vec<f32>> {
    let ok = opts.local_variance.as_ref().is_some_and(|m| m.len() == nch) && opts.sigma.len() >= nch;
    if !ok {
        return Vec::new();
    }
    (0..nch)
        .map(|i| {
            let w: Vec<f32> = (0..nch).map(|c| if opponent { OPP[i][c] * OPP[i][c] } else { f32::from(u8::from(i == c)) } * opts.sigma[c] * opts.sigma[c]).collect();
            let total = w.iter().sum::<f32>();
            w.iter().map(|v| if total > 0.0 { v / total } else { 0.0 }).collect()
        })
        .collect()
}

/// The noise level `σ` of each decorrelated plane (linear axis, before the transfer slope) and
/// each DCT coefficient's level relative to it (`√(σ²_k / mean_k σ²_k)`; all 1 for white noise).
fn plane_noise(opts: &DenoiseOptions, opponent: bool) -> (Vec<f32>, Vec<[f32; 64]>) {
    if let Some(f) = &opts.coefficient_variance {
        return f.variance[0].iter().map(level_and_rel).unzip();
    }
    let sig: Vec<f32> = if opponent {
        (0..3)
            .map(|i| {
                let v: f32 = (0..3).map(|c| OPP[i][c] * OPP[i][c] * opts.sigma[c] * opts.sigma[c]).sum();
                v.sqrt() * if i == 0 { 1.0 } else { opts.chroma }
            })
            .collect()
    } else {
        opts.sigma.clone()
    };
    let n = sig.len();
    (sig, vec![[1.0; 64]; n])
}

/// A plane's level `σ = √(mean_k σ²_k)` and each coefficient's level relative to it,
/// `√(σ²_k / mean_k σ²_k)` (all 1 when the variances vanish).
fn level_and_rel(v: &[f32; 64]) -> (f32, [f32; 64]) {
    let mean = v.iter().sum::<f32>() / 64.0;
    let rel = std::array::from_fn(|k| if mean > 0.0 { (v[k] / mean).max(0.0).sqrt() } else { 1.0 });
    (mean.max(0.0).sqrt(), rel)
}

/// A block's noise for [`bm_stage`]: its level `σ_b` at (local row, column) and each DCT
/// coefficient's level relative to it.
type BlockNoise<'n> = &'n dyn Fn(usize, usize) -> (f32, [f32; 64]);

struct BmContext<'a> {
    w: usize,
    h: usize,
    /// First and one-past-last image row held by the strip buffers.
    a: usize,
    b: usize,
    xs: &'a [usize],
    opts: &'a DenoiseOptions,
}

/// Orthonormal Haar transform across the first `n` (a power of 2) blocks of `g`, coefficient by
/// coefficient (whole blocks at a time, which vectorises); `t` is scratch of the same length.
fn haar_forward(g: &mut [[f32; 64]], t: &mut [[f32; 64]], n: usize) {
    let r = std::f32::consts::FRAC_1_SQRT_2;
    let mut m = n;
    while m > 1 {
        let half = m / 2;
        for i in 0..half {
            for k in 0..64 {
                let (a, b) = (g[2 * i][k], g[2 * i + 1][k]);
                t[i][k] = (a + b) * r;
                t[half + i][k] = (a - b) * r;
            }
        }
        g[..m].copy_from_slice(&t[..m]);
        m = half;
    }
}

/// The inverse of [`haar_forward`].
fn haar_inverse(g: &mut [[f32; 64]], t: &mut [[f32; 64]], n: usize) {
    let r = std::f32::consts::FRAC_1_SQRT_2;
    let mut m = 2;
    while m <= n {
        let half = m / 2;
        for i in 0..half {
            for k in 0..64 {
                let (a, b) = (g[i][k], g[half + i][k]);
                t[2 * i][k] = (a + b) * r;
                t[2 * i + 1][k] = (a - b) * r;
            }
        }
        g[..m].copy_from_slice(&t[..m]);
        m *= 2;
    }
}

/// One BM3D-style stage on a single plane of a strip (rows `ctx.a..ctx.b`): for every reference
/// block (local rows `refs`, columns `ctx.xs`), the most similar blocks within the search window
/// are grouped (matched on `pilot` when given, else on `noisy`), transformed by the 2-D DCT and a
/// 1-D Haar transform across the group, hard-thresholded (no pilot) or Wiener-shrunk against the
/// pilot group, and aggregated into `num`/`den`. `noise` is the block's level `σ_b` and the
/// relative level of each DCT coefficient (all 1 for white noise).
fn bm_stage(ctx: &BmContext, noisy: &[f32], pilot: Option<&[f32]>, refs: &[usize], noise: BlockNoise, num: &mut [f32], den: &mut [f32]) {
    let (w, opts) = (ctx.w, ctx.opts);
    let gmax = opts.group.clamp(1, 32).next_power_of_two().min(32);
    let gmax = if gmax > opts.group.max(1) { gmax / 2 } else { gmax };
    let guide = pilot.unwrap_or(noisy);
    let mut cand: Vec<(f32, usize, usize)> = Vec::new();
    let mut gc = vec![[0.0f32; 64]; gmax];
    let mut gp = vec![[0.0f32; 64]; gmax];
    let mut x = [0.0f32; 64];
    let mut o = [0.0f32; 64];
    let mut scratch = vec![[0.0f32; 64]; gmax];
    let mut members: Vec<(usize, usize)> = Vec::with_capacity(gmax);
    for &py in refs {
        let ly = py - ctx.a;
        for &px in ctx.xs {
            let (sg, rel) = noise(ly, px);
            let (s2, rel) = (sg * sg, &rel);
            match_blocks(ctx, guide, (py, px), opts.match_tau * s2, &mut cand);
            let mut n = 1usize;
            while n * 2 <= gmax && n * 2 - 1 <= cand.len() {
                n *= 2;
            }
            members.clear();
            members.push((ly, px));
            members.extend(cand.iter().take(n - 1).map(|c| (c.1, c.2)));
            for (g, &(my, mx)) in members.iter().enumerate() {
                load_block(noisy, w, my, mx, &mut x);
                dct2(&x, &mut gc[g]);
                if let Some(p) = pilot {
                    load_block(p, w, my, mx, &mut x);
                    dct2(&x, &mut gp[g]);
                }
            }
            haar_forward(&mut gc, &mut scratch, n);
            // the estimate's noise variance in units of σ_b², summed over the group
            let wn = if pilot.is_some() {
                haar_forward(&mut gp, &mut scratch, n);
                gc[..n].iter_mut().zip(&gp[..n]).fold(0.0f32, |wn, (c, p)| wiener_shrink_group(c, p, s2, rel, wn))
            } else {
                let thr = opts.threshold * sg;
                gc[..n].iter_mut().fold(0.0f32, |wn, c| hard_threshold(c, thr, rel, wn))
            };
            haar_inverse(&mut gc, &mut scratch, n);
            let wt = 1.0 / (s2 * wn).max(1e-20);
            for (g, &(my, mx)) in members.iter().enumerate() {
                idct2(&gc[g], &mut o);
                add_block(&o, wt, w, my, mx, num, den);
            }
        }
    }
}

/// [`wiener_shrink`] on one block of a group's 3-D spectrum, accumulating `Σ f_k² rel_k²` onto
/// `wn` (the group's running sum).
#[inline]
fn wiener_shrink_group(c: &mut [f32; 64], p: &[f32; 64], s2: f32, rel: &[f32; 64], mut wn: f32) -> f32 {
    for k in 0..64 {
        let r2 = rel[k] * rel[k];
        let f = if k == 0 { 1.0 } else { p[k] * p[k] / (p[k] * p[k] + s2 * r2).max(1e-30) };
        c[k] *= f;
        wn += f * f * r2;
    }
    wn
}

/// Block matching: the blocks of the search window around the reference at image (row, column)
/// `(py, px)` whose mean squared difference to it on `guide` is below `thr_match`, as
/// (distance, local row, column), nearest first.
fn match_blocks(ctx: &BmContext, guide: &[f32], (py, px): (usize, usize), thr_match: f32, cand: &mut Vec<(f32, usize, usize)>) {
    let (w, opts) = (ctx.w, ctx.opts);
    let sr = opts.search as isize;
    let st = opts.search_step.max(1) as isize;
    let mut x = [0.0f32; 64];
    load_block(guide, w, py - ctx.a, px, &mut x);
    cand.clear();
    let y_lo = (py as isize - sr).max(ctx.a as isize);
    let y_hi = (py as isize + sr).min((ctx.b.min(ctx.h) - B) as isize);
    let x_lo = (px as isize - sr).max(0);
    let x_hi = (px as isize + sr).min((w - B) as isize);
    let mut yy = y_lo;
    while yy <= y_hi {
        let mut xx = x_lo;
        while xx <= x_hi {
            if yy as usize != py || xx as usize != px {
                let cy = yy as usize - ctx.a;
                let mut dsum = 0.0;
                for r in 0..B {
                    let row = &guide[(cy + r) * w + xx as usize..(cy + r) * w + xx as usize + B];
                    for q in 0..B {
                        let e = row[q] - x[r * B + q];
                        dsum += e * e;
                    }
                }
                let dm = dsum / 64.0;
                if dm < thr_match {
                    cand.push((dm, cy, xx as usize));
                }
            }
            xx += st;
        }
        yy += st;
    }
    cand.sort_unstable_by(|p, q| p.0.total_cmp(&q.0));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dct_is_orthonormal_and_inverts() {
        let d = dct_matrix();
        let mut x = [0.0f32; 64];
        x.iter_mut().enumerate().for_each(|(i, v)| *v = ((i * 37 % 11) as f32).sin());
        let (mut c, mut y) = ([0.0f32; 64], [0.0f32; 64]);
        dct2(&x, &mut c);
        idct2(&c, &mut y);
        // the butterflies against the matrix definition D X Dᵀ
        for k in 0..B {
            for l in 0..B {
                let mut s = 0.0;
                for n in 0..B {
                    for m in 0..B {
                        s += d[k * B + n] * x[n * B + m] * d[l * B + m];
                    }
                }
                assert!((s - c[k * B + l]).abs() < 1e-4, "{k},{l}: {s} vs {}", c[k * B + l]);
            }
        }
        let e: f32 = x.iter().map(|v| v * v).sum();
        let ec: f32 = c.iter().map(|v| v * v).sum();
        assert!((e - ec).abs() < 1e-3 * e);
        assert!(x.iter().zip(&y).all(|(a, b)| (a - b).abs() < 1e-5));
    }

    /// A local variance map of 4 everywhere is the same as twice the stationary level; a map of
    /// A field of coefficient variances: exact at the nodes, the bilinear blend between them
    /// (a partition of unity), constant beyond the outer nodes; a uniform field of the same
    /// variances denoises exactly as a one-node field does, and a field whose right half is
    /// noisier smooths the right half more.
    #[test]
    fn coefficient_field_blends_the_nodes() {
        let a: [f32; 64] = std::array::from_fn(|k| 1e-4 * (1.0 + k as f32));
        let b: [f32; 64] = std::array::from_fn(|k| 4e-4 / (1.0 + k as f32));
        let f = CoefficientField { xs: vec![10.0, 30.0], ys: vec![5.0], variance: vec![vec![a], vec![b]] };
        for (x, t) in [(10.0, 0.0), (30.0, 1.0), (20.0, 0.5), (15.0, 0.25), (0.0, 0.0), (50.0, 1.0)] {
            let v = f.at(0, x, 5.0);
            for k in 0..64 {
                let want = (1.0 - t) * a[k] + t * b[k];
                assert!((v[k] - want).abs() <= 1e-6 * want, "x {x} k {k}: {} vs {want}", v[k]);
            }
        }
        let mut rng = crate::rng::Rng::new(3);
        let (w, h) = (64, 48);
        let planes: Vec<Plane> = (0..3).map(|_| Plane::from_fn(w, h, |_, _| 0.3 + (0.02 * rng.normal()) as f32)).collect();
        let white = [4e-4f32; 64];
        let base = DenoiseOptions { sigma: vec![0.02; 3], parallel: false, ..DenoiseOptions::default() };
        let one = denoise(&planes, &DenoiseOptions { coefficient_variance: Some(CoefficientField::uniform(vec![white; 3])), ..base.clone() });
        let two = CoefficientField { xs: vec![0.0, 63.0], ys: vec![0.0], variance: vec![vec![white; 3], vec![white; 3]] };
        let two = denoise(&planes, &DenoiseOptions { coefficient_variance: Some(two), ..base.clone() });
        assert!(one.iter().zip(&two).all(|(p, q)| p.data.iter().zip(&q.data).all(|(a, b)| (a - b).abs() < 1e-6)));
        let ramp = CoefficientField { xs: vec![16.0, 48.0], ys: vec![0.0], variance: vec![vec![[1e-6; 64]; 3], vec![[4e-3; 64]; 3]] };
        let out = denoise(&planes, &DenoiseOptions { coefficient_variance: Some(ramp), ..base });
        let dev = |p: &Plane, x0: usize, x1: usize| {
            let v: Vec<f32> = (8..h - 8).flat_map(|y| (x0..x1).map(move |x| (y, x))).map(|(y, x)| p.data[y * w + x]).collect();
            let m = v.iter().sum::<f32>() / v.len() as f32;
            (v.iter().map(|a| (a - m).powi(2)).sum::<f32>() / v.len() as f32).sqrt()
        };
        let (left, right) = (dev(&out[1], 4, 14), dev(&out[1], 50, 60));
        assert!(right < 0.5 * left, "left {left} right {right}");
    }

    /// 1 changes nothing.
    #[test]
    fn local_variance_scales_the_block_noise_level() {
        let (w, h) = (48, 40);
        let mut noise = crate::deconv::synth::GaussianNoise::new(5);
        let planes: Vec<Plane> = (0..3)
            .map(|c| {
                let mut p = Plane::from_fn(w, h, |x, y| 0.3 + 0.1 * c as f32 + 0.2 * ((x / 9 + y / 7) % 2) as f32);
                noise.add_to(&mut p, 0.02);
                p
            })
            .collect();
        let base = DenoiseOptions { sigma: vec![0.02, 0.01, 0.03], parallel: false, ..DenoiseOptions::default() };
        let maps = |v: f32| Some(vec![Plane::filled(w, h, v); 3]);
        let plain = denoise(&planes, &base);
        let ones = denoise(&planes, &DenoiseOptions { local_variance: maps(1.0), ..base.clone() });
        let doubled = denoise(&planes, &DenoiseOptions { sigma: base.sigma.iter().map(|s| 2.0 * s).collect(), ..base.clone() });
        let four = denoise(&planes, &DenoiseOptions { local_variance: maps(4.0), ..base.clone() });
        let diff = |a: &[Plane], b: &[Plane]| a.iter().zip(b).flat_map(|(p, q)| p.data.iter().zip(&q.data).map(|(x, y)| (x - y).abs())).fold(0.0f32, f32::max);
        assert!(diff(&plain, &ones) < 1e-5, "{}", diff(&plain, &ones));
        assert!(diff(&doubled, &four) < 1e-4, "{}", diff(&doubled, &four));
        assert!(diff(&plain, &four) > 1e-3, "the map must matter");
    }
}
