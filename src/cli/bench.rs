//! `lensrig bench`: the estimation speed benchmark, printed as a table.
//!
//! Cases from the core issue: a 1024×768 RGB pair with 63-pixel kernels on 12 tiles, and
//! (with `--large`) a 4000×3000 RGB pair with 48 tiles. Pairs are rendered with the lens
//! simulator's PSFs on a coarse field grid (rendering is not what is timed), with an ideal
//! pinhole reference; only `estimate` is timed, on all cores rayon sees. Each case is timed with
//! the per-window fits alone (`--joint-iterations 0`) and with the joint refinement
//! ([`lensrig::estimate::joint`], the default pipeline: at most 40 FISTA iterations, stopping
//! when χ² stalls; on the 12-megapixel case on a subsample of the image's blocks,
//! [`lensrig::estimate::joint::JOINT_DATA_PIXELS`]).
use anyhow::Result;
use clap::Args;
use lensrig::estimate::{estimate, relative_error, EstimateOptions};
use lensrig::image::Plane;
use lensrig::optics::capture::{render, Blur, Sensor, Shot};
use lensrig::optics::lens::LensModel;
use lensrig::rng::Rng;
use lensrig::target::{render_noise_scene, TargetSpec};

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Also run the 12-megapixel case (several minutes).
    #[arg(long)]
    pub large: bool,
    #[arg(long, default_value_t = 150)]
    pub max_iterations: usize,
    /// Relative step at which a window's iterations stop.
    #[arg(long, default_value_t = 1e-3)]
    pub tolerance: f64,
    /// Iterations of the joint refinement with the interpolated forward model (0: off).
    #[arg(long, default_value_t = 40)]
    pub joint_iterations: usize,
    /// Fit window side around each PSF centre; default: chosen by `estimate`.
    #[arg(long)]
    pub window: Option<usize>,
}

struct Case {
    name: &'static str,
    width: usize,
    height: usize,
    kernel: usize,
    columns: usize,
    rows: usize,
}

pub fn run(a: &BenchArgs) -> Result<()> {
    let mut cases = vec![Case { name: "1024x768 RGB, 63 px, 12 tiles", width: 1024, height: 768, kernel: 63, columns: 4, rows: 3 }];
    if a.large {
        cases.push(Case { name: "4000x3000 RGB, 63 px, 48 tiles", width: 4000, height: 3000, kernel: 63, columns: 8, rows: 6 });
    }
    println!("machine: {} logical cores (rayon), {}", rayon::current_num_threads(), std::env::consts::ARCH);
    println!("| case | stage | seconds (wall) | median kernel error | iterations (median) |");
    println!("| --- | --- | --- | --- | --- |");
    for c in cases {
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
        let tile = c.width / c.columns;
        let joint_runs: Vec<usize> = if a.joint_iterations > 0 { vec![0, a.joint_iterations] } else { vec![0] };
        for joint in joint_runs {
        let opts = EstimateOptions { kernel_size: Some(c.kernel), tile: Some(tile), max_iterations: a.max_iterations, tolerance: a.tolerance, window: a.window, joint_iterations: joint, ..Default::default() };
        let t = std::time::Instant::now();
        let est = estimate(&open.image, &pin.image, &opts)?;
        let secs = t.elapsed().as_secs_f64();
        let g = &est.profile.grid;
        let mut errs: Vec<f64> = Vec::new();
        for ch in 0..3 {
            for t in 0..g.tile_count() {
                let [x, y] = g.centers[t];
                errs.push(relative_error(&g.kernels[ch][t], &grid.kernel_at(ch, x, y)));
            }
        }
        errs.sort_by(|x, y| x.total_cmp(y));
        let mut its: Vec<usize> = est.profile.meta.estimation.iterations.iter().flatten().copied().collect();
        its.sort_unstable();
        let stage = if joint > 0 { format!("window fits + joint refinement (≤ {joint} its)") } else { "window fits".to_string() };
        println!("| {} | {stage} | {:.1} | {:.1}% | {} |", c.name, secs, errs[errs.len() / 2] * 100.0, its[its.len() / 2]);
        }
    }
    Ok(())
}
