//! PSF estimation from a wide-open / pinhole pair (Heide et al. 2013, Sec. 6; METHOD.md §6).
//!
//! # Pipeline
//! 1. Both captures are linearised ([`crate::image::Transfer`]) and the black level removed.
//! 2. Saturated pixels (≥ `saturation` of full scale in the stored values) are found in both;
//!    a wide-open pixel is excluded from the data term when it is saturated or when any pinhole
//!    pixel in its kernel footprint is.
//! 3. The pinhole capture is registered to the wide-open one ([`register`]).
//! 4. The exposure ratio `s_c = Σ open / Σ pinhole` per channel over valid pixels (kernels sum
//!    to one, so blur preserves the mean).
//! 5. PSF centres on a regular grid ([`default_tile`] spacing); each centre is fitted on its own
//!    window ([`default_window`], [`fit_window`]), windows in parallel ([`solver`]). The TV
//!    weight `λ = c_λ · σ̂ · std(s·I) · √N_data` uses the noise level `σ̂` measured from the
//!    window's residual after a short first phase (`c_λ` defaults to 1).
//! 6. Per channel, all kernels are refined jointly with the interpolated forward model
//!    ([`joint`]), `σ̂` re-measured from the joint residual.
//!
//! # Units
//! Kernels are `k × k` on the sensor's pixel grid, sum ≈ 1, centre = zero displacement, true
//! convolution ([`crate::solve::conv`]); values linear on the full-scale axis; image axes
//! row-major `(x, y)` with `x` to the right. `s` is stored per channel in the profile; centres
//! are `[x, y]` pixel coordinates (pixel centres at integers).

pub mod joint;
pub mod register;
pub mod session;
pub mod solver;

use crate::image::{Image, Plane};
use crate::optics::psf_grid::PsfGrid;
use crate::profile::{EstimationInfo, Profile, PsfTable, SourceInfo};
use rayon::prelude::*;
use register::RegistrationModel;
use solver::{solve_tile, TileData, TileSettings};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};

/// Why estimation failed.
#[derive(Debug, thiserror::Error)]
pub enum EstimateError {
    #[error("the images differ: {0}")]
    Mismatch(String),
    #[error("invalid option: {0}")]
    Option(String),
    #[error("{0}")]
    Data(String),
    #[error("cancelled")]
    Cancelled,
}

/// Below this standard deviation (fraction of full scale; a quarter of one 8-bit level) an
/// image plane counts as blank.
pub const TEXTURE_MIN: f64 = 1e-3;

/// Estimation settings; `None` means "chosen from the data".
#[derive(Clone, Debug)]
pub struct EstimateOptions {
    pub kernel_size: Option<usize>,
    /// Spacing of the PSF centres in pixels (the "tile" side: one kernel per tile).
    pub tile: Option<usize>,
    /// Side of the square fit window around each centre (clipped to the image); may be larger
    /// than the spacing (overlapping windows) or smaller (a subset of the tile's data).
    pub window: Option<usize>,
    pub lambda_scale: f64,
    pub mu_relative: f64,
    pub max_iterations: usize,
    /// Iterations of the joint refinement of all kernels of a channel with the interpolated
    /// forward model ([`joint`]); 0 skips it. It stops at a relative step of `tolerance / 10`.
    pub joint_iterations: usize,
    /// Relative step `‖Δb‖ / ‖b‖` at which a window's iterations stop.
    pub tolerance: f64,
    pub registration: RegistrationModel,
    /// Stored values at or above this fraction of full scale count as saturated.
    pub saturation: f32,
    /// Black level per channel (or one for all) on the full-scale axis, subtracted first.
    pub black_level: Vec<f32>,
    pub progress: bool,
}

impl Default for EstimateOptions {
    fn default() -> Self {
        Self {
            kernel_size: None,
            tile: None,
            window: None,
            lambda_scale: 1.0,
            mu_relative: 1.0,
            max_iterations: 150,
            joint_iterations: 40,
            tolerance: 1e-3,
            registration: RegistrationModel::Translation,
            saturation: 0.995,
            black_level: vec![],
            progress: false,
        }
    }
}

