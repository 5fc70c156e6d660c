//! Bias of the noise curve measured from the diagnosis' provisional fit, against the law the
//! proof case rendered (the simulator's default sensor): the raw residual curve and the one
//! corrected for the share of the noise's high-pass the kernel fit absorbs (`1 − α_hp`).
//! Also the estimator alone (the residual of the noise-free render: the real noise), the same
//! signal with homoscedastic white noise, and the reference-noise share ρ.
//! `cargo run --release --example noisebias -- EFFECT|clean SEED W H K CHANNELS ITERS`
//! (`K` the kernel size; `ITERS` kernel iterations per round of the 3-round provisional fit;
//! `PROBE_SUBSET=PIXELS` also runs the probe on the screening subset of that size and prints
//! its count and scaled `α_hp` next to the whole-image probe's; `LENS=DIR` renders through a
//! truth profile, e.g. a real design in `../shared/data/lenses/`, whose size, grid and kernel
//! size replace `W H K` and the case is RGB, as `diagnose --bench-lens` does).
use lensrig::diagnose::bench::proof_options;
use lensrig::diagnose::fit::{fit, measure_kernel_dof, Data, FitSettings, Model, KERNEL_STEP};
use lensrig::diagnose::proof::{render_case, CaseSpec};
use lensrig::diagnose::{model, noise, residual_curves};
use lensrig::estimate::{estimate, EstimateOptions};
use lensrig::image::{Plane, Transfer};
use lensrig::optics::capture::Sensor;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let effect = (a[1] != "clean").then(|| a[1].as_str());
    let n = |i: usize| a[i].parse::<usize>().unwrap();
    let (seed, w, h, k, ch, iters) = (n(2) as u64, n(3), n(4), n(5), n(6), n(7));
    let mut spec = CaseSpec { width: w, height: h, channels: ch, kernel_size: k, ..CaseSpec::default() };
    if w != 256 {
        spec.grid = (7, 5);
    }
    if let Some(dir) = std::env::var_os("LENS") {
        let p = lensrig::profile::Profile::load(std::path::Path::new(&dir)).unwrap();
        spec = spec.through_truth(&p).expect("an RGB truth profile");
    }
    let (w, h, k, ch) = (spec.width, spec.height, spec.kernel_size, spec.channels);
    let case = render_case(effect, seed, &spec).unwrap();
    let mut opts = proof_options(&spec);
    if w != 256 {
        opts.estimate.tile = None;
    }
    let (open, pinhole) = (&case.open.image, &case.pinhole.image);
    let eo = EstimateOptions { saturation: f32::INFINITY, ..opts.estimate.clone() };
    let prof = estimate(open, pinhole, &eo).unwrap().profile;
    let data = Data::new(open, pinhole, 1.0 / case.pinhole_frames as f64);
    let init = Model { corrections: model::Corrections::default(), grid: prof.grid.clone(), exposure: prof.meta.exposure_ratio.clone() };
    let settings = FitSettings { rounds: 3, kernel_iterations: iters };
    let mut f = fit(&data, &init.corrections, &init, settings);
    let raw = residual_curves(open, &f);
    let dof = measure_kernel_dof(&data, &f, settings, 0x00d0_f5eed, usize::MAX);
    if let Some(px) = std::env::var("PROBE_SUBSET").ok().and_then(|v| v.parse::<usize>().ok()) {
        let sub = measure_kernel_dof(&data, &f, settings, 0x00d0_f5eed, px);
        let scaled: Vec<String> = sub.highpass_absorbed.iter().map(|a| format!("{:.4}", a * sub.share)).collect();
        println!("probe on every pixel: df {:.1} α {:?}; on ~{px} pixels per channel (share {:.3}): df {:.1} α×share {scaled:?}", dof.df, dof.highpass_absorbed, sub.share, sub.df);
    }
    if std::env::var_os("PROBE_ROUNDS1").is_some() {
        let one = measure_kernel_dof(&data, &f, FitSettings { rounds: 1, ..settings }, 0x00d0_f5eed, usize::MAX);
        println!("probe 3 rounds: df {:.1} α {:?}; 1 round: df {:.1} α {:?}", dof.df, dof.highpass_absorbed, one.df, one.highpass_absorbed);
    }
    f.set_dof(dof.clone());
    let corrected = residual_curves(open, &f);
    let sensor = Sensor::default();
    // count-weighted mean of measured / true variance over the bins, and the fitted law at two levels
    let ratio = |c: &noise::NoiseCurve| c.bins.iter().map(|b| b.1 / sensor.variance(b.0 as f32) as f64 * b.2 as f64).sum::<f64>() / c.bins.iter().map(|b| b.2 as f64).sum::<f64>();
    let law = |c: &noise::NoiseCurve, l: f64| {
        let pg = noise::PoissonGaussian::fit(c, Transfer::Linear);
        pg.variance(l) / sensor.variance(l as f32) as f64
    };
    println!("{} seed {seed} {w}x{h}x{ch} k {k} iters 3x{iters} step {KERNEL_STEP:?}: N {} p_eff {:.0} (p_eff/N {:.4}), α_hp {:?}", a[1], f.n(), dof.df, dof.df / f.n() as f64, dof.highpass_absorbed.iter().map(|v| format!("{v:.4}")).collect::<Vec<_>>());
    let energy = |g: &lensrig::optics::psf_grid::PsfGrid, c: usize| g.kernels[c].iter().map(|k| k.data.iter().map(|v| (v * v) as f64).sum::<f64>()).sum::<f64>() / g.kernels[c].len() as f64;
    for c in 0..ch {
        // the estimator alone: the residual of the noiseless render is the wide-open noise
        let pure = noise::measure_residual(&open.planes[c], &case.open.clean[c], &f.eval[c], 16, 8, None);
        println!("  channel {c}: residual of the noiseless render: measured/true {:.4}", ratio(&pure));
        for b in &pure.bins {
            println!("    bin {:.4}: {:.4} ({} windows)", b.0, b.1 / sensor.variance(b.0 as f32) as f64, b.2);
        }
        // homoscedastic white noise on the same signal
        let mut r = lensrig::rng::Rng::new(99);
        let v = 2e-5f64;
        let homo = Plane::from_fn(w, h, |x, y| case.open.clean[c].get(x, y) + (v.sqrt() * r.normal()) as f32);
        let hc = noise::measure_residual(&homo, &case.open.clean[c], &f.eval[c], 16, 8, None);
        println!("  channel {c}: homoscedastic noise: measured/true {:?}", hc.bins.iter().map(|b| format!("{:.4}", b.1 / v)).collect::<Vec<_>>());
        let rho = f.reference_highpass[c].data.iter().zip(&f.eval[c]).filter(|p| *p.1).map(|p| *p.0 as f64).sum::<f64>() / f.eval[c].iter().filter(|e| **e).count() as f64;
        println!("  channel {c}: mean ρ {rho:.4}; ΣK² fitted {:.5}, true {:.5}", energy(&f.model.grid, c), case.open.psfs.as_ref().map_or(0.0, |g| energy(g, c)));
        println!(
            "  channel {c}: measured/true variance raw {:.4} corrected {:.4}; law at 0.15, 0.35: raw {:.4} {:.4}, corrected {:.4} {:.4}",
            ratio(&raw[c]),
            ratio(&corrected[c]),
            law(&raw[c], 0.15),
            law(&raw[c], 0.35),
            law(&corrected[c], 0.15),
            law(&corrected[c], 0.35)
        );
        for b in &corrected[c].bins {
            println!("    corrected bin {:.4}: {:.4} ({} windows)", b.0, b.1 / sensor.variance(b.0 as f32) as f64, b.2);
        }
    }
}
