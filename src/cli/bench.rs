//! `lensrig bench`: the estimation speed benchmark, printed as a table (wall seconds, median
//! relative L2 kernel error against the truth, median iterations).
//!
//! Cases from the core issue: a 1024×768 RGB pair with 63-pixel kernels on a fixed 4×3 grid, and
//! (with `--large`) a 4000×3000 RGB pair on a fixed 8×6 grid; each case is also timed on the
//! grid `estimate` picks by default (`--tile` unset: the spacing tied to the lens,
//! [`lensrig::estimate::lens_tile`]), which is what users get and what the speed goal of issue
//! 16 is about. The grid column says which. Pairs are rendered with the lens
//! simulator's PSFs on a coarse field grid (rendering is not what is timed), with an ideal
//! pinhole reference; only `estimate` is timed, on all cores rayon sees. Each case is timed with
//! the per-window fits alone (`--joint-iterations 0`) and with the joint refinement
//! ([`lensrig::estimate::joint`], the default pipeline: at most 32 FISTA iterations, stopping
//! when χ² stalls; on the 12-megapixel case on a subsample of the image's blocks,
//! [`lensrig::estimate::joint::JOINT_DATA_PIXELS`]). `--kernel` and `--tile` replace a case's
//! 63-pixel kernel and its tile side. The criterion benches (`benches/`) time the kernels
//! underneath.
//!
//! `--testbed DIR` runs the estimation test bed instead (issue 16, docs/benchmarks.md): the
//! truth lenses in DIR and the simulator's singlet at two chromatic strengths, rendered at
//! 1024×768 RGB with Poisson–Gaussian noise (full well 15 000 e⁻, read 4 e⁻) and estimated with
//! the default options; kernel errors (relative L2, per cent) per lens and channel against the
//! truth blended at each estimated centre ([`lensrig::estimate::testbed`]) and, layout-free,
//! at a fixed lattice reaching a kernel radius from the frame's edges
//! ([`lensrig::estimate::testbed::field_errors_against_truth`]), cross-validation
//! on an independent pair (residual RMS ÷ the noise RMS the true kernels leave: the wide-open
//! capture's noise plus the pinhole's noise propagated through the true kernels,
//! [`lensrig::estimate::testbed::CrossValidation`]; then ÷ the wide-open noise alone, the former
//! figure), wall and CPU seconds of `estimate`.
use super::args::EstimateArgs;
use anyhow::{Context, Result};
use clap::Args;
use lensrig::diagnose::simulate::predict;
use lensrig::estimate::bootstrap::{bootstrap_estimate, predicted_error, BootstrapOptions, KernelUncertainty};
use lensrig::estimate::testbed::{errors_against_truth, field_errors_against_truth, lens_selected, noise_target_pair, quantile, simulator_short_name, CrossValidation};
use lensrig::estimate::{estimate, kernel_errors, median_max, process_cpu_seconds, EstimateOptions};
use lensrig::image::{Image, Plane};
use lensrig::optics::capture::{render, Blur, Rendered, Sensor, Shot};
use lensrig::optics::lens::LensModel;
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::rng::Rng;
use lensrig::profile::Profile;
use lensrig::target::{render_noise_scene, TargetSpec};
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Also run the 12-megapixel case (several minutes); with `--testbed`, the simulator's
    /// singlet at 4000x3000.
    #[arg(long)]
    pub large: bool,
    /// Run the estimation test bed instead: every truth lens in DIR (e.g.
    /// ../shared/data/lenses) and the simulator's singlet at two chromatic strengths, with the
    /// default settings unless estimation flags change them.
    #[arg(long, value_name = "DIR")]
    pub testbed: Option<PathBuf>,
    /// With `--testbed`: only the lenses whose name contains this text, or whose short name
    /// does (`sim1`, `sim2`: the simulator's singlet at chromatic strength ×1, ×2;
    /// `sim1-4000x3000` with `--large`).
    #[arg(long, requires = "testbed")]
    pub only: Option<String>,
    /// With `--testbed`: also bootstrap the uncertainty with this many replicates and print the
    /// predicted relative L2 error (‖std‖/‖k‖, median over kernels) against the measured one.
    #[arg(long, requires = "testbed", default_value_t = 0)]
    pub bootstrap: usize,
    #[command(flatten)]
    pub estimation: EstimateArgs,
}