/// The estimate and what was learnt on the way.
pub struct Estimate {
    pub profile: Profile,
    pub noise_sigma: Vec<f64>,
    pub valid_masks: Vec<Vec<bool>>,
    /// The registered pinhole planes (linear, black removed, not scaled).
    pub pinhole_registered: Vec<Plane>,
    /// The wide-open planes (linear, black removed).
    pub open_linear: Vec<Plane>,
}

/// Robust noise standard deviation of a plane: MAD of a zero-mean 3×3 high-pass normalised to
/// unit gain on white noise.
pub fn noise_sigma(p: &Plane) -> f64 {
    let (w, h) = (p.width, p.height);
    let mut v = Vec::with_capacity(w * h / 4);
    for y in (1..h.saturating_sub(1)).step_by(2) {
        for x in (1..w.saturating_sub(1)).step_by(2) {
            let c = p.get(x, y);
            let d = 4.0 * c - p.get(x - 1, y) - p.get(x + 1, y) - p.get(x, y - 1) - p.get(x, y + 1);
            v.push((d / 20f32.sqrt()).abs());
        }
    }
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    1.4826 * *m as f64
}

fn linear_planes(img: &Image, black: &[f32]) -> Vec<Plane> {
    img.planes
        .iter()
        .enumerate()
        .map(|(c, p)| {
            let b = black.get(c).or(black.first()).copied().unwrap_or(0.0);
            p.map(|v| img.transfer.decode(v) - b)
        })
        .collect()
}

/// Dilates a mask by a square of radius `r` (separable max filter).
pub fn dilate(mask: &[bool], w: usize, h: usize, r: usize) -> Vec<bool> {
    if r == 0 {
        return mask.to_vec();
    }
    // running count of set pixels in a sliding window, rows then columns
    let pass = |src: &[bool], len: usize, stride: usize, lines: usize, lstride: usize| -> Vec<bool> {
        let mut out = vec![false; src.len()];
        for l in 0..lines {
            let at = |i: usize| src[l * lstride + i * stride];
            let mut count = (0..=r.min(len - 1)).filter(|&i| at(i)).count();
            for i in 0..len {
                out[l * lstride + i * stride] = count > 0;
                if i + r + 1 < len && at(i + r + 1) {
                    count += 1;
                }
                if i >= r && at(i - r) {
                    count -= 1;
                }
            }
        }
        out
    };
    let rows = pass(mask, w, 1, h, w);
    pass(&rows, h, w, w, 1)
}

/// Tile grid for an image: `(columns, rows)`.
pub fn tile_grid(w: usize, h: usize, tile: usize) -> (usize, usize) {
    (((w as f64 / tile as f64).round() as usize).max(1), ((h as f64 / tile as f64).round() as usize).max(1))
}

/// Default spacing of the PSF centres for a kernel size: about 1.8 kernels, so the
/// Catmull–Rom blend follows a quickly varying field; each centre is still fitted on a
/// [`default_window`] of 4 kernels, and the joint refinement makes the dense grid consistent.
pub fn default_tile(k: usize, w: usize, h: usize) -> usize {
    (9 * k / 5).max(32).min(w.min(h))
}

/// Default fit window for a kernel size: enough data for a well-posed fit (≥ 4 kernels across).
pub fn default_window(k: usize, w: usize, h: usize) -> usize {
    (4 * k).max(96).min(w.max(h))
}

/// The fit window `[x0, x1) × [y0, y1)` of side `window` centred on `center`, clipped to the
/// image.
pub fn fit_window(center: [f64; 2], window: usize, w: usize, h: usize) -> (usize, usize, usize, usize) {
    let span = |c: f64, n: usize| {
        let lo = (c + 0.5 - window as f64 / 2.0).round().clamp(0.0, n as f64 - 1.0) as usize;
        let hi = (c + 0.5 + window as f64 / 2.0).round().clamp(lo as f64 + 1.0, n as f64) as usize;
        (lo, hi)
    };
    let (x0, x1) = span(center[0], w);
    let (y0, y1) = span(center[1], h);
    (x0, x1, y0, y1)
}

