use lensrig::estimate::{estimate, relative_error, EstimateOptions};
use lensrig::optics::capture::{render, Sensor, Shot};
use lensrig::optics::lens::LensModel;
use lensrig::rng::Rng;
use lensrig::target::{render_noise_scene, TargetSpec};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let lam: f64 = args.get(1).map(|s| s.parse().unwrap()).unwrap_or(1.0);
    let sigma: f32 = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(1.0);
    let (w, h) = (384, 288);
    let lens = LensModel::demo(w, h);
    let k = lens.suggested_kernel_size(4.0);
    println!("suggested k = {k}");
    let spec = TargetSpec::new("A4", 300, 4, 7).unwrap();
    let scene = render_noise_scene(&spec, w, h, 1.6, 10.0, 10.0);
    let scene3 = vec![scene.clone(), scene.clone(), scene];
    let sensor = Sensor::default();
    let t = std::time::Instant::now();
    let open = render(&scene3, &lens, &Shot::lens(4.0, 0.8, 8, 6, k), &sensor, &mut Rng::new(1));
    let pin = render(&scene3, &lens, &Shot::ideal(0.8), &sensor, &mut Rng::new(2));
    println!("render {:.2}s", t.elapsed().as_secs_f64());
    let opts = EstimateOptions { kernel_size: Some(k), tile: Some(96), lambda_scale: lam, sigma, ..Default::default() };
    let t = std::time::Instant::now();
    let est = estimate(&open.image, &pin.image, &opts).unwrap();
    println!("estimate {:.2}s reg {:?} s {:?}", t.elapsed().as_secs_f64(), est.profile.meta.registration.translation, est.profile.meta.exposure_ratio);
    let truth = open.psfs.unwrap();
    let g = &est.profile.grid;
    let mut errs = vec![];
    for c in 0..3 {
        for t in 0..g.tile_count() {
            let [x, y] = g.centers[t];
            let tk = truth.kernel_at(c, x, y);
            let e = relative_error(&g.kernels[c][t], &tk);
            errs.push(e);
        }
    }
    let its = &est.profile.meta.estimation.iterations;
    let gaps = &est.profile.meta.estimation.relative_gap;
    println!("iters {:?}\ngaps {:?}", its[1], gaps[1].iter().map(|g| format!("{g:.1e}")).collect::<Vec<_>>());
    let mut s = errs.clone();
    s.sort_by(|a, b| a.partial_cmp(b).unwrap());
    println!("rel err median {:.4} max {:.4} min {:.4}", s[s.len() / 2], s[s.len() - 1], s[0]);
    println!("noise {:?}", est.noise_sigma);
}
