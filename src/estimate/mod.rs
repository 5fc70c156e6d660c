//! PSF estimation from a wide-open / pinhole pair (Heide et al. 2013, Sec. 6; docs/method.md §6).
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
//!    ([`joint`]), `σ̂` re-measured from the joint residual and the multiplier of the TV
//!    weight chosen per channel on held-out pixels ([`joint::LAMBDA_LADDER`]).
//!
//! # Units
//! Kernels are `k × k` on the sensor's pixel grid, sum ≈ 1, centre = zero displacement, true
//! convolution ([`crate::solve::conv`]); values linear on the full-scale axis; image axes
//! row-major `(x, y)` with `x` to the right. `s` is stored per channel in the profile; centres
//! are `[x, y]` pixel coordinates (pixel centres at integers).

pub mod bootstrap;
pub mod joint;
pub mod register;
pub mod session;
pub mod solver;
pub mod testbed;

use crate::image::{Image, Plane};
use crate::optics::psf_grid::PsfGrid;
use crate::profile::{EstimationInfo, Profile, PsfTable, RegistrationInfo, SourceInfo};
use rayon::prelude::*;
use register::RegistrationModel;
use solver::{solve_tile, TileData, TileSettings};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};

/// Why estimation failed. Sizes in pixels; channels by name.
#[derive(Debug, thiserror::Error)]
pub enum EstimateError {
    #[error("the images differ: wide-open is {}x{}, pinhole is {}x{}", open[0], open[1], pinhole[0], pinhole[1])]
    Size { open: [usize; 2], pinhole: [usize; 2] },
    #[error("the images differ: wide-open has {open} channels, pinhole {pinhole}")]
    Channels { open: usize, pinhole: usize },
    #[error("images of {width}x{height} are too small (at least 32x32)")]
    TooSmall { width: usize, height: usize },
    #[error("invalid option: --kernel must be odd and at least 3, got {0}")]
    KernelSize(usize),
    #[error("invalid option: tile {tile} is smaller than the kernel {kernel}; use a larger --tile or a smaller --kernel")]
    TileTooSmall { tile: usize, kernel: usize },
    #[error("invalid option: fit window {window} is smaller than the kernel {kernel}")]
    WindowTooSmall { window: usize, kernel: usize },
    /// A blank frame (lens cap on, target out of view, a dead camera).
    #[error("the {image} image has no texture in channel {channel} (standard deviation {std_dev:.1e} of full scale, below {TEXTURE_MIN:.0e}): is the target in view and the lens cap off?")]
    Blank { image: &'static str, channel: String, std_dev: f64 },
    #[error("channel {channel}: no valid pixels (all saturated or black)")]
    NoValidPixels { channel: String },
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
    /// Choose the joint fit's TV weight multiplier per channel on held-out pixels
    /// (`joint::select_lambda` among [`joint::LAMBDA_LADDER`]); `false` keeps the rule's weight (multiplier 1).
    pub select_lambda: bool,
    /// Relative step `‖Δb‖ / ‖b‖` at which a window's iterations stop.
    pub tolerance: f64,
    pub registration: RegistrationModel,
    /// Stored values at or above this fraction of full scale count as saturated.
    pub saturation: f32,
    /// Black level per channel (or one for all) on the full-scale axis, subtracted first.
    pub black_level: Vec<f32>,
    pub progress: bool,
    /// The field variation rates `g_c` of the field-smoothness prior ([`joint`]) when both
    /// `kernel_size` and `tile` are given (no probe then measures them; the bootstrap passes the
    /// profile's, [`Estimate::field_variation`]); `None`: from the probes, or no such prior.
    pub field_variation: Option<Vec<f64>>,
    /// Continue the joint fit past its end to measure how far each kernel still is from the
    /// fit's optimum ([`Estimate::convergence`], `joint::continue_fit`); the kernels are not
    /// changed. The bootstrap's uncertainty adds it (`bootstrap::convergence_map`).
    pub convergence_tail: bool,
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
            joint_iterations: 32,
            select_lambda: true,
            tolerance: 1e-3,
            registration: RegistrationModel::Translation,
            saturation: 0.995,
            black_level: vec![],
            progress: false,
            field_variation: None,
            convergence_tail: false,
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
    /// Time of each stage, in order: `registration`, `layout` (the probe fits that choose the
    /// kernel size and grid), `window fits`, `joint refinement` (≈ 0 when skipped), `noise law`
    /// (the profile's noise law: the wide-open capture's and the residual's fits).
    pub stage_seconds: Vec<StageTime>,
    /// The field variation rate `g_c` per channel the field-smoothness prior used (empty: none).
    pub field_variation: Vec<f64>,
    /// `[channel][tile]`: the convergence term of each kernel, the predicted per-pixel distance
    /// `|b_∞ − b̂|` to the joint fit's optimum (`bootstrap::convergence_map`); empty unless
    /// [`EstimateOptions::convergence_tail`] and the joint refinement ran.
    pub convergence: Vec<Vec<Plane>>,
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

/// A spacing that gives the grid `(columns, rows)` under [`tile_grid`] (the largest such), so a
/// refit (the bootstrap's replicates) lands on the profile's grid without probing the field again.
pub fn tile_for_grid(w: usize, h: usize, columns: usize, rows: usize) -> Option<usize> {
    (1..=w.max(h)).rev().find(|&t| tile_grid(w, h, t) == (columns, rows))
}

/// Default spacing of the PSF centres for a kernel size: about 1.8 kernels, so the
/// Catmull–Rom blend follows a quickly varying field; each centre is still fitted on a
/// [`default_window`] of 4 kernels, and the joint refinement makes the dense grid consistent.
pub fn default_tile(k: usize, w: usize, h: usize) -> usize {
    (9 * k / 5).max(32).min(w.min(h))
}

/// Largest relative change of the kernel between neighbouring PSF centres the grid allows
/// ([`lens_tile`]).
pub const GRID_CHANGE: f64 = 0.1;

/// Most PSF centres the default grid places ([`lens_tile`]): it bounds the cost of large images
/// (a 4000×3000 capture gets at most 20 × 15 centres; 1024×768 is not affected).
pub const MAX_CENTRES: usize = 300;

/// Spacing of the PSF centres tied to the lens (docs/estimation.md "Grid"): neighbouring centres
/// differ by at most [`GRID_CHANGE`] at the measured variation rate `g`, so the spacing is
/// `GRID_CHANGE / g`, bounded below by [`default_tile`] (1.8 kernels) and by the spacing that places
/// [`MAX_CENTRES`] centres, and above by half the
/// shorter image side (at least 2 × 2 centres).
pub fn lens_tile(k: usize, variation: f64, w: usize, h: usize) -> usize {
    let lo = default_tile(k, w, h).max(((w * h) as f64 / MAX_CENTRES as f64).sqrt().ceil() as usize).min(w.min(h));
    let hi = (w.min(h) / 2).max(lo);
    if variation.is_finite() && variation > 0.0 {
        ((GRID_CHANGE / variation).round() as usize).clamp(lo, hi)
    } else {
        hi
    }
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

/// Estimates a profile from a wide-open and a pinhole capture of the same target (the
/// module docs give the stages).
///
/// # Errors
/// Size or channel mismatch, an even kernel size, a kernel larger than a tile, images too
/// small, a blank frame, or no valid (unsaturated) data.
pub fn estimate(open: &Image, pinhole: &Image, opts: &EstimateOptions) -> Result<Estimate, EstimateError> {
    let t0 = std::time::Instant::now();
    check_inputs(open, pinhole, opts)?;
    let open_lin = linear_planes(open, &opts.black_level);
    let pin_lin = linear_planes(pinhole, &opts.black_level);
    // a blank frame (lens cap, target out of view, a dead camera) has nothing to estimate a
    // PSF from: without this it would give a delta-like profile and no complaint
    check_texture("wide-open", &open_lin, &open.channels)?;
    check_texture("pinhole", &pin_lin, &open.channels)?;
    let mut stages = Vec::new();
    let mut lap = stage_clock();
    let (reg, pin_reg, pin_sat_reg) = register_pair(&open_lin, &pin_lin, pinhole, opts);
    stages.push(lap("registration"));
    let layout = Layout::choose(&open_lin, &pin_reg, opts)?;
    stages.push(lap("layout"));
    let data = valid_data(open, &open_lin, &pin_reg, &pin_sat_reg, layout.kernel, opts)?;
    let (mut kernels, mut info, tile_fits) = fit_windows(&open_lin, &pin_reg, &data, &layout, opts);
    stages.push(lap("window fits"));
    let (mut convergence, mut predictions) = (Vec::new(), Vec::new());
    if opts.joint_iterations > 0 {
        let factors = spread_factors(&kernels, SPREAD_EXPONENT);
        let scaled: TileFits = tile_fits.iter().zip(&factors).map(|(f, g)| f.iter().zip(g).map(|(&(l, n, s), &x)| (l * x as f32, n, s)).collect()).collect();
        (convergence, predictions) = refine_jointly(&open_lin, &pin_reg, &data, &layout, &open.channels, &scaled, &mut kernels, &mut info, opts);
    }
    stages.push(lap("joint refinement"));
    // the noise level per channel: median over tiles of the least-squares residual level
    let noise: Vec<f64> = tile_fits
        .iter()
        .map(|fits| {
            let mut v: Vec<f64> = fits.iter().map(|f| f.2).collect();
            v.sort_by(|a, b| a.total_cmp(b));
            v[v.len() / 2]
        })
        .collect();
    info.noise_sigma = noise.clone();
    info.seconds = t0.elapsed().as_secs_f64();
    let mut profile = assemble_profile(open, &layout, kernels, data.ratio, reg.info, info, opts);
    // the sensor's noise law (issue 12; crate::profile::noise): first from the wide-open capture
    // alone, then the lower of that and the residual's law per channel (profile_noise_law)
    profile.meta.noise = crate::profile::noise::NoiseLaw::fit_image(&open_lin, opts.saturation).ok();
    let field_variation = if opts.joint_iterations > 0 && opts.lambda_scale > 0.0 { layout.variation.clone() } else { vec![] };
    let mut est = Estimate { profile, noise_sigma: noise, valid_masks: data.valid_masks, pinhole_registered: pin_reg, open_linear: open_lin, stage_seconds: stages, field_variation, convergence };
    // the fitted model's prediction: the joint fit's, or (without it) the forward model's
    let predictions = if predictions.len() == est.open_linear.len() { predictions } else { bootstrap::predictions(&est) };
    est.profile.meta.noise = profile_noise_law(&est, &predictions);
    est.stage_seconds.push(lap("noise law"));
    Ok(est)
}

/// The noise law stored in the profile (docs/estimation.md "Noise law of the profile"): per
/// channel, the lower at the channel's median level `m_c` of two fits that can only over-count
/// the sensor's variance: the wide-open capture's local differences
/// ([`crate::profile::noise::NoiseLaw::fit_image`], which also count the texture a nearly sharp
/// channel keeps) and the fitted model's residual ([`bootstrap::residual_noise_law`], which
/// also counts the model's misfit),
///
/// `law_c = argmin_{L ∈ {image, residual}} g_L·m_c + r_L²`.
///
/// Either alone when the other cannot be fitted; `None` when neither can. `pred`: the fitted
/// model's prediction per channel (the joint fit's, [`joint::ChannelFit::prediction`], or
/// without the joint fit [`bootstrap::predictions`]: the same forward model).
fn profile_noise_law(est: &Estimate, pred: &[Plane]) -> Option<crate::profile::noise::NoiseLaw> {
    let image = est.profile.meta.noise.clone();
    let residual = bootstrap::residual_noise_law(est, pred);
    let (image, residual) = match (image, residual) {
        (Some(i), Some(r)) if i.channels() == r.channels() => (i, r),
        (i, r) => return r.or(i),
    };
    let mut law = residual.clone();
    let mut picked = Vec::with_capacity(law.channels());
    for c in 0..law.channels() {
        let mut v: Vec<f32> = est.open_linear[c].data.iter().copied().filter(|x| x.is_finite()).collect();
        let mid = v.len() / 2;
        let m = if v.is_empty() { 0.0 } else { *v.select_nth_unstable_by(mid, f32::total_cmp).1 };
        let from_image = image.variance(c, m) < residual.variance(c, m);
        if from_image {
            (law.gain[c], law.read[c]) = (image.gain[c], image.read[c]);
        }
        picked.push(from_image);
    }
    law.source = match (picked.iter().all(|&p| p), picked.iter().any(|&p| p)) {
        (true, _) => "image".into(),
        (false, true) => "image+residual".into(),
        (false, false) => "residual".into(),
    };
    Some(law)
}

/// Wall and CPU seconds of one stage of [`estimate`] (CPU: user + system of the whole process,
/// all threads; `None` where [`process_cpu_seconds`] cannot read it).
#[derive(Clone, Copy, Debug)]
pub struct StageTime {
    pub stage: &'static str,
    pub wall: f64,
    pub cpu: Option<f64>,
}

/// A lap clock: each call returns the time since the previous call (or its creation); the
/// stages of [`estimate`] and of [`crate::diagnose::diagnose`].
pub fn stage_clock() -> impl FnMut(&'static str) -> StageTime {
    let (mut last, mut last_cpu) = (std::time::Instant::now(), process_cpu_seconds());
    move |stage| {
        let (now, cpu) = (std::time::Instant::now(), process_cpu_seconds());
        let t = StageTime { stage, wall: now.duration_since(last).as_secs_f64(), cpu: cpu.zip(last_cpu).map(|(b, a)| b - a) };
        (last, last_cpu) = (now, cpu);
        t
    }
}

/// CPU seconds of this process so far (user + system, all threads; Linux `/proc/self/stat`,
/// USER_HZ = 100), or `None` elsewhere.
pub fn process_cpu_seconds() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/stat").ok()?;
    // fields after the command name (which may hold spaces) start at the state, field 3
    let rest = &s[s.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Sizes and the kernel option, before any work.
fn check_inputs(open: &Image, pinhole: &Image, opts: &EstimateOptions) -> Result<(), EstimateError> {
    if open.width() != pinhole.width() || open.height() != pinhole.height() {
        return Err(EstimateError::Size { open: [open.width(), open.height()], pinhole: [pinhole.width(), pinhole.height()] });
    }
    if open.channel_count() != pinhole.channel_count() {
        return Err(EstimateError::Channels { open: open.channel_count(), pinhole: pinhole.channel_count() });
    }
    let (w, h) = (open.width(), open.height());
    if w < 32 || h < 32 {
        return Err(EstimateError::TooSmall { width: w, height: h });
    }
    match opts.kernel_size {
        Some(k) if k % 2 == 0 || k < 3 => Err(EstimateError::KernelSize(k)),
        _ => Ok(()),
    }
}

/// Refuses a plane whose standard deviation is below [`TEXTURE_MIN`].
fn check_texture(image: &'static str, planes: &[Plane], channels: &[String]) -> Result<(), EstimateError> {
    for (c, p) in planes.iter().enumerate() {
        let sd = p.variance().sqrt();
        if sd < TEXTURE_MIN {
            return Err(EstimateError::Blank { image, channel: channels.get(c).map_or("?", |s| s.as_str()).to_string(), std_dev: sd });
        }
    }
    Ok(())
}

/// Registers the pinhole capture to the wide-open one on the sum of channels; returns the
/// registration, the registered pinhole planes and their registered saturation masks.
fn register_pair(open_lin: &[Plane], pin_lin: &[Plane], pinhole: &Image, opts: &EstimateOptions) -> (register::Registration, Vec<Plane>, Vec<Vec<bool>>) {
    let reg = register::register(&Plane::sum_of(open_lin), &Plane::sum_of(pin_lin), opts.registration);
    let pin_reg: Vec<Plane> = pin_lin.iter().map(|p| register::apply(p, &reg.info)).collect();
    let pin_sat_reg: Vec<Vec<bool>> = pinhole
        .planes
        .iter()
        .map(|p| {
            let m = Plane { width: p.width, height: p.height, data: p.data.iter().map(|&v| (v >= opts.saturation) as u8 as f32).collect() };
            register::apply(&m, &reg.info).data.iter().map(|&v| v > 0.0).collect()
        })
        .collect();
    (reg, pin_reg, pin_sat_reg)
}

/// Kernel size, PSF centre grid and fit window (pixels).
struct Layout {
    kernel: usize,
    columns: usize,
    rows: usize,
    window: usize,
    centers: Vec<[f64; 2]>,
    /// Field variation rate `g_c` per channel from the probes (empty when none ran): the scale
    /// of the field-smoothness prior ([`joint`]).
    variation: Vec<f64>,
}

impl Layout {
    fn choose(open_lin: &[Plane], pin_reg: &[Plane], opts: &EstimateOptions) -> Result<Layout, EstimateError> {
        let (w, h) = (open_lin[0].width, open_lin[0].height);
        let probe = match (opts.kernel_size, opts.tile) {
            (Some(k), Some(_)) => FieldProbe { kernel: k, variation: 0.0, channel_variation: opts.field_variation.clone().unwrap_or_default() },
            (fixed, _) => probe_field(open_lin, pin_reg, fixed, opts)?,
        };
        let k = probe.kernel;
        let tile = opts.tile.unwrap_or_else(|| lens_tile(k, probe.variation, w, h));
        if tile < k {
            return Err(EstimateError::TileTooSmall { tile, kernel: k });
        }
        let (columns, rows) = tile_grid(w, h, tile);
        let window = opts.window.unwrap_or_else(|| default_window(k, w, h));
        if window < k {
            return Err(EstimateError::WindowTooSmall { window, kernel: k });
        }
        Ok(Layout { kernel: k, columns, rows, window, centers: PsfGrid::regular_centers(w, h, columns, rows), variation: probe.channel_variation })
    }

    fn tiles(&self) -> usize {
        self.columns * self.rows
    }
}

/// The data term's masks and the exposure ratios.
struct ValidData {
    valid_masks: Vec<Vec<bool>>,
    /// `s_c = Σ open / Σ pinhole` over the valid pixels.
    ratio: Vec<f64>,
    saturated_fraction: f64,
}

/// Valid pixels per channel (a kernel radius from the edges, the wide-open pixel unsaturated
/// and no saturated pinhole pixel in its footprint) and the exposure ratio over them.
fn valid_data(open: &Image, open_lin: &[Plane], pin_reg: &[Plane], pin_sat_reg: &[Vec<bool>], k: usize, opts: &EstimateOptions) -> Result<ValidData, EstimateError> {
    let (w, h, nch) = (open.width(), open.height(), open.channel_count());
    let r = k / 2;
    let mut valid_masks = Vec::with_capacity(nch);
    let mut ratio = Vec::with_capacity(nch);
    let mut sat_count = 0usize;
    for c in 0..nch {
        let bad_pin = dilate(&pin_sat_reg[c], w, h, r);
        let so: Vec<bool> = open.planes[c].data.iter().map(|&v| v >= opts.saturation).collect();
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
            return Err(EstimateError::NoValidPixels { channel: open.channels[c].clone() });
        }
        ratio.push(so_sum / sp_sum);
        valid_masks.push(m);
    }
    Ok(ValidData { valid_masks, ratio, saturated_fraction: sat_count as f64 / (w * h * nch) as f64 })
}

/// Per channel and tile: `(TV weight, data pixels, noise level)` of the window fit.
type TileFits = Vec<Vec<(f32, usize, f64)>>;

/// Fits every (channel, centre) on its own window, in parallel; returns the kernels, the
/// profile's estimation figures and the per-tile fit figures.
fn fit_windows(open_lin: &[Plane], pin_reg: &[Plane], data: &ValidData, layout: &Layout, opts: &EstimateOptions) -> (Vec<Vec<Plane>>, EstimationInfo, TileFits) {
    let (w, h, nch, k, nt) = (open_lin[0].width, open_lin[0].height, open_lin.len(), layout.kernel, layout.tiles());
    let jobs: Vec<(usize, usize)> = (0..nch).flat_map(|c| (0..nt).map(move |t| (c, t))).collect();
    let bar = progress_bar(opts.progress, jobs.len() as u64, "estimating PSFs");
    let cancelled = AtomicBool::new(false);
    let results: Vec<_> = jobs
        .par_iter()
        .map(|&(c, t)| {
            let win = fit_window(layout.centers[t], layout.window, w, h);
            let td = tile_data(&open_lin[c], &pin_reg[c], &data.valid_masks[c], data.ratio[c] as f32, win, k);
            let settings = TileSettings {
                kernel_size: k,
                lambda: None,
                lambda_scale: opts.lambda_scale as f32,
                noise_sigma: None,
                mu_relative: opts.mu_relative as f32,
                max_iterations: opts.max_iterations,
                tolerance: opts.tolerance,
            };
            let res = solve_tile(&td, &settings, |_, _| !cancelled.load(Ordering::Relaxed));
            bar.inc(1);
            (c, t, res)
        })
        .collect();
    bar.finish_and_clear();

    let mut kernels = vec![vec![Plane::new(k, k); nt]; nch];
    let mut info = EstimationInfo {
        lambda: 0.0,
        mu: opts.mu_relative,
        noise_sigma: vec![],
        iterations: vec![vec![0; nt]; nch],
        relative_gap: vec![vec![0.0; nt]; nch],
        residual_rms: vec![vec![0.0; nt]; nch],
        saturated_fraction: data.saturated_fraction,
        seconds: 0.0,
    };
    let mut lam_sum = 0.0;
    let mut fits = vec![vec![(0.0f32, 0usize, 0.0f64); nt]; nch];
    for (c, t, res) in results {
        fits[c][t] = (res.lambda, res.data_pixels, res.noise_sigma);
        kernels[c][t] = res.kernel;
        info.iterations[c][t] = res.stats.iterations;
        info.relative_gap[c][t] = res.stats.criterion;
        info.residual_rms[c][t] = res.residual_rms;
        lam_sum += res.lambda as f64;
    }
    info.lambda = lam_sum / jobs.len() as f64;
    (kernels, info, fits)
}

/// Exponent `p` of the TV weight's scaling by the kernel's energy spread ([`spread_factors`]).
pub const SPREAD_EXPONENT: f64 = 1.0;

/// Bounds of the spread factor ([`spread_factors`]).
pub const SPREAD_BOUNDS: (f64, f64) = (0.5, 3.0);

/// The TV weight's factor per channel from its kernels' energy spread (docs/estimation.md
/// "Prior scaled by spread"): `f_c = clamp(((r_c + 1) / (r̃ + 1))^p, 1/2, 3)`, with `r_c` the
/// median over the channel's window fits of the main-lobe radius ([`support_radius`], 99 %) and
/// `r̃` the median of `r_c` over the channels; every kernel of channel `c` gets `f_c`. TV costs
/// `≈ 2/R` for a unit-sum disc of radius `R`, so one `λ` regularises a wide kernel far less than
/// a compact one while its many small coefficients are the noisiest; a compact, structured
/// kernel (a sharp core, rings) suffers TV's flattening most. Per channel, not per kernel: the
/// radius of one noisy window fit is itself noisy (per kernel, the achromat's p90 rose from
/// 9.7 % to 10.7 %).
pub fn spread_factors(kernels: &[Vec<Plane>], p: f64) -> Vec<Vec<f64>> {
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(1.0)
    };
    let radii: Vec<f64> = kernels.iter().map(|ch| median(ch.iter().map(|b| support_radius(b, SUPPORT_ENERGY) + 1.0).collect())).collect();
    let typical = median(radii.clone());
    kernels.iter().zip(&radii).map(|(ch, &r)| vec![(r / typical).powf(p).clamp(SPREAD_BOUNDS.0, SPREAD_BOUNDS.1); ch.len()]).collect()
}

/// Refines all kernels of each channel jointly with the interpolated forward model
/// ([`joint`]); the profile's per-tile figures then describe the refined kernels. Returns the
/// convergence terms `[channel][tile]` with [`EstimateOptions::convergence_tail`], else nothing,
/// and the fitted model's prediction of every channel ([`joint::refine_channel`]'s
/// `prediction`).
#[allow(clippy::too_many_arguments)]
fn refine_jointly(open_lin: &[Plane], pin_reg: &[Plane], data: &ValidData, layout: &Layout, channels: &[String], fits: &TileFits, kernels: &mut [Vec<Plane>], info: &mut EstimationInfo, opts: &EstimateOptions) -> (Vec<Vec<Plane>>, Vec<Plane>) {
    let shape = PsfGrid { kernel_size: layout.kernel, columns: layout.columns, rows: layout.rows, centers: layout.centers.clone(), channels: channels.to_vec(), kernels: vec![] };
    let o = crate::solve::primal_dual::SplitOptions { max_iterations: opts.joint_iterations, min_iterations: 5, tolerance: opts.tolerance * 0.1 };
    let mut power = Vec::new();
    let bar = progress_bar(opts.progress, (open_lin.len() * opts.joint_iterations) as u64, "joint refinement");
    let mut convergence = Vec::new();
    let mut predictions = Vec::with_capacity(open_lin.len());
    for c in 0..open_lin.len() {
        let mut sharp = pin_reg[c].clone();
        sharp.scale(data.ratio[c] as f32);
        let field = if opts.lambda_scale > 0.0 { layout.variation.get(c).copied() } else { None };
        let fit = joint::refine_channel(&open_lin[c], &sharp, &data.valid_masks[c], &shape, &mut kernels[c], &fits[c], &o, &mut power, &bar, joint::JOINT_DATA_PIXELS, opts.select_lambda && opts.lambda_scale > 0.0, field, opts.convergence_tail);
        predictions.push(fit.prediction);
        if opts.convergence_tail {
            convergence.push(fit.convergence);
        }
        let (st, rms) = (fit.stats, fit.residual_rms);
        bar.set_position(((c + 1) * opts.joint_iterations) as u64);
        for t in 0..layout.tiles() {
            info.iterations[c][t] += st.iterations;
            info.residual_rms[c][t] = rms;
        }
    }
    bar.finish_and_clear();
    (convergence, predictions)
}

/// The profile of an estimate: grid, source description and metadata.
fn assemble_profile(open: &Image, layout: &Layout, kernels: Vec<Vec<Plane>>, ratio: Vec<f64>, registration: RegistrationInfo, info: EstimationInfo, opts: &EstimateOptions) -> Profile {
    let (w, h, k) = (open.width(), open.height(), layout.kernel);
    let (cols, rows) = (layout.columns, layout.rows);
    let grid = PsfGrid { kernel_size: k, columns: cols, rows, centers: layout.centers.clone(), channels: open.channels.clone(), kernels };
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
    let psf = PsfTable { kernel_size: k, columns: cols, rows, centers: layout.centers.clone(), tile_size: Some(grid.tile_size(w, h)), files: BTreeMap::new() };
    let mut meta = Profile::new_meta(source, ratio, psf);
    meta.registration = registration;
    meta.estimation = info;
    meta.raw = open.raw.clone();
    Profile { meta, grid }
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

/// Fraction of the floor-subtracted probe energy the kernel support must hold
/// ([`support_radius`]).
pub const SUPPORT_ENERGY: f64 = 0.99;

/// Margin on the support radius: `r_k = ⌈SUPPORT_MARGIN · r_99 + 2⌉`, `k = 2 r_k + 1`.
pub const SUPPORT_MARGIN: f64 = 1.15;

/// What the probe kernels measured (docs/estimation.md "Kernel size", "Grid").
#[derive(Clone, Debug)]
pub struct FieldProbe {
    /// Kernel size (odd, pixels).
    pub kernel: usize,
    /// Field variation rate `g` (relative L2 change of the kernel per pixel of field distance,
    /// [`variation_rate`]): the largest over channels.
    pub variation: f64,
    /// `g_c` per channel (empty when no probe ran).
    pub channel_variation: Vec<f64>,
}

#[cfg(test)]
/// Picks the kernel size from probe estimates (docs/estimation.md "Kernel size"): a generous
/// probe kernel on five spots (centre and the four corners) of every channel, in parallel; each
/// probe's main-lobe support ([`support_radius`]), a probe far wider than its channel's other
/// spots checked with a smaller kernel ([`suspect_probes`], [`checked_radius`]); the largest over
/// channels and spots, with margin ([`SUPPORT_MARGIN`]), clamped to `[7, probe]`.
fn choose_kernel_size(open: &[Plane], pin: &[Plane], opts: &EstimateOptions) -> Result<usize, EstimateError> {
    probe_field(open, pin, None, opts).map(|p| p.kernel)
}

/// Probe kernels on five spots (centre, then the four corners) of every channel: the kernel
/// size (docs/estimation.md "Kernel size"; `fixed` when given) and the field variation rate
/// ([`variation_rate`]) of the kernels cropped to that size.
fn probe_field(open: &[Plane], pin: &[Plane], fixed: Option<usize>, opts: &EstimateOptions) -> Result<FieldProbe, EstimateError> {
    let (w, h) = (open[0].width, open[0].height);
    let probe_k = ((w.min(h) / 6) | 1).clamp(9, 127);
    // the probe window: a third of the short side, at least 2 and at most 4 probe kernels
    let tsz = (w.min(h) / 3).min(4 * probe_k).max(probe_k * 2).min(w.min(h));
    let all = vec![true; w * h];
    let spots = [((w - tsz) / 2, (h - tsz) / 2), (0, 0), (w - tsz, 0), (0, h - tsz), (w - tsz, h - tsz)];
    let jobs: Vec<(usize, (usize, usize))> = (0..open.len()).flat_map(|c| spots.iter().map(move |&s| (c, s))).collect();
    let ratio: Vec<f32> = open.iter().zip(pin).map(|(o, p)| (o.sum() / p.sum().max(1e-30)) as f32).collect();
    let probe = |c: usize, (x0, y0): (usize, usize), k: usize| -> Plane {
        let data = tile_data(&open[c], &pin[c], &all, ratio[c], (x0, x0 + tsz, y0, y0 + tsz), k);
        let st = TileSettings { kernel_size: k, lambda: None, lambda_scale: opts.lambda_scale as f32, noise_sigma: None, mu_relative: 1.0, max_iterations: 150, tolerance: 1e-3 };
        solve_tile(&data, &st, |_, _| true).kernel
    };
    let mut probes: Vec<Plane> = jobs.par_iter().map(|&(c, s)| probe(c, s, probe_k)).collect();
    let kernel = fixed.unwrap_or_else(|| {
        let mut radii: Vec<f64> = probes.iter().map(|p| support_radius(p, SUPPORT_ENERGY)).collect();
        // a probe far wider than its channel's other spots is fitted again with a smaller kernel
        let checks: Vec<(usize, Plane)> = suspect_probes(&radii, spots.len(), probe_k).into_par_iter().map(|(i, k2)| (i, probe(jobs[i].0, jobs[i].1, k2))).collect();
        for (i, p) in checks {
            if let Some(r) = checked_radius(support_radius(&p, SUPPORT_ENERGY), p.width) {
                radii[i] = r;
                probes[i] = p;
            }
        }
        let radius = radii.iter().copied().fold(1.0, f64::max);
        kernel_for_radius(radius).clamp(7, probe_k)
    });
    let centres: Vec<[f64; 2]> = spots.iter().map(|&(x, y)| [x as f64 + tsz as f64 / 2.0, y as f64 + tsz as f64 / 2.0]).collect();
    let channel_variation: Vec<f64> = probes.chunks(spots.len()).map(|p| variation_rate(p, &centres, kernel)).collect();
    let variation = channel_variation.iter().copied().fold(0.0, f64::max);
    Ok(FieldProbe { kernel, variation, channel_variation })
}

/// The probes to fit again before their radius sets the kernel size (docs/estimation.md "Kernel
/// size", *One wide probe*): `(index, k₂)` for every probe whose `r₉₉` exceeds
/// [`PROBE_OUTLIER`] times the median of its channel's spots (`radii[c · spots + s]`), with the
/// check kernel `k₂ = 2⌈2 · SUPPORT_MARGIN · r̃_c + 2⌉ + 1` (twice the support the typical spot
/// needs, `r̃_c` that median), when `k₂` is smaller than the probe `probe_k`.
///
/// A 127-px probe has 16 k unknowns against ≈ 66 k data pixels (its 256-px window padded by the
/// probe's radius), so a direction the target's content constrains weakly is left to TV, which
/// lets a faint streak grow from the core, and the 99 % radius counts it. The achromat on the deblur matrix's
/// calibration pair (`examples/deblur_matrix.rs`) read `r₉₉` 32 / 39 / 42 px at its top-right
/// corner in R / G / B against 2–11 at the other spots (true kernel 35 px), and 33 at the
/// top-left of G under Poisson–Gaussian noise: the kernel became 79–103 px, the grid 6×4–7×5.
pub fn suspect_probes(radii: &[f64], spots: usize, probe_k: usize) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    if spots == 0 {
        return out;
    }
    for (c, ch) in radii.chunks(spots).enumerate() {
        let mut sorted = ch.to_vec();
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2].max(1.0);
        let k2 = kernel_for_radius(2.0 * median);
        if k2 >= probe_k {
            continue;
        }
        out.extend(ch.iter().enumerate().filter(|&(_, &r)| r > PROBE_OUTLIER * median).map(|(s, _)| (c * spots + s, k2)));
    }
    out
}

/// The kernel side that holds a support radius `r` with margin: `2⌈SUPPORT_MARGIN · r + 2⌉ + 1`
/// (odd, unclamped).
fn kernel_for_radius(r: f64) -> usize {
    2 * (SUPPORT_MARGIN * r + 2.0).ceil() as usize + 1
}

/// How many times its channel's median spot radius a probe's `r₉₉` may be before it is fitted
/// again ([`suspect_probes`]). 2: a lens's PSF grows towards the corners, but rarely to twice
/// the typical spot's support at once; the artefacts seen were 3–5×.
pub const PROBE_OUTLIER: f64 = 2.0;

/// The radius a check probe of side `k₂` gives a suspect spot, or `None` when the check reaches
/// towards its own border (`r₉₉ ≥` [`PROBE_REACH`] `· (k₂ − 1)/2`): then the light really is
/// that wide (a kernel too small to hold it fills its outer rings) and the wide probe's radius
/// stands; otherwise the wide probe's extra support was the artefact and the check's radius is
/// the spot's.
pub fn checked_radius(r2: f64, k2: usize) -> Option<f64> {
    (r2 < PROBE_REACH * (k2.saturating_sub(1) / 2) as f64).then_some(r2)
}

/// The share of its half-width at which a check probe's radius counts as reaching its border
/// ([`checked_radius`]). 0.6, not ¾: [`support_radius`] takes the floor from a kernel's outer
/// quarter, so light that really fills a too-small check kernel out to its edge is partly
/// subtracted as floor and reads 0.65–0.75 of the half-width (a review's simulation of 47-px
/// checks of Gaussians σ 8–12 and discs R 22–26 px: r₉₉ 15–17 of 23); the artefacts' checks read
/// at most 11 of 23.
pub const PROBE_REACH: f64 = 0.6;

/// Field variation rate of one channel from its probes (`probes[0]` at the centre spot, the
/// rest at the corners, `centres` in pixels), each cropped to `k × k` about its centre:
/// `g = mean_i ‖b_i − b_0‖ / (‖b_0‖ · |x_i − x_0|)`, relative change per pixel.
pub fn variation_rate(probes: &[Plane], centres: &[[f64; 2]], k: usize) -> f64 {
    let b0 = testbed::embed_centered(&probes[0], k);
    let rates: Vec<f64> = probes[1..]
        .iter()
        .zip(&centres[1..])
        .map(|(p, c)| {
            let d = ((c[0] - centres[0][0]).powi(2) + (c[1] - centres[0][1]).powi(2)).sqrt().max(1.0);
            relative_error(&testbed::embed_centered(p, k), &b0) / d
        })
        .collect();
    rates.iter().sum::<f64>() / rates.len().max(1) as f64
}

/// Main-lobe support of a probe kernel: the Chebyshev radius about the centre holding `frac`
/// of its energy once the TV floor is removed. With `m(r)` the mean of the ring of Chebyshev
/// radius `r` and `n(r)` its pixel count, the floor `f` is the median of `m(r)` over the outer
/// quarter of the radii (`r ≥ 3c/4`, `c = (k − 1)/2`), and the radius is the smallest `r` with
/// `Σ_{ρ ≤ r} n(ρ)(m(ρ) − f) ≥ frac · Σ_ρ n(ρ)(m(ρ) − f)`. The raw encircled energy
/// counts the floor, which adds ~1 % of the energy per 10 rings of a
/// 127-px probe, and picks nearly the whole probe.
pub fn support_radius(k: &Plane, frac: f64) -> f64 {
    let c = k.width / 2;
    let (mut sum, mut count) = (vec![0.0f64; c + 1], vec![0usize; c + 1]);
    for y in 0..k.height {
        for x in 0..k.width {
            let r = x.abs_diff(c).max(y.abs_diff(c)).min(c);
            sum[r] += k.get(x, y) as f64;
            count[r] += 1;
        }
    }
    let mut outer: Vec<f64> = (3 * c / 4..=c).map(|r| sum[r] / count[r] as f64).collect();
    outer.sort_by(f64::total_cmp);
    let floor = outer.get(outer.len() / 2).copied().unwrap_or(0.0);
    let lobe: Vec<f64> = (0..=c).map(|r| sum[r] - floor * count[r] as f64).collect();
    let total: f64 = lobe.iter().sum();
    if total <= 0.0 {
        return c as f64;
    }
    let mut acc = 0.0;
    (0..=c).find(|&r| {
        acc += lobe[r];
        acc >= frac * total
    })
    .unwrap_or(c) as f64
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

/// Relative L2 errors ([`testbed::relative_error_centered`]: kernels of different sizes compare
/// about their centres) of every kernel of `g` against `truth`'s kernel interpolated at the same
/// tile centre, channel by channel, tiles in grid order.
pub fn kernel_errors(g: &PsfGrid, truth: &PsfGrid) -> Vec<f64> {
    let mut e = Vec::with_capacity(g.channels.len() * g.tile_count());
    for c in 0..g.channels.len() {
        for t in 0..g.tile_count() {
            let [x, y] = g.centers[t];
            e.push(testbed::relative_error_centered(&g.kernels[c][t], &truth.kernel_at(c, x, y)));
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

    /// Which probes are checked: only those more than 2× their channel's median spot, each with a
    /// check kernel twice the typical support (the achromat's measured radii on the deblur
    /// matrix's calibration pair under Poisson–Gaussian noise: three top-right probes and one
    /// top-left); a channel whose check kernel would not be smaller than the probe is left as it
    /// is; a check that reaches its border keeps the wide radius, one that stays inside replaces it.
    #[test]
    fn wide_probes_are_checked_with_a_smaller_kernel() {
        // R / G / B × centre, top-left, top-right, bottom-left, bottom-right
        let achromat = [4.0, 9.0, 41.0, 9.0, 9.0, 2.0, 33.0, 32.0, 9.0, 9.0, 5.0, 8.0, 31.0, 9.0, 8.0];
        let k2 = |r: f64| 2 * (2.0 * SUPPORT_MARGIN * r + 2.0).ceil() as usize + 1;
        assert_eq!(suspect_probes(&achromat, 5, 127), vec![(2, k2(9.0)), (6, k2(9.0)), (7, k2(9.0)), (12, k2(8.0))]);
        assert_eq!(k2(9.0), 47);
        // a lens whose corners are all wide, and a graded field within 2×, are not checked
        assert!(suspect_probes(&[10.0, 11.0, 12.0, 11.0, 12.0, 24.0, 26.0, 26.0, 28.0, 27.0], 5, 127).is_empty());
        assert!(suspect_probes(&[5.0, 8.0, 17.0, 9.0, 9.0], 5, 127).is_empty());
        // the check kernel must be smaller than the probe
        assert!(suspect_probes(&[40.0, 41.0, 90.0, 40.0, 40.0], 5, 127).is_empty());
        // the check's verdict: inside its border it replaces the radius, at its border the wide one stands
        // (a 47-px check has half-width 23; it reaches its border from 0.6 · 23 = 13.8: light that
        // really is wider reads 15–17 there, the artefacts' checks at most 11)
        assert_eq!(checked_radius(9.0, 47), Some(9.0));
        assert_eq!(checked_radius(13.0, 47), Some(13.0));
        assert_eq!(checked_radius(14.0, 47), None);
        assert_eq!(checked_radius(17.0, 47), None);
        assert_eq!(checked_radius(3.0, 0), None);
        assert!(suspect_probes(&achromat, 0, 127).is_empty());
    }

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
            Err(e @ EstimateError::Blank { image: "pinhole", .. }) => assert!(e.to_string().contains("pinhole image has no texture"), "{e}"),
            other => panic!("expected a blank-frame error, got {:?}", other.map(|_| ())),
        }
        match estimate(&blank, &textured, &opts) {
            Err(e @ EstimateError::Blank { image: "wide-open", .. }) => assert!(e.to_string().contains("wide-open image has no texture"), "{e}"),
            other => panic!("expected a blank-frame error, got {:?}", other.map(|_| ())),
        }
        assert!(estimate(&textured, &textured, &opts).is_ok());
    }

    /// A unit-sum kernel of side `k` from a profile `f(dx, dy)` about the centre.
    fn unit_kernel(k: usize, f: impl Fn(f32, f32) -> f32) -> Plane {
        let c = (k / 2) as f32;
        let mut p = Plane::from_fn(k, k, |x, y| f(x as f32 - c, y as f32 - c));
        let s = p.sum() as f32;
        p.scale(1.0 / s);
        p
    }

    /// The raw encircled energy: radius (about the kernel centre, Chebyshev distance) holding `frac` of the energy.
    fn energy_radius(k: &Plane, frac: f64) -> f64 {
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

    /// A disc of radius 6 on a flat floor (as TV leaves in a probe) has a support radius of 6,
    /// while the raw encircled energy counts the floor and is much larger.
    #[test]
    fn support_radius_ignores_the_floor() {
        let k = unit_kernel(41, |dx, dy| if dx.abs().max(dy.abs()) <= 6.0 { 1.0 } else { 0.004 });
        assert_eq!(support_radius(&k, 0.99), 6.0);
        assert!(energy_radius(&k, 0.99) > 15.0, "{}", energy_radius(&k, 0.99));
    }

    /// A synthetic lens with a known chromatic blur: red a disc of radius 12 px, green and blue
    /// Gaussians of σ 1.2 and 1.6 px. The chosen kernel covers the red disc (k ≥ 25) and stays
    /// within the margin rule's bound for a 13-px support (k ≤ 2⌈1.15·13 + 2⌉ + 1 = 37).
    #[test]
    fn kernel_size_covers_the_widest_channel() {
        let (w, h) = (240, 240);
        let mut r = crate::rng::Rng::new(3);
        let sharp = two_pixel_cells(w, h, &mut r);
        let gauss = |s: f32| unit_kernel(13, move |dx, dy| (-(dx * dx + dy * dy) / (2.0 * s * s)).exp());
        let kernels = [unit_kernel(25, |dx, dy| if dx * dx + dy * dy <= 144.0 { 1.0 } else { 0.0 }), gauss(1.2), gauss(1.6)];
        let open: Vec<Plane> = kernels
            .iter()
            .map(|k| {
                let b = crate::solve::conv::convolve_direct(&sharp, k);
                Plane::from_fn(w, h, |x, y| b.get(x, y) + 0.002 * r.normal() as f32)
            })
            .collect();
        let pin = vec![sharp; 3];
        let k = choose_kernel_size(&open, &pin, &EstimateOptions::default()).expect("kernel size");
        assert!((25..=37).contains(&k), "kernel {k}");
    }

    /// A random target of 2 × 2-px cells, values uniform in [0.2, 0.8] (the kernel-size tests).
    fn two_pixel_cells(w: usize, h: usize, r: &mut crate::rng::Rng) -> Plane {
        let cells: Vec<f32> = (0..(w / 2) * (h / 2)).map(|_| 0.2 + 0.6 * r.uniform() as f32).collect();
        Plane::from_fn(w, h, |x, y| cells[(y / 2) * (w / 2) + x / 2])
    }

    /// One corner that really is wide is not taken for a probe artefact: a sharp field (Gaussian
    /// σ 1.2 px) with an 18-px-radius disc in the top-right corner only. That probe is more than
    /// 2× its channel's median, so it is checked with a smaller kernel (25 px, half-width 12);
    /// the disc fills the check to its border and the wide radius stands: the kernel is the wide
    /// probe's (35 px: the probe's `r₉₉` undershoots the 18-px disc, as on the test bed), not the
    /// check's (27 px when the check is believed, `PROBE_REACH` = 2).
    #[test]
    fn one_wide_corner_that_is_real_keeps_its_kernel() {
        let (w, h) = (240, 240);
        let mut r = crate::rng::Rng::new(5);
        let sharp = two_pixel_cells(w, h, &mut r);
        let narrow = crate::solve::conv::convolve_direct(&sharp, &unit_kernel(13, |dx, dy| (-(dx * dx + dy * dy) / (2.0 * 1.2 * 1.2)).exp()));
        let disc = crate::solve::conv::convolve_direct(&sharp, &unit_kernel(37, |dx, dy| if dx * dx + dy * dy <= 324.0 { 1.0 } else { 0.0 }));
        let open = Plane::from_fn(w, h, |x, y| if x >= 150 && y < 90 { disc.get(x, y) } else { narrow.get(x, y) } + 0.002 * r.normal() as f32);
        let k = choose_kernel_size(&[open], &[sharp], &EstimateOptions::default()).expect("kernel size");
        assert!((33..=41).contains(&k), "kernel {k}");
    }

    /// The variation rate is the mean relative change centre → corner per pixel: identical
    /// probes give 0; corners whose kernel differs by a known relative L2 amount give that
    /// amount over the distance; the probes are cropped to `k` first.
    #[test]
    fn variation_rate_is_relative_change_per_pixel() {
        let g = |s: f32| unit_kernel(21, move |dx, dy| (-(dx * dx + dy * dy) / (2.0 * s * s)).exp());
        let centres = [[100.0, 100.0], [0.0, 0.0], [200.0, 0.0], [0.0, 200.0], [200.0, 200.0]];
        let same = vec![g(2.0); 5];
        assert!(variation_rate(&same, &centres, 21) < 1e-12);
        let mut varied = same.clone();
        for p in &mut varied[1..] {
            *p = g(2.5);
        }
        let d = relative_error(&g(2.5), &g(2.0));
        let want = d / (2.0f64.sqrt() * 100.0);
        assert!((variation_rate(&varied, &centres, 21) - want).abs() < 1e-9 * want.max(1e-9), "{} vs {want}", variation_rate(&varied, &centres, 21));
        // a change only in the tails beyond k does not count
        let mut tails = same.clone();
        tails[1].data[0] += 0.05;
        assert!(variation_rate(&tails, &centres, 11) < 1e-12);
    }

    /// The spread factor, per channel: a channel whose median kernel has twice the typical
    /// channel's radius gets twice the TV weight on every kernel, the typical channel 1, a
    /// channel of deltas the lower bound; `p = 0` turns it off.
    #[test]
    fn spread_factors_follow_the_channel_radius() {
        let disc = |r: f32| unit_kernel(41, move |dx, dy| if dx.abs().max(dy.abs()) <= r { 1.0 } else { 0.0 });
        let ks = vec![vec![disc(4.0), disc(4.0), disc(5.0)], vec![disc(9.0), disc(9.0), disc(0.0)], vec![disc(0.0)]];
        let f = spread_factors(&ks, 1.0);
        assert_eq!(f.iter().map(Vec::len).collect::<Vec<_>>(), vec![3, 3, 1]);
        assert!(f[0].iter().all(|&x| (x - 1.0).abs() < 1e-12), "{f:?}");
        assert!(f[1].iter().all(|&x| (x - 2.0).abs() < 1e-12), "{f:?}");
        assert_eq!(f[2][0], SPREAD_BOUNDS.0);
        assert!(spread_factors(&ks, 0.0).iter().flatten().all(|&x| x == 1.0));
    }

    /// The lens-tied spacing: `GRID_CHANGE / g` within [1.8 kernels, half the short side]; a
    /// field that does not vary gets the coarsest grid, a quickly varying one the finest.
    #[test]
    fn lens_tile_follows_the_variation() {
        let (k, w, h) = (31, 1024, 768);
        assert_eq!(lens_tile(k, 0.0, w, h), 384);
        assert_eq!(lens_tile(k, 1e-6, w, h), 384);
        assert_eq!(lens_tile(k, 1.0, w, h), default_tile(k, w, h));
        assert_eq!(lens_tile(k, GRID_CHANGE / 200.0, w, h), 200);
        assert_eq!(lens_tile(k, f64::NAN, w, h), 384);
    }

    /// Every grid a spacing gives is given back by the spacing found for it.
    #[test]
    fn tile_for_grid_reproduces_the_grid() {
        for (w, h) in [(1024, 768), (4000, 3000), (256, 192)] {
            for t in (32..w.min(h)).step_by(7) {
                let (c, r) = tile_grid(w, h, t);
                let back = tile_for_grid(w, h, c, r).expect("a spacing");
                assert_eq!(tile_grid(w, h, back), (c, r), "{w}x{h} tile {t}");
                assert!(back >= t, "{w}x{h}: {back} < {t}");
            }
        }
        assert_eq!(tile_for_grid(1024, 768, 1, 9), None);
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