/// Estimates a profile from a wide-open and a pinhole capture of the same target.
///
/// # Errors
/// Size or channel mismatch, an even kernel size, a kernel larger than a tile, images too
/// small, or no valid (unsaturated) data.
pub fn estimate(open: &Image, pinhole: &Image, opts: &EstimateOptions) -> Result<Estimate, EstimateError> {
    let t0 = std::time::Instant::now();
    if open.width() != pinhole.width() || open.height() != pinhole.height() {
        return Err(EstimateError::Mismatch(format!(
            "wide-open is {}x{}, pinhole is {}x{}",
            open.width(),
            open.height(),
            pinhole.width(),
            pinhole.height()
        )));
    }
    if open.channel_count() != pinhole.channel_count() {
        return Err(EstimateError::Mismatch(format!("wide-open has {} channels, pinhole {}", open.channel_count(), pinhole.channel_count())));
    }
    let (w, h) = (open.width(), open.height());
    if w < 32 || h < 32 {
        return Err(EstimateError::Data(format!("images of {w}x{h} are too small (at least 32x32)")));
    }
    if let Some(k) = opts.kernel_size {
        if k % 2 == 0 || k < 3 {
            return Err(EstimateError::Option(format!("--kernel must be odd and at least 3, got {k}")));
        }
    }
    let nch = open.channel_count();
    let open_lin = linear_planes(open, &opts.black_level);
    let pin_lin = linear_planes(pinhole, &opts.black_level);
    // a blank frame (lens cap, target out of view, a dead camera) has nothing to estimate a
    // PSF from: without this it would give a delta-like profile and no complaint
    for (name, planes) in [("wide-open", &open_lin), ("pinhole", &pin_lin)] {
        for (c, p) in planes.iter().enumerate() {
            let sd = p.variance().sqrt();
            if sd < TEXTURE_MIN {
                return Err(EstimateError::Data(format!(
                    "the {name} image has no texture in channel {} (standard deviation {sd:.1e} of full scale, below {TEXTURE_MIN:.0e}): is the target in view and the lens cap off?",
                    open.channels.get(c).map_or("?", |s| s.as_str())
                )));
            }
        }
    }
    let sat = |img: &Image, c: usize| -> Vec<bool> { img.planes[c].data.iter().map(|&v| v >= opts.saturation).collect() };

    // registration on the sum of channels
    let sum_planes = |ps: &[Plane]| {
        let mut s = Plane::new(w, h);
        for p in ps {
            for (a, b) in s.data.iter_mut().zip(&p.data) {
                *a += b;
            }
        }
        s
    };
    let reg = register::register(&sum_planes(&open_lin), &sum_planes(&pin_lin), opts.registration);
    let pin_reg: Vec<Plane> = pin_lin.iter().map(|p| register::apply(p, &reg.info)).collect();
    let pin_sat_reg: Vec<Vec<bool>> = (0..nch)
        .map(|c| {
            let m = Plane { width: w, height: h, data: sat(pinhole, c).iter().map(|&b| b as u8 as f32).collect() };
            register::apply(&m, &reg.info).data.iter().map(|&v| v > 0.0).collect()
        })
        .collect();

    // kernel size
    let k = match opts.kernel_size {
        Some(k) => k,
        None => choose_kernel_size(&open_lin, &pin_reg, opts)?,
    };
    let tile = opts.tile.unwrap_or_else(|| default_tile(k, w, h));
    if tile < k {
        return Err(EstimateError::Option(format!("tile {tile} is smaller than the kernel {k}; use a larger --tile or a smaller --kernel")));
    }
    let (cols, rows) = tile_grid(w, h, tile);
    let window = opts.window.unwrap_or_else(|| default_window(k, w, h));
    if window < k {
        return Err(EstimateError::Option(format!("fit window {window} is smaller than the kernel {k}")));
    }
    let r = k / 2;

    // valid data masks and exposure ratios
    let mut valid_masks = Vec::with_capacity(nch);
    let mut ratio = Vec::with_capacity(nch);
    let mut sat_count = 0usize;
    for c in 0..nch {
        let bad_pin = dilate(&pin_sat_reg[c], w, h, r);
        let so = sat(open, c);
        let mut m = vec![false; w * h];
        let (mut so_sum, mut sp_sum) = (0.0f64, 0.0f64);
        for y in r..h.saturating_sub(r) {
            for x in r..w.saturating_sub(r) {
                let i = y * w + x;
                if !so[i] && !bad_pin[i] {
                    m[i] = true;
                    so_sum += open_lin[c].data[i] as f64;
                    sp_sum += pin_reg[c].data[i] as f64;
                }
            }
        }
        sat_count += so.iter().filter(|&&b| b).count();
        if sp_sum <= 0.0 || m.iter().all(|&b| !b) {
            return Err(EstimateError::Data(format!("channel {}: no valid pixels (all saturated or black)", open.channels[c])));
        }
        ratio.push(so_sum / sp_sum);
        valid_masks.push(m);
    }

    let centers = PsfGrid::regular_centers(w, h, cols, rows);
    let jobs: Vec<(usize, usize)> = (0..nch).flat_map(|c| (0..cols * rows).map(move |t| (c, t))).collect();
    let bar = progress_bar(opts.progress, jobs.len() as u64, "estimating PSFs");
    let cancelled = AtomicBool::new(false);
    let results: Vec<_> = jobs
        .par_iter()
        .map(|&(c, t)| {
            let win = fit_window(centers[t], window, w, h);
            let data = tile_data(&open_lin[c], &pin_reg[c], &valid_masks[c], ratio[c] as f32, win, k);
            let settings = TileSettings {
                kernel_size: k,
                lambda: None,
                lambda_scale: opts.lambda_scale as f32,
                noise_sigma: None,
                mu_relative: opts.mu_relative as f32,
                max_iterations: opts.max_iterations,
                tolerance: opts.tolerance,
            };
            let res = solve_tile(&data, &settings, |_, _| !cancelled.load(Ordering::Relaxed));
            bar.inc(1);
            (c, t, res)
        })
        .collect();
    bar.finish_and_clear();

    let mut kernels = vec![vec![Plane::new(k, k); cols * rows]; nch];
    let mut info = EstimationInfo {
        lambda: 0.0,
        mu: opts.mu_relative,
        noise_sigma: vec![],
        iterations: vec![vec![0; cols * rows]; nch],
        relative_gap: vec![vec![0.0; cols * rows]; nch],
        residual_rms: vec![vec![0.0; cols * rows]; nch],
        saturated_fraction: sat_count as f64 / (w * h * nch) as f64,
        seconds: 0.0,
    };
    let mut lam_sum = 0.0;
    let mut tile_noise = vec![Vec::new(); nch];
    let mut tile_lambda = vec![vec![(0.0f32, 0usize, 0.0f64); cols * rows]; nch];
    for (c, t, res) in results {
        tile_lambda[c][t] = (res.lambda, res.data_pixels, res.noise_sigma);
        tile_noise[c].push(res.noise_sigma);
        let lambda = res.lambda;
        kernels[c][t] = res.kernel;
        info.iterations[c][t] = res.stats.iterations;
        info.relative_gap[c][t] = res.stats.criterion;
        info.residual_rms[c][t] = res.residual_rms;
        lam_sum += lambda as f64;
    }
    info.lambda = lam_sum / jobs.len() as f64;
    if opts.joint_iterations > 0 {
        let shape = PsfGrid { kernel_size: k, columns: cols, rows, centers: centers.clone(), channels: open.channels.clone(), kernels: vec![] };
        let o = crate::solve::primal_dual::SplitOptions { max_iterations: opts.joint_iterations, min_iterations: 5, tolerance: opts.tolerance * 0.1 };
        let mut power = Vec::new();
        let bar = progress_bar(opts.progress, (nch * opts.joint_iterations) as u64, "joint refinement");
        for c in 0..nch {
            let mut sharp = pin_reg[c].clone();
            sharp.scale(ratio[c] as f32);
            let (st, rms) = joint::refine_channel(&open_lin[c], &sharp, &valid_masks[c], &shape, &mut kernels[c], &tile_lambda[c], &o, &mut power, &bar, joint::JOINT_DATA_PIXELS);
            bar.set_position(((c + 1) * opts.joint_iterations) as u64);
            // the profile's per-tile figures then describe the refined kernels
            for t in 0..cols * rows {
                info.iterations[c][t] += st.iterations;
                info.residual_rms[c][t] = rms;
            }
        }
        bar.finish_and_clear();
    }
    // the noise level per channel: median over tiles of the least-squares residual level
    let noise: Vec<f64> = tile_noise
        .into_iter()
        .map(|mut v| {
            v.sort_by(|a, b| a.total_cmp(b));
            v[v.len() / 2]
        })
        .collect();
    info.noise_sigma = noise.clone();
    info.seconds = t0.elapsed().as_secs_f64();
    let grid = PsfGrid { kernel_size: k, columns: cols, rows, centers: centers.clone(), channels: open.channels.clone(), kernels };
    let source = SourceInfo {
        width: w,
        height: h,
        channels: open.channels.clone(),
        sample_format: open.format,
        transfer: open.transfer,
        open: None,
        pinhole: None,
        black_level: opts.black_level.clone(),
    };
    let psf = PsfTable { kernel_size: k, columns: cols, rows, centers, tile_size: Some([w / cols, h / rows]), files: BTreeMap::new() };
    let mut meta = Profile::new_meta(source, ratio, psf);
    meta.registration = reg.info;
    meta.estimation = info;
    meta.raw = open.raw.clone();
    Ok(Estimate { profile: Profile { meta, grid }, noise_sigma: noise, valid_masks, pinhole_registered: pin_reg, open_linear: open_lin })
}

