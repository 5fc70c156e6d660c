//! What the bootstrap cannot see: the split of a test-bed lens's kernel error against the truth
//! (issue 16, branch e15u; docs/notes/estimation-history.md "Re-measured on the present code, and
//! what the achromat's missing error is (issue 16, branch e15u)").
//!
//! `cargo run --release --example unc_split -- /work/shared/data/lenses/achromat-f4 [steps]`
//!
//! Renders the test bed's first pair (seed 1) through a truth profile exactly as
//! `lensrig bench --testbed` does, estimates it with the default options (the bench's estimate),
//! then refits **noise-free** renderings of the same scene on fixed grids so that each
//! approximation of the model shows alone:
//!
//! - `A`: the truth's own grid and kernel size (the model can hold the truth exactly: what is
//!   left is the solver and the registration);
//! - `B`: the estimate's grid, the truth's kernel size (+ the grid's representation of the field);
//! - `C`: the estimate's grid and kernel size (+ the crop to the estimate's support);
//! - `C0`: as `C` with registration off (the pair is aligned by construction);
//! - `E`: as `C` without the prior (`c_λ = 0`): the noise-free data fitted by least squares;
//! - `F`: as `E` with 4× the iterations and tolerance 1e-5 (convergence);
//! - `G`: the noisy pair on the estimate's grid without the prior (the bootstrap's `b̂₀`);
//!
//! and prints, per channel, the median relative L2 error of each against the truth blended at
//! the fit's centres, the crop's own share (‖T − crop_k T‖ / ‖T‖), and the noisy estimate's
//! error. `steps` (e.g. `ABC`) picks the refits (default all).

use lensrig::estimate::testbed::{embed_centered, errors_against_truth, noise_target_pair, quantile, relative_error_centered};
use lensrig::estimate::register::RegistrationModel;
use lensrig::estimate::{estimate, tile_for_grid, Estimate, EstimateOptions};
use lensrig::image::Transfer;
use lensrig::optics::capture::{Rendered, Sensor};
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::profile::Profile;

fn pair(truth: &PsfGrid, w: usize, h: usize, seed: u64, noise: bool) -> (Rendered, Rendered) {
    let sensor = Sensor { full_well_e: 15_000.0, read_noise_e: 4.0, bits: 16, transfer: Transfer::Linear, noise };
    noise_target_pair(truth, w, h, seed, &sensor, 0.75).unwrap()
}

fn med(v: &[f64]) -> f64 {
    quantile(v, 0.5).unwrap_or(f64::NAN)
}

fn fit(label: &str, p: &(Rendered, Rendered), o: &EstimateOptions, truth: &PsfGrid) -> (Estimate, Vec<Vec<f64>>) {
    let t0 = std::time::Instant::now();
    let e = estimate(&p.0.image, &p.1.image, o).unwrap();
    let errs = errors_against_truth(&e.profile.grid, truth);
    let g = &e.profile.grid;
    let m: Vec<String> = errs.iter().map(|v| format!("{:.2}%", med(v) * 100.0)).collect();
    let p90: Vec<String> = errs.iter().map(|v| format!("{:.2}%", quantile(v, 0.9).unwrap_or(f64::NAN) * 100.0)).collect();
    let sig: Vec<String> = e.noise_sigma.iter().map(|v| format!("{v:.2e}")).collect();
    println!("{label}: {}x{} of {} px, {:.0} s; median error {} (p90 {}); noise σ {}", g.columns, g.rows, g.kernel_size, t0.elapsed().as_secs_f64(), m.join(" / "), p90.join(" / "), sig.join(" / "));
    (e, errs)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let truth = Profile::load(std::path::Path::new(&args[1])).unwrap().grid;
    let steps = args.get(2).cloned().unwrap_or_else(|| "ABCDEFG".into());
    let (w, h) = (1024, 768);
    let noisy = pair(&truth, w, h, 1, true);
    let (est, errs) = fit("estimate (noisy, defaults)", &noisy, &EstimateOptions::default(), &truth);
    let g = &est.profile.grid;
    // the crop's share at the estimate's centres
    for (c, name) in g.channels.iter().enumerate() {
        let crop: Vec<f64> = g.centers.iter().map(|&[x, y]| {
            let t = truth.kernel_at(c, x, y);
            relative_error_centered(&embed_centered(&t, g.kernel_size), &t)
        }).collect();
        let vs_crop: Vec<f64> = g.centers.iter().enumerate().map(|(i, &[x, y])| relative_error_centered(&g.kernels[c][i], &embed_centered(&truth.kernel_at(c, x, y), g.kernel_size))).collect();
        println!("{name}: crop share median {:.2}% (p90 {:.2}%); noisy estimate vs cropped truth {:.2}% (vs truth {:.2}%)", med(&crop) * 100.0, quantile(&crop, 0.9).unwrap_or(0.0) * 100.0, med(&vs_crop) * 100.0, med(&errs[c]) * 100.0);
    }
    let clean = pair(&truth, w, h, 1, false);
    let fixed = |cols: usize, rows: usize, k: usize, reg: RegistrationModel| EstimateOptions { kernel_size: Some(k), tile: tile_for_grid(w, h, cols, rows), field_variation: Some(est.field_variation.clone()), registration: reg, ..EstimateOptions::default() };
    let t = RegistrationModel::Translation;
    if steps.contains('A') {
        fit("A noise-free, truth grid, truth size", &clean, &fixed(truth.columns, truth.rows, truth.kernel_size, t), &truth);
    }
    if steps.contains('B') {
        fit("B noise-free, estimate grid, truth size", &clean, &fixed(g.columns, g.rows, truth.kernel_size, t), &truth);
    }
    if steps.contains('C') {
        fit("C noise-free, estimate grid, estimate size", &clean, &fixed(g.columns, g.rows, g.kernel_size, t), &truth);
    }
    if steps.contains('D') {
        fit("C0 as C, registration off", &clean, &fixed(g.columns, g.rows, g.kernel_size, RegistrationModel::None), &truth);
    }
    if steps.contains('E') {
        fit("E as C, no prior (c_λ = 0)", &clean, &EstimateOptions { lambda_scale: 0.0, ..fixed(g.columns, g.rows, g.kernel_size, t) }, &truth);
    }
    if steps.contains('F') {
        let o = EstimateOptions { lambda_scale: 0.0, max_iterations: 600, joint_iterations: 160, tolerance: 1e-5, ..fixed(g.columns, g.rows, g.kernel_size, t) };
        fit("F as E, 4x the iterations, tolerance 1e-5", &clean, &o, &truth);
    }
    if steps.contains('G') {
        let o = EstimateOptions { lambda_scale: 0.0, ..fixed(g.columns, g.rows, g.kernel_size, t) };
        fit("G noisy pair, as C, no prior", &noisy, &o, &truth);
    }
}
