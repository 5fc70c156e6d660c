//! How far the kernels of a `pinhole_diffraction` model are from converged at camera size: a
//! benchmark pair (`lensrig diagnose --bench-effect pinhole_diffraction`'s rendering) fitted
//! with the restoration fixed, round after round on every pixel, printing χ²/N, each round's
//! fall against χ²'s noise `√(2N)` and the floor ratio. The noise curves come from the residual
//! of a first fit of three rounds and stay fixed after.
//!
//! `cargo run --release --example diffconv -- SEED W H K ROUNDS R,G,B EPS_R,EPS_G,EPS_B SIGMA`
//! (the Airy radii, Wiener ε and aberration σ, e.g. the ones a diagnosis fitted).
//! docs/notes/diagnosis-history.md, "Session 58".
use lensrig::diagnose::bench::proof_options;
use lensrig::diagnose::fit::{fit, fit_from, Data, FitSettings, Model};
use lensrig::diagnose::model::{self, DiffractionCorrection};
use lensrig::diagnose::diffraction::{channel_bandwidth, channel_wavelength_um};
use lensrig::diagnose::residual_curves;
use lensrig::diagnose::proof::{floor_ratio, render_case, CaseSpec};
use lensrig::estimate::{estimate, EstimateOptions};

fn list(s: &str) -> Vec<f64> {
    s.split(',').map(|v| v.parse().unwrap()).collect()
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let n = |i: usize| a[i].parse::<usize>().unwrap();
    let (seed, w, h, k, rounds) = (n(1) as u64, n(2), n(3), n(4), n(5));
    let diff = DiffractionCorrection { airy_radius_px: list(&a[6]), epsilon: list(&a[7]), aberration_sigma_px: a[8].parse().unwrap(), bandwidth: ["R", "G", "B"].iter().map(|c| channel_bandwidth(c)).collect(), wavelength_um: ["R", "G", "B"].iter().map(|c| channel_wavelength_um(c)).collect(), spectral_stop: None };
    let spec = CaseSpec { width: w, height: h, channels: 3, kernel_size: k, grid: (7, 5), ..CaseSpec::default() };
    let case = render_case(Some("pinhole_diffraction"), seed, &spec).unwrap();
    println!("seed {seed} {w}x{h} k {k}: truth {}", case.truth);
    let mut opts = proof_options(&spec);
    opts.estimate.tile = None;
    let (open, pinhole) = (&case.open.image, &case.pinhole.image);
    let eo = EstimateOptions { saturation: f32::INFINITY, ..opts.estimate.clone() };
    let prof = estimate(open, pinhole, &eo).unwrap().profile;
    let mut data = Data::new(open, pinhole, 1.0 / case.pinhole_frames as f64);
    let corr = model::Corrections { pinhole_diffraction: Some(diff), ..Default::default() };
    let init = Model { corrections: corr.clone(), grid: prof.grid.clone(), exposure: prof.meta.exposure_ratio.clone() };
    let iters = opts.base_fit.kernel_iterations;
    let t = std::time::Instant::now();
    let mut f = fit(&data, &corr, &init, FitSettings { rounds: 3, kernel_iterations: iters });
    data.curves = residual_curves(open, &f);
    let noise = (2.0 * f.n() as f64).sqrt();
    // the first fit scored again with the curves measured from it: round 1's fall compares like
    // with like
    let mut last = fit(&data, &corr, &f.model, FitSettings { rounds: 0, kernel_iterations: 0 }).chi2();
    println!("first fit (3 rounds): floor× {:.4}  {:.0} s", floor_ratio(&case, &f.predicted, &f.eval), t.elapsed().as_secs_f64());
    for r in 1..=rounds {
        f = fit_from(&data, &f.model.corrections, &f.model, FitSettings { rounds: 1, kernel_iterations: iters }, &f.warm);
        let chi2 = f.chi2();
        println!("round {r}: χ²/N {:.4}  fall {:8.0} ({:5.1}× noise)  floor× {:.4}  {:.0} s", chi2 / f.n() as f64, last - chi2, (last - chi2) / noise, floor_ratio(&case, &f.predicted, &f.eval), t.elapsed().as_secs_f64());
        last = chi2;
    }
}
