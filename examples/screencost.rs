//! Seconds of one screening fit (2 rounds × 40 kernel iterations on the diagnosis' subset of
//! about 150 000 pixels per channel) at W×H RGB, 45-px kernels on a 7×5 grid, clean seed 41
//! from the truth PSFs, twice: docs/notes/diagnosis-history.md "Session 67: a covering subset
//! of large blocks". `cargo run --release --example screencost -- W H`
use lensrig::diagnose::fit::{fit_subset, Data, FitSettings, Model};
use lensrig::diagnose::proof::{render_case, CaseSpec};
use lensrig::diagnose::{model, noise};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let (w, h): (usize, usize) = (a[1].parse().unwrap(), a[2].parse().unwrap());
    let spec = CaseSpec { width: w, height: h, channels: 3, kernel_size: 45, grid: (7, 5), ..CaseSpec::default() };
    let t = std::time::Instant::now();
    let case = render_case(None, 41, &spec).unwrap();
    eprintln!("render {:.1} s", t.elapsed().as_secs_f64());
    let (open, pinhole) = (&case.open.image, &case.pinhole.image);
    let mut data = Data::new(open, pinhole, 1.0 / case.pinhole_frames as f64);
    let all = vec![true; w * h];
    data.curves = (0..3).map(|c| noise::measure_residual(&open.planes[c], &case.open.clean[c], &all, 16, 8, None)).collect();
    let grid = case.open.psfs.clone().unwrap();
    let init = Model { corrections: model::Corrections::default(), grid, exposure: vec![1.0; 3] };
    for _ in 0..2 {
        let t = std::time::Instant::now();
        let f = fit_subset(&data, &init.corrections, &init, FitSettings { rounds: 2, kernel_iterations: 40 }, 150_000);
        eprintln!("screening fit {:.1} s, chi2/N {:.3}", t.elapsed().as_secs_f64(), f.chi2() / f.n() as f64);
    }
}
