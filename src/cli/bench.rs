//! `lensrig bench`: the estimation speed benchmark, printed as a table (wall seconds, median
//! relative L2 kernel error against the truth, median iterations).
//!
//! Cases from the core issue: a 1024×768 RGB pair with 63-pixel kernels on 12 tiles, and
//! (with `--large`) a 4000×3000 RGB pair with 48 tiles. Pairs are rendered with the lens
//! simulator's PSFs on a coarse field grid (rendering is not what is timed), with an ideal
//! pinhole reference; only `estimate` is timed, on all cores rayon sees. Each case is timed with
//! the per-window fits alone (`--joint-iterations 0`) and with the joint refinement
//! ([`lensrig::estimate::joint`], the default pipeline: at most 40 FISTA iterations, stopping
//! when χ² stalls; on the 12-megapixel case on a subsample of the image's blocks,
//! [`lensrig::estimate::joint::JOINT_DATA_PIXELS`]). `--kernel` and `--tile` replace a case's
//! 63-pixel kernel and its tile side. The criterion benches (`benches/`) time the kernels
//! underneath.
use super::args::EstimateArgs;
use anyhow::Result;
use clap::Args;
use lensrig::estimate::{estimate, kernel_errors, median_max};
use lensrig::image::{Image, Plane};
use lensrig::optics::capture::{render, Blur, Sensor, Shot};
use lensrig::optics::lens::LensModel;
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::rng::Rng;
use lensrig::target::{render_noise_scene, TargetSpec};

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Also run the 12-megapixel case (several minutes).
    #[arg(long)]
    pub large: bool,
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

/// Times one estimate and prints its table row.
fn time_row(a: &BenchArgs, c: &Case, open: &Image, pin: &Image, truth: &PsfGrid, joint: usize) -> Result<()> {
    let mut opts = a.estimation.options();
    opts.kernel_size = Some(a.estimation.kernel.unwrap_or(c.kernel));
    opts.tile = Some(a.estimation.tile.unwrap_or(c.width / c.columns));
    opts.joint_iterations = joint;
    let t = std::time::Instant::now();
    let est = estimate(open, pin, &opts)?;
    let secs = t.elapsed().as_secs_f64();
    let (median, _) = median_max(&kernel_errors(&est.profile.grid, truth));
    let mut its: Vec<usize> = est.profile.meta.estimation.iterations.iter().flatten().copied().collect();
    its.sort_unstable();
    let stage = if joint > 0 { format!("window fits + joint refinement (≤ {joint} its)") } else { "window fits".to_string() };
    println!("| {} | {stage} | {:.1} | {:.1}% | {} |", c.name, secs, median * 100.0, its.get(its.len() / 2).copied().unwrap_or(0));
    Ok(())
}

pub fn run(a: &BenchArgs) -> Result<()> {
    let mut cases = vec![Case { name: "1024x768 RGB, 63 px, 12 tiles", width: 1024, height: 768, kernel: 63, columns: 4, rows: 3 }];
    if a.large {
        cases.push(Case { name: "4000x3000 RGB, 63 px, 48 tiles", width: 4000, height: 3000, kernel: 63, columns: 8, rows: 6 });
    }
    println!("machine: {} logical cores (rayon), {}", rayon::current_num_threads(), std::env::consts::ARCH);
    println!("| case | stage | seconds (wall) | median kernel error | iterations (median) |");
    println!("| --- | --- | --- | --- | --- |");
    let joint = a.estimation.joint_iterations;
    for c in cases {
        let (open, pin, truth) = render_case(&c)?;
        let joint_runs: Vec<usize> = if joint > 0 { vec![0, joint] } else { vec![0] };
        for j in joint_runs {
            time_row(a, &c, &open, &pin, &truth, j)?;
        }
    }
    Ok(())
}
