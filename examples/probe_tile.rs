// Experiment (not committed): convergence of one tile vs iterations and sigma.
use lensrig::estimate::solver::{solve_tile, TileSettings};
use lensrig::estimate::{noise_sigma, relative_error, tile_data};
use lensrig::optics::capture::{render, Sensor, Shot};
use lensrig::optics::lens::LensModel;
use lensrig::rng::Rng;
use lensrig::target::{render_noise_scene, TargetSpec};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let tile: usize = a[1].parse().unwrap();
    let fnum: f64 = a[2].parse().unwrap();
    let sigmas: Vec<f32> = a[3].split(',').map(|s| s.parse().unwrap()).collect();
    let iters: Vec<usize> = a[4].split(',').map(|s| s.parse().unwrap()).collect();
    let lams: Vec<f64> = a.get(5).map(|s| s.split(',').map(|v| v.parse().unwrap()).collect()).unwrap_or(vec![1.0]);
    let (w, h) = (tile + 140, tile + 140);
    let mut lens = LensModel::demo(1024, 768);
    lens.width = 1024; lens.height = 768;
    let k = lens.suggested_kernel_size(fnum);
    let spec = TargetSpec::new("A4", 300, 4, 7).unwrap();
    let scene = render_noise_scene(&spec, w, h, 1.6, 10.0, 10.0);
    let sc = vec![scene.clone(), scene.clone(), scene];
    // a uniform kernel over this patch: the lens's PSF at a mid-field point
    let mut g = lens.psf_grid(fnum, 1, 1, k);
    g.centers = vec![[(w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0]];
    for c in 0..3 { g.kernels[c][0] = lens.psf(fnum, c, 700.0, 500.0, k); }
    let sensor = Sensor::default();
    let open = render(&sc, &lens, &Shot { blur: lensrig::optics::capture::Blur::Grid(g.clone()), ..Shot::ideal(0.8) }, &sensor, &mut Rng::new(1));
    let pin = render(&sc, &lens, &Shot::ideal(0.8), &sensor, &mut Rng::new(2));
    let c = 1;
    let all = vec![true; w * h];
    let x0 = (w - tile) / 2;
    let td = tile_data(&open.image.planes[c], &pin.image.planes[c], &all, 1.0, (x0, x0 + tile, x0, x0 + tile), k);
    println!("k={k} domain {}x{} noise est {:.4} true {:.4}", td.pw, td.ph, noise_sigma(&open.image.planes[c]), (open.variance[c].mean()).sqrt());
    let sd = { let m = td.sharp.iter().map(|&v| v as f64).sum::<f64>() / td.sharp.len() as f64; (td.sharp.iter().map(|&v| (v as f64 - m).powi(2)).sum::<f64>() / td.sharp.len() as f64).sqrt() };
    let npx = td.mask.iter().filter(|&&b| b).count();
    let sig_true = (open.variance[c].mean()).sqrt();
    for &lam in &lams {
    for &s in &sigmas {
        for &it in &iters {
            let lambda = (lam * sig_true * sd * (npx as f64).sqrt()) as f32;
            let st = TileSettings { kernel_size: k, lambda: if lam < 0.0 { None } else { Some(lambda) }, lambda_scale: 1.0, mu_relative: 1.0, max_iterations: it, tolerance: 0.0, sigma: s };
            let t = std::time::Instant::now();
            let r = solve_tile(&td, &st, |_, _| true);
            println!("lam {lam} ({:.3}) noise {:.4} sigma {s:6} it {it:5}: err {:.4} gap {:.2e} resid {:.5} t {:.2}s", r.lambda, r.noise_sigma, relative_error(&r.kernel, &g.kernels[c][0]), r.stats.criterion, r.residual_rms, t.elapsed().as_secs_f64());
        }
    }
    }
}
