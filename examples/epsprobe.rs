//! Which noise variance the reference's Wiener restoration should take: on a benchmark pair
//! (`lensrig diagnose --bench-effect pinhole_diffraction`'s rendering, 1024×768 RGB, 45-px
//! kernels), per channel, the reference's true noise variance (the simulator's, averaged over
//! the frame), three estimates of it (`noise::measure` on the wide-open capture and on the
//! reference, and the reference's Hann-windowed periodogram beyond the cut-off of the band's
//! shortest wavelength, where a diffraction-limited reference holds noise only), and the flat
//! noise-to-signal ratio (`diffraction::noise_to_signal`, unbounded) each gives.
//!
//! `cargo run --release --example epsprobe -- SEED R,G,B` (the Airy radii in px at the bands'
//! centres; the model's radii, or the nominal ones). docs/notes/diagnosis-history.md, "Session 59".
use lensrig::diagnose::diffraction::{channel_bandwidth, noise_to_signal, ReferencePsf};
use lensrig::diagnose::noise::measure;
use lensrig::diagnose::proof::{render_case, CaseSpec};
use lensrig::image::{Plane, Transfer};
use lensrig::solve::fft::Fft2;

/// Mean periodogram power of `p` (mean removed, Hann window) at radial frequencies above `fc`
/// cycles per pixel, normalised so that white noise of variance σ² gives σ²; and the bin count.
fn power_beyond(p: &Plane, fc: f64) -> (f64, usize) {
    let (w, h) = (p.width, p.height);
    let hann = |i: usize, n: usize| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * (i as f64 + 0.5) / n as f64).cos();
    let mean = p.mean();
    let mut sw2 = 0.0;
    let mut win = vec![0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let ww = hann(x, w) * hann(y, h);
            win[y * w + x] = ((p.data[y * w + x] as f64 - mean) * ww) as f32;
            sw2 += ww * ww;
        }
    }
    let fft = Fft2::plan(w, h);
    let spec = fft.forward(&win);
    let (mut acc, mut n) = (0.0, 0usize);
    for (i, s) in spec.iter().enumerate() {
        let (fx, fy) = fft.frequency(i);
        if ((fx * fx + fy * fy) as f64).sqrt() > fc {
            acc += s.norm_sqr() as f64;
            n += 1;
        }
    }
    (acc / n.max(1) as f64 / sw2, n)
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seed: u64 = a[1].parse().unwrap();
    let radii: Vec<f64> = a[2].split(',').map(|v| v.parse().unwrap()).collect();
    let spec = CaseSpec { width: 1024, height: 768, channels: 3, kernel_size: 45, grid: (7, 5), ..CaseSpec::default() };
    let case = render_case(Some("pinhole_diffraction"), seed, &spec).unwrap();
    println!("seed {seed}: truth {}", case.truth);
    println!("channel  mean  true var  measure(open)  measure(ref)  beyond cut-off (bins)  |  noise/signal: true  beyond cut-off");
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        let (p, o) = (&case.pinhole.image.planes[c], &case.open.image.planes[c]);
        let m = p.mean();
        let truth = case.pinhole.variance[c].mean() as f64;
        let at_mean = |q: &Plane| measure(q, 16).linear_variance(m as f32, Transfer::Linear) as f64;
        let band = channel_bandwidth(name);
        let (beyond, bins) = power_beyond(p, 1.05 * 1.22 / (radii[c] * (1.0 - band)));
        let psf = ReferencePsf { radius_px: radii[c], aberration_px: 0.0, bandwidth: band };
        println!(
            "{name}  {m:.4}  {truth:.3e}  {:.3e}  {:.3e}  {beyond:.3e} ({bins})  |  {:.3e}  {:.3e}",
            at_mean(o),
            at_mean(p),
            noise_to_signal(p, truth, &psf),
            noise_to_signal(p, beyond, &psf)
        );
    }
}
