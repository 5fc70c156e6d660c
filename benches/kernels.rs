//! Criterion benches of the hot code paths, one group per kernel over a few sizes (pixels):
//! FFT convolution of a plane with one kernel ([`lensrig::solve::conv::Convolver`]), one
//! window's PSF solve ([`lensrig::estimate::solver::solve_tile`]; `160px_k31` is the
//! achromat's window: a regression of its normal operator's codegen, such as the accumulator
//! moved to the stack in session 17, shows there first), the joint refinement's blocked kernel
//! operator ([`lensrig::optics::kernel_operator::KernelOperator`], `A b` and `Aᵀ r` on an
//! achromat-like grid of 31-px kernels), and the deconvolution of one tile
//! ([`lensrig::deconv::deblur`] on an image that is a single tile). Inputs are
//! synthetic and seeded; sizes are small so `cargo bench --no-run` builds quickly and a run
//! takes about a minute. `lensrig bench` prints the end-to-end estimation table instead.
//!
//! Run with `cargo bench --bench kernels` (add a group name to filter, e.g. `conv`).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use lensrig::deconv::synth::SyntheticLens;
use lensrig::deconv::{deblur, DeconvOptions};
use lensrig::estimate::solver::{solve_tile, TileSettings};
use lensrig::estimate::tile_data;
use lensrig::image::Plane;
use lensrig::optics::kernel_operator::KernelOperator;
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::rng::Rng;
use lensrig::solve::conv::Convolver;
use lensrig::solve::operator::LinearOperator;
use std::hint::black_box;
use std::time::Duration;

/// A seeded uniform-noise plane in [0.2, 0.8] (full scale).
fn noise_plane(w: usize, h: usize, seed: u64) -> Plane {
    let mut r = Rng::new(seed);
    Plane::from_fn(w, h, |_, _| 0.2 + 0.6 * r.uniform() as f32)
}

/// A normalised Gaussian kernel of side `k` and width `sigma` pixels.
fn gaussian(k: usize, sigma: f32) -> Plane {
    let c = (k / 2) as f32;
    let mut p = Plane::from_fn(k, k, |x, y| (-((x as f32 - c).powi(2) + (y as f32 - c).powi(2)) / (2.0 * sigma * sigma)).exp());
    let s = p.sum() as f32;
    p.scale(1.0 / s);
    p
}

fn conv(c: &mut Criterion) {
    let mut g = c.benchmark_group("conv");
    g.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(2));
    for &(n, k) in &[(128usize, 15usize), (256, 31), (512, 63)] {
        let img = noise_plane(n, n, 1);
        let conv = Convolver::new(&gaussian(k, k as f32 / 6.0), n, n);
        g.bench_with_input(BenchmarkId::new("plane", format!("{n}px_k{k}")), &img, |b, img| b.iter(|| black_box(conv.apply(img))));
    }
    g.finish();
}

fn psf_window(c: &mut Criterion) {
    let mut g = c.benchmark_group("psf_window");
    g.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(3));
    for &(n, k) in &[(64usize, 9usize), (96, 15), (128, 21), (160, 31)] {
        let sharp = noise_plane(n, n, 2);
        let open = Convolver::new(&gaussian(k, k as f32 / 6.0), n, n).apply(&sharp);
        let valid = vec![true; n * n];
        let data = tile_data(&open, &sharp, &valid, 1.0, (0, n, 0, n), k);
        let settings = TileSettings { kernel_size: k, lambda: None, lambda_scale: 1.0, noise_sigma: None, mu_relative: 1.0, max_iterations: 50, tolerance: 1e-3 };
        g.bench_with_input(BenchmarkId::new("solve_tile", format!("{n}px_k{k}")), &data, |b, d| b.iter(|| black_box(solve_tile(d, &settings, |_, _| true).kernel)));
    }
    g.finish();
}

/// `A b` and `Aᵀ r` of the joint refinement's operator on a 512×384 image with a 10×7 grid of
/// 31-px kernels (the achromat's kernel size and centre spacing, a quarter of its area).
fn kernel_operator(c: &mut Criterion) {
    let mut g = c.benchmark_group("kernel_operator");
    g.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(3));
    let (w, h, k, cols, rows) = (512usize, 384usize, 31usize, 10usize, 7usize);
    let sharp = noise_plane(w, h, 5);
    let kernels = vec![(0..cols * rows).map(|t| gaussian(k, 2.0 + (t % 5) as f32)).collect()];
    let grid = PsfGrid { kernel_size: k, columns: cols, rows, centers: PsfGrid::regular_centers(w, h, cols, rows), channels: vec!["G".into()], kernels };
    let op = KernelOperator::new(&sharp, &grid, usize::MAX);
    let b: Vec<f32> = grid.kernels[0].iter().flat_map(|p| p.data.iter().copied()).collect();
    let resid = noise_plane(w, h, 6).data;
    let mut out = vec![0.0f32; op.output_len()];
    g.bench_function(BenchmarkId::new("apply", format!("{w}x{h}_k{k}")), |bch| bch.iter(|| op.apply(black_box(&b), &mut out)));
    let mut grad = vec![0.0f32; op.input_len()];
    g.bench_function(BenchmarkId::new("adjoint", format!("{w}x{h}_k{k}")), |bch| bch.iter(|| op.apply_adjoint(black_box(&resid), &mut grad)));
    g.finish();
}

fn deconv_tile(c: &mut Criterion) {
    let mut g = c.benchmark_group("deconv_tile");
    g.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(4));
    for &n in &[48usize, 64, 96] {
        let grid = SyntheticLens::new(9, 3).grid(n, n, 3, 1, 1);
        let planes: Vec<Plane> = (0..3).map(|ch| Convolver::new(&grid.kernels[ch][0], n, n).apply(&noise_plane(n, n, 3 + ch as u64))).collect();
        let opts = DeconvOptions { tile_core: Some(n), ..DeconvOptions::default() };
        g.bench_with_input(BenchmarkId::new("rgb", format!("{n}px_k9")), &planes, |b, p| b.iter(|| black_box(deblur(p, &grid, &opts, &|_, _| {}).map(|r| r.1.tiles))));
    }
    g.finish();
}

criterion_group!(benches, conv, psf_window, kernel_operator, deconv_tile);
criterion_main!(benches);
