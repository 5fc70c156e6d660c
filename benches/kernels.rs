//! Criterion benches of the hot code paths, one group per kernel over a few sizes (pixels):
//! FFT convolution of a plane with one kernel ([`lensrig::solve::conv::Convolver`]), one
//! window's PSF solve ([`lensrig::estimate::solver::solve_tile`]), and the deconvolution of
//! one tile ([`lensrig::deconv::deblur`] on an image that is a single tile). Inputs are
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
use lensrig::rng::Rng;
use lensrig::solve::conv::Convolver;
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
    for &(n, k) in &[(64usize, 9usize), (96, 15), (128, 21)] {
        let sharp = noise_plane(n, n, 2);
        let open = Convolver::new(&gaussian(k, k as f32 / 6.0), n, n).apply(&sharp);
        let valid = vec![true; n * n];
        let data = tile_data(&open, &sharp, &valid, 1.0, (0, n, 0, n), k);
        let settings = TileSettings { kernel_size: k, lambda: None, lambda_scale: 1.0, noise_sigma: None, mu_relative: 1.0, max_iterations: 50, tolerance: 1e-3 };
        g.bench_with_input(BenchmarkId::new("solve_tile", format!("{n}px_k{k}")), &data, |b, d| b.iter(|| black_box(solve_tile(d, &settings, |_, _| true).kernel)));
    }
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

criterion_group!(benches, conv, psf_window, deconv_tile);
criterion_main!(benches);