/// Builds the working domain of one tile: the tile plus the kernel radius on every side,
/// rounded up to a fast FFT size, centred on the tile.
pub fn tile_data(open: &Plane, pin: &Plane, valid: &[bool], s: f32, tile: (usize, usize, usize, usize), k: usize) -> TileData {
    let (x0, x1, y0, y1) = tile;
    let (w, h) = (open.width, open.height);
    let r = k / 2;
    let pw = crate::solve::fft::good_size(x1 - x0 + 2 * r);
    let ph = crate::solve::fft::good_size(y1 - y0 + 2 * r);
    let ox = x0 as isize - ((pw - (x1 - x0)) / 2) as isize;
    let oy = y0 as isize - ((ph - (y1 - y0)) / 2) as isize;
    let mut sharp = pin.window_reflect(ox, oy, pw, ph);
    sharp.scale(s);
    let blurred = open.window_reflect(ox, oy, pw, ph);
    let mut mask = vec![false; pw * ph];
    for yy in r..ph - r {
        for xx in r..pw - r {
            let (ix, iy) = (ox + xx as isize, oy + yy as isize);
            if ix >= 0 && iy >= 0 && (ix as usize) < w && (iy as usize) < h {
                mask[yy * pw + xx] = valid[iy as usize * w + ix as usize];
            }
        }
    }
    TileData { pw, ph, sharp: sharp.data, blurred: blurred.data, mask }
}