struct Case {
    name: &'static str,
    width: usize,
    height: usize,
    kernel: usize,
    columns: usize,
    rows: usize,
}

/// A case's pair (wide open through the lens's PSF grid, ideal pinhole) and the true grid.
fn render_case(c: &Case) -> Result<(Image, Image, PsfGrid)> {
    let mut lens = LensModel::demo(c.width, c.height);
    // scale the blur so the PSFs fill a 63-px kernel at f/4 on this sensor
    lens.pixel_pitch_um = 2.0;
    let spec = TargetSpec::new("A4", 300, 4, 3)?;
    let scene = render_noise_scene(&spec, c.width, c.height, 1.6, 3.0, 3.0);
    let scene: Vec<Plane> = vec![scene; 3];
    let grid = lens.psf_grid(4.0, c.columns, c.rows, c.kernel);
    let shot = Shot { blur: Blur::Grid(grid.clone()), ..Shot::ideal(0.75) };
    let open = render(&scene, &lens, &shot, &Sensor::default(), &mut Rng::new(1));
    let pin = render(&scene, &lens, &Shot::ideal(0.75), &Sensor::default(), &mut Rng::new(2));
    Ok((open.image, pin.image, grid))
}

/// Times one estimate and prints its table row. `default_grid`: the grid `estimate` picks by
/// default for the kernel (`--tile` unset: [`lensrig::estimate::lens_tile`], what users get)
/// instead of the case's fixed grid.
fn time_row(a: &BenchArgs, c: &Case, open: &Image, pin: &Image, truth: &PsfGrid, joint: usize, default_grid: bool) -> Result<()> {
    let mut opts = a.estimation.options();
    opts.kernel_size = Some(a.estimation.kernel.unwrap_or(c.kernel));
    opts.tile = if default_grid { a.estimation.tile } else { Some(a.estimation.tile.unwrap_or(c.width / c.columns)) };
    opts.joint_iterations = joint;
    let t = std::time::Instant::now();
    let est = estimate(open, pin, &opts)?;
    let secs = t.elapsed().as_secs_f64();
    let (median, _) = median_max(&kernel_errors(&est.profile.grid, truth));
    let mut its: Vec<usize> = est.profile.meta.estimation.iterations.iter().flatten().copied().collect();
    its.sort_unstable();
    let stage = if joint > 0 { format!("window fits + joint refinement (≤ {joint} its)") } else { "window fits".to_string() };
    let g = &est.profile.grid;
    let grid = format!("{}×{}{}", g.columns, g.rows, if default_grid { " (default)" } else { " (fixed)" });
    println!("| {} | {grid} | {stage} | {:.1} | {:.1}% | {} |", c.name, secs, median * 100.0, its.get(its.len() / 2).copied().unwrap_or(0));
    Ok(())
}

pub fn run(a: &BenchArgs) -> Result<()> {
    if let Some(dir) = &a.testbed {
        return run_testbed(a, dir);
    }
    let mut cases = vec![Case { name: "1024x768 RGB, 63 px", width: 1024, height: 768, kernel: 63, columns: 4, rows: 3 }];
    if a.large {
        cases.push(Case { name: "4000x3000 RGB, 63 px", width: 4000, height: 3000, kernel: 63, columns: 8, rows: 6 });
    }
    println!("machine: {} logical cores (rayon), {}", rayon::current_num_threads(), std::env::consts::ARCH);
    println!("| case | grid | stage | seconds (wall) | median kernel error | iterations (median) |");
    println!("| --- | --- | --- | --- | --- | --- |");
    let joint = a.estimation.joint_iterations;
    for c in cases {
        let (open, pin, truth) = render_case(&c)?;
        let joint_runs: Vec<usize> = if joint > 0 { vec![0, joint] } else { vec![0] };
        for j in joint_runs {
            time_row(a, &c, &open, &pin, &truth, j, false)?;
        }
        // the grid users get (the default pipeline): what the speed goal is about
        time_row(a, &c, &open, &pin, &truth, joint, true)?;
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// The estimation test bed (issue 16): lenses lensrig did not make, default settings.
// ---------------------------------------------------------------------------------------------

/// Sensor of the test bed's captures: Poisson–Gaussian noise, full well 15 000 e⁻, read noise
/// 4 e⁻, 16-bit linear.
pub const TESTBED_SENSOR: Sensor = Sensor { full_well_e: 15_000.0, read_noise_e: 4.0, bits: 16, transfer: lensrig::image::Transfer::Linear, noise: true };

/// Exposure of a white scene point on the full-scale axis (as the demo).
const TESTBED_EXPOSURE: f64 = 0.75;

/// Whether a test-bed lens may be used to tune the estimator or is held out.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Split {
    Tuning,
    HeldOut,
}

impl Split {
    fn name(self) -> &'static str {
        match self {
            Split::Tuning => "tuning",
            Split::HeldOut => "held out",
        }
    }
}

