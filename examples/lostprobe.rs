//! The detail a restored reference gives up, on a benchmark pair: per channel, the lost
//! signal's variance `L` ([`lensrig::diagnose::diffraction::lost_signal_variance`]) from the
//! wide-open capture's PSD less its true mean noise variance, from the noise-free wide-open
//! signal's PSD, and the PSD's excess over the noise in bands of `|f|`, all ÷ the noise.
//!
//! `LENS=DIR cargo run --release --example lostprobe -- SEED R,G,B EPS_R,EPS_G,EPS_B SIGMA`
//! (the Airy radii, Wiener ε and aberration σ a diagnosis fitted).
use lensrig::diagnose::diffraction::{channel_bandwidth, lost_signal_variance, ReferencePsf};
use lensrig::diagnose::proof::{render_case, CaseSpec};
use lensrig::image::spectrum::RadialPsd;

fn list(s: &str) -> Vec<f64> {
    s.split(',').map(|v| v.parse().unwrap()).collect()
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seed: u64 = a[1].parse().unwrap();
    let (radii, eps, sigma) = (list(&a[2]), list(&a[3]), a[4].parse::<f64>().unwrap());
    let mut spec = CaseSpec { width: 1024, height: 768, channels: 3, kernel_size: 45, grid: (7, 5), ..CaseSpec::default() };
    if let Some(dir) = std::env::var_os("LENS") {
        let p = lensrig::profile::Profile::load(std::path::Path::new(&dir)).unwrap();
        spec = spec.through_truth(&p).expect("an RGB truth profile");
    }
    let case = render_case(Some("pinhole_diffraction"), seed, &spec).unwrap();
    println!("seed {seed}: truth {}", case.truth);
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        let open = &case.open.image.planes[c];
        let noise = case.open.variance[c].data.iter().map(|&v| v as f64).sum::<f64>() / open.data.len() as f64;
        let psf = ReferencePsf { radius_px: radii[c], aberration_px: sigma, bandwidth: channel_bandwidth(name) };
        let (psd, clean) = (RadialPsd::of(open), RadialPsd::of(&case.open.clean[c]));
        let l = lost_signal_variance(&psd, noise, &psf, eps[c]);
        let lc = lost_signal_variance(&clean, 0.0, &psf, eps[c]);
        let bands: Vec<String> = (0..10).map(|b| 0.05 * b as f64 + 0.025).map(|f| format!("{f:.3}:{:.2}|{:.2}", (psd.at(f, 0.0) - noise) / noise, clean.at(f, 0.0) / noise)).collect();
        println!("{name}: noise {noise:.3e}; L {:.3} (noisy PSD), {:.3} (clean PSD) × noise; PSD excess / clean, × noise, by |f|: {}", l / noise, lc / noise, bands.join(" "));
    }
}