/// Picks a kernel size from a probe estimate: a generous kernel on the centre and corner
/// tiles of the middle channel, then the radius holding 99% of the energy, with margin.
fn choose_kernel_size(open: &[Plane], pin: &[Plane], opts: &EstimateOptions) -> Result<usize, EstimateError> {
    let (w, h) = (open[0].width, open[0].height);
    let c = open.len() / 2;
    let probe_k = ((w.min(h) / 6) | 1).clamp(9, 127);
    let tsz = (w.min(h) / 3).max(probe_k * 2).min(w.min(h));
    let s = (open[c].sum() / pin[c].sum().max(1e-30)) as f32;
    let all = vec![true; w * h];
    let spots = [((w - tsz) / 2, (h - tsz) / 2), (0, 0), (w - tsz, h - tsz)];
    let mut radius: f64 = 1.0;
    for &(x0, y0) in &spots {
        let data = tile_data(&open[c], &pin[c], &all, s, (x0, x0 + tsz, y0, y0 + tsz), probe_k);
        let st = TileSettings { kernel_size: probe_k, lambda: None, lambda_scale: opts.lambda_scale as f32, noise_sigma: None, mu_relative: 1.0, max_iterations: 150, tolerance: 1e-3 };
        let res = solve_tile(&data, &st, |_, _| true);
        radius = radius.max(energy_radius(&res.kernel, 0.99));
    }
    let k = ((2.0 * (radius * 1.25 + 2.0)).ceil() as usize) | 1;
    Ok(k.clamp(7, probe_k))
}

/// Radius (about the kernel centre, Chebyshev distance) holding `frac` of the energy.
pub fn energy_radius(k: &Plane, frac: f64) -> f64 {
    let c = (k.width / 2) as isize;
    let total = k.sum();
    if total <= 0.0 {
        return 0.0;
    }
    for r in 0..=c {
        let mut s = 0.0;
        for y in (c - r)..=(c + r) {
            for x in (c - r)..=(c + r) {
                s += k.get(x as usize, y as usize) as f64;
            }
        }
        if s >= frac * total {
            return r as f64;
        }
    }
    c as f64
}