/// The truth lenses (directories of `--testbed`) and their split. The simulator's own singlets
/// and the achromat are the tuning subset; the two real singlet designs are held out.
const TRUTH_LENSES: [(&str, Split); 3] = [("achromat-f4", Split::Tuning), ("sf11-singlet-25mm-f5.6", Split::HeldOut), ("lac9-singlet-stop-behind-f6.3", Split::HeldOut)];

/// One lens of the test bed: its name, split, and true PSF grid with the sensor size.
struct TestLens {
    name: String,
    /// The short name `--only` also matches (`sim1`, `sim2`; a truth lens's file name).
    short: String,
    split: Split,
    width: usize,
    height: usize,
    truth: PsfGrid,
}

/// The simulator's chromatic singlet ([`LensModel::demo`]) on the truth lenses' 3.45 µm pixels
/// at f/4, with the glass's Abbe number divided by `strength` (1: N-BK7; 2: twice the
/// chromatic focal shift), its PSFs at the simulator's suggested kernel size on a 9 × 7 lattice
/// whose outer centres lie on the frame's edges ([`PsfGrid::edge_centers`], as the mock camera
/// renders its lens), so the truth keeps changing out to the corners.
fn simulator_lens(strength: f64, width: usize, height: usize) -> TestLens {
    let mut lens = LensModel::demo(width, height);
    lens.pixel_pitch_um = 3.45;
    lens.glass = Some(lensrig::optics::lens::Glass { n_d: 1.5168, abbe: 64.17 / strength });
    let k = lens.suggested_kernel_size(4.0);
    let truth = lens.psf_grid_to_edges(4.0, 9, 7, k);
    let large = (width > 1024).then_some((width, height));
    let name = format!("simulator singlet, chromatic ×{strength}{}", large.map_or(String::new(), |(w, h)| format!(", {w}x{h}")));
    TestLens { name, short: simulator_short_name(strength, large), split: Split::Tuning, width, height, truth }
}

/// The test bed's lenses: the truth profiles found under `dir`, then the simulator's singlet at
/// two chromatic strengths; `only` keeps the lenses whose name or short name (`sim1`, `sim2`)
/// contains it ([`lens_selected`]).
fn testbed_lenses(dir: &Path, only: Option<&str>, large: bool) -> Result<Vec<TestLens>> {
    let keep = |n: &str, short: &str| lens_selected(n, short, only);
    let mut out = Vec::new();
    for (name, split) in TRUTH_LENSES {
        if !keep(name, name) {
            continue;
        }
        let p = Profile::load(&dir.join(name)).with_context(|| format!("test-bed lens {name} in {}", dir.display()))?;
        out.push(TestLens { name: name.to_string(), short: name.to_string(), split, width: p.meta.source.width, height: p.meta.source.height, truth: p.grid });
    }
    for strength in [1.0, 2.0] {
        let l = simulator_lens(strength, 1024, 768);
        if keep(&l.name, &l.short) {
            out.push(l);
        }
    }
    if large {
        out.push(simulator_lens(1.0, 4000, 3000));
    }
    Ok(out)
}

