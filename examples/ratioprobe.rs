//! The stop read from the reference's colour spectra (`diffraction::spectral_stop`) on the
//! benchmark's `pinhole_diffraction` pairs (1024×768 RGB, 45-px kernels), against the
//! rendered truth, for each seed given.
//!
//! `cargo run --release --example ratioprobe -- SEED [SEED …]`; `EFFECT=…` renders another
//! bench effect (e.g. `misregistration+pinhole_diffraction`). docs/notes/diagnosis-history.md,
//! "Session 60".
use lensrig::diagnose::diffraction::spectral_stop;
use lensrig::diagnose::proof::{render_case, CaseSpec};

fn main() {
    let spec = CaseSpec { width: 1024, height: 768, channels: 3, kernel_size: 45, grid: (7, 5), ..CaseSpec::default() };
    println!("seed  true N/p  spectral N/p  ratio  spread  bands");
    for seed in std::env::args().skip(1).map(|a| a.parse::<u64>().expect("a seed")) {
        let effect = std::env::var("EFFECT").unwrap_or_else(|_| "pinhole_diffraction".into());
        let case = render_case(Some(&effect), seed, &spec).expect("a rendered case");
        let truth = case.truth["f_number_per_um_pitch"].as_f64().expect("the truth's N/p");
        match spectral_stop(&case.pinhole.image.planes, &["R", "G", "B"]) {
            Some(s) => println!("{seed}  {truth:.3}  {:.3}  {:.4}  {:.3}  {}", s.f_number_per_um_pitch, s.f_number_per_um_pitch / truth, s.spread, s.bands),
            None => println!("{seed}  {truth:.3}  –"),
        }
    }
}
