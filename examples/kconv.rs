//! Convergence of the diagnosis' kernel fit on a benchmark case: the base model (as
//! `diagnose` builds it) with several kernel budgets, χ²/N and the floor ratio of each.
//! `cargo run --release --example kconv -- W H K ITERS[,ITERS…] [seed]`
use lensrig::diagnose::bench::proof_options;
use lensrig::diagnose::fit::{fit, Data, FitSettings, Model};
use lensrig::diagnose::proof::{floor_ratio, render_case, CaseSpec};
use lensrig::diagnose::{model, noise};
use lensrig::estimate::{estimate, EstimateOptions};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let (w, h, k): (usize, usize, usize) = (a[1].parse().unwrap(), a[2].parse().unwrap(), a[3].parse().unwrap());
    let iters: Vec<usize> = a[4].split(',').map(|s| s.parse().unwrap()).collect();
    let seed: u64 = a.get(5).map_or(41, |s| s.parse().unwrap());
    let mut spec = CaseSpec { width: w, height: h, channels: 3, kernel_size: k, ..CaseSpec::default() };
    if w != 256 {
        spec.grid = (7, 5);
    }
    if std::env::var("MONO").is_ok() {
        spec.channels = 1;
    }
    let t = std::time::Instant::now();
    let case = render_case(None, seed, &spec).unwrap();
    eprintln!("render {:.1} s", t.elapsed().as_secs_f64());
    let mut opts = proof_options(&spec);
    if w != 256 {
        opts.estimate.tile = None;
    }
    let (open, pinhole) = (&case.open.image, &case.pinhole.image);
    let t = std::time::Instant::now();
    let eo = EstimateOptions { saturation: f32::INFINITY, ..opts.estimate.clone() };
    let prof = estimate(open, pinhole, &eo).unwrap().profile;
    eprintln!("estimate {:.1} s", t.elapsed().as_secs_f64());
    let mut data = Data::new(open, pinhole, 1.0 / case.pinhole_frames as f64);
    let init = Model { corrections: model::Corrections::default(), grid: prof.grid.clone(), exposure: prof.meta.exposure_ratio.clone() };
    // noise curves from a long fit's residual (fixed for every budget below)
    let t = std::time::Instant::now();
    let long = fit(&data, &init.corrections, &init, FitSettings { rounds: 3, kernel_iterations: *iters.last().unwrap() });
    eprintln!("curve fit {:.1} s", t.elapsed().as_secs_f64());
    data.curves = (0..open.channel_count()).map(|c| noise::measure_residual(&open.planes[c], &long.predicted[c], &long.eval[c], 16, 8, Some(&long.reference_highpass[c]))).collect();
    for &it in &iters {
        let t = std::time::Instant::now();
        let f = fit(&data, &init.corrections, &init, FitSettings { rounds: 3, kernel_iterations: it });
        println!("iters {it:4}: χ²/N {:.4}  floor× {:.4}  {:.1} s", f.chi2() / f.n() as f64, floor_ratio(&case, &f.predicted, &f.eval), t.elapsed().as_secs_f64());
    }
}