/// A calibration pair through `truth` (wide open: the noise target blurred by the truth grid
/// the way `simulate` blends it; pinhole: the sharp target), both with the test bed's noise;
/// `seed` picks the target pattern and the noise.
fn testbed_pair(l: &TestLens, seed: u64) -> Result<(Rendered, Rendered)> {
    Ok(noise_target_pair(&l.truth, l.width, l.height, seed, &TESTBED_SENSOR, TESTBED_EXPOSURE)?)
}

/// Cross-validation of `profile` on an independent pair (all channels pooled, `margin` px
/// from every edge left out): the residual against the wide-open capture's noise and against
/// the noise the true kernels of `truth` leave, which include the pinhole's own noise
/// ([`CrossValidation`]).
fn cross_validation(profile: &Profile, truth: &Profile, pair2: &(Rendered, Rendered), margin: usize) -> Result<CrossValidation> {
    let (open, pin) = pair2;
    let mut clean = pin.image.clone();
    clean.planes = pin.clean.clone();
    let pred = predict(profile, &pin.image)?;
    let (noisy, quiet) = (predict(truth, &pin.image)?, predict(truth, &clean)?);
    Ok(CrossValidation::from_planes(&pred.planes, &noisy.planes, &quiet.planes, &open.image.planes, &open.variance, margin))
}

/// Bootstraps the uncertainty of `est` ([`bootstrap_estimate`]: both captures resampled, the
/// whole pipeline per replicate, bias and variance) and prints one row per channel: the median
/// predicted relative L2 error (‖u‖/‖b̂‖) with its standard-deviation-only and bias-only parts,
/// the median measured error against the truth, the ratio of the medians, the per-kernel
/// ratio's p10 / p50 / p90, and PASS when the ratio of the medians is within [1/1.5, 1.5].
fn bootstrap_rows(replicates: usize, est: &lensrig::estimate::Estimate, opts: &EstimateOptions, errors: &[Vec<f64>], l: &TestLens) -> Result<Vec<String>> {
    let o = BootstrapOptions { replicates: replicates.max(2), ..BootstrapOptions::default() };
    let t0 = std::time::Instant::now();
    let unc = bootstrap_estimate(est, opts, &o)?;
    let secs = t0.elapsed().as_secs_f64();
    let g = &est.profile.grid;
    let med = |v: &[f64]| quantile(v, 0.5).unwrap_or(f64::NAN);
    let mut rows = Vec::new();
    for (c, ch) in g.channels.iter().enumerate() {
        let part = |f: fn(&KernelUncertainty) -> &Plane| -> Vec<f64> { (0..g.tile_count()).map(|t| predicted_error(f(&unc[c][t]), &g.kernels[c][t])).collect() };
        let (pred, std, bias, conv) = (part(|u| &u.total), part(|u| &u.std), part(|u| &u.bias), part(|u| &u.convergence));
        let ratios: Vec<f64> = pred.iter().zip(&errors[c]).map(|(p, m)| p / m.max(1e-12)).collect();
        let (p, m) = (med(&pred), med(&errors[c]));
        let ratio = p / m;
        let pass = if (1.0 / 1.5..=1.5).contains(&ratio) { "PASS" } else { "FAIL" };
        let q = |f: f64| quantile(&ratios, f).map_or("–".into(), |v| format!("{v:.2}"));
        rows.push(format!(
            "| {} | {} | {ch} | {:.2}% | {:.2}% / {:.2}% / {:.2}% | {:.2}% | {ratio:.2} | {} / {} / {} | {pass} | {replicates} / {secs:.0} |",
            l.name,
            l.split.name(),
            p * 100.0,
            med(&std) * 100.0,
            med(&bias) * 100.0,
            med(&conv) * 100.0,
            m * 100.0,
            q(0.1),
            q(0.5),
            q(0.9)
        ));
    }
    Ok(rows)
}

fn pct(v: Option<f64>) -> String {
    v.map_or("–".into(), |e| format!("{:.1}%", e * 100.0))
}