/// A progress bar on stderr, or a hidden one.
pub fn progress_bar(show: bool, len: u64, msg: &'static str) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let pb = indicatif::ProgressBar::new(len);
    if let Ok(style) = indicatif::ProgressStyle::with_template("{msg:>18} [{bar:40}] {pos}/{len} {elapsed_precise} eta {eta}") {
        pb.set_style(style.progress_chars("=> "));
    }
    pb.set_message(msg);
    pb
}

/// Relative L2 error `‖a − b‖ / ‖b‖` of two kernels.
pub fn relative_error(a: &Plane, b: &Plane) -> f64 {
    let num: f64 = a.data.iter().zip(&b.data).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
    let den: f64 = b.data.iter().map(|y| (*y as f64).powi(2)).sum();
    (num / den.max(1e-300)).sqrt()
}

/// Relative L2 errors ([`relative_error`]) of every kernel of `g` against `truth`'s kernel
/// interpolated at the same tile centre, channel by channel, tiles in grid order.
pub fn kernel_errors(g: &PsfGrid, truth: &PsfGrid) -> Vec<f64> {
    let mut e = Vec::with_capacity(g.channels.len() * g.tile_count());
    for c in 0..g.channels.len() {
        for t in 0..g.tile_count() {
            let [x, y] = g.centers[t];
            e.push(relative_error(&g.kernels[c][t], &truth.kernel_at(c, x, y)));
        }
    }
    e
}

/// The median and the largest of a list of errors (`NaN`s when it is empty).
pub fn median_max(errors: &[f64]) -> (f64, f64) {
    let mut e = errors.to_vec();
    e.sort_by(f64::total_cmp);
    match e.last() {
        Some(&max) => (e[e.len() / 2], max),
        None => (f64::NAN, f64::NAN),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A blank frame (constant, as with the lens cap on) is refused with a clear error naming
    /// the image, not turned into a delta-like profile; a textured pair passes the check.
    #[test]
    fn a_blank_frame_is_refused() {
        let (w, h) = (64, 48);
        let mut r = crate::rng::Rng::new(9);
        let textured = Image::new(vec![Plane::from_fn(w, h, |_, _| r.uniform() as f32 * 0.5 + 0.2)]);
        let blank = Image::new(vec![Plane::filled(w, h, 0.4)]);
        let opts = EstimateOptions { kernel_size: Some(5), max_iterations: 5, joint_iterations: 0, ..Default::default() };
        match estimate(&textured, &blank, &opts) {
            Err(EstimateError::Data(m)) => assert!(m.contains("pinhole image has no texture"), "{m}"),
            other => panic!("expected a data error, got {:?}", other.map(|_| ())),
        }
        match estimate(&blank, &textured, &opts) {
            Err(EstimateError::Data(m)) => assert!(m.contains("wide-open image has no texture"), "{m}"),
            other => panic!("expected a data error, got {:?}", other.map(|_| ())),
        }
        assert!(estimate(&textured, &textured, &opts).is_ok());
    }

    #[test]
    fn dilate_matches_brute_force() {
        let (w, h) = (13, 9);
        let mut r = crate::rng::Rng::new(5);
        let m: Vec<bool> = (0..w * h).map(|_| r.uniform() < 0.08).collect();
        for rad in 0..4 {
            let d = dilate(&m, w, h, rad);
            for y in 0..h {
                for x in 0..w {
                    let want = (0..h).any(|yy| (0..w).any(|xx| m[yy * w + xx] && xx.abs_diff(x) <= rad && yy.abs_diff(y) <= rad));
                    assert_eq!(d[y * w + x], want, "r={rad} at {x},{y}");
                }
            }
        }
    }

    #[test]
    fn noise_sigma_of_white_noise() {
        let mut r = crate::rng::Rng::new(9);
        let p = Plane::from_fn(200, 200, |_, _| 0.5 + 0.01 * r.normal() as f32);
        let s = noise_sigma(&p);
        assert!((s - 0.01).abs() < 0.0008, "{s}");
    }
}
