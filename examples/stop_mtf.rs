//! The simulator's stopped-down PSFs against `pinhole_diffraction`'s model: per channel, the
//! MTF50 of the lens's PSFs at f/N (the centre tile, and the mean over a 9 × 7 grid) and of the
//! band-averaged Airy transfer at the channel's nominal wavelength
//! (`diagnose::diffraction::ReferencePsf`, no aberration blur), and the modulation of both at
//! 0.1–0.4 cycles/px. Where they agree the stop is diffraction-limited and the model holds.
//!
//! `cargo run --release --example stop_mtf -- 16.28` (the f-number; seed 71's stopped-down
//! reference is f/16.28; docs/notes/diagnosis-history.md, "Session 57").
use lensrig::diagnose::diffraction::{half_modulation, ReferencePsf, channel_wavelength_um, channel_bandwidth};
use lensrig::diagnose::proof::kernel_modulation;
use lensrig::optics::lens::LensModel;
fn main() {
    let lens = LensModel::demo(1024, 768);
    let n: f64 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(16.28);
    let g = lens.psf_grid(n, 9, 7, 61);
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        let centre = &g.kernels[c][31..32];
        let all = &g.kernels[c][..];
        let m_c = half_modulation(|f| kernel_modulation(centre, f));
        let m_a = half_modulation(|f| kernel_modulation(all, f));
        let r = 1.22 * channel_wavelength_um(name) * n / lens.pixel_pitch_um;
        let psf = ReferencePsf { radius_px: r, aberration_px: 0.0, bandwidth: channel_bandwidth(name) };
        let mods: Vec<String> = [0.1, 0.2, 0.3, 0.4].iter().map(|&f| format!("{:.3}/{:.3}", kernel_modulation(all, f), psf.transfer(f, 0.0))).collect();
        println!("{name}: airy r {r:.2}  mtf50 centre {m_c:.3} all {m_a:.3} model {:.3}  mod(true/model) {:?}", psf.mtf50(), mods);
    }
}