/// Runs the test bed: for each lens, a pair, `estimate` with the options of `a.estimation`
/// (the defaults unless flags change them), the kernel errors against the truth per channel,
/// the cross-validation on an independent pair, and the time.
fn run_testbed(a: &BenchArgs, dir: &Path) -> Result<()> {
    let lenses = testbed_lenses(dir, a.only.as_deref(), a.large)?;
    println!("machine: {} logical cores (rayon), {}; noise: full well {} e-, read {} e-", rayon::current_num_threads(), std::env::consts::ARCH, TESTBED_SENSOR.full_well_e, TESTBED_SENSOR.read_noise_e);
    println!("| lens | split | channel | kernel est / true | grid | median | p90 | max | field median / p90 | cross-validation ÷ open + pinhole noise (true kernels) | ÷ open noise only (true kernels) | seconds wall / CPU |");
    println!("| --- | --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    let mut boot = Vec::new();
    for l in &lenses {
        let pair = testbed_pair(l, 1)?;
        let pair2 = testbed_pair(l, 2)?;
        // with the bootstrap the joint fit is continued past its end to measure its
        // convergence term (the kernels are not changed; the timing then includes it)
        let opts = EstimateOptions { progress: false, convergence_tail: a.bootstrap > 0, ..a.estimation.options() };
        let (t0, c0) = (std::time::Instant::now(), process_cpu_seconds());
        let est = estimate(&pair.0.image, &pair.1.image, &opts)?;
        let wall = t0.elapsed().as_secs_f64();
        let cpu = process_cpu_seconds().zip(c0).map(|(b, a)| b - a);
        let stages: Vec<String> = est.stage_seconds.iter().map(|t| format!("{} {:.1} s / {} CPU-s", t.stage, t.wall, t.cpu.map_or("–".into(), |c| format!("{c:.1}")))).collect();
        eprintln!("{}: {}", l.name, stages.join(", "));
        let g = &est.profile.grid;
        let errors = errors_against_truth(g, &l.truth);
        let field = field_errors_against_truth(g, &l.truth, l.width, l.height);
        let field_all: Vec<f64> = field.iter().flatten().copied().collect();
        let margin = g.kernel_size.max(l.truth.kernel_size) / 2;
        let truth_profile = Profile { meta: est.profile.meta.clone(), grid: l.truth.clone() };
        let cv = cross_validation(&est.profile, &truth_profile, &pair2, margin)?;
        let cv_truth = cross_validation(&truth_profile, &truth_profile, &pair2, margin)?;
        let all: Vec<f64> = errors.iter().flatten().copied().collect();
        if a.bootstrap > 0 {
            let rows = bootstrap_rows(a.bootstrap, &est, &opts, &errors, l)?;
            rows.iter().for_each(|r| eprintln!("{r}"));
            boot.extend(rows);
        }
        let rows = g.channels.iter().map(String::as_str).zip(errors.iter().map(Vec::as_slice).zip(field.iter().map(Vec::as_slice))).chain([("all", (all.as_slice(), field_all.as_slice()))]);
        for (ch, (e, f)) in rows {
            let last = ch == "all";
            println!(
                "| {} | {} | {ch} | {} / {} | {}×{} | {} | {} | {} | {} / {} | {} | {} |",
                l.name,
                l.split.name(),
                g.kernel_size,
                l.truth.kernel_size,
                g.columns,
                g.rows,
                pct(quantile(e, 0.5)),
                pct(quantile(e, 0.9)),
                pct(quantile(e, 1.0)),
                pct(quantile(f, 0.5)),
                pct(quantile(f, 0.9)),
                if last { format!("{:.3} ({:.3}) | {:.3} ({:.3})", cv.ratio(), cv_truth.ratio(), cv.ratio_open(), cv_truth.ratio_open()) } else { " | ".to_string() },
                if last { format!("{wall:.1} / {}", cpu.map_or("–".into(), |c| format!("{c:.1}"))) } else { String::new() },
            );
        }
    }
    if !boot.is_empty() {
        println!("\nUncertainty calibration (predicted = ‖u‖/‖b̂‖ with u = √(bias² + var) per pixel; measured = error against the truth; medians over kernels; PASS: ratio of medians within [1/1.5, 1.5])");
        println!("| lens | split | channel | predicted | std / bias / convergence | measured | ratio | per-kernel ratio p10 / p50 / p90 | check | replicates / seconds |");
        println!("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | --- | ---: |");
        boot.iter().for_each(|r| println!("{r}"));
    }
    Ok(())
}

